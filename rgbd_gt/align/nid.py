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


def bspline3(x: torch.Tensor) -> torch.Tensor:
    """The cubic B-spline kernel (support |x| < 2, sums to 1 over integer shifts)."""
    ax = x.abs()
    inner = 2.0 / 3.0 - ax**2 + 0.5 * ax**3
    outer = (2.0 - ax).clamp_min(0) ** 3 / 6.0
    return torch.where(ax < 1, inner, outer)


def joint_histogram(a: torch.Tensor, b: torch.Tensor, bins: int) -> torch.Tensor:
    """(bins, bins) joint probability of the values a, b (n,), each in [0, 1].

    A value v sits at bin coordinate 1 + v (bins - 3), so that its 4 B-spline neighbours
    floor(x) - 1 .. floor(x) + 2 all exist."""
    xa = a.clamp(0, 1) * (bins - 3) + 1
    xb = b.clamp(0, 1) * (bins - 3) + 1
    # clamped so that v = 1 (x = bins - 2, on a knot) keeps its 4 neighbours inside
    ia, ib = (x.detach().floor().long().clamp(max=bins - 3) for x in (xa, xb))
    wa = torch.stack([bspline3(xa - (ia + k)) for k in (-1, 0, 1, 2)])  # (4, n)
    wb = torch.stack([bspline3(xb - (ib + k)) for k in (-1, 0, 1, 2)])
    offsets = torch.arange(-1, 3, device=a.device)
    cell = (ia[None, None] + offsets[:, None, None]) * bins + (ib[None, None] + offsets[None, :, None])  # (4, 4, n)
    weight = wa[:, None] * wb[None, :]
    hist = torch.zeros(bins * bins, dtype=weight.dtype, device=a.device).index_add(0, cell.reshape(-1), weight.reshape(-1))
    return (hist / hist.sum().clamp_min(1e-12)).reshape(bins, bins)


def entropy(p: torch.Tensor) -> torch.Tensor:
    """Shannon entropy (nats) of a probability table."""
    return -(p * torch.log(p.clamp_min(1e-12))).sum()


def nid_and_entropy(a: torch.Tensor, b: torch.Tensor, bins: int = 16) -> tuple[torch.Tensor, torch.Tensor]:
    """NID (a scalar in [0, 1]) of paired values a, b (n,) in [0, 1], and their joint entropy
    H(A, B) in nats (the scale that turns NID into a log-likelihood)."""
    p = joint_histogram(a, b, bins)
    h_ab = entropy(p)
    return 2.0 - (entropy(p.sum(1)) + entropy(p.sum(0))) / h_ab.clamp_min(1e-12), h_ab


def nid(a: torch.Tensor, b: torch.Tensor, bins: int = 16) -> torch.Tensor:
    """NID (a scalar in [0, 1]) of paired values a, b (n,) in [0, 1]."""
    return nid_and_entropy(a, b, bins)[0]
