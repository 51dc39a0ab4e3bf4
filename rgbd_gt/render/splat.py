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
    keys, zs, owners = [], [], []
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            x, y = px[:, 0] + dx, px[:, 1] + dy
            inside = (x >= 0) & (y >= 0) & (x < w) & (y < h)
            keys.append((y * w + x)[inside])
            zs.append(z[inside])
            owners.append(ids[inside])
    key, zz, owner = torch.cat(keys), torch.cat(zs), torch.cat(owners)
    zmin = torch.full((h * w,), float("inf"), dtype=zz.dtype, device=zz.device)
    zmin = zmin.scatter_reduce(0, key, zz, reduce="amin", include_self=True)
    win = zz <= zmin[key]
    index = torch.full((h * w,), -1, dtype=torch.long, device=zz.device)
    index[key[win]] = owner[win]
    have = index >= 0
    image = torch.zeros(h * w, values.shape[1], dtype=values.dtype, device=values.device)
    image[have] = values[index[have]]
    depth = torch.where(have, zmin, torch.zeros_like(zmin))
    return image.reshape(h, w, -1), depth.reshape(h, w), index.reshape(h, w)
