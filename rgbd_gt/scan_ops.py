"""Whole-cloud operations on a `Scan`: crop, voxel downsampling, point spacing."""

from __future__ import annotations

import numpy as np

from rgbd_gt.scan import Scan


def crop(scan: Scan, box_min: np.ndarray, box_max: np.ndarray) -> Scan:
    """Keep the points inside the axis-aligned box [box_min, box_max] (metres, inclusive)."""
    lo, hi = np.asarray(box_min, float), np.asarray(box_max, float)
    inside = np.all((scan.xyz >= lo) & (scan.xyz <= hi), axis=1)
    return scan.subset(inside)


def voxel_downsample(scan: Scan, voxel: float) -> Scan:
    """One point per occupied voxel of edge `voxel` metres: the mean position, color and intensity.

    Grid indices (row/col) no longer describe a grid afterwards and are dropped; scan_id keeps
    the value of the voxel's first point.
    """
    if len(scan) == 0:
        return scan
    keys = np.floor((scan.xyz - scan.xyz.min(axis=0)) / voxel).astype(np.int64)
    dims = keys.max(axis=0) + 1
    flat = (keys[:, 0] * dims[1] + keys[:, 1]) * dims[2] + keys[:, 2]
    del keys
    _, first, inverse = np.unique(flat, return_index=True, return_inverse=True)
    del flat
    count = np.bincount(inverse).astype(np.float64)

    def mean(values: np.ndarray) -> np.ndarray:
        return np.bincount(inverse, weights=values, minlength=count.size) / count

    xyz = np.stack([mean(scan.xyz[:, j]) for j in range(3)], axis=1)
    rgb = None
    if scan.rgb is not None:
        rgb = np.stack([np.rint(mean(scan.rgb[:, j].astype(np.float64))) for j in range(3)], axis=1).astype(np.uint8)
    intensity = mean(scan.intensity.astype(np.float64)).astype(np.float32) if scan.intensity is not None else None
    scan_id = scan.scan_id[first] if scan.scan_id is not None else None
    return Scan(xyz=xyz, rgb=rgb, intensity=intensity, scan_id=scan_id, origins=scan.origins)


def median_spacing(scan: Scan, samples: int = 20000, seed: int = 0) -> float:
    """Median point spacing in metres.

    A structured scan (row/col) uses the distances between grid neighbours, which costs one
    sort even for tens of millions of points. Otherwise: the median distance from a random
    sample of `samples` points to their nearest other point (a k-d tree over all points).
    """
    if scan.has_grid:
        return _grid_spacing(scan)
    xyz = scan.xyz
    n = xyz.shape[0]
    if n < 2:
        return float("nan")
    import open3d as o3d

    pts = o3d.core.Tensor(np.ascontiguousarray(xyz, np.float64))
    nns = o3d.core.nns.NearestNeighborSearch(pts)
    nns.knn_index()
    pick = np.random.default_rng(seed).choice(n, size=min(samples, n), replace=False)
    _, dist2 = nns.knn_search(o3d.core.Tensor(np.ascontiguousarray(xyz[pick], np.float64)), 2)
    return float(np.median(np.sqrt(dist2.numpy()[:, 1])))


def _grid_spacing(scan: Scan) -> float:
    """Median over points of the distance to the nearest of their (up to 4) grid neighbours."""
    sid = scan.scan_id if scan.scan_id is not None else np.zeros(len(scan), np.int32)
    nearest = np.full(len(scan), np.inf)
    for major, minor in ((scan.col, scan.row), (scan.row, scan.col)):
        order = np.lexsort((minor, major, sid))
        adjacent = (np.diff(minor[order]) == 1) & (np.diff(major[order]) == 0) & (np.diff(sid[order]) == 0)
        a, b = order[:-1][adjacent], order[1:][adjacent]
        d = np.linalg.norm(scan.xyz[a] - scan.xyz[b], axis=1)
        # within one direction each point is `a` at most once and `b` at most once
        nearest[a] = np.minimum(nearest[a], d)
        nearest[b] = np.minimum(nearest[b], d)
    nearest = nearest[np.isfinite(nearest)]
    return float(np.median(nearest)) if nearest.size else float("nan")
