"""The one alignment driver: refine T_cam_from_scan coarse to fine over an objective's image
pyramid, with Levenberg-Marquardt, Adam (the paper's) or L-BFGS, and for objectives with spurious
far minima a wide search on the coarsest level.

An objective (align/photometric.py, align/nid_objective.py; the interface: align/objective.py)
keeps its data in a local frame (`centre`: float32 stays exact for georeferenced coordinates) and
evaluates a batch of local-frame poses (one pose is a batch of one) with the shared camera
corrections q (Q_SIZE,) (`render.project.project_corrected`): `prepare` chooses every level's points
once, `evaluate` gives per pose the loss and, for LM, the Gauss-Newton system, `trial` the loss at
other poses on the same points and fits; L-BFGS (`method == "lbfgs"`) takes `units`, `batch`
and `value_and_gradient` besides (the starts of a level run in lockstep, evaluated together).
The driver holds no state between calls: every refine starts from the camera file's intrinsics.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from rgbd_gt.align import lbfgs
from rgbd_gt.align.covariance import sandwich
from rgbd_gt.align.objective import Objective, lockstep
from rgbd_gt.errors import LEFT_THE_SCAN, InputError
from rgbd_gt.pose import apply_update, random_starts, rotation_error_deg, translated
from rgbd_gt.camera import Q_SIZE

# An L-BFGS level moves each pose parameter by at most this many of its pixels and at most the
# search size (smoothly, through tanh): NID has spurious minima far away, where other structure
# lines up by chance, and a line search reaches them in one step; in a street scene one pixel of a
# coarse level is a metre of camera motion.
STEP_CAP_PX = 16.0


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
    objective: str = "photometric"  # or "nid" (align/nid_objective.py); loss is then the mean NID
    # with cfg.refine_intrinsics: the camera corrections q (Q_SIZE,) (`render.project.project_corrected`)
    # and their 1-sigma (inf where not refined)
    intrinsics: np.ndarray | None = None
    intrinsics_sigma: np.ndarray | None = None
    start_residuals: tuple[np.ndarray, np.ndarray] | None = None  # (uv (N, 2), |r| (N,)) at full resolution
    end_residuals: tuple[np.ndarray, np.ndarray] | None = None
    # a joint solve (nid, several frames): each frame's share of the objective as a quadratic at
    # the result, (g (F, 6), H (F, 6, 6), units (6,)) (`Nid.frame_quadratics`)
    frame_quadratics: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    # the covariance (6, 6) of the update with the photo's tiles as the samples
    # (`align.covariance.sandwich` of the objective's `tile_scores`; a joint nid solve: of all its
    # frames' tiles; a bundle's photo: of all its photos' tiles in its joint system), and how many tiles
    tiles: tuple[np.ndarray, int] | None = None


def tiles_sandwich(scores: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, int] | None:
    """`RefineResult.tiles` from a photo's tile scores (g (K, P), H (P, P)), or None."""
    if scores is None:
        return None
    C = sandwich(*scores)
    return None if C is None else (C[:6, :6], len(scores[0]))


def damped(H: np.ndarray, lam: float) -> np.ndarray:
    """Levenberg-Marquardt's matrix: H (P, P) with lam times its diagonal added (Marquardt's
    scaling: each parameter damped in its own units)."""
    return H + lam * np.diag(np.diag(H) + 1e-12)


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


class Aligner:
    """Refines poses against one objective (see the module's docstring)."""

    def __init__(self, objective: Objective):
        self.objective = objective
        self.cfg = objective.cfg
        self.device = objective.device

    def _q(self, intrinsics: np.ndarray | None) -> torch.Tensor:
        q = np.zeros(Q_SIZE) if intrinsics is None else np.asarray(intrinsics, np.float64)
        return torch.as_tensor(q, dtype=torch.float32, device=self.device)

    def _local(self, T: np.ndarray) -> np.ndarray:
        return translated(np.asarray(T, np.float64), self.objective.centre)

    def _scan(self, T_local: np.ndarray) -> np.ndarray:
        return translated(T_local, -self.objective.centre)

    def _converged(self, delta: np.ndarray, level: int = 0) -> bool:
        """The update is below the stop thresholds, scaled by the level's pixel size (2^level):
        a coarse level only hands its pose on to a finer one."""
        scale = 2.0**level
        return (np.degrees(np.linalg.norm(delta[:3])) < self.cfg.stop_rotation_deg * scale
                and np.linalg.norm(delta[3:6]) < self.cfg.stop_translation_m * scale)

    # -- refine ------------------------------------------------------------------------------------
    def refine(self, T_init: np.ndarray, progress: Callable[[dict], None] | None = None,
               keep_residuals: bool = False, finest: int = 0, coarsest: int | None = None,
               iterations: int | None = None, intrinsics: np.ndarray | None = None) -> RefineResult:
        """Refine T_init (4x4 T_cam_from_scan). progress(record) is called after each iteration
        (after each level with L-BFGS).

        finest, coarsest: the pyramid levels to run (0 = full resolution; default all);
        iterations: another cap per level than the config's; intrinsics: the camera corrections
        q (Q_SIZE,) to start from (default: the camera file's, zeros)."""
        start = time.perf_counter()
        obj = self.objective
        T = self._local(T_init)
        n_levels = obj.prepare(T)
        top = n_levels - 1 if coarsest is None else min(coarsest, n_levels - 1)
        finest = min(finest, top)  # a pyramid shallower than the level asked for (--levels 2) ends on its top
        q = self._q(intrinsics)
        start_res = obj.residuals(0, obj.evaluate(0, [T], q, jacobian=False)) if keep_residuals else None
        if obj.method == "lbfgs":
            (run,) = self._searched([T], top, finest, iterations or self.cfg.iterations, progress)
            if run is None:
                raise InputError(LEFT_THE_SCAN)
            T, history, level_info = run
        else:
            history, level_info = [], []
            for level in range(top, finest - 1, -1):
                if obj.method == "lm":
                    Ts, q, its, stops, _ = self._lm(level, [T], q, iterations or self.cfg.iterations, history, progress)
                    T, n_it, stop = Ts[0], int(its[0]), stops[0]
                else:
                    T, n_it, stop = self._adam(level, T, q, history, progress, iterations)
                level_info.append({"level": level, "iterations": n_it, "stop": stop})
        final = obj.evaluate(finest, [T], q, jacobian=finest == 0)
        cov = obj.covariance(finest, T, q, final) if finest == 0 else None
        sigma = None
        if obj.free and cov is not None:
            sigma = np.full(Q_SIZE, np.inf)
            sigma[:obj.free] = np.sqrt(np.diag(cov)[6:])
        return RefineResult(
            T_cam_from_scan=self._scan(T), iterations=sum(info["iterations"] for info in level_info),
            seconds=time.perf_counter() - start, history=history, levels=level_info,
            covariance=cov[:6, :6] if cov is not None else None, objective=obj.name,
            intrinsics=q.double().cpu().numpy() if obj.free else None, intrinsics_sigma=sigma,
            start_residuals=start_res, end_residuals=obj.residuals(0, final) if keep_residuals else None,
            frame_quadratics=getattr(final, "quadratics", None) if cov is not None else None,
            tiles=tiles_sandwich(getattr(final, "tiles", None)) if cov is not None else None,
            **obj.summary(final),
        )

    def refine_many(self, starts: list[np.ndarray], finest: int = 0, coarsest: int | None = None,
                    iterations: int | None = None, intrinsics: np.ndarray | None = None) -> list[np.ndarray | None]:
        """`refine` from each of several starts (4x4 T_cam_from_scan) on the prepared points, with
        the camera corrections `intrinsics` (Q_SIZE,) held (a result's). All at once: with
        Levenberg-Marquardt in one set of tensor operations (each keeps its own damping, acceptance
        and stop), with L-BFGS in lockstep, wide search included (a repeat that skipped it would
        answer another question); with Adam one after another. Returns the poses, None for a start
        that lost the scan."""
        obj = self.objective
        if obj.method == "adam":
            return refine_each(self, starts, finest=finest, coarsest=coarsest, iterations=iterations)
        Ts = [self._local(T) for T in starts]
        n_levels = obj.prepare(Ts[0])  # prepared by an earlier refine, else around the first start
        top = n_levels - 1 if coarsest is None else min(coarsest, n_levels - 1)
        finest = min(finest, top)
        if obj.method == "lbfgs":
            runs = self._searched(Ts, top, finest, iterations or self.cfg.iterations, None)
            return [None if run is None else self._scan(run[0]) for run in runs]
        q = self._q(intrinsics)
        lost = np.zeros(len(Ts), bool)
        for level in range(top, finest - 1, -1):
            Ts, _, _, _, lost = self._lm(level, Ts, q, iterations or self.cfg.iterations, lost=lost)
        return [None if gone else self._scan(T) for T, gone in zip(Ts, lost)]

    def prepare(self, T_init: np.ndarray) -> int:
        """Choose the points of every level around T_init (4x4 T_cam_from_scan), as the first
        refine does (later refines and repeats keep them). Returns the number of levels."""
        return self.objective.prepare(self._local(T_init))

    # -- what the verification (align/verify.py) asks of a result ---------------------------------
    def visible_scan_points(self, T: np.ndarray, intrinsics: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) float64 scan-frame points of the finest level visible at pose T."""
        return self.objective.visible_scan_points(self._local(T), self._q(intrinsics)) + self.objective.centre

    def median_depth(self, T: np.ndarray) -> float:
        """Median depth (m) of the points in view at pose T over all frames (`Nid.median_depth`)."""
        return self.objective.median_depth(self._local(T))

    def ring_edge_check(self, T: np.ndarray, shift_px: float) -> dict | None:
        """The objective's image check of a sweep at pose T (`Nid.ring_edge_check`), or None."""
        check = getattr(self.objective, "ring_edge_check", None)
        return None if check is None else check(self._local(T), shift_px)

    def loss_profile(self, T: np.ndarray, deltas: np.ndarray, level: int = 0,
                     intrinsics: np.ndarray | None = None) -> tuple[float, np.ndarray]:
        """The loss at pose T and at T moved by each update of deltas (k, 6) (`apply_update`), on a
        pyramid level with the points and fits of T: how clear a minimum T is."""
        obj, q = self.objective, self._q(intrinsics)
        T_local = self._local(T)
        level = min(level, obj.prepare(T_local) - 1)
        at = obj.evaluate(level, [T_local], q, jacobian=False)
        if not len(deltas):
            return float(at.loss[0]), np.zeros(0)
        return float(at.loss[0]), obj.trial(level, [apply_update(T_local, d) for d in deltas], q, at)

    # -- Levenberg-Marquardt -----------------------------------------------------------------------
    def _lm(self, level: int, Ts: list[np.ndarray], q: torch.Tensor, iterations: int, history: list | None = None,
            progress: Callable[[dict], None] | None = None, lost: np.ndarray | None = None):
        """Levenberg-Marquardt on each pose of Ts (local frame) in lockstep; with one pose and
        refined intrinsics (history given: a refine, not the repeats) also on q[:free]. The
        visibility, color fit and scale are re-fitted at every accepted pose; a step is accepted
        when the loss on the same points with the same fits decreases.

        With `lost` (B,) (the repeats) a pose that sees fewer than 10 points is lost and no longer
        moves; otherwise that raises InputError. Returns (poses, q, iterations (B,), why each
        stopped (B,), lost (B,))."""
        obj = self.objective
        free = obj.free if history is not None else 0
        tolerate = lost is not None
        at = obj.evaluate(level, Ts, q, None, True, free, not tolerate)
        B = len(Ts)
        lost = (np.zeros(B, bool) if lost is None else lost) | (at.visible < 10)
        lam = np.full(B, 1e-4)
        active = ~lost
        its = np.zeros(B, int)
        stops = np.array(["iteration cap"] * B, dtype=object)
        for it in range(1, iterations + 1):
            if not active.any():
                break
            its[active] = it
            deltas = np.zeros((B, at.H.shape[1]))
            for i in np.nonzero(active)[0]:
                deltas[i] = -np.linalg.solve(damped(at.H[i], lam[i]), at.g[i])
            T_new = [apply_update(T, d[:6]) if on else T for T, d, on in zip(Ts, deltas, active)]
            q_new = q
            if free:  # the camera corrections move with the pose (kept only when the step is)
                q_new = q.clone()
                q_new[:free] += torch.as_tensor(deltas[0, 6:], dtype=q.dtype, device=q.device)
            accepted = active & (obj.trial(level, T_new, q_new, at) <= at.loss)
            if accepted.any():
                Ts = [Tn if ok else T for T, Tn, ok in zip(Ts, T_new, accepted)]
                q = q_new
                at = obj.evaluate(level, Ts, q, at, True, free, not tolerate).where(accepted, at)
                gone = accepted & (at.visible < 10)
                lost |= gone
                active &= ~gone
            lam = np.where(accepted, np.maximum(lam / 4, 1e-7), np.where(active, lam * 8, lam))
            if history is not None:
                self._record(history, progress, level, it, at, deltas[0], bool(accepted[0]))
            done = accepted & np.array([self._converged(d, level) for d in deltas])
            ran_away = active & ~done & (lam > 1e6)  # no step lowers the loss: a minimum at this precision, or a broken one
            stops[done], stops[ran_away] = "converged", "damping ran away"
            active &= ~done & ~ran_away
        return Ts, q, its, stops, lost

    def _adam(self, level: int, T: np.ndarray, q: torch.Tensor, history: list, progress, iterations: int | None = None):
        """Adam on the 6 pose parameters (the paper's optimiser), separate step sizes for
        rotation and translation. Returns (pose, iterations, why it stopped)."""
        cfg = self.cfg
        lr = np.array([cfg.adam_lr_rotation] * 3 + [cfg.adam_lr_translation] * 3)
        m1, m2 = np.zeros(6), np.zeros(6)
        b1, b2, eps = 0.9, 0.999, 1e-12
        at = None
        it = 0
        for it in range(1, (iterations or cfg.adam_iterations) + 1):
            at = self.objective.evaluate(level, [T], q, at, True)
            g = at.g[0][:6] / max(int(at.visible[0]), 1)
            m1 = b1 * m1 + (1 - b1) * g
            m2 = b2 * m2 + (1 - b2) * g * g
            delta = -lr * (m1 / (1 - b1**it)) / (np.sqrt(m2 / (1 - b2**it)) + eps)
            T = apply_update(T, delta)
            self._record(history, progress, level, it, at, delta, True)
        return T, it, "converged" if self._converged(delta, level) else "iteration cap"

    @staticmethod
    def _record(history, progress, level, iteration, at, delta: np.ndarray, accepted: bool):
        figures = at.record(0)
        rec = {"level": level, "iteration": iteration, "loss": figures.pop("loss"),
               "rotation_update_deg": float(np.degrees(np.linalg.norm(delta[:3]))),
               "translation_update_m": float(np.linalg.norm(delta[3:6])), **figures, "accepted": accepted}
        history.append(rec)
        if progress is not None:
            progress(rec)

    # -- L-BFGS and the wide search ----------------------------------------------------------------
    def _lbfgs(self, level: int, Ts: list[np.ndarray], iterations: int) -> list[tuple | None]:
        """L-BFGS on one level from each pose of Ts (local frame) in lockstep, each on the points
        the objective sees at its start, in units of one level pixel of image motion: each round
        evaluates every unfinished start's next point in one call (`lockstep`). Returns per start
        (pose, loss, iterations, why it stopped), None for a start that lost the scan."""
        obj, q = self.objective, self._q(None)
        ats = []
        for T in Ts:
            try:
                ats.append(obj.evaluate(level, [T], q, jacobian=False))
            except InputError:
                ats.append(None)
        out: list[tuple | None] = [None] * len(Ts)
        for group in lockstep([int(at.visible[0]) if at is not None else None for at in ats]):
            xs = self._lbfgs_lockstep(level, [Ts[i] for i in group], [ats[i] for i in group], iterations)
            for i, x in zip(group, xs):
                if x is None:
                    continue
                T, n_iter = x
                try:
                    out[i] = (T, float(obj.trial(level, [T], q, ats[i])[0]), n_iter,
                              "iteration cap" if n_iter >= iterations else "converged")
                except InputError:
                    pass
        return out

    def _lbfgs_lockstep(self, level: int, Ts: list[np.ndarray], ats: list, iterations: int) -> list[tuple | None]:
        """`_lbfgs`'s minimisation from the poses Ts with their terms ats, all at once: per start
        (pose, iterations), None for one that lost the scan on the way."""
        obj = self.objective
        units = torch.stack([obj.units(level, T, at) for T, at in zip(Ts, ats)])  # (k, 6)
        r, m = math.radians(self.cfg.search_rotation_deg), self.cfg.search_translation_m
        cap = torch.minimum(units * STEP_CAP_PX, torch.tensor([r, r, r, m, m, m], dtype=units.dtype, device=units.device))
        batches: dict[tuple, object] = {}  # joined once per set of unfinished starts

        def update(x: torch.Tensor, which) -> torch.Tensor:  # smoothly at most `cap` per parameter
            return cap[which] * torch.tanh(units[which] * x / cap[which])

        def objective(X: np.ndarray, which: list[int]) -> tuple[np.ndarray, np.ndarray]:
            key = tuple(which)
            if key not in batches:
                batches.clear()
                batches[key] = obj.batch([ats[i] for i in which])
            x = torch.tensor(X, device=self.device)
            values, gradients = obj.value_and_gradient(level, [Ts[i] for i in which], update(x, which), batches[key])
            slope = units[which] * (1 - torch.tanh(units[which] * x / cap[which]) ** 2)
            return values, (gradients * slope).cpu().numpy()

        # a step moves the pose by at most units x step (tanh's slope is at most 1): the run stops
        # as LM's does, once that is below the stop thresholds (its last ~third moved < 0.1 mm on KITTI)
        sizes = units.cpu().numpy()
        found = lbfgs.minimize_many(objective, np.zeros((len(Ts), 6)), iterations,
                                    lambda k, step: self._converged(sizes[k] * step, level))
        return [None if f is None else
                (apply_update(Ts[k], update(torch.tensor(f[0][None], device=self.device), [k])[0].cpu().numpy()), f[1])
                for k, f in enumerate(found)]

    def _search(self, level: int, Ts: list[np.ndarray]) -> list[list[np.ndarray]]:
        """The coarsest level from each pose of Ts and from cfg.search_starts random starts around
        it, all in lockstep: per pose of Ts the cfg.search_keep results of lowest loss, lowest first
        (a start that loses the scan drops out)."""
        cfg = self.cfg
        starts = [[T] + random_starts(T, cfg.search_starts, math.radians(cfg.search_rotation_deg),
                                      cfg.search_translation_m, cfg.seed + 1) for T in Ts]
        runs = iter(self._lbfgs(level, [S for group in starts for S in group], cfg.search_iterations))
        kept = []
        for T, group in zip(Ts, starts):
            found = [(run[1], run[0]) for run in (next(runs) for _ in group) if run is not None]
            found.sort(key=lambda c: c[0])
            kept.append([T1 for _, T1 in found[: cfg.search_keep]] or [T])
        return kept

    def _descend(self, runs: list[tuple | None], top: int, bottom: int, iterations: int,
                 progress: Callable[[dict], None] | None = None) -> list[tuple | None]:
        """L-BFGS level by level from top down to bottom (inclusive), each run in lockstep from
        where it stands: a run is (pose, loss of its last level, history records, per-level
        iterations and stop reasons), or None (it lost the scan: it stays None). Returns the runs
        gone on, None for one that lost the scan."""
        runs = list(runs)
        for level in range(top, bottom - 1, -1):
            live = [i for i, run in enumerate(runs) if run is not None]
            for i, found in zip(live, self._lbfgs(level, [runs[i][0] for i in live], iterations)):
                if found is None:
                    runs[i] = None
                    continue
                T_before, _, history, level_info = runs[i]
                T, loss, n_it, stop = found
                level_info = level_info + [{"level": level, "iterations": n_it, "stop": stop}]
                step = T @ np.linalg.inv(T_before)
                rec = {"level": level, "iteration": n_it, "loss": loss, "rotation_update_deg": rotation_error_deg(T, T_before),
                       "translation_update_m": float(np.linalg.norm(step[:3, 3])), "accepted": True}
                if progress is not None:
                    progress(rec)
                runs[i] = (T, loss, history + [rec], level_info)
        return runs

    def _searched(self, Ts: list[np.ndarray], top: int, finest: int, iterations: int,
                  progress: Callable[[dict], None] | None) -> list[tuple | None]:
        """L-BFGS coarse to fine after the wide search (cfg.search_starts, for objectives with
        `wide_search`), from each pose of Ts in lockstep. The coarsest level's loss ranks the
        search's results poorly (at 1/16 scale a wrong basin can score lower): each of the best
        few goes on to level 1 and the lowest loss at its result there wins (docs/lidar-method.md,
        "Which search result goes on"). Returns per pose of Ts (pose, history records, per-level
        iterations and stop reasons), None where every run lost the scan."""
        search = self.objective.wide_search and self.cfg.search_starts > 0
        candidates = self._search(top, Ts) if search else [[T] for T in Ts]
        judge = max(finest, min(1, top))
        runs = iter(self._descend([(c, math.inf, [], []) for group in candidates for c in group], top, judge,
                                  iterations, progress))
        chosen = []
        for group in candidates:
            mine = [run for run in (next(runs) for _ in group) if run is not None]
            if len(mine) > 1:
                # a run's own loss is on the points it saw where the level began, which a candidate
                # that moved far no longer sees so: KITTI's joint draw 7 from 3 deg picked one 5.9 deg off
                mine = [(T1, self._loss_at(judge, T1), h, info) for T1, _, h, info in mine]
            chosen.append(min(mine, key=lambda r: r[1]) if mine else None)
        chosen = self._descend(chosen, judge - 1, finest, iterations, progress)
        return [None if run is None else (run[0], run[2], run[3]) for run in chosen]

    def _loss_at(self, level: int, T: np.ndarray) -> float:
        """The loss at T on a level's points seen there; inf where it sees too few."""
        try:
            return float(self.objective.evaluate(level, [T], self._q(None), jacobian=False).loss[0])
        except InputError:
            return math.inf
