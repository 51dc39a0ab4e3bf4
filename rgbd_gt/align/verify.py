"""A verdict on a refined pose, from evidence that does not trust the optimiser's own loss.

The loss and the inlier fraction of a wrong pose can equal those of a right one (a color
transform refitted at every pose fits noise too), so the verdict rests on other questions:
- how well the data fix the pose (uncertainty from the Gauss-Newton normal matrix);
- whether each pyramid level converged;
- whether nearby starts reproduce the result (repeatability);
- whether the result is a clear minimum of the objective (sharpness);
- whether the scan's structure lands on the photo's strongest gradients, better than chance
  (an image check independent of the color model: `qa.edges.structural_qa`);
- with held-out picked points, their reprojection error; with an init that states its own
  uncertainty, how far refine moved in units of it.
Distances between poses are also given as the photo pixels they move the visible scan points,
so that one threshold serves a room 3 m across and a street 50 m deep.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np

from rgbd_gt.align.aligner import Aligner, RefineResult
from rgbd_gt.align.config import VerifyConfig
from rgbd_gt.align.covariance import sandwich, wider
from rgbd_gt.camera import Camera, backproject, project, without_distortion
from rgbd_gt.pose import (apply_update, invert, random_starts, rotation_error_deg, transform_points, translation_error_m,
                          update_of, worst_sigmas)
from rgbd_gt.camera import Q_SIZE

VERDICTS = ("ok", "suspect", "failed")


@dataclass
class Verification:
    verdict: str  # ok | suspect | failed
    reasons: list[str]  # short sentences, empty when ok
    evidence: dict  # the numbers (docs/trust.md says what each means)
    seconds: float = 0.0
    # (6, 6) of the pose update, as `RefineResult.covariance`, that the pose file states: the
    # aligner's, widened where the frames of a joint solve (`frames_covariance`) and then the
    # tiles of its photos (`RefineResult.tiles`) as the samples say more
    covariance: np.ndarray | None = None


@dataclass
class _View:
    """The visible scan points at the result and the undistorted photo camera, for measuring
    pose differences in pixels."""

    points: np.ndarray  # (n, 3) scan frame
    camera: Camera

    def motion_px(self, Ta: np.ndarray, Tb: np.ndarray) -> float:
        """RMS image motion (photo pixels) of the points between poses Ta and Tb."""
        ua, za = project(self.camera, transform_points(Ta, self.points))
        ub, zb = project(self.camera, transform_points(Tb, self.points))
        ok = (za > 0) & (zb > 0)
        if not ok.any():
            return float("inf")
        return float(np.sqrt(np.mean(np.sum((ua[ok] - ub[ok]) ** 2, axis=1))))

    def motion_metric(self, T: np.ndarray) -> np.ndarray:
        """M (6, 6) with d^T M d = the mean squared image motion (photo px^2) of the points for a
        small update d = (rotation vector, translation) at pose T."""
        import torch

        from rgbd_gt.render.project import projection_jacobian

        du, dv = projection_jacobian(torch.as_tensor(transform_points(T, self.points)), self.camera.fx, self.camera.fy)
        return ((du.T @ du + dv.T @ dv) / du.shape[0]).numpy()

    def median_depth(self, T: np.ndarray) -> float:
        return float(np.median(transform_points(T, self.points)[:, 2]))

    def across_photo(self, T: np.ndarray, grid: int = 16) -> "_View":
        """A grid x grid of points over the whole photo at the points' median depth, seen from T:
        how far a pose difference moves the photo where the scan has no points (a scan that
        covers a corner of it fixes the pose there only)."""
        w, h = self.camera.size
        u, v = np.meshgrid(np.linspace(0, w - 1, grid), np.linspace(0, h - 1, grid))
        cam = backproject(self.camera, np.stack([u.ravel(), v.ravel()], 1), np.full(u.size, self.median_depth(T)))
        return _View(transform_points(np.linalg.inv(T), cam), self.camera)


def uncertainty(cov: np.ndarray | None, M: np.ndarray) -> dict:
    """The worst-determined direction's 1-sigma of a result's covariance cov (6, 6) (the aligner's,
    `RefineResult.covariance`: a lower bound, compared against thresholds measured on cases with
    known truth) for rotation (deg), camera position (mm) and image motion (px; M:
    `_View.motion_metric` at the result), and the condition number of the covariance with its
    parameters scaled to unit diagonal."""
    if cov is None or not np.isfinite(cov).all():
        return {"rotation_deg": float("inf"), "translation_mm": float("inf"), "image_px": float("inf"), "condition": float("inf")}
    s = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    eig = np.linalg.eigvalsh(cov / s[:, None] / s[None, :])
    L = np.linalg.cholesky(cov + 1e-30 * np.eye(6))
    sig_px = np.sqrt(max(np.linalg.eigvalsh(L.T @ M @ L)[-1], 0.0))
    return {**worst_sigmas(cov), "image_px": float(sig_px), "condition": float(eig[-1] / max(eig[0], 1e-300))}


def start_size(T_init: np.ndarray, T: np.ndarray, init_sigma: dict | None, view: _View, floor_px: float) -> tuple[float, float]:
    """(rotation rad, translation m) of the starts drawn around the init: the init's own stated
    uncertainty, else a quarter of the change refine made from it (a start as far from the init
    as the result is would be a harder problem than the one refine solved); at least what moves
    the image floor_px."""
    if init_sigma:
        rot, trans = np.radians(float(init_sigma["rotation_deg"])), float(init_sigma["translation_mm"]) / 1e3
    else:
        rot, trans = 0.25 * np.radians(rotation_error_deg(T, T_init)), 0.25 * translation_error_m(T, T_init)
    return max(rot, floor_px / view.camera.fx), max(trans, floor_px * view.median_depth(T) / view.camera.fx)


def _coarsest(result: RefineResult) -> int:
    """The coarsest pyramid level the result's refine ran."""
    return max(lv["level"] for lv in result.levels)


def repeatability(aligner: Aligner, result: RefineResult, T_init: np.ndarray, view: _View, cfg: VerifyConfig,
                  init_sigma: dict | None, seed: int) -> dict:
    """Refine again from the init and from cfg.repeats starts around it, all at once
    (`Aligner.refine_many`) on the coarse levels down to cfg.repeat_finest, with at most
    cfg.repeat_iterations a level (for nid with cfg.repeat_nid_whole, the whole way as refine runs:
    its wide search, all levels, its own iterations; the result itself stands for the init's run);
    the largest distance of the starts' results from the init's: in pixels of the visible points
    and of a grid over the whole photo (`_View.across_photo`), in mm and deg. (The runs may stop
    at a coarser level than the result, so they are compared among themselves, on the same levels.)"""
    finest = min(cfg.repeat_finest, _coarsest(result))
    rot, trans = start_size(T_init, result.T_cam_from_scan, init_sigma, view, cfg.start_floor_px)
    starts = [T_init] + random_starts(T_init, cfg.repeats, rot, trans, seed)
    if result.objective == "nid" and cfg.repeat_nid_whole:  # the init's run would be refine's again
        ends = [result.T_cam_from_scan] + aligner.refine_many(starts[1:], intrinsics=result.intrinsics)
    else:
        ends = aligner.refine_many(starts, finest, cfg.repeat_coarsest, cfg.repeat_iterations, result.intrinsics)
    reference, others = ends[0], ends[1:]
    lost = sum(T is None for T in ends)
    if reference is None or lost:  # a run that lost the scan certainly did not reproduce the result
        worst = {"px": float("inf"), "photo_px": float("inf"), "mm": float("inf"), "deg": float("inf")}
    else:
        photo = view.across_photo(reference)
        worst = {"px": max(view.motion_px(T, reference) for T in others),
                 "photo_px": max(photo.motion_px(T, reference) for T in others),
                 "mm": max(translation_error_m(T, reference) for T in others) * 1e3,
                 "deg": max(rotation_error_deg(T, reference) for T in others)}
    return {"spread_px": worst["px"], "spread_photo_px": worst["photo_px"], "spread_mm": worst["mm"], "spread_deg": worst["deg"],
            "starts": cfg.repeats,
            "lost_the_scan": lost, "start_rotation_deg": float(np.degrees(rot)), "start_translation_mm": trans * 1e3}


def frame_folds(aligner: Aligner, result: RefineResult, view: _View, cfg: VerifyConfig) -> dict:
    """Frames judged against each other: the frames of a joint solve (one rig over several
    frames) dealt into cfg.folds groups (frame k into group k mod folds), each refined apart from
    the result, from pyramid level cfg.fold_coarsest down to cfg.fold_finest; each group's distance
    from the result, in pixels of the visible points and of a grid over the whole photo, mm and
    deg, and the largest, and where it ended as an update of the result (`update`: rotation
    vector (rad), translation (m); `T_end = apply_update(T, update)`; `groups_covariance`).
    Where the frames agree, each group's own minimum lies at the result; where some frames'
    structure made it by chance, the others slide away. (Solved from the init instead, half a
    drive's frames often miss the basin all of them find: KITTI's from 3 deg.)"""
    from rgbd_gt.errors import InputError

    obj = aligner.objective
    T = result.T_cam_from_scan
    photo = view.across_photo(T)
    finest = min(cfg.fold_finest, _coarsest(result))
    groups = []
    for k in range(cfg.folds):
        keep = list(range(k, len(obj.frames), cfg.folds))
        try:  # no wide search: the question is where the group's own minimum lies
            fold = Aligner(obj.of_frames(keep, replace(obj.cfg, search_starts=0)))
            end = fold.refine(T, finest=finest, coarsest=max(finest, cfg.fold_coarsest)).T_cam_from_scan
        except InputError:
            end = None
        if end is None:  # a group that lost the scan did not find the result
            groups.append({"frames": keep, "px": float("inf"), "photo_px": float("inf"), "mm": float("inf"), "deg": float("inf")})
            continue
        groups.append({"frames": keep, "px": view.motion_px(end, T), "photo_px": photo.motion_px(end, T),
                       "mm": translation_error_m(end, T) * 1e3, "deg": rotation_error_deg(end, T),
                       "update": update_of(end @ invert(T)).tolist()})
    worst = {key: max(g[key] for g in groups) for key in ("px", "photo_px", "mm", "deg")}
    return {"folds": cfg.folds, "spread_px": worst["px"], "spread_photo_px": worst["photo_px"],
            "spread_mm": worst["mm"], "spread_deg": worst["deg"], "groups": groups}


def groups_covariance(groups: list[dict]) -> np.ndarray | None:
    """(6, 6) the covariance that the groups of frames refined apart (`frame_folds`) show: each of
    K groups is an estimate of the pose from 1/K of the frames, so their updates' sample
    covariance is about K times the whole's. It sees what the frames' quadratics cannot: where
    a group's own minimum lies beyond their reach (KITTI's two halves 1-2 cm apart along the
    optical axis, docs/lidar-method.md). Rank K - 1 at most: it widens only the directions the
    groups disagree in. None for fewer than 2 groups that ended."""
    ends = np.array([g["update"] for g in groups if g.get("update") is not None])
    if len(ends) < 2:
        return None
    return np.cov(ends, rowvar=False) / len(ends)


def frames_covariance(result: RefineResult, groups: list[dict] = ()) -> np.ndarray | None:
    """A joint solve's covariance with its frames as the independent samples: the sandwich of the
    frames' shares (`RefineResult.frame_quadratics`), wherever it is wider than the aligner's
    (`align.covariance`): on KITTI's and Waymo's drives 3-13 times wider in the worst direction
    (docs/lidar-method.md); then wider still where the groups refined apart disagree more
    (`groups_covariance` of `frame_folds`' groups). None for a single frame."""
    if result.frame_quadratics is None:
        return None
    g, H, units = result.frame_quadratics
    framed = wider(result.covariance, sandwich(g, H.sum(0), units))
    apart = groups_covariance(groups)
    return framed if apart is None else wider(framed, apart)


def leave_one_out_steps(g: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Frames judged against each other, linearised: the objective is a sum over frames, each
    frame's share a quadratic around the result (gradients g (F, k), Hessians H (F, k, k)).
    Returns, relative to the minimum of the sum, (F, k) each: where the minimum lies with frame
    f left out, and where frame f alone has its minimum; rows of nan where what is left (or the
    frame alone) has no minimum (not positive definite)."""
    Hs, gs = H.sum(0), g.sum(0)
    if np.linalg.eigvalsh(Hs)[0] <= 0:
        return np.full_like(g, np.nan), np.full_like(g, np.nan)
    at = -np.linalg.solve(Hs, gs)

    def minima(Hf: np.ndarray, gf: np.ndarray) -> np.ndarray:
        ok = np.linalg.eigvalsh(Hf)[:, 0] > 0
        out = np.full_like(gf, np.nan)
        if ok.any():
            out[ok] = -np.linalg.solve(Hf[ok], gf[ok][:, :, None])[:, :, 0] - at
        return out

    return minima(Hs - H, gs - g), minima(H, g)


def leave_one_frame_out(result: RefineResult, view: _View) -> dict | None:
    """Per frame of a joint solve: how far the result moves when the frame is left out, and how
    far the frame's own minimum lies from it, both from the frames' shares of the objective as
    quadratics at the result (`RefineResult.frame_quadratics`, which its covariance made;
    `leave_one_out_steps`): no solve per frame. In pixels of the visible points (the larger of
    theirs and a grid across the photo; inf where there is no minimum). A frame whose own structure made the result
    moves it when left out; frames that each agree put their own minima near it (single sparse
    frames seldom have a clear one: how many do is part of the evidence). None for a single frame."""
    if result.frame_quadratics is None or len(result.frame_quadratics[0]) < 2:
        return None
    g, H, units = result.frame_quadratics
    T = result.T_cam_from_scan
    photo = view.across_photo(T)

    def px(step: np.ndarray) -> float:
        if not np.isfinite(step).all():
            return float("inf")
        moved = apply_update(T, step * units)
        return max(view.motion_px(moved, T), photo.motion_px(moved, T))

    left_out, own = leave_one_out_steps(g, H)
    left_px = [px(x) for x in left_out]
    own_px = [px(x) for x in own]
    finite = [p for p in own_px if np.isfinite(p)]
    return {"left_out_px": left_px, "worst_left_out_px": max(left_px), "worst_frame": int(np.argmax(left_px)),
            "own_minimum_px": own_px, "frames_with_minimum": len(finite),
            "median_own_minimum_px": float(np.median(finite)) if finite else float("inf")}


def sharpness(aligner: Aligner, T: np.ndarray, M: np.ndarray, step_px: float, level: int,
              intrinsics: np.ndarray | None = None) -> dict:
    """The robust loss at the result against the same at the 12 poses that move the image by
    +-step_px (RMS, photo pixels) along each pose parameter, on one pyramid level: the relative
    rise (L_k - L_0) / L_0, smallest and median. A right pose is a clear minimum: every rise is
    positive. (A coarse level sees a 1.5 px motion as well as level 0 does, at a fraction of the cost.)"""
    per_unit = np.sqrt(np.diag(M))  # (6,) RMS px per unit of each parameter
    steps = np.diag(step_px / np.maximum(per_unit, 1e-12))
    loss0, losses = aligner.loss_profile(T, np.concatenate([steps, -steps]), level, intrinsics)
    rise = (losses - loss0) / max(loss0, 1e-12)
    return {"min_rise": float(rise.min()), "median_rise": float(np.median(rise)), "step_px": step_px}


def camera_check(aligner: Aligner, result: RefineResult, view: _View, cfg: VerifyConfig,
                 shared: bool = False) -> dict | None:
    """Whether the camera agrees with the photo: the result refined again from its pose with the
    focal length free as well (`Photometric.freeing`), from the camera file's (or, shared: from
    the camera the result's intrinsics make, solved with other photos). A wrong focal length is
    absorbed by the pose (the camera moves along its axis, the scan still lines up), so the pose
    alone cannot tell; freed, the focal moves back toward the photo's. None where the focal was
    refined on this photo alone already or the objective has no camera corrections (NID)."""
    obj = aligner.objective
    if (result.intrinsics is not None and not shared) or not hasattr(obj, "freeing"):
        return None
    # the finest level: on level 1 (the photo's own pixels) right cameras moved up to 0.45%
    # (docs/trust-method.md); its sigma comes with the refine's final evaluation there
    start = np.zeros(Q_SIZE) if result.intrinsics is None else np.asarray(result.intrinsics, np.float64)
    freed = Aligner(obj.freeing(1)).refine(result.T_cam_from_scan, coarsest=0, iterations=cfg.camera_iterations,
                                           intrinsics=start)
    change, sigma = float((1 + freed.intrinsics[0]) / (1 + start[0]) - 1), float(freed.intrinsics_sigma[0])
    return {"focal_change": change, "focal_sigma": sigma, "focal_sigmas": abs(change) / max(sigma, 1e-12),
            "pose_moved_px": view.motion_px(freed.T_cam_from_scan, result.T_cam_from_scan)}


def check_pairs(pairs: tuple[np.ndarray, np.ndarray], camera: Camera, T_init: np.ndarray, T: np.ndarray) -> dict:
    """RMS reprojection error (px) of held-out picked pairs (img (n, 2), scan points (n, 3)) at the
    init and at the result."""
    from rgbd_gt.init.pnp import reprojection_rms

    img, obj = pairs
    return {"pairs": len(img), "rms_init_px": reprojection_rms(T_init, obj, img, camera),
            "rms_px": reprojection_rms(T, obj, img, camera)}


def _ratio_reasons(count: int, ratio: float, failed_below: float, ok_from: float, cfg: VerifyConfig, what: str,
                   fit: str, failed: list[str], suspect: list[str]) -> None:
    """An image check's reasons, appended to failed and suspect: too few `what` to score (fewer
    than cfg.min_edge_pixels), a ratio against chance below failed_below (or not a number), or
    below ok_from. fit: what the ratio says fits, as the reasons name it."""
    if count < cfg.min_edge_pixels:
        suspect.append(f"too few {what} to check against the photo ({count})")
    elif not ratio >= failed_below:
        failed.append(f"{fit} no better than chance (ratio {ratio:.2f})")
    elif ratio < ok_from:
        suspect.append(f"{fit} weakly (ratio {ratio:.2f})")


def decide(ev: dict, cfg: VerifyConfig) -> tuple[str, list[str]]:
    """The verdict and its reasons from the evidence, by the thresholds in cfg (docs/trust.md)."""
    failed, suspect = [], []
    edges, rings = ev.get("edges"), ev.get("ring_edges")
    # a sweep: its rings' edges, wherever it has enough of them; its points drawn as splats make
    # weak structural edges even where dense enough to score (at the truth of a synthetic sweep
    # in a room 1.11-1.15, against 1.7-2.2 for its ring edges: docs/lidar-method.md)
    if rings is not None and (rings["ring_edges"] >= cfg.min_edge_pixels or edges is None
                              or not edges["edge_check_usable"]):
        _ratio_reasons(rings["ring_edges"], rings["ratio"], cfg.ring_edge_ratio_failed, cfg.ring_edge_ratio_ok, cfg,
                       "depth edges along the sweep's rings in view", "the sweep's depth edges fit the photo's edges",
                       failed, suspect)
    elif edges is not None:
        if not edges["edge_check_usable"]:
            suspect.append(f"the scan is too sparse to check against the photo's edges (splats of {edges['splat_radius_px']} px)")
        else:
            _ratio_reasons(edges["structural_edge_pixels"], edges["edge_ratio"], cfg.edge_ratio_failed, cfg.edge_ratio_ok,
                           cfg, "structural edges", "the scan's edges fit the photo", failed, suspect)
    rep = ev.get("repeatability")
    if rep is not None:
        if rep["spread_px"] > (cfg.spread_failed_px_nid if ev.get("objective") == "nid" else cfg.spread_failed_px):
            failed.append(f"nearby starts end elsewhere ({rep['spread_px']:.1f} px, {rep['spread_mm']:.0f} mm apart)")
        elif rep["spread_px"] > cfg.spread_ok_px:
            suspect.append(f"nearby starts disagree by {rep['spread_px']:.2f} px")
        elif rep.get("spread_photo_px", 0.0) > cfg.spread_ok_px:
            suspect.append(f"nearby starts agree on the scan's points but not across the photo "
                           f"({rep['spread_photo_px']:.2f} px): the scan fixes the pose where it is only")
    folds = ev.get("frames")
    fold_px = None if folds is None else max(folds["spread_px"], folds["spread_photo_px"])
    if folds is not None:
        if folds["spread_px"] > cfg.spread_failed_px_nid:
            failed.append(f"the frames disagree: refined apart in {folds['folds']} groups, they end "
                          f"{folds['spread_px']:.1f} px ({folds['spread_mm']:.0f} mm, {folds['spread_deg']:.2f} deg) from the result")
        elif fold_px > cfg.fold_ok_px:
            suspect.append(f"the frames agree only roughly: refined apart in {folds['folds']} groups, they end "
                           f"{fold_px:.1f} px from the result")
        loo = folds.get("leave_one_out")
        # inf: the other frames alone leave a direction open (Waymo's frames, one of which fixes it): no say
        if loo is not None and cfg.fold_ok_px < loo["worst_left_out_px"] < float("inf"):
            suspect.append(f"the result hinges on frame {loo['worst_frame'] + 1}: left out, the result moves "
                           f"{loo['worst_left_out_px']:.1f} px")
    sh = ev.get("sharpness")
    if sh is not None:
        if sh["median_rise"] < cfg.sharpness_failed:
            failed.append(f"the objective has no clear minimum here (median rise {sh['median_rise']:.2g} at {sh['step_px']} px)")
        elif sh["min_rise"] < cfg.sharpness_ok:
            suspect.append(f"the objective is flat in some direction (smallest rise {sh['min_rise']:.2g} at {sh['step_px']} px)")
    unc = ev["uncertainty"]
    if not unc["image_px"] <= cfg.sigma_failed_px and fold_px is not None and fold_px <= cfg.fold_ok_px:
        # a drive's frames that agree make the result; the objective is flat along one direction
        # (on Waymo: the optical axis with a turn about the vertical), within the noise of its Hessian
        suspect.append(f"the data fix the pose weakly along one direction (1-sigma {unc['image_px']:.2f} px), "
                       "though the frames refined apart agree")
    elif not unc["image_px"] <= cfg.sigma_failed_px:
        failed.append(f"the data do not fix the pose (1-sigma {unc['image_px']:.2f} px)")
    elif unc["image_px"] > (cfg.sigma_ok_px_nid if ev.get("objective") == "nid" else cfg.sigma_ok_px):
        suspect.append(f"the pose is weakly determined (1-sigma {unc['image_px']:.2f} px, {unc['translation_mm']:.1f} mm)")
    finest = ev["convergence"]["levels"][-1]
    if finest["stop"] != "converged":
        suspect.append(f"the finest level stopped on its {finest['stop']}")
    chk = ev.get("check")
    if chk is not None:
        if chk["rms_px"] > cfg.check_failed_px:
            keep = "; keep the init" if chk["rms_init_px"] <= cfg.check_failed_px else ""
            failed.append(f"the check points are {chk['rms_px']:.1f} px off ({chk['rms_init_px']:.1f} px at the init{keep})")
        elif chk["rms_px"] > max(cfg.check_ok_px, chk["rms_init_px"]):
            suspect.append(f"the check points are {chk['rms_px']:.1f} px off ({chk['rms_init_px']:.1f} px at the init)")
    cam = ev.get("camera")
    if cam is not None and cam["focal_sigmas"] > cfg.camera_sigmas and abs(cam["focal_change"]) > cfg.camera_min_change:
        suspect.append(f"the camera file disagrees with the photo: freed, the focal length moves "
                       f"{cam['focal_change']:+.2%} ({cam['focal_sigmas']:.0f} sigma)")
    ch = ev.get("change_in_init_sigmas")
    if ch is not None and ch > cfg.change_max_sigmas:
        suspect.append(f"refine moved {ch:.1f} times the init's own uncertainty")
    if failed:
        return "failed", failed + suspect
    return ("suspect", suspect) if suspect else ("ok", [])


def frame_verdict(verdict: str, reasons: list[str], rings: dict | None, k: int, cfg: VerifyConfig) -> tuple[str, list[str]]:
    """Frame k's verdict in a joint solve (one rig over several frames): the solve's verdict and
    reasons, made worse where the frame's own depth edges fit its photo poorly at the result
    (rings: the evidence's `ring_edges`, whose `frames` `Nid.ring_edge_check` gives): failed below
    cfg.ring_edge_ratio_failed, suspect below cfg.ring_edge_frame_ok. The joint NID outweighs one
    frame whose sweep and photo disagree (a time offset, a camera moved between frames), so the
    result can be right for the rig and wrong for that frame. A frame with fewer than
    cfg.min_edge_pixels ring edges in view has no say: the rig's pose is checked on the others."""
    frames = (rings or {}).get("frames") or []
    frame = frames[k] if k < len(frames) else None
    if frame is None or frame["ring_edges"] < cfg.min_edge_pixels:
        return verdict, list(reasons)
    ratio, own = frame["ratio"], "this frame's depth edges fit its photo"
    if not ratio >= cfg.ring_edge_ratio_failed:
        return "failed", [f"{own} no better than chance at the rig's pose (ratio {ratio:.2f}): its sweep and photo "
                          "disagree (taken at other times? the camera moved?)"] + list(reasons)
    if ratio < cfg.ring_edge_frame_ok:
        return ("failed" if verdict == "failed" else "suspect"), list(reasons) + [f"{own} weakly at the rig's pose (ratio {ratio:.2f})"]
    return verdict, list(reasons)


def verify(aligner: Aligner, result: RefineResult, T_init: np.ndarray, camera: Camera, photo: np.ndarray,
           renders, cfg: VerifyConfig, seed: int = 0, init_meta: dict | None = None,
           check: tuple[np.ndarray, np.ndarray] | None = None, shared_camera: bool = False) -> Verification:
    """The evidence on `result` (refined from T_init by `aligner`) and the verdict.

    camera, photo: the photo's own (distorted) camera and image (H, W, 3) uint8; renders: the
    scan's `render.renders.Renders` (with its colors), for the structural image check; init_meta: the
    init pose file's other keys (its `uncertainty`, when it states one); check: held-out pairs
    (img (n, 2) px, scan points (n, 3)); shared_camera: the result's intrinsics were solved with
    other photos (`refine --bundle`), and the camera check asks whether this photo agrees with them.
    """
    from rgbd_gt.qa.edges import structural_qa, working_view

    start = time.perf_counter()
    seconds: dict[str, float] = {}
    covariance = result.covariance

    def timed(name, fn, *args):
        t = time.perf_counter()
        out = fn(*args)
        seconds[name] = round(time.perf_counter() - t, 3)
        return out

    T = result.T_cam_from_scan
    view = _View(aligner.visible_scan_points(T, result.intrinsics), without_distortion(camera))
    M = view.motion_metric(T)
    ev: dict = {"objective": result.objective, "uncertainty": timed("uncertainty", uncertainty, result.covariance, M)}
    ev["convergence"] = {"levels": result.levels,
                         "damping_ran_away": any(lv["stop"] == "damping ran away" for lv in result.levels)}
    init_sigma = (init_meta or {}).get("uncertainty")
    frames = len(getattr(aligner.objective, "frames", ()))
    if cfg.repeats > 0 and cfg.folds > 1 and frames >= cfg.folds:  # the frames' own agreement: no repeats needed on top
        ev["frames"] = timed("frames", frame_folds, aligner, result, view, cfg)
        loo = timed("leave_one_frame_out", leave_one_frame_out, result, view)
        if loo is not None:
            ev["frames"]["leave_one_out"] = loo
        framed = frames_covariance(result, ev["frames"]["groups"])
        if framed is not None:
            covariance = framed
            ev["frames"]["uncertainty"] = uncertainty(framed, M)
    elif cfg.repeats > 0:
        ev["repeatability"] = timed("repeatability", repeatability, aligner, result, T_init, view, cfg, init_sigma, seed)
    if result.tiles is not None:  # the photos' tiles as the samples (`RefineResult.tiles`), where they say more than the above
        tiles = wider(covariance, result.tiles[0])
        if tiles is not None:
            covariance = tiles
            ev["tiles"] = {"count": result.tiles[1], "uncertainty": uncertainty(tiles, M)}
    if result.objective != "nid":  # NID's values rise by 1e-5..1e-3: its uncertainty, from their Hessian, stands for it
        ev["sharpness"] = timed("sharpness", sharpness, aligner, T, M, cfg.sharpness_step_px, cfg.sharpness_level,
                                 result.intrinsics)

    if cfg.camera_check:
        if hasattr(aligner.objective, "freeing"):
            camera_ev = timed("camera", camera_check, aligner, result, view, cfg, shared_camera)
            if camera_ev is not None:
                ev["camera"] = camera_ev
        else:
            # NID cannot free the focal, and a file about 1 % off passes as `ok`: say how far that
            # moves the pose along the axis, about the focal's error times the median depth of all
            # frames' points (KITTI, Waymo: docs/trust-method.md, "What the verdict does not cover")
            ev["camera_unchecked"] = {"axis_mm_per_focal_percent": timed("camera", lambda: 10.0 * aligner.median_depth(T))}

    def edge_check():
        drawn = working_view(renders, photo, camera, T, cfg.edge_max_side, cfg.edge_shift_px)
        return structural_qa(drawn, cfg.edge_shift_px)[1]

    score = timed("edges", edge_check)
    ev["edges"] = score.as_dict()
    rings = timed("ring_edges", aligner.ring_edge_check, T, cfg.edge_shift_px)
    if rings is not None:
        ev["ring_edges"] = rings
    if check is not None:
        ev["check"] = check_pairs(check, camera, T_init, T)
    moved_mm, moved_deg = translation_error_m(T, T_init) * 1e3, rotation_error_deg(T, T_init)
    ev["change_from_init"] = {"translation_mm": moved_mm, "rotation_deg": moved_deg, "image_px": view.motion_px(T, T_init)}
    if init_sigma:
        ev["change_in_init_sigmas"] = max(moved_mm / max(float(init_sigma["translation_mm"]), 1e-9),
                                          moved_deg / max(float(init_sigma["rotation_deg"]), 1e-9))
    ev["seconds"] = seconds
    verdict, reasons = decide(ev, cfg)
    return Verification(verdict, reasons, ev, time.perf_counter() - start, covariance)


def bundle_reasons(ev: dict, cfg: VerifyConfig) -> list[str]:
    """The reasons a photo of a bundle is suspect from its cross-photo evidence (`align.bundle`):
    left out, the other photos' shared camera and rig move its pose by more than
    cfg.bundle_sigmas of its sigma; freed from its rig it moves by more than that; its residual
    scale exceeds cfg.bundle_residual_ratio times the other photos'. Freed from its rig, a photo
    must also move cfg.bundle_freed_ratio times the median photo's: one shot off the rig pulls the
    rig, and every shot then moves some (docs/bundle.md)."""
    reasons = []
    loo = ev.get("leave_one_out_sigmas")
    if loo is not None and loo > cfg.bundle_sigmas:
        reasons.append(f"the other photos disagree with this one: their shared camera (and rig) moves its pose by "
                       f"{loo:.1f} sigma (its camera or zoom differs from theirs?)")
    freed = ev.get("freed_from_rig_sigmas")
    if freed is not None and freed > cfg.bundle_sigmas and ev.get("freed_vs_others", 0.0) > cfg.bundle_freed_ratio:
        reasons.append(f"the shot disagrees with the rig: freed from it, this photo's pose moves {freed:.1f} sigma, "
                       f"{ev['freed_vs_others']:.1f}x the median photo's")
    ratio = ev.get("residual_vs_others", 1.0)
    if ratio > cfg.bundle_residual_ratio:
        reasons.append(f"its residuals are {ratio:.1f}x the other photos' (a photo of another scene or time?)")
    return reasons
