"""Student-t robust weights (Kerl, Sturm, Cremers 2013), as used by the paper."""

from __future__ import annotations

import torch


def student_t_weights(r: torch.Tensor, nu: float, sigma2: torch.Tensor | None = None,
                      iterations: int = 5) -> tuple[torch.Tensor, torch.Tensor]:
    """Weights w = (nu + 1) / (nu + r^2 / sigma^2) for residuals r (any shape).

    sigma^2 is re-estimated by the fixed point sigma^2 = mean(w r^2) (starting from `sigma2`,
    or from mean(r^2)); pass iterations=0 to keep a given sigma2. Returns (w, sigma2).
    """
    r2 = r * r
    s2 = r2.mean().clamp_min(1e-12) if sigma2 is None else sigma2
    for _ in range(iterations):
        w = (nu + 1) / (nu + r2 / s2)
        s2 = (w * r2).mean().clamp_min(1e-12)
    return (nu + 1) / (nu + r2 / s2), s2


def student_t_loss(r: torch.Tensor, nu: float, sigma2: torch.Tensor) -> torch.Tensor:
    """Mean negative log-likelihood (up to constants) of the residuals: the quantity the
    weighted least squares above minimises locally."""
    return ((nu + 1) / 2 * torch.log1p(r * r / (nu * sigma2))).mean()
