"""Pinhole projection of point tensors."""

from __future__ import annotations

import torch


def project_pinhole(points: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-frame points (N, 3), metres -> pixels uv (N, 2) and depth z (N,).

    K: (3, 3) intrinsics (no distortion: photos are undistorted once beforehand).
    Points with z <= 0 produce meaningless uv; callers mask them by z.
    """
    z = points[:, 2]
    zs = z.clamp_min(1e-9)
    u = K[0, 0] * points[:, 0] / zs + K[0, 2]
    v = K[1, 1] * points[:, 1] / zs + K[1, 2]
    return torch.stack([u, v], dim=1), z


def projection_jacobian(points: torch.Tensor, fx, fy) -> tuple[torch.Tensor, torch.Tensor]:
    """d(u, v) / d(rotation vector, translation) (two (N, 6) tensors) of camera-frame points
    (N, 3) for the update p' = exp(w) p + v at w = v = 0 (`pose.apply_update`)."""
    x, y, z = points.unbind(1)
    iz = 1.0 / z
    du = torch.stack([-fx * x * y * iz**2, fx * (1 + x * x * iz**2), -fx * y * iz,
                      fx * iz, torch.zeros_like(x), -fx * x * iz**2], 1)
    dv = torch.stack([-fy * (1 + y * y * iz**2), fy * x * y * iz**2, fy * x * iz,
                      torch.zeros_like(x), fy * iz, -fy * y * iz**2], 1)
    return du, dv
