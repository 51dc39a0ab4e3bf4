"""Depth maps: OpenEXR (channel Z, float32 metres, 0 = no depth) and 16-bit PNG (millimetres)."""

from __future__ import annotations

import os

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError, require_file
from rgbd_gt.io.atomic import atomic_output


def write_depth_exr(path: str | os.PathLike, z: np.ndarray, camera: Camera, T_cam_from_scan: np.ndarray,
                    scan_name: str, normals: np.ndarray | None = None, seen_from_behind: float | None = None) -> None:
    """Write z (H, W) metres as channel Z (float32; 0 where there is no depth), with the
    intrinsics, distortion, pose and scan file name as header attributes (and the fraction of
    the view seen from behind, `render.depth.back_facing_fraction`, when known). With `normals`
    (H, W, 3), also channels N.X, N.Y, N.Z (camera frame)."""
    import OpenEXR

    header = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "rgbd_gt_K": np.asarray(camera.K, np.float64),
        "rgbd_gt_distortion": " ".join(repr(float(d)) for d in camera.distortion) or "none",
        "rgbd_gt_T_cam_from_scan": np.asarray(T_cam_from_scan, np.float64),
        "rgbd_gt_scan": str(scan_name),
        "rgbd_gt_units": "metres, z along the optical axis; 0 = no depth",
    }
    if seen_from_behind is not None:
        header["rgbd_gt_seen_from_behind"] = repr(float(seen_from_behind))
    channels = {"Z": np.ascontiguousarray(z, np.float32)}
    if normals is not None:
        for k, c in enumerate("XYZ"):
            channels[f"N.{c}"] = np.ascontiguousarray(normals[..., k], np.float32)
    with atomic_output(path) as tmp, OpenEXR.File(header, channels) as f:
        f.write(str(tmp))


def read_depth_exr(path: str | os.PathLike) -> tuple[np.ndarray, dict]:
    """(z (H, W) float32 metres, header dict) of a depth EXR written by rgbd-gt."""
    import OpenEXR

    path = require_file(path)
    try:
        with OpenEXR.File(str(path)) as f:
            return np.array(f.channels()["Z"].pixels, np.float32), dict(f.header())
    except Exception as exc:  # OpenEXR raises plain exceptions for every failure
        raise InputError(f"not a depth EXR with a Z channel ({exc})", path) from None


def write_depth_png16(path: str | os.PathLike, z: np.ndarray) -> None:
    """16-bit PNG in millimetres, 0 = no depth (as TUM and ScanNet); depths over 65.535 m are 0."""
    import cv2

    mm = np.round(np.asarray(z, np.float64) * 1000.0)
    mm[(mm > 65535) | ~np.isfinite(mm)] = 0
    with atomic_output(path) as tmp:
        if not cv2.imwrite(str(tmp), mm.astype(np.uint16)):
            raise InputError("could not write PNG", path)
