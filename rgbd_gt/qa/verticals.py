"""Whether a pose holds the photo upright: the photo's near-vertical line segments (poles,
building, door and vehicle edges) against the scan's own vertical (the median direction of its
pole-like columns of points), as a rotation about the camera's optical axis. Geometry alone: no
color, intensity or gray level enters it, so it checks LiDAR sweeps, which the edge scores
cannot (they are too sparse to draw). Measured on the PJLab scenes: docs/lidar-method.md."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.pose import camera_centre, so3_exp
from rgbd_gt.render.blocks import thinning_step

MIN_SEGMENTS, MIN_POLES = 8, 10  # fewer say nothing: the interval of a few segments' median is degrees wide
# the column grid is laid at these fractions of a cell (along its diagonal) and the rolls averaged:
# on one grid, which columns a pole splits into moved the PJLab rolls by up to 0.3 deg
GRID_OFFSETS = (0.0, 0.25, 0.5, 0.75)
# added to both ends of the bootstrap interval: on synthetic scenes with exact truth the
# bootstrap alone missed 0 in 5 of 31 cases, by at most 0.06 deg (LSD's angles on rendered
# edges; the roll's linearisation away from the principal point). `python -m benchmarks.verticals`
SYSTEMATIC_DEG = 0.1
REACH = 40.0  # metres around the camera that the scan's poles are taken from
# of those, every k-th beyond this: on a 40.8M-point scan (docs/scale.md) 500k give the rolls of
# 2M to the hundredth of a degree at a fifth of the time (0.4 s a pose)
MAX_POINTS = 500_000


@dataclass
class VerticalsScore:
    """roll: the rotation (degrees) about the optical axis, after the pose, that would stand the
    photo's vertical lines along the scan's vertical (0: upright); low, high: its 95% bootstrap
    interval over the segments and the poles, widened by SYSTEMATIC_DEG; segments, poles: how
    many entered (poles: on the first grid). usable is False with fewer than MIN_SEGMENTS
    segments or MIN_POLES poles (roll and interval nan)."""

    roll: float
    low: float
    high: float
    segments: int
    poles: int
    usable: bool = True

    def summary(self) -> str:
        if not self.usable:
            return f"says nothing ({self.segments} vertical lines in the photo, {self.poles} poles in the scan)"
        return (f"roll {self.roll:+.2f} deg (95% {self.low:+.2f} .. {self.high:+.2f}) off the scan's vertical, "
                f"{self.segments} lines, {self.poles} poles")

    def as_dict(self, prefix: str = "") -> dict:
        """Plain values for JSON and pose files: the roll and its interval None when it says nothing."""
        roll, low, high = (self.roll, self.low, self.high) if self.usable else (None, None, None)
        return {f"{prefix}verticals_roll_deg": roll, f"{prefix}verticals_roll_low_deg": low,
                f"{prefix}verticals_roll_high_deg": high, f"{prefix}verticals_segments": self.segments,
                f"{prefix}verticals_poles": self.poles, f"{prefix}verticals_usable": self.usable}


def photo_segments(image: np.ndarray, camera: Camera, min_px: float = 40.0, max_tilt_deg: float = 12.0,
                   max_side: int = 1920) -> np.ndarray:
    """(n, 4) x1, y1, x2, y2 (the photo's pixels, lens distortion removed) of the line segments
    (OpenCV's LSD) that are at least `min_px` long and within `max_tilt_deg` of the image's
    vertical, found on the undistorted photo scaled to at most `max_side` pixels (a 24 MP photo
    costs what a 2 MP one does). image: (h, w, 3) RGB uint8 of the camera's size."""
    import cv2

    from rgbd_gt.camera import rescale, undistort_image

    s = min(1.0, max_side / max(camera.width, camera.height))
    size = (max(1, round(camera.width * s)), max(1, round(camera.height * s)))
    small = image if s == 1.0 else cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    gray = cv2.cvtColor(undistort_image(rescale(camera, *size), small), cv2.COLOR_RGB2GRAY)
    found = cv2.createLineSegmentDetector().detect(gray)[0]
    seg = np.zeros((0, 4)) if found is None else found.reshape(-1, 4).astype(np.float64)
    d = seg[:, 2:] - seg[:, :2]
    tilt = np.degrees(np.arctan2(np.abs(d[:, 0]), np.abs(d[:, 1])))
    seg = seg[(np.hypot(d[:, 0], d[:, 1]) >= min_px) & (tilt <= max_tilt_deg)]
    scale = np.tile([camera.width / size[0], camera.height / size[1]], 2)
    return (seg + 0.5) * scale - 0.5


def scan_vertical(points: np.ndarray, centre: np.ndarray, cell: float = 0.25, min_height: float = 2.0,
                  max_tilt_deg: float = 8.0, reach: float = REACH, offset: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """The scan's vertical (3,), unit, in its own frame (z roughly up, as scanners and vehicles
    hold it): the median of the directions of its pole-like columns (the points of one `cell` x
    `cell` metre column within `reach` metres of `centre` (3,) horizontally, spanning at least
    `min_height` metres, close to a line, within `max_tilt_deg` of z; the grid shifted by `offset`
    cells along x and y). Also returns those directions (k, 3); none: (0, 0, 1). points: (N, 3) metres."""
    near = points[np.linalg.norm(points[:, :2] - centre[:2], axis=1) < reach].astype(np.float64)
    up, none = np.array([0.0, 0.0, 1.0]), np.zeros((0, 3))
    if not len(near):
        return up, none
    # cells on the scan's own grid, not one anchored at `centre`: where the camera stands does
    # not decide which columns a pole splits into
    ij = np.floor(near[:, :2] / cell + offset).astype(np.int64)
    ij -= ij.min(axis=0)
    key = ij[:, 0] * (ij[:, 1].max() + 1) + ij[:, 1]
    order = np.argsort(key, kind="stable")
    near, key = near[order], key[order]
    starts = np.flatnonzero(np.r_[True, np.diff(key) != 0])
    counts = np.diff(np.r_[starts, len(key)])
    height = np.maximum.reduceat(near[:, 2], starts) - np.minimum.reduceat(near[:, 2], starts)
    tall = (counts >= 8) & (height >= min_height)
    if not tall.any():
        return up, none
    # every tall column's scatter matrix at once (a wall or a dense scan has thousands of them)
    n = counts[tall]
    first = np.r_[0, np.cumsum(n)[:-1]]
    q = near[np.repeat(tall, counts)]
    q -= np.repeat(q[first], n, axis=0)  # about each column's first point: no cancellation far from 0
    i, j = np.triu_indices(3)
    sums = np.add.reduceat(q, first, axis=0)
    prods = np.add.reduceat(q[:, i] * q[:, j], first, axis=0)
    scatter = np.zeros((len(n), 3, 3))
    scatter[:, i, j] = prods - sums[:, i] * sums[:, j] / n[:, None]
    scatter[:, j, i] = scatter[:, i, j]
    w, V = np.linalg.eigh(scatter)
    d = V[:, :, -1] * np.sign(V[:, 2:3, -1])
    dirs = d[(w[:, 1] <= 0.01 * w[:, 2]) & (d[:, 2] >= np.cos(np.radians(max_tilt_deg)))]
    if not len(dirs):
        return up, none
    up = np.median(dirs, axis=0)
    return up / np.linalg.norm(up), dirs


def residuals_deg(segments: np.ndarray, K: np.ndarray, R: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(n,) signed angle (degrees) of each segment against the direction, at its midpoint, toward
    the vanishing point K R up of the vertical; for b verticals `up` (b, 3): (b, n). R: (3, 3)
    camera from scan."""
    v = np.atleast_2d(up) @ (K @ R).T  # (b, 3)
    mid = (segments[:, :2] + segments[:, 2:]) / 2
    toward = v[:, None, :2] - mid[None] * v[:, None, 2:]
    d = segments[:, 2:] - segments[:, :2]
    diff = np.degrees(np.arctan2(d[:, 1], d[:, 0]) - np.arctan2(toward[..., 1], toward[..., 0]))
    res = (diff + 90) % 180 - 90
    return res if np.ndim(up) == 2 else res[0]


def _rolled(R: np.ndarray, deg: float) -> np.ndarray:
    """R (3, 3) followed by a rotation of `deg` degrees about the camera's optical axis."""
    return so3_exp(np.array([0.0, 0.0, np.radians(deg)])) @ R


def roll_deg(segments: np.ndarray, K: np.ndarray, R: np.ndarray, up: np.ndarray) -> float:
    """The rotation (degrees) about the optical axis, applied after R, that brings the segments'
    median residual (`residuals_deg`) to zero: how far R is rolled off the scan's vertical."""
    lo, hi = -10.0, 10.0  # the median residual falls as the roll grows
    for _ in range(40):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if np.median(residuals_deg(segments, K, _rolled(R, mid), up)) > 0 else (lo, mid)
    return (lo + hi) / 2


def roll_interval(segments: np.ndarray, K: np.ndarray, R: np.ndarray, poles: list[np.ndarray], rolls: list[float],
                  boots: int = 400, seed: int = 0) -> tuple[float, float]:
    """95% bootstrap interval (degrees) of the mean of `rolls`, each the `roll_deg` against the
    median of one grid's pole directions (k, 3) in `poles` (`scan_vertical`), resampling both the
    segments and the poles: the vertical is a measurement too. Each residual falls by the roll
    added (exactly at the principal point, nearly elsewhere), so a resample's roll is the roll
    plus the median of its residuals there: all resamples in one array operation per grid."""
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, len(segments), (boots, len(segments)))
    spread = np.zeros(boots)
    for dirs, roll in zip(poles, rolls):
        ups = np.median(dirs[rng.integers(0, len(dirs), (boots, len(dirs)))], axis=1)
        at = residuals_deg(segments, K, _rolled(R, roll), ups / np.linalg.norm(ups, axis=1, keepdims=True))
        spread += roll + np.median(np.take_along_axis(at, pick, axis=1), axis=1)
    spread /= len(poles)
    return float(np.percentile(spread, 2.5)), float(np.percentile(spread, 97.5))


def verticals_qa(points: np.ndarray, photo: np.ndarray, camera: Camera, poses: list[np.ndarray],
                 boots: int = 200) -> list[VerticalsScore]:
    """How far each of `poses` (4, 4, camera from scan) is rolled off the scan's vertical, by the
    photo's (H, W, 3 RGB uint8) vertical lines and the scan's points (N, 3) around the cameras,
    behind them too, not only in view (a view holds too few poles: PJLab 8-24 against 170-250
    within REACH). Both are found once, the vertical near the first pose's camera (averaged over
    GRID_OFFSETS), so that the poses of one photo (an init and its refinement) are measured
    against the same one. A photo taken rolled by more than about 10 deg has no lines within the
    tilt limit: it says nothing."""
    seg = photo_segments(photo, camera)
    centre = camera_centre(np.asarray(poses[0], np.float64))
    around = points[np.linalg.norm(points[:, :2] - centre[:2], axis=1) < REACH]
    around = around[:: thinning_step(len(around), MAX_POINTS)]
    found = [scan_vertical(around, centre, offset=o) for o in GRID_OFFSETS]
    poles = [dirs for _, dirs in found]
    if len(seg) < MIN_SEGMENTS or min(map(len, poles)) < MIN_POLES:
        return [VerticalsScore(float("nan"), float("nan"), float("nan"), len(seg), len(poles[0]), usable=False) for _ in poses]
    scores = []
    for T in poses:
        R = np.asarray(T, np.float64)[:3, :3]
        rolls = [roll_deg(seg, camera.K, R, up) for up, _ in found]
        low, high = roll_interval(seg, camera.K, R, poles, rolls, boots)
        scores.append(VerticalsScore(float(np.mean(rolls)), low - SYSTEMATIC_DEG, high + SYSTEMATIC_DEG, len(seg), len(poles[0])))
    return scores
