"""Triangulating a structured scan along its row/column grid."""

from __future__ import annotations

import numpy as np

from rgbd_gt.io.scan import Scan


def grid_triangles(scan: Scan, max_stretch: float = 8.0) -> np.ndarray:
    """(T, 3) int64 vertex indices of triangles between grid neighbours, per scan.

    Each 2x2 grid cell gives two triangles when its vertices exist. A triangle is left out when
    an edge is longer than `max_stretch` x the spacing expected at its range (range x angular
    step): it then spans a depth discontinuity (or a surface seen at over ~83 degrees), and
    keeping it would paint a false surface between foreground and background.
    """
    sid = scan.scan_id if scan.scan_id is not None else np.zeros(len(scan), np.int32)
    origins = scan.origins if len(scan.origins) else np.zeros((1, 3))
    tris = []
    for s in np.unique(sid):
        idx = np.nonzero(sid == s)[0]
        row, col = scan.row[idx].astype(np.int64), scan.col[idx].astype(np.int64)
        r0, c0 = row.min(), col.min()
        rows, cols = row.max() - r0 + 1, col.max() - c0 + 1
        grid = np.full((rows, cols), -1, np.int64)
        grid[row - r0, col - c0] = idx
        a, b = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()
        c, d = grid[1:, :-1].ravel(), grid[1:, 1:].ravel()
        cand = np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, d], 1)])
        cand = cand[np.all(cand >= 0, axis=1)]
        if not len(cand):
            continue
        origin = origins[min(int(s), len(origins) - 1)]
        p = scan.xyz[cand]  # (T, 3, 3)
        rng = np.linalg.norm(p - origin, axis=2)
        step = _angular_step(scan.xyz[idx], row, col, origin)
        longest = np.max(np.linalg.norm(p - np.roll(p, 1, axis=1), axis=2), axis=1)
        keep = longest <= max_stretch * step * rng.min(axis=1)
        tris.append(cand[keep])
    return np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)


def _angular_step(xyz: np.ndarray, row: np.ndarray, col: np.ndarray, origin: np.ndarray) -> float:
    """Median angle (radians) between grid neighbours along a row, seen from the origin."""
    order = np.lexsort((col, row))
    r, c = row[order], col[order]
    nb = (np.diff(r) == 0) & (np.diff(c) == 1)
    u = xyz[order] - origin
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    cos = np.sum(u[:-1][nb] * u[1:][nb], axis=1)
    return float(np.median(np.arccos(np.clip(cos, -1, 1)))) if nb.any() else 1e-3
