"""The scan rendered at a pose, shown over the photo: the check a person trusts most.

Two pictures at the photo's full resolution (crop them to inspect an edge): a checkerboard whose
squares alternate between the photo and the rendered scan (edges must continue across square
borders), and a 50% blend (doubled edges mean a wrong pose).
"""

from __future__ import annotations

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.io.scan import Scan, scan_colors


def render_colors(scan: Scan, camera: Camera, T: np.ndarray, max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The scan's colors (gray for intensity) as the camera sees them at T: (H, W, 3) uint8 and
    (H, W) bool where the scan has a surface (the depth renderer: occlusion and back faces)."""
    from rgbd_gt.render.depth import render_depth

    colors = scan_colors(scan).astype(np.float32)
    if colors.shape[1] == 1:
        colors = np.repeat(colors * 255, 3, axis=1)
    depth = render_depth(scan, camera, T, max_depth, values=colors)
    have = depth.z > 0
    return np.clip(np.rint(depth.colors), 0, 255).astype(np.uint8) * have[..., None], have


def checkerboard(photo: np.ndarray, rendered: np.ndarray, have: np.ndarray, squares: int = 16) -> np.ndarray:
    """(H, W, 3) uint8: squares (`squares` along the longer side) alternating between the photo
    and the rendering; the photo, darkened, where the scan has nothing."""
    h, w = photo.shape[:2]
    side = max(8, max(h, w) // squares)
    v, u = np.ogrid[0:h, 0:w]
    scan_square = ((v // side + u // side) % 2).astype(bool) & have
    out = np.where(scan_square[..., None], rendered, photo)
    dark = ((v // side + u // side) % 2).astype(bool) & ~have
    out[dark] = (out[dark] * 0.45).astype(np.uint8)
    return out


def blend(photo: np.ndarray, rendered: np.ndarray, have: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: 50% photo, 50% rendering where the scan has a surface; the photo elsewhere."""
    mixed = ((photo.astype(np.uint16) + rendered) // 2).astype(np.uint8)
    return np.where(have[..., None], mixed, photo)


def overlay(scan: Scan, photo: np.ndarray, camera: Camera, T: np.ndarray,
            max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """(checkerboard, blend, fraction of the photo the scan covers) at the photo's resolution."""
    rendered, have = render_colors(scan, camera, T, max_depth)
    return checkerboard(photo, rendered, have), blend(photo, rendered, have), float(have.mean())
