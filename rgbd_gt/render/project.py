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
