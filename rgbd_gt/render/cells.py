"""How big a Z-buffer cell must be for a projection of scan points: the one cell-size rule, in two
forms (from the 3D spacing, or measured in the image). No torch: the overlay of a colored scan
uses it without paying torch's import."""

from __future__ import annotations

import math

import numpy as np


def cell_size_for(spacing_m: float, focal_px: float, median_depth_m: float, minimum: int = 1) -> int:
    """Cell side (pixels) that no gap between neighbouring points can slip through:
    1.5 x the projected point spacing at the median depth, at least `minimum`."""
    projected = focal_px * spacing_m / max(median_depth_m, 1e-6)
    return max(minimum, int(math.ceil(1.5 * projected)))


def cell_for_density(uv, size: tuple[int, int], per_cell: int = 3, largest: int = 64) -> int:
    """Cell side (pixels, a power of 2, at most `largest`) at which the occupied cells of a
    projection uv (N, 2) (numpy or torch) hold at least `per_cell` points at the (lower) median:
    the projected spacing, measured in the image.

    `cell_size_for` derives it from the 3D spacing at the median depth, which fits dense scans;
    a LiDAR sweep has rings with large vertical gaps, points from 2 to 100 m and nothing on the
    sky, so its spacing is best measured where it lands."""
    uv = uv.detach().cpu().numpy() if hasattr(uv, "detach") else np.asarray(uv)
    w, h = size
    inside = (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
    u, v = uv[inside, 0], uv[inside, 1]
    cell = 1
    while cell < largest and len(u):
        cw = (w + cell - 1) // cell
        counts = np.bincount((v // cell).astype(np.int64) * cw + (u // cell).astype(np.int64))
        occupied = np.sort(counts[counts > 0])
        if occupied[(len(occupied) - 1) // 2] >= per_cell:
            break
        cell *= 2
    return cell
