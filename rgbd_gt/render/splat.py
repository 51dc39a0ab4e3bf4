"""Rendering a point cloud into a camera by splatting with a depth test."""

from __future__ import annotations

import torch


def render_points(points_cam: torch.Tensor, values: torch.Tensor, K: torch.Tensor, size: tuple[int, int],
                  radius: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest-point image of camera-frame points (N, 3) through the pinhole K (3, 3); see `splat`."""
    from rgbd_gt.render.project import project_pinhole

    uv, z = project_pinhole(points_cam, K)
    return splat(uv, z, values, size, radius)


def splat(uv: torch.Tensor, z: torch.Tensor, values: torch.Tensor, size: tuple[int, int],
          radius: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Nearest-point image of points projected at uv (N, 2) with depth z (N,).

    Each point covers the (2 radius + 1)^2 pixels around its projection; per pixel the nearest
    point wins. values: (N, C); size: (width, height). Returns image (H, W, C) (0 where empty),
    depth (H, W) metres (0 where empty) and index (H, W) int64 of the winning point (-1 where empty).
    """
    w, h = size
    px = torch.round(uv).long()
    ok = (z > 1e-6) & (px[:, 0] >= -radius) & (px[:, 1] >= -radius) & (px[:, 0] < w + radius) & (px[:, 1] < h + radius)
    ids = torch.nonzero(ok).squeeze(1)
    px, z = px[ids], z[ids]
    r = torch.arange(-radius, radius + 1, device=px.device)
    offsets = torch.stack(torch.meshgrid(r, r, indexing="ij"), -1).reshape(-1, 2)  # (K, 2) as (dy, dx)
    zmin = torch.full((h * w,), float("inf"), dtype=z.dtype, device=z.device)
    index = torch.full((h * w,), -1, dtype=torch.long, device=z.device)
    # every point's footprint at once, in chunks of offsets that keep a pass near 2^22 entries
    chunk = max(1, (1 << 22) // max(len(ids), 1))
    passes = []
    for k in range(0, len(offsets), chunk):
        off = offsets[k:k + chunk]
        x = px[None, :, 0] + off[:, None, 1]
        y = px[None, :, 1] + off[:, None, 0]
        inside = (x >= 0) & (y >= 0) & (x < w) & (y < h)
        key = (y * w + x)[inside]
        zz = z.expand_as(x)[inside]
        owner = ids.expand_as(x)[inside]
        zmin.scatter_reduce_(0, key, zz, reduce="amin", include_self=True)
        passes.append((key, zz, owner))
    for key, zz, owner in passes:  # the nearest point of each pixel owns it
        win = zz <= zmin[key]
        index[key[win]] = owner[win]
    have = index >= 0
    image = torch.zeros(h * w, values.shape[1], dtype=values.dtype, device=values.device)
    image[have] = values[index[have]]
    depth = torch.where(have, zmin, torch.zeros_like(zmin))
    return image.reshape(h, w, -1), depth.reshape(h, w), index.reshape(h, w)
