"""Pinhole versions of a photo and rectified stereo pairs (OpenCV), and disparity from depth
rendered in the rectified cameras."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError


@dataclass
class Warp:
    """A photo's resampling into another pinhole camera: `camera` (no distortion), the rotation
    R (3, 3) from the photo's camera frame to the new one (identity when only undistorted), and
    OpenCV's remap tables (H, W) float32 (None: the photo is already that camera)."""

    camera: Camera
    R: np.ndarray
    map_x: np.ndarray | None
    map_y: np.ndarray | None

    def pose(self, T_cam_from_scan: np.ndarray) -> np.ndarray:
        """(4, 4) the new camera's T_cam_from_scan."""
        out = T_cam_from_scan.copy()
        out[:3] = self.R @ T_cam_from_scan[:3]
        return out

    def covariance(self, covariance: np.ndarray) -> np.ndarray:
        """(6, 6) a pose update's covariance (`align.aligner.RefineResult.covariance`: rotation
        vector, translation, in the photo's camera frame) in the new camera's frame."""
        A = np.kron(np.eye(2), self.R)
        return A @ covariance @ A.T

    def image(self, photo: np.ndarray, nearest: bool = False) -> np.ndarray:
        """The photo (H, W[, C]) resampled (bilinear; nearest for masks); 0 outside the photo."""
        import cv2

        if self.map_x is None:
            return photo
        return cv2.remap(photo, self.map_x, self.map_y, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def _cv(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    return camera.K, np.asarray(camera.distortion or (0.0, 0.0, 0.0, 0.0), np.float64)


def _warp(camera: Camera, R: np.ndarray, P: np.ndarray) -> Warp:
    import cv2

    K, D = _cv(camera)
    new = Camera(camera.width, camera.height, P[0, 0], P[1, 1], P[0, 2], P[1, 2])
    mx, my = cv2.initUndistortRectifyMap(K, D, R, P[:3, :3], camera.size, cv2.CV_32FC1)
    return Warp(new, R, mx, my)


def pinhole(camera: Camera) -> Warp:
    """The photo undistorted: a pinhole camera of the same size whose every pixel the photo
    covers (OpenCV's optimal new camera matrix at alpha 0); the photo itself when it has no
    distortion."""
    import cv2

    if not camera.has_distortion:
        return Warp(camera, np.eye(3), None, None)
    K, D = _cv(camera)
    P, _ = cv2.getOptimalNewCameraMatrix(K, D, camera.size, 0.0)
    return _warp(camera, np.eye(3), P)


@dataclass
class Pair:
    """A rectified stereo pair: left and right `Warp`s into two pinhole cameras that share K and
    orientation, the right `baseline` metres along the left's +x (disparity = f baseline / z,
    doffs 0); swapped: the rig's second camera is the left one."""

    left: Warp
    right: Warp
    baseline: float
    swapped: bool


def rectify(cam0: Camera, T0: np.ndarray, cam1: Camera, T1: np.ndarray) -> Pair:
    """The pair of photos taken by cam0 at T0 and cam1 at T1 (T_cam_from_scan) rectified from
    their relative pose (OpenCV's stereoRectify, zero disparity at infinity, every pixel of the
    rectified left image inside the photos: alpha 0), the left one first."""
    import cv2

    if cam0.size != cam1.size:
        raise InputError(f"a stereo pair needs photos of one size: {cam0.width}x{cam0.height} and {cam1.width}x{cam1.height}")
    T10 = T1 @ np.linalg.inv(T0)  # x1 = R x0 + t
    K0, D0 = _cv(cam0)
    K1, D1 = _cv(cam1)
    R0, R1, P0, P1, *_ = cv2.stereoRectify(K0, D0, K1, D1, cam0.size, T10[:3, :3], T10[:3, 3:],
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    if P1[0, 3] > 0:  # the second camera lies to the left of the first
        pair = rectify(cam1, T1, cam0, T0)
        return Pair(pair.left, pair.right, pair.baseline, True)
    f = max(cam0.fx, cam0.fy, cam1.fx, cam1.fy)
    if not P0[0, 0] <= 10 * f:  # alpha 0 zooms in on the pixels valid in both: far in, almost none are
        raise InputError(f"rectified, the two photos share almost no view (a focal length of {P0[0, 0]:.0f} px, "
                         f"{f:.0f} px before): check the cameras' principal points and distortion")
    return Pair(_warp(cam0, R0, P0), _warp(cam1, R1, P1), float(-P1[0, 3] / P1[0, 0]), False)


def disparity(z: np.ndarray, f: float, baseline: float) -> np.ndarray:
    """(H, W) float32 disparity (pixels) f baseline / z of a rectified depth map; 0 where z is 0."""
    return np.where(z > 0, f * baseline / np.where(z > 0, z, 1), 0).astype(np.float32)


def occluded(z_left: np.ndarray, z_right: np.ndarray, disp: np.ndarray, tolerance: float = 0.01) -> np.ndarray:
    """(H, W) bool: left pixels with depth whose point the right camera does not see: its pixel
    (u - d, v) lies outside the right image, or the right camera sees something nearer there (a
    rectified pair shares its orientation: a point has one z in both), by more than `tolerance`
    of the depth. The right depth is interpolated linearly along the row between its two pixels."""
    h, w = z_left.shape
    v, u = np.nonzero(z_left > 0)
    x = u - disp[v, u]
    inside = (x >= 0) & (x <= w - 1)
    x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 2)
    a = np.clip(x - x0, 0, 1)
    z0, z1 = z_right[v, x0], z_right[v, x0 + 1]
    zr = np.where((z0 > 0) & (z1 > 0), (1 - a) * z0 + a * z1, np.where(a < 0.5, z0, z1))  # an edge: the nearer pixel's
    seen = inside & (zr > 0) & (zr >= z_left[v, u] * (1 - tolerance))
    out = np.zeros((h, w), bool)
    out[v[~seen], u[~seen]] = True
    return out
