"""koide3's direct_visual_lidar_calibration `calib.json`: the camera (`camera.intrinsics`
[fx, fy, cx, cy], `camera.distortion_coeffs`, `camera.camera_model`) and the extrinsic
(`results.T_lidar_camera`, or before calibration `results.init_T_lidar_camera`: [x, y, z, qx, qy,
qz, qw], the camera's pose in the LiDAR frame, i.e. the inverse of T_cam_from_scan). Like a
calibration text file it holds no image size: the photo gives it.

Also the `gt.json` of CLAIM's example data sets (KITTI, Waymo: `intrinsics.K` [fx, fy, cx, cy],
`intrinsics.D`, `extrinsics.translation` [x, y, z] and `extrinsics.rotation` [qw, qx, qy, qz],
scalar first): T_cam_from_scan itself, LiDAR points into the camera.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError, require_file

MODELS = ("plumb_bob",)  # OpenCV's k1 k2 p1 p2 k3; the tool's fisheye, omnidir and atan models are other lenses
POSE_KEYS = ("T_lidar_camera", "init_T_lidar_camera")


def is_calib_json(path: str | Path) -> bool:
    return Path(path).suffix.lower() == ".json"


def _numbers(value, count: int, what: str, path: Path) -> np.ndarray:
    try:
        a = np.array(value, float).ravel()
    except (TypeError, ValueError):
        a = None
    if a is None or a.size != count or not np.isfinite(a).all():
        raise InputError(f"{what} must be {count} finite numbers, got {json.dumps(value)[:80]}", path)
    return a


def read_calib_json(path: str | Path) -> dict:
    path = require_file(path)
    try:
        data = json.loads(path.read_text(errors="replace"))
    except json.JSONDecodeError as exc:
        raise InputError(f"invalid JSON ({exc.msg}, line {exc.lineno})", path) from None
    if not isinstance(data, dict):
        raise InputError("a calibration JSON file must be an object", path)
    return data


def read_json_camera(path: str | Path, size: tuple[int, int]) -> Camera:
    """The camera of a calib.json, for a photo of `size` (width, height)."""
    from rgbd_gt.io.checked import camera_from_values

    path = Path(path)
    data = read_calib_json(path)
    if isinstance(data.get("intrinsics"), dict):  # CLAIM's gt.json
        fx, fy, cx, cy = _numbers(data["intrinsics"].get("K"), 4, "intrinsics.K ([fx, fy, cx, cy])", path)
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
        return camera_from_values(path, size[0], size[1], K, data["intrinsics"].get("D"))
    cam = data.get("camera")
    if not isinstance(cam, dict) or "intrinsics" not in cam:
        raise InputError("no camera.intrinsics ([fx, fy, cx, cy])", path)
    model = cam.get("camera_model", "plumb_bob")
    if model not in MODELS:
        raise InputError(f"camera_model {model!r} is not supported (only {', '.join(MODELS)}: OpenCV's model)", path)
    fx, fy, cx, cy = _numbers(cam["intrinsics"], 4, "camera.intrinsics", path)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return camera_from_values(path, size[0], size[1], K, cam.get("distortion_coeffs"))


def read_json_pose(path: str | Path) -> np.ndarray:
    """T_cam_from_scan (4, 4): the inverse of results.T_lidar_camera (else init_T_lidar_camera);
    a gt.json's extrinsics as they are.
    The quaternion is normalised when within 1e-3 of unit length (printed digits), else refused."""
    from rgbd_gt.io.checked import check_rigid
    from rgbd_gt.pose import invert, quat_to_matrix, rigid

    path = Path(path)
    data = read_calib_json(path)
    if isinstance(data.get("extrinsics"), dict):  # CLAIM's gt.json: already T_cam_from_scan
        ext = data["extrinsics"]
        x, y, z = _numbers(ext.get("translation"), 3, "extrinsics.translation ([x, y, z])", path)
        q = _numbers(ext.get("rotation"), 4, "extrinsics.rotation ([qw, qx, qy, qz])", path)
        if abs(np.linalg.norm(q) - 1) > 1e-3:
            raise InputError(f"extrinsics.rotation: the quaternion's length is {np.linalg.norm(q):.4g}, not 1", path)
        return check_rigid(rigid(quat_to_matrix(q), (x, y, z)), path)
    results = data.get("results")
    key = next((k for k in POSE_KEYS if isinstance(results, dict) and k in results), None)
    if key is None:
        raise InputError(f"no extrinsic (results.{' or results.'.join(POSE_KEYS)})", path)
    x, y, z, qx, qy, qz, qw = _numbers(results[key], 7, f"results.{key} ([x, y, z, qx, qy, qz, qw])", path)
    norm = np.linalg.norm([qw, qx, qy, qz])
    if abs(norm - 1) > 1e-3:
        raise InputError(f"results.{key}: the quaternion's length is {norm:.4g}, not 1", path)
    R = quat_to_matrix([qw, qx, qy, qz])
    return check_rigid(invert(rigid(R, (x, y, z))), path)
