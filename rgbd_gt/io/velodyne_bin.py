"""KITTI's LiDAR sweeps (`velodyne_points/data/*.bin`, `training/velodyne/*.bin`): float32
little-endian x y z reflectance per return, in metres in the sensor's frame, reflectance in
[0, 1], no header.

Without a header nothing says a file is one, so it is checked as far as the format allows: a
whole number of 16-byte returns, finite values, coordinates within a LiDAR's reach and
reflectance in [0, 1]. Another layout read as this one (nuScenes' five floats a return, raw
0-255 intensities) fails the last two with near certainty.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbd_gt.errors import InputError
from rgbd_gt.scan import Scan

RETURN_BYTES = 16
MAX_RANGE_M = 1000.0  # automotive LiDARs reach 100-300 m
NOT_ONE = "not a KITTI .bin sweep (x y z reflectance as float32)"


def read_velodyne_bin(path: str | Path) -> Scan:
    """A KITTI .bin sweep as a Scan: xyz (float64), intensity (its reflectance), origin 0, 0, 0."""
    path = Path(path)
    size = path.stat().st_size
    if size % RETURN_BYTES:
        raise InputError(f"{size} bytes is not a whole number of KITTI returns (x y z reflectance as float32, "
                         f"{RETURN_BYTES} bytes each): truncated, or not a KITTI .bin sweep", path)
    data = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    if not np.isfinite(data).all():
        raise InputError(f"return {int(np.flatnonzero(~np.isfinite(data).all(1))[0])} has non-finite values", path)
    far = np.abs(data[:, :3]).max(axis=1) > MAX_RANGE_M
    if far.any():
        raise InputError(f"return {int(np.flatnonzero(far)[0])} lies {float(np.abs(data[far][0, :3]).max()):.3g} m away "
                         f"(beyond {MAX_RANGE_M:g} m): {NOT_ONE}", path)
    odd = (data[:, 3] < 0) | (data[:, 3] > 1)
    if odd.any():
        raise InputError(f"return {int(np.flatnonzero(odd)[0])} has reflectance {float(data[odd][0, 3]):.4g}, outside "
                         f"[0, 1]: {NOT_ONE}", path)
    return Scan(xyz=data[:, :3].astype(np.float64), intensity=np.ascontiguousarray(data[:, 3]), origins=np.zeros((1, 3)))
