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


# Camera corrections refined with the pose (`refine --refine-intrinsics`), per mode: how many of
# q = (focal scale - 1, principal point shift x and y in normalised units, k1, k2) are free.
INTRINSICS = {"none": 0, "focal": 1, "focal+principal": 3, "focal+principal+k1k2": 5}


def project_corrected(points: torch.Tensor, K: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`project_pinhole` through a corrected camera: the normalised coordinates (x, y) get the
    radial factor 1 + k1 r^2 + k2 r^4, then u = fx (1 + q0) x_d + cx + fx q1, likewise v. q (5,)
    is relative, so one q serves every pyramid level. (On a photo undistorted with the camera's
    own coefficients, k1 and k2 are what is left to add to them, to first order.)"""
    z = points[:, 2]
    zs = z.clamp_min(1e-9)
    x, y = points[:, 0] / zs, points[:, 1] / zs
    r2 = x * x + y * y
    radial = 1 + q[3] * r2 + q[4] * r2 * r2
    u = K[0, 0] * ((1 + q[0]) * x * radial + q[1]) + K[0, 2]
    v = K[1, 1] * ((1 + q[0]) * y * radial + q[2]) + K[1, 2]
    return torch.stack([u, v], dim=1), z


def corrected_jacobian(points: torch.Tensor, K: torch.Tensor, q: torch.Tensor, free: int) -> tuple[torch.Tensor, torch.Tensor]:
    """d(u, v) / d(rotation vector, translation, q[:free]) of `project_corrected`: two (N, 6 + free)."""
    x_, y_ = projection_jacobian(points, 1.0, 1.0)  # d(x, y) / d(pose) of the normalised coordinates
    z = points[:, 2].clamp_min(1e-9)
    x, y = points[:, 0] / z, points[:, 1] / z
    r2 = x * x + y * y
    radial = 1 + q[3] * r2 + q[4] * r2 * r2
    dradial = 2 * (q[3] + 2 * q[4] * r2)  # d radial / d(r^2) x 2
    fu, fv = K[0, 0] * (1 + q[0]), K[1, 1] * (1 + q[0])
    du = fu * ((radial + x * x * dradial)[:, None] * x_ + (x * y * dradial)[:, None] * y_)
    dv = fv * ((x * y * dradial)[:, None] * x_ + (radial + y * y * dradial)[:, None] * y_)
    zero = torch.zeros_like(x)
    cu = [K[0, 0] * x * radial, K[0, 0] * torch.ones_like(x), zero, fu * x * r2, fu * x * r2 * r2]
    cv = [K[1, 1] * y * radial, zero, K[1, 1] * torch.ones_like(x), fv * y * r2, fv * y * r2 * r2]
    return (torch.cat([du, torch.stack(cu[:free], 1)], 1) if free else du,
            torch.cat([dv, torch.stack(cv[:free], 1)], 1) if free else dv)
