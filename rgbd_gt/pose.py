"""Rigid-pose arithmetic on 4x4 numpy matrices, SO(3) once for numpy and torch, and the error
measures of the benchmarks."""

from __future__ import annotations

import numpy as np


def project_to_so3(R: np.ndarray) -> np.ndarray:
    """The nearest rotation (Frobenius norm) to a 3x3 matrix, by SVD."""
    U, _, Vt = np.linalg.svd(np.asarray(R, np.float64))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def rotation_error_deg(Ta: np.ndarray, Tb: np.ndarray) -> float:
    """Geodesic angle (degrees) between the rotations of two poses (4x4 or 3x3).

    Uses 2 asin(|Ra Rb^T - I|_F / sqrt 8) on rotations projected onto SO(3): the usual
    arccos((trace - 1) / 2) loses ~0.03 deg to round-off near zero, more than the errors measured.
    """
    Ra = project_to_so3(np.asarray(Ta)[:3, :3])
    Rb = project_to_so3(np.asarray(Tb)[:3, :3])
    x = np.linalg.norm(Ra @ Rb.T - np.eye(3)) / np.sqrt(8.0)
    return float(np.degrees(2 * np.arcsin(min(x, 1.0))))


def camera_centre(T_cam_from_scan: np.ndarray) -> np.ndarray:
    """(3,) position of the camera in the scan frame: -R^T t."""
    T = np.asarray(T_cam_from_scan, np.float64)
    return -T[:3, :3].T @ T[:3, 3]


def translation_error_m(Ta: np.ndarray, Tb: np.ndarray) -> float:
    """Distance (metres) between the camera centres of two T_cam_from_scan poses."""
    return float(np.linalg.norm(camera_centre(Ta) - camera_centre(Tb)))


def rigid(R: np.ndarray, t) -> np.ndarray:
    """The 4x4 transform p -> R p + t of a rotation R (3, 3) and a translation t (3,)."""
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = np.ravel(t)
    return T


def invert(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform."""
    R, t = T[:3, :3], T[:3, 3]
    return rigid(R.T, -R.T @ t)


def translated(T: np.ndarray, c) -> np.ndarray:
    """T (4x4) applied after a shift by c (3,): p -> T (p + c). With c the centre of a scan,
    it is the pose in the scan's local frame (float32 stays exact there); with -c, back."""
    out = np.array(T, np.float64)
    out[:3, 3] = out[:3, :3] @ np.asarray(c, np.float64) + out[:3, 3]
    return out


def random_starts(T: np.ndarray, count: int, rot: float, trans: float, seed: int) -> list[np.ndarray]:
    """`count` poses around T, each turned by `rot` radians about a random axis and moved by
    `trans` metres in a random direction (camera frame)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(count):
        a, b = rng.normal(size=3), rng.normal(size=3)
        out.append(apply_update(T, np.r_[a / np.linalg.norm(a) * rot, b / np.linalg.norm(b) * trans]))
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points."""
    return points @ T[:3, :3].T + T[:3, 3]


def _torch_or_numpy(w):
    """The array module of w: torch for a tensor (imported only when one is given), else numpy."""
    if not type(w).__module__.startswith("torch"):
        return np
    import torch

    return torch


def _hat_and_eye(w):
    """(..., 3, 3) cross-product matrices of w (..., 3) and the identity (3, 3), in w's array
    module, dtype and device."""
    xp = _torch_or_numpy(w)
    x, y, z = w[..., 0], w[..., 1], w[..., 2]
    zero = x * 0
    K = xp.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(w.shape[:-1] + (3, 3))
    eye = xp.eye(3, dtype=w.dtype) if xp is np else xp.eye(3, dtype=w.dtype, device=w.device)
    return xp, K, eye


def so3_exp(w):
    """Rotation matrices (..., 3, 3) of the rotation vectors w (..., 3), radians (Rodrigues). numpy
    float64, or a torch tensor of any float dtype and device (differentiable, also at 0)."""
    w = w if _torch_or_numpy(w) is not np else np.asarray(w, np.float64)
    xp, K, eye = _hat_and_eye(w)
    theta2 = (w * w).sum(-1)[..., None, None]
    small = theta2 < 1e-12
    theta = xp.sqrt(xp.where(small, theta2 * 0 + 1, theta2))
    a = xp.where(small, 1 - theta2 / 6, xp.sin(theta) / theta)
    b = xp.where(small, 0.5 - theta2 / 24, (1 - xp.cos(theta)) / theta**2)
    return eye + a * K + b * (K @ K)


def so3_left_jacobian(w):
    """(..., 3, 3) J with so3_exp(w + e) = so3_exp(J e) so3_exp(w) to first order in e (3,); w (..., 3)
    as `so3_exp`'s."""
    w = w if _torch_or_numpy(w) is not np else np.asarray(w, np.float64)
    xp, K, eye = _hat_and_eye(w)
    theta2 = (w * w).sum(-1)[..., None, None]
    small = theta2 < 1e-8
    theta = xp.sqrt(xp.where(small, theta2 * 0 + 1, theta2))
    a = xp.where(small, 0.5 - theta2 / 24, (1 - xp.cos(theta)) / theta**2)
    b = xp.where(small, 1 / 6 - theta2 / 120, (theta - xp.sin(theta)) / theta**3)
    return eye + a * K + b * (K @ K)


def apply_update(T: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Left-multiply T (4x4) by the update delta = (rotation vector (3,), translation (3,)):
    p' = exp(w) p + v, in the camera frame."""
    return rigid(so3_exp(delta[:3]), delta[3:]) @ T


def update_of(T: np.ndarray) -> np.ndarray:
    """The update d (6,) with apply_update(I, d) = T (4x4): (rotation vector, translation)."""
    R = T[:3, :3]
    angle = np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    w = w * (0.5 if angle < 1e-8 else angle / (2 * np.sin(angle)))
    return np.r_[w, T[:3, 3]]


def update_through(A: np.ndarray) -> np.ndarray:
    """(6, 6) M: the update of A @ B (`apply_update`, in the camera frame of A @ B) when B gets
    the update d, to first order: M d. A: 4x4 (the adjoint of A in apply_update's terms)."""
    R, t = np.asarray(A[:3, :3], np.float64), np.asarray(A[:3, 3], np.float64)
    M = np.zeros((6, 6))
    M[:3, :3] = R
    M[3:, :3] = _hat_and_eye(t)[1] @ R
    M[3:, 3:] = R
    return M


def worst_sigmas(cov: np.ndarray) -> dict:
    """The 1-sigma of a pose along its worst-determined directions, from the covariance (6, 6)
    of the update (rotation vector, translation) of `apply_update`: `rotation_deg` and
    `translation_mm` (the camera centre moves by -R^T v for an update (w, v), so the
    translation block's eigenvalues are the camera position's)."""
    return {"rotation_deg": float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov[:3, :3])[-1], 0.0)))),
            "translation_mm": float(np.sqrt(max(np.linalg.eigvalsh(cov[3:, 3:])[-1], 0.0)) * 1e3)}


def quat_to_matrix(q: list[float]) -> np.ndarray:
    """(w, x, y, z), normalised (some writers store non-unit quaternions) -> (3, 3)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_to_quat(R: np.ndarray) -> list[float]:
    """(3, 3) rotation -> (w, x, y, z), numerically stable for any rotation."""
    m = np.asarray(R, float)
    tr = np.trace(m)
    cands = [
        (tr, [1 + tr, m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]),
        (m[0, 0], [m[2, 1] - m[1, 2], 1 + m[0, 0] - m[1, 1] - m[2, 2], m[0, 1] + m[1, 0], m[0, 2] + m[2, 0]]),
        (m[1, 1], [m[0, 2] - m[2, 0], m[0, 1] + m[1, 0], 1 - m[0, 0] + m[1, 1] - m[2, 2], m[1, 2] + m[2, 1]]),
        (m[2, 2], [m[1, 0] - m[0, 1], m[0, 2] + m[2, 0], m[1, 2] + m[2, 1], 1 - m[0, 0] - m[1, 1] + m[2, 2]]),
    ]
    q = np.array(max(cands, key=lambda c: c[0])[1])
    q /= np.linalg.norm(q)
    return list(q * np.sign(q[0] if q[0] != 0 else 1))
