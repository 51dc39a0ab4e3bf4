"""Calibration text files as LiDAR-camera tools write them: one `KEY: numbers` line per matrix.

Read here: the camera from `K` (3x3) and `D` (OpenCV distortion; PJLab's SensorsCalibration) or
from KITTI's `P2` / `P_rect_02` (3x4, no distortion); the pose T_cam_from_scan from `T` (PJLab)
or `Tr_velo_to_cam` / `Tr` (KITTI), 3x4 or 4x4. Such files hold no image size: the photo gives it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError, require_file

CAMERA_KEYS = ("K", "P2", "P_rect_02")
POSE_KEYS = ("T", "Tr_velo_to_cam", "Tr")


def is_calib_txt(path: str | Path) -> bool:
    return Path(path).suffix.lower() == ".txt"


def read_calib_txt(path: str | Path) -> dict[str, np.ndarray]:
    """{key: values (n,) float64} of every `KEY: numbers` line; non-finite values are an error."""
    path = require_file(path)
    rows = {}
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if ":" not in line or line.lstrip().startswith("#"):
            continue
        key, values = line.split(":", 1)
        try:
            rows[key.strip()] = np.array(values.split(), float)
        except ValueError:
            raise InputError(f"line {number} ({key.strip()}): not a list of numbers", path) from None
        if not np.isfinite(rows[key.strip()]).all():
            raise InputError(f"line {number} ({key.strip()}): non-finite values", path)
    return rows


def _first(rows: dict, keys: tuple[str, ...], path: Path, what: str) -> tuple[str, np.ndarray]:
    for key in keys:
        if key in rows:
            return key, rows[key]
    raise InputError(f"no {what} line ({' or '.join(k + ':' for k in keys)})", path)


def read_calib_camera(path: str | Path, size: tuple[int, int]) -> Camera:
    """The camera of a calibration text file, for a photo of `size` (width, height)."""
    from rgbd_gt.io.camera_file import camera_from_values

    path = Path(path)
    rows = read_calib_txt(path)
    key, values = _first(rows, CAMERA_KEYS, path, "camera matrix")
    if values.size not in (9, 12):
        raise InputError(f"{key} must hold 9 (3x3) or 12 (3x4) numbers, got {values.size}", path)
    K = values.reshape(3, -1)[:, :3]
    return camera_from_values(path, size[0], size[1], K, rows.get("D") if key == "K" else None)


def read_calib_pose(path: str | Path) -> np.ndarray:
    """T_cam_from_scan (4, 4) of a calibration text file. Rotations printed with 6 digits are
    orthonormal to about 1e-6 only: they are projected onto SO(3) (a change far below any
    calibration's accuracy); beyond 1e-3 it is not a rotation and is refused."""
    from rgbd_gt.io.pose_file import check_rigid
    from rgbd_gt.pose import project_to_so3

    path = Path(path)
    key, values = _first(read_calib_txt(path), POSE_KEYS, path, "extrinsic")
    if values.size not in (12, 16):
        raise InputError(f"{key} must hold 12 (3x4) or 16 (4x4) numbers, got {values.size}", path)
    T = np.vstack([values[:12].reshape(3, 4), [0, 0, 0, 1]])
    R = T[:3, :3]
    if np.abs(R @ R.T - np.eye(3)).max() < 1e-3 and np.linalg.det(R) > 0:
        T[:3, :3] = project_to_so3(R)
    return check_rigid(T, path)
