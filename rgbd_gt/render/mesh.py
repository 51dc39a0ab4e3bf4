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
        origin = origins[min(int(s), len(origins) - 1)]
        # per grid vertex its point and range, per grid edge its length: each edge serves up to
        # four triangles, so this is cheaper than measuring every triangle's three edges
        have = grid >= 0
        xyz = np.zeros((rows, cols, 3))
        xyz[have] = scan.xyz[grid[have]]
        rng = np.where(have, np.linalg.norm(xyz - origin, axis=2), np.inf)

        def length(p, q):
            return np.linalg.norm(p - q, axis=2)

        ab, cd = length(xyz[:-1, :-1], xyz[:-1, 1:]), length(xyz[1:, :-1], xyz[1:, 1:])
        ac, bd = length(xyz[:-1, :-1], xyz[1:, :-1]), length(xyz[:-1, 1:], xyz[1:, 1:])
        bc = length(xyz[:-1, 1:], xyz[1:, :-1])
        ra, rb, rc, rd = rng[:-1, :-1], rng[:-1, 1:], rng[1:, :-1], rng[1:, 1:]
        limit = max_stretch * _angular_step(scan.xyz[idx], row, col, origin)
        ha, hb, hc, hd = have[:-1, :-1], have[:-1, 1:], have[1:, :-1], have[1:, 1:]
        keep1 = (ha & hb & hc & (np.maximum(np.maximum(ab, bc), ac) <= limit * np.minimum(np.minimum(ra, rb), rc))).ravel()
        keep2 = (hc & hb & hd & (np.maximum(np.maximum(bc, bd), cd) <= limit * np.minimum(np.minimum(rc, rb), rd))).ravel()
        a, b = grid[:-1, :-1].ravel(), grid[:-1, 1:].ravel()
        c, d = grid[1:, :-1].ravel(), grid[1:, 1:].ravel()
        tris.append(np.concatenate([np.stack([a, b, c], 1)[keep1], np.stack([c, b, d], 1)[keep2]]))
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
