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




def _distorted(x: torch.Tensor, y: torch.Tensor, q: torch.Tensor):
    """OpenCV's distortion of normalised coordinates by q[3:8] = (k1, k2, p1, p2, k3): x_d, y_d,
    and r^2 and the radial factor."""
    r2 = x * x + y * y
    radial = 1 + q[3] * r2 + q[4] * r2 * r2 + q[7] * r2 * r2 * r2
    xd = x * radial + 2 * q[5] * x * y + q[6] * (r2 + 2 * x * x)
    yd = y * radial + q[5] * (r2 + 2 * y * y) + 2 * q[6] * x * y
    return xd, yd, r2, radial


def project_corrected(points: torch.Tensor, K: torch.Tensor, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`project_pinhole` through a corrected camera: the normalised coordinates (x, y) get
    OpenCV's distortion by (k1, k2, p1, p2, k3) = q[3:8], then u = fx (1 + q0) x_d + cx + fx q1,
    likewise v. q (Q_SIZE,) is relative, so one q serves every pyramid level. (On a photo
    undistorted with the camera's own coefficients, these are what is left to add to them, to
    first order.)"""
    z = points[:, 2]
    zs = z.clamp_min(1e-9)
    xd, yd, _, _ = _distorted(points[:, 0] / zs, points[:, 1] / zs, q)
    u = K[0, 0] * ((1 + q[0]) * xd + q[1]) + K[0, 2]
    v = K[1, 1] * ((1 + q[0]) * yd + q[2]) + K[1, 2]
    return torch.stack([u, v], dim=1), z


def corrected_jacobian(points: torch.Tensor, K: torch.Tensor, q: torch.Tensor, free: int) -> tuple[torch.Tensor, torch.Tensor]:
    """d(u, v) / d(rotation vector, translation, q[:free]) of `project_corrected`: two (N, 6 + free)."""
    x_, y_ = projection_jacobian(points, 1.0, 1.0)  # d(x, y) / d(pose) of the normalised coordinates
    z = points[:, 2].clamp_min(1e-9)
    x, y = points[:, 0] / z, points[:, 1] / z
    xd, yd, r2, radial = _distorted(x, y, q)
    dradial = 2 * (q[3] + 2 * q[4] * r2 + 3 * q[7] * r2 * r2)  # d radial / d(r^2) x 2
    dxx = radial + x * x * dradial + 2 * q[5] * y + 6 * q[6] * x
    dxy = x * y * dradial + 2 * q[5] * x + 2 * q[6] * y  # = d y_d / d x
    dyy = radial + y * y * dradial + 6 * q[5] * y + 2 * q[6] * x
    fu, fv = K[0, 0] * (1 + q[0]), K[1, 1] * (1 + q[0])
    du = fu * (dxx[:, None] * x_ + dxy[:, None] * y_)
    dv = fv * (dxy[:, None] * x_ + dyy[:, None] * y_)
    zero, one = torch.zeros_like(x), torch.ones_like(x)
    xy2, r4 = 2 * x * y, r2 * r2
    cu = [K[0, 0] * xd, K[0, 0] * one, zero, fu * x * r2, fu * x * r4, fu * xy2, fu * (r2 + 2 * x * x), fu * x * r4 * r2]
    cv = [K[1, 1] * yd, zero, K[1, 1] * one, fv * y * r2, fv * y * r4, fv * (r2 + 2 * y * y), fv * xy2, fv * y * r4 * r2]
    return (torch.cat([du, torch.stack(cu[:free], 1)], 1) if free else du,
            torch.cat([dv, torch.stack(cv[:free], 1)], 1) if free else dv)
