"""Several photos of one scan in one solve: every photo's pose, per camera the corrections its
file leaves open (shared by all that camera's photos), and per rig the relative pose of each
camera to the rig's first (shared by all shots). One Levenberg-Marquardt over all of it, coarse to
fine, as ETH3D's pipeline (Schöps et al., CVPR 2017), on the photos' own photometric objectives.
A scan with intensity alone (nid, no Gauss-Newton form): L-BFGS over the same unknowns (`_lbfgs`),
started where each photo's own wide search lands (`_starts`), the cameras held, and each photo's
Laplace Hessian in the place of its Gauss-Newton matrix for the covariance and the evidence
(`_quadratics`). A rig without a prior starts from each photo's own coarse refine too: its
relative pose from the shots that agree, each shot's pose from the photo its others confirm
(`_initial`), so that one photo off its basin does not hold the others back.

Unknowns. A *body* is a pose of its own: a photo outside a rig, or a rig's shot (the pose of the
rig's first camera). Photo i's pose is T_i = rig[c_i] @ body[b_i] (rig[0] = I; outside a rig
T_i = body[b_i]). The *shared* parameters are the free camera corrections q_c[:free_c]
(`render.project.project_corrected`) and the relative poses rig[c] of cameras c >= 1. The bodies'
6 x 6 blocks are eliminated (Schur complement), so a step costs one small solve per body and one
solve of the shared parameters: 100 photos stay cheap.

Weights. Each photo's objective gives its Gauss-Newton system of the Student-t loss with its own
scale sigma_i^2 (`align.photometric.Photometric.evaluate`); the sum of the photos' negative
log-likelihoods sum_i rho_i has gradient sum_i g_i / sigma_i^2 and Gauss-Newton matrix
sum_i H_i / sigma_i^2, which is what is solved: a photo with noisier residuals counts less.

Agreement (rigs, cfg.bundle_agreement > 0): ETH3D's multi-view term, for the photos of one shot:
at the scan points the shot's first photo sees, its colors and another photo's, each mapped into
the scan's colors by its own color fit, should agree (Student-t, its own scale, times the weight).
Both photos belong to one body, so it keeps the Schur structure; it pins the rig's relative pose
to the photos' own detail, finer than the scan's (docs/bundle.md measures it).

Cross-photo evidence (`evidence`): per body, leave-one-out (the shared parameters re-solved
without it, linearised at the solution, and how far its pose then moves, in its sigmas); per
photo its robust residual scale against the other photos'; per rig photo how far its pose
moves when freed from the rig (linearised), in its own sigmas and against the median photo's.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from rgbd_gt.align import lbfgs
from rgbd_gt.align.aligner import STEP_CAP_PX, Aligner, damped
from rgbd_gt.align.covariance import sandwich, wider
from rgbd_gt.align.photometric import scaled_inverse
from rgbd_gt.errors import LEFT_THE_SCAN, InputError
from rgbd_gt.pose import (apply_update, invert, rotation_error_deg, translated, translation_error_m, update_of,
                          update_through)
from rgbd_gt.camera import Q_SIZE

# the agreement term runs on the finest levels alone: on the coarse ones, blurred, the photos
# agree wherever the scan lands, and the pose is not yet close enough for it to say more
AGREEMENT_FINEST_LEVELS = 2

# a level stops when the camera corrections move the image's edge by less than this (pixels of the
# level) and the poses less than the refine's stop thresholds. At 0.01 px the finest level of an
# 8-photo `focal+principal+k1k2` bundle took 26 iterations where its poses had stopped at 14, the
# last steps k1 and k2 trading along a flat direction; the poses, focal and k1 ended the same to
# 0.0001 deg and 0.0001 % (docs/bundle.md, "Costs")
CAMERA_STOP_PX = 0.05

# a coarse level also stops when this many accepted steps in a row each turn back on the one
# before (cosine below -0.5): the re-fits between steps (colors, scale, inliers) then hold the
# level at that precision, and its pose only goes on to a finer one
OSCILLATION_STEPS = 3


@dataclass
class RigPrior:
    """A prior on a rig camera's pose relative to the rig's first (e.g. a stereo calibration's)."""

    T: np.ndarray  # (4, 4) T_cam_c_from_cam_0
    sigma_rotation_rad: float
    sigma_translation_m: float


@dataclass
class BundlePhoto:
    """One photo of the bundle: its objective (`Photometric`, whose `free` says which camera
    corrections it shares), its initial pose (4x4 T_cam_from_scan, scan frame), its camera's
    index and, in a rig, its shot (None: a body of its own). In a rig, `camera` is also the
    photo's place in the rig (0: the rig's first camera)."""

    objective: object
    T_init: np.ndarray
    camera: int = 0
    shot: int | None = None
    name: str = ""


@dataclass
class BundleResult:
    poses: list[np.ndarray]  # per photo 4x4 T_cam_from_scan
    q: np.ndarray  # (C, Q_SIZE) per camera its corrections (0 where not free)
    q_sigma: np.ndarray  # (C, Q_SIZE) 1-sigma, inf where not free
    pose_covariance: list[np.ndarray]  # per photo (6, 6) of its update (rotation vector, translation), camera frame
    rig: np.ndarray | None  # (C, 4, 4) T_cam_c_from_cam_0 (rig[0] = I), or None without a rig
    rig_covariance: np.ndarray | None  # (C, 6, 6) of each relative pose's update
    terms: list  # per photo its objective's terms at the result, finest level
    iterations: int
    levels: list[dict]
    seconds: float
    evidence: list[dict] = field(default_factory=list)  # per photo: the cross-photo evidence
    q_covariance: list[np.ndarray] = field(default_factory=list)  # per camera (F, F) of its F free corrections
    # photometric: per photo the covariance (6, 6) of its update with every photo's tiles as the
    # samples (`_tiles`) and how many tiles, the same of each relative pose (C, 6, 6) and of each
    # camera's free corrections (F, F); None for nid
    tiles: list[tuple[np.ndarray, int]] | None = None
    rig_tiles: np.ndarray | None = None
    q_tiles: list[np.ndarray] | None = None

    def stated_q_sigma(self, c: int) -> np.ndarray:
        """(Q_SIZE,) camera c's 1-sigmas as a bundle states them (cameras/NAME.yaml): with every
        photo's tiles as the samples wherever wider than the aligner's (`covariance.wider`), inf
        where not free."""
        qs = self.q_sigma[c].copy()
        stated = wider(self.q_covariance[c], self.q_tiles[c]) if self.q_tiles and self.q_covariance else None
        if stated is not None and len(stated):
            qs[:len(stated)] = np.sqrt(np.diag(stated))
        return qs

    def stated_rig_covariance(self, c: int) -> np.ndarray:
        """(6, 6) rig camera c's relative pose covariance as a bundle states it (rig.yaml): the
        same rule as `stated_q_sigma`."""
        stated = wider(self.rig_covariance[c], None if self.rig_tiles is None else self.rig_tiles[c])
        return self.rig_covariance[c] if stated is None else stated


def _apart(T: np.ndarray, U: np.ndarray) -> float:
    """How far two relative poses lie apart: degrees plus centimetres."""
    return rotation_error_deg(T, U) + 100 * translation_error_m(T, U)


def determined(C: np.ndarray) -> np.ndarray:
    """A covariance C (P, P), or all inf where any of it is not finite (inf - inf left NaN)."""
    return C if np.isfinite(C).all() else np.full(C.shape, np.inf)


class Bundle:
    """The joint solve of `photos` (each a `BundlePhoto`); rig_cameras: how many cameras the rig
    has (0: no rig); priors: {camera: RigPrior} for rig cameras >= 1."""

    def __init__(self, photos: list[BundlePhoto], cameras: int, rig_cameras: int = 0,
                 priors: dict[int, RigPrior] | None = None):
        if not photos:
            raise InputError("a bundle needs at least one photo")
        self.photos = photos
        self.cameras = cameras
        self.rig_cameras = rig_cameras
        self.priors = priors or {}
        self.cfg = photos[0].objective.cfg
        self.device = photos[0].objective.device
        self.nid = photos[0].objective.name == "nid"
        if any((p.objective.name == "nid") != self.nid for p in photos):
            raise InputError("a bundle's photos share one objective: photometric (colored scan) or nid (intensity)")
        # bodies: one per shot of the rig, one per photo outside it
        keys = [("shot", p.shot) if p.shot is not None else ("photo", i) for i, p in enumerate(photos)]
        self.body_keys = list(dict.fromkeys(keys))
        self.body_of = np.array([self.body_keys.index(k) for k in keys])
        self.free = np.zeros(cameras, int)
        for p in photos:
            self.free[p.camera] = p.objective.free
        # shared parameters: each camera's free corrections, then each rig camera's relative pose
        self.q_at = np.r_[0, np.cumsum(self.free)][:-1]
        self.rig_at = int(self.free.sum()) + 6 * np.arange(-1, max(rig_cameras, 1) - 1)  # rig_at[c] for c >= 1
        self.shared = int(self.free.sum()) + 6 * max(rig_cameras - 1, 0)
        # the agreement term's pairs: in each rig shot, its first photo with each other one
        self.weight = 0.0 if self.nid else self.cfg.bundle_agreement  # the term compares colors by their fits
        self.pairs = []
        if self.weight > 0 and rig_cameras:
            for b in range(len(self.body_keys)):
                members = sorted((self.photos[i].camera, i) for i in np.nonzero(self.body_of == b)[0] if self._in_rig(i))
                self.pairs += [(members[0][1], i) for _, i in members[1:]]

    # -- the photos' poses from the unknowns -------------------------------------------------------
    def _in_rig(self, i: int) -> bool:
        return self.photos[i].shot is not None and self.rig_cameras > 0

    def pose(self, i: int, bodies: list[np.ndarray], rig: np.ndarray) -> np.ndarray:
        """Photo i's 4x4 T_cam_from_scan (scan frame)."""
        return self._of_body(i, bodies[self.body_of[i]], rig)

    def _of_body(self, i: int, body: np.ndarray, rig: np.ndarray) -> np.ndarray:
        """Photo i's 4x4 T_cam_from_scan where its body's pose is `body`."""
        return rig[self.photos[i].camera] @ body if self._in_rig(i) else body

    def _starts(self) -> tuple[list[np.ndarray], int | None]:
        """Per photo where the solve starts, and the pyramid level its own refine ended on (None:
        its init). Objectives with far spurious minima (nid) start where the photo's wide search
        and its refine down to level 1 land (the joint L-BFGS has no search of its own); a rig
        without a prior starts where each photo's refine down to level 3 lands, since its
        relative pose would otherwise come from one shot's two inits. From inits 5 deg / 20 cm
        off either ended a shot off its basin where single refines do not (docs/bundle.md)."""
        search = self.photos[0].objective.wide_search and self.cfg.search_starts > 0
        unknown_rig = any(c not in self.priors for c in range(1, self.rig_cameras))
        if not (search or unknown_rig):
            return [p.T_init for p in self.photos], None
        level = 1 if search else 3
        starts = []
        for i, p in enumerate(self.photos):
            try:
                starts.append(Aligner(p.objective).refine(p.T_init, finest=level).T_cam_from_scan)
            except InputError as exc:
                raise InputError(f"{p.name or f'photo {i + 1}'}: {exc}") from None
        return starts, level

    def _initial(self, starts: list[np.ndarray], level: int | None) -> tuple[list[np.ndarray], np.ndarray]:
        """The bodies and the rig from the photos' starting poses (`_starts`). The rig from its
        prior, else from the shots holding both cameras: the relative pose closest to the other
        shots' (one photo off its basin spoils its shot's, not the rig's). A shot's body from its
        first camera's photo, or, where the starts are the photos' own refines (down to `level`),
        from whichever of its photos the others fit best there (`_confirmed`)."""
        rig = np.stack([np.eye(4)] * max(self.rig_cameras, 1))
        for c in range(1, self.rig_cameras):
            if c in self.priors:
                rig[c] = self.priors[c].T
                continue
            found = []
            for k in self.body_keys:
                members = {p.camera: T for p, T in zip(self.photos, starts) if p.shot is not None and ("shot", p.shot) == k}
                if 0 in members and c in members:
                    found.append(members[c] @ invert(members[0]))
            if not found:
                raise InputError(f"rig camera {c}: no shot has photos of it and of the rig's first camera, and the "
                                 "rig gives no prior for it")
            rig[c] = found[int(np.argmin([sum(_apart(T, U) for U in found) for T in found]))]
        bodies = []
        for b in range(len(self.body_keys)):
            members = sorted(np.nonzero(self.body_of == b)[0], key=lambda i: self.photos[i].camera)
            found = [invert(rig[self.photos[i].camera]) @ starts[i] if self._in_rig(i) else starts[i] for i in members]
            bodies.append(self._confirmed(members, found, rig, starts, level) if level is not None and len(found) > 1 else found[0])
        return bodies, rig

    def _confirmed(self, members: list[int], found: list[np.ndarray], rig: np.ndarray, starts: list[np.ndarray],
                   level: int) -> np.ndarray:
        """Of a shot's candidate bodies `found` (one per member photo), the one its photos fit
        best on `level` (where their starts ended): each photo's loss there on the points, color
        fit and scale of its own start, summed over the photos whose start sees the scan."""
        q = torch.zeros(Q_SIZE, device=self.device)
        score = np.zeros(len(found))
        for i in members:
            obj = self.photos[i].objective
            start = translated(starts[i], obj.centre)
            on = min(level, obj.prepare(start) - 1)  # prepared by the photo's own refine already
            try:
                at = obj.evaluate(on, [start], q, jacobian=False)
            except InputError:
                continue
            score += [float(obj.trial(on, [translated(self._of_body(i, B, rig), obj.centre)], q, at)[0]) for B in found]
        return found[int(np.argmin(score))]

    def _q(self, q: np.ndarray, c: int) -> torch.Tensor:
        return torch.as_tensor(q[c], dtype=torch.float32, device=self.device)

    # -- evaluation --------------------------------------------------------------------------------
    def _evaluate(self, level: int, bodies, rig, q, prev=None) -> list:
        out = []
        for i, p in enumerate(self.photos):
            T = translated(self.pose(i, bodies, rig), p.objective.centre)
            try:
                out.append(p.objective.evaluate(level, [T], self._q(q, p.camera), None if prev is None else prev[i], True))
            except InputError as exc:
                raise InputError(f"{p.name or f'photo {i + 1}'}: {exc}") from None
        return out

    def _agreement(self, level: int, bodies, rig, q, at: list, held: list | None = None,
                   tried: list | None = None) -> list[dict]:
        """The agreement term of each pair (i, j) of a shot (ETH3D's multi-view term): at the
        points photo i sees, photo i's colors mapped into the scan's by its color fit minus photo
        j's by its own, Student-t weighted. Per pair: its sum of negative log-likelihoods `rho`,
        and (without `held`) its Gauss-Newton system over photo i's parameters then photo j's,
        its points and scale. held: the pairs' terms a trial step keeps (points, scale); tried:
        then each photo's predictions at its trial pose (`trial_colors`). Photo i's colors are
        those its own evaluation or trial sampled at these points."""
        from rgbd_gt.align.robust import student_t_loss, student_t_weights

        out = []
        if level > AGREEMENT_FINEST_LEVELS - 1:
            return out
        for k, (i, j) in enumerate(self.pairs):
            pi, pj = self.photos[i], self.photos[j]
            pts = pi.objective.levels[level].points[at[i].mask[0]]
            shift = torch.as_tensor(pi.objective.centre - pj.objective.centre, dtype=pts.dtype, device=pts.device)
            Tj = translated(self.pose(j, bodies, rig), pj.objective.centre)
            jac = held is None
            ci, Ji = pi.objective.own_colors(at[i]) if jac else (tried[i], None)
            cj, ok_j, Jj = pj.objective.seen_colors(level, Tj, self._q(q, pj.camera), pts + shift, at[j].D[0], jac)
            ok = ok_j if jac else held[k]["ok"]  # photo i sees all its visible points
            r = (ci - cj)[ok]
            if not jac:
                out.append({"rho": float(student_t_loss(r, self.cfg.nu, held[k]["sigma2"])) * r.numel()})
                continue
            w, sigma2 = student_t_weights(r, self.cfg.nu)
            J = torch.cat([Ji[ok], -Jj[ok]], 2).reshape(-1, Ji.shape[2] + Jj.shape[2]).double()
            wf, rf = w.reshape(-1).double(), r.reshape(-1).double()
            out.append({"ok": ok, "sigma2": sigma2, "rho": float(student_t_loss(r, self.cfg.nu, sigma2)) * r.numel(),
                        "H": (J.T @ (wf[:, None] * J)).cpu().numpy(), "g": (J.T @ (wf * rf)).cpu().numpy(),
                        "wrr": float((wf * rf * rf).sum()), "count": r.numel(), "scale": float(sigma2)})
        return out

    @staticmethod
    def _rho(at) -> float:
        """The photo's sum of negative log-likelihoods (its loss is their mean per residual)."""
        return float(at.loss[0]) * float(at.count[0])

    def _prior_terms(self, rig: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """The rig priors' energy, gradient (S,) and matrix (S, S) over the shared parameters."""
        g, H, energy = np.zeros(self.shared), np.zeros((self.shared, self.shared)), 0.0
        for c, prior in self.priors.items():
            e = update_of(rig[c] @ invert(prior.T))
            w = np.r_[[1 / prior.sigma_rotation_rad**2] * 3, [1 / prior.sigma_translation_m**2] * 3]
            s = slice(self.rig_at[c], self.rig_at[c] + 6)
            g[s] += w * e
            H[s, s] += np.diag(w)
            energy += 0.5 * float(e @ (w * e))
        return energy, g, H

    def _maps(self, i: int, rig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Photo i's parameters (pose 6, its free corrections) as linear maps of its body's
        update (P, 6) and of the shared update (P, S)."""
        p = self.photos[i]
        P = 6 + p.objective.free
        Jb, Js = np.zeros((P, 6)), np.zeros((P, self.shared))
        c = p.camera
        if self._in_rig(i):
            Jb[:6] = update_through(rig[c])
            if c >= 1:
                Js[:6, self.rig_at[c]:self.rig_at[c] + 6] = np.eye(6)
        else:
            Jb[:6] = np.eye(6)
        for k in range(p.objective.free):
            Js[6 + k, self.q_at[c] + k] = 1.0
        return Jb, Js

    def _pair_maps(self, i: int, j: int, rig: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """`_maps` of an agreement pair's parameters (photo i's, then photo j's; one body)."""
        (Jbi, Jsi), (Jbj, Jsj) = self._maps(i, rig), self._maps(j, rig)
        return np.vstack([Jbi, Jbj]), np.vstack([Jsi, Jsj])

    def _system(self, Hs: list, gs: list, rig: np.ndarray, scale: list[float], pairs: list[dict] = ()):
        """The joint Gauss-Newton system of the photos' matrices Hs (P, P) and gradients gs (P,)
        over their parameters (pose, free corrections), each divided by its scale, per body:
        U (nb, 6, 6), W (nb, 6, S), gb (nb, 6) and its share of the shared parameters' block
        Vb (nb, S, S) and gradient gsb (nb, S); with the agreement term's pairs (`_agreement`,
        each weighted by cfg.bundle_agreement over its scale)."""
        nb, S = len(self.body_keys), self.shared
        U, W, gb = np.zeros((nb, 6, 6)), np.zeros((nb, 6, S)), np.zeros((nb, 6))
        Vb, gsb = np.zeros((nb, S, S)), np.zeros((nb, S))
        # (body, maps of its parameters, H, g): each photo, then each pair (both photos of one shot: one body)
        parts = [(self.body_of[i], self._maps(i, rig), H / scale[i], g / scale[i]) for i, (H, g) in enumerate(zip(Hs, gs))]
        for (i, j), pair in zip(self.pairs, pairs):
            w = self.weight / pair["scale"]
            parts.append((self.body_of[i], self._pair_maps(i, j, rig), pair["H"] * w, pair["g"] * w))
        for b, (Jb, Js), H, g in parts:
            U[b] += Jb.T @ H @ Jb
            W[b] += Jb.T @ H @ Js
            gb[b] += Jb.T @ g
            Vb[b] += Js.T @ H @ Js
            gsb[b] += Js.T @ g
        return U, W, gb, Vb, gsb

    def _step(self, system, prior, lam: float) -> tuple[np.ndarray, np.ndarray]:
        """The damped Gauss-Newton step: bodies' updates (nb, 6) and the shared update (S,),
        the bodies eliminated first (Schur complement)."""
        U, W, gb, Vb, gsb = system
        _, pg, pH = prior
        V, gs = Vb.sum(0) + pH, gsb.sum(0) + pg
        reduced, rhs = V.copy(), -gs.copy()
        Ud = [damped(U[b], lam) for b in range(len(U))]
        Ui_W = [np.linalg.solve(Ud[b], W[b]) for b in range(len(U))]
        Ui_g = [np.linalg.solve(Ud[b], gb[b]) for b in range(len(U))]
        for b in range(len(U)):
            reduced -= W[b].T @ Ui_W[b]
            rhs += W[b].T @ Ui_g[b]
        xs = np.linalg.solve(damped(reduced, lam), rhs) if self.shared else np.zeros(0)
        xb = np.stack([-Ui_g[b] - Ui_W[b] @ xs for b in range(len(U))])
        return xb, xs

    def _moved(self, bodies, rig, q, xb, xs):
        bodies = [apply_update(T, d) for T, d in zip(bodies, xb)]
        rig, q = rig.copy(), q.copy()
        for c in range(1, self.rig_cameras):
            rig[c] = apply_update(rig[c], xs[self.rig_at[c]:self.rig_at[c] + 6])
        for c in range(self.cameras):
            q[c, :self.free[c]] += xs[self.q_at[c]:self.q_at[c] + self.free[c]]
        return bodies, rig, q

    def _converged(self, xb: np.ndarray, xs: np.ndarray, level: int) -> bool:
        """Every body, rig pose and camera moves less than the stop thresholds at this level's
        pixel size (a camera correction by its effect at the image's edge, taken as 0.5 in
        normalised units, against CAMERA_STOP_PX)."""
        scale = 2.0**level
        poses = [xb[b] for b in range(len(xb))] + [xs[self.rig_at[c]:self.rig_at[c] + 6] for c in range(1, self.rig_cameras)]
        still = all(np.degrees(np.linalg.norm(d[:3])) < self.cfg.stop_rotation_deg * scale
                    and np.linalg.norm(d[3:]) < self.cfg.stop_translation_m * scale for d in poses)
        for c in range(self.cameras):
            dq = xs[self.q_at[c]:self.q_at[c] + self.free[c]]
            if len(dq):
                fx = float(self.photos[[p.camera for p in self.photos].index(c)].objective.pyramid[0].K[0, 0])
                still &= bool(np.abs(dq).max() * 0.5 * fx < CAMERA_STOP_PX * scale)
        return still

    # -- the solve ---------------------------------------------------------------------------------
    def solve(self, progress=None) -> BundleResult:
        """Coarse to fine, Levenberg-Marquardt on all the unknowns at once; then the covariance
        and the cross-photo evidence at the result."""
        start = time.perf_counter()
        starts, start_level = self._starts()
        bodies, rig = self._initial(starts, start_level)
        q = np.zeros((self.cameras, Q_SIZE))
        levels = [p.objective.prepare(translated(self.pose(i, bodies, rig), p.objective.centre))
                  for i, p in enumerate(self.photos)]
        top = min(levels) - 1
        if start_level is not None and not self.nid:
            # a colored rig goes on where its photos' own refines ended: their coarser levels are
            # done. nid's joint L-BFGS runs them again: from level 1 it cost about as much and
            # left the default-size seed-0 rig's worst pose 1.26 mm off, not 0.95 (docs/bundle.md)
            top = min(top, start_level)
        level_info, total = [], 0
        for level in range(top, -1, -1):
            if self.nid:
                bodies, rig, its, stop = self._lbfgs(level, bodies, rig, self.cfg.iterations, progress)
            else:
                bodies, rig, q, its, stop = self._lm(level, bodies, rig, q, self.cfg.iterations, progress)
            level_info.append({"level": level, "iterations": its, "stop": stop})
            total += its
        terms = self._evaluate(0, bodies, rig, q)
        result = BundleResult([self.pose(i, bodies, rig) for i in range(len(self.photos))], q, np.full_like(q, np.inf),
                              [np.full((6, 6), np.inf)] * len(self.photos), rig if self.rig_cameras else None, None,
                              terms, total, level_info, 0.0)
        self._uncertainty_and_evidence(result, bodies, rig, terms)
        result.seconds = time.perf_counter() - start
        return result

    def _loss(self, at: list, pairs: list[dict], prior) -> float:
        return sum(self._rho(a) for a in at) + self.weight * sum(p["rho"] for p in pairs) + prior[0]

    def _lm(self, level, bodies, rig, q, iterations, progress):
        at = self._evaluate(level, bodies, rig, q)
        pairs = self._agreement(level, bodies, rig, q, at)
        prior = self._prior_terms(rig)
        loss = self._loss(at, pairs, prior)
        lam, stop, it = 1e-4, "iteration cap", 0
        last, reversals = None, 0
        for it in range(1, iterations + 1):
            scale = [float(a.sigma2.reshape(-1)[0]) for a in at]
            xb, xs = self._step(self._system([a.H[0] for a in at], [a.g[0] for a in at], rig, scale, pairs), prior, lam)
            nb, nr, nq = self._moved(bodies, rig, q, xb, xs)
            tried = [p.objective.trial_colors(level, [translated(self.pose(i, nb, nr), p.objective.centre)],
                                              self._q(nq, p.camera), a) for i, (p, a) in enumerate(zip(self.photos, at))]
            trial = sum(float(loss[0]) * float(a.count[0]) for (loss, _), a in zip(tried, at))
            trial += self.weight * sum(p["rho"] for p in self._agreement(level, nb, nr, nq, at, pairs,
                                                                           [colors[0] for _, colors in tried]))
            new_prior = self._prior_terms(nr)
            accepted = trial + new_prior[0] <= loss
            if accepted:
                bodies, rig, q, prior = nb, nr, nq, new_prior
                at = self._evaluate(level, bodies, rig, q, at)
                pairs = self._agreement(level, bodies, rig, q, at)
                loss = self._loss(at, pairs, prior)
                lam = max(lam / 4, 1e-7)
            else:
                lam *= 8
            if progress is not None:
                progress({"level": level, "iteration": it, "loss": loss, "accepted": accepted})
            if accepted and self._converged(xb, xs, level):
                stop = "converged"
                break
            if accepted and level > 0:
                step = np.r_[xb.ravel(), xs]
                reversals = reversals + 1 if last is not None and step @ last < -0.5 * np.linalg.norm(step) * np.linalg.norm(last) else 0
                last = step
                if reversals >= OSCILLATION_STEPS:
                    stop = "oscillating"
                    break
            if lam > 1e6:
                stop = "damping ran away"
                break
        return bodies, rig, q, it, stop

    def _lbfgs(self, level, bodies, rig, iterations, progress):
        """nid (no Gauss-Newton form): L-BFGS on one level over every body's and rig camera's
        update at once, each photo's update their linear map (`_maps`, as the LM step takes it),
        on the points each photo sees at the level's start; each unknown in units of one level
        pixel of its first photo and capped smoothly at STEP_CAP_PX of them (the single aligner
        also bounds each step by its wide search's size; the joint solve, after each photo's own
        search in `_starts`, has no such bound)."""
        n, nb = len(self.photos), len(self.body_keys)
        q = np.zeros((self.cameras, Q_SIZE))
        Ts = [translated(self.pose(i, bodies, rig), p.objective.centre) for i, p in enumerate(self.photos)]
        at = self._evaluate(level, bodies, rig, q)
        maps = [self._maps(i, rig) for i in range(n)]
        batches = [p.objective.batch([at[i]]) for i, p in enumerate(self.photos)]
        units = np.zeros(6 * nb + self.shared)
        for i, p in enumerate(self.photos):  # each unknown measured on the first photo it moves
            u = p.objective.units(level, Ts[i], at[i]).cpu().numpy()
            blocks = [6 * self.body_of[i]] + ([6 * nb + self.rig_at[p.camera]] if self._in_rig(i) and p.camera >= 1 else [])
            for b in blocks:
                if not units[b:b + 6].any():
                    units[b:b + 6] = u

        def unknowns(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            squash = np.tanh(y / STEP_CAP_PX)
            return units * STEP_CAP_PX * squash, units * (1 - squash**2)

        def objective(y: np.ndarray) -> tuple[float, np.ndarray]:
            x, dx = unknowns(y)
            value, grad = 0.0, np.zeros_like(y)
            for i, p in enumerate(self.photos):
                (Jb, Js), b = maps[i], self.body_of[i]
                d = Jb @ x[6 * b:6 * b + 6] + Js @ x[6 * nb:]
                (v,), g = p.objective.value_and_gradient(level, [Ts[i]], torch.as_tensor(d, device=self.device)[None], batches[i])
                if not np.isfinite(v):
                    raise InputError(f"{p.name or f'photo {i + 1}'}: {LEFT_THE_SCAN}")
                g = g[0].cpu().numpy()
                value += v
                grad[6 * b:6 * b + 6] += Jb.T @ g
                grad[6 * nb:] += Js.T @ g
            return value, grad * dx

        y, its = lbfgs.minimize(objective, np.zeros(len(units)), iterations)
        x = unknowns(y)[0]
        bodies, rig, _ = self._moved(bodies, rig, q, x[:6 * nb].reshape(nb, 6), x[6 * nb:])
        if progress is not None:
            progress({"level": level, "iteration": its, "loss": objective(y)[0], "accepted": True})
        return bodies, rig, its, "iteration cap" if its >= iterations else "converged"

    # -- what the result is worth ------------------------------------------------------------------
    def _uncertainty_and_evidence(self, result: BundleResult, bodies, rig, terms) -> None:
        """The covariance of every unknown from the joint Gauss-Newton matrix at the result (each
        photo's residual variance as its own covariance does: `photometric.covariance`), by blocks
        through the Schur complement (the shared parameters' covariance is its inverse), so that it
        costs what a step does; and the cross-photo evidence (the module's docstring)."""
        nb = len(self.body_keys)
        Hs, gs, scale, spread = self._quadratics(terms, bodies, rig)
        pairs = self._agreement(0, bodies, rig, result.q, terms)
        for pair in pairs:  # the residual variance, as for the photos
            pair["scale"] = pair["wrr"] / max(pair["count"] - len(pair["H"]), 1)
        system = self._system(Hs, gs, rig, scale, pairs)
        U, W, _, Vb, _ = system
        prior = self._prior_terms(rig)
        Ui = [scaled_inverse(U[b]) for b in range(nb)]
        # a body at no minimum of its photos (U not positive definite: a shot solved off its basin,
        # its inverse all inf) says nothing of the shared parameters, and its pose is undetermined;
        # the others' covariances come from the kept bodies alone
        kept = [bool(np.isfinite(Ui[b]).all()) for b in range(nb)]
        UiW = [Ui[b] @ W[b] if kept[b] else np.zeros_like(W[b]) for b in range(nb)]
        # the reduced problem of the shared parameters is a sum over the kept bodies (and the prior)
        S_b = [Vb[b] - W[b].T @ UiW[b] if kept[b] else np.zeros_like(Vb[b]) for b in range(nb)]
        Si = scaled_inverse(sum(S_b) + prior[2]) if self.shared else np.zeros((0, 0))
        # shared parameters that the kept bodies do not fix leave Si all inf, and inf x 0 NaN
        # below: `determined` makes those covariances all inf, quietly
        with np.errstate(invalid="ignore"):
            cov_body = [determined(Ui[b] + UiW[b] @ Si @ UiW[b].T) for b in range(nb)]  # each body's 6 x 6 block
            for i in range(len(self.photos)):
                Jb, Js = (m[:6] for m in self._maps(i, rig))
                b = self.body_of[i]
                cross = -Jb @ UiW[b] @ Si @ Js.T
                result.pose_covariance[i] = determined(Jb @ cov_body[b] @ Jb.T + cross + cross.T + Js @ Si @ Js.T)
            for c in range(self.cameras):
                s = slice(self.q_at[c], self.q_at[c] + self.free[c])
                result.q_covariance.append(Si[s, s])
                result.q_sigma[c, :self.free[c]] = np.sqrt(np.diag(Si[s, s]))
            if self.rig_cameras:
                result.rig_covariance = np.zeros((self.rig_cameras, 6, 6))
                for c in range(1, self.rig_cameras):
                    s = slice(self.rig_at[c], self.rig_at[c] + 6)
                    result.rig_covariance[c] = determined(Si[s, s])
            result.evidence = self._evidence(Hs, gs, scale, spread, system, prior, Ui, cov_body, kept, S_b)
        if not self.nid:
            self._tiles(result, terms, rig, scale, pairs, system, prior, kept)

    def _tiles(self, result: BundleResult, terms: list, rig: np.ndarray, scale: list[float], pairs: list[dict],
               system, prior, kept: list[bool]) -> None:
        """The covariance of every photo's pose and of the rig with the photos' tiles as the samples
        (`Photometric.tile_scores`; each pair of the agreement term one sample more): the sandwich
        of the joint system over all unknowns at once (6 a body, then the shared parameters), of
        the kept bodies (as the aligner's covariance), into result.tiles (None for a photo of a
        body left out), result.rig_tiles and result.q_tiles. Left None where the system has no minimum."""
        nb = len(self.body_keys)
        n = 6 * nb + self.shared
        U, W, _, Vb, _ = system
        H = np.zeros((n, n))
        H[6 * nb:, 6 * nb:] = sum(Vb[b] for b in range(nb) if kept[b]) + prior[2]
        for b in range(nb):
            H[6 * b:6 * b + 6, 6 * b:6 * b + 6] = U[b] if kept[b] else np.eye(6)  # a body left out: its own, apart
            if kept[b]:
                H[6 * b:6 * b + 6, 6 * nb:] = W[b]
                H[6 * nb:, 6 * b:6 * b + 6] = W[b].T

        def placed(b: int, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:  # (P, n): a photo's parameters' rows
            out = np.zeros((len(maps[0]), n))
            out[:, 6 * b:6 * b + 6], out[:, 6 * nb:] = maps
            return out

        samples = [self.photos[i].objective.tile_scores(0, at)[0] / scale[i] @ placed(self.body_of[i], self._maps(i, rig))
                   for i, at in enumerate(terms) if kept[self.body_of[i]]]
        for (i, j), pair in zip(self.pairs, pairs):
            if kept[self.body_of[i]]:
                samples.append((pair["g"] * self.weight / pair["scale"])[None] @ placed(self.body_of[i], self._pair_maps(i, j, rig)))
        C = sandwich(np.concatenate(samples), H) if samples else None
        if C is None:
            return
        count = sum(len(x) for x in samples)
        result.tiles = []
        for i in range(len(self.photos)):
            M = placed(self.body_of[i], self._maps(i, rig))[:6]
            result.tiles.append((M @ C @ M.T, count) if kept[self.body_of[i]] else None)
        if self.rig_cameras:
            result.rig_tiles = np.zeros((self.rig_cameras, 6, 6))
            for c in range(1, self.rig_cameras):
                k = 6 * nb + self.rig_at[c]
                result.rig_tiles[c] = C[k:k + 6, k:k + 6]
        result.q_tiles = [C[6 * nb + self.q_at[c]:, 6 * nb + self.q_at[c]:][:self.free[c], :self.free[c]]
                          for c in range(self.cameras)]

    def _quadratics(self, terms: list, bodies, rig) -> tuple[list, list, list[float], list[float] | None]:
        """Per photo at the result, finest level: its matrix H (P, P) and gradient g (P,) over
        its parameters, the scale they are divided by, and its residuals' robust scale (None for
        nid). Photometric: its Gauss-Newton terms and their residual variance. nid: the Laplace
        Hessian of its negative log-likelihood (`Nid.frame_quadratics`, per unit of the
        parameters), whose scale is already 1."""
        if not self.nid:
            return ([a.H[0] for a in terms], [a.g[0] for a in terms],
                    [float(a.wrr[0]) / max(float(a.count[0]) - a.H.shape[1], 1) for a in terms],
                    [float(a.sigma2.reshape(-1)[0]) ** 0.5 for a in terms])
        Hs, gs = [], []
        for i, (p, at) in enumerate(zip(self.photos, terms)):
            g, H, u = p.objective.frame_quadratics(0, translated(self.pose(i, bodies, rig), p.objective.centre), at)
            Hs.append(H[0] / u[:, None] / u[None, :])
            gs.append(g[0] / u)
        return Hs, gs, [1.0] * len(terms), None

    def _evidence(self, Hs, gs, scale, spread, system, prior, Ui, cov_body, kept, S_b) -> list[dict]:
        """Per photo: leave its body out, its residual scale against the others', and (in a rig)
        its pose freed from the rig; see the module's docstring. kept: per body whether it is at
        a minimum of its photos (the others count without it); S_b: each body's part of the
        shared parameters' reduced matrix (0 where not kept)."""
        U, W, gb, Vb, gsb = system
        nb = len(self.body_keys)
        ev = [dict() for _ in self.photos]
        if self.shared:
            # without body b, its part is taken out and the others' Newton step taken
            r_b = [gsb[b] - W[b].T @ Ui[b] @ gb[b] if kept[b] else np.zeros_like(gsb[b]) for b in range(nb)]
            S, r = sum(S_b) + prior[2], sum(r_b) + prior[1]
            for b in range(nb):
                others = scaled_inverse(S - S_b[b])
                d_shared = -others @ (r - r_b[b])
                d_body = -Ui[b] @ (gb[b] + W[b] @ d_shared)
                C = cov_body[b]
                sig = float(np.sqrt(max(d_body @ scaled_inverse(C) @ d_body, 0.0))) if np.isfinite(d_body).all() \
                    and np.isfinite(C).all() else None  # None: the others alone do not fix the shared parameters
                for i in np.nonzero(self.body_of == b)[0]:
                    ev[i]["leave_one_out_sigmas"] = sig
        for i in range(len(self.photos) if spread is not None else 0):
            others = np.delete(spread, i)
            ev[i]["residual_vs_others"] = float(spread[i] / np.median(others)) if len(others) else 1.0
        for i, (H, g) in enumerate(zip(Hs, gs)):
            if self._in_rig(i):
                Hp = H[:6, :6] / scale[i]
                step = -np.linalg.solve(Hp, g[:6] / scale[i])
                ev[i]["freed_from_rig_sigmas"] = float(np.sqrt(max(step @ Hp @ step, 0.0)))
        # a shot off the rig pulls the rig, so that every shot moves when freed: how far each moves
        # against the typical shot tells the one that pulls
        freed = [e["freed_from_rig_sigmas"] for e in ev if "freed_from_rig_sigmas" in e]
        for e in ev:
            if "freed_from_rig_sigmas" in e:
                e["freed_vs_others"] = e["freed_from_rig_sigmas"] / max(float(np.median(freed)), 1e-9)
        return ev
