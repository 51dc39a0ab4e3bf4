"""`rgbd-gt synth`: build a scene, take the photo and the scan, write every file with the truth."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from rgbd_gt.camera import Camera, lens_reach, project
from rgbd_gt.config import require
from rgbd_gt.errors import InputError
from rgbd_gt.io import atomic_output, save_scan, write_camera, write_pose
from rgbd_gt.scan import Scan
from rgbd_gt.io.e57 import write_e57
from rgbd_gt.io.image import write_image
from rgbd_gt.pose import rigid, transform_points
from rgbd_gt.synth import color
from rgbd_gt.synth.scene import Scene, make_layout
from rgbd_gt.synth.sensors import (ScanGrid, blur_over_grid, build_raycaster, cast, grid_covering, laser_scan,
                                   render_photo_radiance)
from rgbd_gt.synth.textures import make_texture

FILES = ("scan.e57", "scan.ply", "photo.png", "camera.yaml", "gt_pose.yaml", "init_pose.yaml", "board_corners.csv", "scene.json")


@dataclass
class SizePreset:
    width: int = 1280
    height: int = 960
    scan_step_deg: float = 0.1
    texture_px: int = 1024
    supersample: int = 3
    # [horizontal, vertical] degrees the scan covers, centred on what the cameras see, level
    # (a FARO-like dome); None: only what the cameras see plus scan_margin_deg
    scan_fov_deg: list[float] | None = None


@dataclass
class SynthConfig:
    """Scene generation settings (configs/synth.yaml)."""

    sizes: dict[str, SizePreset] = field(
        default_factory=lambda: {"default": SizePreset(), "small": SizePreset(640, 480, 0.15, 512, 3)}
    )
    board_cols: int = 9
    board_rows: int = 6
    square_m: float = 0.05
    hfov_deg: list[float] = field(default_factory=lambda: [55.0, 70.0])
    board_distance_m: list[float] = field(default_factory=lambda: [1.8, 2.6])
    scanner_distance_m: list[float] = field(default_factory=lambda: [1.0, 2.0])
    range_noise_m: float = 0.001
    # the scan's colors blurred over the scanner's own grid by a Gaussian of this many cells, across
    # depth edges, as the scanner's camera mixes them at its silhouettes (0: each return the color
    # of its own surface; docs/bundle.md measures both)
    scanner_color_blur_cells: float = 0.0
    texel_m: float = 0.0015
    scan_margin_deg: float = 3.0
    init_translation_m: list[float] = field(default_factory=lambda: [0.02, 0.04])
    init_rotation_deg: list[float] = field(default_factory=lambda: [0.7, 1.2])
    max_layout_tries: int = 40

    def check(self) -> "SynthConfig":
        for name, p in self.sizes.items():
            at = f"sizes.{name}."
            require(32 <= p.width <= 8192, at + "width", "32..8192", p.width)
            require(32 <= p.height <= 8192, at + "height", "32..8192", p.height)
            require(0.01 <= p.scan_step_deg <= 5, at + "scan_step_deg", "0.01..5", p.scan_step_deg)
            require(16 <= p.texture_px <= 8192, at + "texture_px", "16..8192", p.texture_px)
            require(1 <= p.supersample <= 8, at + "supersample", "1..8", p.supersample)
            fov = p.scan_fov_deg
            require(fov is None or (len(fov) == 2 and 1 <= fov[0] <= 360 and 1 <= fov[1] <= 180), at + "scan_fov_deg",
                    "[horizontal 1..360, vertical 1..180]", fov)
        for name in ("hfov_deg", "board_distance_m", "scanner_distance_m", "init_translation_m", "init_rotation_deg"):
            lo_hi = getattr(self, name)
            require(len(lo_hi) == 2 and 0 <= lo_hi[0] <= lo_hi[1], name, "[low, high] with 0 <= low <= high", lo_hi)
        require(1 <= self.hfov_deg[0] and self.hfov_deg[1] < 170, "hfov_deg", "within 1..170", self.hfov_deg)
        # the rooms are 5-7.5 m across: a scanner farther from the camera stood outside its walls
        for name in ("board_distance_m", "scanner_distance_m"):
            require(getattr(self, name)[1] <= 5, name, "within 0..5 m (the rooms are 5-7.5 m across)", getattr(self, name))
        # the board must fit in the photo from 1.8-2.6 m (the generator tries layouts until it does)
        require(2 <= self.board_cols <= 50, "board_cols", "2..50", self.board_cols)
        require(2 <= self.board_rows <= 50, "board_rows", "2..50", self.board_rows)
        require(0 < self.square_m <= 0.5, "square_m", "in (0, 0.5]", self.square_m)
        require(self.texel_m > 0, "texel_m", "positive", self.texel_m)
        require(self.range_noise_m >= 0, "range_noise_m", "0 or more", self.range_noise_m)
        # a margin past 90 deg on every side adds nothing a scanner sees but grid rows and columns
        # (1e12 deg asked for a grid no memory holds)
        require(0 <= self.scan_margin_deg <= 90, "scan_margin_deg", "0..90", self.scan_margin_deg)
        require(self.max_layout_tries >= 1, "max_layout_tries", "at least 1", self.max_layout_tries)
        require(0 <= self.scanner_color_blur_cells <= 10, "scanner_color_blur_cells", "0..10", self.scanner_color_blur_cells)
        return self


def random_camera(rng: np.random.Generator, preset: SizePreset, hfov_deg: list[float]) -> Camera:
    w, h = preset.width, preset.height
    f = w / 2 / np.tan(np.deg2rad(rng.uniform(*hfov_deg)) / 2)
    dist = (rng.uniform(-0.15, -0.03), rng.uniform(-0.02, 0.06), rng.uniform(-8e-4, 8e-4), rng.uniform(-8e-4, 8e-4), 0.0)
    cam = Camera(w, h, float(f), float(f * rng.uniform(0.998, 1.002)), float((w - 1) / 2 + rng.normal(0, 0.01 * w)),
                 float((h - 1) / 2 + rng.normal(0, 0.01 * h)), tuple(float(d) for d in dist))
    while lens_reach(cam)[0] < lens_reach(cam)[1]:  # a wide field: weaker radial terms, so that the lens covers it
        cam = dataclasses.replace(cam, distortion=(cam.distortion[0] / 2, cam.distortion[1] / 2) + cam.distortion[2:])
    return cam


def _board_visible(scene: Scene, rc, camera: Camera) -> bool:
    """Every board corner is in the photo (with a margin) and seen, unoccluded, by both sensors."""
    corners = scene.board.corners()
    lo, hi = scene.board.outline_local()
    lo, hi = lo + 0.003, hi - 0.003  # a hair inside, so that rays aimed at the edge hit it
    outline = np.array([[lo[0], lo[1], 0], [hi[0], lo[1], 0], [lo[0], hi[1], 0], [hi[0], hi[1], 0]])
    pts = np.concatenate([corners, transform_points(scene.board.pose, outline)])
    cam_T = np.linalg.inv(scene.camera_pose)
    uv, z = project(camera, transform_points(cam_T, pts))
    m = 0.04 * camera.width
    if not (np.all(z > 0) and np.all(uv > m) and np.all(uv < [camera.width - m, camera.height - m])):
        return False
    if np.ptp(uv[:, 0]) < 0.15 * camera.width:
        return False
    board_id = next(k for k, s in enumerate(scene.surfaces) if s.name == "board")
    for eye in (scene.camera_pose[:3, 3], scene.scanner_pose[:3, 3]):
        d = pts - eye
        dist = np.linalg.norm(d, axis=1)
        t, gid, _ = cast(rc, eye, d / dist[:, None])
        if np.any(gid != board_id) or np.any(np.abs(t - dist) > 0.01):
            return False
    return True


def perturb_pose(T: np.ndarray, rng: np.random.Generator, trans_m: list[float], rot_deg: list[float]) -> np.ndarray:
    """T (4x4) moved by a random translation and rotation of the given magnitude ranges
    (applied in the camera frame)."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(axis * np.deg2rad(rng.uniform(*rot_deg)))
    tdir = rng.normal(size=3)
    tdir /= np.linalg.norm(tdir)
    return rigid(R, tdir * rng.uniform(*trans_m)) @ T


def dome_grid(covering: ScanGrid, step: float, fov: np.ndarray) -> ScanGrid:
    """A grid of `fov` (horizontal, vertical) radians, level, centred on `covering`'s azimuths."""
    cols, rows = int(round(fov[0] / step)), int(round(fov[1] / step))
    az_centre = covering.az0 + (covering.cols - 1) * covering.step / 2
    return ScanGrid(az_centre - (cols - 1) * step / 2, (rows - 1) * step / 2, step, cols, rows)


def extra_cameras(scene: Scene, rc, camera: Camera, count: int, rng: np.random.Generator) -> list[np.ndarray]:
    """`count` more world_from_camera poses near the first (0.15-0.4 m away, looking at the board
    from a slightly different direction), each seeing the whole board."""
    from rgbd_gt.synth.scene import look_at

    base = scene.camera_pose
    target = scene.board.corners().mean(axis=0)
    poses = []
    for _ in range(60 * max(count, 1)):
        if len(poses) == count:
            break
        offset = base[:3, :3] @ np.array([rng.uniform(-1, 1), rng.uniform(-0.3, 0.3), rng.uniform(-0.5, 0.3)])
        offset *= rng.uniform(0.15, 0.4) / np.linalg.norm(offset)
        pose = look_at(base[:3, 3] + offset, target + rng.uniform(-0.25, 0.25, 3), np.deg2rad(rng.uniform(-4, 4)))
        trial = dataclasses.replace(scene, camera_pose=pose)
        if _board_visible(trial, rc, camera):
            poses.append(pose)
    if len(poses) < count:
        raise InputError(f"could place only {len(poses) + 1} cameras that see the board")
    return poses


def _seen_points(rc, camera: Camera, pose: np.ndarray) -> np.ndarray:
    """World points hit by a coarse grid of the camera's rays (what it sees)."""
    from rgbd_gt.camera import undistort_points

    v, u = np.mgrid[0 : camera.height : complex(0, 31), 0 : camera.width : complex(0, 41)]
    xn = undistort_points(camera, np.stack([u.ravel(), v.ravel()], 1))
    d = np.concatenate([xn, np.ones((xn.shape[0], 1))], 1) @ pose[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, _, _ = cast(rc, pose[:3, 3], d)
    return pose[:3, 3] + t[np.isfinite(t), None] * d[np.isfinite(t)]


RIGS = ("stereo",)


def stereo_rig(rng: np.random.Generator, baseline_m: float) -> np.ndarray:
    """T_right_from_left (4x4) of a stereo rig: the right camera `baseline_m` along the left's x
    axis, turned by a few tenths of a degree (as a real rig's cameras are)."""
    from rgbd_gt.pose import so3_exp

    R = so3_exp(np.deg2rad(rng.normal(0, 0.3, 3)))
    return rigid(R, -R @ np.array([baseline_m, 0.0, 0.0]))


def bundle_file(photos: list[dict], cameras: dict[str, str], rig: list[str] | None) -> str:
    """The text of a `refine --bundle` file (docs/bundle.md) of the scene's photos."""
    import yaml

    doc = {"scan": "scan.ply", "cameras": {name: {"file": f, "refine": "none"} for name, f in cameras.items()}}
    if rig:
        doc["rig"] = {"cameras": rig}
    doc["photos"] = photos
    return "# rgbd-gt refine --bundle bundle.yaml -o OUT: the scene's photos, solved together (docs/bundle.md)\n" + \
        yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)


def laid_out(rng: np.random.Generator, preset: SizePreset, cfg: SynthConfig, seed: int,
             pinhole: bool = False) -> tuple[Scene, object, Camera, int]:
    """A random room (`make_layout`, untextured) whose board the random camera sees from the
    scene's camera pose, its raycaster, that camera (pinhole: without the lens's distortion) and
    how many layouts were drawn until one did."""
    for attempt in range(cfg.max_layout_tries):
        layout = make_layout(rng, (cfg.board_cols, cfg.board_rows), cfg.square_m, cfg.board_distance_m,
                             cfg.scanner_distance_m, float(np.mean(cfg.hfov_deg)))
        if layout is None:
            continue
        surfaces, board, room, cam_pose, scan_pose, light = layout
        camera = random_camera(rng, preset, cfg.hfov_deg)
        if pinhole:
            camera = dataclasses.replace(camera, distortion=())
        scene = Scene(room, surfaces, [], [], cfg.texel_m, light, board, cam_pose, scan_pose)
        rc = build_raycaster(scene)
        if _board_visible(scene, rc, camera):
            return scene, rc, camera, attempt + 1
    raise InputError(f"seed {seed}: no layout in {cfg.max_layout_tries} tries (max_layout_tries) where the camera sees the "
                     "whole board and the scanner stands in the room: see board_distance_m, scanner_distance_m, "
                     "hfov_deg and the board's size")


def textured(scene: Scene, rng: np.random.Generator, preset: SizePreset) -> None:
    """Gives the scene's surfaces their textures (and the scanner's blurred ones), in place."""
    scene.textures = [make_texture(rng, preset.texture_px) for _ in range(1 + max(s.texture for s in scene.surfaces))]
    scene.textures_blurred = [cv2.GaussianBlur(t, (0, 0), 1.5) for t in scene.textures]


def generate(out_dir: Path, seed: int, size: str, cfg: SynthConfig,
             progress: Callable[[str], None] | None = None, photos: int = 1, rig: str | None = None,
             baseline_m: float = 0.12) -> dict:
    """Generate one scene into `out_dir` (the FILES; with photos > 1 also photo_K.png,
    gt_pose_K.yaml, init_pose_K.yaml for K = 1 .. photos-1, taken by the same camera from
    nearby places). rig 'stereo': each photo is a shot of a stereo rig whose second camera
    (camera_right.yaml, its own lens and color response) sits baseline_m to the right: also
    right.png, right_K.png with their gt_ and init_pose_right[_K].yaml, and rig_gt.yaml (the
    true T_right_from_left). With several photos or a rig, bundle.yaml lists them for `refine
    --bundle`. Returns the scene's numbers (also in scene.json). Deterministic: the same seed,
    size, photos, rig and config give byte-identical files."""
    if size not in cfg.sizes:
        raise InputError(f"unknown size '{size}' (choose from {', '.join(cfg.sizes)})")
    if rig is not None and rig not in RIGS:
        raise InputError(f"unknown rig '{rig}' (choose from {', '.join(RIGS)})")
    preset = cfg.sizes[size]
    say = progress or (lambda _msg: None)
    rng = np.random.default_rng(seed)

    say("layout")
    scene, rc, camera, attempts = laid_out(rng, preset, cfg, seed)
    surfaces, board, room, light = scene.surfaces, scene.board, scene.room, scene.light
    cam_pose, scan_pose = scene.camera_pose, scene.scanner_pose
    say("textures")
    textured(scene, rng, preset)
    cam_resp = color.random_camera_response(rng)
    scan_resp = color.random_scanner_response(rng)

    say("photo")
    rad = render_photo_radiance(scene, rc, camera, cam_pose, preset.supersample, rng)
    photo = color.camera_forward(cam_resp, rad, rng)
    # more photos draw from their own generator, so that the first photo's scene stays the same
    more_rng = np.random.default_rng([seed, 7])
    more_poses = extra_cameras(scene, rc, camera, photos - 1, more_rng) if photos > 1 else []
    more_photos = [color.camera_forward(cam_resp, render_photo_radiance(
        scene, rc, camera, pose, preset.supersample, more_rng), more_rng) for pose in more_poses]

    right = None
    if rig is not None:  # its own generator: the left photos stay those of the scene without a rig
        rig_rng = np.random.default_rng([seed, 11])
        right_cam = random_camera(rig_rng, preset, cfg.hfov_deg)
        T_rl = stereo_rig(rig_rng, baseline_m)
        right_resp = color.random_camera_response(rig_rng)
        right_poses = [pose @ np.linalg.inv(T_rl) for pose in [cam_pose] + more_poses]  # world_from_right
        right = (right_cam, T_rl, right_poses, [color.camera_forward(right_resp, render_photo_radiance(
            scene, rc, right_cam, pose, preset.supersample, rig_rng), rig_rng) for pose in right_poses])

    say("scan")
    # the scanner covers what the cameras see, with a margin
    seen = np.concatenate([_seen_points(rc, camera, pose) for pose in [cam_pose] + more_poses]
                          + ([_seen_points(rc, right[0], pose) for pose in right[2]] if right else []))
    Rws, s = scan_pose[:3, :3], scan_pose[:3, 3]
    grid = grid_covering((seen - s) @ Rws, np.deg2rad(preset.scan_step_deg), np.deg2rad(cfg.scan_margin_deg))
    if preset.scan_fov_deg is not None:
        grid = dome_grid(grid, np.deg2rad(preset.scan_step_deg), np.deg2rad(preset.scan_fov_deg))
    local, _world, srad, cos_inc, row, col = laser_scan(scene, rc, grid, cfg.range_noise_m, rng)
    seen_rad = srad if cfg.scanner_color_blur_cells == 0 else blur_over_grid(srad, row, col, (grid.rows, grid.cols),
                                                                            cfg.scanner_color_blur_cells)
    rgb = color.scanner_forward(scan_resp, seen_rad)
    reflect = np.clip(srad @ np.array([0.5, 0.3, 0.2]), 0, 1)
    intensity = np.clip(0.08 + 0.85 * reflect**0.8 * (0.5 + 0.5 * cos_inc) + rng.normal(0, 0.01, reflect.size), 0, 1)
    scan_local = Scan(xyz=local, rgb=rgb, intensity=intensity.astype(np.float32), row=row.astype(np.int32), col=col.astype(np.int32))

    say("writing")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_e57(out_dir / "scan.e57", [scan_local], [scan_pose], names=["synthetic scan"])
    world = Scan(xyz=transform_points(scan_pose, local), rgb=rgb, intensity=scan_local.intensity, row=scan_local.row,
                 col=scan_local.col, scan_id=np.zeros(len(local), np.int32), origins=s[None])
    save_scan(out_dir / "scan.ply", world)
    write_image(out_dir / "photo.png", photo)
    write_camera(out_dir / "camera.yaml", camera)
    T_gt = np.linalg.inv(cam_pose)
    write_pose(out_dir / "gt_pose.yaml", T_gt, method="synthetic ground truth", seed=seed)
    T_init = perturb_pose(T_gt, rng, cfg.init_translation_m, cfg.init_rotation_deg)
    write_pose(out_dir / "init_pose.yaml", T_init, method="ground truth perturbed (synthetic)", seed=seed)
    for k, (pose, img) in enumerate(zip(more_poses, more_photos), start=1):
        write_image(out_dir / f"photo_{k}.png", img)
        T_k = np.linalg.inv(pose)
        write_pose(out_dir / f"gt_pose_{k}.yaml", T_k, method="synthetic ground truth", seed=seed)
        write_pose(out_dir / f"init_pose_{k}.yaml", perturb_pose(T_k, more_rng, cfg.init_translation_m, cfg.init_rotation_deg),
                   method="ground truth perturbed (synthetic)", seed=seed)
    listed = [{"image": "photo.png" if k == 0 else f"photo_{k}.png", "camera": "left" if right else "camera",
               "init": "init_pose.yaml" if k == 0 else f"init_pose_{k}.yaml"} | ({"shot": k} if right else {})
              for k in range(photos)]
    if right is not None:
        right_cam, T_rl, right_poses, right_photos = right
        write_camera(out_dir / "camera_right.yaml", right_cam)
        write_pose(out_dir / "rig_gt.yaml", T_rl, method="synthetic ground truth: T_right_from_left", seed=seed,
                   baseline_m=baseline_m)
        for k, (pose, img) in enumerate(zip(right_poses, right_photos)):
            tail = "" if k == 0 else f"_{k}"
            write_image(out_dir / f"right{tail}.png", img)
            T_k = np.linalg.inv(pose)
            write_pose(out_dir / f"gt_pose_right{tail}.yaml", T_k, method="synthetic ground truth", seed=seed)
            write_pose(out_dir / f"init_pose_right{tail}.yaml", perturb_pose(T_k, rig_rng, cfg.init_translation_m,
                                                                             cfg.init_rotation_deg),
                       method="ground truth perturbed (synthetic)", seed=seed)
            listed.append({"image": f"right{tail}.png", "camera": "right", "init": f"init_pose_right{tail}.yaml", "shot": k})
    if photos > 1 or right is not None:
        cams = {"left": "camera.yaml", "right": "camera_right.yaml"} if right else {"camera": "camera.yaml"}
        with atomic_output(out_dir / "bundle.yaml") as tmp:
            tmp.write_text(bundle_file(listed, cams, ["left", "right"] if right else None))
    corners = board.corners()
    with atomic_output(out_dir / "board_corners.csv") as tmp:
        np.savetxt(tmp, corners, delimiter=",", header="x,y,z", comments="", fmt="%.9f")

    info = {
        "seed": seed,
        "size": size,
        "image": {"width": camera.width, "height": camera.height, "supersample": preset.supersample},
        "room_m": room.tolist(),
        "scanner": {
            "T_world_from_scanner": scan_pose.tolist(),
            "step_deg": preset.scan_step_deg,
            "grid": {"rows": grid.rows, "cols": grid.cols, "azimuth0_rad": grid.az0, "elevation0_rad": grid.el0},
            "points": int(len(local)),
            "range_noise_m": cfg.range_noise_m,
            "color_blur_cells": cfg.scanner_color_blur_cells,
        },
        "camera": {"T_world_from_camera": cam_pose.tolist(), "distance_to_scanner_m": float(np.linalg.norm(cam_pose[:3, 3] - s)),
                   "distance_to_board_m": float(np.linalg.norm(cam_pose[:3, 3] - corners.mean(0)))},
        "board": {"cols": board.cols, "rows": board.rows, "square_m": board.square, "T_world_from_board": board.pose.tolist()},
        "color_response": {"camera": cam_resp.as_dict(), "scanner": scan_resp.as_dict()},
        "light": light.tolist(),
        "texel_m": cfg.texel_m,
        "objects": [{"name": s_.name, "shape": s_.shape, "T_world_from_local": s_.pose.tolist(),
                     "lo": s_.lo.tolist(), "hi": s_.hi.tolist()} for s_ in surfaces],
        "layout_attempts": attempts,
        "more_photos": [{"photo": f"photo_{k}.png", "T_world_from_camera": p.tolist()} for k, p in enumerate(more_poses, start=1)],
    }
    if right is not None:
        info["rig"] = {"kind": rig, "baseline_m": baseline_m, "T_right_from_left": right[1].tolist(),
                       "right_photos": [{"photo": "right.png" if k == 0 else f"right_{k}.png", "T_world_from_camera": p.tolist()}
                                        for k, p in enumerate(right[2])]}
    with atomic_output(out_dir / "scene.json") as tmp:
        tmp.write_text(json.dumps(info, indent=1))
    return info
