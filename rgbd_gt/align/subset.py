"""Random keys for scan points that depend on each point alone, not on the points' order.

The aligners work on a random subset of the points in view. Drawn by a seeded permutation of
indices, the subset changes with the order the points come in: the same scan read whole
(`refine`) or block by block (`run`), or saved again in another order, gave poses a millimetre
apart. A key hashed from the point's coordinates picks the same points in any order.
"""

from __future__ import annotations

import numpy as np

_MIX = (np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB))
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _splitmix(x: np.ndarray) -> np.ndarray:
    """SplitMix64's finaliser on uint64 (wrapping arithmetic): every input bit moves every output bit."""
    x = (x ^ (x >> np.uint64(30))) * _MIX[0]
    x = (x ^ (x >> np.uint64(27))) * _MIX[1]
    return x ^ (x >> np.uint64(31))


def point_keys(points: np.ndarray, seed: int) -> np.ndarray:
    """(N, 3) coordinates -> (N,) float64 keys, uniform in (0, 1), each a function of that point's
    coordinates (as float64) and `seed` only. Equal points get equal keys."""
    xyz = np.ascontiguousarray(np.asarray(points, dtype=np.float64) + 0.0)  # + 0.0: -0.0 hashes as 0.0
    bits = xyz.view(np.uint64).reshape(len(xyz), -1)
    with np.errstate(over="ignore"):
        h = np.full(len(xyz), np.uint64(seed) * _GOLDEN + _GOLDEN, dtype=np.uint64)
        for column in bits.T:  # the 3 coordinates, not the points
            h = _splitmix(h ^ column)
    return ((h >> np.uint64(11)).astype(np.float64) + 0.5) / float(1 << 53)
