"""Pose from 2D-3D correspondences: PnP for boards (with the board's symmetric orderings
resolved by color), RANSAC PnP for hand-picked points, and a focal-length search."""

from __future__ import annotations

import cv2
import numpy as np

from rgbd_gt.camera import Camera, project
from rgbd_gt.errors import InputError
from rgbd_gt.pose import apply_update, rigid, transform_points, worst_sigmas


def _to_T(rvec, tvec) -> np.ndarray:
    return rigid(cv2.Rodrigues(rvec)[0], tvec)


def reprojection_rms(T: np.ndarray, obj: np.ndarray, img: np.ndarray, camera: Camera) -> float:
    uv, _ = project(camera, transform_points(T, obj))
    return float(np.sqrt(np.mean(np.sum((uv - img) ** 2, axis=1))))


def pose_uncertainty(T: np.ndarray, obj: np.ndarray, img: np.ndarray, camera: Camera,
                     floor_px: float = 0.1, focal: bool = False) -> dict | None:
    """1-sigma uncertainty of a PnP pose from its n >= 4 correspondences: covariance
    s^2 (J^T J)^-1 of the update (rotation vector, translation) in the camera frame, J the
    reprojection Jacobian (numerical), s^2 = sum(r^2) / (2n - 6) but at least floor_px^2 (a
    perfect fit does not make a pose exact). The worst direction's sigma for rotation (deg) and
    camera position (mm), or None when the points do not fix the pose. With `focal`, the focal
    length (fx = fy) is a 7th unknown: the pose's sigmas include what it leaves open, and
    `focal_px` is its own."""
    import dataclasses

    n, k = len(obj), 7 if focal else 6
    if n < 4 or (focal and n < 5):
        return None

    def residual(delta):
        cam = dataclasses.replace(camera, fx=camera.fx * (1 + delta[6]), fy=camera.fy * (1 + delta[6])) if focal else camera
        return (project(cam, transform_points(apply_update(T, delta[:6]), obj))[0] - img).ravel()
    r0 = residual(np.zeros(k))
    h = 1e-6
    J = np.stack([(residual(h * e) - residual(-h * e)) / (2 * h) for e in np.eye(k)], 1)
    if not np.isfinite(J).all() or np.linalg.matrix_rank(J) < k:
        return None
    s2 = max(float(r0 @ r0) / max(2 * n - k, 1), floor_px**2)
    cov = s2 * np.linalg.inv(J.T @ J)
    out = worst_sigmas(cov[:6, :6])
    if focal:
        out["focal_px"] = float(np.sqrt(cov[6, 6]) * camera.fx)
    return out


def on_one_line(pts: np.ndarray) -> bool:
    """Whether points (n, d) lie on one line (or at one point), within 1e-3 of their extent."""
    s = np.linalg.svd(pts - pts.mean(axis=0), compute_uv=False)
    return len(s) < 2 or s[1] <= 1e-3 * s[0]


def check_spread(obj: np.ndarray, img: np.ndarray, what: str, minimum: int = 4) -> None:
    """InputError unless `minimum` pairs have distinct scan points and pixels and neither set lies
    on one line: PnP solvers divide by that spread (cv2 asserts, numpy raises LinAlgError).

    obj: (n, 3) metres; img: (n, 2) pixels.
    """
    for pts, unit, tol in ((obj, "scan points", 1e-4), (img, "photo pixels", 0.5)):
        distinct = np.unique(np.round(pts / tol), axis=0)
        if len(distinct) < minimum:
            raise InputError(f"{what}: only {len(distinct)} distinct {unit}; {minimum} or more are needed")
        if on_one_line(pts):
            raise InputError(f"{what}: the {unit} lie on one line; the pose is undetermined")


def pnp(obj: np.ndarray, img: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """T_cam_from_scan from >= 6 correspondences (obj (n, 3) scan frame, img (n, 2) distorted
    pixels): cv2.solvePnP, Levenberg-Marquardt, then once more without the corners whose
    reprojection error exceeds 3x the median (one bad corner tilts a small board by a
    tenth of a degree). Returns (T, mask of the corners kept)."""
    dist = np.asarray(camera.distortion, float)
    obj, img = np.ascontiguousarray(obj, np.float64), np.ascontiguousarray(img, np.float64)
    check_spread(obj, img, "board corners")
    try:  # with an absurd camera the undistorted corners collapse and cv2 asserts
        ok, rvec, tvec = cv2.solvePnP(obj, img, camera.K, dist, flags=cv2.SOLVEPNP_SQPNP)
        if ok:
            rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, dist, rvec, tvec)
    except cv2.error:
        ok = False
    if not ok:
        raise InputError("PnP failed on the board corners (is the camera file right?)")
    err = np.linalg.norm(project(camera, transform_points(_to_T(rvec, tvec), obj))[0] - img, axis=1)
    keep = err <= max(3 * np.median(err), 0.05)
    if 6 <= keep.sum() < len(keep):
        rvec, tvec = cv2.solvePnPRefineLM(obj[keep], img[keep], camera.K, dist, rvec, tvec)
    else:
        keep[:] = True
    return _to_T(rvec, tvec), keep


def color_agreement(T: np.ndarray, points: np.ndarray, gray_scan: np.ndarray, photo_gray: np.ndarray,
                    camera: Camera) -> float:
    """Correlation of the scan's gray values with the photo's at their projections (points
    (N, 3) and gray_scan (N,) near the board): the right ordering of a board correlates, its
    180-degree turn (black squares on white) anti-correlates."""
    uv, z = project(camera, transform_points(T, points))
    ok = (z > 0) & np.all(np.isfinite(uv), axis=1)
    ok &= (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < camera.width - 1) & (uv[:, 1] < camera.height - 1)
    if ok.sum() < 10:
        return -1.0
    px = np.round(uv[ok]).astype(int)
    a = photo_gray[px[:, 1], px[:, 0]].astype(np.float64)
    b = gray_scan[ok].astype(np.float64)
    if a.std() == 0 or b.std() == 0:
        return 0.0
    return float(np.corrcoef(a, b)[0, 1])


def board_pose(img_corners: np.ndarray, img_ids: np.ndarray, scan_corners: np.ndarray, scan_ids: np.ndarray,
               n_corners: int, camera: Camera, board_points: np.ndarray, board_gray: np.ndarray,
               photo_gray: np.ndarray, symmetric: bool) -> tuple[np.ndarray, float, float, dict | None]:
    """PnP between photo corners and scan corners matched by id. For chessboards (symmetric)
    the scan's ids may be the photo's turned by 180 degrees; both are solved and the one whose
    colors agree is kept. Returns (T, reprojection rms px, color correlation, `pose_uncertainty`)."""
    orders = [np.arange(n_corners)]
    if symmetric:
        orders.append(np.arange(n_corners)[::-1])
    best = None
    for order in orders:
        lookup = {int(i): k for k, i in enumerate(order[scan_ids])}
        pairs = [(k, lookup[int(i)]) for k, i in enumerate(img_ids) if int(i) in lookup]
        if len(pairs) < 6:
            continue
        a, b = np.array(pairs).T
        T, keep = pnp(scan_corners[b], img_corners[a], camera)
        rms = reprojection_rms(T, scan_corners[b][keep], img_corners[a][keep], camera)
        corr = color_agreement(T, board_points, board_gray, photo_gray, camera)
        if best is None or corr > best[2]:
            best = (T, rms, corr, pose_uncertainty(T, scan_corners[b][keep], img_corners[a][keep], camera))
    if best is None:
        raise InputError("fewer than 6 board corners are common to the photo and the scan")
    return best


def _fits(n: int, threshold_px: float) -> str:
    # hand picks on a photo of several megapixels are often 10-40 px off: say which knob to turn
    return (f"puts 4 or more of the {n} pairs within {threshold_px:g} px of their pixels "
            f"(--ransac-px: hand picks on a large photo may need 10-40)")


def pnp_ransac(obj: np.ndarray, img: np.ndarray, camera: Camera, threshold_px: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """RANSAC PnP for hand-picked correspondences. Returns (T, inlier mask)."""
    dist = np.asarray(camera.distortion, float)
    try:
        ok, rvec, tvec, inl = cv2.solvePnPRansac(np.ascontiguousarray(obj, np.float64), np.ascontiguousarray(img, np.float64),
                                                 camera.K, dist, reprojectionError=threshold_px, iterationsCount=5000,
                                                 confidence=0.9999, flags=cv2.SOLVEPNP_SQPNP)
    except cv2.error:
        ok, inl = False, None
    if not ok or inl is None or len(inl) < 4:
        raise InputError("RANSAC PnP found no pose that " + _fits(len(obj), threshold_px))
    mask = np.zeros(len(obj), bool)
    mask[inl.ravel()] = True
    rvec, tvec = cv2.solvePnPRefineLM(obj[mask], img[mask], camera.K, dist, rvec, tvec)
    return _to_T(rvec, tvec), mask


def estimate_focal(obj: np.ndarray, img: np.ndarray, camera: Camera,
                   threshold_px: float = 4.0) -> tuple[Camera, np.ndarray, np.ndarray]:
    """Search the focal length (fx = fy, principal point from the camera file, no distortion)
    that minimises the RANSAC PnP reprojection error: a coarse log-spaced scan, then golden
    section. Returns (camera with that focal, T, inlier mask)."""
    import dataclasses

    def cost(f: float):
        cam = dataclasses.replace(camera, fx=f, fy=f, distortion=())
        try:
            T, mask = pnp_ransac(obj, img, cam, threshold_px)
        except InputError:
            return np.inf, None, None, cam
        err = reprojection_rms(T, obj[mask], img[mask], cam)
        return err + 1e3 * (1 - mask.mean()), T, mask, cam

    grid = camera.width * np.geomspace(0.3, 4.0, 28)
    costs = [cost(f)[0] for f in grid]
    k = int(np.argmin(costs))
    lo, hi = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
    g = (np.sqrt(5) - 1) / 2
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    ca, cb = cost(a)[0], cost(b)[0]
    for _ in range(30):  # each step keeps one inner point and its cost: one new evaluation
        if ca < cb:
            hi, b, cb = b, a, ca
            a = hi - g * (hi - lo)
            ca = cost(a)[0]
        else:
            lo, a, ca = a, b, cb
            b = lo + g * (hi - lo)
            cb = cost(b)[0]
    _, T, mask, cam = cost((lo + hi) / 2)
    if T is None:
        raise InputError("no focal length gives a pose that " + _fits(len(obj), threshold_px))
    return cam, T, mask
