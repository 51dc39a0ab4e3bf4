"""export-depth measured on ICL-NUIM: frame i's clean-depth cloud, as a grid scan from camera
i, rendered at frame j's true pose against frame j's clean depth, over the pixels both see."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.icl import ICL_CAMERA, depth_points, frame_cloud, read_depth, read_trajectory
from rgbd_gt.scan import Scan
from rgbd_gt.pose import invert, transform_points
from rgbd_gt.render.depth import render_depth


def frame_grid_scan(folder: Path, i: int, kind: str = "clean") -> Scan:
    """Frame i's depth as a structured scan: rows/cols are the pixels, the origin camera i."""
    xyz, rgb, pixel = frame_cloud(folder, i, kind)
    origin = read_trajectory(folder / "trajectory.log")[i][:3, 3]
    return Scan(xyz=xyz, rgb=rgb, row=pixel[:, 1].astype(np.int32), col=pixel[:, 0].astype(np.int32),
                scan_id=np.zeros(len(xyz), np.int32), origins=origin[None])


def seen_by_both(folder: Path, i: int, j: int) -> np.ndarray:
    """(H, W) bool: frame j's pixels whose surface point frame i also sees (its depth agrees)."""
    poses = read_trajectory(folder / "trajectory.log")
    dj, di = read_depth(folder, j, "clean"), read_depth(folder, i, "clean")
    pj, v, u = depth_points(dj)
    c = ICL_CAMERA
    pi = transform_points(invert(poses[i]) @ poses[j], pj)
    ui = np.round(c.fx * pi[:, 0] / pi[:, 2] + c.cx).astype(int)
    vi = np.round(c.fy * pi[:, 1] / pi[:, 2] + c.cy).astype(int)
    ok = (pi[:, 2] > 0) & (ui >= 0) & (vi >= 0) & (ui < c.width) & (vi < c.height)
    agree = np.zeros(len(pj), bool)
    agree[ok] = np.abs(di[vi[ok], ui[ok]] - pi[ok, 2]) < 0.01 + 0.01 * pi[ok, 2]
    out = np.zeros(dj.shape, bool)
    out[v[agree], u[agree]] = True
    return out


def depth_errors(folder: Path, i: int, j: int, grid: bool = True, origin: bool = True) -> dict:
    """Median absolute error (m), fraction off by > 5 cm (leaks) and fraction filled, over the
    pixels both frames see. grid=False: the same points without their grid (as a merged or
    downsampled scan would come), rendered as surfels; origin=False: without the scanner's
    position either (a plain colored PLY from another tool)."""
    scan = frame_grid_scan(folder, i)
    if not grid:
        scan = Scan(xyz=scan.xyz, rgb=scan.rgb, origins=scan.origins if origin else np.zeros((0, 3)))
    T_j = invert(read_trajectory(folder / "trajectory.log")[j])
    rendered = render_depth(scan, ICL_CAMERA, T_j).z
    both = seen_by_both(folder, i, j)
    truth = read_depth(folder, j, "clean")
    filled = both & (rendered > 0)
    err = np.abs(rendered[filled] - truth[filled])
    return {"pair": f"{i}->{j}", "pixels": int(both.sum()), "median_abs_error_m": float(np.median(err)),
            "leak_fraction": float(np.mean(err > 0.05)), "filled_fraction": float(filled.sum() / max(both.sum(), 1))}
