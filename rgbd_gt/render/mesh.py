"""Triangulating a structured scan along its row/column grid."""

from __future__ import annotations

import numpy as np

from rgbd_gt.scan import Scan


def grid_triangles(scan: Scan, max_stretch: float = 8.0) -> np.ndarray:
    """(T, 3) int32 vertex indices of triangles between grid neighbours, per scan.

    Each 2x2 grid cell gives two triangles when its vertices exist. A triangle is left out when
    an edge is longer than `max_stretch` x the spacing expected at its range (range x angular
    step): it then spans a depth discontinuity (or a surface seen at over ~83 degrees), and
    keeping it would paint a false surface between foreground and background.
    """
    bands = [cell_triangles(*cells) for cells in grid_cells(scan, max_stretch)]
    return np.concatenate(bands) if bands else np.zeros((0, 3), np.int32)


def grid_cells(scan: Scan, max_stretch: float = 8.0) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """The grid's triangles, band by band of grid rows (a 40-million-point grid is triangulated
    in bounded memory), as cells: (grid band (r, c) int32 of point indices (-1: none), keep1,
    keep2 (r-1, c-1) bool: the cells' triangles (a, b, c) and (c, b, d) that `grid_triangles`
    keeps). Six bytes a cell, without coordinates. A scan with `cell_bits` (`grid_cell_bits` of
    the whole scan it is part of: a prepared scan's view) takes its triangles from them, without
    measuring an edge."""
    bits = scan.cell_bits
    if bits is None:
        return [(grid, keep1, keep2) for grid, _, keep1, keep2 in _bands(scan, max_stretch)]
    out = []
    for grid, _ in scan_grids(scan):
        have = grid >= 0
        b = bits[np.maximum(grid, 0)]
        sides = have[:-1, 1:] & have[1:, :-1]  # b and c, in both triangles
        out.append((grid, sides & have[:-1, :-1] & ((b[:-1, :-1] & 1) > 0), sides & have[1:, 1:] & ((b[1:, 1:] & 2) > 0)))
    return out


def grid_cell_bits(scan: Scan, max_stretch: float = 8.0) -> np.ndarray:
    """(N,) uint8, the grid's triangles in a byte a point: bit 1 where the point is the corner a
    of a kept triangle (a, b, c), bit 2 where it is the corner d of a kept (c, b, d) (`_bands`).
    Any subset of the points that keeps its grid indices makes its triangles from them
    (`grid_cells`): what a prepared scan stores for its views (`grid_normals` makes them too, in
    the same pass). The scan's own `cell_bits` when it has them."""
    if scan.cell_bits is not None:
        return scan.cell_bits
    bits = np.zeros(len(scan), np.uint8)
    for grid, _, keep1, keep2 in _bands(scan, max_stretch):
        _set_bits(bits, grid, keep1, keep2)
    return bits


def _set_bits(bits: np.ndarray, grid: np.ndarray, keep1: np.ndarray, keep2: np.ndarray) -> None:
    bits[grid[:-1, :-1][keep1]] |= 1
    bits[grid[1:, 1:][keep2]] |= 2


def cell_triangles(grid: np.ndarray, keep1: np.ndarray, keep2: np.ndarray) -> np.ndarray:
    """(t, 3) int32: the triangles (a, b, c) of the cells keep1 and (c, b, d) of the cells keep2
    (r-1, c-1) bool of the grid band (r, c) (a b above c d)."""
    tri1 = np.stack([grid[:-1, :-1][keep1], grid[:-1, 1:][keep1], grid[1:, :-1][keep1]], 1)
    tri2 = np.stack([grid[1:, :-1][keep2], grid[:-1, 1:][keep2], grid[1:, 1:][keep2]], 1)
    return np.concatenate([tri1, tri2]).astype(np.int32, copy=False)


def grid_normals(scan: Scan, max_stretch: float = 8.0) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) float32 unit normals of a structured scan: per point the area-weighted sum of its
    `grid_triangles`, each turned toward its scanner (0 for a point in no triangle). Summed on
    the grid itself, band by band: no triangle list is made. And the grid's `grid_cell_bits`,
    made in the same pass."""
    out = np.zeros((len(scan), 3), np.float32)
    bits = np.zeros(len(scan), np.uint8)
    for grid, xyz, keep1, keep2 in _bands(scan, max_stretch):
        _set_bits(bits, grid, keep1, keep2)
        a, b, c, d = xyz[:-1, :-1], xyz[:-1, 1:], xyz[1:, :-1], xyz[1:, 1:]
        acc = np.zeros_like(xyz)
        # triangles (a, b, c) and (c, b, d) of each cell; xyz is relative to the scanner, so a
        # normal faces it when n . (0 - a) >= 0
        for (p, q, r), keep, at in (((a, b, c), keep1, ((0, 0), (0, 1), (1, 0))),
                                    ((c, b, d), keep2, ((1, 0), (0, 1), (1, 1)))):
            n = np.cross(q - p, r - p)
            n *= np.where(keep & (np.einsum("ijk,ijk->ij", n, p) > 0), -1, keep.astype(np.float32))[..., None]
            h, w = keep.shape
            for i, j in at:
                acc[i:i + h, j:j + w] += n
        have = grid >= 0
        out[grid[have]] += acc[have]
    # in place: on a 40-million-point scan each (N, 3) temporary is half a gigabyte, and this
    # is the peak of a scan's preparation (a point in no triangle stays 0)
    out /= np.sqrt(np.maximum(np.einsum("ij,ij->i", out, out), np.float32(1e-30)))[:, None]
    return out, bits


def _bands(scan: Scan, max_stretch: float, cells: int = 1 << 20):
    """Per scan of `scan`, per band of about `cells` grid cells: (grid band (r, c) of point indices
    (-1: none), its points (r, c, 3) float32 relative to the scanner, keep1 and keep2 (r-1, c-1):
    the cells' triangles (a, b, c) and (c, b, d) that `grid_triangles` keeps). Bands share their
    boundary row."""
    for grid, origin in scan_grids(scan):
        limit = max_stretch * row_step(scan.xyz, grid, origin)
        rows, cols = grid.shape
        step = max(1, cells // cols)
        for b0 in range(0, rows - 1, step):
            band = grid[b0:min(b0 + step + 1, rows)]
            yield (band, *_band(scan.xyz, band, origin, limit))


def scan_grids(scan: Scan):
    """Per scan of `scan`: (its grid (rows, cols) of point indices, `grid_image`; its scanner
    position (3,))."""
    if len(scan) == 0:
        return
    sid = scan.scan_id if scan.scan_id is not None else np.zeros(len(scan), np.int32)
    origins = scan.origins if len(scan.origins) else np.zeros((1, 3))
    one = sid.min() == sid.max()
    for s in [sid.min()] if one else np.unique(sid):
        idx = None if one else np.flatnonzero(sid == s)
        yield grid_image(scan.row, scan.col, idx), origins[min(int(s), len(origins) - 1)]


def grid_image(row: np.ndarray, col: np.ndarray, index: np.ndarray | None = None) -> np.ndarray:
    """(rows, cols) int32 point index per cell of the grid spanned by the points `index` (all when
    None) with grid indices row, col (N,); -1 where no point is."""
    r, c = (row, col) if index is None else (row[index], col[index])
    r0, c0 = int(r.min()), int(c.min())
    grid = np.full((int(r.max()) - r0 + 1, int(c.max()) - c0 + 1), -1, np.int32)
    grid[r - r0 if r0 else r, c - c0 if c0 else c] = np.arange(len(r), dtype=np.int32) if index is None else index
    return grid


def _band(points: np.ndarray, grid: np.ndarray, origin: np.ndarray, limit: float):
    """(xyz (r, c, 3) float32 relative to the origin, keep1, keep2 (r-1, c-1) bool) for the grid
    band (r, c) of point indices (-1: none); `limit` is the longest edge per metre of range."""
    # per grid vertex its point and range, per grid edge its length: each edge serves up to four
    # triangles, so this is cheaper than measuring every triangle's three edges
    have = grid >= 0
    xyz = np.zeros(grid.shape + (3,), np.float32)  # relative to the origin: float32 is exact to microns
    xyz[have] = points[grid[have]] - origin
    rng2 = np.where(have, np.einsum("ijk,ijk->ij", xyz, xyz), np.inf)

    def length2(p, q):
        d = p - q
        return np.einsum("ijk,ijk->ij", d, d)

    ab, cd = length2(xyz[:-1, :-1], xyz[:-1, 1:]), length2(xyz[1:, :-1], xyz[1:, 1:])
    ac, bd = length2(xyz[:-1, :-1], xyz[1:, :-1]), length2(xyz[:-1, 1:], xyz[1:, 1:])
    bc = length2(xyz[:-1, 1:], xyz[1:, :-1])
    ra, rb, rc, rd = rng2[:-1, :-1], rng2[:-1, 1:], rng2[1:, :-1], rng2[1:, 1:]
    ha, hb, hc, hd = have[:-1, :-1], have[:-1, 1:], have[1:, :-1], have[1:, 1:]
    lim2 = np.float32(limit * limit)  # squared lengths against squared ranges: no square roots
    keep1 = ha & hb & hc & (np.maximum(np.maximum(ab, bc), ac) <= lim2 * np.minimum(np.minimum(ra, rb), rc))
    keep2 = hc & hb & hd & (np.maximum(np.maximum(bc, bd), cd) <= lim2 * np.minimum(np.minimum(rc, rb), rd))
    return xyz, keep1, keep2


def row_step(points: np.ndarray, grid: np.ndarray, origin: np.ndarray, pairs: int = 1 << 20) -> float:
    """Median angle (radians) between grid neighbours along a row, seen from the origin (from
    evenly spaced rows holding about `pairs` neighbour pairs)."""
    rows = grid[:: max(1, grid.size // pairs)]
    a, b = rows[:, :-1].ravel(), rows[:, 1:].ravel()
    nb = (a >= 0) & (b >= 0)
    if not nb.any():
        return 1e-3
    u, v = points[a[nb]] - origin, points[b[nb]] - origin
    cos = np.sum(u * v, axis=1) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1), 1e-30)
    return float(np.median(np.arccos(np.clip(cos, -1, 1))))
