"""A scan's spatial index: its points grouped into voxel blocks with bounds, so that a photo
touches only the blocks its view can reach (the work then scales with what it sees, not with
the scan)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera

BLOCKS_PER_SIDE = 128  # along the scan's longest side: a room's surfaces make some 10^4-10^5 blocks

VIEW_MARGIN = 0.05  # of the image's extent on every side: what a refined pose (a few degrees off at most) may come to see


@dataclass
class Blocks:
    """Block k holds the points start[k]:start[k + 1] of a block-ordered scan; lo, hi (B, 3)
    float64 are their bounds in metres (the scan's frame)."""

    start: np.ndarray  # (B + 1,) int64
    lo: np.ndarray
    hi: np.ndarray

    def __len__(self) -> int:
        return len(self.lo)


def block_order(xyz: np.ndarray, per_side: int = BLOCKS_PER_SIDE) -> tuple[np.ndarray, Blocks]:
    """(order (N,) int64, blocks): xyz[order] is block-ordered (points keep their order within a
    block, so a grid's rows stay together) and `blocks` indexes it. Cubic blocks of the scan's
    longest side / per_side."""
    if len(xyz) == 0:
        return np.zeros(0, np.int64), Blocks(np.zeros(1, np.int64), np.zeros((0, 3)), np.zeros((0, 3)))
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    edge = max(float((hi - lo).max()) / per_side, 1e-6)
    key = np.zeros(len(xyz), np.int32)  # per_side^3 < 2^31
    for j in range(3):
        key = key * (per_side + 1) + np.minimum((xyz[:, j] - lo[j]) // edge, per_side).astype(np.int32)
    order = np.argsort(key, kind="stable")
    key = key[order]
    start = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    del key
    sorted_xyz = xyz[order]
    blocks = Blocks(np.r_[start, len(xyz)].astype(np.int64), np.minimum.reduceat(sorted_xyz, start),
                    np.maximum.reduceat(sorted_xyz, start))
    return order, blocks


def blocks_in_view(blocks: Blocks, camera: Camera, T_cam_from_scan: np.ndarray, margin: float = VIEW_MARGIN,
                   far: float | None = None) -> np.ndarray:
    """(B,) bool: the blocks whose box may hold a point of `points_in_view`. Conservative: a box
    is left out only when all its corners are beyond one side of that frustum."""
    corners = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(8, 3)
    box = np.where(corners[None] == 0, blocks.lo[:, None], blocks.hi[:, None])  # (B, 8, 3)
    p = box @ T_cam_from_scan[:3, :3].T + T_cam_from_scan[:3, 3]
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    x0, x1, y0, y1 = view_bounds(camera, margin)
    out = (z <= 0).all(1) | (x < x0 * z).all(1) | (x > x1 * z).all(1) | (y < y0 * z).all(1) | (y > y1 * z).all(1)
    if far is not None:
        out |= (z > far).all(1)
    return ~out


def thinning_step(n: int, most: int) -> int:
    """k such that every k-th of n items keeps at most `most` of them (1: all)."""
    return max(1, -(-n // most))


def block_points(blocks: Blocks, selected: np.ndarray, step: int = 1) -> np.ndarray:
    """(n,) int64 indices of the points of the selected blocks ((B,) bool), in block order; every
    `step`-th of them (without making the whole list first: a box around a camera may hold
    tens of millions)."""
    first, count = blocks.start[:-1][selected], np.diff(blocks.start)[selected]
    if count.sum() == 0:
        return np.zeros(0, np.int64)
    # ranges first[k] .. first[k] + count[k] without a loop over blocks
    if step == 1:
        offset = np.repeat(first - np.r_[0, np.cumsum(count)[:-1]], count)
        return np.arange(int(count.sum()), dtype=np.int64) + offset
    end = np.cumsum(count)
    at = np.arange(0, int(end[-1]), step, dtype=np.int64)
    k = np.searchsorted(end, at, side="right")
    return at + (first - (end - count))[k]


def view_bounds(camera: Camera, margin: float = VIEW_MARGIN) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1): the normalised image coordinates (x/z, y/z) the distorted photo spans,
    from its border pixels (barrel distortion reaches beyond the pinhole image), grown by
    `margin` x the span on every side."""
    from rgbd_gt.camera import undistort_points

    w, h = camera.width, camera.height
    t = np.linspace(0, 1, 65)
    border = np.concatenate([np.stack([t * (w - 1), np.zeros_like(t)], 1), np.stack([t * (w - 1), np.full_like(t, h - 1)], 1),
                             np.stack([np.zeros_like(t), t * (h - 1)], 1), np.stack([np.full_like(t, w - 1), t * (h - 1)], 1)])
    xy = undistort_points(camera, border - 0.5 + 1.0 * (border > 0))  # the outer edges of the border pixels
    (x0, y0), (x1, y1) = xy.min(0), xy.max(0)
    mx, my = margin * (x1 - x0), margin * (y1 - y0)
    return x0 - mx, x1 + mx, y0 - my, y1 + my


def points_in_view(xyz: np.ndarray, camera: Camera, T_cam_from_scan: np.ndarray, margin: float = VIEW_MARGIN,
                   far: float | None = None) -> np.ndarray:
    """(N,) bool: the points xyz (N, 3) in front of the camera that project into the photo
    grown by `margin` (`view_bounds`), and nearer than `far` metres."""
    x0, x1, y0, y1 = view_bounds(camera, margin)
    p = xyz @ T_cam_from_scan[:3, :3].T.astype(xyz.dtype) + T_cam_from_scan[:3, 3].astype(xyz.dtype)
    z = p[:, 2]
    ok = (z > 1e-6) & (p[:, 0] >= x0 * z) & (p[:, 0] <= x1 * z) & (p[:, 1] >= y0 * z) & (p[:, 1] <= y1 * z)
    return ok if far is None else ok & (z <= far)


def view_of(scan, camera: Camera, poses: list[np.ndarray], margin: float = VIEW_MARGIN):
    """The `Scan`'s points in view of any of the poses (`points_in_view`): all that a photo's
    renders at those poses can show, so that they cost what the photo sees."""
    keep = np.zeros(len(scan), bool)
    for T in poses:
        keep |= points_in_view(scan.xyz, camera, T, margin)
    return scan.subset(keep)
