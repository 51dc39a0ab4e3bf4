"""Depth discontinuities along a sweep's rings (Levinson and Thrun, RSS 2013): a return much
nearer than its neighbour on the ring is the edge of a pole, a car or a trunk against what lies
behind, which a photo shows as an intensity edge. Needs the points in the order the sensor made
them (ring after ring, by azimuth), as KITTI's and Waymo's files and most drivers keep them."""

from __future__ import annotations

import numpy as np

IN_ORDER_SHARE = 0.9  # a sweep is in ring order when this share of consecutive returns are neighbours...
NEIGHBOUR_DEG = 1.0  # ... less than this apart in azimuth
GAP_STEPS = 5.0  # consecutive returns farther apart than this many median azimuth steps are not neighbours


def ring_steps(xyz: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray | None:
    """(N,) float32 metres: how much nearer the sensor each return is than the nearer of its two
    neighbours along its ring (the larger range difference, 0 when it is the farther one), or None
    when the points (N, 3) are not in ring order. origin: the sensor position (3,) in the points'
    frame (default 0), the frame's z its spin axis; a Waymo sweep in the vehicle frame, with the
    sensor 2 m above its origin, keeps its azimuths close enough."""
    d = xyz - (0.0 if origin is None else origin)
    if len(d) < 3:
        return None
    az = np.arctan2(d[:, 1], d[:, 0])
    step = np.abs(np.angle(np.exp(1j * np.diff(az))))  # (N - 1,) wrapped to [0, pi]
    near = step < np.radians(NEIGHBOUR_DEG)
    if near.mean() < IN_ORDER_SHARE:
        return None
    linked = near & (step < GAP_STEPS * np.median(step[near]))
    r = np.linalg.norm(d, axis=1)
    nearer = np.where(linked, r[1:] - r[:-1], 0.0)  # > 0: return i is nearer than return i + 1
    out = np.zeros(len(r))
    out[:-1] = nearer
    out[1:] = np.maximum(out[1:], -nearer)
    return np.clip(out, 0, None).astype(np.float32)
