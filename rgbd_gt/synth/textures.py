"""Procedural, tileable albedo textures with natural-image statistics.

Each texture is a (S, S, 3) float32 array of linear albedo in [0, 1] that tiles seamlessly
(surfaces larger than one tile repeat it). Content: multi-scale noise (a 1/f-like spectrum),
stripes, text-like marks, gradients and patches; nothing finer than a few texels, so that a
camera pixel covering several texels sees natural, not aliased, detail.
"""

from __future__ import annotations

import cv2
import numpy as np


def random_color(rng: np.random.Generator, sat=(0.15, 0.8), val=(0.2, 0.9)) -> np.ndarray:
    """(3,) linear RGB from a random hue, saturation and value."""
    hsv = np.array([[[rng.uniform(0, 180), rng.uniform(*sat) * 255, rng.uniform(*val) * 255]]], np.float32)
    return cv2.cvtColor(hsv.astype(np.uint8), cv2.COLOR_HSV2RGB)[0, 0].astype(np.float32) / 255.0


def fractal_noise(rng: np.random.Generator, size: int, min_period: int = 6, falloff: float = 0.6) -> np.ndarray:
    """(size, size) float32 tileable noise in [0, 1] summed over octaves (periods size/2 ... min_period)."""
    acc = np.zeros((size, size), np.float32)
    amp, period, total = 1.0, size // 2, 0.0
    while period >= min_period:
        k = max(2, size // period)
        cell = size // k
        grid = rng.random((k, k)).astype(np.float32)
        # pad periodically before the resize and crop: the result wraps around seamlessly
        big = cv2.resize(np.pad(grid, 2, mode="wrap"), ((k + 4) * cell, (k + 4) * cell), interpolation=cv2.INTER_CUBIC)
        acc += amp * big[2 * cell : 2 * cell + size, 2 * cell : 2 * cell + size]
        total += amp
        amp *= falloff
        period //= 2
    acc /= total
    lo, hi = np.percentile(acc, [1, 99])
    return np.clip((acc - lo) / max(hi - lo, 1e-6), 0, 1)


def _mix(a: np.ndarray, b: np.ndarray, t: np.ndarray) -> np.ndarray:
    return a * (1 - t[..., None]) + b * t[..., None]


def _stripes(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size, size) soft stripes in [0, 1], periodic over the tile."""
    a, b = rng.integers(-6, 7, 2)
    if a == 0 and b == 0:
        a = 3
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    phase = 2 * np.pi * (a * x + b * y) / size
    sharp = rng.uniform(1.5, 6)
    return (0.5 + 0.5 * np.tanh(sharp * np.sin(phase))).astype(np.float32)


def _text_marks(rng: np.random.Generator, size: int) -> np.ndarray:
    """(size, size) coverage in [0, 1] of lines of random letters, as on labels and posters."""
    canvas = np.zeros((3 * size, 3 * size), np.uint8)  # drawn on a 3x3 tile, then folded: wraps
    letters = "ABCDEFGHJKLMNOPRSTUVWXYZ0123456789-/"
    for _ in range(int(rng.integers(4, 12))):
        scale = rng.uniform(0.8, 2.5) * size / 512
        text = "".join(rng.choice(list(letters), size=int(rng.integers(3, 14))))
        org = (int(rng.integers(size, 2 * size)), int(rng.integers(size, 2 * size)))
        thick = max(2, int(round(scale * 2)))
        cv2.putText(canvas, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, 255, thick, cv2.LINE_AA)
    folded = canvas.reshape(3, size, 3, size).max(axis=(0, 2))
    return cv2.GaussianBlur(folded.astype(np.float32) / 255.0, (0, 0), 1.0)


def _patches(rng: np.random.Generator, size: int, base: np.ndarray) -> np.ndarray:
    """Random colored rectangles and discs on `base` (H, W, 3), wrapping at the tile border."""
    out = base.copy()
    for _ in range(int(rng.integers(3, 9))):
        color = tuple(float(c) for c in random_color(rng))
        cx, cy = int(rng.integers(size)), int(rng.integers(size))
        r = int(rng.integers(size // 20, size // 5))
        disc = rng.random() < 0.5
        for dx in (-size, 0, size):  # each shape drawn at its 9 periodic copies; cv2 clips
            for dy in (-size, 0, size):
                c = (cx + dx, cy + dy)
                if disc:
                    cv2.circle(out, c, r, color, -1, cv2.LINE_AA)
                else:
                    cv2.rectangle(out, (c[0] - r, c[1] - r // 2), (c[0] + r, c[1] + r // 2), color, -1, cv2.LINE_AA)
    return out


def make_texture(rng: np.random.Generator, size: int, kind: str | None = None) -> np.ndarray:
    """A (size, size, 3) float32 albedo texture; `kind` in {'noise', 'stripes', 'text',
    'gradient', 'patches'} or None for a random one."""
    kinds = ("noise", "stripes", "text", "gradient", "patches")
    kind = kind or kinds[int(rng.integers(len(kinds)))]
    c1, c2 = random_color(rng), random_color(rng)
    tex = _mix(c1, c2, fractal_noise(rng, size) ** rng.uniform(0.7, 1.5))
    tex = _overlay(rng, tex, kind, size)
    if kind != "noise" and rng.random() < 0.6:  # a second layer: labels or patches on top
        tex = _overlay(rng, tex, ("text", "patches")[int(rng.integers(2))], size)
    # fine grain everywhere: real surfaces are never flat color
    grain = fractal_noise(rng, size, min_period=4, falloff=0.9) - 0.5
    tex = tex * (1 + 0.35 * grain[..., None])
    return np.clip(tex, 0.02, 0.95).astype(np.float32)


def _overlay(rng: np.random.Generator, tex: np.ndarray, kind: str, size: int) -> np.ndarray:
    if kind == "stripes":
        tex = _mix(tex, tex * rng.uniform(0.3, 0.7) + random_color(rng) * 0.3, _stripes(rng, size))
    elif kind == "text":
        tex = _mix(tex, random_color(rng, val=(0.02, 0.25)), _text_marks(rng, size))
    elif kind == "gradient":
        y, x = np.mgrid[0:size, 0:size].astype(np.float32)
        angle = rng.uniform(0, 2 * np.pi)
        g = 0.5 + 0.5 * np.cos(2 * np.pi * (np.cos(angle) * x + np.sin(angle) * y) / size)
        tex = _mix(tex, random_color(rng), g.astype(np.float32) * 0.7)
    elif kind == "patches":
        tex = _patches(rng, size, tex.astype(np.float32))
    return tex
