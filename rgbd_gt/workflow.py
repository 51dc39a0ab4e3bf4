"""`rgbd-gt run CONFIG.yaml`: one scan, many photos; per photo init-pose -> refine ->
export-depth -> qa-edges -> overlay, skipping steps whose outputs exist, going on past failures."""

from __future__ import annotations

import csv
import glob
import json
import os
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.align.config import RefineConfig
from rgbd_gt.errors import InputError, file_problem, read_yaml, require_listed
from rgbd_gt.io.json_text import json_text

# of the photo's extent: the points the refined pose sees within it must be in the view (a render
# near the border needs the triangles and splats a little beyond it)
REFINED_VIEW_SLACK = 0.01


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

        if not 0 < self.square <= MAX_SQUARE_M:
            raise ValueError(f"board: square must lie between 0 and {MAX_SQUARE_M:g} m, got {self.square}")
        if self.marker is not None and not 0 < self.marker < self.square:
            raise ValueError(f"board: marker must lie between 0 and the square ({self.square} m), got {self.marker}")
        return self


@dataclass
class SiteScan:
    """One scan of a site config (`scans:`) with its photos; camera and board default to the
    config's own."""

    scan: str = ""
    photos: list[str] = field(default_factory=list)  # files or glob patterns
    camera: str | None = None
    name: str | None = None  # its outputs go to OUTPUT/<name>/ (default: the scan file's stem)
    board: BoardConfig | None = None
    init: str | None = None  # its photos' initial pose (default: the config's `init`, else the board)


@dataclass
class RunConfig:
    """configs/example.yaml (one scan) or configs/site.yaml (`scans:`, several). Relative paths are
    relative to the config file's folder."""

    scan: str = ""
    camera: str = ""
    photos: list[str] = field(default_factory=list)  # files or glob patterns
    output: str = "rgbd_gt_out"
    board: BoardConfig = field(default_factory=BoardConfig)
    # a pose file (T_cam_from_scan; a calibration text or JSON file too) that is every photo's initial
    # pose instead of the board's: a LiDAR-camera rig's extrinsic, or photos with no board
    init: str | None = None
    refine: RefineConfig = field(default_factory=RefineConfig)
    device: str = "auto"
    max_depth: float | None = None
    # depth maps of the points alone (sparse, true: `render.depth.point_depth`) or of the surfaces
    # rendered from them (false); null: points for sweeps (`render.points.is_sweep`)
    depth_points: bool | None = None
    scans: list[SiteScan] = field(default_factory=list)
    # the site's scans as the frames of one LiDAR-camera rig (a sweep and its photo each, one init,
    # one camera): one pose solved over all of them (`refine --pairs`), OUTPUT/rig.yaml and each
    # frame's pose.yaml; null: so when the scans are sweeps (`render.points.is_sweep`) that qualify
    rig: bool | None = None
    # a bundle file (docs/bundle.md) instead of scan, camera and photos: several cameras, a rig
    # (stereo), each photo's init; all its photos solved together (`steps.bundle_step`) first
    bundle: str | None = None

    def check(self) -> "RunConfig":
        if not self.output:
            raise ValueError("output must name a folder")
        if self.device not in ("auto", "cpu", "cuda"):
            raise ValueError(f"device must be auto, cpu or cuda, got {self.device!r}")
        if self.max_depth is not None and self.max_depth < 0:
            raise ValueError(f"max_depth must be 0 or more, got {self.max_depth}")
        if self.scans and (self.scan or self.photos):
            raise ValueError("give either scan and photos (one scan) or scans (a site), not both")
        if self.bundle is not None and (self.scan or self.camera or self.photos or self.scans or self.init):
            raise ValueError("bundle: the bundle file names the scan, cameras, photos and inits; leave out "
                             "scan, camera, photos, scans and init")
        if self.bundle is not None and self.refine.refine_intrinsics != "none":
            raise ValueError("bundle: each camera's refine: in the bundle file says what its photos share; "
                             "leave out refine.refine_intrinsics")
        if self.rig and len(self.scans) < 2:
            raise ValueError("rig: true solves the frames of a site (scans:, two or more) together")
        self.board.check()
        for k, s in enumerate(self.scans):
            if s.board is not None:
                s.board.check()
            for key in ("camera", "init"):
                if getattr(s, key) is not None and not getattr(s, key).strip():  # else the config's own is taken
                    raise ValueError(f"scans[{k}].{key}: an empty path; give a file, or leave it out for the config's own")
            if s.name is not None and (not s.name or s.name in (".", "..") or "/" in s.name or s.name.startswith(".")):
                raise ValueError(f"scans[{k}].name must be a plain folder name, got {s.name!r}")
        try:
            self.refine.check()
        except ValueError as exc:
            raise ValueError(f"refine: {exc}") from None
        return self


@dataclass
class ScanJob:
    """A scan with its photos, paths resolved: outputs in out/<photo stem>/."""

    name: str
    scan: Path
    camera: Path
    photos: list[Path]
    out: Path
    board: BoardConfig
    init: Path | None = None  # the initial pose of every photo that has no init.yaml yet (else the board's)
    bundle: Path | None = None  # a bundle file: its photos solved together (`solve_bundle`), each with its camera and init


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
    ring_edge_ratio: float | None = None  # a sweep's depth steps on the photo's edges against chance (a rig's frame: its own)
    edge_before_px: float | None = None
    edge_after_px: float | None = None
    within_1px_before: float | None = None
    within_1px_after: float | None = None
    seen_from_behind: float | None = None  # of the depth map's view (`render.depth.back_facing_fraction`)
    verticals_roll_before_deg: float | None = None  # off the scan's vertical (`qa.verticals`); None: says nothing
    verticals_roll_after_deg: float | None = None
    seconds: float = 0.0
    skipped: list[str] = field(default_factory=list)
    error: str = ""
    scan: str = ""  # the scan's name (a site's folder)
    view_points: int | None = None  # of the scan, the points the photo's steps worked on
    steps: dict[str, float] = field(default_factory=dict)  # seconds per step run (init, view, aligner, verify, depth, qa, overlay)


def resolve(config_path: Path, cfg: RunConfig) -> tuple[list[ScanJob], Path]:
    """The config's scans with their paths resolved, and the output folder. One scan writes to
    OUTPUT/<photo stem>/, a site's scans to OUTPUT/<name>/<photo stem>/. Paths are made absolute:
    workers elsewhere (Ray) do not share this process's working folder."""
    base = config_path.absolute().parent

    def at(p: str) -> Path:
        """A path of the config: relative to its folder, `~` the user's home."""
        return Path(os.path.normpath(base / os.path.expanduser(p)))

    def photos_of(patterns: list[str]) -> list[Path]:
        found: dict[Path, None] = {}  # in order, once each: patterns may overlap
        for pattern in patterns:
            if not pattern.strip():  # would name the config's own folder
                raise InputError("photos: an empty path; give photo files or a pattern such as 'folder/*.png'", config_path)
            hits = sorted(glob.glob(str(at(pattern))))
            files = [h for h in hits if os.path.isfile(h)]
            if hits and not files:
                raise InputError(f"photos: '{pattern}' names a folder, not photos (a pattern such as 'folder/*.png' takes "
                                 "its photos)", config_path)
            if not files:
                raise InputError(f"no photo matches '{pattern}'", config_path)
            found.update((Path(h), None) for h in files)
        stems: dict[str, Path] = {}
        for photo in found:  # a photo's outputs are OUTPUT/<stem>/: a second one there would resume the first's pose
            if photo.stem in stems:
                raise InputError(f"photos {stems[photo.stem]} and {photo} would write to the same folder "
                                 f"'{photo.stem}': rename one, or list them under scans: with names", config_path)
            stems[photo.stem] = photo
        return list(found)

    def existing(path: str, key: str, kind: str) -> Path:
        """The config's file `path`, checked before any scan is prepared."""
        if not path.strip():  # would name the config's own folder
            raise InputError(f"{key}: an empty path; give a {kind} file", config_path)
        found = at(path)
        if problem := file_problem(found, f"{kind} file"):
            raise InputError(f"{key}: {found}: {problem}", config_path)
        return found

    def init_of(path: str | None) -> Path | None:
        return None if path is None else existing(path, "init", "pose")

    def board_of(board: BoardConfig) -> BoardConfig:
        return board if board.points is None else replace(board, points=str(existing(board.points, "board.points", "corners")))

    output = at(cfg.output)
    if cfg.bundle is not None:
        from rgbd_gt.io.bundle_file import read_bundle

        bundle = existing(cfg.bundle, "bundle", "bundle")
        spec = read_bundle(bundle)
        require_listed(spec.named_files(), bundle)
        return [ScanJob(spec.scan.stem, spec.scan, spec.cameras[spec.photos[0].camera].file, [e.image for e in spec.photos],
                        output, board_of(cfg.board), bundle=bundle)], output
    if not cfg.scans:
        if not cfg.scan or not cfg.camera or not cfg.photos:
            raise InputError("the config needs scan, camera and photos (or scans: a list of them)", config_path)
        scan = existing(cfg.scan, "scan", "scan")
        return [ScanJob(scan.stem, scan, at(cfg.camera), photos_of(cfg.photos), output, board_of(cfg.board),
                        init_of(cfg.init))], output
    jobs = []
    for k, s in enumerate(cfg.scans):
        camera = s.camera or cfg.camera
        if not s.scan or not camera or not s.photos:
            raise InputError(f"scans[{k}] needs scan, photos and a camera (its own or the config's)", config_path)
        scan = existing(s.scan, "scan", "scan")
        name = s.name or scan.stem
        jobs.append(ScanJob(name, scan, at(camera), photos_of(s.photos), output / name, board_of(s.board or cfg.board),
                            init_of(s.init or cfg.init)))
    names = [j.name for j in jobs]
    if len(set(names)) < len(names):
        raise InputError(f"two scans would write to the same folder ({', '.join(sorted({n for n in names if names.count(n) > 1}))}): "
                         "give them names", config_path)
    return jobs, output


def job_camera(job: ScanJob):
    """The camera of a scan's photos; a camera file without an image size (calibration text,
    JSON) takes it from the first photo (every photo is checked against the camera when it runs)."""
    from rgbd_gt.io import read_camera
    from rgbd_gt.io.image import read_image

    return read_camera(job.camera, lambda: read_image(job.photos[0]).shape[1::-1], job.photos[0])


def board_spec(b: BoardConfig):
    from rgbd_gt.init.detect import BoardSpec

    return BoardSpec(b.cols, b.rows, b.square, b.charuco, b.marker)


def run_photo(photo: Path, prepared, camera, job: ScanJob, cfg: RunConfig,
              progress: Callable[[str], None] = lambda step: None, export_failed: bool = False) -> PhotoResult:
    """The steps for one photo of `job` into job.out/<photo stem>/, on the points of the prepared
    scan (`prepared.PreparedScan`) its view can reach; the initial pose from job.init (a pose file)
    when given, else from the board. The depth map is written only for a pose whose verdict is ok or
    suspect, unless export_failed."""
    from rgbd_gt.io import read_pose, write_pose
    from rgbd_gt.io.atomic import atomic_output
    from rgbd_gt.io.image import write_image
    from rgbd_gt.scan import scan_colors
    from rgbd_gt.pose import camera_centre
    from rgbd_gt.qa import verticals
    from rgbd_gt.render.depth import back_facing_fraction
    from rgbd_gt.render.renders import Renders
    from rgbd_gt.steps import depth_step, overlay_paths, overlay_step, qa_step, refine_step, write_depth

    start = time.perf_counter()
    res = PhotoResult(photo.name)
    clock = [start]

    def lap(step: str) -> None:
        now = time.perf_counter()
        res.steps[step] = round(now - clock[0], 3)
        clock[0] = now

    def around(T: np.ndarray) -> np.ndarray:
        return prepared.xyz_around(camera_centre(T), verticals.REACH, verticals.MAX_POINTS)

    d = job.out / photo.stem
    files = {"init": d / "init.yaml", "refine": d / "pose.yaml", "depth": d / "depth.exr", "qa": d / "qa.json",
             "overlay": d / "overlay.png"}
    progress("init-pose")
    # solved with the other photos (`solve_rig`, `solve_bundle`): its init and refine not skipped
    joint = files["refine"].exists() and is_joint(read_pose(files["refine"])[1])
    if files["init"].exists() and not joint:
        res.skipped.append("init")
    inputs, seen = photo_inputs(photo, prepared, camera, job, lap)
    image, T_init, scan, renders = inputs.photo, inputs.T_init, inputs.scan, inputs.renders
    res.init_rms_px = inputs.init_meta.get("reprojection_rms_px")

    progress("refine")
    if files["refine"].exists():
        if not joint:
            res.skipped.append("refine")
    else:
        refined = refine_step(inputs, cfg.refine, files["init"], cfg.device, job.camera)
        write_pose(files["refine"], refined.T, **refined.meta)
        res.steps["aligner"] = round(refined.result.seconds, 3)
        lap("refine")
    T, meta = read_pose(files["refine"])
    # a poor init: the refined pose may see beyond the initial view's margin, and the depth map,
    # qa and overlay must have all that the photo sees (a rare second view and ray-casting scene;
    # any view that holds what a pose sees renders it to the same bits: tests/test_steps.py)
    if not np.isin(prepared.view_index(camera, T, margin=REFINED_VIEW_SLACK), seen).all():
        scan = prepared.subset(np.union1d(seen, prepared.view_index(camera, T)))
        renders = Renders(scan, scan_colors(scan, prepared.source), [T_init])
    lap("refined_view")
    res.view_points = len(scan)
    res.refine_loss, res.inlier_fraction = meta.get("final_loss"), meta.get("inlier_fraction")
    res.verdict, res.reasons = meta.get("verdict"), "; ".join(meta.get("reasons") or [])
    edges = (meta.get("evidence") or {}).get("edges", {})
    res.edge_ratio = edges.get("edge_ratio") if edges.get("edge_check_usable", True) else None  # a sweep's says nothing
    rings = meta["frame_ring_edges"] if "frame_ring_edges" in meta else (meta.get("evidence") or {}).get("ring_edges")
    res.ring_edge_ratio = (rings or {}).get("ratio")

    progress("export-depth")
    if files["depth"].exists():
        res.skipped.append("depth")
        from rgbd_gt.io.depth_file import read_depth_exr

        behind = read_depth_exr(files["depth"])[1].get("rgbd_gt_seen_from_behind")  # so that a resumed summary says it too
        res.seen_from_behind = float(behind) if behind is not None else None
    elif res.verdict == "failed" and not export_failed:
        res.skipped.append("depth (failed)")
    else:
        depth = depth_step(renders, camera, T, cfg.max_depth, cfg.depth_points, pose_path=files["refine"])
        res.seen_from_behind = back_facing_fraction(depth)
        write_depth(depth, camera, T, prepared.source.name, files["depth"], png16=d / "depth.png")
        lap("depth")

    progress("qa-edges")
    if files["qa"].exists():
        res.skipped.append("qa")
    else:
        checked = qa_step(renders, image, camera, T, around(T), T_init, files["refine"], files["init"])
        write_image(d / "qa.png", checked.image)
        with atomic_output(files["qa"]) as tmp:
            tmp.write_text(json_text(checked.scores))
        lap("qa")
    progress("overlay")
    if files["overlay"].exists():
        res.skipped.append("overlay")
    else:  # the others first: overlay.png's presence says they are all there
        pictures = overlay_step(renders, image, camera, T, cfg.max_depth, pose_path=files["refine"])
        paths = overlay_paths(files["overlay"])
        for k in ("blend", "points", "checker"):
            if getattr(pictures, k) is not None:
                write_image(paths[k], getattr(pictures, k))
        lap("overlay")
    score = json.loads(files["qa"].read_text())
    res.edge_before_px, res.edge_after_px = score["before_mean_distance_px"], score["mean_distance_px"]
    res.within_1px_before, res.within_1px_after = score["before_within_1px"], score["within_1px"]
    res.verticals_roll_before_deg, res.verticals_roll_after_deg = score.get("before_verticals_roll_deg"), score.get("verticals_roll_deg")
    res.steps["mesh"] = round(renders.mesh_seconds, 3)  # within the steps that rendered first
    res.seconds = time.perf_counter() - start
    return res


def photo_inputs(photo: Path, prepared, camera, job: ScanJob, lap: Callable[[str], None] = lambda step: None):
    """A photo of `job` as the refine step takes it (`align.refine.RefineInputs`): the photo, its
    initial pose (`initial_pose`, into job.out/<photo stem>/init.yaml), the points of the prepared
    scan (`prepared.PreparedScan`) in its view and around its camera, and their renders; and the
    view's indices (block order). lap(step) is called after the init and after the view."""
    from rgbd_gt.align.refine import RefineInputs
    from rgbd_gt.pose import camera_centre
    from rgbd_gt.qa import verticals
    from rgbd_gt.render.renders import Renders
    from rgbd_gt.scan import scan_colors
    from rgbd_gt.steps import open_photo

    d = job.out / photo.stem
    d.mkdir(parents=True, exist_ok=True)
    image = open_photo(photo, camera, to_align=True, camera_path=job.camera).image
    T_init, init_meta = initial_pose(photo, image, prepared, camera, job, d / "init.yaml")
    lap("init")
    seen = prepared.view_index(camera, T_init)
    if len(seen) == 0:
        raise InputError("no scan points in view of the initial pose", d / "init.yaml")
    scan = prepared.subset(seen)
    # the verdict renders the result, qa the init beside it: one ray-casting scene; depth, qa and
    # the overlay take the verdict's render where they ask for the same camera and pose
    renders = Renders(scan, scan_colors(scan, prepared.source), [T_init])
    around = prepared.xyz_around(camera_centre(T_init), verticals.REACH, verticals.MAX_POINTS)
    inputs = RefineInputs(scan.xyz, scan_colors(scan, prepared.source, to_align=True), image, camera, T_init, None,
                          scan, init_meta, around, renders)
    lap("view")
    return inputs, seen


def initial_pose(photo: Path, image: np.ndarray, prepared, camera, job: ScanJob, path: Path) -> tuple[np.ndarray, dict]:
    """The photo's initial pose file `path`: read when it exists, else written from job.init (a
    pose file shared by the photos) or made from job.board (found once per scan, `steps.init_step`).
    It records the SHA-1 of the photo, the scan, the camera file and the init or board corners
    file, and the board's layout: a rerun where one of them has other content is an error, not
    the old pose resumed."""
    from rgbd_gt.io import read_pose, write_pose
    from rgbd_gt.steps import Photo, init_step

    files = {"photo": photo, "camera": job.camera}
    if job.init is not None:
        files["init"] = job.init
    elif job.board.points:
        files["board_points"] = Path(job.board.points)
    b = job.board
    from rgbd_gt.steps import made_from, made_from_other

    made = made_from(prepared.source, prepared.sha1, files,
                     None if job.init is not None else (b.cols, b.rows, b.square, b.charuco, b.marker))
    if path.exists():
        T, meta = read_pose(path)
        kind = made_from_other(meta, made)
        if kind is not None:
            raise InputError(f"{path.parent} holds outputs made from another {kind.replace('_', ' ')} ({meta.get(kind)}, "
                             f"SHA-1 {str(meta[kind + '_sha1'])[:12]}): remove that folder to redo this photo", photo)
        return T, meta
    if job.init is not None:
        T, meta = read_pose(job.init)
        meta["method"] = f"the config's init ({job.init})"
    else:
        r = init_step(prepared, Photo(image, camera), photo, board_spec(job.board), board_corners(job.board))[0]
        T, meta = r.T_cam_from_scan, r.pose_meta()
    write_pose(path, T, **{**meta, **made})
    return read_pose(path)


def board_corners(board: BoardConfig) -> np.ndarray | None:
    """The board's corners (k, 3) in the scan as the config's board.points file gives them, or None."""
    from rgbd_gt.init.run import read_board_corners

    return read_board_corners(Path(board.points)) if board.points else None


RIG_FILE = "rig.yaml"  # under the run's output folder: the pose of a rig's frames


def not_a_rig(jobs: list[ScanJob]) -> str | None:
    """Why the site's scans cannot be the frames of one rig (`RunConfig.rig`), or None."""
    if len(jobs) < 2:
        return "a rig's frames are two or more scans (scans:)"
    if any(len(j.photos) != 1 for j in jobs):
        return "each of a rig's scans has one photo, the camera's at that sweep"
    if any(j.init is None for j in jobs) or len({j.init for j in jobs}) > 1:
        return "a rig's frames share one init (the config's init: the rig's extrinsic)"
    if len({j.camera for j in jobs}) > 1:
        return "a rig's frames share one camera"
    return None


def rig_made_from(jobs: list[ScanJob], prepared: list) -> dict:
    """What a rig's pose is made from, recorded in rig.yaml so that a rerun with other inputs is
    an error, not the old pose resumed: the camera file and its SHA-1, the init's SHA-1 (its path
    is the pose file's own `init` key), and one SHA-1 over the frames' scans and one over their
    photos (`steps.made_from`'s keys)."""
    import hashlib

    from rgbd_gt.steps import made_from

    frames = [made_from(p.source, p.sha1, {"photo": j.photos[0], "camera": j.camera, "init": j.init})
              for j, p in zip(jobs, prepared)]
    made = {k: frames[0][k] for k in ("camera", "camera_sha1", "init_sha1")}
    for kind in ("scan", "photo"):
        made[f"{kind}s_sha1"] = hashlib.sha1(" ".join(f[f"{kind}_sha1"] for f in frames).encode()).hexdigest()
    return made


def solve_rig(jobs: list[ScanJob], prepared: list, camera, cfg: RunConfig, out: Path,
              progress: Callable[[str], None] = lambda step: None) -> tuple[np.ndarray, dict]:
    """One pose for the frames of a rig (`not_a_rig`: a scan and its photo each; prepared: their
    `prepared.PreparedScan`s): `steps.refine_step` over all frames at once, the joint solve of
    `refine --pairs`, judged by its frames refined apart and the sweeps' depth edges. Written to
    out/rig.yaml (with `frames`) and to each frame's pose.yaml (with `rig`: that file), so that
    its steps take it. Reused while rig.yaml names the same frames. Returns the pose and its meta."""
    from rgbd_gt.align.verify import frame_verdict
    from rgbd_gt.io import read_pose, write_pose
    from rgbd_gt.steps import made_from_other, refine_step

    path = out / RIG_FILE
    names = [f"{j.name}/{j.photos[0].name}" for j in jobs]
    made = rig_made_from(jobs, prepared)
    if path.exists():
        T, meta = read_pose(path)
        if meta.get("frames") != names:
            raise InputError(f"it was solved over other frames ({', '.join(meta.get('frames') or [])}): remove it to "
                             "solve this config's frames", path)
        kind = made_from_other(meta, made)
        if kind is not None:
            raise InputError(f"it was solved from other {kind} (SHA-1 {str(meta[kind + '_sha1'])[:12]}): remove it to "
                             "solve this config's frames", path)
    else:
        solo = [job.out / job.photos[0].stem / "pose.yaml" for job in jobs]
        solo = [p for p in solo if p.exists() and "rig" not in read_pose(p)[1]]
        if solo:
            raise InputError("a frame of the rig was refined alone before: remove its pose.yaml to solve the rig "
                             "(or set rig: false)", solo[0])
        inputs = []
        for job, p in zip(jobs, prepared):
            progress(f"rig: {job.name}")
            inputs.append(photo_inputs(job.photos[0], p, camera, job)[0])

        def levels(rec: dict) -> None:
            progress(f"rig of {len(jobs)} frames: level {rec['level']} iteration {rec['iteration']}")

        first = jobs[0].out / jobs[0].photos[0].stem / "init.yaml"
        refined = refine_step(inputs[0], cfg.refine, first, cfg.device, jobs[0].camera, levels, more=inputs[1:])
        T, meta = refined.T, {**refined.meta, "frames": names, **made}
        write_pose(path, T, **meta)
    rings = (meta.get("evidence") or {}).get("ring_edges")
    frames = (rings or {}).get("frames") or []
    for k, job in enumerate(jobs):
        d = job.out / job.photos[0].stem
        if not (d / "pose.yaml").exists():
            # each frame judged on its own depth edges too: the rig's pose can be right and one frame's photo not of its sweep
            verdict, reasons = frame_verdict(meta["verdict"], meta.get("reasons") or [], rings, k, cfg.refine.verify)
            mine = {key: v for key, v in meta.items() if key != "frames" and key not in made} | {"verdict": verdict, "reasons": reasons}
            write_pose(d / "pose.yaml", T, **mine, frame_ring_edges=frames[k] if k < len(frames) else None,
                       rig=os.path.relpath(path, d))
    return T, meta


def is_joint(meta: dict) -> bool:
    """Whether a pose file's keys are those of a pose solved with other photos: a rig's frames
    (`solve_rig`: `rig`) or a bundle's photos (`solve_bundle`: evidence.bundle)."""
    return "rig" in meta or "bundle" in (meta.get("evidence") or {})


def solve_bundle(job: ScanJob, cfg: RunConfig, cache: Path,
                 progress: Callable[[str], None] = lambda step: None) -> tuple[list[tuple], dict | None]:
    """The photos of a bundle job (`ScanJob.bundle`) solved together (`steps.bundle_step`, the
    scan prepared under `cache`) into job.out as `refine --bundle` writes them
    (`steps.write_bundled`: PHOTO/pose.yaml, cameras/, rig.yaml, bundle.json), so that each
    photo's steps take its pose; reused while bundle.json records this bundle file's content.
    Returns per photo (photo, its job: its camera file and init, its camera as solved), and
    rig.yaml's keys for a rig (else None)."""
    from rgbd_gt.io import read_camera, read_pose
    from rgbd_gt.io.bundle_file import read_bundle
    from rgbd_gt.prepared import file_key
    from rgbd_gt.steps import bundle_step, write_bundled

    spec = read_bundle(job.bundle)
    record, poses = job.out / "bundle.json", [job.out / e.image.stem / "pose.yaml" for e in spec.photos]
    if record.exists():
        if _json_or_empty(record).get("bundle_sha1") != file_key(job.bundle)["sha1"]:
            raise InputError("it was solved from another bundle file: remove it and the photos' folders to solve "
                             f"again ({job.bundle})", record)
        missing = next((p for p in poses if not p.exists()), None)
        if missing is not None:
            raise InputError(f"the bundle was solved, but {missing} is gone: remove bundle.json to solve all photos again",
                             record)
    else:
        alone = next((p for p in poses if p.exists() and not is_joint(read_pose(p)[1])), None)
        if alone is not None:
            raise InputError("this photo was refined alone before: remove its pose.yaml to solve the bundle", alone)
        start = time.perf_counter()
        done = bundle_step(spec, cfg.refine, cfg.device, cache, progress)
        job.out.mkdir(parents=True, exist_ok=True)
        write_bundled(job.out, spec, done, job.bundle, time.perf_counter() - start)
    cameras = {name: read_camera(job.out / "cameras" / f"{name}.yaml") for name in spec.cameras}
    rig = read_yaml(job.out / "rig.yaml") if spec.rig else None
    return [(e.image, replace(job, camera=spec.cameras[e.camera].file, photos=[e.image], init=e.init), cameras[e.camera])
            for e in spec.photos], rig


def shared_camera(job: ScanJob, prepared, camera, cfg: RunConfig, progress: Callable[[str], None] = lambda step: None):
    """With cfg.refine.refine_intrinsics, the one camera of all of job's photos: every photo's
    pose and the camera's corrections in one solve (`align.bundle.Bundle`) from the photos'
    initial poses (kept for the run). Each photo's pose given that camera is then its own refine
    (`run_photo`): at the joint solution each pose is optimal for the shared camera. Written to
    job.out/camera.yaml with intrinsics.json beside it (the shared corrections, their 1-sigma,
    each photo's cross-photo evidence); reused when there. Returns the camera."""
    from rgbd_gt.align.bundle import Bundle, BundlePhoto
    from rgbd_gt.align.refine import RefineInputs, make_aligner
    from rgbd_gt.camera import corrected
    from rgbd_gt.io import read_camera
    from rgbd_gt.io.atomic import atomic_output
    from rgbd_gt.io.camera_file import write_camera
    from rgbd_gt.scan import scan_colors
    from rgbd_gt.steps import made_from, made_from_other, open_photo

    out = job.out
    made = made_from(prepared.source, prepared.sha1, {"camera": job.camera})
    if (out / "camera.yaml").exists() and made_from_other(_json_or_empty(out / "intrinsics.json").get("made_from", {}), made) is None:
        return read_camera(out / "camera.yaml")  # else refined again: the camera file or the scan has changed
    photos, names, errors = [], [], []
    for photo in job.photos:
        progress(f"{photo.name}: camera")
        try:
            image = open_photo(photo, camera, to_align=True, camera_path=job.camera).image
            (out / photo.stem).mkdir(parents=True, exist_ok=True)
            T_init, _ = initial_pose(photo, image, prepared, camera, job, out / photo.stem / "init.yaml")
            scan = prepared.view(camera, T_init)
            inputs = RefineInputs(scan.xyz, scan_colors(scan, prepared.source, to_align=True), image, camera, T_init, None, scan)
            aligner = make_aligner(inputs, cfg.refine, cfg.device)
            aligner.prepare(T_init)  # a photo that sees too little of the scan drops out here
        except InputError as exc:
            errors.append(str(exc))  # and the photo's own run reports it
            continue
        photos.append(BundlePhoto(aligner.objective, T_init, name=photo.name))
        names.append(photo.name)
    if not photos:
        raise InputError("no photo gave a camera estimate (refine_intrinsics): " + (errors[0] if errors else "check the boards and the camera file"))
    progress(f"{len(photos)} photos: one camera")
    solved = Bundle(photos, 1).solve()
    q, sigma = solved.q[0], solved.stated_q_sigma(0)  # as a bundle's cameras/ files state it
    result = corrected(camera, q)
    write_camera(out / "camera.yaml", result)
    with atomic_output(out / "intrinsics.json") as tmp:
        tmp.write_text(json_text({
            "mode": cfg.refine.refine_intrinsics, "solve": "joint",
            "photos": [{"photo": n, **ev} for n, ev in zip(names, solved.evidence)],
            "shared": q, "shared_sigma": sigma,
            "camera": out.name + "/camera.yaml", "made_from": made}))
    return result


def _json_or_empty(path: Path) -> dict:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def write_summary(path: Path, results: list[PhotoResult]) -> None:
    from rgbd_gt.io.atomic import atomic_output

    cols = ["photo", "status", "verdict", "init_rms_px", "refine_loss", "inlier_fraction", "edge_ratio", "edge_before_px",
            "edge_after_px", "within_1px_before", "within_1px_after", "seen_from_behind", "seconds", "skipped", "reasons", "error",
            "scan", "view_points", "steps", "verticals_roll_before_deg", "verticals_roll_after_deg", "ring_edge_ratio"]
    with atomic_output(path) as tmp, open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(cols)
        for r in results:
            row = [getattr(r, c) for c in cols]
            row[cols.index("skipped")] = " ".join(r.skipped)
            row[cols.index("steps")] = " ".join(f"{k}={v:.2f}" for k, v in r.steps.items())
            w.writerow(["" if v is None else (f"{v:.6g}" if isinstance(v, float) else v) for v in row])
        # the count, in a last row that no photo name can take
        w.writerow(["# verdicts", "", verdict_counts(results)] + [""] * (len(cols) - 3))


def write_run_record(path: Path, prepared: list, seconds: float, engine: str, workers: int) -> None:
    """OUTPUT/run.json: how the run went as a whole: the engine, each scan's preparation
    (`engine.Prepared`: seconds, from the cache or not, and the parts of it) and the wall time."""
    from rgbd_gt.io.atomic import atomic_output

    scans = []
    for p in prepared:
        entry = {"name": p.job.name, "scan": str(p.job.scan), "camera": str(p.job.camera),
                 "folder": os.path.relpath(p.job.out, path.parent),
                 "photos": [str(f) for f in p.job.photos], "points": p.points, "cached": p.cached,
                 "seconds": round(p.seconds, 3), "steps": p.steps, "error": p.error}
        if p.job.bundle is not None:
            entry["bundle"] = str(p.job.bundle)
        if p.folder is not None and not p.cached:
            entry["prepare_seconds"] = json.loads((p.folder / "meta.json").read_text()).get("seconds")
        scans.append(entry)
    with atomic_output(path) as tmp:
        tmp.write_text(json_text({"engine": engine, "workers": workers, "seconds": round(seconds, 3), "scans": scans}))


def verdict_counts(results: list[PhotoResult]) -> str:
    """'2 ok, 1 suspect, 0 failed' (photos whose steps failed before a verdict count as failed)."""
    from rgbd_gt.align.verify import VERDICTS

    n = {v: sum((r.verdict or "failed") == v for r in results) for v in VERDICTS}
    return ", ".join(f"{n[v]} {v}" for v in VERDICTS)
