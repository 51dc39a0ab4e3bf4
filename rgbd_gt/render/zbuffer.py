"""Visibility of points by a coarse Z-buffer.

A Z-buffer at full image resolution lets background points show through the gaps between
the projections of foreground points, because a point cloud covers only part of the pixels.
Cells of `cell` x `cell` pixels, with `cell` at least the projected point spacing, close those
gaps: a point is visible when its depth is within a tolerance of the nearest depth in its cell.
"""

from __future__ import annotations

import math

import torch


def estimate_spacing(points: torch.Tensor) -> float:
    """Typical distance between neighbouring points (metres) of a surface sampling, from voxel
    occupancy: a voxel of side v holding n/M points on a surface has spacing v / sqrt(n/M)."""
    n = points.shape[0]
    extent = float((points.max(0).values - points.min(0).values).max().clamp_min(1e-6))
    v = extent / 64
    for _ in range(8):
        keys = torch.floor((points - points.min(0).values) / v).long()
        m = torch.unique(keys[:, 0] * 4_000_000_000 + keys[:, 1] * 63_000 + keys[:, 2]).numel()
        if n / m >= 4:  # several points per voxel: the estimate is meaningful
            break
        v *= 2
    return v / math.sqrt(n / m)


def visible_points(uv: torch.Tensor, z: torch.Tensor, size: tuple[int, int], cell: int,
                   rel_tol: float = 0.02, abs_tol: float = 0.01, near: float = 1e-3,
                   group: torch.Tensor | None = None, facing: torch.Tensor | None = None,
                   silhouette: float = 0.0) -> torch.Tensor:
    """Boolean mask (N,) of points that are in the image, in front of the camera, not occluded,
    (given `facing`) not seen from behind and (given `silhouette` > 0) not on a silhouette.

    Args:
        uv: (N, 2) pixel coordinates; z: (N,) depth (metres).
        size: (width, height) of the image.
        cell: Z-buffer cell side in pixels.
        rel_tol, abs_tol: a point is visible when z <= zmin_cell * (1 + rel_tol) + abs_tol.
        group: (N,) int64, optional: points of different groups (the same points seen from
            several poses) are in separate Z-buffers.
        facing: (N,) bool, optional (`render.normals.facing_camera`): points whose surface faces
            away are never visible, but they still hide what lies behind them.
        silhouette: leave out the points on a foreground silhouette, where a surface more than
            this much farther (relative depth) shows in their Z-buffer cell or the 8 around it
            (`_on_silhouette`; 0: silhouettes are visible).
    """
    inside, key, zmin = _cell_minima(uv, z, size, cell, near, group)
    vis = inside & (z <= zmin.reshape(-1)[key] * (1 + rel_tol) + abs_tol)
    if silhouette > 0:
        vis &= ~_on_silhouette(key, zmin, z, silhouette)
    return vis if facing is None else vis & facing


def _cell_minima(uv: torch.Tensor, z: torch.Tensor, size: tuple[int, int], cell: int, near: float = 1e-3,
                 group: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The Z-buffer: per point (N,) whether it is in the image and in front of the camera, and
    its flat cell index into the nearest depth per cell (G, ch, cw) (inf where empty; G groups)."""
    w, h = size
    u, v = uv[:, 0], uv[:, 1]
    inside = (z > near) & (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
    cw, ch = (w + cell - 1) // cell, (h + cell - 1) // cell
    key = (v.clamp(0, h - 1) / cell).long() * cw + (u.clamp(0, w - 1) / cell).long()
    groups = 1
    if group is not None:
        groups = int(group.max()) + 1 if group.numel() else 1
        key = key + group * (ch * cw)
    zz = torch.where(inside, z, torch.full_like(z, float("inf")))
    zmin = torch.full((groups * ch * cw,), float("inf"), dtype=z.dtype, device=z.device)
    zmin = zmin.scatter_reduce(0, key, zz, reduce="amin", include_self=True)
    return inside, key, zmin.reshape(groups, ch, cw)


def _on_silhouette(key: torch.Tensor, zmin: torch.Tensor, z: torch.Tensor, ratio: float) -> torch.Tensor:
    """Per point (N,), on a Z-buffer (`_cell_minima`'s key (N,) and zmin (G, ch, cw)): whether
    a surface more than `ratio` farther than its z (N,) shows in its cell or the 8 around it: a
    point on a foreground silhouette, whose pixel the photo mixes with what lies behind (lens
    blur, pixel area, bilinear sampling), as a scan's color of it, seen from elsewhere, does not.
    Empty cells (gaps, sky) are no edge. (Leaving out the other side of the edge too, the points
    beside an occluder, helped a stereo rig no further and cost ICL-NUIM more: docs/bundle.md.)"""
    grid = zmin[:, None]
    farthest = torch.nn.functional.max_pool2d(torch.where(torch.isinf(grid), torch.zeros_like(grid), grid), 3, 1, 1)
    return farthest.reshape(-1)[key] > z * (1 + ratio)


def check_spread_in_view(uv: torch.Tensor, visible: torch.Tensor, need: int) -> None:
    """InputError when the visible points (uv (N, 2) pixels, visible (N,) bool) fall on fewer than
    `need` / 2 distinct pixels: identical or nearly identical points, which no pose can be fitted to."""
    from rgbd_gt.errors import InputError

    px = torch.round(uv[visible]).long()
    pixels = torch.unique((px[:, 1] - px[:, 1].min()) * (px[:, 0].max() - px[:, 0].min() + 1) + px[:, 0]).numel() if px.numel() else 0
    if pixels < need / 2:
        raise InputError(f"the {int(visible.sum())} scan points in view of the initial pose fall on only {pixels} "
                         "pixels (identical or nearly identical points): there is nothing to align")


def depth_edges(uv: torch.Tensor, z: torch.Tensor, size: tuple[int, int], cell: int, ratio: float = 0.5) -> torch.Tensor:
    """Per point (N,) in [0, 1]: how far the point stands in front of what lies beside it in the
    image, from a Z-buffer of `cell`-pixel cells: (z_side / z - 1) / ratio, clipped, where z_side
    is the larger of the nearest depths in the cells to its left and right; 1 where a side cell
    is empty (a silhouette against the sky or a gap). 0 off the image or at its border.

    Only left and right: a ring-structured sweep leaves empty rows between rings, so vertical
    neighbours say nothing; the rings resolve vertical edges (poles, car sides, trunks) best."""
    inside, key, zmin = _cell_minima(uv, z, size, cell)
    zmin = zmin[0]
    side = torch.full_like(zmin, 0.0)
    side[:, 1:-1] = torch.maximum(zmin[:, :-2], zmin[:, 2:])
    far = side.reshape(-1)[key]
    e = ((far / z.clamp_min(1e-6) - 1) / ratio).clamp(0, 1)
    return torch.where(inside & torch.isfinite(e), e, torch.where(inside & torch.isinf(far), torch.ones_like(e), torch.zeros_like(e)))
