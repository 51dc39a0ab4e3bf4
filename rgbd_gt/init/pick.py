"""What `rgbd-gt pick` shows and computes: the scan as an image to click on (each pixel knows its
scan point), and the live pose from the pairs picked so far.

The scan image is the structured grid itself for scans with row/col (a panorama: one pixel per
laser shot, so a click lands on a real point), otherwise a panorama rendered from the scan
origin, or a view rendered at an initial pose with the photo's camera (closest to the photo).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera, rescale
from rgbd_gt.errors import InputError
from rgbd_gt.scan import Scan, scan_colors

VIEW_SIDE = 4096  # the scan image's longer side at most (pixels): what a browser shows smoothly
DOT_PX = 2  # a sweep's points in the pose view: squares of 5 x 5 pixels, easy to hit, rarely overlapping
NOTHING_IN_VIEW = "no scan surface in view of the initial pose: pick on a panorama instead (--view panorama)"


@dataclass
class ClickView:
    """image: (h, w, 3) uint8 to show; xyz: (h, w, 3) float32 scan point per pixel, NaN where none."""

    image: np.ndarray
    xyz: np.ndarray
    kind: str

    def point_at(self, x: float, y: float, reach: int = 3) -> np.ndarray | None:
        """The scan point (3,) under image pixel (x, y), or at the nearest pixel within `reach`
        that has one; None when there is none."""
        h, w = self.xyz.shape[:2]
        xi, yi = int(np.floor(x)), int(np.floor(y))
        y0, y1, x0, x1 = max(yi - reach, 0), min(yi + reach + 1, h), max(xi - reach, 0), min(xi + reach + 1, w)
        if y0 >= y1 or x0 >= x1:
            return None
        patch = self.xyz[y0:y1, x0:x1]
        ok = np.isfinite(patch[..., 0])
        if not ok.any():
            return None
        vy, vx = np.nonzero(ok)
        k = int(np.argmin((vy + y0 - yi) ** 2 + (vx + x0 - xi) ** 2))
        return patch[vy[k], vx[k]].astype(np.float64)


    def pixel_of(self, xyz, within: float = 0.05) -> tuple[float, float] | None:
        """The centre (x, y) of the image pixel whose scan point is nearest to xyz (3,), if within
        `within` metres: where a pair loaded from a file is drawn."""
        ok = np.isfinite(self.xyz[..., 0])
        d = np.linalg.norm(self.xyz[ok] - np.asarray(xyz, np.float32), axis=1)
        if d.size == 0 or d.min() > within:
            return None
        y, x = np.argwhere(ok)[int(np.argmin(d))]
        return float(x) + 0.5, float(y) + 0.5


def _gray_to_rgb(colors: np.ndarray) -> np.ndarray:
    c = colors.astype(np.float32)
    return np.repeat(c * 255, 3, axis=1) if c.shape[1] == 1 else c


def grid_panorama(scan: Scan, longest: int = VIEW_SIDE) -> ClickView:
    """The first scan's row/col grid as an image (every k-th row and column when larger than
    `longest`), brightness-stretched so that dark scans can be read."""
    sid = scan.scan_id if scan.scan_id is not None else np.zeros(len(scan), np.int32)
    sel = np.nonzero(sid == sid.min())[0]
    row, col = scan.row[sel].astype(np.int64), scan.col[sel].astype(np.int64)
    r0, c0 = row.min(), col.min()
    rows, cols = row.max() - r0 + 1, col.max() - c0 + 1
    step = max(1, int(np.ceil(max(rows, cols) / longest)))
    keep = ((row - r0) % step == 0) & ((col - c0) % step == 0)
    sel, row, col = sel[keep], (row[keep] - r0) // step, (col[keep] - c0) // step
    h, w = int(row.max()) + 1, int(col.max()) + 1
    # shown as seen from the scanner, z up: azimuth falling to the right, elevation rising upward
    up, left = _grid_directions(scan.xyz[sel], row, col, scan.origins[0] if len(scan.origins) else scan.xyz[sel].mean(0))
    row = row if not up else h - 1 - row
    col = col if not left else w - 1 - col
    image = np.zeros((h, w, 3), np.uint8)
    xyz = np.full((h, w, 3), np.nan, np.float32)
    image[row, col] = _stretch(_gray_to_rgb(scan_colors(scan)[sel]))
    xyz[row, col] = scan.xyz[sel]
    return ClickView(image, xyz, f"the scan's grid ({rows} x {cols} shots" + (f", every {step}th" if step > 1 else "") + ")")


def _grid_directions(xyz: np.ndarray, row: np.ndarray, col: np.ndarray, origin: np.ndarray,
                     pairs: int = 1 << 20) -> tuple[bool, bool]:
    """(rows go up, columns go left) as seen from the origin with z up, from grid neighbours:
    the elevation change along rows and the turn (about z) along columns, by majority (over
    about `pairs` neighbour pairs of evenly spaced rows and columns)."""
    index = np.full((int(row.max()) + 1, int(col.max()) + 1), -1, np.int64)
    index[row, col] = np.arange(len(row))
    d = xyz - origin
    step = max(1, index.size // pairs)
    rows = index[::step]  # neighbours along a row: the turn about z
    a, b = rows[:, :-1].ravel(), rows[:, 1:].ravel()
    ok = (a >= 0) & (b >= 0)
    a, b = d[a[ok]], d[b[ok]]
    turn = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]  # > 0: turning counter-clockwise, to the left
    cols = index[:, ::step]  # neighbours along a column: the change of elevation
    a, b = cols[:-1].ravel(), cols[1:].ravel()
    ok = (a >= 0) & (b >= 0)

    def elevation(p):
        return p[:, 2] / np.maximum(np.linalg.norm(p, axis=1), 1e-12)

    rise = elevation(d[b[ok]]) - elevation(d[a[ok]])
    return bool(np.median(rise) > 0) if rise.size else False, bool(np.median(turn) > 0) if turn.size else False


def origin_panorama(scan: Scan, width: int = VIEW_SIDE) -> ClickView:
    """An equirectangular panorama of the scan from its first origin (azimuth across, elevation
    down, z up), the nearest point per pixel."""
    import torch

    from rgbd_gt.render.splat import splat

    d = scan.xyz - scan.origins[0]
    rng = np.linalg.norm(d, axis=1)
    az = np.arctan2(d[:, 1], d[:, 0])
    el = np.arcsin(np.clip(d[:, 2] / np.maximum(rng, 1e-9), -1, 1))
    lo, hi = np.percentile(el, [0.1, 99.9])
    height = int(np.clip(width * (hi - lo) / (2 * np.pi), 64, width))
    uv = np.stack([(np.pi - az) / (2 * np.pi) * (width - 1), (hi - el) / max(hi - lo, 1e-6) * (height - 1)], 1)
    values = np.concatenate([_gray_to_rgb(scan_colors(scan)), scan.xyz], 1)
    img, _, index = splat(torch.as_tensor(uv), torch.as_tensor(rng), torch.as_tensor(values), (width, height), 1)
    img = img.numpy()
    have = index.numpy() >= 0
    xyz = np.where(have[..., None], img[..., 3:], np.nan).astype(np.float32)
    image = np.zeros((height, width, 3), np.uint8)
    image[have] = _stretch(img[..., :3][have])
    return ClickView(image, xyz, "a panorama from the scan origin")


def pose_view(scan: Scan, camera: Camera, T: np.ndarray, longest: int = VIEW_SIDE) -> ClickView:
    """The scan seen with the photo's camera at pose T (scaled to at most `longest`): rendered
    surfaces, or for a sweep (`render.points.is_sweep`: its rings leave gaps that surfaces fill
    with blobs) the visible points themselves as dots (`points_view`), so that a click lands on
    a laser return."""
    from rgbd_gt.render.blocks import view_of
    from rgbd_gt.render.depth import render_depth
    from rgbd_gt.render.points import is_sweep

    s = min(1.0, longest / max(camera.size))
    cam = rescale(camera, max(1, round(camera.width * s)), max(1, round(camera.height * s)))
    scan = view_of(scan, cam, [T])  # a render costs what the photo sees
    if is_sweep(scan):
        return points_view(scan, cam, T)
    values = np.concatenate([_gray_to_rgb(scan_colors(scan)), scan.xyz], 1)
    depth = render_depth(scan, cam, T, values=values, normals=False)
    have = depth.z > 0
    if not have.any():
        raise InputError(NOTHING_IN_VIEW)
    image = np.zeros(depth.z.shape + (3,), np.uint8)
    image[have] = _stretch(depth.colors[..., :3][have])
    xyz = np.where(have[..., None], depth.colors[..., 3:], np.nan).astype(np.float32)
    return ClickView(image, xyz, "the scan rendered at the initial pose")


def points_view(scan: Scan, camera: Camera, T: np.ndarray, dot_px: int = DOT_PX) -> ClickView:
    """The points the camera sees at T (the aligner's visibility), each a square of side
    2 dot_px + 1 in its intensity's (or color's) `point_colors`, on black; the nearest point wins
    where squares overlap."""
    from rgbd_gt.qa.overlay import point_colors
    from rgbd_gt.render.points import dot_pixels, seen_points

    idx, uv, z = seen_points(scan, camera, T)
    if len(idx) == 0:
        raise InputError(NOTHING_IN_VIEW)
    key, owner = dot_pixels(uv, z, camera.size, dot_px)
    w, h = camera.size
    image = np.zeros((h * w, 3), np.uint8)
    xyz = np.full((h * w, 3), np.nan, np.float32)
    image[key] = point_colors(scan, idx)[owner]
    xyz[key] = scan.xyz[idx[owner]]
    return ClickView(image.reshape(h, w, 3), xyz.reshape(h, w, 3), "the scan's points seen from the initial pose")


def _stretch(rgb: np.ndarray) -> np.ndarray:
    """(n, 3) colors 0..255 (float) -> uint8 stretched between their 1st and 99th percentiles."""
    lo, hi = np.percentile(rgb, [1, 99]) if len(rgb) else (0, 255)
    return np.clip((rgb - lo) / max(hi - lo, 1e-6) * 255, 0, 255).astype(np.uint8)


def click_view(scan: Scan, view: str, camera: Camera | None = None, T_init: np.ndarray | None = None) -> ClickView:
    """view: auto (the pose view with an init, else the grid, else a panorama from the origin),
    grid, panorama or pose."""
    if view == "auto":
        view = "pose" if T_init is not None and camera is not None else "grid" if scan.has_grid else "panorama"
    if view == "pose":
        if T_init is None or camera is None:
            raise InputError("--view pose needs --init and --camera")
        return pose_view(scan, camera, T_init)
    if view == "grid":
        if not scan.has_grid:
            raise InputError("--view grid: the scan has no row/column grid (try --view panorama)")
        return grid_panorama(scan)
    if view == "panorama":
        if len(scan.origins) == 0:
            raise InputError("--view panorama: the scan records no scanner position (give --init for a view at that pose)")
        return origin_panorama(scan)
    raise InputError(f"--view must be auto, grid, panorama or pose, got {view!r}")


def solve(pairs: list[dict], camera: Camera, focal: bool, ransac_px: float) -> dict:
    """The pose of the pairs ({u, v, x, y, z, label}), as init-pose computes it, for the page:
    T_cam_from_scan, rms, per pair its residual, inlier flag and where the pose puts its scan
    point (uv), the camera's focal, and the uncertainty."""
    from rgbd_gt.camera import project
    from rgbd_gt.init.run import Picks, init_from_correspondences
    from rgbd_gt.pose import transform_points

    picks = Picks(np.array([[p["u"], p["v"]] for p in pairs], float), np.array([[p["x"], p["y"], p["z"]] for p in pairs], float),
                  [str(p.get("label", k + 1)) for k, p in enumerate(pairs)])
    if len(pairs) < 6 or not np.isfinite(picks.img).all() or not np.isfinite(picks.obj).all():
        raise InputError("need at least 6 complete pairs")
    r = init_from_correspondences(picks, camera, focal, ransac_px)
    uv, _ = project(r.camera, transform_points(r.T_cam_from_scan, picks.obj))
    return {"T_cam_from_scan": r.T_cam_from_scan.tolist(), "rms_px": r.reprojection_rms_px, "inliers": int(r.inliers.sum()),
            "focal_px": r.camera.fx, "uncertainty": r.uncertainty,
            "pairs": [{"residual_px": e["residual_px"], "inlier": e["inlier"], "u": float(a), "v": float(b)}
                      for e, (a, b) in zip(r.extra["pairs"], np.nan_to_num(uv, nan=-1e6))],
            "camera": r.camera}


def write_pairs(path, pairs: list[dict]) -> None:
    """PAIRS.csv: a header line, then u,v,x,y,z,label per pair (atomically)."""
    import csv
    import io

    from rgbd_gt.io.atomic import atomic_output

    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["u", "v", "x", "y", "z", "label"])
    for k, p in enumerate(pairs, 1):
        w.writerow([f"{float(p['u']):.3f}", f"{float(p['v']):.3f}", *(f"{float(p[c]):.6f}" for c in "xyz"),
                    str(p.get("label") or k)])
    with atomic_output(path) as tmp:
        tmp.write_text(buf.getvalue())
