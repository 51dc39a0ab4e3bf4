"""Settings of `rgbd-gt refine` (configs/refine.yaml); each is also a CLI flag where sensible."""

from __future__ import annotations

from dataclasses import dataclass

from rgbd_gt.align.color_models import MODELS


@dataclass
class RefineConfig:
    color_model: str = "quadratic"  # one of color_models.MODELS
    gradient: str = "direct"  # 'direct' (strategy A) or 'central' (strategy B)
    optimizer: str = "lm"  # 'lm' (Levenberg-Marquardt on the 6 pose parameters) or 'adam' (the paper's)
    levels: int = 5  # image pyramid levels (1 = full resolution only)
    upsample: int = 4  # the finest level samples the photo enlarged this much (bicubic; pyramid.py says why)
    iterations: int = 30  # per level (lm) ...
    adam_iterations: int = 300  # ... and per level for adam
    adam_lr_rotation: float = 2.0e-4  # radians per step
    adam_lr_translation: float = 5.0e-4  # metres per step
    beta_max: float = 0.1  # color inlier threshold |D K(I) - c| for the color fit
    nu: float = 5.0  # Student-t degrees of freedom
    max_points: int = 80_000  # points used at full resolution (a quarter per coarser level)
    min_points: int = 4_000  # ... but never fewer
    stop_rotation_deg: float = 2.0e-4  # stop a level when an update is smaller than both
    stop_translation_m: float = 2.0e-5
    zbuffer_rel_tol: float = 0.02  # a point is visible when z <= zmin (1 + rel) + abs
    zbuffer_abs_tol: float = 0.01
    min_visible: int = 200  # fewer visible points than this at the start is an error
    seed: int = 0  # point subsampling
    texture_floor: float = 0.1  # points are drawn with probability ~ local scan contrast + this x its mean

    def check(self) -> "RefineConfig":
        if self.color_model not in MODELS:
            raise ValueError(f"color_model must be one of {', '.join(MODELS)}, got {self.color_model!r}")
        if self.gradient not in ("direct", "central"):
            raise ValueError(f"gradient must be 'direct' or 'central', got {self.gradient!r}")
        if self.optimizer not in ("lm", "adam"):
            raise ValueError(f"optimizer must be 'lm' or 'adam', got {self.optimizer!r}")
        if self.levels < 1 or self.iterations < 1 or self.max_points < 10 or self.upsample < 1:
            raise ValueError("levels, upsample, iterations and max_points must be positive")
        return self
