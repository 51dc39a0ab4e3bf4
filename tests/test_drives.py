"""LiDAR drives with the data sets' own calibrations (KITTI, Waymo: ../shared/data/lidar_camera):
the sweeps' depth steps along their rings, the ring-edge term of the NID objective and its
gradient, the ring-edge image check against chance, and the verdict of a joint solve over
several frames judged against each other; a synthetic sweep with exact truth (`rgbd_gt.synth.drive`)."""

import numpy as np
import pytest
import torch

from conftest import DATA, run_cli
from rgbd_gt.align.config import RefineConfig
from rgbd_gt.pose import apply_update, rotation_error_deg, translated, worst_sigmas
from rgbd_gt.render.rings import ring_steps

DRIVES = DATA / "lidar_camera"


def _drive(name: str, frames: list[int]):
    """Scenes (`benchmarks.lidar.Scene`) of frames of a drive folder (pcd/, img/, gt.json)."""
    from benchmarks.lidar import drive_scenes

    folder = DRIVES / name
    if not (folder / "gt.json").exists():
        pytest.skip(f"needs {folder} (../shared/data, see its README)")
    return drive_scenes(folder, frames)


def test_ring_steps_mark_the_nearer_side_of_a_depth_jump():
    """A ring at 10 m with a pole at 6 m across 10 of its returns: the pole's two outer returns
    are nearer than their neighbours by the difference of their ranges, nothing else steps; shuffled, the points are no sweep
    in ring order."""
    az = np.radians(np.arange(0, 360, 0.2))
    r = np.full(az.size, 10.0)
    r[100:110] = 6.0
    xyz = np.stack([r * np.cos(az), r * np.sin(az), np.full(az.size, -1.0)], 1)
    steps = ring_steps(xyz)
    assert steps is not None and steps.dtype == np.float32
    np.testing.assert_allclose(steps[[100, 109]], np.hypot(10, 1) - np.hypot(6, 1), atol=1e-5)  # ranges, not distances in the plane
    assert np.count_nonzero(steps > 1e-6) == 2
    assert ring_steps(xyz[np.random.default_rng(0).permutation(az.size)]) is None


def test_kitti_and_waymo_sweeps_get_ring_steps_when_prepared():
    """Both files keep the sensor's order: about a tenth of their returns step by 10 cm or more."""
    for name, frame in (("kitti_00", 0), ("waymo", 0)):
        (scene,) = _drive(name, [frame])
        steps = np.asarray(scene.prepared.arrays["edge"])
        assert steps.shape == (len(scene.scan),)
        share = float(np.mean(steps >= 0.1))
        assert 0.03 < share < 0.3, (name, share)


def test_edge_term_gradient_is_autograds():
    """The closed-form gradient of NID plus the ring-edge term equals autograd's on a real KITTI
    frame, 0.6 deg and 8 cm from the reference."""
    from rgbd_gt.align.refine import make_aligner
    from benchmarks.lidar import refine_inputs

    (s,) = _drive("kitti_00", [0])
    al = make_aligner(refine_inputs(s, s.T_ref), RefineConfig(objective="nid", edge_weight=1.0), "cpu")
    obj = al.objective
    T_local = translated(s.T_ref, obj.centre)
    obj.prepare(T_local)
    parts = obj._parts(1, T_local)
    assert parts.edge_points is not None and int((parts.edge_strength[0] > 0).sum()) > 300
    weights = torch.ones(1, dtype=torch.float64)
    d = torch.as_tensor(np.r_[np.radians([0.3, -0.4, 0.3]), 0.05, -0.03, 0.05], dtype=torch.float64).requires_grad_(True)
    at = obj._evaluate(parts, [T_local], d[None], weights)
    assert float(at.edges.sum().detach()) > 0
    at.objective(weights).sum().backward()
    closed, auto = at.gradient[0].detach().numpy(), d.grad.numpy()
    np.testing.assert_allclose(closed, auto, rtol=1e-5, atol=1e-6 * np.abs(auto).max())  # autograd: float32 geometry


def test_tiles_shares_add_up_to_the_gradient():
    """Two KITTI frames as one rig at the reference on the finest level, ring edges and all: the
    points' and ring edges' shares of the objective's gradient, summed per tile of each frame's
    photo (`Nid.tile_scores`), add up to its closed-form gradient; the Hessian beside them is the
    frames' quadratics' sum per radian and metre."""
    from benchmarks.lidar import refine_inputs
    from rgbd_gt.align.refine import make_aligner

    scenes = _drive("kitti_00", [0, 10])
    inputs = [refine_inputs(s, s.T_ref) for s in scenes]
    obj = make_aligner(inputs[0], RefineConfig(objective="nid"), "cpu", inputs[1:]).objective
    T_local = translated(scenes[0].T_ref, obj.centre)
    obj.prepare(T_local)
    terms = obj.evaluate(0, [T_local])
    assert terms.parts.edge_points is not None
    obj.covariance(0, T_local, None, terms)
    g, H = terms.tiles
    _, gradient = obj.value_and_gradient(0, [T_local], torch.zeros(1, 6, dtype=torch.float64), obj.batch([terms]))
    assert 16 < len(g) <= 2 * 64
    np.testing.assert_allclose(g.sum(0), gradient[0].numpy(), rtol=1e-9, atol=1e-9 * np.abs(g).max())
    _, Hf, units = terms.quadratics
    np.testing.assert_allclose(H, Hf.sum(0) / np.outer(units, units))


def test_ring_edge_check_tells_the_reference_from_a_wrong_pose():
    """Over 4 KITTI frames at the reference the sweeps' depth edges land on the photos' edges
    well above chance; 1 deg off they do not."""
    from rgbd_gt.align.refine import make_aligner
    from benchmarks.lidar import refine_inputs

    scenes = _drive("kitti_00", [0, 5, 10, 15])
    inputs = [refine_inputs(s, s.T_ref) for s in scenes]
    al = make_aligner(inputs[0], RefineConfig(objective="nid"), "cpu", inputs[1:])
    al.prepare(scenes[0].T_ref)
    right = al.ring_edge_check(scenes[0].T_ref, 6)
    wrong = al.ring_edge_check(apply_update(scenes[0].T_ref, np.r_[np.radians([0.0, 1.0, 0.0]), 0, 0, 0]), 6)
    assert right["ring_edges"] > 2000
    cfg = RefineConfig().verify
    assert right["ratio"] >= cfg.ring_edge_ratio_ok, right
    assert wrong["ratio"] < right["ratio"] - 0.1, (right, wrong)


def test_a_frame_whose_photo_is_not_of_its_sweep_fails_on_its_own_edges():
    """Four KITTI frames at the reference: each frame's own depth edges fit its photo (the check's
    `frames`), so each frame keeps the rig's verdict. One frame's sweep turned 0.5 deg about the
    camera's vertical (as if its photo were taken elsewhere): its own ratio falls below
    ring_edge_ratio_failed and it alone is failed; the other frames' ratios stay as they were. A
    frame with too few edges in view has no say, and a failed rig stays failed."""
    from dataclasses import replace

    from benchmarks.lidar import refine_inputs
    from rgbd_gt.align.refine import make_aligner
    from rgbd_gt.align.verify import frame_verdict

    scenes = _drive("kitti_00", [0, 5, 10, 15])
    T = scenes[0].T_ref
    cfg = RefineConfig().verify
    inputs = [refine_inputs(s, T) for s in scenes]

    def check(inputs):
        al = make_aligner(inputs[0], RefineConfig(objective="nid"), "cpu", inputs[1:])
        al.prepare(T)
        return al.ring_edge_check(T, cfg.edge_shift_px)

    right = check(inputs)
    assert [f["ratio"] >= cfg.ring_edge_frame_ok for f in right["frames"]] == [True] * 4, right["frames"]
    assert sum(f["ring_edges"] for f in right["frames"]) == right["ring_edges"]
    assert [frame_verdict("ok", [], right, k, cfg) for k in range(4)] == [("ok", [])] * 4
    M = np.linalg.inv(T) @ apply_update(T, np.r_[0.0, np.radians(0.5), 0, 0, 0, 0])  # the turn, in the sweep's frame
    bad = [*inputs[:2], replace(inputs[2], points=inputs[2].points @ M[:3, :3].T + M[:3, 3]), inputs[3]]
    wrong = check(bad)
    assert wrong["frames"][2]["ratio"] < cfg.ring_edge_ratio_failed, wrong["frames"]
    for k in (0, 1, 3):  # the same but for round-off: the points' centre, which the frames share, moved
        assert wrong["frames"][k]["ring_edges"] == right["frames"][k]["ring_edges"]
        assert wrong["frames"][k]["ratio"] == pytest.approx(right["frames"][k]["ratio"], rel=1e-5)
    verdict, reasons = frame_verdict("ok", [], wrong, 2, cfg)
    assert verdict == "failed" and "no better than chance at the rig's pose" in reasons[0]
    assert [frame_verdict("ok", [], wrong, k, cfg)[0] for k in (0, 1, 3)] == ["ok"] * 3
    # between the two bars: suspect; too few edges: no say; a failed rig stays failed with its reasons
    weak = {"frames": [{"ring_edges": 1000, "ratio": (cfg.ring_edge_ratio_failed + cfg.ring_edge_frame_ok) / 2}]}
    assert frame_verdict("ok", [], weak, 0, cfg)[0] == "suspect"
    assert frame_verdict("failed", ["x"], weak, 0, cfg) == ("failed", ["x", frame_verdict("ok", [], weak, 0, cfg)[1][0]])
    few = {"frames": [{"ring_edges": cfg.min_edge_pixels - 1, "ratio": 0.9}]}
    assert frame_verdict("ok", [], few, 0, cfg) == ("ok", [])
    assert frame_verdict("suspect", ["y"], None, 0, cfg) == ("suspect", ["y"])


def test_qa_scores_a_sweeps_ring_edges_as_the_verdict_does():
    """qa-edges' check of a sweep (`qa.edges.ring_edge_check`, on the photo as shipped) is the
    verdict's (`Nid.ring_edge_check`, on the aligner's finest level) for one KITTI frame: the
    same depth steps scored, the same ratio but for round-off; turned 1 deg about the photo's
    vertical, the ratio falls to chance."""
    from benchmarks.lidar import refine_inputs
    from rgbd_gt.align.refine import make_aligner
    from rgbd_gt.qa.edges import ring_edge_check

    (s,) = _drive("kitti_00", [7])
    inputs = refine_inputs(s, s.T_ref)
    al = make_aligner(inputs, RefineConfig(objective="nid"), "cpu")
    al.prepare(s.T_ref)
    verdicts = al.ring_edge_check(s.T_ref, 6)
    turn = apply_update(s.T_ref, np.r_[0.0, np.radians(1.0), 0, 0, 0, 0])
    mine, turned = ring_edge_check(inputs.scan, s.photo, s.camera, [s.T_ref, turn])
    assert "frames" not in verdicts and mine["ring_edges"] == verdicts["ring_edges"] > 500
    assert mine["ring_edge_ratio"] == pytest.approx(verdicts["ratio"], rel=1e-4)
    assert mine["ring_edge_ratio"] > RefineConfig().verify.ring_edge_frame_ok
    assert turned["ring_edge_ratio"] < RefineConfig().verify.ring_edge_ratio_failed


def test_a_sweep_is_judged_by_its_ring_edges_and_its_frames_agreement():
    """decide(): where the rendered sweep is too sparse for the structural edge check, the ring
    edges stand in for it; the frames refined apart in groups fail a result they end far from and
    leave one they end a few pixels from suspect; agreeing frames and clear ring edges are `ok`;
    agreeing frames make a result with no finite 1-sigma suspect, not failed."""
    from rgbd_gt.align.config import VerifyConfig
    from rgbd_gt.align.verify import decide

    cfg = VerifyConfig()
    ev = {"objective": "nid", "uncertainty": {"image_px": 0.3, "translation_mm": 4.0},
          "convergence": {"levels": [{"stop": "converged"}]},
          "edges": {"edge_check_usable": False, "splat_radius_px": 30},
          "ring_edges": {"ring_edges": 5000, "ratio": 1.25},
          "frames": {"folds": 2, "spread_px": 0.7, "spread_photo_px": 0.6, "spread_mm": 8.0, "spread_deg": 0.03}}
    assert decide(ev, cfg) == ("ok", [])  # a Laplace 1-sigma of 0.3 px is ok for nid (sigma_ok_px_nid)
    weak = decide({**ev, "ring_edges": {"ring_edges": 5000, "ratio": 1.1}}, cfg)
    assert weak[0] == "suspect" and "weakly" in weak[1][0]
    assert decide({**ev, "ring_edges": {"ring_edges": 5000, "ratio": 1.0}}, cfg)[0] == "failed"
    assert "too few" in decide({**ev, "ring_edges": {"ring_edges": 50, "ratio": 1.3}}, cfg)[1][0]
    rough = decide({**ev, "frames": {**ev["frames"], "spread_px": 4.0}}, cfg)
    assert rough[0] == "suspect" and "roughly" in rough[1][0]
    far = decide({**ev, "frames": {**ev["frames"], "spread_px": cfg.spread_failed_px_nid + 1}}, cfg)
    assert far[0] == "failed" and "frames disagree" in far[1][0]
    # a Hessian not positive definite (no finite 1-sigma): suspect where the frames agree, else failed
    flat = {**ev, "uncertainty": {"image_px": float("inf"), "translation_mm": float("inf")}}
    verdict, reasons = decide(flat, cfg)
    assert verdict == "suspect" and len(reasons) == 1 and "weakly along one direction" in reasons[0]
    assert decide({**flat, "frames": {**ev["frames"], "spread_px": 4.0}}, cfg)[0] == "failed"
    assert decide({k: v for k, v in flat.items() if k != "frames"}, cfg)[0] == "failed"
    # a frame that alone holds the result (left out, it moves more than fold_ok_px) makes it suspect;
    # one without which the others leave a direction open (inf) has no say
    loo = {"left_out_px": [0.2, 4.5, 0.3], "worst_left_out_px": 4.5, "worst_frame": 1}
    hinged = decide({**ev, "frames": {**ev["frames"], "leave_one_out": loo}}, cfg)
    assert hinged[0] == "suspect" and "hinges on frame 2" in hinged[1][0]
    open_ = {**loo, "left_out_px": [0.2, float("inf"), 0.3], "worst_left_out_px": float("inf")}
    assert decide({**ev, "frames": {**ev["frames"], "leave_one_out": open_}}, cfg) == ("ok", [])


@pytest.fixture(scope="module")
def room_sweep(tmp_path_factory):
    """One frame of a synthetic drive (`rgbd_gt.synth.drive`, seed 3: a room, the LiDAR 27 cm
    behind the camera, an HDL-64E's spacing) as files: sweep.ply, photo.png, camera.yaml and
    truth.yaml (the exact LiDAR-to-camera pose)."""
    from rgbd_gt.io import save_scan, write_camera, write_pose
    from rgbd_gt.io.image import write_image
    from rgbd_gt.synth.drive import synthetic_drive

    d = tmp_path_factory.mktemp("room_sweep")
    drive = synthetic_drive(3, frames=1)
    save_scan(d / "sweep.ply", drive.frames[0].sweep)
    write_image(d / "photo.png", drive.frames[0].photo)
    write_camera(d / "camera.yaml", drive.camera)
    write_pose(d / "truth.yaml", drive.T_cam_from_lidar, method="synthetic truth")
    return d


def test_a_dense_sweep_is_judged_by_its_ring_edges_not_its_splats(room_sweep, tmp_path):
    """A sweep close enough to be dense: its points, drawn as splats, can be scored against the
    photo's structural edges, but fit them weakly even at the truth, where its depth steps along
    the rings fit the photo's edges clearly. refine from about 1 deg / 4 cm ends at the truth and
    is `ok` (it was `suspect` for its splats); moved 2 cm to the side the ring edges fall to
    chance, where the splats' edges barely notice."""
    import json

    from rgbd_gt.align.config import VerifyConfig
    from rgbd_gt.io import read_pose, write_pose
    from rgbd_gt.pose import translation_error_m

    d, cfg = room_sweep, VerifyConfig()
    truth = read_pose(d / "truth.yaml")[0]
    write_pose(tmp_path / "init.yaml", apply_update(truth, np.r_[0.01, -0.01, 0.005, 0.03, -0.02, 0.02]), method="test")
    files = ("--scan", d / "sweep.ply", "--image", d / "photo.png", "--camera", d / "camera.yaml")
    proc = run_cli("refine", *files, "--init", tmp_path / "init.yaml", "-o", tmp_path / "refined.yaml")
    assert proc.returncode == 0, proc.stderr
    T, meta = read_pose(tmp_path / "refined.yaml")
    assert rotation_error_deg(T, truth) < 0.15 and translation_error_m(T, truth) < 0.006, (rotation_error_deg(T, truth), translation_error_m(T, truth))
    edges, rings = meta["evidence"]["edges"], meta["evidence"]["ring_edges"]
    assert edges["edge_check_usable"] and edges["edge_ratio"] < cfg.edge_ratio_ok, edges
    assert rings["ring_edges"] >= cfg.min_edge_pixels and rings["ratio"] > cfg.ring_edge_ratio_ok, rings
    assert meta["verdict"] == "ok", meta["reasons"]

    write_pose(tmp_path / "aside.yaml", apply_update(truth, np.r_[0, 0, 0, 0.02, 0, 0]), method="test")
    proc = run_cli("qa-edges", *files, "--pose", tmp_path / "aside.yaml", "-o", tmp_path / "qa.png",
                   "--json", tmp_path / "qa.json")
    assert proc.returncode == 0, proc.stderr
    scores = json.loads((tmp_path / "qa.json").read_text())
    assert scores["ring_edge_ratio"] < cfg.ring_edge_ratio_failed <= cfg.edge_ratio_failed <= scores["edge_ratio"], scores


def test_a_sweep_states_how_far_an_unchecked_focal_moves_it(room_sweep, tmp_path):
    """NID cannot free the focal length, so a sweep's result gets no camera check; its evidence
    says instead how far a focal 1 % off moves the pose along the camera's axis (10 x the points'
    median depth, mm). The synthetic room with its camera file 2 % long: the pose slides along
    the axis by that order (measured 0.64 of it; KITTI and Waymo 0.9-1.0 at 1 %), and hardly
    anywhere else."""
    from dataclasses import replace

    from rgbd_gt.io import read_camera, read_pose, write_camera, write_pose

    d = room_sweep
    truth = read_pose(d / "truth.yaml")[0]
    camera = read_camera(d / "camera.yaml")
    write_camera(tmp_path / "long.yaml", replace(camera, fx=camera.fx * 1.02, fy=camera.fy * 1.02))
    write_pose(tmp_path / "init.yaml", apply_update(truth, np.r_[0.01, -0.01, 0.005, 0.03, -0.02, 0.02]), method="test")
    proc = run_cli("refine", "--scan", d / "sweep.ply", "--image", d / "photo.png", "--camera", tmp_path / "long.yaml",
                   "--init", tmp_path / "init.yaml", "-o", tmp_path / "refined.yaml")
    assert proc.returncode == 0, proc.stderr
    T, meta = read_pose(tmp_path / "refined.yaml")
    ev = meta["evidence"]
    assert "camera" not in ev and "not checked (nid)" in proc.stdout
    per_percent = ev["camera_unchecked"]["axis_mm_per_focal_percent"]
    assert 20 < per_percent < 60, per_percent  # the room is seen at a median depth of 3.7 m
    shift = (T @ np.linalg.inv(truth))[:3, 3] * 1e3  # mm, camera frame
    assert 0.4 * 2 * per_percent < shift[2] < 1.2 * 2 * per_percent, (shift, per_percent)
    assert np.hypot(shift[0], shift[1]) < 0.2 * shift[2], shift


def test_leave_one_out_steps_are_the_minima_without_each_frame():
    """Frames with quadratic shares of known minima m_f and curvatures A_f: the minimum of the
    sum is the curvature-weighted mean of the m_f; each frame left out, the others' weighted mean;
    each frame alone, its own m_f; all relative to the sum's minimum. A frame with no curvature of
    its own has no minimum alone (nan), and without the only frame that fixes a direction the
    others have none either."""
    from rgbd_gt.align.verify import leave_one_out_steps

    rng = np.random.default_rng(3)
    m = rng.normal(size=(4, 6))
    A = np.stack([(lambda B: B @ B.T + 6 * np.eye(6))(rng.normal(size=(6, 6))) for _ in range(4)])
    g = -np.einsum("fij,fj->fi", A, m)  # the gradient at 0 of 0.5 (x - m)^T A (x - m)
    left_out, own = leave_one_out_steps(g, A)
    at = np.linalg.solve(A.sum(0), np.einsum("fij,fj->i", A, m))
    for f in range(4):
        rest = [k for k in range(4) if k != f]
        expect = np.linalg.solve(A[rest].sum(0), np.einsum("fij,fj->i", A[rest], m[rest]))
        np.testing.assert_allclose(left_out[f], expect - at, atol=1e-10)
        np.testing.assert_allclose(own[f], m[f] - at, atol=1e-10)
    # frame 0 alone fixes the last direction: left out, the others leave it open
    A[1:, 5, :] = A[1:, :, 5] = 0
    left_out, own = leave_one_out_steps(g, A)
    assert np.isnan(left_out[0]).all() and np.isfinite(left_out[1:]).all()
    assert np.isfinite(own[0]).all() and np.isnan(own[1:]).all()


def test_frames_covariance_is_the_sandwich_where_wider_than_the_aligners():
    """Frames whose gradients at the result scatter far more than their curvature says (each frame
    a sample of a sweep's and photo's own errors): the covariance with the frames as samples is
    H^-1 B H^-1 (B: F / (F - 1) times their gradients' scatter), in units of the update; where the
    frames agree better than the aligner's own (Laplace) covariance it keeps that one. A single
    frame has none."""
    from rgbd_gt.align.aligner import RefineResult
    from rgbd_gt.align.verify import frames_covariance

    rng = np.random.default_rng(5)
    F, units = 8, np.array([1e-3, 1e-3, 1e-3, 1e-2, 1e-2, 1e-2])
    H = np.stack([np.eye(6) * (2.0 + f) for f in range(F)])
    Hs = H.sum(0)
    laplace = np.linalg.inv(Hs) * units[:, None] * units[None, :]

    def result(g):
        return RefineResult(np.eye(4), np.zeros((1, 1)), 0, 0.0, 1.0, 1000, 0.0, covariance=laplace, objective="nid",
                            frame_quadratics=(g, H[:len(g)], units))

    g = rng.normal(size=(F, 6)) * 300  # scatter far beyond the curvature's sqrt(H_f) in every direction
    gc = g - g.mean(0)
    sandwich = F / (F - 1) * np.linalg.inv(Hs) @ (gc.T @ gc) @ np.linalg.inv(Hs) * units[:, None] * units[None, :]
    np.testing.assert_allclose(frames_covariance(result(g)), sandwich, rtol=1e-9, atol=1e-18)
    # agreeing frames (no scatter but along the first axis): the Laplace covariance elsewhere
    g = np.zeros((F, 6))
    g[:, 0] = np.linspace(-40, 40, F)
    wide = frames_covariance(result(g))
    assert wide[0, 0] > 100 * laplace[0, 0]
    np.testing.assert_allclose(wide[1:, 1:], laplace[1:, 1:], rtol=1e-9)
    np.testing.assert_allclose(frames_covariance(result(np.zeros((F, 6)))), laplace, rtol=1e-9)
    assert frames_covariance(result(g[:1])) is None


def test_groups_apart_widen_the_frames_covariance_where_they_disagree():
    """K groups of frames refined apart are each an estimate from 1/K of the frames: their ends'
    sample covariance over K is the whole's. Two groups ending at +-e from the result state e e^T;
    a group that lost the scan (no update) is no sample; the frames' covariance is widened along
    e only, to at least e e^T."""
    from rgbd_gt.align.aligner import RefineResult
    from rgbd_gt.align.verify import frames_covariance, groups_covariance

    e = np.array([1e-4, -2e-4, 5e-4, 2e-3, -1e-3, 9e-3])
    np.testing.assert_allclose(groups_covariance([{"update": list(e)}, {"update": list(-e)}]), np.outer(e, e), rtol=1e-12)
    ends = np.random.default_rng(2).normal(size=(4, 6))
    np.testing.assert_allclose(groups_covariance([{"update": list(u)} for u in ends]), np.cov(ends.T) / 4, rtol=1e-12)
    assert groups_covariance([{"update": list(e)}, {"px": float("inf")}]) is None
    F, units = 4, np.full(6, 1e-3)
    H = np.stack([np.eye(6) * 1e4] * F)
    laplace = np.linalg.inv(H.sum(0)) * 1e-6
    result = RefineResult(np.eye(4), np.zeros((1, 1)), 0, 0.0, 1.0, 1000, 0.0, covariance=laplace, objective="nid",
                          frame_quadratics=(np.zeros((F, 6)), H, units))
    groups = [{"update": list(e)}, {"update": list(-e)}]
    wide = frames_covariance(result, groups)
    assert e @ np.linalg.solve(wide, e) == pytest.approx(1.0, rel=1e-6)  # e e^T is now inside it, just
    across = np.linalg.svd(e[None])[2][1:]  # the directions the groups agree in keep the frames' covariance
    np.testing.assert_allclose(across @ wide @ across.T, across @ laplace @ across.T, rtol=1e-6, atol=1e-20)
    np.testing.assert_allclose(frames_covariance(result), laplace, rtol=1e-9)


def test_joint_solve_of_kitti_frames_is_judged_by_its_frames_apart(tmp_path):
    """`refine --pairs` over 4 KITTI frames (3 levels, no wide search, to keep it short) from
    0.3 deg and 5 cm off: the verdict refines the frames in 2 groups apart from the result instead
    of the repeats and reports how far each ended from it; the ring-edge check runs over all 4;
    the pose file and the summary say both."""
    import yaml

    from conftest import run_cli
    from rgbd_gt.io import read_pose, write_pose

    folder = DRIVES / "kitti_00"
    if not (folder / "gt.json").exists():
        pytest.skip(f"needs {folder} (../shared/data, see its README)")
    names = [p.stem for p in sorted((folder / "img").iterdir())][:16:5]
    (tmp_path / "pairs.yaml").write_text(yaml.safe_dump({"pairs": [
        {"scan": str(folder / "pcd" / f"{n}.pcd"), "image": str(folder / "img" / f"{n}.png")} for n in names]}))
    T_ref = read_pose(folder / "gt.json")[0]
    write_pose(tmp_path / "init.yaml", apply_update(T_ref, np.r_[np.radians([0.2, -0.2, 0.1]), 0.03, -0.03, 0.03]))
    out = tmp_path / "rig.yaml"
    proc = run_cli("refine", "--pairs", tmp_path / "pairs.yaml", "--camera", folder / "gt.json", "--init", tmp_path / "init.yaml",
                   "-o", out, "--levels", "3", "--search-starts", "0")
    assert proc.returncode == 0, proc.stderr
    assert "frames apart" in proc.stdout and "ring edges vs chance" in proc.stdout
    _, meta = read_pose(out)
    ev = meta["evidence"]
    assert meta["pairs"] == 4 and meta["edge_weight"] == 3.0
    assert "repeatability" not in ev and ev["frames"]["folds"] == 2
    assert [lv["level"] for lv in ev["convergence"]["levels"]] == [2, 1, 0]
    assert [g["frames"] for g in ev["frames"]["groups"]] == [[0, 2], [1, 3]]
    assert all(np.isfinite(g["px"]) for g in ev["frames"]["groups"])
    T = read_pose(out)[0]
    for g in ev["frames"]["groups"]:  # where each group ended, as an update of the result
        assert rotation_error_deg(apply_update(T, np.array(g["update"])), T) == pytest.approx(g["deg"], rel=1e-3, abs=1e-6)
    assert ev["ring_edges"]["ring_edges"] > 2000 and ev["ring_edges"]["ratio"] > 1.0
    assert len(ev["ring_edges"]["frames"]) == 4 and sum(f["ring_edges"] for f in ev["ring_edges"]["frames"]) == ev["ring_edges"]["ring_edges"]
    assert set(ev["seconds"]) >= {"frames", "ring_edges", "leave_one_frame_out"}
    # each frame left out: the others alone fix the pose here, and none holds the result alone
    loo = ev["frames"]["leave_one_out"]
    assert len(loo["left_out_px"]) == 4 and 0 < loo["worst_left_out_px"] < 3.0
    assert "each frame left out" in proc.stdout
    # the pose file's covariance takes the frames as the samples, then the photos' tiles where
    # they say more: never narrower than the aligner's or the frames'
    for key in ("translation_mm", "rotation_deg"):
        assert ev["tiles"]["uncertainty"][key] >= ev["frames"]["uncertainty"][key] >= ev["uncertainty"][key]
    assert 16 < ev["tiles"]["count"] <= 4 * 64
    cov = np.array(meta["covariance"])
    assert worst_sigmas(cov)["translation_mm"] == pytest.approx(ev["tiles"]["uncertainty"]["translation_mm"])
    # ... nor narrower than the groups apart disagree: half their difference lies within 1 sigma
    half = (np.array(ev["frames"]["groups"][0]["update"]) - np.array(ev["frames"]["groups"][1]["update"])) / 2
    assert half @ np.linalg.solve(cov, half) <= 1 + 1e-6
    assert "uncertainty, frames as samples" in proc.stdout and "uncertainty, photo tiles as samples" in proc.stdout


def test_one_sweep_alone_is_warned_about(tmp_path):
    """refine on a single KITTI sweep (1 level, no search or repeats, to keep it short) warns that
    one sweep fixes the pose poorly and points to --pairs; the pose file keeps the warning."""
    from conftest import run_cli
    from rgbd_gt.io import read_pose

    folder = DRIVES / "kitti_00"
    if not (folder / "gt.json").exists():
        pytest.skip(f"needs {folder} (../shared/data, see its README)")
    out = tmp_path / "pose.yaml"
    proc = run_cli("refine", "--scan", folder / "pcd" / "000000.pcd", "--image", folder / "img" / "000000.png",
                   "--camera", folder / "gt.json", "--init", folder / "gt.json", "-o", out,
                   "--levels", "1", "--search-starts", "0", "--repeats", "0")
    assert proc.returncode == 0, proc.stderr
    assert "--pairs" in proc.stderr + proc.stdout
    assert any("--pairs" in w for w in read_pose(out)[1]["warnings"])



def test_another_drives_camera_file_is_refused(tmp_path):
    """gt.json holds no image size, so the photo gives it: KITTI's K on a Waymo photo (its principal
    point inside the photo, but at 14 % of its height) is one line of error, exit 2, and no output."""
    from conftest import assert_one_line_error

    kitti, waymo = DRIVES / "kitti_00", DRIVES / "waymo"
    if not ((kitti / "gt.json").exists() and (waymo / "gt.json").exists()):
        pytest.skip(f"needs {kitti} and {waymo} (../shared/data, see its README)")
    out = tmp_path / "pose.yaml"
    proc = run_cli("refine", "--scan", kitti / "pcd" / "000000.pcd", "--image", waymo / "img" / "00000.jpg",
                   "--camera", kitti / "gt.json", "--init", kitti / "gt.json", "-o", out)
    assert_one_line_error(proc, "gt.json", "36% of the photo's size from the centre of the 1920x1280 photo", "00000.jpg")
    assert not out.exists()

def test_run_solves_a_drives_frames_as_one_rig(tmp_path):
    """`rgbd-gt run` on a site of 4 KITTI sweeps, a photo each, sharing the config's init (0.3
    deg and 5 cm off the reference) and camera: the sweeps are one rig's frames by default, so
    one pose is solved over all four (3 levels, no wide search, to keep it short), written to
    OUTPUT/rig.yaml and to every frame's pose.yaml, whose steps then take it. A rerun resumes it,
    but not once its init has other content; a rig that is not one is an error."""
    import csv

    import yaml

    from conftest import assert_one_line_error, run_cli
    from rgbd_gt.io import read_pose, write_pose

    folder = DRIVES / "kitti_00"
    if not (folder / "gt.json").exists():
        pytest.skip(f"needs {folder} (../shared/data, see its README)")
    names = [p.stem for p in sorted((folder / "img").iterdir())][:16:5]
    T_ref = read_pose(folder / "gt.json")[0]
    write_pose(tmp_path / "init.yaml", apply_update(T_ref, np.r_[np.radians([0.2, -0.2, 0.1]), 0.03, -0.03, 0.03]))
    config = {"camera": str(folder / "gt.json"), "init": "init.yaml", "output": "out",
              "scans": [{"scan": str(folder / "pcd" / f"{n}.pcd"), "photos": [str(folder / "img" / f"{n}.png")]} for n in names],
              "refine": {"levels": 3, "search_starts": 0}}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    proc = run_cli("run", tmp_path / "run.yaml", "--export-failed")
    assert proc.returncode == 0, proc.stderr
    assert "rig: one pose over 4 frames" in proc.stdout
    T, meta = read_pose(tmp_path / "out" / "rig.yaml")
    assert meta["frames"] == [f"{n}/{n}.png" for n in names] and meta["pairs"] == 4
    assert meta["evidence"]["frames"]["folds"] == 2 and "ring_edges" in meta["evidence"]
    rows = list(csv.DictReader(open(tmp_path / "out" / "summary.csv")))[:-1]
    assert [r["photo"] for r in rows] == [f"{n}.png" for n in names]
    for n, row in zip(names, rows):
        T_frame, frame_meta = read_pose(tmp_path / "out" / n / n / "pose.yaml")
        np.testing.assert_array_equal(T_frame, T)
        assert frame_meta["rig"] == "../../rig.yaml" and frame_meta["verdict"] == meta["verdict"]
        # refine --pairs' keys (its `init` too), not what rig.yaml records to be resumed by
        assert frame_meta["init"] == meta["init"] and "camera_sha1" in meta and "camera_sha1" not in frame_meta
        assert row["status"] == "ok" and row["verdict"] == meta["verdict"] and row["skipped"] == "", row
        assert (tmp_path / "out" / n / n / "depth.exr").exists()
    stamp = (tmp_path / "out" / "rig.yaml").stat().st_mtime_ns
    proc = run_cli("run", tmp_path / "run.yaml")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "out" / "rig.yaml").stat().st_mtime_ns == stamp
    assert all("refine" not in r["skipped"] and "depth" in r["skipped"] for r in list(csv.DictReader(open(tmp_path / "out" / "summary.csv")))[:-1])
    # each frame is judged on its own depth edges too (`verify.frame_verdict`): a frame whose photo is
    # not of its sweep fails alone, and gets no depth map (its ratio set here as a turned sweep gives it:
    # tests/test_drives.py's own-edges test makes one)
    rig = yaml.safe_load((tmp_path / "out" / "rig.yaml").read_text())
    assert [float(r["ring_edge_ratio"]) for r in rows] == pytest.approx([f["ratio"] for f in rig["evidence"]["ring_edges"]["frames"]], rel=1e-5)
    rig["evidence"]["ring_edges"]["frames"][2]["ratio"] = 0.99
    (tmp_path / "out" / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    stamp = (tmp_path / "out" / "rig.yaml").stat().st_mtime_ns
    bad = tmp_path / "out" / names[2] / names[2]
    for f in ("pose.yaml", "depth.exr", "depth.png"):
        (bad / f).unlink()
    proc = run_cli("run", tmp_path / "run.yaml")
    assert proc.returncode == 0, proc.stderr
    frame_meta = read_pose(bad / "pose.yaml")[1]
    assert frame_meta["verdict"] == "failed" and "this frame's depth edges fit its photo no better than chance" in frame_meta["reasons"][0]
    assert frame_meta["frame_ring_edges"]["ratio"] == 0.99 and not (bad / "depth.exr").exists()
    rows = list(csv.DictReader(open(tmp_path / "out" / "summary.csv")))[:-1]
    assert [r["verdict"] for r in rows] == [meta["verdict"]] * 2 + ["failed", meta["verdict"]]
    assert "depth (failed)" in rows[2]["skipped"]
    # the rig's init calibrated again: rig.yaml is not resumed from the old one
    write_pose(tmp_path / "init.yaml", apply_update(T_ref, np.r_[np.radians([0.2, -0.2, 0.1]), 0.03, -0.03, 0.04]))
    proc = run_cli("run", tmp_path / "run.yaml")
    err = proc.stderr.replace("\n", "")  # the console wraps long paths at 80 columns
    assert "rig.yaml: it was solved from other init" in err, proc.stderr
    assert (tmp_path / "out" / "rig.yaml").stat().st_mtime_ns == stamp
    # one frame's photo listed twice is no rig's frame
    config["rig"] = True
    config["scans"][0]["photos"].append(str(folder / "img" / f"{names[1]}.png"))
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    assert_one_line_error(run_cli("run", tmp_path / "run.yaml"), "rig: each of a rig's scans has one photo")
