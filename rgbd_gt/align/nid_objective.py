"""The NID objective, for weak correspondence: the normalised information distance between the
scan's values (laser intensity, or the gray of colors) and the photo's gray levels at the
projected points (align/nid.py), over one or several (scan, photo) pairs that share the pose (a
LiDAR-camera rig over several frames). The driver (align/aligner.py) minimises it with L-BFGS
(strong Wolfe line search) over the 6 pose parameters, in units of one level pixel of image
motion, after a wide search on the coarsest level (docs/lidar-method.md).

Per pyramid level, the level's points (a random subset of those in view of the initial pose) are
Z-buffered at the level's start pose with a cell sized for their density in the image. The
gradient is exact, in closed form (through the B-spline histogram, the bilinear interpolant and
the projection).
Points that land on the photo's sky add cfg.sky_weight times their fraction to NID (align/sky.py):
a sweep has no returns from the sky, and NID alone drifts to poses that put points there. The
charge applies on the levels from cfg.sky_coarse_level up: the sky is found at 1/8 scale, and its
coarse border would otherwise steer the fine levels (docs/lidar-method.md).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch

from rgbd_gt.align.config import RefineConfig
from rgbd_gt.align.covariance import TILES
from rgbd_gt.align.edge_map import CHECK_MIN_STEP_M, EDGE_NEAR_M
from rgbd_gt.align.nid import nid_of_windows, nid_with_gradient, parzen_windows
from rgbd_gt.align.objective import lockstep
from rgbd_gt.align.pyramid import PhotoLevel
from rgbd_gt.align.sampling import bilinear_stacked, central_gradients
from rgbd_gt.align.subset import near_view, point_keys
from rgbd_gt.errors import LEFT_THE_SCAN, InputError
from rgbd_gt.pose import so3_exp, so3_left_jacobian
from rgbd_gt.render.project import project_pinhole, projection_jacobian
from rgbd_gt.render.normals import facing_camera
from rgbd_gt.render.cells import cell_for_density
from rgbd_gt.render.zbuffer import check_spread_in_view, depth_edges, visible_points
from rgbd_gt.scan import LUMA

@dataclass
class Frame:
    """One (scan, photo) pair of the pose being refined."""

    points: np.ndarray  # (N, 3) float64, scan frame, metres
    values: np.ndarray  # (N,) float32 in [0, 1]: intensity, or the gray of the scan's colors
    pyramid: list[PhotoLevel]  # the photo's, finest first (`photo_pyramid`)
    normals: np.ndarray | None = None  # (N, 3) facing the scanner (render/normals.py), or None
    edges: np.ndarray | None = None  # (N,) metres: a sweep's depth steps along its rings (`Scan.edge`), or None


@dataclass
class _Stack:
    """The F frames' images of one level in one tensor, so that one gather samples them all
    (`bilinear_stacked`)."""

    flat: torch.Tensor  # (sum of W H, C) each frame's pixels row by row, frame after frame
    base: torch.Tensor  # (F, 1) long: the row of flat where each frame starts
    size: torch.Tensor  # (F, 2) long: each frame's (W, H)
    valid: torch.Tensor | None = None  # (sum of W H,) bool: usable pixels, or None where all are
    border: float = 0.0  # pixels: the band inside the border where a point's weight rises (`inside`); 0: none

    def sample(self, uv: torch.Tensor, gradient: bool = False):
        """The frames' images at uv (F, n, 2): (F, n, C), with gradient also d/du and d/dv."""
        return bilinear_stacked(self.flat, self.base, self.size, uv, gradient)

    def inside(self, uv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(F, n) each point's weight in the histogram by where it lands (uv (F, n, 2) pixels): 1
        from `border` pixels inside the frame's border on, falling smoothly (C1) to 0 on the
        border; and its d/du and d/dv. A point that stepped onto the photo at full weight made the
        NID jump there, and a sweep's rings cross the left and right borders every few hundredths
        of a pixel of motion: L-BFGS stopped on those steps ("converged" in 2-4 iterations) up to
        1 cm short of the finest level's minimum (docs/lidar-method.md, "The photo's border")."""
        band = max(self.border, 1e-9)

        def ramp(x: torch.Tensor, far: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            """Smoothstep of the distance to the nearer of two opposite borders (x from one, far
            - x from the other), and its slope along x. Where the band is narrower than half the
            level's photo (KITTI's coarsest: 0.25 of 23 px) the farther factor is exactly 1, so
            this is the product of both for half the work."""
            other = far - x
            s = (torch.minimum(x, other) / band).clamp(0, 1)
            slope = 6 * s * (1 - s) / band
            return s * s * (3 - 2 * s), torch.where(x <= other, slope, -slope)

        u, v = uv[..., 0].double(), uv[..., 1].double()
        (across, d_across), (down, d_down) = ramp(u, self.size[:, 0:1] - 1), ramp(v, self.size[:, 1:2] - 1)
        return across * down, d_across * down, across * d_down

    def on_photo(self, uv: torch.Tensor, z: torch.Tensor, near: float) -> torch.Tensor:
        """(F, n) bool: points (pixels uv (F, n, 2), depths z (F, n)) at least `near` metres in
        front that land on their frame's usable pixels (`_on_photo` for all frames at once)."""
        w, h = self.size[:, 0:1], self.size[:, 1:2]
        u, v = uv[..., 0], uv[..., 1]
        ok = (z > near) & (u >= 0) & (v >= 0) & (u <= w - 1) & (v <= h - 1)
        if self.valid is not None:
            col = torch.minimum(u.detach().clamp_min(0).long(), w - 1)
            row = torch.minimum(v.detach().clamp_min(0).long(), h - 1)
            ok &= self.valid[(self.base + row * w + col).reshape(-1)].reshape(ok.shape)
        return ok


def _stack(images: list[torch.Tensor], valid: list[torch.Tensor | None] | None = None, border: float = 0.0) -> _Stack:
    """`_Stack` of F images (H, W, C_f), the channels each lacks zero; valid: their usable-pixel
    masks (H, W) bool or None; border: `_Stack.border`."""
    c = max(img.shape[2] for img in images)
    flat = torch.cat([torch.nn.functional.pad(img, (0, c - img.shape[2])).reshape(-1, c) for img in images])
    sizes = torch.tensor([[img.shape[1], img.shape[0]] for img in images], device=flat.device)
    base = torch.cumsum(sizes[:, 0] * sizes[:, 1], 0) - sizes[:, 0] * sizes[:, 1]
    mask = None
    if valid is not None and any(m is not None for m in valid):
        mask = torch.cat([(torch.ones(img.shape[:2], dtype=torch.bool, device=flat.device) if m is None else m).reshape(-1)
                          for img, m in zip(images, valid)])
    return _Stack(flat, base[:, None], sizes, mask, border)


def _padded(rows: list[torch.Tensor]) -> torch.Tensor:
    """(F, n, ...) the F tensors (n_f, ...) one after another, each padded with zeros to the largest n."""
    out = rows[0].new_zeros((len(rows), max(len(r) for r in rows)) + tuple(rows[0].shape[1:]))
    for f, r in enumerate(rows):
        out[f, :len(r)] = r
    return out


def _moved(points: torch.Tensor, R: torch.Tensor, t: torch.Tensor, delta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Points (G x F, n, 3) in G groups of F rows, group g moved by (R[g], t[g]) ((G, 3, 3), (G,
    3)): q; and p = q + delta[g, 3:] (delta (G, 6)). Each group is one product, as one pose's F
    frames were before there were groups."""
    G = R.shape[0]
    q = points.reshape(G, -1, 3) @ R.transpose(1, 2) + t[:, None]
    p = q + delta[:, None, 3:].to(R.dtype)
    return q.reshape(points.shape), p.reshape(points.shape)


def _project(p: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`project_pinhole` of each frame's camera-frame points p (F, n, 3) through its K (F, 4:
    fx, fy, cx, cy): pixels (F, n, 2), depths (F, n)."""
    z = p[..., 2]
    zs = z.clamp_min(1e-9)
    return torch.stack([K[:, 0:1] * p[..., 0] / zs + K[:, 2:3], K[:, 1:2] * p[..., 1] / zs + K[:, 3:4]], -1), z


@dataclass
class _Parts:
    """The F frames on one level, batch-first, each padded to the n points of the largest (the
    padding never counts: its windows and strengths are zero): their points (local frame), their
    values and the photos' images, as pairs of channels compared by NID: (scan value, gray) and,
    with cfg.nid_edges, (how far the point stands in front of its sides, gray gradient magnitude).
    Several poses' parts evaluated together are G groups of F rows (`_joined`); the shapes below
    are for one."""

    points: torch.Tensor  # (F, n, 3) float32
    real: torch.Tensor  # (F, n) bool: not padding
    windows: torch.Tensor  # (F, n, C, bins) float64: the values, spread over NID's bins (`parzen_windows`)
    images: _Stack  # C channels, then the sky where a frame has one
    K: torch.Tensor  # (F, 4) fx, fy, cx, cy of the level
    sky: torch.Tensor  # (F,) float64: 1 where the images' last channel is the frame's sky, in [0, 1] (align/sky.py)
    edge_points: torch.Tensor | None = None  # (F, m, 3) float32 local frame: the frames' ring edges (cfg.edge_weight)
    edge_strength: torch.Tensor | None = None  # (F, m) float64 their sqrt(depth step / m)
    edge_maps: _Stack | None = None  # (H, W, 1) per frame: the photo's edges spread (`edge_distance_map`)


def _joined(parts: list[_Parts]) -> _Parts:
    """The parts of G poses (each F rows, one level) as one, group after group, every row padded
    to the largest n: one evaluation serves them all (`Nid._evaluate`)."""
    if len(parts) == 1:
        return parts[0]
    G = len(parts)

    def rows(name: str) -> torch.Tensor:
        return _padded([row for part in parts for row in getattr(part, name)])

    def repeated(stack: _Stack) -> _Stack:
        return replace(stack, base=stack.base.repeat(G, 1), size=stack.size.repeat(G, 1))

    first = parts[0]
    joined = _Parts(rows("points"), rows("real"), rows("windows"), repeated(first.images), first.K.repeat(G, 1),
                    first.sky.repeat(G))
    if first.edge_points is not None:  # the same level and frames: all parts have them or none
        joined.edge_points, joined.edge_strength = rows("edge_points"), rows("edge_strength")
        joined.edge_maps = repeated(first.edge_maps)
    return joined


@dataclass
class _Evaluation:
    """NID at G poses, each over the F frames (rows of `_Parts`, group after group)."""

    nid: torch.Tensor  # (G x F x C,) NID per frame and channel pair (the first plus the sky charge), float64
    counts: list[int]  # per frame and channel pair, the points that entered its histogram
    entropies: list[float]  # ... and its joint entropy H(A, B) (nats)
    edges: torch.Tensor  # (G x F,) float64: per frame cfg.edge_weight x its ring edges' score (0 without)
    gradient: torch.Tensor | None = None  # (G, 6) float64 d objective / d delta per pose, when asked
    groups: int = 1  # G

    @property
    def lost(self) -> np.ndarray:
        """(G,) bool: the pose left the scan (fewer than 50 points land on some frame's photo)."""
        return np.array(self.counts).reshape(self.groups, -1).min(1) < 50

    @property
    def loss(self) -> torch.Tensor:
        """Mean NID less the edge score per unit of the frames' weights: the objective minimised
        (`objective`) over the sum of the weights, up to how the weights differ between frames
        (one pose)."""
        return self.nid.mean() - self.edges.sum() / self.weights().sum()

    def objective(self, weights: torch.Tensor) -> torch.Tensor:
        """(G,) what L-BFGS minimises at each pose: sum(weights * NID) - the edge score."""
        return self.per_frame(weights).reshape(self.groups, -1).sum(1)

    def per_frame(self, weights: torch.Tensor) -> torch.Tensor:
        """(G x F,) each frame's share of `objective`: the objective is a sum over the frames."""
        return (self.nid * weights).reshape(len(self.edges), -1).sum(1) - self.edges

    def weights(self) -> torch.Tensor:
        """(F,) n H(A, B) per frame: n H(A, B) NID is, up to a constant, the negative
        log-likelihood of the n samples under their joint histogram against independence
        (n I(A; B)); summed with these weights the frames count by their evidence, and the
        gradient is of order one per pixel of motion (plain NID changes by ~1e-4 per pixel,
        below what a line search in floating point resolves)."""
        return torch.tensor([n * h for n, h in zip(self.counts, self.entropies)], dtype=torch.float64,
                            device=self.nid.device)


def _point_pulls(d_u: torch.Tensor, d_v: torch.Tensor, p: torch.Tensor, q: torch.Tensor,
                 K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each point's share of d loss / d delta at delta's rotation 0: the torque q x d_p and the
    force d_p (rows, n, 3) each, of points p = q + delta[3:] (rows, n, 3, camera frame), given d
    loss / d (u, v) of their pinhole projections through K (rows, 4) (rows, n) each (0 for points
    that do not count)."""
    iz = 1.0 / p[..., 2].clamp_min(1e-9)
    g_x, g_y = d_u * K[:, 0:1] * iz, d_v * K[:, 1:2] * iz
    d_p = torch.stack([g_x, g_y, -(g_x * p[..., 0] + g_y * p[..., 1]) * iz], -1)
    return torch.linalg.cross(q, d_p), d_p


def _pose_gradient(d_u: torch.Tensor, d_v: torch.Tensor, p: torch.Tensor, q: torch.Tensor, K: torch.Tensor,
                   J: torch.Tensor) -> torch.Tensor:
    """(G, 6) d loss / d delta[g] of the points p = so3_exp(w[g]) q + delta[g, 3:] (G x F, n, 3,
    camera frame, in G groups of F rows), given d loss / d (u, v) of their pinhole projections
    through K (G x F, 4) (G x F, n) each (0 for points that do not count) and J =
    so3_left_jacobian(w) (G, 3, 3) float64."""
    G = J.shape[0]
    torque, d_p = (x.reshape(G, -1, 3).sum(1) for x in _point_pulls(d_u, d_v, p, q, K))
    # dp = (J dw) x q, so d loss / dw = J^T sum(q x d_p)
    return torch.cat([(J.transpose(1, 2) @ torque[..., None])[..., 0], d_p], 1)


def _channels(image: torch.Tensor, edges: bool) -> torch.Tensor:
    """(H, W, 3) photo -> (H, W, C): its luma and, with edges, the luma's gradient magnitude
    scaled by its 99th percentile into [0, 1]."""
    gray = (image * torch.tensor(LUMA, dtype=image.dtype, device=image.device)).sum(2, keepdim=True)
    if not edges:
        return gray
    gu, gv = central_gradients(gray)
    mag = torch.sqrt(gu * gu + gv * gv)
    top = torch.quantile(mag.flatten()[:: max(1, mag.numel() // 200_000)], 0.99).clamp_min(1e-6)
    return torch.cat([gray, (mag / top).clamp(0, 1)], dim=2)


# ring edges: returns at least this much nearer than their ring neighbour (the check's steps: with
# steps of 10 cm, kerbs and the like, a KITTI solve from the reference ended 1 cm further off), and
# EDGE_NEAR_M in front of the camera
EDGE_MIN_STEP_M = 1.0
# levels "auto" for nid: its search, sky charge and edge term were tuned on 5 levels; the photometric
# rule's 6 for Waymo's photos took a joint solve from 0.06 to 1.4 deg (docs/lidar-method.md)
NID_LEVELS = 5
# a point's weight in the histogram rises from 0 on the photo's border to 1 this many pixels in on
# the finest level, half as many a level up (`_Stack.inside`); 4 on every level took a KITTI joint
# solve from 3 deg to 10.5 deg: on level 4 (77 x 23 px) that band is a third of the photo's height
BORDER_PX = 4.0
EDGE_LEVELS = 3  # the term applies on the 3 finest levels: coarser, the spread edges fill the image (a KITTI photo is 77 x 23 on level 4)


def _ring_edges(steps: np.ndarray, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The indices (m,) of a frame's ring edges (depth steps (N,) of at least EDGE_MIN_STEP_M) and
    their strengths (m,) float64: sqrt(step / m), Levinson and Thrun's, so that a 5 m step counts
    5 times a 20 cm one, not 25 times."""
    idx = np.flatnonzero(steps >= EDGE_MIN_STEP_M)
    return (torch.as_tensor(idx, device=device),
            torch.as_tensor(np.sqrt(steps[idx].astype(np.float64)), device=device))


def _on_photo(photo: PhotoLevel, uv: torch.Tensor, z: torch.Tensor, near: float) -> torch.Tensor:
    """(n,) bool: points at least `near` metres in front that land on the level's usable pixels."""
    w, h = photo.camera.size
    ok = (z > near) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
    if photo.valid is not None:
        ok &= photo.valid[uv[:, 1].detach().clamp(0, h - 1).long(), uv[:, 0].detach().clamp(0, w - 1).long()]
    return ok


@dataclass
class NidBatch:
    """The terms of G poses on one level joined for one evaluation (`Nid.batch`)."""

    parts: _Parts  # G groups of F rows
    weights: torch.Tensor  # (G x F x C,) float64: each pose's frames' weights (`NidTerms.weights`)


@dataclass
class NidTerms:
    """NID at one pose on one level: the visible points per frame (kept by the calls that use
    these terms), the evaluation there and its frames' weights."""

    level: int
    parts: _Parts
    evaluation: _Evaluation
    weights: torch.Tensor  # (F x C,) float64
    # the frames' shares as quadratics at this pose (`Nid.frame_quadratics`), once the covariance made them
    quadratics: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    tiles: tuple[np.ndarray, np.ndarray] | None = None  # the frames' tile scores (`Nid.tile_scores`), likewise

    @property
    def loss(self) -> np.ndarray:
        return np.array([float(self.evaluation.loss)])

    @property
    def visible(self) -> np.ndarray:
        return np.array([sum(self.evaluation.counts)])


class Nid:
    """The NID objective of one pose against one or more frames (`Frame`). The frames are
    evaluated together (`_Parts`: a 19-frame KITTI joint solve took 55 s frame after frame, 39 s
    so), and several poses' parts joined into one evaluation (`batch`, `_per_frame_at`): the
    starts of a level, the uncertainty's steps."""

    name = "nid"
    method = "lbfgs"
    wide_search = True  # NID has spurious minima where other structure lines up by chance
    free = 0  # no camera corrections

    def __init__(self, frames: list[Frame], cfg: RefineConfig):
        self.cfg = cfg.check()
        self.device = frames[0].pyramid[0].image.device
        self.centre = np.concatenate([f.points for f in frames]).mean(axis=0)
        self.frames = frames
        self._points = [torch.as_tensor(f.points - self.centre, dtype=torch.float32, device=self.device) for f in frames]
        self._values = [torch.as_tensor(f.values, dtype=torch.float32, device=self.device).reshape(-1) for f in frames]
        self._keys = [torch.as_tensor(point_keys(f.points, cfg.seed), device=self.device) for f in frames]
        self._normals = [None if f.normals is None else torch.as_tensor(f.normals, dtype=torch.float32, device=self.device)
                         for f in frames]
        # per frame, per level: the channels NID compares, and the sky once it is found; then per
        # level all frames' in one `_Stack` (`prepare`)
        self._images = [[_channels(lv.image, cfg.nid_edges) for lv in f.pyramid] for f in frames]
        self._stacks: list[_Stack] | None = None
        # the ring edges of the ring-edge term (their indices and strengths), and the photos' maps once needed
        self._ring_edges = [None if f.edges is None else _ring_edges(f.edges, self.device) for f in frames]
        self._edge_maps: dict[int, _Stack] = {}  # per level, once needed
        self._prepared: list[list[torch.Tensor]] | None = None  # per level, per frame: point indices
        self._sky = [False] * len(frames)

    def of_frames(self, keep: list[int], cfg: RefineConfig | None = None) -> "Nid":
        """The objective of the frames `keep` (indices) alone (with cfg, default this one's): the
        frames judged apart."""
        return Nid([self.frames[k] for k in keep], cfg or self.cfg)

    # -- the points of each level (chosen once, at the init) ---------------------------------------
    def prepare(self, T_local: np.ndarray) -> int:
        """Per level, per frame: indices of a random subset of the points near the view of T_local
        (`near_view`; the same subset in any order of the points: align/subset.py), `max_points` at
        full resolution and a quarter per coarser level (nested), never fewer than `min_points`.
        Also finds each photo's sky, with the points seen at T_local (`_find_sky`), and appends it
        to the frame's images (one sampling serves both). Chosen once, at the first pose T_local
        (local frame). Returns the number of levels."""
        if self._prepared is not None:
            return len(self._prepared)
        cfg = self.cfg
        R, t = self._pose(T_local)
        per_frame = []
        for k, (f, pts) in enumerate(zip(self.frames, self._points)):
            finest = f.pyramid[0]
            uv, z = project_pinhole(pts @ R.T + t, finest.K)
            idx = torch.nonzero(near_view(uv, z, finest.camera.size, 0.1, cfg.max_depth)).squeeze(1)
            seen = visible_points(uv[idx], z[idx], finest.camera.size, 1, facing=self._facing(k, idx, R, t))
            if int(seen.sum()) < cfg.min_visible:
                raise InputError(f"fewer than {cfg.min_visible} scan points in view of the initial pose: "
                                 "check the pose, the camera file and the scan")
            check_spread_in_view(uv[idx], seen, cfg.min_visible)
            sky = self._find_sky(f, uv[idx][seen])
            if sky is not None:
                self._images[k] = [torch.cat([img, m], dim=2) for img, m in zip(self._images[k], sky)]
                self._sky[k] = True
            per_frame.append(idx[torch.argsort(self._keys[k][idx])])
        self._prepared = [[idx[: max(cfg.min_points, cfg.max_points // 4**level)] for idx in per_frame]
                          for level in range(len(self.frames[0].pyramid))]
        self._stacks = [_stack([images[level] for images in self._images], [f.pyramid[level].valid for f in self.frames],
                               BORDER_PX / 2**level)
                        for level in range(len(self._prepared))]
        self._images = None  # held once, in the stacks
        return len(self._prepared)

    def _find_sky(self, frame: Frame, uv: torch.Tensor) -> list[torch.Tensor] | None:
        """Per level (H, W, 1): the sky of the frame's photo (`sky_mask`), given the finest-level
        pixels uv (n, 2) of its points seen at the init; None when off or no sky is found."""
        import cv2

        from rgbd_gt.align.sky import sky_mask

        if self.cfg.sky_weight <= 0:
            return None
        mask = sky_mask(frame.pyramid[0].image.cpu().numpy(), uv.cpu().numpy())
        if not mask.any():
            return None
        return [torch.as_tensor(cv2.resize(mask, lv.camera.size, interpolation=cv2.INTER_AREA)[:, :, None],
                                device=self.device) for lv in frame.pyramid]

    def _pose(self, T_local: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        return (torch.as_tensor(T_local[:3, :3], dtype=torch.float32, device=self.device),
                torch.as_tensor(T_local[:3, 3], dtype=torch.float32, device=self.device))

    def _facing(self, k: int, idx: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor | None:
        """Which of frame k's points idx face the camera at (R, t) (None without normals)."""
        if self._normals[k] is None:
            return None
        return facing_camera(self._points[k][idx] @ R.T + t, self._normals[k][idx] @ R.T)

    def _parts(self, level: int, T_local: np.ndarray) -> _Parts:
        """The level's points that are visible at T_local (a Z-buffer with cells sized for their
        density in the image), all frames in one `_Parts`."""
        R, t = self._pose(T_local)
        points, windows, edges = [], [], []
        for k, idx in enumerate(self._prepared[level]):
            photo = self.frames[k].pyramid[level]
            pts = self._points[k][idx]
            uv, z = project_pinhole(pts @ R.T + t, photo.K)
            cell = cell_for_density(uv, photo.camera.size)
            vis = visible_points(uv, z, photo.camera.size, cell, self.cfg.zbuffer_rel_tol, self.cfg.zbuffer_abs_tol,
                                 facing=self._facing(k, idx, R, t))
            values = self._values[k][idx][:, None]
            if self.cfg.nid_edges:
                values = torch.cat([values, depth_edges(uv, z, photo.camera.size, cell)[:, None]], 1)
            points.append(pts[vis])
            windows.append(parzen_windows(values[vis].double().T, self.cfg.nid_bins).transpose(0, 1))
            edges.append(self._edges_of(k, level, R, t))
        photos = [f.pyramid[level] for f in self.frames]
        K = torch.stack([torch.stack([p.K[0, 0], p.K[1, 1], p.K[0, 2], p.K[1, 2]]) for p in photos]).float()
        sky = torch.tensor([float(self._sky[k] and level >= self.cfg.sky_coarse_level) for k in range(len(photos))],
                           dtype=torch.float64, device=self.device)
        parts = _Parts(_padded(points), _padded([torch.ones(len(p), dtype=torch.bool, device=self.device) for p in points]),
                       _padded(windows), self._stacks[level], K, sky)
        if any(e is not None for e in edges):
            none = (self._points[0][:0], torch.zeros(0, dtype=torch.float64, device=self.device))
            parts.edge_points = _padded([(e or none)[0] for e in edges])
            parts.edge_strength = _padded([(e or none)[1] for e in edges])
            parts.edge_maps = self._edge_map_stack(level)
        return parts

    def _edges_of(self, k: int, level: int, R: torch.Tensor, t: torch.Tensor) -> tuple | None:
        """(edge points, strengths) of frame k on a level, or None without the term: the ring
        edges on the photo at (R, t), which the later evaluations of these parts keep. A score
        over whatever edges land on the photo grew as the camera backed away and took in more of
        them: on KITTI its pull alone ran to 20 cm along the optical axis."""
        if self._ring_edges[k] is None or self.cfg.edge_weight <= 0 or level >= EDGE_LEVELS:
            return None
        idx, strength = self._ring_edges[k]
        pts = self._points[k][idx]
        photo = self.frames[k].pyramid[level]
        ok = _on_photo(photo, *project_pinhole(pts @ R.T + t, photo.K), EDGE_NEAR_M)
        return pts[ok], strength[ok]

    def _edge_map_stack(self, level: int) -> _Stack:
        """The frames' photos' edges spread (`edge_distance_map`) on a level, zero for frames without ring edges."""
        if level not in self._edge_maps:
            from rgbd_gt.align.edge_map import edge_distance_map

            photos = [f.pyramid[level] for f in self.frames]
            self._edge_maps[level] = _stack([
                edge_distance_map(p.image) if e is not None else p.image.new_zeros(p.image.shape[:2] + (1,))
                for p, e in zip(photos, self._ring_edges)])
        return self._edge_maps[level]

    # -- NID at a pose ------------------------------------------------------------------------------
    def _evaluate(self, parts: _Parts, Ts: list[np.ndarray], delta: torch.Tensor,
                  weights: torch.Tensor | None = None, shares: list | None = None) -> _Evaluation:
        """NID per frame and channel pair at apply_update(Ts[g], delta[g]) for each of G poses
        (delta (G, 6) float64; parts: G groups of F rows, `_joined`, or F rows for one pose), on
        the points that land on usable pixels. With weights (G x F x C,), also each pose's gradient
        of sum(weights * NID) with respect to its delta, in closed form (`nid_with_gradient` and
        the derivative of the bilinear interpolant, as strategy A); delta may also be
        differentiated by autograd (tests compare the two). All frames and poses at once: a rig's
        19 frames, or the wide search's 17 starts, cost a few operations each, not 19 or 17. With
        weights and a list `shares`, one pose at delta 0: each point's share of the gradient is
        appended to it, as (pixels (F, n, 2), shares (F, n, 6)), for the NID's points and the ring
        edges (`tile_scores`)."""
        T = torch.as_tensor(np.stack(Ts)[:, :3], dtype=torch.float32, device=self.device)  # (G, 3, 4)
        R = so3_exp(delta[:, :3]).to(T.dtype)
        R1, t1 = R @ T[:, :, :3], (R @ T[:, :, 3:])[..., 0]
        rows, C = parts.windows.shape[0], parts.windows.shape[2]
        edges = torch.zeros(rows, dtype=torch.float64, device=self.device)
        gradient = J = None
        if weights is not None:
            J = so3_left_jacobian(delta[:, :3].double())
            gradient = torch.zeros(len(Ts), 6, dtype=torch.float64, device=self.device)
        if parts.edge_points is not None:
            score, g = self._edge_score(parts, R1, t1, delta, J, shares)
            edges = self.cfg.edge_weight * score
            if g is not None:
                gradient -= self.cfg.edge_weight * g
        q, p = _moved(parts.points, R1, t1, delta)
        uv, z = _project(p, parts.K)
        ok = parts.images.on_photo(uv, z, 0.1) & parts.real
        counts = ok.sum(1).tolist()
        inside, in_u, in_v = parts.images.inside(uv)
        use = ok.to(torch.float64) * inside  # the points off the photo do not count, those at its border partly
        if weights is None:
            sampled = parts.images.sample(uv).double()
        else:
            sampled, s_u, s_v = (x.double() for x in parts.images.sample(uv, gradient=True))
            d_sampled = torch.zeros_like(sampled)  # d loss / d sampled channel
            d_use = torch.zeros_like(use)  # d loss / d use
            w = weights.reshape(rows, C)
        sky = parts.sky.any()
        nids, entropies = [], []
        for c in range(C):
            if weights is None:
                value, h_ab = nid_of_windows(parts.windows[:, :, c], parzen_windows(sampled[..., c], self.cfg.nid_bins, use))
            else:
                value, h_ab, d_value, d_weight = nid_with_gradient(parts.windows[:, :, c], sampled[..., c], self.cfg.nid_bins, use)
                d_sampled[..., c] = w[:, c:c + 1] * d_value
                d_use += w[:, c:c + 1] * d_weight
            if c == 0 and sky:
                n = use.sum(1).clamp_min(1e-12)
                on_sky = (sampled[..., -1] * use).sum(1) / n
                value = value + self.cfg.sky_weight * parts.sky * on_sky
                if weights is not None:
                    charge = (w[:, 0] * self.cfg.sky_weight * parts.sky / n)[:, None]
                    d_sampled[..., -1] = charge * use
                    d_use += charge * (sampled[..., -1] - on_sky[:, None])
            nids.append(value)
            entropies.append(h_ab)
        if weights is not None:
            d_use = d_use * ok  # the hard edges of `on_photo` (depth, usable pixels) have no slope
            d_u = (d_sampled * s_u).sum(-1) + d_use * in_u
            d_v = (d_sampled * s_v).sum(-1) + d_use * in_v
            p, q = p.double(), q.double()
            gradient += _pose_gradient(d_u, d_v, p, q, parts.K.double(), J)
            if shares is not None:
                shares.append((uv, torch.cat(_point_pulls(d_u, d_v, p, q, parts.K.double()), -1)))
        return _Evaluation(torch.stack(nids, 1).reshape(-1), [k for k in counts for _ in range(C)],
                           torch.stack(entropies, 1).reshape(-1).detach().tolist(), edges, gradient, len(Ts))

    def _at(self, parts: _Parts, T_local: np.ndarray, delta: torch.Tensor | None = None) -> _Evaluation:
        """`_evaluate` at one pose apply_update(T_local, delta) (delta (6,), default 0), without
        the gradient; InputError where it left the scan."""
        if delta is None:
            delta = torch.zeros(6, dtype=torch.float64, device=self.device)
        with torch.no_grad():
            e = self._evaluate(parts, [T_local], delta[None])
        if e.lost[0]:
            raise InputError(LEFT_THE_SCAN)
        return e

    def _per_frame_at(self, parts: _Parts, T_local: np.ndarray, deltas: torch.Tensor,
                      weights: torch.Tensor) -> np.ndarray:
        """(D, F) each frame's share of the objective (`_Evaluation.per_frame` with weights (F x
        C,)) at apply_update(T_local, deltas[d]) (deltas (D, 6) float64), the deltas evaluated
        together in groups of at most LOCKSTEP_POINTS points (on a single frame's finest level an
        evaluation is mostly per-call overhead); InputError where one left the scan."""
        joined: dict[int, _Parts] = {}  # per group size: the groups but the last are the same size
        out = []
        with torch.no_grad():
            for group in lockstep([int(parts.real.sum())] * len(deltas)):
                if len(group) not in joined:
                    joined[len(group)] = _joined([parts] * len(group))
                e = self._evaluate(joined[len(group)], [T_local] * len(group), deltas[group])
                if e.lost.any():
                    raise InputError(LEFT_THE_SCAN)
                out.append(e.per_frame(weights.repeat(len(group))).reshape(len(group), -1))
        return torch.cat(out).cpu().numpy()

    def _edge_score(self, parts: _Parts, R: torch.Tensor, t: torch.Tensor, delta: torch.Tensor,
                    J: torch.Tensor | None, shares: list | None = None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The ring-edge score of each frame (G x F,) at apply_update((R[g], t[g]), delta[g]) (R (G,
        3, 3), t (G, 3), delta (G, 6)): sum over its ring edges (those on the photo when the parts
        were made, `_edges_of`) of strength x the photo's edge map there, and per pose the gradient
        (G, 6) of their sum with respect to delta when asked by J = so3_left_jacobian(delta[:, :3])
        (G, 3, 3) (else None), each edge's share of the objective's gradient appended to `shares`
        when given (`_evaluate`). The edges are not Z-buffered: a step's nearer return is the
        foreground, which the camera sees but for the parallax of the sensor's offset."""
        q, p = _moved(parts.edge_points, R, t, delta)
        uv, z = _project(p, parts.K)
        size = parts.edge_maps.size
        # an edge that leaves the photo keeps the border's value (the samplers clamp to it): the score is continuous
        inside_u = (uv[..., 0] >= 0) & (uv[..., 0] <= size[:, 0:1] - 1)
        inside_v = (uv[..., 1] >= 0) & (uv[..., 1] <= size[:, 1:2] - 1)
        strength = parts.edge_strength * (z > 0.1)
        if J is None:
            return (strength * parts.edge_maps.sample(uv)[..., 0].double()).sum(1), None
        sampled, s_u, s_v = (x[..., 0].double() for x in parts.edge_maps.sample(uv, gradient=True))
        d_u, d_v, p, q = strength * s_u * inside_u, strength * s_v * inside_v, p.double(), q.double()
        gradient = _pose_gradient(d_u, d_v, p, q, parts.K.double(), J)
        if shares is not None:  # the objective less the edges' score
            shares.append((uv, -self.cfg.edge_weight * torch.cat(_point_pulls(d_u, d_v, p, q, parts.K.double()), -1)))
        return (strength * sampled).sum(1), gradient

    def units(self, level: int, T_local: np.ndarray, at: "NidTerms") -> torch.Tensor:
        """(6,) float64 size of each pose parameter that moves the points of `at` by 1 pixel (RMS)."""
        parts = at.parts
        R, t = self._pose(T_local)
        sq, n = torch.zeros(6, device=self.device), 0
        for points, real, K in zip(parts.points, parts.real, parts.K):
            du, dv = projection_jacobian(points[real] @ R.T + t, K[0], K[1])
            sq += (du * du + dv * dv).sum(0)
            n += du.shape[0]
        return (1.0 / torch.sqrt(sq / max(n, 1)).clamp_min(1e-12)).double()

    # -- what the driver asks ----------------------------------------------------------------------
    def evaluate(self, level: int, Ts: list[np.ndarray], q=None, prev=None, jacobian: bool = False, free=None,
                 lost_is_error: bool = True) -> "NidTerms":
        """NID at the one local-frame pose of Ts, on the level's points visible there (which the
        later calls with these terms keep). Raises InputError where fewer than 50 points land on
        usable pixels. (q, prev, jacobian, free, lost_is_error: the driver's interface; NID has
        no Gauss-Newton terms.)"""
        (T,) = Ts
        parts = self._parts(level, T)
        at = self._at(parts, T)
        return NidTerms(level, parts, at, at.weights())

    def trial(self, level: int, Ts: list[np.ndarray], q, at: "NidTerms") -> np.ndarray:
        """(B,) mean NID at each local-frame pose of Ts on the points of `at`."""
        return np.array([float(self._at(at.parts, T).loss) for T in Ts])

    def batch(self, terms: list["NidTerms"]) -> "NidBatch":
        """The terms of G poses on one level, for `value_and_gradient` to evaluate together."""
        return NidBatch(_joined([t.parts for t in terms]), torch.cat([t.weights for t in terms]))

    def value_and_gradient(self, level: int, Ts: list[np.ndarray], delta: torch.Tensor,
                           batch: "NidBatch") -> tuple[np.ndarray, torch.Tensor]:
        """Per pose g of Ts: sum(weights * NID) at apply_update(Ts[g], delta[g]) (delta (G, 6)
        float64) on the points of its terms in `batch` (`Nid.batch`), with their weights
        (`_Evaluation.weights`: the frames count by their evidence): (G,) float64, NaN for a pose
        that left the scan (`LEFT_THE_SCAN`); and the gradients (G, 6) with respect to delta."""
        with torch.no_grad():
            e = self._evaluate(batch.parts, Ts, delta, batch.weights)
        values = e.objective(batch.weights).cpu().numpy()
        values[e.lost] = np.nan
        return values, e.gradient

    def summary(self, terms: "NidTerms") -> dict:
        """`RefineResult`'s objective-specific fields at the terms' pose."""
        level_points = sum(int(idx.numel()) for idx in self._prepared[terms.level])
        seen = sum(terms.evaluation.counts[:: 2 if self.cfg.nid_edges else 1])  # per frame, not per channel pair
        return {"color_transform": np.zeros((0, 0)), "loss": float(terms.evaluation.loss),
                "inlier_fraction": seen / max(level_points, 1), "visible_points": seen}

    def residuals(self, level: int, terms: "NidTerms") -> None:
        """NID has no per-point residual."""
        return None

    def visible_scan_points(self, T_local: np.ndarray, q=None) -> np.ndarray:
        """(n, 3) float64 local-frame points of the first frame's finest level visible at T_local."""
        parts = self._parts(0, T_local)
        return parts.points[0][parts.real[0]].double().cpu().numpy()

    def median_depth(self, T_local: np.ndarray) -> float:
        """Median depth (m) of all frames' finest-level points visible at T_local."""
        parts = self._parts(0, T_local)
        R, t = self._pose(T_local)
        return float((parts.points @ R.T + t)[..., 2][parts.real].median())

    def frame_quadratics(self, level: int, T_local: np.ndarray, terms: "NidTerms") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each frame's share of the objective (`_Evaluation.per_frame`, its weights those of
        `terms`, the evaluation at T_local) as a quadratic in the pose update measured in steps of
        one pixel of image motion (`units`): gradients g (F, 6) and Hessians H (F, 6, 6) from
        central differences over one pixel along each parameter and each pair (73 evaluations:
        the exact gradient of the bilinear interpolant jumps at pixel borders, and its
        differences over half a pixel were not positive definite at most right results on real
        sweeps, docs/lidar-method.md); and the units (6,) (rad, m per step)."""
        parts, at = terms.parts, terms.evaluation
        units = self.units(level, T_local, terms)
        weights = at.weights()
        E = np.eye(6)
        pairs = list(zip(*np.triu_indices(6, 1)))
        steps = np.concatenate([E, -E] + [[E[i] + E[j], E[i] - E[j], E[j] - E[i], -E[i] - E[j]] for i, j in pairs])
        f = self._per_frame_at(parts, T_local, torch.as_tensor(steps, device=self.device) * units, weights)
        plus, minus, corners = f[:6], f[6:12], f[12:].reshape(len(pairs), 4, -1)
        f0 = at.per_frame(weights).cpu().numpy()
        H = np.zeros((len(f0), 6, 6))
        for i in range(6):
            H[:, i, i] = plus[i] - 2 * f0 + minus[i]
        for (i, j), c in zip(pairs, corners):
            H[:, i, j] = H[:, j, i] = (c[0] - c[1] - c[2] + c[3]) / 4
        g = (plus - minus).T / 2
        return g, H, units.cpu().numpy()

    def tile_scores(self, level: int, T_local: np.ndarray, terms: "NidTerms",
                    tiles: int = TILES) -> tuple[np.ndarray, np.ndarray]:
        """The exact gradient of the objective at T_local (terms' points and weights) summed over
        the points and ring edges in each of tiles x tiles tiles of each frame's photo, (K, 6) for
        the K tiles with any, and the Hessian (6, 6) of terms.quadratics (`frame_quadratics`,
        summed over the frames), both per radian and metre: the samples of the covariance with the
        tiles as the samples (`align.covariance.sandwich`), as a photo of a colored scan's
        (`Photometric.tile_scores`). NID is no sum over points, but its gradient is: each
        point's share is its pull through the histogram's derivative."""
        shares: list = []
        with torch.no_grad():
            self._evaluate(terms.parts, [T_local], torch.zeros(1, 6, dtype=torch.float64, device=self.device),
                           terms.weights, shares)
        size = terms.parts.images.size  # (F, 2) W, H
        sums = torch.zeros(len(size) * tiles * tiles, 6, dtype=torch.float64, device=self.device)
        counts = torch.zeros(len(sums), dtype=torch.long, device=self.device)
        frame = torch.arange(len(size), device=self.device)[:, None]
        for uv, pull in shares:
            col = (uv[..., 0] * (tiles / size[:, 0:1])).long().clamp(0, tiles - 1)
            row = (uv[..., 1] * (tiles / size[:, 1:2])).long().clamp(0, tiles - 1)
            tile = ((frame * tiles + row) * tiles + col).reshape(-1)
            pull = pull.reshape(-1, 6)
            sums.index_add_(0, tile, pull)
            counts += torch.bincount(tile[(pull != 0).any(1)], minlength=len(sums))
        _, H, u = terms.quadratics
        return sums[counts > 0].cpu().numpy(), H.sum(0) / np.outer(u, u)

    def covariance(self, level: int, T_local: np.ndarray, q, terms: "NidTerms") -> np.ndarray:
        """Laplace approximation: the inverse Hessian of the negative log-likelihood
        sum_f n_f H_f NID_f (`_Evaluation.weights`), summed over the frames' `frame_quadratics`;
        a lower bound, as neighbouring points share photo pixels. All inf where it is not
        positive definite: no minimum. The quadratics stay in terms.quadratics (the verdict's
        frames judged against each other use them), and the frames' tiles, the samples of a wider
        one, in terms.tiles (`tile_scores`)."""
        terms.quadratics = self.frame_quadratics(level, T_local, terms)
        terms.tiles = self.tile_scores(level, T_local, terms)
        _, H, u = terms.quadratics
        H = H.sum(0)
        if np.linalg.eigvalsh(H)[0] <= 0:
            return np.full((6, 6), np.inf)
        return np.linalg.inv(H) * u[:, None] * u[None, :]

    # -- what the verification asks (see `Aligner`) ---------------------------------------------------
    def ring_edge_check(self, T_local: np.ndarray, shift_px: float) -> dict | None:
        """The image check of a sweep (whose rendering is too sparse for `qa.edges.structural_qa`):
        at T_local on the finest level, the photos' `edge_strength` at the frames' ring edges of
        CHECK_MIN_STEP_M and more (weighted by their strengths) against the same with the edges
        shifted shift_px in 8 directions (chance), over all frames; with several frames, also each
        frame's own (`frames`: its ring edges and ratio, None for a frame without ring edges). None
        without ring edges."""
        from rgbd_gt.align.edge_map import against_chance, edge_strength

        if all(r is None for r in self._ring_edges):
            return None
        R, t = self._pose(T_local)
        score = chance = weight = 0.0
        count = 0
        frames: list[dict | None] = []
        for k, edges in enumerate(self._ring_edges):
            if edges is None:
                frames.append(None)
                continue
            idx, strength = edges
            strong = strength >= CHECK_MIN_STEP_M**0.5
            idx, strength = idx[strong], strength[strong]
            photo = self.frames[k].pyramid[0]
            uv, z = project_pinhole(self._points[k][idx] @ R.T + t, photo.K)
            ok = _on_photo(photo, uv, z, EDGE_NEAR_M)
            s, uv = strength[ok], uv[ok]
            image = torch.as_tensor(edge_strength(photo.image)[:, :, None], device=self.device)
            mine, mine_chance = against_chance(image, uv, s, shift_px)
            frames.append({"ring_edges": int(ok.sum()), "ratio": mine / mine_chance if mine_chance > 0 else float("nan")})
            score += mine
            chance += mine_chance
            weight += float(s.sum())
            count += int(ok.sum())
        out = {"ring_edges": count, "score": score / max(weight, 1e-12), "chance": chance / max(weight, 1e-12),
               "ratio": score / chance if chance > 0 else float("nan"), "shift_px": shift_px}
        return out | ({"frames": frames} if len(frames) > 1 else {})

