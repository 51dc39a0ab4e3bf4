"""`rgbd-gt run CONFIG.yaml`: one scan, many photos; per photo init-pose -> refine ->
export-depth -> qa-edges -> overlay, skipping steps whose outputs exist, going on past failures."""

from __future__ import annotations

import csv
import glob
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.align.config import RefineConfig
from rgbd_gt.errors import InputError


@dataclass
class BoardConfig:
    cols: int = 9
    rows: int = 6
    square: float = 0.05
    charuco: str | None = None
    marker: float | None = None
    points: str | None = None  # CSV of the board's corners in the scan frame (skips finding it)

    def check(self) -> "BoardConfig":
        if not (2 <= self.cols <= 100 and 2 <= self.rows <= 100):
            raise ValueError(f"board: cols and rows are inner corners, 2..100 each, got {self.cols}x{self.rows}")
        from rgbd_gt.init.detect import MAX_SQUARE_M

        if not 0 < self.square <= MAX_SQUARE_M or (self.marker is not None and not 0 < self.marker < self.square):
            raise ValueError(f"board: square must lie between 0 and {MAX_SQUARE_M:g} m and marker between 0 and square, "
                             f"got {self.square}, {self.marker}")
        return self


@dataclass
class RunConfig:
    """configs/example.yaml. Relative paths are relative to the config file's folder."""

    scan: str = ""
    camera: str = ""
    photos: list[str] = field(default_factory=list)  # files or glob patterns
    output: str = "rgbd_gt_out"
    board: BoardConfig = field(default_factory=BoardConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    device: str = "auto"
    max_depth: float | None = None

    def check(self) -> "RunConfig":
        if not self.output:
            raise ValueError("output must name a folder")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be auto, cpu or cuda, got {self.device!r}")
        if self.max_depth is not None and self.max_depth < 0:
            raise ValueError(f"max_depth must be 0 or more, got {self.max_depth}")
        self.board.check()
        try:
            self.refine.check()
        except ValueError as exc:
            raise ValueError(f"refine: {exc}") from None
        return self


STEPS = ("init", "refine", "depth", "qa", "overlay")


@dataclass
class PhotoResult:
    photo: str
    status: str = "ok"
    verdict: str | None = None  # the refined pose's: ok | suspect | failed
    reasons: str = ""
    init_rms_px: float | None = None
    refine_loss: float | None = None
    inlier_fraction: float | None = None
    edge_ratio: float | None = None  # structural edges against chance (1.0 = chance)
    edge_before_px: float | None = None
    edge_after_px: float | None = None
    within_1px_before: float | None = None
    within_1px_after: float | None = None
    seen_from_behind: float | None = None  # of the depth map's view (`render.depth.back_facing_fraction`)
    seconds: float = 0.0
    skipped: list[str] = field(default_factory=list)
    error: str = ""


def resolve(config_path: Path, cfg: RunConfig) -> tuple[Path, Path, list[Path], Path]:
    """(scan, camera, photos, output folder) with the config's relative paths resolved."""
    base = config_path.parent

    def norm(p: Path) -> Path:
        return Path(os.path.normpath(p))

    if not cfg.scan or not cfg.camera or not cfg.photos:
        raise InputError("the config needs scan, camera and photos", config_path)
    photos: list[Path] = []
    for pattern in cfg.photos:
        hits = sorted(glob.glob(str(base / pattern)))
        if not hits:
            raise InputError(f"no photo matches '{pattern}'", config_path)
        photos += [norm(Path(h)) for h in hits]
    return norm(base / cfg.scan), norm(base / cfg.camera), photos, norm(base / cfg.output)


def run_photo(photo: Path, scan, colors: np.ndarray, camera, cfg: RunConfig, scan_path: Path, out: Path,
              progress: Callable[[str], None], export_failed: bool = False) -> PhotoResult:
    """The four steps for one photo into out/<photo stem>/. The depth map is written only for a
    pose whose verdict is ok or suspect, unless export_failed."""
    from rgbd_gt.align.refine import RefineInputs, refine_meta, refine_verified
    from rgbd_gt.io import read_pose, write_pose
    from rgbd_gt.io.atomic import atomic_output
    from rgbd_gt.io.camera_file import check_image_matches
    from rgbd_gt.io.depth_file import write_depth_exr, write_depth_png16
    from rgbd_gt.io.image import read_image, write_image
    from rgbd_gt.qa.edges import qa, side_by_side
    from rgbd_gt.qa.overlay import overlay
    from rgbd_gt.render.depth import back_facing_fraction, render_depth

    start = time.perf_counter()
    res = PhotoResult(photo.name)
    d = out / photo.stem
    d.mkdir(parents=True, exist_ok=True)
    files = {"init": d / "init.yaml", "refine": d / "pose.yaml", "depth": d / "depth.exr", "qa": d / "qa.json",
             "overlay": d / "overlay.png"}
    image = read_image(photo)
    check_image_matches(camera, image.shape, photo, "the camera file")

    progress("init-pose")
    if files["init"].exists():
        res.skipped.append("init")
    T_init, init_meta = initial_pose(photo, image, scan, camera, cfg, scan_path, files["init"])
    res.init_rms_px = init_meta.get("reprojection_rms_px")

    progress("refine")
    if files["refine"].exists():
        res.skipped.append("refine")
    else:
        inputs = RefineInputs(scan.xyz, colors, image, camera, T_init, None, scan, init_meta)
        r, verification = refine_verified(inputs, cfg.refine, cfg.device)
        write_pose(files["refine"], r.T_cam_from_scan, **refine_meta(r, cfg.refine, T_init, files["init"], verification,
                                                                             camera=camera))
    T, meta = read_pose(files["refine"])
    res.refine_loss, res.inlier_fraction = meta.get("final_loss"), meta.get("inlier_fraction")
    res.verdict, res.reasons = meta.get("verdict"), "; ".join(meta.get("reasons") or [])
    res.edge_ratio = (meta.get("evidence") or {}).get("edges", {}).get("edge_ratio")

    progress("export-depth")
    if files["depth"].exists():
        res.skipped.append("depth")
    elif res.verdict == "failed" and not export_failed:
        res.skipped.append("depth (failed)")
    else:
        depth = render_depth(scan, camera, T, cfg.max_depth, normals=False)
        res.seen_from_behind = back_facing_fraction(depth)
        write_depth_png16(d / "depth.png", depth.z)
        write_depth_exr(files["depth"], depth.z, camera, T, scan_path.name)

    progress("qa-edges")
    if files["qa"].exists():
        res.skipped.append("qa")
    else:
        img_b, before = qa(scan, colors, image, camera, T_init)
        img_a, after = qa(scan, colors, image, camera, T)
        write_image(d / "qa.png", side_by_side(img_b, img_a))
        with atomic_output(files["qa"]) as tmp:
            tmp.write_text(json.dumps({**after.as_dict(), **before.as_dict("before_")}, indent=1))
    progress("overlay")
    if files["overlay"].exists():
        res.skipped.append("overlay")
    else:  # the blend first: overlay.png's presence says both are there
        checker, mixed, _ = overlay(scan, image, camera, T, cfg.max_depth)
        write_image(d / "overlay_blend.png", mixed)
        write_image(files["overlay"], checker)
    score = json.loads(files["qa"].read_text())
    res.edge_before_px, res.edge_after_px = score["before_mean_distance_px"], score["mean_distance_px"]
    res.within_1px_before, res.within_1px_after = score["before_within_1px"], score["within_1px"]
    res.seconds = time.perf_counter() - start
    return res


def initial_pose(photo: Path, image: np.ndarray, scan, camera, cfg: RunConfig, scan_path: Path,
                 path: Path) -> tuple[np.ndarray, dict]:
    """The photo's initial pose file `path`: read when it exists, else made from the board (and
    written)."""
    from rgbd_gt.init.detect import BoardSpec
    from rgbd_gt.init.run import init_from_board, read_csv_rows
    from rgbd_gt.io import read_pose, write_pose

    if not path.exists():
        b = cfg.board
        spec = BoardSpec(b.cols, b.rows, b.square, b.charuco, b.marker)
        corners = read_csv_rows(Path(b.points), "x,y,z") if b.points else None
        r = init_from_board(scan, image, camera, spec, corners, scan_path, photo)
        write_pose(path, r.T_cam_from_scan, **r.pose_meta())
    return read_pose(path)


def shared_camera(photos: list[Path], scan, colors: np.ndarray, camera, cfg: RunConfig, scan_path: Path, out: Path,
                  progress: Callable[[str], None] = lambda step: None):
    """With cfg.refine.refine_intrinsics, the one camera of all the photos: per photo its initial
    pose (kept for the run) and the camera corrections refined with its pose, then their
    inverse-variance weighted mean. Each photo's variance already includes what its pose leaves
    open, so to first order this is the joint solve of all poses and one camera. Written to
    out/camera.yaml with the per-photo estimates in out/intrinsics.json; reused when there.
    Returns the camera."""
    from rgbd_gt.align.refine import RefineInputs, make_aligner
    from rgbd_gt.camera import corrected
    from rgbd_gt.io import read_camera
    from rgbd_gt.io.atomic import atomic_output
    from rgbd_gt.io.camera_file import check_image_matches, write_camera
    from rgbd_gt.io.image import read_image

    if (out / "camera.yaml").exists():
        return read_camera(out / "camera.yaml")
    estimates = []
    for photo in photos:
        progress(f"{photo.name}: camera")
        try:
            image = read_image(photo)
            check_image_matches(camera, image.shape, photo, "the camera file")
            (out / photo.stem).mkdir(parents=True, exist_ok=True)
            T_init, init_meta = initial_pose(photo, image, scan, camera, cfg, scan_path, out / photo.stem / "init.yaml")
            inputs = RefineInputs(scan.xyz, colors, image, camera, T_init, None, scan, init_meta)
            r = make_aligner(inputs, cfg.refine, cfg.device).refine(T_init)
        except InputError:
            continue  # the photo's own run reports why
        if r.intrinsics is not None and np.isfinite(r.intrinsics_sigma[0]):
            estimates.append({"photo": photo.name, "q": r.intrinsics.tolist(), "sigma": r.intrinsics_sigma})
    if not estimates:
        raise InputError("no photo gave a camera estimate (refine_intrinsics): check the boards and the camera file")
    q = np.array([e["q"] for e in estimates])
    w = 1 / np.square(np.array([e["sigma"] for e in estimates]))  # inf sigma (not refined): weight 0
    for e in estimates:  # JSON has no inf: null where not refined
        e["sigma"] = [float(v) if np.isfinite(v) else None for v in e["sigma"]]
    shared = np.where(w.sum(0) > 0, (w * q).sum(0) / np.maximum(w.sum(0), 1e-300), 0.0)
    sigma = np.where(w.sum(0) > 0, 1 / np.sqrt(np.maximum(w.sum(0), 1e-300)), np.inf)
    result = corrected(camera, shared)
    write_camera(out / "camera.yaml", result)
    with atomic_output(out / "intrinsics.json") as tmp:
        tmp.write_text(json.dumps({"mode": cfg.refine.refine_intrinsics, "photos": estimates, "shared": shared.tolist(),
                                   "shared_sigma": [None if not np.isfinite(v) else float(v) for v in sigma],
                                   "camera": out.name + "/camera.yaml"}, indent=1))
    return result


def write_summary(path: Path, results: list[PhotoResult]) -> None:
    from rgbd_gt.io.atomic import atomic_output

    cols = ["photo", "status", "verdict", "init_rms_px", "refine_loss", "inlier_fraction", "edge_ratio", "edge_before_px",
            "edge_after_px", "within_1px_before", "within_1px_after", "seen_from_behind", "seconds", "skipped", "reasons", "error"]
    with atomic_output(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in results:
            row = [getattr(r, c) for c in cols]
            row[cols.index("skipped")] = " ".join(r.skipped)
            w.writerow(["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in row])
        # the count, in a last row that no photo name can take
        w.writerow(["# verdicts", "", verdict_counts(results)] + [""] * (len(cols) - 3))


def verdict_counts(results: list[PhotoResult]) -> str:
    """'2 ok, 1 suspect, 0 failed' (photos whose steps failed before a verdict count as failed)."""
    from rgbd_gt.align.verify import VERDICTS

    n = {v: sum((r.verdict or "failed") == v for r in results) for v in VERDICTS}
    return ", ".join(f"{n[v]} {v}" for v in VERDICTS)
