"""Find the board in the scan: render virtual pinhole views from the scanner position, detect
the board there, and lift its corners to 3D on the board's fitted plane."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.errors import InputError
from rgbd_gt.init.detect import BoardSpec, detect_corners
from rgbd_gt.scan import colors_to_gray
from rgbd_gt.pose import rigid, transform_points

VIEW_FOV_DEG = (70.0, 55.0)  # horizontal, vertical


@dataclass
class ScanView:
    """A virtual pinhole view from the scanner. R: world_from_view (OpenCV axes); f, cx, cy in
    pixels; image: (H, W) uint8 gray of the scan's colors (or intensity)."""

    R: np.ndarray
    origin: np.ndarray
    f: float
    cx: float
    cy: float
    image: np.ndarray

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.f, 0, self.cx], [0, self.f, self.cy], [0, 0, 1.0]])


@dataclass
class ScanBoard:
    corners: np.ndarray  # (n, 3) world, metres
    ids: np.ndarray  # (n,) into BoardSpec.object_points()
    view: ScanView
    pixels: np.ndarray  # (n, 2) where they were detected in the view
    plane_rms_m: float


def _view_rotation(az: float, el: float) -> np.ndarray:
    """world_from_view for a view looking at azimuth az / elevation el (radians), world z up."""
    fwd = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(fwd, right)
    return np.stack([right, down, fwd], 1)


def candidate_views(points: np.ndarray, origin: np.ndarray, sample: int = 1 << 20) -> list[tuple[float, float]]:
    """(azimuth, elevation) of views on a 30-degree grid that hold a useful share of the points
    (counted on an even sample of about `sample` points)."""
    d = points[:: max(1, len(points) // sample)] - origin
    az = np.arctan2(d[:, 1], d[:, 0])
    el = np.arctan2(d[:, 2], np.linalg.norm(d[:, :2], axis=1))
    hx, hy = np.deg2rad(VIEW_FOV_DEG[0]) / 2, np.deg2rad(VIEW_FOV_DEG[1]) / 2
    views = []
    for e in np.deg2rad([-30.0, 0.0, 30.0]):
        for a in np.deg2rad(np.arange(-180.0, 180.0, 30.0)):
            inside = (np.abs(np.angle(np.exp(1j * (az - a)))) < hx) & (np.abs(el - e) < hy)
            if inside.mean() > 0.05:
                views.append((float(inside.mean()), a, e))
    return [(a, e) for _, a, e in sorted(views, reverse=True)]


def render_view(points: np.ndarray, gray: np.ndarray, origin: np.ndarray, az: float, el: float, step_rad: float) -> ScanView:
    """Render the scan's gray values from `origin`, one pixel per angular step of the scan.

    Every front-surface point in a pixel counts (the mean of those within 2 cm of the nearest):
    letting only the nearest win would shift edges on slanted surfaces towards the near side.
    The few empty pixels are filled by normalised convolution.
    """
    import cv2

    from rgbd_gt.render.project import project_pinhole
    from rgbd_gt.render.zbuffer import visible_points

    f = 1.0 / step_rad
    w = int(2 * f * np.tan(np.deg2rad(VIEW_FOV_DEG[0]) / 2))
    h = int(2 * f * np.tan(np.deg2rad(VIEW_FOV_DEG[1]) / 2))
    R = _view_rotation(az, el)
    # the points in the view's cone first (float32 is exact to microns around the scanner): a
    # 40-million-point scan then costs one pass per view
    cam = (points - np.asarray(origin, points.dtype)).astype(np.float32, copy=False) @ R.astype(np.float32)
    reach = cam[:, 2] * np.float32(1.05 * max(w, h) / (2 * f))
    cone = (cam[:, 2] > 0.05) & (np.abs(cam[:, 0]) < reach) & (np.abs(cam[:, 1]) < reach)
    import torch  # here, not at the top: init-pose and pick check their arguments first, in 0.5 s instead of 2.5

    gray = np.asarray(gray)[cone]
    cam = torch.as_tensor(cam[cone], dtype=torch.float64)
    K = torch.tensor([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]], dtype=torch.float64)
    uv, z = project_pinhole(cam, K)
    px = torch.round(uv)
    # the aligners' visibility rule on 1-pixel cells, within 2 cm of the nearest point
    front = visible_points(px, z, (w, h), 1, rel_tol=0.0, abs_tol=0.02, near=0.05)
    key = (px[front, 1] * w + px[front, 0]).long()
    g = torch.as_tensor(gray, dtype=torch.float64)[front]
    total = torch.zeros(h * w, dtype=torch.float64).index_add_(0, key, g)
    count = torch.zeros(h * w, dtype=torch.float64).index_add_(0, key, torch.ones_like(g))
    img = (total / count.clamp_min(1)).reshape(h, w).numpy().astype(np.float32)
    have = (count > 0).reshape(h, w).numpy().astype(np.float32)
    fill = cv2.GaussianBlur(img * have, (0, 0), 1.0) / np.maximum(cv2.GaussianBlur(have, (0, 0), 1.0), 1e-6)
    img = np.where(have > 0, img, fill)
    return ScanView(R, origin, f, (w - 1) / 2, (h - 1) / 2, np.clip(np.round(img), 0, 255).astype(np.uint8))


def _lift(view: ScanView, pixels: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, float]:
    """Intersect the rays of `pixels` with the plane fitted (robustly) to the scan points that
    project inside the detected corners' outline. Returns (corners (n, 3) world, plane rms m)."""
    import cv2

    # float32 around the scanner is exact to microns; only the points that land near the
    # corners' outline are kept (in float64) for the plane fit
    cam = (points - view.origin.astype(points.dtype)).astype(np.float32, copy=False) @ view.R.astype(np.float32)
    z = np.maximum(cam[:, 2], np.float32(1e-6))
    lo, hi = pixels.min(0) - 2, pixels.max(0) + 2
    u = cam[:, 0] / z * np.float32(view.f) + np.float32(view.cx)
    v = cam[:, 1] / z * np.float32(view.f) + np.float32(view.cy)
    near = (cam[:, 2] > 0) & (u >= lo[0]) & (u <= hi[0]) & (v >= lo[1]) & (v <= hi[1])
    cam = cam[near].astype(np.float64)
    uv = cam[:, :2] / cam[:, 2:3] * view.f + [view.cx, view.cy]
    hull = cv2.convexHull(pixels.astype(np.float32))
    centre = pixels.mean(axis=0)
    shrunk = (hull.reshape(-1, 2) - centre) * 0.9 + centre
    inside = in_convex_polygon(uv, shrunk)
    P = cam[inside]
    if len(P) < 20:
        raise InputError("the board in the scan has too few points to fit its plane")
    for _ in range(3):  # fit, drop points off the plane (the stand, the background), refit
        c = P.mean(axis=0)
        _, _, vt = np.linalg.svd(P - c, full_matrices=False)
        n = vt[2]
        dist = (P - c) @ n
        rms = float(np.sqrt(np.mean(dist**2)))
        keep = np.abs(dist) < max(3 * rms, 1e-4)
        if keep.all():
            break
        P = P[keep]
    rays = np.concatenate([(pixels - [view.cx, view.cy]) / view.f, np.ones((len(pixels), 1))], axis=1)
    t = (c @ n) / (rays @ n)
    corners_view = rays * t[:, None]
    return corners_view @ view.R.T + view.origin, rms


def in_convex_polygon(pts: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Points (N, 2) inside the convex polygon poly (M, 2), vectorised over points."""
    nxt = np.roll(poly, -1, axis=0)
    orientation = np.sign(np.sum(poly[:, 0] * nxt[:, 1] - nxt[:, 0] * poly[:, 1]))
    inside = np.ones(len(pts), bool)
    for a, b in zip(poly, nxt):
        inside &= ((b[0] - a[0]) * (pts[:, 1] - a[1]) - (b[1] - a[1]) * (pts[:, 0] - a[0])) * orientation >= 0
    return inside


COARSE_SIDE = 1024  # pixels: views wider than this are searched at a reduced scale first


def find_board_in_scan(points: np.ndarray, colors: np.ndarray, origin: np.ndarray, spec: BoardSpec,
                       step_rad: float, source=None) -> ScanBoard:
    """Search the virtual views (most populated first) for the board; lift the corners of the
    detection that lies farthest inside its view (InputError naming the scan file `source` when
    none holds it).

    A dense scan (views over COARSE_SIDE pixels wide) is searched in views k times coarser made
    from every k^2-th point (the board detector's cost grows with the pixels, the rendering's
    with the points); the view that holds the board is then rendered at the scan's own
    resolution and the board detected again there, around where it was found."""
    gray = colors_to_gray(colors)
    width = 2 * np.tan(np.deg2rad(VIEW_FOV_DEG[0]) / 2) / step_rad
    k = max(1, int(np.ceil(width / COARSE_SIDE)))
    best = None
    for az, el in candidate_views(points, origin):
        view = render_view(points[:: k * k], gray[:: k * k], origin, az, el, step_rad * k)
        found = detect_corners(view.image, spec)
        if found is None:
            continue
        px, ids = found
        h, w = view.image.shape
        margin = min(px[:, 0].min(), px[:, 1].min(), w - px[:, 0].max(), h - px[:, 1].max())
        if best is None or margin > best[0]:
            best = (margin, view, px, ids, az, el)
        if margin > 0.1 * w:
            break
    if best is None:
        raise InputError(f"no {spec.cols}x{spec.rows} board found in the scan's virtual views", source)
    _, view, px, ids, az, el = best
    if k > 1:
        view, px, ids = _detect_again(points, gray, origin, az, el, step_rad, view, px, ids, spec)
    lifted, rms = _lift(view, px, points)
    # the board is a rigid, known grid: fitting it to all lifted corners averages their errors
    model = spec.object_points()[ids]
    T = rigid_fit(model, lifted)
    return ScanBoard(transform_points(T, model), ids, view, px, rms)


def _detect_again(points, gray, origin, az, el, step_rad, coarse: ScanView, px: np.ndarray, ids: np.ndarray,
                  spec: BoardSpec) -> tuple[ScanView, np.ndarray, np.ndarray]:
    """The board's view at the scan's own resolution and the corners detected in it, within the
    region where the coarse view `coarse` found them at px (the coarse corners, carried over,
    when the detector fails there)."""
    view = render_view(points, gray, origin, az, el, step_rad)
    fine = (px - [coarse.cx, coarse.cy]) / coarse.f * view.f + [view.cx, view.cy]
    pad = 0.25 * (fine.max(0) - fine.min(0)) + 8
    h, w = view.image.shape
    x0, y0 = np.maximum(np.floor(fine.min(0) - pad), 0).astype(int)
    x1, y1 = np.minimum(np.ceil(fine.max(0) + pad), [w, h]).astype(int)
    found = detect_corners(np.ascontiguousarray(view.image[y0:y1, x0:x1]), spec)
    if found is None:
        return view, fine, ids
    return view, found[0] + [x0, y0], found[1]


def rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (4x4) taking src (n, 3) onto dst (n, 3) (Kabsch)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return rigid(R, cd - R @ cs)


def scan_step(scan) -> float:
    """The angular spacing (radians) of a scan's points seen from its first scanner position: its
    grid's, or the median point spacing over the median range (`Scan` with origins)."""
    from rgbd_gt.render.mesh import row_step, scan_grids

    origin = scan.origins[0]
    if scan.has_grid:
        return row_step(scan.xyz, *next(scan_grids(scan)))
    from rgbd_gt.scan_ops import median_spacing

    return angular_step(scan.xyz, origin, median_spacing(scan))


def angular_step(points: np.ndarray, origin: np.ndarray, spacing_m: float) -> float:
    """The scan's angular spacing (radians): point spacing over the median range."""
    rng = np.linalg.norm(points - origin, axis=1)
    return float(spacing_m / np.median(rng))
