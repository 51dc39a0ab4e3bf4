"""Running an aligner: its inputs, the aligner of the objective, the refine with its verdict, and
the pose file's keys of a result (`steps.refine_step` calls these)."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from rgbd_gt.align.config import RefineConfig
from rgbd_gt.errors import InputError

if TYPE_CHECKING:  # the aligners import torch: loaded where they run, so that bad arguments fail fast
    from rgbd_gt.align.aligner import RefineResult
    from rgbd_gt.align.verify import Verification


# nid on CUDA pays off from this many frames in one solve: on an H100 machine one frame took
# 1.2-1.4x the CPU's time, 3 frames about the same, 5 frames 0.85x, 10 and 19 frames 0.70x and
# 0.44x (docs/gpu.md); a photometric objective's thousands of points per level pay off at once
NID_CUDA_FRAMES = 5


def resolve_device(name: str, objective: str = "photometric", frames: int = 1):
    """'auto' | 'cpu' | 'cuda' -> torch.device. 'auto' takes CUDA when present, except for the
    nid objective on fewer than NID_CUDA_FRAMES frames solved together: a frame's ~10k points
    per level leave a GPU waiting on kernel launches, and only many frames fill it."""
    import torch

    if name == "auto":
        gpu = torch.cuda.is_available() and (objective != "nid" or frames >= NID_CUDA_FRAMES)
        return torch.device("cuda" if gpu else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device must be auto, cpu or cuda, got {name!r}")
    return torch.device(name)


@dataclass
class RefineInputs:
    points: np.ndarray  # (N, 3) scan frame, metres
    colors: np.ndarray  # `scan.scan_colors`
    photo: np.ndarray  # (H, W, 3) uint8
    camera: object
    T_init: np.ndarray
    ignore: np.ndarray | None
    scan: object = None  # the `Scan` (its grid renders the verification's edge check); points only when None
    init_meta: dict = field(default_factory=dict)  # the init pose file's other keys (its `uncertainty`)
    around: np.ndarray | None = None  # (M, 3) the scan around the init's camera, for the verticals check
    renders: object = None  # the view's `render.renders.Renders`, which the verdict's edge check and later steps share

    @property
    def normals(self) -> np.ndarray | None:
        return self.scan.normals if self.scan is not None else None

    def the_renders(self):
        """`renders`, or new ones of the scan (of the points alone when there is no scan)."""
        from rgbd_gt.render.renders import Renders
        from rgbd_gt.scan import Scan

        if self.renders is not None:
            return self.renders
        return Renders(self.scan if self.scan is not None else Scan(xyz=self.points), self.colors, [self.T_init])


def camera_disagreement(camera, init_meta: dict, camera_path) -> str | None:
    """A warning when init-pose estimated another focal length for this photo than the camera
    file's (more than 1% apart): the pose would absorb the difference."""
    est = init_meta.get("estimated_focal_px")
    if not isinstance(est, (int, float)) or not est > 0 or abs(camera.fx / est - 1) <= 0.01:
        return None
    return (f"--camera {camera_path}: fx is {camera.fx:.1f} px but init-pose estimated {est:.1f} px for this photo "
            f"(init-pose --camera-out writes that camera)")


def read_pairs(path: Path, camera: Path) -> list[dict[str, Path]]:
    """The (scan, image, camera) paths of a --pairs YAML (`pairs:` a list of mappings with scan,
    image and optionally camera, which defaults to `camera`), relative to the file's folder (`~`:
    the user's home)."""
    from rgbd_gt.errors import read_yaml, require_file, require_listed

    path = require_file(path)
    data = read_yaml(path)
    items = data.get("pairs") if isinstance(data, dict) else None
    if not isinstance(items, list) or not items:
        raise InputError("needs `pairs:`, a list of {scan, image[, camera]}", path)
    out = []
    for k, item in enumerate(items, 1):
        if not isinstance(item, dict) or not all(isinstance(item.get(key), str) and item[key].strip() for key in ("scan", "image")):
            raise InputError(f"pair {k}: needs scan and image paths", path)
        if "camera" in item and not (isinstance(item["camera"], str) and item["camera"].strip()):
            raise InputError(f"pair {k}: camera must be a path", path)
        out.append({key: path.parent / os.path.expanduser(item[key]) for key in ("scan", "image", "camera") if key in item})
    require_listed({f"pair {k}: {key}": p for k, paths in enumerate(out, 1) for key, p in paths.items()}, path)
    return [{"camera": Path(camera), **paths} for paths in out]


def objective_of(cfg: RefineConfig, colors: np.ndarray) -> str:
    """The objective that runs: cfg.objective, where 'auto' means nid for a scan with intensity
    only ((N, 1) colors) and photometric for a colored one (docs/lidar.md measures both)."""
    if cfg.objective != "auto":
        return cfg.objective
    return "nid" if colors.shape[1] == 1 else "photometric"


def refine_meta(result: RefineResult, cfg: RefineConfig, T_init: np.ndarray, init_path,
                verification: Verification | None = None, pairs: int = 1, camera=None) -> dict:
    """The keys a refined pose file records besides the pose: the verdict first."""
    from rgbd_gt.pose import rotation_error_deg, translation_error_m

    meta = {}
    if verification is not None:
        meta = dict(verdict=verification.verdict, reasons=verification.reasons, evidence=verification.evidence)
    meta.update(method=f"rgbd-gt refine ({result.objective})", init=str(init_path), objective=result.objective)
    if result.objective == "nid":
        meta.update(nid_bins=cfg.nid_bins, nid_edges=cfg.nid_edges, edge_weight=cfg.edge_weight, sky_weight=cfg.sky_weight,
                    sky_coarse_level=cfg.sky_coarse_level, pairs=pairs)
    else:
        meta.update(color_model=cfg.color_model, gradient=cfg.gradient, optimizer=cfg.optimizer,
                    refine_intrinsics=cfg.refine_intrinsics, color_transform=result.color_transform.tolist())
    meta.update(
        final_loss=result.loss, inlier_fraction=result.inlier_fraction,
        iterations=result.iterations, visible_points=result.visible_points, seconds=round(result.seconds, 3),
        change_from_init={"translation_mm": translation_error_m(result.T_cam_from_scan, T_init) * 1e3,
                          "rotation_deg": rotation_error_deg(result.T_cam_from_scan, T_init)},
    )
    cov = result.covariance if verification is None else verification.covariance
    if cov is not None and np.isfinite(cov).all():
        # what export's per-pixel depth 1-sigma propagates: of the update (rotation vector rad,
        # translation m) in the camera frame, T' = exp(update) T (`pose.apply_update`); a joint
        # solve's widened by its frames' scatter (`verify.frames_covariance`)
        meta["covariance"] = cov.tolist()
    if result.intrinsics is not None and camera is not None:
        meta["intrinsics"] = intrinsics_meta(camera, result)
    if verification is not None:
        meta["verify_seconds"] = round(verification.seconds, 3)
    return meta


def photometric_pyramid(photo: np.ndarray, camera, cfg: RefineConfig, device, ignore: np.ndarray | None = None):
    """The photometric objective's pyramid of `photo` (H, W, 3) uint8 by cfg: enlarged at the
    finest level, and kept as taken (not undistorted) where the camera is refined, so that its
    corrections add to the file's own lens (`photo_pyramid`'s `distorted`)."""
    from rgbd_gt.align.pyramid import photo_pyramid

    return photo_pyramid(photo, camera, cfg.levels, device, ignore, cfg.upsample, distorted=cfg.refine_intrinsics != "none")


def make_aligner(inputs: RefineInputs, cfg: RefineConfig, device: str, more: list[RefineInputs] = ()):
    """The aligner of cfg's objective for inputs (and the further pairs `more` that share its
    pose: nid only)."""
    from rgbd_gt.align.aligner import Aligner
    from rgbd_gt.align.nid_objective import NID_LEVELS, Frame, Nid
    from rgbd_gt.align.photometric import Photometric
    from rgbd_gt.align.pyramid import photo_pyramid
    from rgbd_gt.scan import colors_to_gray

    objective = objective_of(cfg, inputs.colors)
    dev = resolve_device(device, objective, 1 + len(more))
    if cfg.refine_intrinsics != "none" and objective != "photometric":
        raise InputError("--refine-intrinsics works with the photometric objective (a colored scan) only")
    if objective == "photometric":
        if more:
            raise InputError("several pairs are solved jointly with --objective nid only")
        pyramid = photometric_pyramid(inputs.photo, inputs.camera, cfg, dev, inputs.ignore)
        return Aligner(Photometric(inputs.points, inputs.colors, pyramid, cfg, inputs.normals))
    # NID compares value distributions: an enlarged photo adds pixels, not information
    levels = NID_LEVELS if cfg.levels == "auto" else cfg.levels
    frames = [Frame(i.points, colors_to_gray(i.colors) / 255.0, photo_pyramid(i.photo, i.camera, levels, dev, i.ignore),
                    i.normals, i.scan.edge if i.scan is not None else None) for i in [inputs, *more]]
    return Aligner(Nid(frames, cfg))


def run_refine(inputs: RefineInputs, cfg: RefineConfig, device: str = "auto",
               progress: Callable[[dict], None] | None = None, keep_residuals: bool = False) -> RefineResult:
    """Refine inputs.T_init; raises InputError when no scan points are in view."""
    return make_aligner(inputs, cfg, device).refine(inputs.T_init, progress=progress, keep_residuals=keep_residuals)


def refine_verified(inputs: RefineInputs, cfg: RefineConfig, device: str = "auto",
                    progress: Callable[[dict], None] | None = None, keep_residuals: bool = False,
                    check: tuple[np.ndarray, np.ndarray] | None = None,
                    more: list[RefineInputs] = ()) -> tuple[RefineResult, Verification]:
    """`run_refine`, then the verdict on its result (align/verify.py); the repeat runs reuse the
    photo pyramid and the prepared points. check: held-out pairs (img (n, 2), scan points (n, 3));
    more: further pairs that share the pose (solved jointly; the image check uses the first)."""
    from rgbd_gt.align.verify import verify

    aligner = make_aligner(inputs, cfg, device, more)
    result = aligner.refine(inputs.T_init, progress=progress, keep_residuals=keep_residuals)
    verification = verify(aligner, result, inputs.T_init, refined_camera(inputs.camera, result), inputs.photo,
                          inputs.the_renders(), cfg.verify, cfg.seed, inputs.init_meta, check)
    return result, verification


def refined_camera(camera, result: RefineResult):
    """The camera the result's pose goes with: the input's, corrected when its intrinsics were refined."""
    from rgbd_gt.camera import corrected

    return camera if result.intrinsics is None else corrected(camera, result.intrinsics)


def intrinsics_meta(camera, result: RefineResult) -> dict:
    """The refined camera and each refined value's 1-sigma, for the pose file."""
    cam = refined_camera(camera, result)
    q, s = result.intrinsics, result.intrinsics_sigma
    meta = {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "distortion": list(cam.distortion),
            "sigma": {"focal_px": float(s[0] * camera.fx)}}
    if np.isfinite(s[1]):
        meta["sigma"].update(cx_px=float(s[1] * camera.fx), cy_px=float(s[2] * camera.fy))
    if np.isfinite(s[3]):
        meta["sigma"].update(k1=float(s[3]), k2=float(s[4]))
    if np.isfinite(s[5]):
        meta["sigma"].update(p1=float(s[5]), p2=float(s[6]), k3=float(s[7]))
    meta["change"] = {"focal_percent": float(q[0] * 100), "principal_px": [float(q[1] * camera.fx), float(q[2] * camera.fy)],
                      "k1": float(q[3]), "k2": float(q[4]), "p1": float(q[5]), "p2": float(q[6]), "k3": float(q[7])}
    return meta
