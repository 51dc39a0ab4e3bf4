"""Pose files: YAML with `T_cam_from_scan`, a 4x4 rigid transform (rows) that maps scan/world
points in metres into the OpenCV camera frame. Other keys are metadata and are kept."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import yaml

from rgbd_gt.errors import InputError, read_yaml, require_file
from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.io.checked import POSE_KEY, check_rigid

def read_pose(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """Read a pose file. Returns (T_cam_from_scan (4, 4) float64, the other keys as a dict).
    A calibration text file (`io.calib_txt`: a T or Tr_velo_to_cam line, or only a matrix), a
    calib.json (`io.calib_json`: results.T_lidar_camera) or an OpenCV FileStorage file with an
    `ExtrinsicMat` (livox_camera_calib's config) or a `CameraExtrinsicMat` (Autoware's
    calibration), or a Kalibr-style camchain whose camera holds `T_cam_lidar`, is read as a pose too."""
    from rgbd_gt.io.calib_json import is_calib_json, read_json_pose
    from rgbd_gt.io.calib_txt import is_calib_txt, read_calib_pose
    from rgbd_gt.io.camera_file import is_opencv_file, kalibr_camera

    path = require_file(path)
    if is_calib_txt(path):
        return read_calib_pose(path), {}
    if is_calib_json(path):
        return read_json_pose(path), {}
    text = path.read_text(errors="replace")
    if is_opencv_file(path, text):
        return _read_opencv_pose(path), {}
    data = read_yaml(path, text)
    kalibr = kalibr_camera(path, data) if isinstance(data, dict) and POSE_KEY not in data else None
    if kalibr is not None and "T_cam_lidar" in kalibr:
        return _read_kalibr_pose(path, kalibr["T_cam_lidar"]), {}
    if not isinstance(data, dict) or POSE_KEY not in data:
        raise InputError(f"pose file has no '{POSE_KEY}' key", path)
    T = check_rigid(data.pop(POSE_KEY), path)
    return T, data


# OpenCV FileStorage nodes read as a pose; True where the node is the camera's pose in the LiDAR
# frame (Autoware's CameraExtrinsicMat: its points2image projects with the inverse), so that
# T_cam_from_scan is its inverse
OPENCV_POSE_NODES = {"ExtrinsicMat": False, POSE_KEY: False, "CameraExtrinsicMat": True}


def _read_opencv_pose(path: Path) -> np.ndarray:
    """T_cam_from_scan of an OpenCV FileStorage file: its `ExtrinsicMat` (4x4, LiDAR to camera;
    livox_camera_calib's config), `T_cam_from_scan`, or `CameraExtrinsicMat` (4x4, camera to
    LiDAR; Autoware's calibration file) node."""
    from rgbd_gt.io.calib_txt import extrinsic
    from rgbd_gt.io.camera_file import opencv_nodes
    from rgbd_gt.pose import invert

    found = {k: m for k, m in opencv_nodes(path, tuple(OPENCV_POSE_NODES)).items() if isinstance(m, np.ndarray)}
    if not found:
        raise InputError(f"OpenCV file has no {', '.join(repr(k) for k in OPENCV_POSE_NODES)} matrix", path)
    key, m = next(iter(found.items()))
    if m.shape not in ((3, 4), (4, 4)) or not np.isfinite(m).all():
        raise InputError(f"{key} must be a 3x4 or 4x4 matrix of finite numbers, got shape {m.shape}", path)
    T = extrinsic(m.astype(float).ravel(), key, path)
    return check_rigid(invert(T) if OPENCV_POSE_NODES[key] else T, path)


def _read_kalibr_pose(path: Path, m) -> np.ndarray:
    """T_cam_from_scan from a camchain camera's `T_cam_lidar` (4x4 rows, LiDAR to camera, as
    Kalibr names T_cam_imu), its rotation projected onto SO(3) as a printed extrinsic's."""
    from rgbd_gt.io.calib_txt import extrinsic

    try:
        values = np.asarray(m, float).ravel()
    except (TypeError, ValueError):
        values = np.zeros(0)
    if values.size not in (12, 16) or not np.isfinite(values).all():
        raise InputError("T_cam_lidar must be 3 or 4 rows of 4 finite numbers", path)
    return check_rigid(extrinsic(values, "T_cam_lidar", path), path)


def _plain(value):
    """numpy scalars/arrays -> plain Python so that yaml.safe_dump accepts them."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def write_pose(path: str | os.PathLike, T: np.ndarray, **meta) -> None:
    """Write a pose file (atomically): `T_cam_from_scan` first, then `meta` keys in order."""
    T = check_rigid(T, path)
    doc = {POSE_KEY: [[float(x) for x in row] for row in T]}
    doc.update(_plain(meta))
    with atomic_output(path) as tmp:
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False, default_flow_style=None))
