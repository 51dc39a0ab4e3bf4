"""Calibration text files as LiDAR-camera tools write them: one `KEY: numbers` line per matrix.

Read here: the camera from `K` (3x3) and `D` (OpenCV distortion; PJLab's SensorsCalibration) or
from KITTI's `P2` / `P_rect_02` (3x4, rectified, no distortion); the pose T_cam_from_scan from
`T` (PJLab, 3x4 or 4x4) or KITTI's `Tr_velo_to_cam` / `Tr` / `R:` + `T:` (the LiDAR into camera 0),
composed as KITTI's devkit projects (x = P2 R0_rect Tr X): camera 0's rectifying rotation
`R0_rect` / `R_rect_00` where the file has one, then camera 2's offset from camera 0 (P2's fourth
column). Such files hold no image size: the photo gives it. Lines that are not needed may hold
anything (KITTI's `calib_time: 09-Jan-2012 13:57:47`).
A text file that is only a matrix, 3 or 4 rows of 4 numbers split by commas or spaces
(livox_camera_calib's `extrinsic.txt`, numpy's `savetxt`), is read as the pose T_cam_from_scan.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError, require_file

CAMERA_KEYS = ("K", "P2", "P_rect_02")
POSE_KEYS = ("T", "Tr_velo_to_cam", "Tr")
RECTIFY_KEYS = ("R0_rect", "R_rect_00")


def is_calib_txt(path: str | Path) -> bool:
    return Path(path).suffix.lower() == ".txt"


def read_calib_txt(path: str | Path) -> dict[str, tuple[int, str]]:
    """{key: (line number, the text after the colon)} of every `KEY: ...` line."""
    path = require_file(path)
    rows = {}
    for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
        if ":" in line and not line.lstrip().startswith("#"):
            key, values = line.split(":", 1)
            rows[key.strip()] = (number, values)
    return rows


def _numbers(rows: dict, key: str, sizes: tuple[int, ...] | None, path: Path) -> np.ndarray:
    """The finite numbers of line `key`, as many as one of `sizes` (3, 9, 12 or 16) unless None."""
    number, text = rows[key]
    try:
        values = np.array(text.split(), float)
    except ValueError:
        raise InputError(f"line {number} ({key}): not a list of numbers", path) from None
    if not np.isfinite(values).all():
        raise InputError(f"line {number} ({key}): non-finite values", path)
    if sizes is not None and values.size not in sizes:
        shapes = {9: " (3x3)", 12: " (3x4)", 16: " (4x4)"}
        wanted = " or ".join(f"{n}{shapes.get(n, '')}" for n in sizes)
        raise InputError(f"{key} must hold {wanted} numbers, got {values.size}", path)
    return values


def _first(rows: dict, keys: tuple[str, ...]) -> str | None:
    return next((key for key in keys if key in rows), None)


def read_calib_camera(path: str | Path, size: tuple[int, int]) -> Camera:
    """The camera of a calibration text file, for a photo of `size` (width, height)."""
    from rgbd_gt.io.checked import camera_from_values

    path = Path(path)
    rows = read_calib_txt(path)
    key = _first(rows, CAMERA_KEYS)
    if key is None:
        raise InputError(f"no camera matrix line ({' or '.join(k + ':' for k in CAMERA_KEYS)})", path)
    K = _numbers(rows, key, (9, 12), path).reshape(3, -1)[:, :3]
    dist = _numbers(rows, "D", None, path) if key == "K" and "D" in rows else None  # its length checked there
    return camera_from_values(path, size[0], size[1], K, dist)


def read_calib_pose(path: str | Path) -> np.ndarray:
    """T_cam_from_scan (4, 4) of a calibration text file. Rotations printed with 6 digits are
    orthonormal to about 1e-6 only: they are projected onto SO(3) (a change far below any
    calibration's accuracy); beyond 1e-3 it is not a rotation and is refused."""
    from rgbd_gt.io.checked import check_rigid

    path = Path(path)
    rows = read_calib_txt(path)
    key = _first(rows, POSE_KEYS)
    if key is None:
        values = _plain_matrix(path) if not rows else None
        if values is None:
            raise InputError(f"no extrinsic line ({' or '.join(k + ':' for k in POSE_KEYS)}) and not a plain 3x4 or "
                             "4x4 matrix", path)
        key = "the matrix"
    elif key == "T" and "R" in rows:  # KITTI raw's calib_velo_to_cam.txt: R (3x3) and T (3) apart
        values = np.hstack([_numbers(rows, "R", (9,), path).reshape(3, 3), _numbers(rows, "T", (3,), path)[:, None]]).ravel()
    else:
        values = _numbers(rows, key, (12, 16), path)
    T = extrinsic(values, key, path)
    rectify = _first(rows, RECTIFY_KEYS)
    if rectify is not None:
        T = _rigid(np.hstack([_numbers(rows, rectify, (9,), path).reshape(3, 3), np.zeros((3, 1))]), rectify, path) @ T
    camera = _first(rows, CAMERA_KEYS)
    if camera is not None and camera != "K":  # a rectified P = K [I | t]: the camera t from the reference camera
        P = _numbers(rows, camera, (12,), path).reshape(3, 4)
        if not abs(np.linalg.det(P[:, :3])) > 1e-12:
            raise InputError(f"{camera}: its first three columns are not a camera matrix", path)
        T[:3, 3] += np.linalg.solve(P[:, :3], P[:, 3])
    return check_rigid(T, path)


def extrinsic(values: np.ndarray, key: str, path: Path) -> np.ndarray:
    """(4, 4) from the 12 or 16 numbers (rows) of a 3x4 or 4x4 extrinsic printed by a tool, its
    rotation projected onto SO(3) (`_rigid`)."""
    if values.size == 16 and not np.allclose(values[12:], [0, 0, 0, 1]):
        raise InputError(f"{key}: the last row of a 4x4 extrinsic must be 0 0 0 1, got {values[12:].tolist()}", path)
    return _rigid(values[:12].reshape(3, 4), key, path)


def _plain_matrix(path: Path) -> np.ndarray | None:
    """(12,) or (16,) float64, rows first: a file of only numeric rows (commas or spaces between, `#` comments
    and blank lines skipped); None when some row is not numbers. Rows of another shape, or
    non-finite numbers, are an InputError."""
    lines = [ln for ln in path.read_text(errors="replace").splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    try:
        table = [[float(x) for x in re.split(r"[,\s]+", ln.strip().strip(","))] for ln in lines]
    except ValueError:
        return None
    if not table:
        raise InputError("the file is empty: no extrinsic", path)
    if len(table) not in (3, 4) or any(len(r) != 4 for r in table):
        raise InputError(f"a matrix file must hold 3 or 4 rows of 4 numbers, got rows of {[len(r) for r in table]}", path)
    values = np.array(table).ravel()
    if not np.isfinite(values).all():
        raise InputError("the matrix holds non-finite values", path)
    return values


def _rigid(Rt: np.ndarray, key: str, path: Path) -> np.ndarray:
    """[R | t] (3, 4) as a 4x4 transform, R projected onto SO(3) (it must be within 1e-3 of it)."""
    from rgbd_gt.pose import project_to_so3

    R = Rt[:, :3]
    err, det = np.abs(R @ R.T - np.eye(3)).max(), np.linalg.det(R)
    if err > 1e-3 or det <= 0:
        raise InputError(f"{key} is not rigid: its rotation is not orthonormal (|R Rt - I| = {err:.2e}, det {det:.3f})", path)
    return np.vstack([np.hstack([project_to_so3(R), Rt[:, 3:]]), [0, 0, 0, 1]])
