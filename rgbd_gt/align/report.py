"""`refine --report DIR`: a convergence plot and the color-difference images (the paper's Fig. 2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbd_gt.align.aligner import RefineResult
from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.io.image import write_image


def residual_image(uv: np.ndarray, err: np.ndarray, size: tuple[int, int], vmax: float) -> np.ndarray:
    """|D K(I) - c| of each visible point drawn at its pixel, color-mapped (H, W, 3) uint8 RGB;
    black where no point projects."""
    import cv2

    w, h = size
    img = np.zeros((h, w), np.float32)
    hit = np.zeros((h, w), bool)
    px = np.clip(np.round(uv).astype(int), 0, [w - 1, h - 1])
    img[px[:, 1], px[:, 0]] = err
    hit[px[:, 1], px[:, 0]] = True
    u8 = np.clip(img / vmax * 255, 0, 255).astype(np.uint8)
    color = cv2.applyColorMap(u8, cv2.COLORMAP_INFERNO)[:, :, ::-1]
    color[~hit] = 0
    return color


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
    axes[0].plot(x, [r["median_residual"] for r in h], ".-")
    axes[0].set_ylabel("median color residual")
    axes[1].semilogy(x, [max(r["rotation_update_deg"], 1e-9) for r in h], ".-")
    axes[1].set_ylabel("rotation update (deg)")
    axes[2].semilogy(x, [max(r["translation_update_m"] * 1e3, 1e-9) for r in h], ".-")
    axes[2].set_ylabel("translation update (mm)")
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
        for name, (uv, err) in (("residuals_start.png", result.start_residuals), ("residuals_end.png", result.end_residuals)):
            write_image(out_dir / name, residual_image(uv, err, size, vmax))
            written.append(out_dir / name)
    return written
