"""`refine --report DIR`: a convergence plot and the color-difference images (the paper's Fig. 2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbd_gt.align.aligner import RefineResult
from rgbd_gt.io.atomic import atomic_output


READABLE_SIDE = 1600  # residual images: the longer side, pixels


def residual_image(uv: np.ndarray, err: np.ndarray, size: tuple[int, int], longest: int = READABLE_SIDE) -> np.ndarray:
    """|D K(I) - c| of the visible points (uv (N, 2) photo pixels, err (N,)) as an image (h, w)
    float32 at a readable scale (the longer side at most `longest`): the mean per pixel, each
    point spread over the gap to its neighbours (a splat), NaN where no point reaches."""
    import cv2

    w, h = size
    s = min(1.0, longest / max(w, h))
    sw, sh = max(1, round(w * s)), max(1, round(h * s))
    px = np.clip(np.floor(uv * s).astype(int), 0, [sw - 1, sh - 1])
    key = px[:, 1] * sw + px[:, 0]
    total = np.bincount(key, weights=err, minlength=sw * sh).reshape(sh, sw).astype(np.float32)
    count = np.bincount(key, minlength=sw * sh).reshape(sh, sw).astype(np.float32)
    occupied = max(int((count > 0).sum()), 1)
    # points that cover only part of the pixels leave gaps about sqrt(area / occupied) wide
    r = int(np.clip(np.ceil(0.5 * np.sqrt(np.ptp(px[:, 0]) * np.ptp(px[:, 1]) / occupied)), 0, 12)) if len(px) else 0
    if r > 0:
        k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        total, count = cv2.dilate(total * (count > 0) / np.maximum(count, 1), k), cv2.dilate(count, k)
        return np.where(count > 0, total, np.nan).astype(np.float32)
    return np.where(count > 0, total / np.maximum(count, 1), np.nan).astype(np.float32)


def _save_residuals(path: Path, image: np.ndarray, vmax: float, title: str) -> None:
    """The residual image with a color scale bar (matplotlib), black where no point projects."""
    import matplotlib.pyplot as plt

    h, w = image.shape
    fig = plt.figure(figsize=(w / 100 + 1.4, h / 100 + 0.6), dpi=100)
    ax = fig.add_axes([0.01, 0.01, w / 100 / (w / 100 + 1.4), 1 - 0.6 / (h / 100 + 0.6)])
    ax.set_facecolor("black")
    im = ax.imshow(image, cmap="inferno", vmin=0, vmax=vmax, interpolation="nearest")
    ax.set_title(title, fontsize=10)
    ax.set_xticks([])
    ax.set_yticks([])
    cax = fig.add_axes([ax.get_position().x1 + 0.01, 0.1, 0.02, 0.8])
    fig.colorbar(im, cax=cax, label="|color residual| (colors scaled to 0-1)")
    with atomic_output(path) as tmp:
        fig.savefig(tmp, format="png", facecolor="white")
    plt.close(fig)


def write_report(out_dir: Path, result: RefineResult, size: tuple[int, int]) -> list[Path]:
    """Write convergence.png, residuals_start.png and residuals_end.png into out_dir."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    h = result.history
    fig, axes = plt.subplots(3, 1, figsize=(7, 8), sharex=True)
    x = np.arange(len(h))
    levels = np.array([r["level"] for r in h])
    # nid records one entry per level and has no per-point residual: its objective instead
    key, label = ("loss", "NID (+ sky charge)") if result.objective == "nid" else ("median_residual", "median color residual")
    axes[0].plot(x, [r[key] for r in h], ".-")
    axes[0].set_ylabel(label)
    axes[1].semilogy(x, [max(r["rotation_update_deg"], 1e-9) for r in h], ".-")
    axes[1].set_ylabel("rotation update (deg)")
    axes[2].semilogy(x, [max(r["translation_update_m"] * 1e3, 1e-9) for r in h], ".-")
    axes[2].set_ylabel("translation update (mm)")
    if result.objective == "nid":
        axes[2].set_xticks(x, [str(v) for v in levels])
        axes[2].set_xlabel("pyramid level, coarse to fine (each its own points and image scale)")
    else:
        axes[2].set_xlabel("iteration (pyramid levels coarse to fine, separated by lines)")
    for ax in axes:
        for k in np.nonzero(np.diff(levels))[0]:
            ax.axvline(k + 0.5, color="gray", lw=0.5)
    fig.suptitle("rgbd-gt refine: convergence")
    fig.tight_layout()
    with atomic_output(out_dir / "convergence.png") as tmp:
        fig.savefig(tmp, dpi=100)
    plt.close(fig)
    written.append(out_dir / "convergence.png")
    if result.start_residuals is not None and result.end_residuals is not None:
        vmax = float(np.percentile(result.start_residuals[1], 95)) or 1.0
        for name, title, (uv, err) in (("residuals_start.png", "at the initial pose", result.start_residuals),
                                       ("residuals_end.png", "at the refined pose", result.end_residuals)):
            _save_residuals(out_dir / name, residual_image(uv, err, size), vmax, f"color residuals {title}")
            written.append(out_dir / name)
    return written
