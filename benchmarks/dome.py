"""The scale benchmark: `rgbd-gt run` on a FARO-sized structured scan (a synthetic 190 x 150
degree dome of about 40 million points, made once and cached) with ten 1280x960 photos; every
step's time per photo and the run's peak memory (docs/scale.md)."""

from __future__ import annotations

import math
from pathlib import Path

from rgbd_gt.synth.generate import SizePreset, SynthConfig, generate

DOME_DEG = (190.0, 150.0)


def dome_scene(out: Path, points: float = 40.8e6, photos: int = 10, seed: int = 3, progress=print) -> Path:
    """A synthetic scene whose scan is a FARO-like grid over DOME_DEG with about `points`
    points, and `photos` photos of 1280x960 that see its board; made once into `out` (its
    scene.json says it is complete). Returns out."""
    if (out / "scene.json").exists():
        return out
    step = math.sqrt(DOME_DEG[0] * DOME_DEG[1] / points)
    cfg = SynthConfig(sizes={"dome": SizePreset(1280, 960, step, 1024, 2, list(DOME_DEG))})
    generate(out, seed, "dome", cfg, progress=progress, photos=photos)
    return out
