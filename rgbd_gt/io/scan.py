"""The one entry point that loads or saves any scan file (`rgbd_gt.scan.Scan`)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rgbd_gt.errors import InputError, require_file
from rgbd_gt.scan import Scan

SCAN_SUFFIXES = (".e57", ".ply", ".pcd", ".bin")


def merge_scans(scans: list[Scan]) -> Scan:
    """Concatenate scans into one, renumbering scan_id so each input scan keeps its origins.

    A field is kept only when every input has it.
    """
    if len(scans) == 1:
        return scans[0]
    out: dict[str, np.ndarray | None] = {}
    for name in (n for n in Scan.PER_POINT if n != "scan_id"):  # scan_id is renumbered below
        parts = [getattr(s, name) for s in scans]
        out[name] = np.concatenate(parts) if all(p is not None for p in parts) else None
    ids, offset = [], 0
    for s in scans:
        local = s.scan_id if s.scan_id is not None else np.zeros(len(s), np.int32)
        ids.append(local + offset)
        offset += max(len(s.origins), 1)
    origins = [s.origins if len(s.origins) else np.zeros((1, 3)) for s in scans]
    return Scan(**out, scan_id=np.concatenate(ids).astype(np.int32), origins=np.concatenate(origins))


def load_scan(path: str | os.PathLike, scan_index: int | None = None, progress=None,
              require_points: bool = False) -> Scan:
    """Load an `.e57`, `.ply`, `.pcd` or KITTI `.bin` scan file.

    Args:
        path: the file.
        scan_index: for E57, load only this scan (0-based); None loads and merges all.
        progress: optional callable(done_points, total_points) for progress reporting.
        require_points: raise InputError for a scan without points.
    """
    scan = _load(Path(path), scan_index, progress)
    if require_points and len(scan) == 0:
        raise InputError("the scan has no points", path)
    check_values(scan, path)
    return scan


MAX_COORDINATE_M = 1e7  # georeferenced scans reach ~1e7 m (UTM northings); beyond is corruption


def check_values(scan: Scan, path: object) -> None:
    """InputError naming the first bad point: a non-finite or absurd coordinate, intensity or
    normal, or grid indices that are negative; or an absurd scanner position. (Readers drop the
    points a format marks as missing, like a PCD's NaN returns, before this.)"""
    fields = [("coordinate", scan.xyz), ("intensity", scan.intensity), ("normal", scan.normals)]
    for name, values in fields:
        if values is None or values.size == 0:
            continue
        lo, hi = values.min(), values.max()  # NaN and inf show in these: no per-point temporaries
        if np.isfinite(lo) and np.isfinite(hi) and (name != "coordinate" or max(-lo, hi) <= MAX_COORDINATE_M):
            continue
        bad = ~np.isfinite(values)
        if name == "coordinate":
            bad |= np.abs(values) > MAX_COORDINATE_M
        if bad.any():
            k = int(np.flatnonzero(bad.reshape(len(values), -1).any(axis=1))[0])
            raise InputError(f"point {k} has an invalid {name} ({np.asarray(values[k]).tolist()})", path)
    far = np.flatnonzero(~(np.abs(scan.origins) <= MAX_COORDINATE_M).all(axis=1))
    if far.size:  # the origin turns the surfaces to face it: from there every one would face one way
        raise InputError(f"scanner position {int(far[0])} is {scan.origins[far[0]].tolist()}, beyond "
                         f"{MAX_COORDINATE_M:g} m", path)
    if scan.row is not None and scan.col is not None and len(scan):
        if min(scan.row.min(), scan.col.min()) < 0:
            raise InputError("the scan's row and col indices must be 0 or more", path)
        cells = (int(scan.row.max()) + 1) * (int(scan.col.max()) + 1)
        if cells > 20 * len(scan) + 1_000_000:  # the grid is allocated: it must be mostly points
            raise InputError(f"the scan's grid indices span {cells:,} cells for {len(scan):,} points", path)


def _load(path: Path, scan_index: int | None, progress) -> Scan:
    require_file(path)
    suffix = path.suffix.lower()
    if suffix == ".e57":
        from rgbd_gt.io.e57 import read_e57

        return read_e57(path, scan_index=scan_index, progress=progress)
    if suffix not in SCAN_SUFFIXES:
        raise InputError(f"unknown scan format '{path.suffix}' (expected one of {', '.join(SCAN_SUFFIXES)})", path)
    if scan_index is not None:
        raise InputError("--scan-index applies to E57 files only", path)
    if suffix == ".ply":
        from rgbd_gt.io.ply import read_ply

        return read_ply(path)
    if suffix == ".pcd":
        from rgbd_gt.io.pcd import read_pcd

        return read_pcd(path)
    from rgbd_gt.io.velodyne_bin import read_velodyne_bin

    return read_velodyne_bin(path)


def save_scan(path: str | os.PathLike, scan: Scan) -> None:
    """Write a scan as binary little-endian PLY (atomically)."""
    path = Path(path)
    if path.suffix.lower() != ".ply":
        raise InputError("scans are written as .ply", path)
    from rgbd_gt.io.ply import write_ply

    write_ply(path, scan)
