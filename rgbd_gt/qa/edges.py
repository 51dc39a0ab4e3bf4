"""Canny edges of the photo and of the scan rendered into its camera (the paper's Fig. 5), and
how far the scan's edges lie from the photo's."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.io.scan import Scan, colors_to_gray
from rgbd_gt.render.depth import render_depth


@dataclass
class EdgeScore:
    median_distance_px: float
    mean_distance_px: float
    within_1px: float
    scan_edge_pixels: int

    def summary(self) -> str:
        return (f"median {self.median_distance_px:.2f} px, mean {self.mean_distance_px:.2f} px, "
                f"within 1 px {self.within_1px:.1%}")

    def as_dict(self, prefix: str = "") -> dict:
        return {f"{prefix}median_distance_px": self.median_distance_px, f"{prefix}mean_distance_px": self.mean_distance_px,
                f"{prefix}within_1px": self.within_1px, f"{prefix}scan_edge_pixels": self.scan_edge_pixels}


def auto_canny(gray: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Canny edges (H, W) bool with thresholds from the image's own gradient statistics: the
    high threshold at the 85th percentile of the (slightly blurred) gradient magnitude over the
    valid pixels, the low one at half of it. Edges of the valid region itself are dropped."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    region = np.ones(gray.shape, bool) if valid is None else valid
    high = float(np.percentile(mag[region], 85)) if region.any() else 1.0
    edges = cv2.Canny(np.clip(g, 0, 255).astype(np.uint8), max(high * 0.25, 1), max(high * 0.5, 2), L2gradient=True) > 0
    if valid is not None:
        edges &= cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return edges


def scan_view(scan: Scan, colors: np.ndarray, camera: Camera, T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scan's gray values as the camera sees them (H, W) float32 0..255, and where it sees them."""
    out = render_depth(scan, camera, T, values=colors_to_gray(colors).reshape(-1, 1))
    return out.colors[..., 0], out.z > 0


def edge_score(photo_edges: np.ndarray, scan_edges: np.ndarray) -> EdgeScore:
    """Distance (px) from each scan edge pixel to the nearest photo edge pixel."""
    dist = cv2.distanceTransform((~photo_edges).astype(np.uint8), cv2.DIST_L2, 5)
    d = dist[scan_edges]
    if d.size == 0:
        return EdgeScore(float("nan"), float("nan"), 0.0, 0)
    return EdgeScore(float(np.median(d)), float(d.mean()), float(np.mean(d <= 1.0)), int(d.size))


def overlay(photo: np.ndarray, photo_edges: np.ndarray, scan_edges: np.ndarray) -> np.ndarray:
    """Darkened photo with red photo edges, blue scan edges, white where both (H, W, 3) uint8 RGB."""
    out = (photo.astype(np.float32) * 0.35).astype(np.uint8)
    out[photo_edges] = (255, 40, 40)
    out[scan_edges] = (60, 110, 255)
    out[photo_edges & scan_edges] = (255, 255, 255)
    return out


def side_by_side(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Two overlays (H, W, 3) as one panel, separated by an 8-pixel white bar."""
    return np.concatenate([before, np.full((before.shape[0], 8, 3), 255, np.uint8), after], axis=1)


def qa(scan: Scan, colors: np.ndarray, photo: np.ndarray, camera: Camera, T: np.ndarray) -> tuple[np.ndarray, EdgeScore]:
    """(overlay image, score) for one pose."""
    photo_edges = auto_canny(cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY))
    gray, seen = scan_view(scan, colors, camera, T)
    scan_edges = auto_canny(gray, seen)
    return overlay(photo, photo_edges, scan_edges), edge_score(photo_edges, scan_edges)
