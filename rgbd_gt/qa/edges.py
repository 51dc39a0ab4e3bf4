"""Edges of the photo against edges of the scan rendered into its camera (the paper's Fig. 5).

Two scores. The Canny score (how far the scan's Canny edges lie from the photo's) is the
paper's picture, but on real photos it measures chance: Canny marks a quarter of a busy photo's
pixels, so a pose 30 cm off scores as well as a right one. The structural score takes only the
scan's structure (depth discontinuities and strong color edges of the rendered scan), weighs
each by the photo's gradient strength there, and divides by the same with those edges shifted
by several pixels: 1.0 means no better than chance."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np

from rgbd_gt.camera import Camera, rescale
from rgbd_gt.render.renders import Renders
from rgbd_gt.scan import Scan, colors_to_gray


WORKING_SIDE = 1280  # the longer side (pixels) of the picture the scores are taken on
SHIFT_PX = 6  # working pixels: the structural score's chance shift, and the widest splats either score can use


@dataclass
class EdgeScore:
    """Distances (photo pixels) from the scan's Canny edges to the photo's; scan_edge_pixels: how
    many were measured. usable is False where the scan was drawn with splats wider than
    `qa`'s usable_splat_px: their own discs are then the edges, and the distances (nan) say nothing."""

    median_distance_px: float
    mean_distance_px: float
    within_1px: float
    scan_edge_pixels: int
    usable: bool = True

    def summary(self) -> str:
        if not self.usable:
            return "says nothing (the scan is too sparse: its splats are the edges)"
        return (f"median {self.median_distance_px:.2f} px, mean {self.mean_distance_px:.2f} px, "
                f"within 1 px {self.within_1px:.1%}")

    def as_dict(self, prefix: str = "") -> dict:
        return {f"{prefix}median_distance_px": self.median_distance_px, f"{prefix}mean_distance_px": self.mean_distance_px,
                f"{prefix}within_1px": self.within_1px, f"{prefix}scan_edge_pixels": self.scan_edge_pixels,
                f"{prefix}canny_usable": self.usable}


def auto_canny(gray: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Canny edges (H, W) bool with thresholds from the image's own gradient statistics: the
    high threshold at the 85th percentile of the (slightly blurred) gradient magnitude over the
    valid pixels, the low one at half of it. Edges of the valid region itself are dropped."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    region = np.ones(gray.shape, bool) if valid is None else valid
    high = float(np.percentile(mag[region], 85)) if region.any() else 1.0
    edges = cv2.Canny(np.clip(g, 0, 255).astype(np.uint8), max(high * 0.25, 1), max(high * 0.5, 2), L2gradient=True) > 0
    if valid is not None:
        edges &= cv2.erode(valid.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    return edges


def edge_score(photo_edges: np.ndarray, scan_edges: np.ndarray, pixel: float = 1.0) -> EdgeScore:
    """Distance from each scan edge pixel to the nearest photo edge pixel, in units of `pixel`
    edge-image pixels (the photo's own pixels for edges found at a reduced scale)."""
    dist = cv2.distanceTransform((~photo_edges).astype(np.uint8), cv2.DIST_L2, 5)
    d = dist[scan_edges] * pixel
    if d.size == 0:
        return EdgeScore(float("nan"), float("nan"), 0.0, 0)
    return EdgeScore(float(np.median(d)), float(d.mean()), float(np.mean(d <= 1.0)), int(d.size))


def overlay(photo: np.ndarray, photo_edges: np.ndarray, scan_edges: np.ndarray) -> np.ndarray:
    """Darkened photo with red photo edges, blue scan edges, white where both (H, W, 3) uint8 RGB."""
    out = (photo.astype(np.float32) * 0.35).astype(np.uint8)
    out[photo_edges] = (255, 40, 40)
    out[scan_edges] = (60, 110, 255)
    out[photo_edges & scan_edges] = (255, 255, 255)
    return out


def side_by_side(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Two overlays (H, W, 3) as one panel, separated by an 8-pixel white bar."""
    return np.concatenate([before, np.full((before.shape[0], 8, 3), 255, np.uint8), after], axis=1)


@dataclass
class WorkingView:
    """The photo and the scan rendered at a pose, both at a working resolution (`working_camera`):
    what both edge checks look at."""

    camera: Camera
    photo: np.ndarray  # (h, w, 3) uint8
    gray: np.ndarray  # (h, w) float32 0..255: the scan's colors as gray, 0 where it sees none
    z: np.ndarray  # (h, w) metres, 0 where the scan has no surface (or everywhere: splats not drawn)
    radius: int  # the splat radius in pixels (0 for a mesh)


def working_view(renders: Renders, photo: np.ndarray, camera: Camera, T: np.ndarray,
                 max_side: int = WORKING_SIDE, max_splat_px: int | None = None) -> WorkingView:
    """The view (`renders`: `render.renders.Renders` of the scan, with its colors) at T and the
    photo (H, W, 3) uint8 of `camera`, at the working resolution whose longer side is at most
    max_side; splats wider than max_splat_px are not drawn (z all 0)."""
    cam = working_camera(camera, max_side)
    small = photo if cam.size == camera.size else cv2.resize(photo, cam.size, interpolation=cv2.INTER_AREA)
    # squares for a scan without sides: its edges are the same, and the thresholds were measured on them
    out = renders.surfaces(cam, T, colors=True, max_splat_px=max_splat_px, planes=False)
    gray = colors_to_gray(out.colors.reshape(-1, out.colors.shape[-1])).reshape(out.z.shape)
    return WorkingView(cam, small, gray, out.z, out.splat_radius)


def qa(view: WorkingView, camera: Camera, usable_splat_px: int = SHIFT_PX) -> tuple[np.ndarray, EdgeScore]:
    """(overlay image, score) for one pose from its `working_view` (distances in the pixels of
    the photo's `camera`): Canny on every pixel of a 24 MP photo costs seconds and gigabytes, and
    its edges are no surer. A scan drawn with splats wider than usable_splat_px (working pixels;
    a LiDAR sweep's are 30 and more) scores as not usable, as `structural_qa` does beyond its shift."""
    photo_edges = auto_canny(cv2.cvtColor(view.photo, cv2.COLOR_RGB2GRAY))
    scan_edges = auto_canny(view.gray, view.z > 0)
    if view.radius > usable_splat_px:
        score = EdgeScore(float("nan"), float("nan"), float("nan"), int(scan_edges.sum()), usable=False)
    else:
        score = edge_score(photo_edges, scan_edges, camera.width / view.camera.width)
    return overlay(view.photo, photo_edges, scan_edges), score


@dataclass
class StructuralScore:
    """ratio: score / chance (1.0 = no better than chance; nan without structural edges);
    score: mean photo gradient strength (0..1) at the scan's structural edge pixels;
    chance: the same with those edges shifted by a few pixels in 8 directions (mean);
    edge_pixels: how many structural edge pixels were scored (at the working resolution);
    splat_radius: pixels of the splats a scan without a grid was drawn with (0: a mesh). Splats
    much wider than the chance shift draw their own squares and rings as edges: the score then
    says nothing (`usable` is False)."""

    ratio: float
    score: float
    chance: float
    edge_pixels: int
    splat_radius: int = 0
    usable: bool = True

    def summary(self) -> str:
        sparse = "" if self.usable else f" (says nothing: the scan is too sparse, splats of {self.splat_radius} px)"
        return f"edges vs chance {self.ratio:.2f}{sparse}"

    def as_dict(self, prefix: str = "") -> dict:
        return {f"{prefix}edge_ratio": self.ratio, f"{prefix}edge_strength": self.score,
                f"{prefix}edge_strength_chance": self.chance, f"{prefix}structural_edge_pixels": self.edge_pixels,
                f"{prefix}splat_radius_px": self.splat_radius, f"{prefix}edge_check_usable": self.usable}


def photo_strength(gray: np.ndarray) -> np.ndarray:
    """Gradient strength of a photo (H, W) in [0, 1]: the gradient magnitude (after a 1-px blur)
    over its 95th percentile, clipped, then the 3x3 maximum so that a scan edge one pixel off
    still counts. 1 on the photo's strongest gradients, near 0 on flat regions."""
    g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
    mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    top = float(np.percentile(mag, 95)) or 1.0
    return cv2.dilate(np.clip(mag / top, 0, 1), np.ones((3, 3), np.uint8))


def structural_edges(z: np.ndarray, gray: np.ndarray) -> np.ndarray:
    """(H, W) bool structural edges of a rendered scan (z-depth, 0 = nothing; gray 0..255):
    depth discontinuities (the nearer side of a jump of more than 5% of the depth between
    neighbours that both have depth) and strong color edges (Canny at the 90th percentile of the
    gradient, inside the rendered region). The border of the rendered region is not an edge:
    it is where the scan ends, not structure."""
    edges = np.zeros(z.shape, bool)
    for a, b, ea, eb in ((z[:-1], z[1:], edges[:-1], edges[1:]), (z[:, :-1], z[:, 1:], edges[:, :-1], edges[:, 1:])):
        jump = (a > 0) & (b > 0) & (np.abs(a - b) > 0.05 * np.minimum(a, b))
        ea |= jump & (a < b)
        eb |= jump & (b <= a)
    inner = cv2.erode((z > 0).astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    if inner.any():
        g = cv2.GaussianBlur(gray.astype(np.float32), (0, 0), 1.0)
        mag = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
        high = max(float(np.percentile(mag[inner], 90)), 1.0)
        canny = cv2.Canny(np.clip(g, 0, 255).astype(np.uint8), 0.5 * high, high, L2gradient=True) > 0
        edges |= canny & inner
    return edges


SHIFTS = ((-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1))


def chance_relative(strength: np.ndarray, edges: np.ndarray, shift_px: int) -> StructuralScore:
    """The mean of `strength` (H, W) at `edges` (H, W bool) against its mean with the edges
    shifted by shift_px in each of 8 directions (edges shifted out of the image are left out)."""
    v, u = np.nonzero(edges)
    if v.size == 0:
        return StructuralScore(float("nan"), float("nan"), float("nan"), 0)
    h, w = strength.shape
    score = float(strength[v, u].mean())
    shifted = []
    for dv, du in SHIFTS:
        vv, uu = v + dv * shift_px, u + du * shift_px
        keep = (vv >= 0) & (vv < h) & (uu >= 0) & (uu < w)
        if keep.any():
            shifted.append(float(strength[vv[keep], uu[keep]].mean()))
    chance = float(np.mean(shifted)) if shifted else float("nan")
    return StructuralScore(score / max(chance, 1e-6), score, chance, int(v.size))


def working_camera(camera: Camera, max_side: int) -> Camera:
    """The camera at a resolution whose longer side is at most max_side (its own when smaller):
    the structural score needs the photo's structure, not every pixel of a 24 MP photo."""
    s = min(1.0, max_side / max(camera.width, camera.height))
    return camera if s == 1.0 else rescale(camera, max(1, round(camera.width * s)), max(1, round(camera.height * s)))


def structural_qa(view: WorkingView, shift_px: int = SHIFT_PX) -> tuple[np.ndarray, StructuralScore]:
    """(overlay at the working resolution: red = the photo's strongest gradients, blue = the
    scan's structural edges that were scored, white = both; the chance-relative score) for one
    pose from its `working_view`. shift_px is in working-resolution pixels; splats wider than it
    make the score unusable (a view whose splats were not drawn lacks the scan's edges)."""
    small, gray, z, radius = view.photo, view.gray, view.z, view.radius
    strength = photo_strength(cv2.cvtColor(small, cv2.COLOR_RGB2GRAY))
    edges = structural_edges(z, gray)
    strong = cv2.erode((strength > 0.5).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # undo the 3x3 maximum
    score = dataclasses.replace(chance_relative(strength, edges, shift_px), splat_radius=radius, usable=radius <= shift_px)
    return overlay(small, strong, edges), score


def ring_edge_check(scan: Scan, photo: np.ndarray, camera: Camera, poses: list[np.ndarray],
                    shift_px: float = SHIFT_PX) -> list[dict] | None:
    """A sweep's image check of one photo at each of poses (4, 4), as the verdict takes it for
    each frame (`Nid.ring_edge_check`): the photo's (H, W, 3 uint8, with its camera's lens) edge
    strength at the sweep's depth steps along its rings of CHECK_MIN_STEP_M and more (weights
    sqrt(step / m)) against the same shifted shift_px photo pixels in 8 directions. Per pose
    `ring_edge_ratio` (1.0 = chance) and `ring_edges` (how many landed on the photo, at least
    EDGE_NEAR_M in front); None for a scan without ring steps (`Scan.edge`)."""
    import torch

    from rgbd_gt.align.edge_map import CHECK_MIN_STEP_M, EDGE_NEAR_M, against_chance, edge_strength
    from rgbd_gt.camera import project
    from rgbd_gt.pose import transform_points

    if scan.edge is None:
        return None
    idx = np.flatnonzero(scan.edge >= CHECK_MIN_STEP_M)
    weights = np.sqrt(scan.edge[idx].astype(np.float64))
    edges = torch.as_tensor(edge_strength(torch.as_tensor(photo / 255.0))[:, :, None])  # once for all poses
    w, h = camera.size
    out = []
    for T in poses:
        uv, z = project(camera, transform_points(T, scan.xyz[idx]))
        with np.errstate(invalid="ignore"):
            ok = (z > EDGE_NEAR_M) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
        score, chance = against_chance(edges, torch.as_tensor(uv[ok]), torch.as_tensor(weights[ok]), shift_px)
        out.append({"ring_edge_ratio": score / chance if chance > 0 else float("nan"), "ring_edges": int(ok.sum())})
    return out
