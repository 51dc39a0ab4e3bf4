"""The scan rendered at a pose, shown over the photo: the check a person trusts most.

Three pictures at the photo's full resolution (crop them to inspect an edge): a checkerboard whose
squares alternate between the photo and the rendered scan (edges must continue across square
borders), a 50% blend (doubled edges mean a wrong pose), and the visible scan points as dots of
their own value over the photo: for a sparse LiDAR sweep, whose rings leave gaps that surfaces
rendered from it can only fill with blobs, the clearest of the three.
"""

from __future__ import annotations

import numpy as np

from rgbd_gt.camera import Camera, project, rescale, without_distortion
from rgbd_gt.pose import transform_points
from rgbd_gt.render.cells import cell_for_density
from rgbd_gt.render.renders import Renders
from rgbd_gt.scan import Scan, scan_colors


def render_scale(scan: Scan, camera: Camera, T: np.ndarray, per_step: float = 2.0) -> float:
    """The scale (at most 1) at which `per_step` pixels span one step between neighbouring scan
    points in view: finer rendering only interpolates. Measured in the image: the side of the
    square cells whose occupied ones hold 3 points at the median (`render.cells.cell_for_density`),
    over sqrt(3)."""
    # pinhole: the lens distortion hardly changes how densely points land
    uv, z = project(without_distortion(camera), transform_points(T, scan.xyz))
    uv = uv[z > 0]
    if int(((uv >= 0) & (uv <= np.array(camera.size) - 1)).all(1).sum()) < 100:
        return 1.0
    return float(min(1.0, per_step * np.sqrt(3) / cell_for_density(uv, camera.size, largest=256)))


def render_colors(renders: Renders, camera: Camera, T: np.ndarray,
                  max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The scan's colors (gray for intensity) as the camera sees them at T: (H, W, 3) uint8 and
    (H, W) bool where the scan has a surface (the depth renderer: occlusion and back faces), from
    `renders` (`render.renders.Renders` of the view, with its colors). Rendered at `render_scale`
    and enlarged: the cost follows the scan, not the photo's pixels."""
    import cv2

    s = render_scale(renders.scan, camera, T)
    cam = camera if s >= 0.999 else rescale(camera, max(1, round(camera.width * s)), max(1, round(camera.height * s)))
    depth = renders.surfaces(cam, T, max_depth, colors=True)
    c = depth.colors if depth.colors.shape[-1] == 3 else np.repeat(depth.colors * 255, 3, axis=-1)
    rendered, have = np.clip(np.rint(c), 0, 255).astype(np.uint8), (depth.z > 0).astype(np.uint8)
    if cam.size != camera.size:
        rendered = cv2.resize(rendered, camera.size, interpolation=cv2.INTER_LINEAR)
        have = cv2.resize(have, camera.size, interpolation=cv2.INTER_NEAREST)
    return rendered, have > 0


def checkerboard(photo: np.ndarray, rendered: np.ndarray, have: np.ndarray, squares: int = 16) -> np.ndarray:
    """(H, W, 3) uint8: squares (`squares` along the longer side) alternating between the photo
    and the rendering; the photo, darkened, where the scan has nothing."""
    import cv2

    h, w = photo.shape[:2]
    side = max(8, max(h, w) // squares)
    out = photo.copy()
    mask = have.view(np.uint8)
    # square by square (a few hundred): full-size masks would cost more than the copying itself
    for y in range(0, h, side):
        for x in range((y // side % 2 == 0) * side, w, 2 * side):
            sl = (slice(y, y + side), slice(x, x + side))
            out[sl] = cv2.convertScaleAbs(photo[sl], alpha=0.45)
            cv2.copyTo(rendered[sl], mask[sl], out[sl])
    return out


def blend(photo: np.ndarray, rendered: np.ndarray, have: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8: 50% photo, 50% rendering where the scan has a surface; the photo elsewhere."""
    import cv2

    out = photo.copy()
    cv2.copyTo(cv2.addWeighted(photo, 0.5, rendered, 0.5, 0), have.view(np.uint8), out)
    return out


def overlay(renders: Renders, photo: np.ndarray, camera: Camera, T: np.ndarray,
            max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """(checkerboard, blend, fraction of the photo the scan covers) at the photo's resolution."""
    rendered, have = render_colors(renders, camera, T, max_depth)
    return checkerboard(photo, rendered, have), blend(photo, rendered, have), float(have.mean())


def points_image(renders: Renders, photo: np.ndarray, camera: Camera, T: np.ndarray, max_depth: float | None = None,
                 dot_px: int = 1) -> tuple[np.ndarray, int]:
    """(H, W, 3) uint8: the photo, dimmed, with the scan points the camera sees at T
    (`Renders.seen`) drawn as squares of side 2 dot_px + 1 (`dot_pixels`: the nearest wins where
    they overlap) in their colors (`point_colors`); and the number of points drawn."""
    import cv2

    from rgbd_gt.render.points import dot_pixels

    idx, uv, z, _ = renders.seen(camera, T, max_depth)
    out = cv2.convertScaleAbs(photo, alpha=0.6)
    key, owner = dot_pixels(uv, z, camera.size, dot_px)
    out.reshape(-1, 3)[key] = point_colors(renders.scan, idx)[owner]
    return out, len(idx)


def point_colors(scan: Scan, idx: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 RGB of the points idx: their colors, or their intensity in the turbo colormap
    (blue low, red high), spread by the 1st-99th percentiles of these points."""
    import cv2

    colors = scan_colors(scan)[idx]
    if colors.shape[1] == 3:
        return colors.astype(np.uint8)
    lo, hi = np.percentile(colors, [1, 99]) if len(colors) else (0.0, 1.0)
    level = np.clip((colors[:, 0] - lo) / max(hi - lo, 1e-9) * 255, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(level[:, None], cv2.COLORMAP_TURBO)[:, 0, ::-1].copy()  # BGR -> RGB
