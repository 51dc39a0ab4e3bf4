"""The photometric objective of "Multimodal Colored Point Cloud to Image Alignment" (Rotstein,
Bracha, Kimmel, CVPR 2022), evaluated on a batch of poses at once (one pose is a batch of one).

At each pose of the batch: move the points, drop occluded ones (coarse Z-buffer), project, sample
the photo bilinearly with its gradient (strategy A or B), lift the colors with the color model's
kernel, fit the color transform D on inliers, clip the prediction to [0, 1] (keeping the
unclipped gradient), and weight the residuals with a Student-t. It returns the robust loss and
the Gauss-Newton terms of the 6 pose parameters and of the shared camera corrections q
(`render.project.project_corrected`); the driver (align/aligner.py) optimises them.
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass

import numpy as np
import torch

from rgbd_gt.align.color_models import ColorModel, fit_many_with_inliers, unclipped
from rgbd_gt.align.config import RefineConfig
from rgbd_gt.align.covariance import TILES
from rgbd_gt.align.pyramid import PhotoLevel
from rgbd_gt.align.robust import student_t_loss, student_t_weights
from rgbd_gt.align.sampling import bilinear, bilinear_sparse, bilinear_with_gradient, central_gradients
from rgbd_gt.align.subset import near_view, point_keys
from rgbd_gt.camera import INTRINSICS, Q_SIZE, fold_radius
from rgbd_gt.errors import InputError
from rgbd_gt.render.normals import facing_camera
from rgbd_gt.render.project import corrected_jacobian, project_corrected, project_pinhole, projection_jacobian
from rgbd_gt.render.cells import cell_size_for
from rgbd_gt.render.zbuffer import check_spread_in_view, estimate_spacing, visible_points

@dataclass
class Level:
    """The objective's data on one pyramid level."""

    photo: PhotoLevel
    image: torch.Tensor  # (H, W, C) what is sampled: the photo, and its gray's high pass where the sharpness is fitted
    grads: tuple[torch.Tensor, torch.Tensor] | None
    points: torch.Tensor  # (n, 3) float32, local frame
    target: torch.Tensor  # (n, m)
    cell: int
    normals: torch.Tensor | None = None  # (n, 3) float32, facing the scanner (render/normals.py)


@dataclass
class Terms:
    """The objective at B poses of one level: per pose its visible points, color fit, robust
    scale, loss and (when asked) Gauss-Newton system. P = 6 pose parameters, plus the free camera
    corrections when they are refined."""

    loss: np.ndarray  # (B,) robust loss with this D and sigma
    D: torch.Tensor  # (B, m, k)
    sigma2: torch.Tensor  # (B, 1, 1)
    mask: torch.Tensor  # (B, n) the level's points visible on usable pixels
    visible: np.ndarray  # (B,) int
    inlier_fraction: np.ndarray  # (B,) of the visible points
    err: torch.Tensor  # (B, n) |r| per point (meaningful where mask)
    uv: torch.Tensor  # (B, n, 2) level pixels
    H: np.ndarray | None = None  # (B, P, P) J^T W J
    g: np.ndarray | None = None  # (B, P) J^T W r
    wrr: np.ndarray | None = None  # (B,) sum of w r^2 over points and channels
    count: np.ndarray | None = None  # (B,) residuals: points x channels
    # one pose, with its system: the unclipped predictions (c, m) at its visible points and their
    # derivatives' factors dr/du, dr/dv (c, m) and du, dv (c, P) (`own_colors`)
    seen: tuple | None = None
    pulls: tuple | None = None  # ... and each visible point's pull (`_normal_equations`): two (c,)
    # the photo's tiles as the samples (`Photometric.tile_scores`), once the covariance made them
    tiles: tuple[np.ndarray, np.ndarray] | None = None

    def where(self, keep: np.ndarray, other: "Terms") -> "Terms":
        """Per pose: these terms where keep (B,) is True, else other's."""
        if keep.all():
            return self
        k = torch.as_tensor(keep, device=self.D.device)

        def pick(a, b):
            if a is None:
                return None
            if isinstance(a, np.ndarray):
                return np.where(keep.reshape((-1,) + (1,) * (a.ndim - 1)), a, b)
            return torch.where(k.reshape((-1,) + (1,) * (a.dim() - 1)), a, b)

        return Terms(*(pick(getattr(self, f), getattr(other, f)) for f in self.__dataclass_fields__))

    def record(self, b: int = 0) -> dict:
        """Pose b's figures for the refine history."""
        return {"loss": float(self.loss[b]), "median_residual": float(self.err[b][self.mask[b]].median()),
                "visible": int(self.visible[b]), "inlier_fraction": float(self.inlier_fraction[b])}


def texture_score(uv: torch.Tensor, z: torch.Tensor, size: tuple[int, int], cell: int,
                  colors: torch.Tensor) -> torch.Tensor:
    """Per point (N,), the local contrast of the scan's own colors as seen from a pose: the
    visible points' mean gray per Z-buffer cell, then the central-difference gradient magnitude
    of that cell image, widened by a 3x3 maximum. 0 for points outside the image."""
    w, h = size
    vis = visible_points(uv, z, size, cell)
    cw, ch = (w + cell - 1) // cell, (h + cell - 1) // cell
    key = (uv[:, 1].clamp(0, h - 1) / cell).long() * cw + (uv[:, 0].clamp(0, w - 1) / cell).long()
    gray = colors.mean(dim=1)
    total = torch.zeros(ch * cw, dtype=gray.dtype, device=gray.device).index_add_(0, key[vis], gray[vis])
    count = torch.zeros_like(total).index_add_(0, key[vis], torch.ones_like(gray[vis]))
    img = (total / count.clamp_min(1)).reshape(ch, cw)
    have = (count > 0).reshape(ch, cw)
    g = torch.zeros_like(img)
    ok = have[:, 2:] & have[:, :-2]
    g[:, 1:-1] += torch.where(ok, (img[:, 2:] - img[:, :-2]).abs(), torch.zeros_like(img[:, 1:-1]))
    ok = have[2:] & have[:-2]
    g[1:-1] += torch.where(ok, (img[2:] - img[:-2]).abs(), torch.zeros_like(img[1:-1]))
    g = torch.nn.functional.max_pool2d(g[None, None], 3, stride=1, padding=1)[0, 0]
    return torch.where(vis, g.reshape(-1)[key], torch.zeros_like(gray))


def pixel_sums(uv: torch.Tensor, target: torch.Tensor, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """The pixels of an image of size (W, H) that points at uv (N, 2) fall nearest to: their flat
    indices (K,) sorted, and per pixel the sum of those points' targets (N, m) and their count
    (K, m + 1). Only the occupied pixels: a 24-megapixel photo's levels cost what the scan has."""
    w, h = size
    ok = (uv[:, 0] > -0.5) & (uv[:, 1] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] < h - 0.5)
    keys, inverse = torch.unique((uv[ok, 1] + 0.5).long() * w + (uv[ok, 0] + 0.5).long(), return_inverse=True)
    sums = torch.zeros(keys.numel(), target.shape[1] + 1, dtype=target.dtype, device=target.device)
    return keys, sums.index_add_(0, inverse, torch.cat([target[ok], torch.ones_like(target[ok, :1])], 1))


def halved(cells: tuple[torch.Tensor, torch.Tensor], size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """`pixel_sums` of an image of size (W, H) on the next pyramid level (W // 2, H // 2): each
    level pixel sums its 2x2 pixels, as the pyramid's box averaging does (align/pyramid.py)."""
    keys, sums = cells
    w = size[0]
    y, x = keys // w // 2, keys % w // 2
    ok = (x < w // 2) & (y < size[1] // 2)
    new, inverse = torch.unique(y[ok] * (w // 2) + x[ok], return_inverse=True)
    return new, torch.zeros(new.numel(), sums.shape[1], dtype=sums.dtype, device=sums.device).index_add_(0, inverse, sums[ok])


def blurred_targets(cells: tuple[torch.Tensor, torch.Tensor], size: tuple[int, int], uv: torch.Tensor,
                    target: torch.Tensor) -> torch.Tensor:
    """The targets (n, m) of points at uv (n, 2) of a coarse pyramid level of size (W, H), blurred
    as the level blurs the photo: the mean target of the seen points in each level pixel (cells:
    `pixel_sums`, the level's box average), sampled bilinearly (the aligner's interpolant). Without
    it a coarse level compares a blurred photo with sharp scan colors: the black and white points
    of a checkerboard that the level averages to gray pull towards the board shifted by a square
    (docs/intrinsics.md). Points with no seen point near keep their own target."""
    m = target.shape[1]
    s = bilinear_sparse(*cells, size[::-1], uv)
    return torch.where(s[:, m:] > 1e-3, s[:, :m] / s[:, m:].clamp_min(1e-3), target)


def high_pass(image: torch.Tensor, sigma: float) -> torch.Tensor:
    """(H, W, C) image less its Gaussian blur of `sigma` pixels (reflected at the borders), on
    the image's device (blurred by OpenCV on the CPU: 20 times torch's convolution there).

    Part of the color fit (`RefineConfig.fit_sharpness`): a photo blurred more than the scan's
    colors is about the scan's colors blurred, and blur minus sharp is about a multiple of this
    high pass, which the fit's weights on it undo (or add, for a photo sharper than the scan).
    """
    import cv2

    img = image.cpu().numpy()
    blurred = cv2.GaussianBlur(img, (0, 0), sigma, borderType=cv2.BORDER_REFLECT).reshape(img.shape)
    return image - torch.as_tensor(blurred, device=image.device)


def _normal_equations(du: torch.Tensor, dv: torch.Tensor, a: torch.Tensor, b: torch.Tensor, r: torch.Tensor,
                      w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, tuple[torch.Tensor, torch.Tensor]]:
    """The Gauss-Newton system J^T W J (B, 6, 6) and J^T W r (B, 6), float64, of B poses' residuals
    r (B, n, m) with weights w (B, n, m) (0 for points not used), where the residual's Jacobian
    is J_nm = a_nm du_n + b_nm dv_n: a, b (B, n, m) its derivatives along the image axes, du, dv
    (B, n, 6) the pixel motion per pose parameter. Summed over the channels first, which needs
    only 2x2 sums per point. Also each point's pull (sum_m w a r, sum_m w b r), two (B, n): its
    share of J^T W r is du_n times the first plus dv_n times the second."""
    saa, sab, sbb = ((w * a * a).sum(2).double(), (w * a * b).sum(2).double(), (w * b * b).sum(2).double())
    sar, sbr = (w * a * r).sum(2).double(), (w * b * r).sum(2).double()
    du, dv = du.double(), dv.double()
    duT, dvT = du.transpose(1, 2), dv.transpose(1, 2)
    cross = duT @ (sab[..., None] * dv)
    H = duT @ (saa[..., None] * du) + cross + cross.transpose(1, 2) + dvT @ (sbb[..., None] * dv)
    return H, (duT @ sar[..., None] + dvT @ sbr[..., None])[..., 0], (sar, sbr)


def scaled_inverse(H: np.ndarray) -> np.ndarray:
    """The inverse of a Gauss-Newton matrix H (P, P), inverted with its parameters scaled to unit
    diagonal (rotations, metres and camera corrections differ by orders of magnitude); all inf
    where H is singular or not finite (built from another such inverse)."""
    if not np.isfinite(H).all():
        return np.full(H.shape, np.inf)
    s = 1.0 / np.sqrt(np.clip(np.diag(H), 1e-30, None))
    Hs = H * s[:, None] * s[None, :]
    eig = np.linalg.eigvalsh(Hs)
    if eig[0] <= eig[-1] * 1e-12:
        return np.full(H.shape, np.inf)
    return s[:, None] * np.linalg.inv(Hs) * s[None, :]


def covariance(H: np.ndarray, energy: float, count: int) -> np.ndarray:
    """The covariance (P, P) of the parameters (the pose's 6 first) from a Gauss-Newton matrix
    H = J^T W J, scaled by the residual variance energy / (count - P) (energy = sum w r^2), or
    all inf where H is singular (`scaled_inverse`). Residuals are treated as independent:
    neighbouring points share photo pixels, so this is a lower bound."""
    inverse = scaled_inverse(H)
    return inverse if np.isinf(inverse).all() else energy / max(count - len(H), 1) * inverse


def _times_transposed(a: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """a M^T per pose: a (B, n, k) or (n, k) shared by the poses, M (B, m, k) -> (B, n, m). One
    pose as a plain 2-D product: torch's batched kernel is slower there (a refine is one pose)."""
    if M.shape[0] == 1:
        return ((a[0] if a.dim() == 3 else a) @ M[0].T)[None]
    return a @ M.transpose(1, 2)


def _valid_at(valid: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """All four bilinear neighbours of uv (N, 2) are usable pixels."""
    h, w = valid.shape
    u0 = uv[:, 0].floor().clamp(0, w - 2).long()
    v0 = uv[:, 1].floor().clamp(0, h - 2).long()
    return valid[v0, u0] & valid[v0, u0 + 1] & valid[v0 + 1, u0] & valid[v0 + 1, u0 + 1]


POOL = 16  # x max_points: the most scan points an aligner keeps (drawn at random)


class Photometric:
    """The photometric objective of one photo against one colored scan.

    Args:
        points: (N, 3) float64 scan points (metres, scan frame).
        colors: (N, 3) uint8 colors, or (N, 1) intensity in [0, 1] for scans without color.
        pyramid: the photo's pyramid (`photo_pyramid`), finest first.
        cfg: settings.
        normals: (N, 3) unit normals facing the scanner (`render.normals.scan_normals`), or None:
            points seen from behind are then not told apart.
    """

    name = "photometric"
    wide_search = False

    def __init__(self, points: np.ndarray, colors: np.ndarray, pyramid: list[PhotoLevel], cfg: RefineConfig,
                 normals: np.ndarray | None = None):
        self.cfg = cfg.check()
        self.pyramid = pyramid
        self.device = pyramid[0].image.device
        self.dtype = torch.float32
        self.model = ColorModel(cfg.color_model)
        if len(points) > POOL * cfg.max_points:
            # a big scan's view: a random pool, so that setting up costs what max_points needs. Its
            # keys are a stream of their own: its lowest keys, reused as `self.keys`, would rank its
            # points with noise squeezed into (0, 0.18) and the subsets follow texture alone
            # (docs/scale.md: repeats 7-14 px apart on a 7-million-point view)
            pool = POOL * cfg.max_points
            keep = np.sort(np.argpartition(point_keys(points, cfg.seed + 1), pool)[:pool])
            points, colors = points[keep], colors[keep]
            normals = None if normals is None else normals[keep]
        # a local frame keeps float32 exact for georeferenced coordinates
        self.centre = points.mean(axis=0)
        self.points = torch.as_tensor(points - self.centre, dtype=self.dtype, device=self.device)
        c = torch.as_tensor(colors, device=self.device)
        c = c.to(self.dtype) / 255.0 if colors.dtype == np.uint8 else c.to(self.dtype)
        self.target = self.model.target(c.reshape(len(points), -1))
        self.normals = None if normals is None else torch.as_tensor(normals, dtype=self.dtype, device=self.device)
        self.keys = torch.as_tensor(point_keys(points, cfg.seed), device=self.device)  # the subsets' order (align/subset.py)
        # the camera corrections refined with the pose (cfg.refine_intrinsics: the first `free` of q),
        # parameters shared by every pose of a batch
        self.free = INTRINSICS[cfg.refine_intrinsics]
        # a photo kept as taken (`photo_pyramid`'s `distorted`) is projected through its file's
        # distortion, to which q's corrections add (q's distortion slots are OpenCV's k1 k2 p1 p2 k3)
        lens = list(self.pyramid[0].camera.distortion)[:Q_SIZE - 3]
        self.lens = torch.zeros(Q_SIZE, dtype=self.dtype, device=self.device)
        self.lens[3:3 + len(lens)] = torch.as_tensor(lens, dtype=self.dtype)
        self.distorted = bool(self.lens.abs().sum() > 0)
        self.fold = fold_radius(self.pyramid[0].camera.distortion)  # beyond it the lens model turns back (ghosts)
        self.method = cfg.optimizer  # 'lm' or 'adam' (align/aligner.py)
        self.sharpness = cfg.fit_sharpness and self.model.fitted
        self.levels: list[Level] | None = None

    def freeing(self, free: int) -> "Photometric":
        """This objective with the first `free` camera corrections refined with the pose: the
        same points, levels and photo (the verdict's camera check frees the focal length of a
        result refined without it)."""
        other = copy.copy(self)
        other.free = free
        return other

    def prepare(self, T_local: np.ndarray) -> int:
        """Per level: a random subset of the points near the initial view (`near_view`; nested
        subsets, `max_points` at full resolution and a quarter per coarser level, the same in any
        order of the points: align/subset.py) and its Z-buffer cell, chosen once at the first pose
        T_local (4x4, local frame): every later evaluation, the verification's repeat runs from
        nearby starts included, sees the same points. Returns the number of levels."""
        if self.levels is not None:
            return len(self.levels)
        finest = self.pyramid[0]
        R, t = self._pose_tensors([T_local])
        p = self.points @ R[0].T + t[0]
        uv, z = self._uv(p, finest.K, None)
        w, h = finest.camera.size
        idx = torch.nonzero(near_view(uv, z, (w, h), 1e-3, self.cfg.max_depth)).squeeze(1)
        need = self.cfg.min_visible
        spacing = estimate_spacing(self.points[idx]) if idx.numel() >= need else 0.0
        depth = float(z[idx].median()) if idx.numel() else 1.0
        # cells that close the gaps between the points: through them, what a surface hides would count as seen
        cell = cell_size_for(spacing, finest.camera.fx, depth)
        facing = None if self.normals is None else facing_camera(p[idx], self.normals[idx] @ R[0].T)
        seen = visible_points(uv[idx], z[idx], (w, h), cell, facing=facing)
        visible = int(seen.sum())
        if visible >= need:
            check_spread_in_view(uv[idx], seen, need)
        if visible < need:
            if facing is not None and int(visible_points(uv[idx], z[idx], (w, h), cell).sum()) >= need:
                raise InputError(f"only {visible} scan points in view of the initial pose face the camera "
                                 f"(need {need}): the photo sees the back of what the scanner saw")
            raise InputError(f"only {visible} scan points in view of the initial pose "
                             f"(need {need}): check the pose, the camera file and the scan")
        # order the points so that every prefix favours textured ones (they carry the pose)
        score = texture_score(uv[idx], z[idx], (w, h), cell, self.target[idx])
        gumbel = (-torch.log(-torch.log(self.keys[idx]))).to(self.dtype)
        weight = score + self.cfg.texture_floor * score.mean().clamp_min(1e-6)
        order = torch.argsort(torch.log(weight) + gumbel, descending=True)
        idx, seen = idx[order], seen[order]
        out = []
        p_near, target_near = p[idx], self.target[idx]
        for level, photo in enumerate(self.pyramid):
            n = min(idx.numel(), max(self.cfg.min_points, self.cfg.max_points // 4**level))
            sub = idx[:n]
            cell = cell_size_for(spacing * math.sqrt(idx.numel() / n), photo.camera.fx, depth)
            image = photo.image
            if self.sharpness:  # one native pixel: the blur a lens, the pixels and a demosaic add
                # of the gray alone: a blur is the same in every channel, and a weight per output
                # channel (3, not 9 for a high pass per channel) leaves the fit little noise to
                # learn (ICL-NUIM i±1: 0.152 mm; per channel 0.160, without a high pass 0.150: docs/bundle.md)
                image = torch.cat([image, high_pass(image.mean(2, keepdim=True), float(photo.zoom))], 2)
            grads = central_gradients(image) if self.cfg.gradient == "central" else None
            target = target_near[:n]
            if level:
                size = photo.camera.size
                cells = pixel_sums(self._uv(p_near[seen], photo.K, None)[0], target_near[seen], size) if level == 1 \
                    else halved(cells, self.pyramid[level - 1].camera.size)
                target = blurred_targets(cells, size, self._uv(p_near[:n], photo.K, None)[0], target)
            out.append(Level(photo, image, grads, self.points[sub], target, min(cell, 16 * photo.zoom),
                             None if self.normals is None else self.normals[sub]))
        self.levels = out
        return len(out)

    # -- one evaluation of a batch of poses ------------------------------------------------------
    def _pose_tensors(self, Ts: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotations (B, 3, 3) and translations (B, 3) of local-frame poses."""
        T = torch.as_tensor(np.stack(Ts), dtype=self.dtype, device=self.device)
        return T[:, :3, :3].contiguous(), T[:, :3, 3].contiguous()  # strided views make slow products

    def _project(self, lv: Level, Ts: list[np.ndarray], q: torch.Tensor, cols: torch.Tensor | None = None,
                 points: torch.Tensor | None = None):
        """The level's points (or those of cols, or other local-frame `points` (n, 3)) at each
        pose: camera frame (B, n, 3), pixels and depths (B*n, 2), (B*n,) through the camera
        corrected by q (Q_SIZE,)."""
        R, t = self._pose_tensors(Ts)
        pts = points if points is not None else lv.points if cols is None else lv.points[cols]
        p = _times_transposed(pts, R) + t[:, None]
        uv, z = self._uv(p.reshape(-1, 3), lv.photo.K, q)
        return p, uv, z

    def _uv(self, p: torch.Tensor, K: torch.Tensor, q: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Camera-frame points (n, 3) -> pixels (n, 2) and depths (n,) through K, the photo's
        own distortion (a pyramid that keeps it) and the corrections q (Q_SIZE,; None: none)."""
        if not (self.free or self.distorted):
            return project_pinhole(p, K)
        uv, z = project_corrected(p, K, self.lens if q is None else q + self.lens)
        if math.isfinite(self.fold):  # no pixel images a point beyond the fold: sent far off the photo
            r2 = (p[:, 0] ** 2 + p[:, 1] ** 2) / p[:, 2].clamp_min(1e-9) ** 2
            uv = torch.where((r2 < self.fold**2)[:, None], uv, torch.full_like(uv, -1e6))
        return uv, z

    def _visible(self, lv: Level, Ts: list[np.ndarray], q: torch.Tensor, lost_is_error: bool) -> torch.Tensor:
        """(B, n) the level's points visible at each pose on usable pixels; on the finest level,
        given `RefineConfig.depth_edge_ratio`, not on a silhouette (the coarser levels' targets
        are blurred as their pixels mix, `blurred_targets`; leaving silhouettes out there too lost
        a rig's photo, docs/bundle.md). lost_is_error: a pose that sees fewer than 10 raises
        InputError (saying so when the rest face away)."""
        p, uv, z = self._project(lv, Ts, q)
        B, n = p.shape[:2]
        group = torch.arange(B, device=self.device).repeat_interleave(n) if B > 1 else None
        facing = None
        if lv.normals is not None:
            R, _ = self._pose_tensors(Ts)
            facing = facing_camera(p.reshape(-1, 3), _times_transposed(lv.normals, R).reshape(-1, 3))
        size, tol = lv.photo.camera.size, (self.cfg.zbuffer_rel_tol, self.cfg.zbuffer_abs_tol)
        silhouette = self.cfg.depth_edge_ratio if lv is self.levels[0] else 0.0
        vis = visible_points(uv, z, size, lv.cell, *tol, group=group, facing=facing, silhouette=silhouette)
        if lv.photo.valid is not None:
            vis &= _valid_at(lv.photo.valid, uv)
        vis = vis.reshape(B, n)
        if lost_is_error and int(vis.sum(1).min()) < 10:
            if facing is not None and int(visible_points(uv, z, size, lv.cell, *tol, group=group).reshape(B, n).sum(1).min()) >= 10:
                raise InputError("fewer than 10 scan points in view face the camera: the photo sees the back of "
                                 "what the scanner saw")
            raise InputError("the pose left the scan: fewer than 10 points in view")
        return vis

    def _sample(self, lv: Level, Ts: list[np.ndarray], q: torch.Tensor, cols: torch.Tensor, gradient: bool):
        """Points cols at each pose: camera frame p (B, c, 3), pixels uv (B, c, 2) (clamped to the
        level: a point may drift out), photo colors I, kernel K(I) (B, c, k) and, with gradient,
        dI/du, dI/dv (B*c, 3)."""
        p, uv, _ = self._project(lv, Ts, q, cols)
        B, c = p.shape[:2]
        w, h = lv.photo.camera.size
        uv = torch.stack([uv[:, 0].clamp(0, w - 1), uv[:, 1].clamp(0, h - 1)], 1)
        if gradient:
            I, Iu, Iv = bilinear_with_gradient(lv.image, uv, self.cfg.gradient, lv.grads)
        else:
            I, Iu, Iv = bilinear(lv.image, uv), None, None
        return p, uv.reshape(B, c, 2), I, self._kernel(I).reshape(B, c, -1), Iu, Iv

    def _kernel(self, I: torch.Tensor) -> torch.Tensor:
        """Sampled colors (n, C) -> the color fit's kernel (n, k): the model's of the photo's colors,
        then the gray's high pass itself where the sharpness is fitted (`high_pass`)."""
        K = self.model.kernel(I[:, :3])
        return torch.cat([K, I[:, 3:]], 1) if self.sharpness else K

    def _kernel_derivative(self, I: torch.Tensor, dI: torch.Tensor) -> torch.Tensor:
        """dK/dI . dI (n, k) of `_kernel` at I (n, C) along dI (n, C)."""
        dK = self.model.kernel_derivative(I[:, :3], dI[:, :3])
        return torch.cat([dK, dI[:, 3:]], 1) if self.sharpness else dK

    def evaluate(self, level: int, Ts: list[np.ndarray], q: torch.Tensor, prev: Terms | None = None,
                 jacobian: bool = True, free: int | None = None, lost_is_error: bool = True) -> Terms:
        """Visibility, color fit, robust weights and (with jacobian) the Gauss-Newton system at
        each local-frame pose of Ts (B of 4x4), with the camera corrections q (Q_SIZE,). prev (the last
        accepted terms) seeds the inliers and sigma. free: the camera corrections differentiated
        (default: those refined; 0 for the verification's repeats, which keep q)."""
        cfg, lv = self.cfg, self.levels[level]
        free = self.free if free is None else free
        vis = self._visible(lv, Ts, q, lost_is_error)
        # the points some pose sees: a single pose's evaluation costs what it sees
        cols = torch.nonzero(vis.any(0)).squeeze(1)
        seen = vis[:, cols]
        target = lv.target[cols]
        p, uv, I, Kk, Iu, Iv = self._sample(lv, Ts, q, cols, gradient=jacobian)
        B, c, k = Kk.shape
        m = target.shape[1]
        if self.model.fitted:
            fit = seen & unclipped(I[:, :3]).reshape(B, c)
            few = fit.sum(1) < torch.clamp(0.05 * seen.sum(1), min=100)  # a photo clipped almost everywhere
            fit = torch.where(few[:, None], seen, fit)
            D0 = prev.D if prev is not None else None
            if B == 1:  # one pose: its fit's rows alone, fewer than all it sees
                rows = fit[0]
                D, inliers = fit_many_with_inliers(Kk[:, rows], target[rows], rows[rows][None], cfg.beta_max, D0=D0)
            else:
                D, inliers = fit_many_with_inliers(Kk, target, fit, cfg.beta_max, D0=D0)
        else:
            D = self.model.identity(k, m, Kk).expand(B, m, k)
            inliers = seen & ((_times_transposed(Kk, D) - target).norm(dim=2) < cfg.beta_max)
        pred = _times_transposed(Kk, D)
        r = pred.clamp(0, 1) - target  # clipped values; the Jacobian below is the unclipped one
        # one pose sees all of cols: its plain means are the masked ones, at less cost
        mask = seen if B > 1 else None
        w, sigma2 = student_t_weights(r, cfg.nu, prev.sigma2 if prev is not None else None, mask=mask)
        sigma2 = sigma2.reshape(B, 1, 1)
        loss = student_t_loss(r, cfg.nu, sigma2, mask=mask).reshape(B)
        visible = seen.sum(1).cpu().numpy()
        n = lv.points.shape[0]
        err = torch.zeros(B, n, dtype=r.dtype, device=self.device)
        err[:, cols] = r.norm(dim=2)
        uv_all = torch.zeros(B, n, 2, dtype=uv.dtype, device=self.device)
        uv_all[:, cols] = uv
        terms = Terms(loss.double().cpu().numpy(), D, sigma2, vis, visible,
                      inliers.sum(1).cpu().numpy() / np.maximum(visible, 1), err, uv_all)
        if not jacobian:
            return terms
        # dr/du = D (dK/dI . dI/du), likewise for v: (B, c, m)
        a = _times_transposed(self._kernel_derivative(I, Iu).reshape(B, c, k), D)
        b = _times_transposed(self._kernel_derivative(I, Iv).reshape(B, c, k), D)
        du, dv = self._jacobian(p.reshape(-1, 3), lv.photo.K, q, free)
        ws = w if B == 1 else w * seen[..., None]  # one pose sees all of cols
        H, g, pulls = _normal_equations(du.reshape(B, c, -1), dv.reshape(B, c, -1), a, b, r, ws)
        terms.H, terms.g = H.cpu().numpy(), g.cpu().numpy()
        terms.wrr = (ws * r * r).sum((1, 2)).double().cpu().numpy()
        terms.count = visible * m
        if B == 1:
            terms.seen = (pred[0], a[0], b[0], du, dv)
            terms.pulls = (pulls[0][0], pulls[1][0])
        return terms

    def _jacobian(self, p: torch.Tensor, K: torch.Tensor, q: torch.Tensor, free: int) -> tuple[torch.Tensor, torch.Tensor]:
        """d(u, v) / d(pose, q[:free]): two (n, 6 + free)."""
        if not (self.free or self.distorted):
            return projection_jacobian(p, K[0, 0], K[1, 1])
        return corrected_jacobian(p, K, q + self.lens, free)

    def trial(self, level: int, Ts: list[np.ndarray], q: torch.Tensor, at: Terms) -> np.ndarray:
        """(B,) the robust loss at each pose of Ts on the points, color fit and scale of the
        terms `at` (so that it compares with at.loss as a smooth function of the pose)."""
        return self.trial_colors(level, Ts, q, at)[0]

    def trial_colors(self, level: int, Ts: list[np.ndarray], q: torch.Tensor, at: Terms) -> tuple[np.ndarray, torch.Tensor]:
        """`trial`, and the predictions it compared (B, c, m), unclipped, at the c points some
        pose of `at` sees: the bundle's agreement term reuses them."""
        lv = self.levels[level]
        cols = torch.nonzero(at.mask.any(0)).squeeze(1)
        _, _, _, Kk, _, _ = self._sample(lv, Ts, q, cols, gradient=False)
        pred = _times_transposed(Kk, at.D)
        r = pred.clamp(0, 1) - lv.target[cols]
        return student_t_loss(r, self.cfg.nu, at.sigma2, mask=at.mask[:, cols]).double().cpu().numpy(), pred

    @staticmethod
    def own_colors(at: Terms) -> tuple[torch.Tensor, torch.Tensor]:
        """`seen_colors` at the points the one pose of `at` sees, from its evaluation (with its
        system): the predictions (c, m) and their derivative (c, m, P)."""
        pred, a, b, du, dv = at.seen
        return pred, a[..., None] * du[:, None] + b[..., None] * dv[:, None]

    def seen_colors(self, level: int, T_local: np.ndarray, q: torch.Tensor, points: torch.Tensor, D: torch.Tensor,
                    jacobian: bool = True):
        """The photo's colors at `points` (n, 3), local frame, seen from T_local (4x4) with the
        camera corrections q (Q_SIZE,), mapped into the scan's colors by the color fit D (m, k): the
        prediction (n, m), whether each point lands on usable pixels in front of the camera (n,),
        and with jacobian its derivative (n, m, 6 + free) by the pose and the free corrections.
        For the bundle's agreement term (two photos of one scan point, `align.bundle`)."""
        lv = self.levels[level]
        p, uv, z = self._project(lv, [T_local], q, points=points)
        w, h = lv.photo.camera.size
        inside = (z > 1e-6) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
        if lv.photo.valid is not None:
            inside &= _valid_at(lv.photo.valid, uv)
        uv = torch.stack([uv[:, 0].clamp(0, w - 1), uv[:, 1].clamp(0, h - 1)], 1)
        if not jacobian:
            return self._kernel(bilinear(lv.image, uv)) @ D.T, inside, None
        I, Iu, Iv = bilinear_with_gradient(lv.image, uv, self.cfg.gradient, lv.grads)
        a = self._kernel_derivative(I, Iu) @ D.T
        b = self._kernel_derivative(I, Iv) @ D.T
        du, dv = self._jacobian(p[0], lv.photo.K, q, self.free)
        return self._kernel(I) @ D.T, inside, a[..., None] * du[:, None] + b[..., None] * dv[:, None]

    # -- what a result reports ---------------------------------------------------------------------
    def residuals(self, level: int, at: Terms) -> tuple[np.ndarray, np.ndarray]:
        """The first pose's visible points: photo pixels (n, 2) and |r| (n,)."""
        seen = at.mask[0]
        return (self.levels[level].photo.to_photo_pixels(at.uv[0][seen]).cpu().numpy(), at.err[0][seen].cpu().numpy())

    def covariance(self, level: int, T: np.ndarray, q: torch.Tensor, at: Terms) -> np.ndarray | None:
        """(P, P) the parameters' covariance at the first pose of `at` (evaluated with its Jacobian).
        Its pose's share of the objective per tile of the photo stays in at.tiles (`tile_scores`)."""
        if at.H is None:
            return None
        if at.pulls is not None:
            at.tiles = self.tile_scores(level, at)
        return covariance(at.H[0], float(at.wrr[0]), int(at.count[0]))

    def tile_scores(self, level: int, at: Terms, tiles: int = TILES) -> tuple[np.ndarray, np.ndarray]:
        """The gradient of the objective (J^T W r) over the parameters (pose, free corrections)
        summed over the visible points in each of tiles x tiles tiles of the photo, (K, P) for
        the K tiles with points, and J^T W J (P, P), at the first pose of `at` (evaluated alone
        with its Jacobian): the samples of the covariance with the tiles as the samples
        (`align.covariance.sandwich`)."""
        _, _, _, du, dv = at.seen
        sar, sbr = at.pulls
        pull = du.double() * sar[:, None] + dv.double() * sbr[:, None]  # (c, P)
        uv = at.uv[0][at.mask[0]]
        h, w = self.levels[level].photo.image.shape[:2]
        tile = (uv[:, 1] * (tiles / h)).long().clamp(0, tiles - 1) * tiles + (uv[:, 0] * (tiles / w)).long().clamp(0, tiles - 1)
        sums = torch.zeros(tiles * tiles, pull.shape[1], dtype=pull.dtype, device=pull.device).index_add_(0, tile, pull)
        return sums[torch.bincount(tile, minlength=tiles * tiles) > 0].cpu().numpy(), at.H[0]

    def summary(self, at: Terms) -> dict:
        """`RefineResult`'s objective-specific fields of the first pose of at."""
        D = at.D[0].double().cpu().numpy()  # the color transform; then the high pass's weights, if fitted
        return {"color_transform": D[:, :-1] if self.sharpness else D, "loss": float(at.loss[0]),
                "inlier_fraction": float(at.inlier_fraction[0]), "visible_points": int(at.visible[0])}

    def visible_scan_points(self, T_local: np.ndarray, q: torch.Tensor) -> np.ndarray:
        """(n, 3) float32 local-frame points of the finest level visible at T_local."""
        lv = self.levels[0]
        return lv.points[self._visible(lv, [T_local], q, True)[0]].double().cpu().numpy()
