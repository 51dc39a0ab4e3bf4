"""Rendering a point cloud into a camera by splatting with a depth test."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch


@dataclass
class Surfels:
    """Points as discs of their tangent planes: per point (N,) the inverse-depth slope
    d(1/z)/d(u, v) (N, 2) (1/m per pixel; inverse depth is affine in the image for a plane) and
    the disc radius (N,) in metres; fx, fy the focal lengths in pixels."""

    inv_depth_slope: torch.Tensor
    radius_m: torch.Tensor
    fx: float
    fy: float


def render_points(points_cam: torch.Tensor, values: torch.Tensor, K: torch.Tensor, size: tuple[int, int],
                  radius: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest-point image of camera-frame points (N, 3) through the pinhole K (3, 3); see `splat`."""
    from rgbd_gt.render.project import project_pinhole

    uv, z = project_pinhole(points_cam, K)
    return splat(uv, z, values, size, radius)


# `_squares` costs about 1/12 of a footprint entry per pixel and offset: it is the quicker where the
# points are at least 1/12 of the pixels (a dense scan: 10x on 267k points, radius 2, 640x480), the
# per-point footprints where they are fewer (a LiDAR sweep's few thousand, wide)
SQUARES_DENSITY = 12


def splat(uv: torch.Tensor, z: torch.Tensor, values: torch.Tensor, size: tuple[int, int],
          radius: int = 0, surfels: Surfels | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest-point image of points projected at uv (N, 2) with depth z (N,).

    Each point covers the (2 radius + 1)^2 pixels around its projection; per pixel the nearest
    point wins. values: (N, C); size: (width, height). surfels: each point is then a disc of its
    tangent plane, whose depth varies over its footprint, and which covers only the pixels whose
    rays meet the disc (a flat square at the point's depth grows every silhouette by the
    footprint); radius then bounds the footprints. Returns image (H, W, C) (0 where empty),
    depth (H, W) metres (0 where empty) and index (H, W) int64 of the winning point (-1 where empty).
    """
    w, h = size
    px = torch.round(uv).long()
    ok = (z > 1e-6) & (px[:, 0] >= -radius) & (px[:, 1] >= -radius) & (px[:, 0] < w + radius) & (px[:, 1] < h + radius)
    ids = torch.nonzero(ok).squeeze(1)
    px, z = px[ids], z[ids]
    if surfels is None and len(z) * SQUARES_DENSITY >= w * h:
        index, zmin = _squares(px, z, ids, size, radius)
        depth = torch.where(index >= 0, zmin, torch.zeros_like(zmin))
        return values_at(values, index), depth, index
    footprint = torch.full_like(z, radius, dtype=torch.long)
    if surfels is not None:
        slope, reach = surfels.inv_depth_slope[ids].to(z.dtype), surfels.radius_m[ids].to(z.dtype)
        frac = uv[ids].to(z.dtype) - px.to(z.dtype)  # the footprint's offsets are from the point's own position
        # most discs are far smaller than the largest, so each is drawn with its own footprint:
        # d pixels out, where the plane's inverse depth is 1/z + s d (s its slope), the ray meets it
        # reach away once d = reach f / z / (1 - reach f s)
        f = max(surfels.fx, surfels.fy)
        tilt = (1 - reach * f * slope.norm(dim=1)).clamp_min(1e-3)
        footprint = torch.ceil(reach * f / z / tilt).long().clamp(1, max(radius, 1))
    zmin = torch.full((h * w,), float("inf"), dtype=z.dtype, device=z.device)
    index = torch.full((h * w,), -1, dtype=torch.long, device=z.device)
    passes = []
    for size_px in torch.unique(footprint).tolist():
        group = torch.nonzero(footprint == size_px).squeeze(1)
        r = torch.arange(-size_px, size_px + 1, device=px.device)
        offsets = torch.stack(torch.meshgrid(r, r, indexing="ij"), -1).reshape(-1, 2)  # (K, 2) as (dy, dx)
        # the group's footprints at once, in chunks of offsets that keep a pass near 2^22 entries
        chunk = max(1, (1 << 22) // max(len(group), 1))
        zg, owners = z[group], ids[group]
        for k in range(0, len(offsets), chunk):
            off = offsets[k:k + chunk]
            x = px[None, group, 0] + off[:, None, 1]
            y = px[None, group, 1] + off[:, None, 0]
            inside = (x >= 0) & (y >= 0) & (x < w) & (y < h)
            if surfels is None:
                zz = zg.expand_as(x)
            else:
                du = off[:, None, 1].to(z.dtype) - frac[None, group, 0]
                dv = off[:, None, 0].to(z.dtype) - frac[None, group, 1]
                zz = 1 / (1 / zg[None] + slope[None, group, 0] * du + slope[None, group, 1] * dv).clamp_min(1e-6)
                # the ray meets the plane this far from the point: sideways and in depth
                lateral2 = zz**2 * ((du / surfels.fx) ** 2 + (dv / surfels.fy) ** 2)
                inside &= lateral2 + (zz - zg[None]) ** 2 <= reach[None, group] ** 2
            key = (y * w + x)[inside]
            zz = zz[inside]
            owner = owners.expand_as(x)[inside]
            zmin.scatter_reduce_(0, key, zz, reduce="amin", include_self=True)
            passes.append((key, zz, owner))
    for key, zz, owner in passes:  # the nearest point of each pixel owns it
        win = zz <= zmin[key]
        index[key[win]] = owner[win]
    index, zmin = index.reshape(h, w), zmin.reshape(h, w)
    depth = torch.where(index >= 0, zmin, torch.zeros_like(zmin))
    return values_at(values, index), depth, index


def _squares(px: torch.Tensor, z: torch.Tensor, ids: torch.Tensor, size: tuple[int, int],
             radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """`splat` of flat squares: (index (H, W) of the nearest point whose square covers each pixel,
    -1 where none; its depth (H, W), inf where none), for points at pixels px (n, 2) (within
    radius of the image) with depths z (n,) and indices ids (n,). Every square of one centre
    pixel covers the same pixels, so only the nearest point of each centre pixel can win: a
    minimum filter over an image of the centres, one shifted slice per offset instead of
    (2 radius + 1)^2 entries per point."""
    w, h = size
    W, H = w + 2 * radius, h + 2 * radius  # the centres, with the border whose squares reach in
    key = (px[:, 1] + radius) * W + px[:, 0] + radius
    centre_z = torch.full((H * W,), float("inf"), dtype=z.dtype, device=z.device)
    centre_z.scatter_reduce_(0, key, z, reduce="amin", include_self=True)
    nearest = z <= centre_z[key]
    centre_i = torch.full((H * W,), -1, dtype=torch.long, device=z.device)
    centre_i[key[nearest]] = ids[nearest]
    centre_z, centre_i = centre_z.reshape(H, W), centre_i.reshape(H, W)
    zmin = torch.full((h, w), float("inf"), dtype=z.dtype, device=z.device)
    index = torch.full((h, w), -1, dtype=torch.long, device=z.device)
    for dy in range(-radius, radius + 1):  # pixel (y, x) is covered by the square of centre (y - dy, x - dx)
        for dx in range(-radius, radius + 1):
            zs = centre_z[radius - dy:radius - dy + h, radius - dx:radius - dx + w]
            nearer = zs < zmin
            zmin = torch.where(nearer, zs, zmin)
            index = torch.where(nearer, centre_i[radius - dy:radius - dy + h, radius - dx:radius - dx + w], index)
    return index, zmin


def values_at(values: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """The image (H, W, C) of the points' values (N, C) at the pixels they own (index (H, W),
    -1 where empty: 0)."""
    have = index >= 0
    image = torch.zeros(index.shape + (values.shape[1],), dtype=values.dtype, device=values.device)
    image[have] = values[index[have]]
    return image


def close_gaps(depth: np.ndarray, index: np.ndarray, reach_px: np.ndarray,
               tolerance: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Fill the empty runs of pixels, along rows and along columns, that lie between two pixels
    of one surface: depths (H, W) metres (0 empty) within `tolerance` of each other, and a run
    no longer than the discs of the points that own its two ends reach together (reach_px (N,)
    pixels, by the points' index (H, W)): a gap the scan's sampling does not resolve. The
    inverse depth is interpolated (affine in the image on a plane) and each pixel takes the
    index of the nearer end. A scanner's columns are often much farther apart than the points
    within one (pumpA: 4 times), and discs that covered the columns' gaps would grow every
    silhouette along them by as much; a run between unlike depths (a silhouette) or wider than
    the two discs (a gap between two bars against the sky) stays empty. Returns new arrays."""
    filled_z, filled_i = depth.copy(), index.copy()
    best = np.full(depth.shape, np.inf)
    longest = int(np.ceil(2 * reach_px.max())) if len(reach_px) else 0
    for axis in (1, 0):
        z, idx = (depth, index) if axis == 1 else (depth.T, index.T)
        n = z.shape[1]
        at = np.broadcast_to(np.arange(n, dtype=np.int32), z.shape)
        have = z > 0
        left = np.maximum.accumulate(np.where(have, at, -1), axis=1)
        right = np.minimum.accumulate(np.where(have, at, n)[:, ::-1], axis=1)[:, ::-1]
        r, c = np.nonzero(~have & (left >= 0) & (right < n) & (right - left <= longest + 1))
        lo, hi = left[r, c], right[r, c]
        zl, zr = z[r, lo], z[r, hi]
        keep = (np.abs(zl - zr) <= tolerance * np.minimum(zl, zr)) & \
            (hi - lo - 1 <= reach_px[idx[r, lo]] + reach_px[idx[r, hi]])
        r, c, lo, hi, zl, zr = r[keep], c[keep], lo[keep], hi[keep], zl[keep], zr[keep]
        t = (c - lo) / (hi - lo)
        z_new = 1 / ((1 - t) / zl + t / zr)
        i_new = np.where(t <= 0.5, idx[r, lo], idx[r, hi])
        rr, cc = (r, c) if axis == 1 else (c, r)
        shorter = (hi - lo) < best[rr, cc]  # where both passes fill, the shorter run decides
        rr, cc = rr[shorter], cc[shorter]
        filled_z[rr, cc], filled_i[rr, cc], best[rr, cc] = z_new[shorter], i_new[shorter], (hi - lo)[shorter]
    return filled_z, filled_i
