"""The aligner: refine T_cam_from_scan by direct photometric alignment of a colored scan to a
photo, following Rotstein, Bracha, Kimmel, "Multimodal Colored Point Cloud to Image
Alignment" (CVPR 2022).

Each evaluation at a pose: move the points, drop occluded ones (coarse Z-buffer), project,
sample the photo bilinearly with its gradient (strategy A or B), lift the colors with the
color model's kernel, fit the color transform D on inliers, clip the prediction to [0, 1]
(keeping the unclipped gradient), and weight the residuals with a Student-t. The pose is
optimised by Levenberg-Marquardt on the 6 pose parameters (or by Adam, as in the paper), on an
image pyramid, coarse to fine.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from rgbd_gt.align.color_models import ColorModel, fit_many_with_inliers, fit_with_inliers, unclipped
from rgbd_gt.align.config import RefineConfig
from rgbd_gt.align.pyramid import PhotoLevel
from rgbd_gt.align.robust import student_t_loss, student_t_weights
from rgbd_gt.align.sampling import bilinear, bilinear_sparse, bilinear_with_gradient, central_gradients
from rgbd_gt.align.subset import point_keys
from rgbd_gt.errors import InputError
from rgbd_gt.pose import apply_update, translated
from rgbd_gt.render.normals import facing_camera
from rgbd_gt.render.project import (INTRINSICS, corrected_jacobian, project_corrected, project_pinhole,
                                    projection_jacobian)
from rgbd_gt.render.zbuffer import cell_size_for, check_spread_in_view, estimate_spacing, visible_points


@dataclass
class RefineResult:
    T_cam_from_scan: np.ndarray  # (4, 4) float64
    color_transform: np.ndarray  # (m, k) D
    iterations: int
    loss: float
    inlier_fraction: float
    visible_points: int
    seconds: float
    history: list[dict] = field(default_factory=list)
    # per level, coarse to fine: {level, iterations, stop: converged | iteration cap | damping ran away}
    levels: list[dict] = field(default_factory=list)
    # at the result, on the finest level: the 1-sigma covariance (6, 6) of the update
    # (rotation vector, translation) in the camera frame (`apply_update`); inf where undetermined
    covariance: np.ndarray | None = None
    objective: str = "photometric"  # or "nid" (align/nid_aligner.py); loss is then the mean NID
    # with cfg.refine_intrinsics: the camera corrections q (5,) (`render.project.project_corrected`)
    # and their 1-sigma (inf where not refined)
    intrinsics: np.ndarray | None = None
    intrinsics_sigma: np.ndarray | None = None
    start_residuals: tuple[np.ndarray, np.ndarray] | None = None  # (uv (N, 2), |r| (N,)) at full resolution
    end_residuals: tuple[np.ndarray, np.ndarray] | None = None


@dataclass
class _LevelData:
    photo: PhotoLevel
    grads: tuple[torch.Tensor, torch.Tensor] | None
    points: torch.Tensor  # (n, 3) float32, local frame
    target: torch.Tensor  # (n, m)
    cell: int
    normals: torch.Tensor | None = None  # (n, 3) float32, facing the scanner (render/normals.py)


@dataclass
class _State:
    """One evaluation at a pose."""

    own_loss: float  # robust loss at this pose with this state's D and sigma
    D: torch.Tensor
    sigma2: torch.Tensor
    visible: int
    inlier_fraction: float
    idx: torch.Tensor  # the visible points (indices into the level's points)
    uv: torch.Tensor
    err: torch.Tensor  # |r| per visible point
    H: np.ndarray | None = None  # (6, 6) Gauss-Newton matrix J^T W J
    g: np.ndarray | None = None  # (6,) gradient J^T W r
    wrr: float = 0.0  # sum of w r^2 over points and channels (the weighted residual energy)
    n_residuals: int = 0  # points x channels


@dataclass
class _Many:
    """One evaluation of several poses at once (the verification's repeat runs): per pose B its
    visible points, color fit, robust scale, loss and Gauss-Newton system."""

    loss: np.ndarray  # (B,)
    D: torch.Tensor  # (B, m, k)
    sigma2: torch.Tensor  # (B, 1, 1)
    mask: torch.Tensor  # (B, n) the level's points visible on usable pixels
    H: np.ndarray  # (B, 6, 6)
    g: np.ndarray  # (B, 6)

    def where(self, keep: np.ndarray, other: "_Many") -> "_Many":
        """Per pose: this state where keep (B,) is True, else other's."""
        k = torch.as_tensor(keep, device=self.D.device)
        return _Many(np.where(keep, self.loss, other.loss), torch.where(k[:, None, None], self.D, other.D),
                     torch.where(k[:, None, None], self.sigma2, other.sigma2), torch.where(k[:, None], self.mask, other.mask),
                     np.where(keep[:, None, None], self.H, other.H), np.where(keep[:, None], self.g, other.g))


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


def _normal_equations(du: torch.Tensor, dv: torch.Tensor, a: torch.Tensor, b: torch.Tensor, r: torch.Tensor,
                      w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The Gauss-Newton system J^T W J (B, 6, 6) and J^T W r (B, 6), float64, of B poses' residuals
    r (B, n, m) with weights w (B, n, m) (0 for points not used), where the residual's Jacobian
    is J_nm = a_nm du_n + b_nm dv_n: a, b (B, n, m) its derivatives along the image axes, du, dv
    (B, n, 6) the pixel motion per pose parameter. Summed over the channels first, which needs
    only 2x2 sums per point."""
    saa, sab, sbb = ((w * a * a).sum(2).double(), (w * a * b).sum(2).double(), (w * b * b).sum(2).double())
    sar, sbr = (w * a * r).sum(2).double(), (w * b * r).sum(2).double()
    du, dv = du.double(), dv.double()
    duT, dvT = du.transpose(1, 2), dv.transpose(1, 2)
    cross = duT @ (sab[..., None] * dv)
    H = duT @ (saa[..., None] * du) + cross + cross.transpose(1, 2) + dvT @ (sbb[..., None] * dv)
    return H, (duT @ sar[..., None] + dvT @ sbr[..., None])[..., 0]


def covariance(H: np.ndarray, energy: float, count: int) -> np.ndarray:
    """The covariance (P, P) of the parameters (the pose's 6 first) from a Gauss-Newton matrix
    H = J^T W J, scaled by the residual variance energy / (count - P) (energy = sum w r^2), or
    all inf where H is singular. Inverted
    with its parameters scaled to unit diagonal (rotation and translation differ by orders of
    magnitude). Residuals are treated as independent: neighbouring points share photo pixels, so
    this is a lower bound."""
    s = 1.0 / np.sqrt(np.clip(np.diag(H), 1e-30, None))
    Hs = H * s[:, None] * s[None, :]
    eig = np.linalg.eigvalsh(Hs)
    if eig[0] <= eig[-1] * 1e-12:
        return np.full(H.shape, np.inf)
    return energy / max(count - len(H), 1) * (s[:, None] * np.linalg.inv(Hs) * s[None, :])


def refine_each(aligner, starts: list[np.ndarray], **refine_args) -> list[np.ndarray | None]:
    """`aligner.refine(T0, **refine_args)`'s pose from each start in turn; None for a start that
    lost the scan."""
    out = []
    for T0 in starts:
        try:
            out.append(aligner.refine(T0, **refine_args).T_cam_from_scan)
        except InputError:
            out.append(None)
    return out


def _valid_at(valid: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """All four bilinear neighbours of uv (N, 2) are usable pixels."""
    h, w = valid.shape
    u0 = uv[:, 0].floor().clamp(0, w - 2).long()
    v0 = uv[:, 1].floor().clamp(0, h - 2).long()
    return valid[v0, u0] & valid[v0, u0 + 1] & valid[v0 + 1, u0] & valid[v0 + 1, u0 + 1]


POOL = 16  # x max_points: the most scan points an aligner keeps (drawn at random)
ALIGN_MARGIN = 0.15  # of the photo's width and height on every side: a pose moves a few degrees


def near_view(uv: torch.Tensor, z: torch.Tensor, size: tuple[int, int], near: float, far: float = 0.0) -> torch.Tensor:
    """(N,) bool: the points at pixels uv (N, 2) and depths z (N,) metres that an aligner
    considers: within ALIGN_MARGIN of the photo of size (W, H), deeper than `near` and, when
    far > 0, shallower than `far`."""
    w, h = size
    mu, mv = ALIGN_MARGIN * w, ALIGN_MARGIN * h
    keep = (z > near) & (uv[:, 0] > -mu) & (uv[:, 1] > -mv) & (uv[:, 0] < w + mu) & (uv[:, 1] < h + mv)
    return keep & (z < far) if far > 0 else keep


class Aligner:
    """Refines one photo's pose against one colored scan.

    Args:
        points: (N, 3) float64 scan points (metres, scan frame).
        colors: (N, 3) uint8 colors, or (N, 1) intensity in [0, 1] for scans without color.
        pyramid: the photo's pyramid (`photo_pyramid`), finest first.
        cfg: settings.
        normals: (N, 3) unit normals facing the scanner (`render.normals.scan_normals`), or None:
            points seen from behind are then not told apart.
    """

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
        # the camera corrections refined with the pose (cfg.refine_intrinsics: the first `free` of q)
        self.free = INTRINSICS[cfg.refine_intrinsics]
        self.q = torch.zeros(5, dtype=self.dtype, device=self.device)
        self._prepared: tuple[np.ndarray, list[_LevelData]] | None = None

    # -- pose conversion between the scan frame and the local frame ---------------------------
    def _to_local(self, T: np.ndarray) -> np.ndarray:
        return translated(T, self.centre)

    def _to_scan(self, L: np.ndarray) -> np.ndarray:
        return translated(L, -self.centre)

    # -- set-up of each level ----------------------------------------------------------------
    def _levels(self, T_local: np.ndarray) -> list[_LevelData]:
        """Per level: a random subset of the points near the initial view (`near_view`; nested
        subsets, `max_points` at full resolution and a quarter per coarser level, the same in any
        order of the points: align/subset.py) and its Z-buffer cell."""
        finest = self.pyramid[0]
        R, t = self._pose_tensors(T_local)
        p = self.points @ R.T + t
        uv, z = project_pinhole(p, finest.K)
        w, h = finest.camera.size
        idx = torch.nonzero(near_view(uv, z, (w, h), 1e-3, self.cfg.max_depth)).squeeze(1)
        need = self.cfg.min_visible
        spacing = estimate_spacing(self.points[idx]) if idx.numel() >= need else 0.0
        depth = float(z[idx].median()) if idx.numel() else 1.0
        # cells that close the gaps between the points: through them, what a surface hides would count as seen
        cell = cell_size_for(spacing, finest.camera.fx, depth)
        facing = None if self.normals is None else facing_camera(p[idx], self.normals[idx] @ R.T)
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
            grads = central_gradients(photo.image) if self.cfg.gradient == "central" else None
            target = target_near[:n]
            if level:
                size = photo.camera.size
                cells = pixel_sums(project_pinhole(p_near[seen], photo.K)[0], target_near[seen], size) if level == 1 \
                    else halved(cells, self.pyramid[level - 1].camera.size)
                target = blurred_targets(cells, size, project_pinhole(p_near[:n], photo.K)[0], target)
            out.append(_LevelData(photo, grads, self.points[sub], target, min(cell, 16 * photo.zoom),
                                  None if self.normals is None else self.normals[sub]))
        return out

    # -- one evaluation ------------------------------------------------------------------------
    def _project(self, p: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Camera-frame points (n, 3) -> pixels (n, 2), depths (n,), through the camera corrected by q."""
        return project_corrected(p, K, self.q) if self.free else project_pinhole(p, K)

    def _jacobian(self, p: torch.Tensor, K: torch.Tensor, free: int) -> tuple[torch.Tensor, torch.Tensor]:
        """d(u, v) / d(pose, q[:free]): two (n, 6 + free)."""
        if not self.free:
            return projection_jacobian(p, K[0, 0], K[1, 1])
        return corrected_jacobian(p, K, self.q, free)

    def _pose_tensors(self, T_local: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        R = torch.as_tensor(T_local[:3, :3], dtype=self.dtype, device=self.device)
        t = torch.as_tensor(T_local[:3, 3], dtype=self.dtype, device=self.device)
        return R, t

    def _visible(self, lv: _LevelData, T_local: np.ndarray) -> torch.Tensor:
        """Indices (into lv.points) of the points visible at this pose on usable pixels."""
        R, t = self._pose_tensors(T_local)
        p = lv.points @ R.T + t
        uv, z = self._project(p, lv.photo.K)
        facing = None if lv.normals is None else facing_camera(p, lv.normals @ R.T)
        vis = visible_points(uv, z, lv.photo.camera.size, lv.cell, self.cfg.zbuffer_rel_tol, self.cfg.zbuffer_abs_tol,
                             facing=facing)
        if lv.photo.valid is not None:
            vis &= _valid_at(lv.photo.valid, uv)
        idx = torch.nonzero(vis).squeeze(1)
        if idx.numel() < 10:
            if facing is not None and int(visible_points(uv, z, lv.photo.camera.size, lv.cell, self.cfg.zbuffer_rel_tol,
                                                         self.cfg.zbuffer_abs_tol).sum()) >= 10:
                raise InputError("fewer than 10 scan points in view face the camera: the photo sees the back of "
                                 "what the scanner saw")
            raise InputError("the pose left the scan: fewer than 10 points in view")
        return idx

    def _sample(self, lv: _LevelData, T_local: np.ndarray, idx: torch.Tensor):
        """Points idx at this pose: camera-frame p (n, 3), uv (n, 2), photo colors I (n, 3),
        kernel K(I) (n, k), image gradients dI/du, dI/dv (n, 3) and the targets (n, m)."""
        R, t = self._pose_tensors(T_local)
        p = lv.points[idx] @ R.T + t
        uv, _ = self._project(p, lv.photo.K)
        w, h = lv.photo.camera.size
        uv = torch.stack([uv[:, 0].clamp(0, w - 1), uv[:, 1].clamp(0, h - 1)], 1)  # a point may drift out
        I, Iu, Iv = bilinear_with_gradient(lv.photo.image, uv, self.cfg.gradient, lv.grads)
        return p, uv, I, self.model.kernel(I), Iu, Iv, lv.target[idx]

    def _loss_at(self, lv: _LevelData, T_local: np.ndarray, state: _State) -> float:
        """Robust loss at a candidate pose on the state's points with the state's D and sigma,
        so that it compares with state.own_loss as a smooth function of the pose."""
        _, _, _, Kk, _, _, target = self._sample(lv, T_local, state.idx)
        r = (Kk @ state.D.T).clamp(0, 1) - target
        return float(student_t_loss(r, self.cfg.nu, state.sigma2))

    def _evaluate(self, lv: _LevelData, T_local: np.ndarray, prev: _State | None, jacobian: bool) -> _State:
        """Visibility, color fit, robust weights and (optionally) the Gauss-Newton system at a
        pose. `prev` (the last accepted state) seeds the inliers and sigma."""
        cfg = self.cfg
        idx = self._visible(lv, T_local)
        p, uv, I, Kk, Iu, Iv, target = self._sample(lv, T_local, idx)
        m = target.shape[1]
        if self.model.fitted:
            fit = unclipped(I)
            if int(fit.sum()) < max(100, int(0.05 * fit.numel())):  # a photo clipped almost everywhere
                fit = torch.ones_like(fit)
            D, inliers = fit_with_inliers(Kk[fit], target[fit], cfg.beta_max, D0=prev.D if prev is not None else None)
        else:
            D = self.model.identity(Kk.shape[1], m, Kk)
            inliers = (Kk @ D.T - target).norm(dim=1) < cfg.beta_max
        inlier_fraction = float(inliers.sum()) / max(int(idx.numel()), 1)  # of all visible points
        r = (Kk @ D.T).clamp(0, 1) - target  # clipped values; the Jacobian below is the unclipped one
        w, sigma2 = student_t_weights(r, cfg.nu, prev.sigma2 if prev is not None else None)
        own = float(student_t_loss(r, cfg.nu, sigma2))
        state = _State(own, D, sigma2, int(idx.numel()), inlier_fraction, idx=idx, uv=uv, err=r.norm(dim=1))
        if not jacobian:
            return state

        # dr/du = D (dK/dI . dI/du), likewise for v: (n, m)
        a = self.model.kernel_derivative(I, Iu) @ D.T
        b = self.model.kernel_derivative(I, Iv) @ D.T
        du, dv = self._jacobian(p, lv.photo.K, self.free)
        H, g = _normal_equations(du[None], dv[None], a[None], b[None], r[None], w[None])
        state.H, state.g = H[0].cpu().numpy(), g[0].cpu().numpy()
        state.wrr = float((w * r * r).sum())
        state.n_residuals = int(r.numel())
        return state

    # -- optimisation ----------------------------------------------------------------------------
    def prepared_levels(self, T_init: np.ndarray) -> list[_LevelData]:
        """The per-level points for T_init, made once: later calls (the verification's repeat
        runs from nearby starts) reuse the first call's, so that every run sees the same points."""
        if self._prepared is None:
            self._prepared = (np.asarray(T_init, np.float64), self._levels(self._to_local(T_init)))
        return self._prepared[1]

    def refine(self, T_init: np.ndarray, progress: Callable[[dict], None] | None = None,
               keep_residuals: bool = False, finest: int = 0, coarsest: int | None = None,
               iterations: int | None = None) -> RefineResult:
        """Refine T_init (4x4 T_cam_from_scan). progress(record) is called after each iteration.

        finest, coarsest: the pyramid levels to run (0 = full resolution; default all);
        iterations: another cap per level than the config's (the verification's cheap repeat
        runs use all three)."""
        start = time.perf_counter()
        cfg = self.cfg
        T_init = np.asarray(T_init, np.float64)
        levels = self.prepared_levels(T_init)
        # the camera corrections start from the camera file every time: two refines of one aligner
        # start alike (the repeat runs of `refine_many` keep the ones this run ends with)
        self.q = torch.zeros(5, dtype=self.dtype, device=self.device)
        T = self._to_local(T_init)
        history: list[dict] = []
        start_res = None
        if keep_residuals:
            s0 = self._evaluate(levels[0], T, None, jacobian=False)
            start_res = (levels[0].photo.to_photo_pixels(s0.uv).cpu().numpy(), s0.err.cpu().numpy())
        total_iterations = 0
        level_info = []
        step = self._lm_level if cfg.optimizer == "lm" else self._adam_level
        top = len(levels) - 1 if coarsest is None else min(coarsest, len(levels) - 1)
        for level in range(top, finest - 1, -1):
            T, n_it, stop = step(levels[level], level, T, history, progress, iterations)
            total_iterations += n_it
            level_info.append({"level": level, "iterations": n_it, "stop": stop})
        final = self._evaluate(levels[finest], T, None, jacobian=finest == 0)
        end_res = (levels[0].photo.to_photo_pixels(final.uv).cpu().numpy(), final.err.cpu().numpy()) if keep_residuals else None
        cov = covariance(final.H, final.wrr, final.n_residuals) if final.H is not None else None
        sigma = None
        if self.free and cov is not None:
            sigma = np.full(5, np.inf)
            sigma[:self.free] = np.sqrt(np.diag(cov)[6:])
        return RefineResult(
            T_cam_from_scan=self._to_scan(T),
            color_transform=final.D.double().cpu().numpy(),
            iterations=total_iterations,
            loss=final.own_loss,
            inlier_fraction=final.inlier_fraction,
            visible_points=final.visible,
            seconds=time.perf_counter() - start,
            history=history,
            levels=level_info,
            covariance=cov[:6, :6] if cov is not None else None,
            intrinsics=self.q.double().cpu().numpy() if self.free else None,
            intrinsics_sigma=sigma,
            start_residuals=start_res,
            end_residuals=end_res,
        )

    # -- several poses at once (the verification's repeat runs) ------------------------------------
    def refine_many(self, starts: list[np.ndarray], finest: int = 0, coarsest: int | None = None,
                    iterations: int | None = None) -> list[np.ndarray | None]:
        """`refine` from each of several starts (4x4 T_cam_from_scan) on the prepared points,
        Levenberg-Marquardt on all of them in one set of tensor operations (each keeps its own
        damping, acceptance and stop). Returns the poses, None for a start that lost the scan.
        (The paper's Adam has no batched form here: one run after another.)"""
        if self.cfg.optimizer != "lm":
            return refine_each(self, starts, finest=finest, coarsest=coarsest, iterations=iterations)
        levels = self.prepared_levels(starts[0])  # prepared by an earlier refine, else around the first start
        Ts = [self._to_local(np.asarray(T, np.float64)) for T in starts]
        lost = np.zeros(len(Ts), bool)
        top = len(levels) - 1 if coarsest is None else min(coarsest, len(levels) - 1)
        for level in range(top, finest - 1, -1):
            Ts, lost = self._lm_many(levels[level], level, Ts, lost, iterations or self.cfg.iterations)
        return [None if gone else self._to_scan(T) for T, gone in zip(Ts, lost)]

    def _project_many(self, lv: _LevelData, Ts: list[np.ndarray]):
        """The level's points at each pose: camera-frame (B, n, 3), pixels (B*n, 2), depths (B*n,)."""
        R = torch.stack([self._pose_tensors(T)[0] for T in Ts])
        t = torch.stack([self._pose_tensors(T)[1] for T in Ts])
        p = torch.einsum("bij,nj->bni", R, lv.points) + t[:, None]
        uv, z = self._project(p.reshape(-1, 3), lv.photo.K)
        w, h = lv.photo.camera.size
        return p, uv, z, torch.stack([uv[:, 0].clamp(0, w - 1), uv[:, 1].clamp(0, h - 1)], 1)

    def _evaluate_many(self, lv: _LevelData, Ts: list[np.ndarray], prev: _Many | None) -> _Many:
        """`_evaluate` (with the Jacobian) at each of several poses."""
        cfg = self.cfg
        p, uv, z, uvc = self._project_many(lv, Ts)
        B, n = p.shape[:2]
        group = torch.arange(B, device=self.device).repeat_interleave(n)
        facing = None
        if lv.normals is not None:
            R = torch.stack([self._pose_tensors(T)[0] for T in Ts])
            facing = facing_camera(p.reshape(-1, 3), torch.einsum("bij,nj->bni", R, lv.normals).reshape(-1, 3))
        vis = visible_points(uv, z, lv.photo.camera.size, lv.cell, cfg.zbuffer_rel_tol, cfg.zbuffer_abs_tol, group=group,
                             facing=facing)
        if lv.photo.valid is not None:
            vis &= _valid_at(lv.photo.valid, uv)
        vis = vis.reshape(B, n)
        I, Iu, Iv = bilinear_with_gradient(lv.photo.image, uvc, cfg.gradient, lv.grads)
        Kk = self.model.kernel(I).reshape(B, n, -1)
        m, k = lv.target.shape[1], Kk.shape[2]
        if self.model.fitted:
            fit = vis & unclipped(I).reshape(B, n)
            few = fit.sum(1) < torch.clamp(0.05 * vis.sum(1), min=100)  # a photo clipped almost everywhere
            fit = torch.where(few[:, None], vis, fit)
            D, _ = fit_many_with_inliers(Kk, lv.target, fit, cfg.beta_max, D0=prev.D if prev is not None else None)
        else:
            D = self.model.identity(k, m, Kk).expand(B, m, k)
        r = (Kk @ D.transpose(1, 2)).clamp(0, 1) - lv.target
        w, sigma2 = student_t_weights(r, cfg.nu, prev.sigma2 if prev is not None else None, mask=vis)
        loss = student_t_loss(r, cfg.nu, sigma2, mask=vis)
        a = self.model.kernel_derivative(I, Iu).reshape(B, n, k) @ D.transpose(1, 2)
        b = self.model.kernel_derivative(I, Iv).reshape(B, n, k) @ D.transpose(1, 2)
        du, dv = self._jacobian(p.reshape(-1, 3), lv.photo.K, 0)
        H, g = _normal_equations(du.reshape(B, n, 6), dv.reshape(B, n, 6), a, b, r, w * vis[..., None])
        return _Many(loss.double().cpu().numpy(), D, sigma2, vis, H.cpu().numpy(), g.cpu().numpy())

    def _loss_many(self, lv: _LevelData, Ts: list[np.ndarray], state: _Many) -> np.ndarray:
        """`_loss_at` for several poses: (B,) the robust loss on each state's points with its D and sigma."""
        _, _, _, uvc = self._project_many(lv, Ts)
        Kk = self.model.kernel(bilinear(lv.photo.image, uvc)).reshape(len(Ts), lv.points.shape[0], -1)
        r = (Kk @ state.D.transpose(1, 2)).clamp(0, 1) - lv.target
        return student_t_loss(r, self.cfg.nu, state.sigma2, mask=state.mask).double().cpu().numpy()

    def _lm_many(self, lv, level, Ts, lost, iterations):
        """`_lm_level` for several poses in lockstep. Returns (poses, lost): a pose that sees fewer
        than 10 points is lost and no longer moves."""
        state = self._evaluate_many(lv, Ts, None)
        lost = lost | (state.mask.sum(1) < 10).cpu().numpy()
        lam = np.full(len(Ts), 1e-4)
        active = ~lost
        for _ in range(iterations):
            if not active.any():
                break
            deltas = np.zeros((len(Ts), 6))
            for i in np.nonzero(active)[0]:
                deltas[i] = -np.linalg.solve(state.H[i] + lam[i] * np.diag(np.diag(state.H[i]) + 1e-12), state.g[i])
            T_new = [apply_update(T, d) if on else T for T, d, on in zip(Ts, deltas, active)]
            accepted = active & (self._loss_many(lv, T_new, state) <= state.loss)
            if accepted.any():
                Ts = [Tn if ok else T for T, Tn, ok in zip(Ts, T_new, accepted)]
                state = self._evaluate_many(lv, Ts, state).where(accepted, state)
                gone = accepted & (state.mask.sum(1) < 10).cpu().numpy()
                lost |= gone
                active &= ~gone
            lam = np.where(accepted, np.maximum(lam / 4, 1e-7), np.where(active, lam * 8, lam))
            done = accepted & np.array([self._converged(d, level) for d in deltas])
            active &= ~done & (lam <= 1e6)
        return Ts, lost

    # -- what the verification (align/verify.py) asks of a result ---------------------------------
    def visible_scan_points(self, T: np.ndarray) -> np.ndarray:
        """(n, 3) float64 scan-frame points of the finest level that are visible at pose T."""
        lv = self._prepared[1][0]
        idx = self._visible(lv, self._to_local(T))
        return lv.points[idx].double().cpu().numpy() + self.centre

    def loss_profile(self, T: np.ndarray, deltas: np.ndarray, level: int = 0) -> tuple[float, np.ndarray]:
        """The robust loss at pose T and at T moved by each update of deltas (k, 6) (`apply_update`),
        on a pyramid level with the points, color fit and scale of T: how clear a minimum T is."""
        levels = self._prepared[1]
        lv = levels[min(level, len(levels) - 1)]
        T_local = self._to_local(T)
        state = self._evaluate(lv, T_local, None, jacobian=False)
        return state.own_loss, np.array([self._loss_at(lv, apply_update(T_local, d), state) for d in deltas])

    def _record(self, history, progress, level, iteration, state: _State, delta: np.ndarray, accepted: bool):
        rec = {
            "level": level, "iteration": iteration, "loss": state.own_loss,
            "rotation_update_deg": float(np.degrees(np.linalg.norm(delta[:3]))),
            "translation_update_m": float(np.linalg.norm(delta[3:6])),
            "median_residual": float(state.err.median()),
            "visible": state.visible, "inlier_fraction": state.inlier_fraction, "accepted": accepted,
        }
        history.append(rec)
        if progress is not None:
            progress(rec)

    def _converged(self, delta: np.ndarray, level: int = 0) -> bool:
        """The update is below the stop thresholds, scaled by the level's pixel size (2^level):
        a coarse level only hands its pose on to a finer one."""
        scale = 2.0**level
        return (np.degrees(np.linalg.norm(delta[:3])) < self.cfg.stop_rotation_deg * scale
                and np.linalg.norm(delta[3:6]) < self.cfg.stop_translation_m * scale)

    def _lm_level(self, lv, level, T, history, progress, iterations=None):
        """Levenberg-Marquardt on the 6 pose parameters. Visibility, D and sigma are re-fitted at
        every accepted pose; a step is accepted when the robust loss on the same points with the
        same D and sigma decreases. Returns (T, iterations, why it stopped)."""
        state = self._evaluate(lv, T, None, jacobian=True)
        lam = 1e-4
        it = 0
        stop = "iteration cap"
        for it in range(1, (iterations or self.cfg.iterations) + 1):
            A = state.H + lam * np.diag(np.diag(state.H) + 1e-12)
            delta = -np.linalg.solve(A, state.g)
            T_new = apply_update(T, delta[:6])
            q_old = self.q
            if self.free:  # the camera corrections move with the pose (kept only when the step is)
                self.q = q_old.clone()
                self.q[:self.free] += torch.as_tensor(delta[6:], dtype=self.dtype, device=self.device)
            accepted = self._loss_at(lv, T_new, state) <= state.own_loss
            if accepted:
                T = T_new
                state = self._evaluate(lv, T, state, jacobian=True)
                lam = max(lam / 4, 1e-7)
            else:
                self.q = q_old
                lam *= 8
            self._record(history, progress, level, it, state, delta, accepted)
            if accepted and self._converged(delta, level):
                stop = "converged"
                break
            if lam > 1e6:  # no step lowers the loss: a minimum at this level's precision, or a broken one
                stop = "damping ran away"
                break
        return T, it, stop

    def _adam_level(self, lv, level, T, history, progress, iterations=None):
        """Adam on the 6 pose parameters (the paper's optimiser), separate step sizes for
        rotation and translation."""
        cfg = self.cfg
        lr = np.array([cfg.adam_lr_rotation] * 3 + [cfg.adam_lr_translation] * 3)
        m1, m2 = np.zeros(6), np.zeros(6)
        b1, b2, eps = 0.9, 0.999, 1e-12
        state = None
        it = 0
        for it in range(1, (iterations or cfg.adam_iterations) + 1):
            state = self._evaluate(lv, T, state, jacobian=True)
            g = state.g / max(state.visible, 1)
            m1 = b1 * m1 + (1 - b1) * g
            m2 = b2 * m2 + (1 - b2) * g * g
            delta = -lr * (m1 / (1 - b1**it)) / (np.sqrt(m2 / (1 - b2**it)) + eps)
            T = apply_update(T, delta)
            self._record(history, progress, level, it, state, delta, True)
        return T, it, "converged" if self._converged(delta, level) else "iteration cap"
