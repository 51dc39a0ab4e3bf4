"""`rgbd-gt init-pose`: the whole coarse-pose step on arrays (files are read by the CLI)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from rgbd_gt.camera import Camera, project
from rgbd_gt.errors import InputError, numpy_text_problem, require_file
from rgbd_gt.init.detect import BoardSpec, detect_corners
from rgbd_gt.init.pnp import board_pose, check_spread, estimate_focal, on_one_line, pnp_ransac, pose_uncertainty, reprojection_rms
from rgbd_gt.init.scan_board import ScanBoard, find_board_in_scan, in_convex_polygon, scan_step
from rgbd_gt.scan import Scan, colors_to_gray, scan_colors
from rgbd_gt.pose import transform_points


@dataclass
class InitResult:
    T_cam_from_scan: np.ndarray
    method: str
    reprojection_rms_px: float
    n_points: int
    camera: Camera  # the camera used (its focal estimated with --estimate-focal)
    color_agreement: float | None = None
    photo_corners: np.ndarray | None = None  # (n, 2)
    scan_corners: np.ndarray | None = None  # (n, 3) matched to photo_corners
    scan_board: ScanBoard | None = None
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)
    # 1-sigma {rotation_deg, translation_mm} of the pose (refine's verification draws its repeat
    # starts at this size and compares its change with it)
    uncertainty: dict | None = None
    inliers: np.ndarray | None = None  # (n,) bool, per photo corner: used by the pose
    labels: list[str] | None = None  # per photo corner, for hand picks

    def pose_meta(self) -> dict:
        """The keys an initial pose file records besides the pose."""
        meta = {"method": self.method, "reprojection_rms_px": self.reprojection_rms_px,
                "points_used": self.n_points, "seconds": round(self.seconds, 3)}
        if self.uncertainty is not None:
            meta["uncertainty"] = self.uncertainty
        if self.color_agreement is not None:
            meta["color_agreement"] = self.color_agreement
        meta.update({k: v for k, v in self.extra.items() if v is not None})
        return meta


def board_neighbourhood(scan: Scan, corners: np.ndarray, square: float) -> np.ndarray:
    """Indices of scan points on the board: within 1 cm of the corners' plane and inside their
    outline grown by one square (the checkerboard's outer squares)."""
    c = corners.mean(axis=0)
    _, _, vt = np.linalg.svd(corners - c, full_matrices=False)
    d = scan.xyz - c
    near = np.abs(d @ vt[2]) < 0.01
    uv = d[near] @ vt[:2].T
    cuv = (corners - c) @ vt[:2].T
    hull = cv2.convexHull(cuv.astype(np.float32)).reshape(-1, 2).astype(np.float64)
    grow = hull + square * 1.4 * (hull / np.linalg.norm(hull, axis=1, keepdims=True))
    idx = np.nonzero(near)[0]
    return idx[in_convex_polygon(uv, grow)]


@dataclass
class BoardInScan:
    """The board's corners in the scan (n, 3) (ids into BoardSpec.object_points()) and the scan
    points on it, xyz (m, 3) with their gray levels (m,) (which of a checkerboard's two turns
    fits the photo): found once per scan and used for every photo."""

    corners: np.ndarray
    ids: np.ndarray
    near_xyz: np.ndarray
    near_gray: np.ndarray
    method: str
    plane_rms_m: float | None = None
    scan_board: ScanBoard | None = None  # the virtual view it was found in (for the init report)


def board_in_scan(scan: Scan, spec: BoardSpec, board_points: np.ndarray | None = None, scan_path=None) -> BoardInScan:
    """The board found in the scan's virtual views from its first scanner position (one pixel
    per angular step of the scan), or given as its corners `board_points`."""
    colors = scan_colors(scan, scan_path)
    sb = None
    if board_points is not None:
        if len(board_points) != spec.cols * spec.rows:
            raise InputError(f"--board-points has {len(board_points)} corners, the {spec.cols}x{spec.rows} board has {spec.cols * spec.rows}")
        corners, ids, method = board_points, np.arange(len(board_points)), "board corners given"
    else:
        if len(scan.origins) == 0:
            raise InputError("the scan records no scanner position to render views from; give --board-points", scan_path)
        origin = scan.origins[0]
        sb = find_board_in_scan(scan.xyz, colors, origin, spec, scan_step(scan), scan_path)
        corners, ids, method = sb.corners, sb.ids, "board found in the scan's virtual views"
    near = board_neighbourhood(scan, corners, spec.square)
    return BoardInScan(corners, ids, scan.xyz[near], colors_to_gray(colors[near]), method,
                       sb.plane_rms_m if sb else None, sb)


def detect_photo_board(photo: np.ndarray, spec: BoardSpec, image_path=None) -> tuple[np.ndarray, np.ndarray]:
    """The board's corners (n, 2) in the photo and their ids (n,); InputError when not found."""
    found = detect_corners(cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY), spec)
    if found is None:
        raise InputError(f"no {spec.cols}x{spec.rows} {'ChArUco board' if spec.charuco else 'checkerboard'} found in the photo", image_path)
    return found


def init_from_board(board: BoardInScan, photo: np.ndarray, camera: Camera, spec: BoardSpec,
                    found: tuple[np.ndarray, np.ndarray]) -> InitResult:
    """PnP of the board's corners in the photo (`detect_photo_board`) against those in the scan."""
    start = time.perf_counter()
    img_corners, img_ids = found
    T, rms, corr, sigma = board_pose(img_corners, img_ids, board.corners, board.ids, spec.cols * spec.rows, camera,
                                     board.near_xyz, board.near_gray, cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY),
                                     symmetric=spec.charuco is None)
    return InitResult(T, f"{'charuco' if spec.charuco else 'checkerboard'} PnP ({board.method})", rms, len(img_ids), camera,
                      corr, img_corners, board.corners, board.scan_board, time.perf_counter() - start,
                      {"board_plane_rms_mm": board.plane_rms_m * 1e3 if board.plane_rms_m is not None else None}, sigma)


def _is_number(cell: str) -> bool:
    try:
        float(cell)
        return True
    except ValueError:
        return False


def read_csv_rows(path: Path, fields: str) -> np.ndarray:
    """A CSV of numeric rows with the given comma-separated `fields` (an optional header line
    is skipped) -> (n, len(fields)) float64."""
    require_file(path)
    first = path.read_text(errors="replace").lstrip().split("\n", 1)[0]
    header = not all(_is_number(c) for c in first.split(","))  # "1e-01" has letters and is no header
    try:
        data = np.loadtxt(path, delimiter=",", ndmin=2, skiprows=int(header))
    except UnicodeDecodeError as exc:  # its position counts within numpy's chunk, not the file
        raise InputError(f"not a CSV of {fields} rows: not UTF-8 text (a byte 0x{exc.object[exc.start]:02x})", path) from None
    except ValueError as exc:
        raise InputError(f"not a CSV of {fields} rows ({numpy_text_problem(exc)})", path) from None
    if data.size == 0:  # loadtxt gives an empty file one column
        raise InputError(f"holds no {fields} rows", path)
    if data.shape[1] != len(fields.split(",")):
        raise InputError(f"expected {fields} rows, got {_values(data.shape[1])} per row", path)
    bad = np.flatnonzero(~np.isfinite(data).all(axis=1))
    if len(bad):
        raise InputError(f"row {bad[0] + 1} has a value that is not a finite number", path)
    return data


def _values(n: int) -> str:
    return f"{n} value{'' if n == 1 else 's'}"


def read_board_corners(path: Path) -> np.ndarray:
    """The board's inner corners (n, 3) (scan frame, metres) from a CSV of x,y,z rows (--board-points,
    a run's board.points); InputError naming the file when they do not span a plane, which PnP
    would report later without it."""
    corners = read_csv_rows(path, "x,y,z")
    # fewer than 3: the count against the board's is the clearer error (`board_in_scan`)
    if len(corners) >= 3 and on_one_line(corners):
        raise InputError("the corners lie on one line or at one point, not on a board", path)
    return corners


@dataclass
class Picks:
    """Hand-picked correspondences: photo pixels img (n, 2) (distorted, as in the photo), scan
    points obj (n, 3) (scan frame, metres) and a label per pair."""

    img: np.ndarray
    obj: np.ndarray
    labels: list[str]


PICK_COLUMNS = ("u", "v", "x", "y", "z", "label")


def read_correspondences(path: Path, minimum: int = 6) -> Picks:
    """A CSV of u,v,x,y,z[,label] rows (`rgbd-gt pick` writes them): at least `minimum` rows,
    all finite. A header line, when there is one, names the columns (any order); without one the
    columns are in that order. Unlabelled rows are labelled by their row number."""
    import csv

    require_file(path)
    rows = [r for r in csv.reader(path.read_text(errors="replace").splitlines()) if r and any(c.strip() for c in r)]
    rows = [[c.strip() for c in r] for r in rows]

    order = list(range(6))
    if rows and not all(_is_number(c) for c in rows[0][:5]):
        names = [c.lower().lstrip("#").strip() for c in rows.pop(0)]
        missing = [c for c in PICK_COLUMNS[:5] if c not in names]
        if missing:
            raise InputError(f"the header names no column {', '.join(missing)} (expected u,v,x,y,z[,label])", path)
        order = [names.index(c) if c in names else -1 for c in PICK_COLUMNS]
    elif rows and len(rows[0]) not in (5, 6):
        raise InputError(f"expected u,v,x,y,z[,label] rows, got {_values(len(rows[0]))} in the first", path)
    values, labels = [], []
    for k, r in enumerate(rows, 1):
        if max(order[:5]) >= len(r) or not all(_is_number(r[j]) for j in order[:5]):
            raise InputError(f"row {k}: expected u,v,x,y,z numbers, got {','.join(r)!r}", path)  # !r: shows a control byte
        values.append([float(r[j]) for j in order[:5]])
        labels.append(r[order[5]] if 0 <= order[5] < len(r) and r[order[5]] else str(k))
    data = np.array(values, np.float64).reshape(-1, 5)
    if len(data) < minimum:
        raise InputError(f"need at least {minimum} row{'s' if minimum > 1 else ''} of u,v,x,y,z, got {len(data)}", path)
    if not np.isfinite(data).all():
        raise InputError(f"row {int(np.nonzero(~np.isfinite(data).all(1))[0][0]) + 1} has a value that is not a finite number", path)
    return Picks(data[:, :2], data[:, 2:], labels)


def check_picks(picks: Picks, camera: Camera, points: np.ndarray, path: object,
                origins: np.ndarray | None = None) -> None:
    """InputError when a pick's pixel lies a photo's size or more outside the photo (a pick just
    off it is a mis-click for RANSAC to drop), or its scan point outside the bounding box of the
    scan and its scanner positions, with a 10 cm margin (pairs picked on another scan, or a corrupt
    file; the scanner itself, seen in a photo, is a fair pick). points: (N, 3) the scan's points,
    or the two corners of their box (`prepared.PreparedScan.bounds`); origins: (S, 3); metres."""
    size = np.array(camera.size, float)
    far = np.flatnonzero(((picks.img < -size) | (picks.img > 2 * size)).any(axis=1))
    if len(far):
        raise InputError(f"pair {picks.labels[far[0]]}: pixel {picks.img[far[0]].tolist()} is far outside the "
                         f"{camera.width}x{camera.height} photo", path)
    lo, hi = points.min(axis=0), points.max(axis=0)
    if origins is not None and len(origins):
        lo, hi = np.minimum(lo, origins.min(axis=0)), np.maximum(hi, origins.max(axis=0))
    lo, hi = lo - 0.1, hi + 0.1
    outside = np.flatnonzero(((picks.obj < lo) | (picks.obj > hi)).any(axis=1))
    if len(outside):
        k = outside[0]
        raise InputError(f"pair {picks.labels[k]}: scan point {picks.obj[k].tolist()} lies outside the scan "
                         f"({np.round(lo, 2).tolist()} .. {np.round(hi, 2).tolist()}): picked on another scan?", path)


def init_from_correspondences(picks: Picks, camera: Camera, focal: bool, ransac_px: float = 4.0) -> InitResult:
    """RANSAC PnP on hand picks (with the focal length searched when `focal`). The result's
    extra keys list every pair's reprojection error and inlier flag; with `focal` its
    uncertainty includes the focal length's."""
    start = time.perf_counter()
    img, obj = picks.img, picks.obj
    check_spread(obj, img, "correspondences", 6)
    if focal:
        camera, T, mask = estimate_focal(obj, img, camera, ransac_px)
    else:
        T, mask = pnp_ransac(obj, img, camera, ransac_px)
    rms = reprojection_rms(T, obj[mask], img[mask], camera)
    uv, _ = project(camera, transform_points(T, obj))
    err = np.linalg.norm(uv - img, axis=1)
    pairs = [{"label": lab, "residual_px": round(float(e), 3) if np.isfinite(e) else None, "inlier": bool(m)}
             for lab, e, m in zip(picks.labels, err, mask)]
    return InitResult(T, "RANSAC PnP on hand-picked correspondences" + (" (focal estimated)" if focal else ""), rms,
                      int(mask.sum()), camera, photo_corners=img, scan_corners=obj, seconds=time.perf_counter() - start,
                      extra={"inliers": int(mask.sum()), "correspondences": len(mask), "ransac_px": ransac_px,
                             "estimated_focal_px": camera.fx if focal else None, "pairs": pairs},
                      uncertainty=pose_uncertainty(T, obj[mask], img[mask], camera, focal=focal),
                      inliers=mask, labels=picks.labels)


def write_report(out_dir: Path, result: InitResult, photo: np.ndarray) -> None:
    """init_photo.png: the photo's corners or picks (green circles: used; red: dropped as
    outliers) with a line to where the pose puts their scan points (crosses), labelled for hand
    picks; init_scan_view.png: the virtual scan view with the corners found there."""
    from rgbd_gt.io.image import write_image

    out_dir.mkdir(parents=True, exist_ok=True)
    img = photo.copy()
    uv, _ = project(result.camera, transform_points(result.T_cam_from_scan, result.scan_corners))
    n = len(result.photo_corners)
    inliers = result.inliers if result.inliers is not None else np.ones(n, bool)
    r = max(3, photo.shape[1] // 200)
    scale = max(0.4, photo.shape[1] / 2000)
    for k in range(n):
        color = (0, 220, 0) if inliers[k] else (255, 40, 40)
        p = tuple(int(v) for v in np.round(result.photo_corners[k]))
        cv2.circle(img, p, r, color, max(1, r // 3), cv2.LINE_AA)
        if k < len(uv) and np.all(np.isfinite(uv[k])) and np.all(np.abs(uv[k]) < 1e6):
            q = tuple(int(v) for v in np.round(uv[k]))
            cv2.line(img, p, q, color, 1, cv2.LINE_AA)
            cv2.drawMarker(img, q, color, cv2.MARKER_CROSS, 2 * r, max(1, r // 3), cv2.LINE_AA)
        if result.labels is not None:
            cv2.putText(img, result.labels[k], (p[0] + r + 2, p[1] - r - 2), cv2.FONT_HERSHEY_SIMPLEX, scale, color,
                        max(1, int(2 * scale)), cv2.LINE_AA)
    legend = "circle: photo, cross: scan point at the pose; green: used, red: dropped as outlier"
    cv2.putText(img, legend, (10, int(30 * scale) + 5), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255),
                max(1, int(2 * scale)) + 2, cv2.LINE_AA)
    cv2.putText(img, legend, (10, int(30 * scale) + 5), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0),
                max(1, int(2 * scale)), cv2.LINE_AA)
    write_image(out_dir / "init_photo.png", img)
    if result.scan_board is not None:
        view = cv2.cvtColor(result.scan_board.view.image, cv2.COLOR_GRAY2RGB)
        for p in result.scan_board.pixels:
            cv2.circle(view, tuple(int(v) for v in np.round(p)), 3, (0, 255, 0), 1, cv2.LINE_AA)
        write_image(out_dir / "init_scan_view.png", view)
