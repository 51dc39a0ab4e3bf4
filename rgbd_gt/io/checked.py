"""The checks of what a camera or pose file holds, shared by every reader of such files (the
project's YAML, calibration text and JSON files, OpenCV and Kalibr files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbd_gt.camera import Camera, lens_reach
from rgbd_gt.errors import InputError

VALID_DISTORTION_LENGTHS = (0, 4, 5, 8, 12, 14)


def _not_a_number(values) -> str:
    """The entry of a flat list that is not a number, with its place, for a message (the whole
    list, cut to 80 characters, hid a bad last coefficient); anything else (rows too) as it is."""
    if isinstance(values, (list, tuple)) and not any(isinstance(v, (list, tuple)) for v in values):
        for k, v in enumerate(values, 1):
            try:
                float(v)
            except (TypeError, ValueError):
                return f"{v!r:.40} (entry {k} of {len(values)})"
    return f"{values!r:.80}"


def camera_from_values(path: Path, width, height, K: np.ndarray, dist) -> Camera:
    """A Camera from a file's values, each checked: whole positive sizes, finite numbers, a focal
    length between 1 px and 1000 x the image size, the principal point near the image."""
    try:
        K = np.asarray(K, float)
    except (TypeError, ValueError):
        raise InputError(f"fx, fy, cx and cy must be numbers, got {_not_a_number(K)}", path) from None
    try:
        dist = tuple(float(d) for d in np.asarray(dist if dist is not None else [], float).ravel())
    except (TypeError, ValueError):
        raise InputError(f"distortion must be numbers, got {_not_a_number(dist)}", path) from None
    if len(dist) not in VALID_DISTORTION_LENGTHS:
        raise InputError(f"distortion must have 4, 5, 8, 12 or 14 coefficients, got {len(dist)}"
                         + (f" ({dist[0]:g})" if len(dist) == 1 else ""), path)
    if not (np.isfinite(dist).all() and np.isfinite(K).all()):
        raise InputError("camera values must be finite numbers", path)
    if K.shape != (3, 3) or np.abs(K[2] - [0, 0, 1]).max() > 1e-9 or K[1, 0] != 0 or abs(K[0, 1]) > 1e-6 * abs(K[0, 0]):
        raise InputError(f"the camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), got {K.tolist()}", path)
    if np.abs(dist).max(initial=0) > 1000:  # even fisheye rational models stay far below
        raise InputError(f"distortion coefficients must lie within +-1000, got {max(dist, key=abs)}", path)
    sizes = []
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) or not float(v).is_integer() \
                or not 1 <= v <= 100_000:
            shown = v.item() if isinstance(v, np.generic) else v  # not numpy's repr: np.float64(1e+30)
            raise InputError(f"{name} must be a whole number of pixels (1..100000), got {shown!r}", path)
        sizes.append(int(v))
    w, h = sizes
    cam = Camera(w, h, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), dist)
    for name, f in (("fx", cam.fx), ("fy", cam.fy)):
        if not 1 <= f <= 1000 * max(w, h):
            raise InputError(f"{name} must lie between 1 and 1000 x the image size ({w}x{h}: up to {1000 * max(w, h)}), got {f}", path)
    if not (-w < cam.cx < 2 * w and -h < cam.cy < 2 * h):
        raise InputError(f"the principal point ({cam.cx}, {cam.cy}) is far outside the {w}x{h} image", path)
    reach, corner = lens_reach(cam)
    if reach < corner:
        off = "" if 0 <= cam.cx <= w and 0 <= cam.cy <= h else f"the principal point ({cam.cx:g}, {cam.cy:g}) off the image, "
        raise InputError(f"the lens model turns back inside the {w}x{h} image (its distortion reaches a radius of "
                         f"{reach:.3f} in x/z, y/z; the corners lie at {corner:.3f}), so its outer pixels have no ray: "
                         f"{off}coefficients fitted for another image size, or a fisheye lens, which this model does not "
                         "describe", path)
    return cam


POSE_KEY = "T_cam_from_scan"
MAX_TRANSLATION_M = 1e8  # georeferenced scans lie up to ~1e7 m from their origin; beyond is corruption


def check_rigid(T: np.ndarray, path: object = None, tol: float = 1e-6) -> np.ndarray:
    """Validate a 4x4 rigid transform; returns it as float64 or raises InputError."""
    try:
        T = np.asarray(T, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{POSE_KEY} must be a 4x4 list of numbers", path) from None
    if T.shape != (4, 4):
        raise InputError(f"{POSE_KEY} must be 4x4, got shape {T.shape}", path)
    if not np.isfinite(T).all():
        raise InputError(f"{POSE_KEY} has non-finite values", path)
    if np.abs(T[:3, 3]).max() > MAX_TRANSLATION_M:
        raise InputError(f"{POSE_KEY} translation {T[:3, 3].tolist()} is beyond {MAX_TRANSLATION_M:g} m", path)
    if not np.allclose(T[3], [0, 0, 0, 1], atol=tol, rtol=0):
        raise InputError(f"{POSE_KEY} last row must be 0 0 0 1, got {T[3].tolist()}", path)
    R = T[:3, :3]
    err = np.abs(R @ R.T - np.eye(3)).max()
    if err > tol:
        raise InputError(f"{POSE_KEY} is not rigid: rotation is not orthonormal (|R Rt - I| = {err:.2e})", path)
    if np.linalg.det(R) < 0:
        raise InputError(f"{POSE_KEY} is not rigid: rotation is a reflection (det < 0)", path)
    return T
