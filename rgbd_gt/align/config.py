"""Settings of `rgbd-gt refine` (configs/refine.yaml); each is also a CLI flag where sensible."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

from rgbd_gt.config import require

OBJECTIVES = ("auto", "photometric", "nid")
# align/color_models.py's, named here so that reading a config does not import torch
MODELS = ("quadratic", "quadratic_rgb", "linear", "none", "gray", "gray_affine")


@dataclass
class VerifyConfig:
    """The evidence behind a refined pose's verdict and the thresholds that turn it into one
    (align/verify.py; docs/trust.md says how they were chosen)."""

    repeats: int = 4  # refine again from this many starts around the init (0: no repeatability check)
    repeat_coarsest: int = 9  # the repeat runs' pyramid levels, coarse (9: the coarsest there is) ...
    repeat_finest: int = 2  # ... to fine (compared with the result's pose after that level)
    repeat_iterations: int = 6  # per level of a repeat run
    # nid: the repeat runs go the whole way, as refine does (its wide search, every level, its
    # iterations): L-BFGS stopped early on a coarse level lands anywhere (measured: 4-26 px apart
    # where finished runs agree), and from 3 deg inits only the search lands right
    repeat_nid_whole: bool = True
    start_floor_px: float = 2.0  # the starts move the image at least this much
    sharpness_step_px: float = 1.5  # the image motion of the sharpness probes (photo pixels) ...
    sharpness_level: int = 2  # ... on this pyramid level
    edge_max_side: int = 1280  # the structural edge check renders at most this size (longer side)
    edge_shift_px: int = 6  # ... and measures chance with its edges shifted this far
    min_edge_pixels: int = 200  # fewer structural edges than this cannot confirm a pose
    # thresholds: failed beyond the first of each pair, suspect beyond the second
    edge_ratio_failed: float = 1.1
    edge_ratio_ok: float = 1.2
    ring_edge_ratio_failed: float = 1.05  # sweeps: the same of the ring edges (`Nid.ring_edge_check`) ...
    ring_edge_ratio_ok: float = 1.15
    # each frame of a joint solve, its own ring edges at the result: failed below ring_edge_ratio_failed,
    # suspect below this (honest KITTI and Waymo frames 1.10-1.40; a frame 0.5 deg off mostly under
    # 1.05: docs/lidar-method.md, "One frame's own depth edges")
    ring_edge_frame_ok: float = 1.08
    spread_failed_px: float = 3.0
    spread_ok_px: float = 1.0
    # nid on a sweep: finished repeats of results within 0.2 deg of the reference ended up to
    # 3.6 px apart, of wrong ones 10 px and more (docs/lidar-method.md)
    spread_failed_px_nid: float = 6.0
    folds: int = 2  # several frames of one rig (nid): refine them in this many groups apart, instead of the repeats (0/1: repeats)
    # ... each refined from the result, from this pyramid level down to fold_finest. Level 1 alone:
    # KITTI's coarser level 2 holds half the frames' own minimum 6 px off the right result (a
    # false `failed` on configs/drive.yaml), level 1 puts every right group of the 40 stored joint
    # results within 1.6 px and the wrong one 66 px away, in 4 s of KITTI's 19 frames (levels
    # 2-1: 7 s; level 0: 12 s). docs/lidar-method.md
    fold_coarsest: int = 1
    fold_finest: int = 1
    # ... suspect when a group ends farther than this (px) from the result (failed: spread_failed_px_nid);
    # on 20 KITTI joint results the right ones' groups ended 0.8-2.3 px away, those over 0.3 deg off 4.7 px and more
    # (the same bar for a frame left out: on the 40 stored KITTI and Waymo joint results the right
    # ones moved 0.2-2.2 px, where the others alone fix the pose)
    fold_ok_px: float = 3.0
    sharpness_failed: float = 0.0
    sharpness_ok: float = 0.003
    sigma_failed_px: float = 1.0
    sigma_ok_px: float = 0.1
    # nid: a Laplace approximation over samples that share pixels, the lower bound is looser;
    # right joint solves of Waymo's 10 frames state 0.2 px (docs/lidar.md)
    sigma_ok_px_nid: float = 0.5
    check_failed_px: float = 5.0
    check_ok_px: float = 2.0
    change_max_sigmas: float = 10.0
    # the camera check: a result refined with the camera file as it is, refined again with the
    # focal length free (on the finest level; camera_iterations: 3 take a focal 2% off 1.5-1.95%
    # back); suspect when the focal moves more than camera_sigmas of its own 1-sigma and more
    # than camera_min_change (relative)
    camera_check: bool = True
    camera_iterations: int = 3
    camera_sigmas: float = 5.0
    camera_min_change: float = 0.002
    # a photo of a bundle (`refine --bundle`): suspect when, left out, the others' shared camera
    # and rig move its pose more than bundle_sigmas of its sigma, when freed from its rig its pose
    # moves more than that, or when its residual scale exceeds bundle_residual_ratio x the others'
    bundle_sigmas: float = 15.0
    bundle_residual_ratio: float = 2.0
    bundle_freed_ratio: float = 3.0  # ... and freed from the rig, a photo moves this many times the median photo's

    def check(self) -> "VerifyConfig":
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, bool) and not (v == v and abs(v) != float("inf")):
                raise ValueError(f"verify.{f.name} must be a finite number, got {v}")
        at = "verify."
        require(self.camera_iterations >= 1, at + "camera_iterations", "at least 1", self.camera_iterations)
        # beyond these a verdict would take days: a typo
        require(0 <= self.repeats <= 64, at + "repeats", "0..64", self.repeats)
        require(1 <= self.repeat_iterations <= 1_000, at + "repeat_iterations", "1..1000", self.repeat_iterations)
        require(0 <= self.repeat_finest, at + "repeat_finest", "0 or more", self.repeat_finest)
        require(self.repeat_finest <= self.repeat_coarsest <= 12, at + "repeat_coarsest", "repeat_finest..12", self.repeat_coarsest)
        require(0 <= self.sharpness_level <= 12, at + "sharpness_level", "0..12", self.sharpness_level)
        require(0 <= self.folds <= 64, at + "folds", "0..64", self.folds)
        require(0 <= self.fold_finest, at + "fold_finest", "0 or more", self.fold_finest)
        require(self.fold_finest <= self.fold_coarsest <= 12, at + "fold_coarsest", "fold_finest..12", self.fold_coarsest)
        require(self.fold_ok_px >= 0, at + "fold_ok_px", "0 or more", self.fold_ok_px)
        require(64 <= self.edge_max_side <= 8192, at + "edge_max_side", "64..8192", self.edge_max_side)
        require(self.min_edge_pixels >= 0, at + "min_edge_pixels", "0 or more", self.min_edge_pixels)
        require(self.edge_shift_px >= 1, at + "edge_shift_px", "at least 1", self.edge_shift_px)
        require(self.sharpness_step_px > 0, at + "sharpness_step_px", "positive", self.sharpness_step_px)
        require(self.start_floor_px >= 0, at + "start_floor_px", "0 or more", self.start_floor_px)
        return self


@dataclass
class RefineConfig:
    objective: str = "auto"  # photometric | nid | auto (nid for scans with intensity only, else photometric)
    color_model: str = "quadratic"  # one of color_models.MODELS
    gradient: str = "direct"  # 'direct' (strategy A) or 'central' (strategy B)
    optimizer: str = "lm"  # 'lm' (Levenberg-Marquardt on the 6 pose parameters) or 'adam' (the paper's)
    # image pyramid levels (1 = full resolution only), or "auto": photometric, as many as bring the
    # coarsest level's longer side to 40-79 px (align/pyramid.py: `pyramid_levels`); nid, 5
    levels: int | str = "auto"
    upsample: int = 4  # the finest level samples the photo enlarged this much (bicubic; pyramid.py says why)
    iterations: int = 30  # per level (lm) ...
    adam_iterations: int = 300  # ... and per level for adam
    adam_lr_rotation: float = 2.0e-4  # radians per step
    adam_lr_translation: float = 5.0e-4  # metres per step
    # photometric: the color fit also weighs the high pass of the photo's gray (align/photometric.py:
    # `high_pass`), so that a photo blurrier or sharper than the scan's colors is compared as
    # sharp as they are. Blur alone moved synthetic poses by about 1 mm, all photos of a scene alike
    fit_sharpness: bool = True
    beta_max: float = 0.1  # color inlier threshold |D K(I) - c| for the color fit
    nu: float = 5.0  # Student-t degrees of freedom
    max_points: int = 80_000  # points used at full resolution (a quarter per coarser level)
    min_points: int = 4_000  # ... but never fewer
    stop_rotation_deg: float = 2.0e-4  # stop a level when an update is smaller than both
    stop_translation_m: float = 2.0e-5
    zbuffer_rel_tol: float = 0.02  # a point is visible when z <= zmin (1 + rel) + abs
    zbuffer_abs_tol: float = 0.01
    # photometric, finest level: points on a foreground silhouette (a surface more than this much
    # farther, relative depth, within a Z-buffer cell around them) are left out: the photo mixes
    # their pixels with the background, a scan whose colors are pure there does not. 0: all count.
    # Off by default: on the synthetic stereo rig 0.1 brings the baseline's error from 0.19 to
    # 0.05 mm, on ICL-NUIM (whose cloud's colors mix there as the photos do) it costs a third
    # of the accuracy (docs/bundle.md)
    depth_edge_ratio: float = 0.0
    min_visible: int = 200  # fewer visible points than this at the start is an error
    seed: int = 0  # point subsampling
    texture_floor: float = 0.1  # points are drawn with probability ~ local scan contrast + this x its mean
    max_depth: float = 0.0  # metres: points farther from the initial camera are not used (0: all)
    nid_bins: int = 16  # nid: bins per axis of the joint histogram
    nid_edges: bool = False  # nid: also NID of depth discontinuities against the photo's gradient magnitude
    edge_weight: float = 3.0  # nid: weight of the ring-edge term (sweeps: depth steps along rings on the photo's edges; 0: off)
    sky_weight: float = 0.5  # nid: added to NID per unit fraction of points that land on the photo's sky (align/sky.py; 0: off) ...
    sky_coarse_level: int = 2  # ... on pyramid levels this coarse and coarser (0: every level; the sky is found at 1/8 scale)
    search_starts: int = 16  # nid: before the coarsest level, also run it from this many starts (0: none) ...
    search_rotation_deg: float = 3.0  # ... turned this much ...
    search_translation_m: float = 0.2  # ... and moved this much from the init
    search_iterations: int = 10  # ... for at most this many iterations each ...
    search_keep: int = 3  # ... and this many of lowest NID go on to level 1, where the lowest NID wins
    # photometric, lm: also refine the camera (camera.INTRINSICS): none | focal |
    # focal+principal | focal+principal+k1k2 | full (k1 k2 p1 p2 k3)
    refine_intrinsics: str = "none"
    # refine --bundle, rigs: the weight of the agreement term between the photos of a shot
    # (align/bundle.py; 0: off). 0.2 measured best of 0.05-4 on the rig's relative pose at little
    # cost to the absolute poses (docs/bundle.md)
    bundle_agreement: float = 0.2
    verify: VerifyConfig = field(default_factory=VerifyConfig)  # the verdict's evidence and thresholds

    def check(self) -> "RefineConfig":
        if self.color_model not in MODELS:
            raise ValueError(f"color_model must be one of {', '.join(MODELS)}, got {self.color_model!r}")
        if self.gradient not in ("direct", "central"):
            raise ValueError(f"gradient must be 'direct' or 'central', got {self.gradient!r}")
        if self.optimizer not in ("lm", "adam"):
            raise ValueError(f"optimizer must be 'lm' or 'adam', got {self.optimizer!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {', '.join(OBJECTIVES)}, got {self.objective!r}")
        for name, least in (("nid_bins", 6), ("search_starts", 0), ("search_iterations", 1), ("search_keep", 1), ("max_depth", 0)):
            require(getattr(self, name) >= least, name, f"at least {least}", getattr(self, name))
        from rgbd_gt.camera import INTRINSICS  # torch-free: a command's config is checked before torch is imported

        if self.refine_intrinsics not in INTRINSICS:
            raise ValueError(f"refine_intrinsics must be one of {', '.join(INTRINSICS)}, got {self.refine_intrinsics!r}")
        if self.refine_intrinsics != "none" and (self.optimizer != "lm" or self.objective == "nid"):
            raise ValueError("refine_intrinsics works with the photometric objective and optimizer lm")
        if isinstance(self.levels, str) and self.levels != "auto":
            raise ValueError(f"levels must be a number or 'auto', got {self.levels!r}")
        levels = 1 if self.levels == "auto" else self.levels
        require(1 <= levels <= 12, "levels", "1..12 or 'auto'", self.levels)
        require(1 <= self.upsample <= 8, "upsample", "1..8", self.upsample)
        require(self.iterations >= 1, "iterations", "at least 1", self.iterations)
        require(self.max_points >= 10, "max_points", "at least 10", self.max_points)
        for name, most in (("iterations", 10_000), ("adam_iterations", 100_000), ("search_starts", 1_000), ("search_keep", 1_000),
                           ("search_iterations", 10_000), ("max_points", 100_000_000), ("min_points", 100_000_000),
                           ("nid_bins", 256)):  # beyond these a run would take days: a typo
            if getattr(self, name) > most:
                raise ValueError(f"{name} must be at most {most:,}, got {getattr(self, name)}")
        positive = ("adam_iterations", "adam_lr_rotation", "adam_lr_translation", "beta_max", "nu", "min_points",
                    "min_visible")
        not_negative = ("stop_rotation_deg", "stop_translation_m", "zbuffer_rel_tol", "zbuffer_abs_tol", "depth_edge_ratio", "seed",
                        "texture_floor", "search_rotation_deg", "search_translation_m", "sky_weight", "sky_coarse_level", "edge_weight")
        for name in positive + not_negative:
            v = getattr(self, name)
            if not (v == v and abs(v) != float("inf")) or (v <= 0 if name in positive else v < 0):
                raise ValueError(f"{name} must be {'positive' if name in positive else '0 or more'}, got {v}")
        self.verify.check()
        return self
