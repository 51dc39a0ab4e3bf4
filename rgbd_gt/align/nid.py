"""Normalised information distance (NID) between two sets of values, with a gradient.

Where a scan's values (laser intensity, or colors taken at another time or by another sensor)
relate to the photo's gray levels only statistically, no per-point regression predicts one
from the other; their statistical dependence still peaks at the right pose. NID measures it
(Koide et al., direct_visual_lidar_calibration; Pandey et al. use mutual information):

    NID(A, B) = (H(A, B) - I(A; B)) / H(A, B) = 2 - (H(A) + H(B)) / H(A, B)

0 when one determines the other, 1 when they are independent. The entropies come from a joint
histogram in which every sample spreads over 4 x 4 bins with cubic B-spline weights (Parzen
windowing), so that NID is twice differentiable in the sample values.
"""

from __future__ import annotations

import torch


def bspline3_weights(x: torch.Tensor, bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Bin coordinates of values x (n,) in [0, 1] and their cubic B-spline windows.

    A value sits at bin coordinate 1 + x (bins - 3), so that its 4 neighbours floor - 1 ..
    floor + 2 all exist. Returns (first bin (n,) long, weights (n, 4) summing to 1): the uniform
    cubic B-spline's 4 pieces at the fractional part f, which is the kernel sampled at the 4
    neighbours without branches (half the operations, and of its backward)."""
    c = x.clamp(0, 1) * (bins - 3) + 1
    # clamped so that x = 1 (c = bins - 2, on a knot: f = 1) keeps its 4 neighbours inside
    first = c.detach().floor().clamp(max=bins - 3)
    f = c - first
    f2 = f * f
    f3 = f2 * f
    w = torch.stack([(1 - f) ** 3, 3 * f3 - 6 * f2 + 4, 3 * (f + f2 - f3) + 1, f3], dim=1) / 6
    return first.long() - 1, w


def parzen_windows(x: torch.Tensor, bins: int) -> torch.Tensor:
    """(n, bins): each value of x (n,) in [0, 1] spread over its 4 bins (`bspline3_weights`)."""
    first, w = bspline3_weights(x, bins)
    cols = first[:, None] + torch.arange(4, device=x.device)
    return torch.zeros(x.shape[0], bins, dtype=w.dtype, device=x.device).scatter(1, cols, w)


def joint_histogram(a: torch.Tensor, b: torch.Tensor, bins: int) -> torch.Tensor:
    """(bins, bins) joint probability of the values a, b (n,), each in [0, 1]."""
    return windows_histogram(parzen_windows(a, bins), parzen_windows(b, bins))


def windows_histogram(wa: torch.Tensor, wb: torch.Tensor) -> torch.Tensor:
    """(bins, bins) joint probability of paired values given as their windows wa, wb (n, bins)."""
    hist = wa.T @ wb
    return hist / hist.sum().clamp_min(1e-12)


def entropy(p: torch.Tensor) -> torch.Tensor:
    """Shannon entropy (nats) of a probability table."""
    return -(p * torch.log(p.clamp_min(1e-12))).sum()


def nid_of_windows(wa: torch.Tensor, wb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """NID (a scalar in [0, 1]) of paired values given as their windows wa, wb (n, bins)
    (`parzen_windows`; the scan's side can be spread once and reused), and their joint entropy
    H(A, B) in nats (the scale that turns NID into a log-likelihood)."""
    p = windows_histogram(wa, wb)
    h_ab = entropy(p)
    return 2.0 - (entropy(p.sum(1)) + entropy(p.sum(0))) / h_ab.clamp_min(1e-12), h_ab


def nid(a: torch.Tensor, b: torch.Tensor, bins: int = 16) -> torch.Tensor:
    """NID (a scalar in [0, 1]) of paired values a, b (n,) in [0, 1]."""
    return nid_of_windows(parzen_windows(a, bins), parzen_windows(b, bins))[0]
