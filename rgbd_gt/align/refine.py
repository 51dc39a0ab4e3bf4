"""`rgbd-gt refine` on files: read the inputs, check them against each other, run the aligner."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.align.aligner import Aligner, RefineResult
from rgbd_gt.align.config import RefineConfig
from rgbd_gt.align.verify import Verification, verify
from rgbd_gt.errors import InputError
from rgbd_gt.io.scan import scan_colors


def resolve_device(name: str):
    """'auto' | 'cpu' | 'cuda' -> torch.device ('auto' takes CUDA when present)."""
    import torch

    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise InputError("--device cuda: no CUDA device is available")
    if name not in ("cpu", "cuda"):
        raise InputError(f"--device must be auto, cpu or cuda, got {name!r}")
    return torch.device(name)


@dataclass
class RefineInputs:
    points: np.ndarray  # (N, 3) scan frame, metres
    colors: np.ndarray  # `io.scan.scan_colors`
    photo: np.ndarray  # (H, W, 3) uint8
    camera: object
    T_init: np.ndarray
    ignore: np.ndarray | None
    scan: object = None  # the `io.Scan` (its grid renders the verification's edge check); points only when None
    init_meta: dict = field(default_factory=dict)  # the init pose file's other keys (its `uncertainty`)

    def the_scan(self):
        from rgbd_gt.io.scan import Scan

        return self.scan if self.scan is not None else Scan(xyz=self.points)


def load_inputs(scan_path: Path, image_path: Path, camera_path: Path, init_path: Path,
                mask_path: Path | None = None) -> RefineInputs:
    from rgbd_gt.io import load_scan, read_camera, read_pose
    from rgbd_gt.io.camera_file import check_image_matches
    from rgbd_gt.io.image import read_image, read_mask

    camera = read_camera(camera_path)
    photo = read_image(image_path)
    check_image_matches(camera, photo.shape, image_path, camera_path)
    T_init, init_meta = read_pose(init_path)
    ignore = read_mask(mask_path, photo.shape[:2]) if mask_path is not None else None
    scan = load_scan(scan_path, require_points=True)
    return RefineInputs(scan.xyz, scan_colors(scan, scan_path), photo, camera, T_init, ignore, scan, init_meta)


def refine_meta(result: RefineResult, cfg: RefineConfig, T_init: np.ndarray, init_path,
                verification: Verification | None = None) -> dict:
    """The keys a refined pose file records besides the pose: the verdict first."""
    from rgbd_gt.pose import rotation_error_deg, translation_error_m

    meta = {}
    if verification is not None:
        meta = dict(verdict=verification.verdict, reasons=verification.reasons, evidence=verification.evidence)
    meta.update(
        method="rgbd-gt refine (photometric)", init=str(init_path), color_model=cfg.color_model,
        gradient=cfg.gradient, optimizer=cfg.optimizer, color_transform=result.color_transform.tolist(),
        iterations=result.iterations, final_loss=result.loss, inlier_fraction=result.inlier_fraction,
        visible_points=result.visible_points, seconds=round(result.seconds, 3),
        change_from_init={"translation_mm": translation_error_m(result.T_cam_from_scan, T_init) * 1e3,
                          "rotation_deg": rotation_error_deg(result.T_cam_from_scan, T_init)},
    )
    if verification is not None:
        meta["verify_seconds"] = round(verification.seconds, 3)
    return meta


def _aligner(inputs: RefineInputs, cfg: RefineConfig, device: str) -> Aligner:
    from rgbd_gt.align.pyramid import photo_pyramid

    pyramid = photo_pyramid(inputs.photo, inputs.camera, cfg.levels, resolve_device(device), inputs.ignore,
                            cfg.upsample)
    return Aligner(inputs.points, inputs.colors, pyramid, cfg)


def run_refine(inputs: RefineInputs, cfg: RefineConfig, device: str = "auto",
               progress: Callable[[dict], None] | None = None, keep_residuals: bool = False) -> RefineResult:
    """Refine inputs.T_init; raises InputError when no scan points are in view."""
    return _aligner(inputs, cfg, device).refine(inputs.T_init, progress=progress, keep_residuals=keep_residuals)


def refine_verified(inputs: RefineInputs, cfg: RefineConfig, device: str = "auto",
                    progress: Callable[[dict], None] | None = None, keep_residuals: bool = False,
                    check: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[RefineResult, Verification]:
    """`run_refine`, then the verdict on its result (align/verify.py); the repeat runs reuse the
    photo pyramid and the prepared points. check: held-out pairs (img (n, 2), scan points (n, 3))."""
    aligner = _aligner(inputs, cfg, device)
    result = aligner.refine(inputs.T_init, progress=progress, keep_residuals=keep_residuals)
    verification = verify(aligner, result, inputs.T_init, inputs.camera, inputs.photo, inputs.the_scan(),
                          inputs.colors, cfg.verify, cfg.seed, inputs.init_meta, check)
    return result, verification
