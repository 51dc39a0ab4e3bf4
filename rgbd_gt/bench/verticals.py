"""How upright a pose holds a street photo: the photo's near-vertical line segments (poles,
building and vehicle edges) against the vertical of the sweep (the median direction of its
pole-like clusters), as a rotation about the camera's optical axis. A check of a reference
extrinsic from geometry alone: no intensity and no gray level enters it.

    python -m rgbd_gt.bench.verticals [--data ../shared/data] [--cases bench_out/lidar/cases.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from rgbd_gt.camera import Camera


def photo_segments(image: np.ndarray, camera: Camera, min_px: float = 40.0, max_tilt_deg: float = 12.0) -> np.ndarray:
    """(n, 4) x1, y1, x2, y2 of the line segments (LSD) of the undistorted photo that are at least
    `min_px` long and within `max_tilt_deg` of the image's vertical. image: (h, w, 3) BGR uint8."""
    import cv2

    from rgbd_gt.camera import undistort_image

    gray = cv2.cvtColor(undistort_image(camera, image), cv2.COLOR_BGR2GRAY)
    found = cv2.createLineSegmentDetector().detect(gray)[0]
    seg = np.zeros((0, 4)) if found is None else found.reshape(-1, 4).astype(np.float64)
    d = seg[:, 2:] - seg[:, :2]
    tilt = np.degrees(np.arctan2(np.abs(d[:, 0]), np.abs(d[:, 1])))
    return seg[(np.hypot(d[:, 0], d[:, 1]) >= min_px) & (tilt <= max_tilt_deg)]


def sweep_vertical(points: np.ndarray, cell: float = 0.25, min_height: float = 2.0, max_tilt_deg: float = 8.0,
                   reach: float = 40.0) -> tuple[np.ndarray, np.ndarray]:
    """The sweep's vertical (3,), unit, in its own frame: the median of the directions of its
    pole-like clusters (the points of one `cell` x `cell` metre column within `reach` of the
    sensor, spanning at least `min_height` metres, close to a line, within `max_tilt_deg` of z).
    Also returns those directions (k, 3). points: (N, 3) metres."""
    near = points[np.linalg.norm(points[:, :2], axis=1) < reach]
    key = np.unique(np.floor(near[:, :2] / cell).astype(np.int64), axis=0, return_inverse=True)[1].ravel()
    order = np.argsort(key, kind="stable")
    near, key = near[order], key[order]
    starts = np.flatnonzero(np.r_[True, np.diff(key) != 0])
    ends = np.r_[starts[1:], len(key)]
    height = np.maximum.reduceat(near[:, 2], starts) - np.minimum.reduceat(near[:, 2], starts)
    tall = (ends - starts >= 8) & (height >= min_height)
    dirs = []
    for a, b in zip(starts[tall], ends[tall]):  # the tall columns: some hundreds
        q = near[a:b] - near[a:b].mean(axis=0)
        w, V = np.linalg.eigh(q.T @ q)
        d = V[:, -1] * np.sign(V[2, -1])
        if w[1] <= 0.01 * w[2] and d[2] >= np.cos(np.radians(max_tilt_deg)):
            dirs.append(d)
    dirs = np.array(dirs).reshape(-1, 3)
    if not len(dirs):
        return np.array([0.0, 0.0, 1.0]), dirs
    up = np.median(dirs, axis=0)
    return up / np.linalg.norm(up), dirs


def residuals_deg(segments: np.ndarray, K: np.ndarray, R: np.ndarray, up: np.ndarray) -> np.ndarray:
    """(n,) signed angle (degrees) of each segment against the direction, at its midpoint, toward
    the vanishing point K R up of the vertical. R: (3, 3) camera from scan."""
    v = K @ (R @ up)
    mid = (segments[:, :2] + segments[:, 2:]) / 2
    toward = v[None, :2] - mid * v[2]
    d = segments[:, 2:] - segments[:, :2]
    diff = np.degrees(np.arctan2(d[:, 1], d[:, 0]) - np.arctan2(toward[:, 1], toward[:, 0]))
    return (diff + 90) % 180 - 90


def roll_deg(segments: np.ndarray, K: np.ndarray, R: np.ndarray, up: np.ndarray) -> float:
    """The rotation (degrees) about the optical axis, applied after R, that brings the segments'
    median residual (`residuals_deg`) to zero: how far R is rolled from upright."""
    import cv2

    lo, hi = -10.0, 10.0  # the median residual falls as the roll grows
    for _ in range(40):
        mid = (lo + hi) / 2
        Rz = cv2.Rodrigues(np.array([0.0, 0.0, np.radians(mid)]))[0]
        lo, hi = (mid, hi) if np.median(residuals_deg(segments, K, Rz @ R, up)) > 0 else (lo, mid)
    return (lo + hi) / 2


def roll_interval(segments: np.ndarray, K: np.ndarray, R: np.ndarray, up: np.ndarray, boots: int = 400,
                  seed: int = 0) -> tuple[float, float]:
    """95% bootstrap interval (degrees) of `roll_deg` over the segments."""
    rng = np.random.default_rng(seed)
    spread = [roll_deg(segments[rng.integers(0, len(segments), len(segments))], K, R, up) for _ in range(boots)]
    return float(np.percentile(spread, 2.5)), float(np.percentile(spread, 97.5))


def main(argv: list[str] | None = None) -> None:
    import cv2

    from rgbd_gt.io.calib_txt import read_calib_camera, read_calib_pose
    from rgbd_gt.io.pcd import read_pcd

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--cases", type=Path, default=Path("bench_out/lidar/cases.json"),
                    help="benchmarks/lidar.py's results: the roll of its nid results too")
    args = ap.parse_args(argv)
    cases = json.loads(args.cases.read_text()) if args.cases.exists() else []
    print("| scene | segments | sweep's poles; their vertical from z | roll of the reference (95%) | "
          "roll of the nid results: median (range) |")
    print("|---|---|---|---|---|")
    for scene in ("pjlab_1", "pjlab_2", "pjlab_3"):
        folder = args.data / "lidar_camera" / scene
        photo = next(p for p in (folder / "calib.png", folder / "calib.jpg") if p.exists())
        image = cv2.imread(str(photo))
        camera = read_calib_camera(folder / "calib.txt", (image.shape[1], image.shape[0]))
        K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
        segments = photo_segments(image, camera)
        up, dirs = sweep_vertical(read_pcd(folder / "calib.pcd").xyz)
        T = read_calib_pose(folder / "calib.txt")
        roll, (lo, hi) = roll_deg(segments, K, T[:3, :3], up), roll_interval(segments, K, T[:3, :3], up)
        results = [roll_deg(segments, K, np.array(c["T"])[:3, :3], up) for c in cases if c.get("objective") == "nid" and c.get("scenes") == scene]
        tail = f"{np.median(results):+.2f} ({min(results):+.2f} .. {max(results):+.2f}), {len(results)} results" if results else ""
        print(f"| {scene} | {len(segments)} | {len(dirs)}; {np.degrees(np.arccos(up[2])):.2f} deg | "
              f"{roll:+.2f} deg ({lo:+.2f} .. {hi:+.2f}) | {tail} |")


if __name__ == "__main__":
    main()
