"""`rgbd-gt init-pose`: the whole coarse-pose step on arrays (files are read by the CLI)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from rgbd_gt.camera import Camera, project
from rgbd_gt.errors import InputError, require_file
from rgbd_gt.init.detect import BoardSpec, detect_corners
from rgbd_gt.init.pnp import board_pose, estimate_focal, pnp_ransac, pose_uncertainty, reprojection_rms
from rgbd_gt.init.scan_board import ScanBoard, angular_step, find_board_in_scan, in_convex_polygon
from rgbd_gt.io.scan import Scan, colors_to_gray, scan_colors
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


def init_from_board(scan: Scan, photo: np.ndarray, camera: Camera, spec: BoardSpec,
                    board_points: np.ndarray | None = None, scan_path=None, image_path=None) -> InitResult:
    """Board corners in the photo and in the scan (found in virtual views, or given), then PnP."""
    from rgbd_gt.scan_ops import median_spacing

    start = time.perf_counter()
    photo_gray = cv2.cvtColor(photo, cv2.COLOR_RGB2GRAY)
    found = detect_corners(photo_gray, spec)
    if found is None:
        raise InputError(f"no {spec.cols}x{spec.rows} {'ChArUco board' if spec.charuco else 'checkerboard'} found in the photo", image_path)
    img_corners, img_ids = found
    colors = scan_colors(scan, scan_path)
    sb = None
    if board_points is not None:
        if len(board_points) != spec.cols * spec.rows:
            raise InputError(f"--board-points has {len(board_points)} corners, the {spec.cols}x{spec.rows} board has {spec.cols * spec.rows}")
        scan_corners, scan_ids, method = board_points, np.arange(len(board_points)), "board corners given"
    else:
        if len(scan.origins) == 0:
            raise InputError("the scan records no scanner position to render views from; give --board-points", scan_path)
        origin = scan.origins[0]
        sb = find_board_in_scan(scan.xyz, colors, origin, spec, angular_step(scan.xyz, origin, median_spacing(scan)))
        scan_corners, scan_ids, method = sb.corners, sb.ids, "board found in the scan's virtual views"
    near = board_neighbourhood(scan, scan_corners, spec.square)
    T, rms, corr, sigma = board_pose(img_corners, img_ids, scan_corners, scan_ids, spec.cols * spec.rows, camera,
                              scan.xyz[near], colors_to_gray(colors[near]), photo_gray, symmetric=spec.charuco is None)
    return InitResult(T, f"{'charuco' if spec.charuco else 'checkerboard'} PnP ({method})", rms, len(img_ids), camera,
                      corr, img_corners, scan_corners, sb, time.perf_counter() - start,
                      {"board_plane_rms_mm": sb.plane_rms_m * 1e3 if sb else None}, sigma)


def read_csv_rows(path: Path, fields: str) -> np.ndarray:
    """A CSV of numeric rows with the given comma-separated `fields` (an optional header line
    is skipped) -> (n, len(fields)) float64."""
    require_file(path)
    first = path.read_text(errors="replace").lstrip().split("\n", 1)[0]
    try:
        data = np.loadtxt(path, delimiter=",", ndmin=2, skiprows=1 if any(ch.isalpha() for ch in first) else 0)
    except ValueError as exc:
        raise InputError(f"not a CSV of {fields} rows ({exc})", path) from None
    if data.shape[1] != len(fields.split(",")):
        raise InputError(f"expected {fields} rows, got {data.shape[1]} values per row", path)
    return data


def read_correspondences(path: Path, minimum: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """CSV rows u,v,x,y,z -> (img (n, 2), obj (n, 3)); at least `minimum` rows, all finite."""
    data = read_csv_rows(path, "u,v,x,y,z")
    if len(data) < minimum:
        raise InputError(f"need at least {minimum} rows of u,v,x,y,z, got {len(data)}", path)
    if not np.isfinite(data).all():
        raise InputError(f"row {int(np.nonzero(~np.isfinite(data).all(1))[0][0]) + 1} has a value that is not a finite number", path)
    return data[:, :2], data[:, 2:]


def init_from_correspondences(img: np.ndarray, obj: np.ndarray, camera: Camera, focal: bool) -> InitResult:
    start = time.perf_counter()
    if focal:
        camera, T, mask = estimate_focal(obj, img, camera)
    else:
        T, mask = pnp_ransac(obj, img, camera)
    rms = reprojection_rms(T, obj[mask], img[mask], camera)
    return InitResult(T, "RANSAC PnP on hand-picked correspondences" + (" (focal estimated)" if focal else ""), rms,
                      int(mask.sum()), camera, photo_corners=img, scan_corners=obj, seconds=time.perf_counter() - start,
                      extra={"inliers": int(mask.sum()), "correspondences": len(mask),
                             "estimated_focal_px": camera.fx if focal else None},
                      uncertainty=pose_uncertainty(T, obj[mask], img[mask], camera))


def write_report(out_dir: Path, result: InitResult, photo: np.ndarray) -> None:
    """init_photo.png: detected corners (green) and the scan corners reprojected (red);
    init_scan_view.png: the virtual scan view with the corners found there."""
    from rgbd_gt.io.image import write_image

    out_dir.mkdir(parents=True, exist_ok=True)
    img = photo.copy()
    uv, _ = project(result.camera, transform_points(result.T_cam_from_scan, result.scan_corners))
    r = max(3, photo.shape[1] // 200)
    for p in result.photo_corners:
        cv2.circle(img, tuple(int(v) for v in np.round(p)), r, (0, 255, 0), 1, cv2.LINE_AA)
    for p in uv[np.all(np.isfinite(uv), axis=1)]:
        q = tuple(int(v) for v in np.round(p))
        cv2.drawMarker(img, q, (255, 0, 0), cv2.MARKER_CROSS, 2 * r, 1, cv2.LINE_AA)
    write_image(out_dir / "init_photo.png", img)
    if result.scan_board is not None:
        view = cv2.cvtColor(result.scan_board.view.image, cv2.COLOR_GRAY2RGB)
        for p in result.scan_board.pixels:
            cv2.circle(view, tuple(int(v) for v in np.round(p)), 3, (0, 255, 0), 1, cv2.LINE_AA)
        write_image(out_dir / "init_scan_view.png", view)
