"""Color models: how photo colors map to scan colors (or intensity).

A model lifts photo colors I (N, 3) with a kernel K(I) (N, k) and predicts the scan's
target t (N, m) as K(I) D^T, D (m, k) fitted by least squares on inliers at every iteration
(scanner and camera see color differently). Models:

| name          | kernel K(I)                                  | target        | D      |
| quadratic     | [1, R, G, B, RG, GB, RB, R², G², B²]         | scan RGB      | fitted |
| quadratic_rgb | quadratic + [RGB]                            | scan RGB      | fitted |
| linear        | [1, R, G, B]                                 | scan RGB      | fitted |
| none          | [R, G, B]                                    | scan RGB      | I      |
| gray          | [Y]                                          | scan gray     | 1      |
| gray_affine   | [1, Y] (Engel et al.'s affine brightness)    | scan gray     | fitted |

For a scan with intensity and no color, the target is the intensity (m = 1).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from rgbd_gt.align.config import MODELS
from rgbd_gt.scan import LUMA



@dataclass(frozen=True)
class ColorModel:
    name: str

    def __post_init__(self):
        if self.name not in MODELS:
            raise ValueError(f"unknown color model {self.name!r} (choose from {', '.join(MODELS)})")

    @property
    def fitted(self) -> bool:
        return self.name not in ("none", "gray")

    @property
    def gray_target(self) -> bool:
        return self.name in ("gray", "gray_affine")

    def target(self, colors: torch.Tensor) -> torch.Tensor:
        """Scan colors (N, 3) in [0, 1], or intensity (N, 1) -> the target (N, m)."""
        if colors.shape[1] == 3 and self.gray_target:
            return colors @ colors.new_tensor(LUMA).unsqueeze(1)
        return colors

    def kernel(self, I: torch.Tensor) -> torch.Tensor:
        """Photo colors I (N, 3) -> K(I) (N, k)."""
        R, G, B = I[:, 0:1], I[:, 1:2], I[:, 2:3]
        one = torch.ones_like(R)
        if self.name in ("gray", "gray_affine"):
            Y = I @ I.new_tensor(LUMA).unsqueeze(1)
            return Y if self.name == "gray" else torch.cat([one, Y], 1)
        if self.name == "none":
            return I
        if self.name == "linear":
            return torch.cat([one, I], 1)
        K = [one, R, G, B, R * G, G * B, R * B, R * R, G * G, B * B]
        if self.name == "quadratic_rgb":
            K.append(R * G * B)
        return torch.cat(K, 1)

    def kernel_derivative(self, I: torch.Tensor, dI: torch.Tensor) -> torch.Tensor:
        """Directional derivative dK/dI . dI (N, k) of the kernel at I (N, 3) along dI (N, 3),
        e.g. the image gradient along u: how K(I) changes as the point moves one pixel."""
        R, G, B = I[:, 0:1], I[:, 1:2], I[:, 2:3]
        dR, dG, dB = dI[:, 0:1], dI[:, 1:2], dI[:, 2:3]
        zero = torch.zeros_like(R)
        if self.name in ("gray", "gray_affine"):
            dY = dI @ I.new_tensor(LUMA).unsqueeze(1)
            return dY if self.name == "gray" else torch.cat([zero, dY], 1)
        if self.name == "none":
            return dI
        if self.name == "linear":
            return torch.cat([zero, dI], 1)
        d = [zero, dR, dG, dB, dR * G + R * dG, dG * B + G * dB, dR * B + R * dB, 2 * R * dR, 2 * G * dG, 2 * B * dB]
        if self.name == "quadratic_rgb":
            d.append(dR * G * B + R * dG * B + R * G * dB)
        return torch.cat(d, 1)

    def identity(self, k: int, m: int, like: torch.Tensor) -> torch.Tensor:
        """D of the models that fit nothing: 'none' (I) and 'gray' (1)."""
        return torch.eye(m, k, dtype=like.dtype, device=like.device)


def unclipped(I: torch.Tensor, levels: int = 255) -> torch.Tensor:
    """(N,) mask of photo colors I (N, 3) in [0, 1] with no channel clipped at black or white.

    A clipped channel reads the same for a range of scene colors, so no color transform maps it
    to the scan's color: such samples are left out of the fit (they still count in the loss,
    where the Student-t weights handle them). A sample is clipped when it is within half a
    quantisation step (1 / (2 levels)) of 0 or 1, i.e. all its bilinear neighbours are.
    """
    half = 0.5 / levels
    return ((I > half) & (I < 1 - half)).all(dim=1)


def fit_transform(K: torch.Tensor, target: torch.Tensor, weights: torch.Tensor | None = None,
                  ridge: float = 1e-10) -> torch.Tensor:
    """Least-squares D (m, k) minimising sum_i w_i |D K_i - t_i|^2 (`fit_transforms` for one pose)."""
    w = torch.ones(K.shape[0], dtype=K.dtype, device=K.device) if weights is None else weights
    return fit_transforms(K[None], target, w[None], ridge)[0]


def fit_with_inliers(K: torch.Tensor, target: torch.Tensor, beta_max: float, rounds: int = 3,
                     min_fraction: float = 0.2, D0: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Alternate D and inliers (|D K - t| < beta_max), starting from all points, or from the
    inliers of a previous D0 (then one round: the aligner re-fits at every iteration anyway).

    When fewer than `min_fraction` of the points would be inliers (far from alignment), the
    best `min_fraction` by residual are used, so the fit never collapses. Returns (D, inlier mask).
    (`fit_many_with_inliers` for one pose.)
    """
    mask = torch.ones(1, K.shape[0], dtype=torch.bool, device=K.device)
    D, inliers = fit_many_with_inliers(K[None], target, mask, beta_max, rounds, min_fraction,
                                       None if D0 is None else D0[None])
    return D[0], inliers[0]


def fit_transforms(K: torch.Tensor, target: torch.Tensor, weights: torch.Tensor, ridge: float = 1e-10) -> torch.Tensor:
    """Least-squares D (B, m, k) minimising sum_i w_bi |D_b K_bi - t_i|^2 for several poses at once:
    K (B, n, k) the kernels of each pose's samples, target (n, m) the points' targets, weights
    (B, n) (a bool mask: the rows each fit uses).

    A tiny ridge keeps the solve well posed when a kernel column is constant (a gray photo).
    Solved in float64: the quadratic kernel's normal matrix is badly conditioned.
    """
    Kd = K.double()
    Kw = (Kd * weights.double()[..., None]).transpose(1, 2)
    A, b = Kw @ Kd, Kw @ target.double()
    scale = A.diagonal(dim1=1, dim2=2).mean(1).clamp_min(1e-12)[:, None, None]
    A = A + ridge * scale * torch.eye(A.shape[1], dtype=A.dtype, device=A.device)
    return torch.linalg.solve(A, b).transpose(1, 2).to(K.dtype)


def fit_many_with_inliers(K: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, beta_max: float, rounds: int = 3,
                          min_fraction: float = 0.2, D0: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """`fit_with_inliers` for several poses at once (K (B, n, k), target (n, m), mask (B, n) of
    the rows each may use, D0 (B, m, k)); the rounds stop when no pose's inliers change.
    Returns (D (B, m, k), inliers (B, n))."""
    inliers = mask.clone()
    D = fit_transforms(K, target, mask) if D0 is None else D0
    count = mask.sum(1)
    for _ in range(rounds if D0 is None else 1):
        err = (K @ D.transpose(1, 2) - target).norm(dim=2)
        new = mask & (err < beta_max)
        few = new.sum(1) < min_fraction * count
        if few.any():  # far from alignment: the best min_fraction of that pose's rows
            ranked = torch.where(mask, err, torch.full_like(err, float("inf"))).sort(dim=1).values
            k = (min_fraction * count).long().clamp_min(1) - 1
            kth = ranked.gather(1, k[:, None])
            new = torch.where(few[:, None], mask & (err <= kth), new)
        if torch.equal(new, inliers):
            break
        inliers = new
        D = fit_transforms(K, target, inliers)
    return D, inliers
