"""The two sensors' color responses: how scene radiance (linear RGB) becomes 8-bit color.

The camera and the scanner see the same radiance but report different colors (white
balance, color mixing, gamma, saturation), which is what the aligner's color model must
bridge. Both responses are invertible so tests can map one sensor's colors to the other's.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np

LUMA = np.array([0.2126, 0.7152, 0.0722], np.float32)


@dataclass
class CameraResponse:
    """Photo = gamma(clip(M @ (wb * exposure * vignetting * blur(radiance)) + noise))."""

    exposure: float
    white_balance: list[float]  # (3,) per-channel gains
    mix: list[list[float]]  # (3, 3) color mixing (rows sum to 1)
    gamma: float  # display gamma: value = linear ** (1 / gamma)
    vignetting: float  # brightness falls by this fraction at the image corners
    blur_px: float  # Gaussian sigma of the optics, pixels
    noise: float  # sensor noise std in linear units at full scale

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class ScannerResponse:
    """Scan color = gamma(clip(saturate(wb * exposure * radiance)))."""

    exposure: float
    white_balance: list[float]
    saturation: float  # 1 = unchanged, <1 washed out, >1 vivid
    gamma: float

    def as_dict(self) -> dict:
        return asdict(self)


def random_camera_response(rng: np.random.Generator) -> CameraResponse:
    mix = np.eye(3) + rng.uniform(-0.08, 0.08, (3, 3)) * (1 - np.eye(3))
    mix /= mix.sum(axis=1, keepdims=True)
    return CameraResponse(
        exposure=float(rng.uniform(0.9, 1.2)),
        white_balance=rng.uniform(0.85, 1.15, 3).round(4).tolist(),
        mix=mix.round(5).tolist(),
        gamma=float(rng.uniform(1.8, 2.4)),
        vignetting=float(rng.uniform(0.1, 0.3)),
        blur_px=float(rng.uniform(0.4, 0.7)),
        noise=float(rng.uniform(0.003, 0.008)),
    )


def random_scanner_response(rng: np.random.Generator) -> ScannerResponse:
    return ScannerResponse(
        exposure=float(rng.uniform(0.8, 1.3)),
        white_balance=rng.uniform(0.75, 1.25, 3).round(4).tolist(),
        saturation=float(rng.choice([rng.uniform(0.55, 0.85), rng.uniform(1.15, 1.4)])),
        gamma=float(rng.uniform(1.4, 2.8)),
    )


def vignetting_factor(resp: CameraResponse, uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(N,) brightness factor at pixels uv (N, 2) of an image of size (width, height)."""
    w, h = size
    r2 = (((uv[:, 0] - (w - 1) / 2) / (w / 2)) ** 2 + ((uv[:, 1] - (h - 1) / 2) / (h / 2)) ** 2) / 2
    return 1.0 - resp.vignetting * r2


def camera_forward(resp: CameraResponse, radiance: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) float linear radiance -> (H, W, 3) uint8 RGB photo."""
    h, w = radiance.shape[:2]
    img = cv2.GaussianBlur(radiance.astype(np.float32), (0, 0), resp.blur_px)
    v, u = np.mgrid[0:h, 0:w]
    vig = vignetting_factor(resp, np.stack([u.ravel(), v.ravel()], 1), (w, h)).reshape(h, w, 1)
    lin = img * vig * resp.exposure * np.asarray(resp.white_balance, np.float32)
    lin = lin @ np.asarray(resp.mix, np.float32).T
    # shot noise grows with the signal; read noise is constant
    lin = lin + rng.normal(size=lin.shape).astype(np.float32) * resp.noise * np.sqrt(0.2 + np.clip(lin, 0, 1))
    return np.round(np.clip(lin, 0, 1) ** (1 / resp.gamma) * 255).astype(np.uint8)


def camera_inverse(resp: CameraResponse, rgb: np.ndarray, uv: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Photo colors (N, 3) in 0..255 at pixels uv (N, 2) -> radiance (N, 3) (noise and blur aside)."""
    lin = (np.asarray(rgb, np.float64) / 255.0) ** resp.gamma
    lin = lin @ np.linalg.inv(np.asarray(resp.mix)).T
    lin /= resp.exposure * np.asarray(resp.white_balance)
    return lin / vignetting_factor(resp, uv, size)[:, None]


def scanner_forward(resp: ScannerResponse, radiance: np.ndarray) -> np.ndarray:
    """(N, 3) linear radiance -> (N, 3) uint8 scan colors."""
    lin = np.asarray(radiance, np.float64) * resp.exposure * np.asarray(resp.white_balance)
    luma = (lin @ LUMA)[:, None]
    lin = luma + resp.saturation * (lin - luma)
    return np.round(np.clip(lin, 0, 1) ** (1 / resp.gamma) * 255).astype(np.uint8)
