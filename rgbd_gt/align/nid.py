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


def _bin_coordinates(x: torch.Tensor, bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(first of the 4 bins (..., n) long, fractional part f (..., n)) of values x (..., n) in [0, 1],
    which sit at bin coordinate 1 + x (bins - 3), so that the 4 neighbours floor - 1 .. floor + 2 exist."""
    c = x.clamp(0, 1) * (bins - 3) + 1
    # clamped so that x = 1 (c = bins - 2, on a knot: f = 1) keeps its 4 neighbours inside
    first = c.detach().floor().clamp(max=bins - 3)
    return first.long() - 1, c - first


def bspline3_weights(x: torch.Tensor, bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Bin coordinates of values x (..., n) in [0, 1] and their cubic B-spline windows: (first bin
    (..., n) long, weights (..., n, 4) summing to 1), the uniform cubic B-spline's 4 pieces at the
    fractional part f, which is the kernel sampled at the 4 neighbours without branches."""
    first, f = _bin_coordinates(x, bins)
    return first, _pieces(f)


def _pieces(f: torch.Tensor) -> torch.Tensor:
    f2 = f * f
    f3 = f2 * f
    return torch.stack([(1 - f) ** 3, 3 * f3 - 6 * f2 + 4, 3 * (f + f2 - f3) + 1, f3], dim=-1) / 6


def _slopes(f: torch.Tensor) -> torch.Tensor:
    """(..., n, 4): d(`_pieces`)/df."""
    f2 = f * f
    return torch.stack([-0.5 * (1 - f) ** 2, 1.5 * f2 - 2 * f, 0.5 + f - 1.5 * f2, 0.5 * f2], dim=-1)


def parzen_windows(x: torch.Tensor, bins: int, use: torch.Tensor | None = None) -> torch.Tensor:
    """(..., n, bins): each value of x (..., n) in [0, 1] spread over its 4 bins (`bspline3_weights`);
    none where use (..., n) (0 or 1) is 0: paired with another set's windows, that sample does not
    count (masked on its 4 weights, not on the other's bins: the same products, a quarter of the work)."""
    first, w = bspline3_weights(x, bins)
    return _spread(first, w if use is None else w * use[..., None], bins)[0]


def _spread(first: torch.Tensor, w: torch.Tensor, bins: int) -> tuple[torch.Tensor, torch.Tensor]:
    """((..., n, bins) windows, (..., n, 4) their columns) of weights w (..., n, 4) from bins first (..., n) on."""
    cols = first[..., None] + torch.arange(4, device=w.device)
    return torch.zeros(w.shape[:-1] + (bins,), dtype=w.dtype, device=w.device).scatter_(-1, cols, w), cols


def joint_histogram(a: torch.Tensor, b: torch.Tensor, bins: int) -> torch.Tensor:
    """(..., bins, bins) joint probability of the values a, b (..., n), each in [0, 1]."""
    return windows_histogram(parzen_windows(a, bins), parzen_windows(b, bins))


def windows_histogram(wa: torch.Tensor, wb: torch.Tensor) -> torch.Tensor:
    """(..., bins, bins) joint probability of paired values given as their windows wa, wb (..., n, bins)."""
    hist = wa.transpose(-1, -2) @ wb
    return hist / hist.sum((-1, -2), keepdim=True).clamp_min(1e-12)


def entropy(p: torch.Tensor, dims: int = 2) -> torch.Tensor:
    """Shannon entropy (nats) of probability tables p (..., table) whose last `dims` dimensions are the table."""
    return -(p * torch.log(p.clamp_min(1e-12))).sum(tuple(range(-dims, 0)))


def nid_of_windows(wa: torch.Tensor, wb: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """NID (...) in [0, 1] of paired values given as their windows wa, wb (..., n, bins)
    (`parzen_windows`; the scan's side can be spread once and reused), and their joint entropy
    H(A, B) in nats (the scale that turns NID into a log-likelihood)."""
    p = windows_histogram(wa, wb)
    h_ab = entropy(p)
    return 2.0 - (entropy(p.sum(-1), 1) + entropy(p.sum(-2), 1)) / h_ab.clamp_min(1e-12), h_ab


def _entropy_slope(p: torch.Tensor) -> torch.Tensor:
    """d(`entropy`)/dp, elementwise."""
    return -(torch.log(p.clamp_min(1e-12)) + (p >= 1e-12).to(p.dtype))


def nid_with_gradient(wa: torch.Tensor, b: torch.Tensor, bins: int,
                      use: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """`nid_of_windows`(wa, parzen_windows(b, bins, use)), d NID / d b and d NID / d use (..., n)
    each, in closed form: the chain through the entropies, the histogram and the B-spline windows
    costs a few small matrix products, where autograd's backward took a third of the aligner's
    time. wa (..., n, bins), b (..., n); a sample whose window wa is zero does not count
    (padding); use (..., n) in [0, 1] weighs each sample (default 1). The weight goes on b's 4
    weights a sample rather than on wa's bins: the same products, a quarter of the work."""
    first, f = _bin_coordinates(b, bins)
    unweighted = _pieces(f)
    pieces = unweighted if use is None else unweighted * use[..., None]
    wb, cols = _spread(first, pieces, bins)
    hist = wa.transpose(-1, -2) @ wb
    total = hist.sum((-1, -2), keepdim=True).clamp_min(1e-12)
    p = hist / total
    pa, pb = p.sum(-1), p.sum(-2)
    h_ab, h_sum = entropy(p), entropy(pa, 1) + entropy(pb, 1)
    h_ab_safe = h_ab.clamp_min(1e-12)[..., None, None]
    # NID = 2 - (H(A) + H(B)) / H(A, B), each entropy a function of p
    d_sum = _entropy_slope(pa)[..., :, None] + _entropy_slope(pb)[..., None, :]
    d_p = h_sum[..., None, None] / h_ab_safe**2 * _entropy_slope(p) - d_sum / h_ab_safe
    d_hist = (d_p - (d_p * p).sum((-1, -2), keepdim=True)) / total  # through the normalisation p = hist / total
    pulls = (wa @ d_hist).gather(-1, cols)  # d NID / d each of a sample's 4 weights in b's windows
    d_f = (pulls * _slopes(f)).sum(-1)
    inside = ((b >= 0) & (b <= 1)).to(d_f.dtype)  # f moves with clamp(b)
    if use is not None:
        inside = inside * use
    return 2.0 - h_sum / h_ab_safe[..., 0, 0], h_ab, d_f * inside * (bins - 3), (pulls * unweighted).sum(-1)


def nid(a: torch.Tensor, b: torch.Tensor, bins: int = 16) -> torch.Tensor:
    """NID (...) in [0, 1] of paired values a, b (..., n) in [0, 1]."""
    return nid_of_windows(parzen_windows(a, bins), parzen_windows(b, bins))[0]
