"""The workflow's steps, each written once: the commands (`cli.py`) and `run` (`workflow.py`)
call these, so that a file of one name holds one content whoever wrote it.

Each step takes plain data (arrays, `Camera`, 4x4 poses, `Scan`) and returns plain data; the
callers read files, choose what to write and print. A step raises `InputError` naming the pose
file (when given) for what makes its output meaningless (no scan in view).

    open_photo    photo + camera (+ mask), checked against each other
    init_step     the initial pose: a board (found in the photo and the scan) or picked pairs
    load_inputs   what refine works on: the photo, the init and the scan in view of it
    refine_step   the aligner, the verdict and the verticals check -> the pose file's keys
    depth_step    the depth map (surfaces or points), and write_depth for its files
    qa_step       structural, Canny, verticals (and a sweep's ring-edge) scores, and a before pose -> qa.png, qa.json
    overlay_step  checkerboard, blend and points pictures
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError

PathLike = str | os.PathLike


def finite(step: str, what: str, values) -> None:
    """InputError naming the step unless every number of `values` (an array) is finite: a NaN or
    inf that would reach an output is said, not written."""
    bad = int(np.size(values) - np.isfinite(values).sum())
    if bad:
        raise InputError(f"{step}: {what} holds {bad} NaN or inf value(s); nothing was written")


@dataclass
class Photo:
    """A photo (H, W, 3) uint8 RGB with its camera, checked to match; `ignore` (H, W) bool: pixels
    to leave out (a mask), or None."""

    image: np.ndarray
    camera: Camera
    ignore: np.ndarray | None = None


def open_photo(image: PathLike, camera: PathLike | Camera, mask: PathLike | None = None,
               to_align: bool = False, camera_path: PathLike | None = None) -> Photo:
    """Read the photo and its camera (a camera file without an image size takes the photo's) and
    check that they match; `mask`: a mask image of the photo's size. `to_align`: a photo of one
    value is an error (nothing to align a scan to). camera_path: the file a `Camera` given was
    read from, for the messages."""
    from rgbd_gt.io import read_camera
    from rgbd_gt.io.camera_file import check_image_matches
    from rgbd_gt.io.image import read_image, read_mask

    photo = read_image(image, to_align=to_align)
    cam = camera if isinstance(camera, Camera) else read_camera(camera, (photo.shape[1], photo.shape[0]), image)
    check_image_matches(cam, photo.shape, image, camera_path if isinstance(camera, Camera) else camera)
    ignore = read_mask(mask, photo.shape[:2]) if mask is not None else None
    return Photo(photo, cam, ignore)


def load_inputs(scan_path: PathLike, image_path: PathLike, camera_path: PathLike, init_path: PathLike,
                mask_path: PathLike | None = None, cache: PathLike | None = None, prepared=None):
    """The refine step's inputs (`align.refine.RefineInputs`): the photo and its camera
    (`open_photo`), the init, and the scan's points in view of the init and around its camera,
    from `prepared` (`prepared.PreparedScan`, of several photos of one scan) or the scan
    prepared under `cache` when given, else from the file."""
    from rgbd_gt.align.refine import RefineInputs
    from rgbd_gt.io import read_pose
    from rgbd_gt.pose import camera_centre
    from rgbd_gt.prepared import prepare_scan
    from rgbd_gt.qa.verticals import MAX_POINTS, REACH
    from rgbd_gt.render.renders import Renders
    from rgbd_gt.scan import scan_colors

    opened = open_photo(image_path, camera_path, mask_path, to_align=True)
    photo, camera, ignore = opened.image, opened.camera, opened.ignore
    T_init, init_meta = read_pose(init_path)
    # what the photo can see from poses around T_init (its normals made on the whole scan when it
    # was prepared): the renders then cost what the photo sees. The view `run` takes
    # (render.blocks.VIEW_MARGIN), of the same prepared arrays: both hand the aligner the same
    # points and get the same pose.
    prepared = prepared or prepare_scan(Path(scan_path), cache)
    scan, around = prepared.views(camera, [T_init]), prepared.xyz_around(camera_centre(T_init), REACH, MAX_POINTS)
    if len(scan) == 0:
        raise InputError("no scan points in view of the initial pose (nor near it): check the pose, the camera file "
                         "and the scan", init_path)
    colors = scan_colors(scan, scan_path, to_align=True)
    return RefineInputs(scan.xyz, colors, photo, camera, T_init, ignore, scan, init_meta, around,
                        Renders(scan, colors, [T_init]))


def board_in_prepared(prepared, spec, corners: np.ndarray | None = None):
    """The board (`init.run.BoardInScan`, of `init.detect.BoardSpec` spec) in the prepared scan
    (`prepared.PreparedScan`): its given corners (k, 3) with the scan points around them, or
    found in the scan's virtual views (kept beside a cached scan: searched once per scan)."""
    from rgbd_gt.init.run import board_in_scan

    if corners is None:
        return prepared.board(spec, prepared.source)
    pad = 2 * spec.square + 0.02
    return board_in_scan(prepared.near(corners.min(0) - pad, corners.max(0) + pad), spec, corners, prepared.source)


def init_step(prepared, photo: Photo, image_path: PathLike, spec=None, corners: np.ndarray | None = None,
              correspondences: PathLike | None = None, estimate_focal: bool = False, ransac_px: float = 4.0):
    """The photo's initial pose (`init.run.InitResult`) in the prepared scan: from the board of
    `spec` (`init.detect.BoardSpec`) found in the photo and in the scan (or at its given corners
    (k, 3)), or from the pairs picked in the CSV file `correspondences` (u,v,x,y,z[,label];
    RANSAC PnP, with estimate_focal the focal length too). Returns (result, the verticals check
    of the result for picks, which take no part in it, else None)."""
    from rgbd_gt.init.run import detect_photo_board, init_from_board, init_from_correspondences, read_correspondences

    if correspondences is None:
        found = detect_photo_board(photo.image, spec, image_path)
        return init_from_board(board_in_prepared(prepared, spec, corners), photo.image, photo.camera, spec, found), None
    from rgbd_gt.init.pnp import check_spread
    from rgbd_gt.init.run import check_picks
    from rgbd_gt.qa.verticals import verticals_qa

    picks = read_correspondences(Path(correspondences))
    check_picks(picks, photo.camera, prepared.bounds(), correspondences, prepared.origins)
    check_spread(picks.obj, picks.img, str(correspondences), 6)  # named after the file
    result = init_from_correspondences(picks, photo.camera, estimate_focal, ransac_px)
    # a check the picks do not take part in: a few pairs hardly check each other
    return result, verticals_qa(prepared.whole().xyz, photo.image, result.camera, [result.T_cam_from_scan])[0]


def made_from(scan: PathLike, scan_sha1: str | None, files: dict[str, PathLike],
              board: tuple | None = None) -> dict:
    """The path and SHA-1 of the scan (scan_sha1, or read from the file when None) and of each of
    `files` ({kind: path}) that a pose file is made from, recorded beside the pose so that a rerun
    with other inputs is told apart; with board (cols, rows, square, charuco, marker) its layout,
    whose text stands for a file's content."""
    import hashlib

    from rgbd_gt.prepared import file_key

    made = {"scan": str(scan), "scan_sha1": scan_sha1 or file_key(Path(scan))["sha1"]}
    for kind, path in files.items():
        made |= {kind: str(path), f"{kind}_sha1": file_key(Path(path))["sha1"]}
    if board is not None:
        cols, rows, square, charuco, marker = board
        made["board"] = f"{cols}x{rows} inner corners, square {square} m" + (f", {charuco} markers {marker} m" if charuco else "")
        made["board_sha1"] = hashlib.sha1(made["board"].encode()).hexdigest()
    return made


def made_from_other(recorded: dict, made: dict) -> str | None:
    """The first kind of input whose SHA-1 in `recorded` differs from `made`'s (`made_from`), or
    None. No SHA-1 recorded is no difference: outputs written before they were are resumed."""
    return next((k.removesuffix("_sha1") for k in made if k.endswith("_sha1") and recorded.get(k) not in (None, made[k])), None)


def refine_config(config: PathLike | None = None, repeats: int | None = None, **flags):
    """The aligner's settings: configs/refine.yaml (or `config`) with the options given (None:
    as the file says); InputError naming them when they make it inconsistent."""
    import dataclasses

    from rgbd_gt.align.config import RefineConfig
    from rgbd_gt.config import load_config

    cfg = load_config(RefineConfig, config, "refine.yaml")
    cfg = dataclasses.replace(cfg, **{k: v for k, v in flags.items() if v is not None})
    if flags.get("optimizer") == "adam" and flags.get("iterations") is not None:
        cfg = dataclasses.replace(cfg, adam_iterations=flags["iterations"])
    if repeats is not None:
        cfg = dataclasses.replace(cfg, verify=dataclasses.replace(cfg.verify, repeats=repeats))
    try:
        cfg.check()
    except ValueError as exc:  # the config file was checked as it was read: an option made it wrong
        options = ", ".join(f"--{k.replace('_', '-')} {v}" for k, v in {**flags, "repeats": repeats}.items() if v is not None)
        raise InputError(f"{exc} (options given: {options})") from None
    return cfg


@dataclass
class Refined:
    """A refined pose and what the pose file records of it: `meta` (verdict, reasons, evidence,
    the aligner's figures, the verticals check of the result and the init, warnings); `camera`:
    the camera the pose goes with (refined when the intrinsics were)."""

    result: object  # align.aligner.RefineResult
    verification: object  # align.verify.Verification
    camera: Camera
    meta: dict
    verticals: object  # qa.verticals.VerticalsScore of the result
    init_verticals: object  # ... and of the init
    warnings: list[str] = field(default_factory=list)

    @property
    def T(self) -> np.ndarray:
        return self.result.T_cam_from_scan


def refine_step(inputs, cfg, init_path: PathLike, device: str = "auto", camera_path: PathLike | None = None,
                progress: Callable[[dict], None] | None = None, keep_residuals: bool = False,
                check: tuple[np.ndarray, np.ndarray] | None = None, more: list = ()) -> Refined:
    """Refine inputs.T_init (`align.refine.RefineInputs`), judge the result and measure it and
    the init against the scan's vertical (around: inputs.around). check: held-out pairs (img (n, 2)
    px, scan points (n, 3)); more: further pairs that share the pose (solved jointly)."""
    from rgbd_gt.align.refine import refine_verified

    result, verification = refine_verified(inputs, cfg, device, progress, keep_residuals=keep_residuals, check=check,
                                           more=more)
    return judged(inputs, result, verification, cfg, init_path, camera_path, pairs=1 + len(more))


def judged(inputs, result, verification, cfg, init_path: PathLike, camera_path: PathLike | None = None,
           pairs: int = 1) -> Refined:
    """A result (`align.aligner.RefineResult`) of inputs.T_init with its verdict as the pose
    file holds it: the camera it goes with, the aligner's figures, the verticals check of the
    result and the init, a warning when init-pose estimated another focal length or when one
    sweep is solved alone (refine_step's and bundle_step's)."""
    from rgbd_gt.align.refine import camera_disagreement, refine_meta, refined_camera
    from rgbd_gt.qa.verticals import verticals_qa

    warnings = [w for w in [camera_disagreement(inputs.camera, inputs.init_meta, camera_path or "camera")] if w]
    if pairs == 1 and inputs.scan is not None and inputs.scan.edge is not None:  # a sweep (its rings' steps are known)
        warnings.append("one sweep fixes a LiDAR-camera pose poorly (KITTI single frames from 1 deg end degrees off: "
                        "docs/lidar.md); solve the drive's frames together with --pairs")
    camera = refined_camera(inputs.camera, result)
    finite("refine", "the refined pose", result.T_cam_from_scan)
    finite("refine", "the refined camera", np.r_[camera.K.ravel(), camera.distortion])
    meta = refine_meta(result, cfg, inputs.T_init, init_path, verification, pairs=pairs, camera=inputs.camera)
    # geometry alone, outside the verdict (one of six parameters): the one check a sweep's pose has
    upright, upright_init = verticals_qa(inputs.around, inputs.photo, camera, [result.T_cam_from_scan, inputs.T_init])
    meta |= upright.as_dict() | upright_init.as_dict("init_")
    if warnings:
        meta["warnings"] = warnings
    return Refined(result, verification, camera, meta, upright, upright_init, warnings)


def renders_of(view):
    """`view` (a `Scan`, or its `render.renders.Renders`) as Renders: the steps of one photo that
    share them render each camera and pose once."""
    from rgbd_gt.render.renders import Renders

    return view if isinstance(view, Renders) else Renders(view)


def depth_step(view, camera: Camera, T: np.ndarray, max_depth: float | None = None, points: bool | None = None,
               normals: bool = False, pose_path: PathLike | None = None):
    """The depth map (`render.depth.DepthMap`) of the view (`renders_of`) at T: of its points
    alone (sparse) or of the surfaces rendered from them; points=None chooses points for LiDAR
    sweeps (`render.points.as_points`). An empty map is an error naming the pose."""
    from rgbd_gt.render.depth import point_depth
    from rgbd_gt.render.points import as_points

    renders = renders_of(view)
    if as_points(renders.scan, points):
        depth = point_depth(renders.scan, camera, T, max_depth, normals, renders.seen(camera, T, max_depth))
    else:
        depth = renders.surfaces(camera, T, max_depth, normals=normals)
    finite("depth", "the depth map", depth.z)
    if not (depth.z > 0).any():
        if depth.back_facing:
            raise InputError("the camera sees only the back of the scan's surfaces at this pose: the depth map "
                             "would be empty", pose_path)
        raise InputError("no scan points in view of this pose: the depth map would be empty", pose_path)
    return depth


def write_depth(depth, camera: Camera, T: np.ndarray, scan_name: str, exr: PathLike, png16: PathLike | None = None,
                normals: PathLike | None = None, mask: PathLike | None = None) -> None:
    """The depth map's files: EXR (z, metres, with the camera, pose, scan name and the fraction
    seen from behind in its header), and optionally a 16-bit PNG in millimetres, the normals as
    EXR and a validity mask PNG (255 where there is depth)."""
    from rgbd_gt.io.depth_file import write_depth_exr, write_depth_png16
    from rgbd_gt.io.image import write_image
    from rgbd_gt.render.depth import back_facing_fraction

    behind = back_facing_fraction(depth)
    write_depth_exr(exr, depth.z, camera, T, scan_name, seen_from_behind=behind)
    if png16 is not None:
        write_depth_png16(png16, depth.z)
    if normals is not None:
        write_depth_exr(normals, depth.z, camera, T, scan_name, normals=depth.normals, seen_from_behind=behind)
    if mask is not None:
        write_image(mask, (depth.z > 0).astype(np.uint8) * 255)


@dataclass
class QA:
    """qa_step's result: the picture (H, W, 3) uint8 (before | after when a before pose was given),
    the scores as qa.json holds them, and a line per pose for the user."""

    image: np.ndarray
    scores: dict
    rows: list[tuple[str, str]]


def qa_step(view, photo: np.ndarray, camera: Camera, T: np.ndarray, around: np.ndarray,
            T_before: np.ndarray | None = None, pose_path: PathLike | None = None,
            before_path: PathLike | None = None) -> QA:
    """How well the view (`renders_of`, with the scan's colors) rendered at T lines up with the
    photo: the structural edges against chance, the Canny distances (`qa.edges`), the verticals
    check (`qa.verticals`, on `around`: (n, 3) scan points around the camera) and, for a sweep,
    its depth steps along the rings against chance (`qa.edges.ring_edge_check`); the same for
    T_before with keys prefixed before_. A pose that sees no scan edge is an error naming it."""
    from rgbd_gt.align.edge_map import CHECK_MIN_STEP_M
    from rgbd_gt.qa.edges import qa, ring_edge_check, side_by_side, structural_qa, working_view
    from rgbd_gt.qa.verticals import verticals_qa

    renders = renders_of(view)
    poses = [(T, pose_path, "")] + ([(T_before, before_path, "before_")] if T_before is not None else [])
    uprights = verticals_qa(around, photo, camera, [p[0] for p in poses])
    # a sweep's: its rendering is too sparse for the other scores
    ring_scores = ring_edge_check(renders.scan, photo, camera, [p[0] for p in poses]) or [None] * len(poses)
    images, scores, rows = [], {}, []
    for (pose, path, prefix), upright, rings in zip(poses, uprights, ring_scores):
        view = working_view(renders, photo, camera, pose)
        _, canny = qa(view, camera)
        if canny.scan_edge_pixels == 0:
            raise InputError("no scan edges in view of this pose (no scan points in view?)", path)
        img, structural = structural_qa(view)
        images.append(img)
        scores |= structural.as_dict(prefix) | canny.as_dict(prefix) | upright.as_dict(prefix)
        if rings is not None:
            scores |= {prefix + key: value for key, value in rings.items()}
        ring_text = "" if rings is None else (f"; ring edges {rings['ring_edge_ratio']:.2f} x chance over "
                                              f"{rings['ring_edges']:,} depth steps" if rings["ring_edges"] else
                                              f"; ring edges: no depth steps of {CHECK_MIN_STEP_M:g} m or more in view")
        rows.append((prefix.rstrip("_") or ("after" if T_before is not None else "score"),
                     f"{structural.summary()}; Canny {canny.summary()}; verticals {upright.summary()}{ring_text}"))
    if T_before is not None:
        return QA(side_by_side(images[1], images[0]), scores, rows[::-1])
    return QA(images[0], scores, rows)


@dataclass
class Overlay:
    """overlay_step's pictures (H, W, 3) uint8 at the photo's resolution: `checker`, `blend` and,
    for sweeps or when asked, `points` (None otherwise); the fraction of the photo the scan
    covers and the points drawn."""

    checker: np.ndarray
    blend: np.ndarray
    points: np.ndarray | None
    covered: float
    drawn: int = 0


def overlay_step(view, photo: np.ndarray, camera: Camera, T: np.ndarray, max_depth: float | None = None,
                 points: bool | None = None, pose_path: PathLike | None = None) -> Overlay:
    """The view (`renders_of`, with the scan's colors) rendered at T over the photo; points=None
    draws the points picture for LiDAR sweeps (`render.points.as_points`). Nothing of the scan in
    view is an error naming the pose."""
    from rgbd_gt.qa.overlay import overlay, points_image
    from rgbd_gt.render.points import as_points

    renders = renders_of(view)
    checker, mixed, covered = overlay(renders, photo, camera, T, max_depth)
    if covered == 0:
        raise InputError("no scan surface in view of this pose (or only surfaces seen from behind)", pose_path)
    if not as_points(renders.scan, points):
        return Overlay(checker, mixed, None, covered)
    dots, drawn = points_image(renders, photo, camera, T, max_depth)
    return Overlay(checker, mixed, dots, covered, drawn)


def overlay_paths(output: Path) -> dict[str, Path]:
    """Where the overlay's pictures go: OVERLAY.png, OVERLAY_blend.png, OVERLAY_points.png."""
    return {"checker": output, **{k: output.with_name(f"{output.stem}_{k}{output.suffix}") for k in ("blend", "points")}}


@dataclass
class Bundled:
    """bundle_step's result: per photo its `Refined` (pose file keys with the cross-photo
    evidence), per camera name the camera and the file's keys with each refined value's 1-sigma,
    and for a rig rig.yaml's keys (None without one)."""

    photos: list[Refined]
    cameras: dict[str, tuple[Camera, dict]]
    rig: dict | None
    result: object  # align.bundle.BundleResult
    scan_sha1: str  # of the scan file as it was prepared (bundle.json's)


def bundle_step(spec, cfg, device: str = "auto", cache: PathLike | None = None,
                progress: Callable[[str], None] = lambda message: None) -> Bundled:
    """Refine every photo of `spec` (`io.bundle_file.BundleSpec`) in one solve
    (`align.bundle.Bundle`: the poses, each camera's free corrections, the rig), then judge each
    photo: its own verdict (as refine_step's, with its camera as solved) and the cross-photo
    evidence (`align.verify.bundle_reasons`)."""
    import dataclasses

    from rgbd_gt.align.aligner import Aligner, RefineResult
    from rgbd_gt.align.bundle import Bundle, BundlePhoto, RigPrior
    from rgbd_gt.align.refine import make_aligner, objective_of, refined_camera
    from rgbd_gt.align.verify import bundle_reasons, verify
    from rgbd_gt.io import read_pose
    from rgbd_gt.prepared import file_key, prepare_scan

    progress("reading the scan")
    prepared = prepare_scan(Path(spec.scan), cache)
    names = list(spec.cameras)
    order = spec.rig + [n for n in names if n not in spec.rig]  # rig cameras first: their index is their place in the rig
    inputs, photos = [], []
    for k, entry in enumerate(spec.photos):
        progress(f"{entry.image.name}: reading")
        inp = load_inputs(spec.scan, entry.image, spec.cameras[entry.camera].file, entry.init, entry.mask, cache, prepared)
        mode = spec.cameras[entry.camera].refine
        if objective_of(cfg, inp.colors) != "photometric" and mode != "none":
            raise InputError(f"the bundle's cameras.{entry.camera}.refine: {mode} needs the photometric objective (a "
                             "colored scan); with nid (intensity only) the camera files are held", spec.scan)
        mode_cfg = dataclasses.replace(cfg, refine_intrinsics=mode)
        photos.append(BundlePhoto(make_aligner(inp, mode_cfg, device).objective, inp.T_init, order.index(entry.camera),
                                  entry.shot, entry.image.name))
        inputs.append(inp)
    for k, entry in enumerate(spec.photos):  # one camera file per name: its photos must agree on its size
        first = next(i for i, e in enumerate(spec.photos) if e.camera == entry.camera)
        if inputs[k].camera != inputs[first].camera:
            raise InputError(f"camera {entry.camera}: {entry.image.name} and {spec.photos[first].image.name} read it "
                             "differently (a file without an image size, photos of two sizes?)")
    priors = {order.index(name): RigPrior(read_pose(p.pose)[0], np.radians(p.sigma_rotation_deg), p.sigma_translation_mm / 1e3)
              for name, p in spec.priors.items()}
    progress(f"solving {len(photos)} photos together")
    result = Bundle(photos, len(order), len(spec.rig), priors).solve()
    out = []
    for k, (entry, inp, photo) in enumerate(zip(spec.photos, inputs, photos)):
        progress(f"{entry.image.name}: verdict")
        c, obj = photo.camera, photo.objective
        refined = RefineResult(T_cam_from_scan=result.poses[k], iterations=result.iterations, seconds=result.seconds / len(photos),
                               levels=result.levels, covariance=result.pose_covariance[k], objective=obj.name,
                               tiles=result.tiles[k] if result.tiles else None,
                               intrinsics=result.q[c] if obj.free else None,
                               intrinsics_sigma=result.q_sigma[c] if obj.free else None, **obj.summary(result.terms[k]))
        finite("refine", "the refined pose", refined.T_cam_from_scan)  # before the verdict works on it
        verification = verify(Aligner(obj), refined, inp.T_init, refined_camera(inp.camera, refined), inp.photo,
                              inp.the_renders(), cfg.verify, cfg.seed, inp.init_meta, shared_camera=True)
        ev = result.evidence[k] | {"photos": len(photos), "camera": entry.camera} | ({"shot": entry.shot} if entry.shot is not None else {})
        verification.evidence["bundle"] = ev
        extra = bundle_reasons(ev, cfg.verify)
        if extra and verification.verdict == "ok":
            verification.verdict = "suspect"
        verification.reasons += extra
        out.append(judged(inp, refined, verification, obj.cfg, entry.init, spec.cameras[entry.camera].file))
    cameras = {}
    for name in names:
        c = order.index(name)
        k = next(i for i, e in enumerate(spec.photos) if e.camera == name)
        qs = result.stated_q_sigma(c)
        sigma = {"focal_px": qs[0] * inputs[k].camera.fx, "cx_px": qs[1] * inputs[k].camera.fx, "cy_px": qs[2] * inputs[k].camera.fy,
                 **{coef: qs[3 + j] for j, coef in enumerate(("k1", "k2", "p1", "p2", "k3"))}}
        keys = {"refined": spec.cameras[name].refine, "photos": sum(e.camera == name for e in spec.photos),
                "sigma": {key: float(v) for key, v in sigma.items() if np.isfinite(v)}}
        cameras[name] = (out[k].camera, keys)
    rig = None
    if spec.rig:
        from rgbd_gt.pose import invert

        rig = {"cameras": spec.rig, "reference": spec.rig[0], "relative": {}}
        for name in spec.rig[1:]:
            c = order.index(name)
            sd = np.sqrt(np.diag(result.stated_rig_covariance(c)))
            rig["relative"][name] = {
                "T_cam_from_reference": result.rig[c].tolist(), "baseline_m": float(np.linalg.norm(invert(result.rig[c])[:3, 3])),
                "sigma": {"rotation_deg": np.degrees(sd[:3]).tolist(), "translation_mm": (sd[3:] * 1e3).tolist()}}
    # a scan prepared in memory (no cache) was not hashed
    return Bundled(out, cameras, rig, result, prepared.sha1 or file_key(Path(spec.scan))["sha1"])


def write_bundled(folder: Path, spec, done: Bundled, bundle: Path, total_seconds: float) -> None:
    """bundle_step's files in `folder` (docs/bundle.md), as `refine --bundle` and `run` with a
    bundle write them: PHOTO/pose.yaml per photo, cameras/NAME.yaml, rig.yaml for a rig, and
    last bundle.json (the bundle file, with its SHA-1, and each photo's verdict and cross-photo
    evidence), whose presence says the others are all there."""
    import yaml

    from rgbd_gt.io import write_pose
    from rgbd_gt.io.atomic import atomic_output
    from rgbd_gt.io.camera_file import write_camera
    from rgbd_gt.io.json_text import json_text
    from rgbd_gt.prepared import file_key

    for entry, refined in zip(spec.photos, done.photos):
        (folder / entry.image.stem).mkdir(parents=True, exist_ok=True)
        write_pose(folder / entry.image.stem / "pose.yaml", refined.T, **refined.meta)
    (folder / "cameras").mkdir(exist_ok=True)
    for name, (camera, keys) in done.cameras.items():
        write_camera(folder / "cameras" / f"{name}.yaml", camera, **keys)
    if done.rig is not None:
        with atomic_output(folder / "rig.yaml") as tmp:
            tmp.write_text(yaml.safe_dump(done.rig, sort_keys=False, default_flow_style=None))
    r = done.result
    summary = {"bundle": str(Path(bundle).resolve()), "bundle_sha1": file_key(Path(bundle))["sha1"],
               "scan_sha1": done.scan_sha1, "photos": [
        {"image": str(e.image), "photo_sha1": file_key(e.image)["sha1"], "pose": f"{e.image.stem}/pose.yaml",
         "camera": e.camera, "shot": e.shot,
         "verdict": d.verification.verdict, "reasons": d.verification.reasons, **d.verification.evidence["bundle"]}
        for e, d in zip(spec.photos, done.photos)], "iterations": r.iterations, "levels": r.levels,
        "seconds": round(r.seconds, 3), "total_seconds": round(total_seconds, 3)}
    with atomic_output(folder / "bundle.json") as tmp:
        tmp.write_text(json_text(summary))
