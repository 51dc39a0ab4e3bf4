"""Student-t robust weights (Kerl, Sturm, Cremers 2013), as used by the paper."""

from __future__ import annotations

import torch


def _mean(x: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """The mean of x over all of it, or with mask (B, n) for x (B, n, m): per leading index over
    the masked rows, shaped (B, 1, 1)."""
    if mask is None:
        return x.mean()
    m = mask.to(x.dtype)[..., None]
    return ((x * m).sum(dim=(1, 2)) / (m.sum(dim=(1, 2)) * x.shape[2]).clamp_min(1))[:, None, None]


def student_t_weights(r: torch.Tensor, nu: float, sigma2: torch.Tensor | None = None,
                      iterations: int = 5, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights w = (nu + 1) / (nu + r^2 / sigma^2) for residuals r (any shape).

    sigma^2 is re-estimated by the fixed point sigma^2 = mean(w r^2) (starting from `sigma2`,
    or from mean(r^2)); pass iterations=0 to keep a given sigma2. Returns (w, sigma2).
    With mask (B, n) and r (B, n, m) (several poses at once), sigma^2 is per pose (B, 1, 1),
    estimated on its masked rows.
    """
    r2 = r * r
    s2 = _mean(r2, mask).clamp_min(1e-12) if sigma2 is None else sigma2
    for _ in range(iterations):
        w = (nu + 1) / (nu + r2 / s2)
        s2 = _mean(w * r2, mask).clamp_min(1e-12)
    return (nu + 1) / (nu + r2 / s2), s2


def student_t_loss(r: torch.Tensor, nu: float, sigma2: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Mean negative log-likelihood (up to constants) of the residuals: the quantity the
    weighted least squares above minimises locally. With mask (B, n): per pose, (B,)."""
    rho = (nu + 1) / 2 * torch.log1p(r * r / (nu * sigma2))
    return rho.mean() if mask is None else _mean(rho, mask).reshape(-1)
