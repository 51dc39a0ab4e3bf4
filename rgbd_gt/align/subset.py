"""Random keys for scan points that depend on each point alone, not on the points' order.

The aligners work on a random subset of the points in view. Drawn by a seeded permutation of
indices, the subset changes with the order the points come in: the same scan read whole
(`refine`) or block by block (`run`), or saved again in another order, gave poses a millimetre
apart. A key hashed from the point's coordinates picks the same points in any order.

And which points an aligner considers at all: those near the view of its initial pose.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

_MIX = (np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB))
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_SHIFTS = (np.uint64(30), np.uint64(27), np.uint64(31))


def _splitmix(x: np.ndarray, tmp: np.ndarray) -> None:
    """SplitMix64's finaliser on uint64, in place (wrapping arithmetic; tmp: scratch of x's shape):
    every input bit moves every output bit."""
    for shift, mix in ((_SHIFTS[0], _MIX[0]), (_SHIFTS[1], _MIX[1])):
        np.right_shift(x, shift, out=tmp)
        x ^= tmp
        x *= mix
    np.right_shift(x, _SHIFTS[2], out=tmp)
    x ^= tmp


def point_keys(points: np.ndarray, seed: int) -> np.ndarray:
    """(N, 3) coordinates -> (N,) float64 keys, uniform in (0, 1), each a function of that point's
    coordinates (as float64) and `seed` only. Equal points get equal keys. In place, without
    temporaries per step: it runs on every point of a photo's view (0.5 s for 7 million)."""
    bits = (np.asarray(points, dtype=np.float64) + 0.0).view(np.uint64)  # + 0.0: -0.0 hashes as 0.0
    with np.errstate(over="ignore"):
        h = np.full(len(bits), np.uint64(seed) * _GOLDEN + _GOLDEN, dtype=np.uint64)
        tmp = np.empty_like(h)
        for j in range(bits.shape[1]):  # the 3 coordinates, not the points
            h ^= bits[:, j]
            _splitmix(h, tmp)
    keys = (h >> np.uint64(11)).astype(np.float64)
    keys += 0.5
    keys /= float(1 << 53)
    return keys


ALIGN_MARGIN = 0.15  # of the photo's width and height on every side: a pose moves a few degrees


def near_view(uv: torch.Tensor, z: torch.Tensor, size: tuple[int, int], near: float, far: float = 0.0) -> torch.Tensor:
    """(N,) bool: the points at pixels uv (N, 2) and depths z (N,) metres that an aligner
    considers: within ALIGN_MARGIN of the photo of size (W, H), deeper than `near` and, when
    far > 0, shallower than `far`."""
    w, h = size
    mu, mv = ALIGN_MARGIN * w, ALIGN_MARGIN * h
    keep = (z > near) & (uv[:, 0] > -mu) & (uv[:, 1] > -mv) & (uv[:, 0] < w + mu) & (uv[:, 1] < h + mv)
    return keep & (z < far) if far > 0 else keep
