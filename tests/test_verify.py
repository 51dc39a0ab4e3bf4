"""The verdict on refined poses: right results are ok, a wrong photo and a mirrored photo are not,
--strict exits 3 on failed; the evidence's parts against their definitions."""

import cv2
import numpy as np
import pytest
import yaml

from conftest import run_cli
from rgbd_gt.camera import Camera
from rgbd_gt.init.pnp import pnp, pose_uncertainty
from rgbd_gt.io import read_pose
from rgbd_gt.pose import apply_update, rigid, worst_sigmas
from rgbd_gt.qa.edges import chance_relative, photo_strength, structural_edges


@pytest.fixture(scope="module")
def scene(tmp_path_factory, synth_scene):
    """A scene where refine is reliable from its init's distance: from 12 starts 1 deg / 5 cm
    around the truth, none of the 72 runs with seeds 0-5 ended off (the seed-3 scene: 5 of 72,
    so that there the verdict's nearby starts fail a right result with some seeds, as its
    false alarms in docs/trust.md)."""
    d = tmp_path_factory.mktemp("verify")
    synth_scene(d, 2)
    return d


def _refine(d, photo, out, *extra):
    return run_cli("refine", "--scan", d / "scan.ply", "--image", photo, "--camera", d / "camera.yaml",
                   "--init", d / "init_pose.yaml", "-o", out, *extra)


def test_right_result_is_ok_and_the_pose_file_carries_the_evidence(scene, tmp_path):
    proc = _refine(scene, scene / "photo.png", tmp_path / "pose.yaml")
    assert proc.returncode == 0, proc.stderr
    doc = yaml.safe_load((tmp_path / "pose.yaml").read_text())
    assert doc["verdict"] == "ok", doc["reasons"]
    assert doc["reasons"] == []
    ev = doc["evidence"]
    for key in ("uncertainty", "convergence", "repeatability", "sharpness", "edges", "change_from_init"):
        assert key in ev, key
    assert ev["edges"]["edge_ratio"] > 1.25  # clearly better than chance
    assert ev["sharpness"]["min_rise"] > 0  # a minimum in every direction
    assert ev["repeatability"]["starts"] == 4 and ev["repeatability"]["spread_px"] < 0.5
    assert 0 < ev["uncertainty"]["translation_mm"] < 5 and ev["uncertainty"]["condition"] >= 1
    # the covariance the file states has the photo's tiles as the samples, never narrower than the aligner's
    assert 2 <= ev["tiles"]["count"] <= 64
    for key in ("translation_mm", "rotation_deg", "image_px"):
        assert ev["tiles"]["uncertainty"][key] >= ev["uncertainty"][key]
    assert worst_sigmas(np.array(doc["covariance"]))["translation_mm"] == pytest.approx(ev["tiles"]["uncertainty"]["translation_mm"])
    assert "uncertainty, photo tiles as samples" in proc.stdout
    assert ev["convergence"]["levels"][-1]["level"] == 0
    # the camera file is right: freed, the focal length stays (0.02% at most on the synthetic scenes)
    assert abs(ev["camera"]["focal_change"]) < 0.001, ev["camera"]
    assert "verdict" in proc.stdout


def test_a_camera_file_two_percent_off_is_not_ok(scene, tmp_path):
    """A wrong focal length is absorbed by the pose (the camera slides along its axis): without
    the camera check this result was `ok` 60 mm off. Freed, the focal moves back to the photo's."""
    from rgbd_gt.io import read_camera
    from rgbd_gt.io.camera_file import write_camera
    from rgbd_gt.pose import translation_error_m

    cam = read_camera(scene / "camera.yaml")
    write_camera(tmp_path / "camera.yaml", Camera(cam.width, cam.height, cam.fx * 1.02, cam.fy * 1.02, cam.cx, cam.cy,
                                                  cam.distortion))
    proc = run_cli("refine", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera",
                   tmp_path / "camera.yaml", "--init", scene / "init_pose.yaml", "-o", tmp_path / "pose.yaml",
                   "--repeats", "1")
    assert proc.returncode == 0, proc.stderr
    T, doc = read_pose(tmp_path / "pose.yaml")
    assert translation_error_m(T, read_pose(scene / "gt_pose.yaml")[0]) > 0.02  # the pose did absorb it
    assert doc["verdict"] != "ok"
    assert any("camera file disagrees with the photo" in r for r in doc["reasons"]), doc["reasons"]
    assert -0.022 < doc["evidence"]["camera"]["focal_change"] < -0.01  # toward 1/1.02 - 1 (3 iterations)


def test_mirrored_photo_is_failed_and_strict_exits_3(scene, tmp_path):
    photo = cv2.imread(str(scene / "photo.png"))
    cv2.imwrite(str(tmp_path / "mirrored.png"), photo[:, ::-1])
    out = tmp_path / "pose.yaml"
    proc = _refine(scene, tmp_path / "mirrored.png", out, "--strict", "--repeats", "2")
    doc = yaml.safe_load(out.read_text())  # written even when failed, with the verdict
    assert doc["verdict"] == "failed", doc
    assert proc.returncode == 3, (proc.returncode, proc.stderr)
    # the edge check flags it: a mirrored scene's edges at chance (ratio about 1.0-1.1, at the
    # failed threshold 1.1 or under it: "weakly" or "no better than chance")
    assert any("the scan's edges fit the photo" in r for r in doc["reasons"]), doc["reasons"]
    assert doc["evidence"]["edges"]["edge_ratio"] < 1.2, doc["evidence"]["edges"]


def test_photo_of_another_scene_is_not_ok(scene, tmp_path_factory, tmp_path, synth_scene):
    other = tmp_path_factory.mktemp("other")
    synth_scene(other, 5)
    out = tmp_path / "pose.yaml"
    proc = _refine(scene, other / "photo.png", out, "--repeats", "2")
    assert proc.returncode == 0, proc.stderr  # without --strict a failed verdict is no error
    doc = yaml.safe_load(out.read_text())
    assert doc["verdict"] != "ok", doc["evidence"]


def test_check_pairs_enter_the_evidence(scene, tmp_path):
    """Held-out pairs made from the truth: near 0 px after refine, more at the init."""
    from rgbd_gt.camera import project
    from rgbd_gt.io import load_scan, read_camera
    from rgbd_gt.pose import transform_points

    cam = read_camera(scene / "camera.yaml")
    gt = read_pose(scene / "gt_pose.yaml")[0]
    xyz = load_scan(scene / "scan.ply").xyz[::5000][:20]
    uv, z = project(cam, transform_points(gt, xyz))
    ok = (z > 0) & (uv[:, 0] > 0) & (uv[:, 1] > 0) & (uv[:, 0] < cam.width) & (uv[:, 1] < cam.height)
    rows = np.concatenate([uv[ok], xyz[ok]], 1)
    np.savetxt(tmp_path / "check.csv", rows, delimiter=",", header="u,v,x,y,z", comments="")
    proc = _refine(scene, scene / "photo.png", tmp_path / "pose.yaml", "--check", tmp_path / "check.csv", "--repeats", "0")
    assert proc.returncode == 0, proc.stderr
    chk = yaml.safe_load((tmp_path / "pose.yaml").read_text())["evidence"]["check"]
    assert chk["pairs"] == int(ok.sum()) and chk["rms_px"] < 0.5 < chk["rms_init_px"]
    assert "repeatability" not in yaml.safe_load((tmp_path / "pose.yaml").read_text())["evidence"]
    # fuzz seed 38: the pairs were held to the box of the scan's points in view of the init (there,
    # of a camera file gone wrong), and one outside it was "outside the scan ([...] .. [...]):
    # picked on another scan?". A camera zoomed in 4 times sees a corner of the room
    from rgbd_gt.prepared import prepare_scan

    keys = yaml.safe_load((scene / "camera.yaml").read_text())
    (tmp_path / "narrow.yaml").write_text(yaml.safe_dump({**keys, "fx": keys["fx"] * 4, "fy": keys["fy"] * 4}))
    view = prepare_scan(scene / "scan.ply").views(read_camera(tmp_path / "narrow.yaml"), [read_pose(scene / "init_pose.yaml")[0]])
    assert ((rows[:, 2:] < view.xyz.min(0) - 0.1) | (rows[:, 2:] > view.xyz.max(0) + 0.1)).any(), "no pair outside its box"
    proc = run_cli("refine", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera", tmp_path / "narrow.yaml",
                   "--init", scene / "init_pose.yaml", "-o", tmp_path / "off.yaml", "--check", tmp_path / "check.csv",
                   "--repeats", "0")
    assert proc.returncode == 0, proc.stderr
    off = yaml.safe_load((tmp_path / "off.yaml").read_text())
    assert off["evidence"]["check"]["pairs"] == int(ok.sum()) and off["verdict"] == "failed"


def test_structural_score_is_one_at_chance_and_high_on_matching_edges():
    rng = np.random.default_rng(0)
    img = np.zeros((240, 320), np.float32)
    for _ in range(25):  # rectangles at two depths: depth and color edges in the same places
        x, y = rng.integers(0, 280), rng.integers(0, 200)
        img[y:y + rng.integers(10, 40), x:x + rng.integers(10, 40)] = rng.uniform(50, 250)
    z = np.where(img > 0, 2.0, 3.0).astype(np.float32)
    edges = structural_edges(z, img)
    assert edges.sum() > 500
    strength = photo_strength(img)
    matched = chance_relative(strength, edges, 6)
    assert matched.ratio > 2.0
    noise = photo_strength(rng.uniform(0, 255, img.shape).astype(np.float32))  # no structure: chance
    assert abs(chance_relative(noise, edges, 6).ratio - 1.0) < 0.05
    flat = np.zeros_like(z)  # nothing rendered: no edges, nothing to score
    assert chance_relative(strength, structural_edges(flat, img), 6).edge_pixels == 0


def test_pnp_uncertainty_matches_the_spread_of_noisy_solutions():
    """The stated 1-sigma against the scatter of PnP on many noisy copies of the same picks."""
    rng = np.random.default_rng(1)
    cam = Camera(1280, 960, 1000.0, 1000.0, 639.5, 479.5)
    T = rigid(cv2.Rodrigues(np.array([0.1, -0.2, 0.05]))[0], [0.1, -0.05, 0.2])
    obj = rng.uniform([-1.5, -1, 3], [1.5, 1, 6], (30, 3))
    from rgbd_gt.camera import project
    from rgbd_gt.pose import camera_centre, invert, transform_points

    obj = transform_points(invert(T), obj)
    img, _ = project(cam, transform_points(T, obj))
    noise = 0.7
    centres = []
    for _ in range(200):
        Tk, _ = pnp(obj, img + rng.normal(0, noise, img.shape), cam)
        centres.append(camera_centre(Tk))
    spread_mm = np.sqrt(np.linalg.eigvalsh(np.cov(np.array(centres).T))[-1]) * 1e3
    noisy = img + rng.normal(0, noise, img.shape)
    stated = pose_uncertainty(pnp(obj, noisy, cam)[0], obj, noisy, cam)
    assert 0.6 < stated["translation_mm"] / spread_mm < 1.6, (stated, spread_mm)
    assert pose_uncertainty(T, obj[:3], img[:3], cam) is None  # too few points fix nothing
    moved = apply_update(T, np.r_[0, 0, 0, 0.01, 0, 0])
    assert pose_uncertainty(moved, obj, img, cam)["translation_mm"] > stated["translation_mm"]  # bad fit, larger sigma


def test_check_points_worse_than_at_the_init_say_keep_the_init():
    """decide(): held-out pairs far off after refine fail the result; when the init fits them
    within check_failed_px the reason tells the user to keep the init, otherwise not."""
    from rgbd_gt.align.config import VerifyConfig
    from rgbd_gt.align.verify import decide

    cfg = VerifyConfig()
    ev = {"uncertainty": {"image_px": 0.1, "translation_mm": 1.0}, "convergence": {"levels": [{"stop": "converged"}]}}
    verdict, reasons = decide({**ev, "check": {"rms_px": 40.0, "rms_init_px": 2.3}}, cfg)
    assert verdict == "failed" and reasons == ["the check points are 40.0 px off (2.3 px at the init; keep the init)"]
    verdict, reasons = decide({**ev, "check": {"rms_px": 40.0, "rms_init_px": cfg.check_failed_px + 1}}, cfg)
    assert verdict == "failed" and "keep the init" not in reasons[0]
    assert decide({**ev, "check": {"rms_px": 0.5, "rms_init_px": 9.0}}, cfg) == ("ok", [])


def test_nid_repeats_are_judged_by_their_own_threshold():
    """decide(): a spread of the repeats that fails a photometric result leaves a nid result
    (a sweep: a precision of a few pixels) suspect; beyond spread_failed_px_nid it fails too."""
    from rgbd_gt.align.config import VerifyConfig
    from rgbd_gt.align.verify import decide

    cfg = VerifyConfig()
    ev = {"uncertainty": {"image_px": 0.1, "translation_mm": 1.0}, "convergence": {"levels": [{"stop": "converged"}]}}
    rep = {"spread_px": (cfg.spread_failed_px + cfg.spread_failed_px_nid) / 2, "spread_mm": 40.0}
    assert decide({**ev, "objective": "photometric", "repeatability": rep}, cfg)[0] == "failed"
    assert decide({**ev, "objective": "nid", "repeatability": rep}, cfg) == ("suspect", [f"nearby starts disagree by {rep['spread_px']:.2f} px"])
    far = {**rep, "spread_px": cfg.spread_failed_px_nid + 1}
    assert decide({**ev, "objective": "nid", "repeatability": far}, cfg)[0] == "failed"


def test_repeats_that_agree_on_a_strip_only_leave_the_result_suspect():
    """A scan in the photo's corner: a turn about the ray through it (a pose the scan cannot pin
    down) barely moves its points but moves the rest of the photo by pixels; decide() makes such
    repeats `suspect`, not `ok`."""
    from rgbd_gt.align.config import VerifyConfig
    from rgbd_gt.align.verify import _View, decide

    cam = Camera(640, 480, 500.0, 500.0, 319.5, 239.5)
    rng = np.random.default_rng(0)
    corner = np.c_[rng.uniform(-1.9, -1.6, 200), rng.uniform(-1.4, -1.1, 200), rng.uniform(2.8, 3.2, 200)]  # top left
    view, T = _View(corner, cam), np.eye(4)
    axis = corner.mean(axis=0) / np.linalg.norm(corner.mean(axis=0))
    T2 = rigid(cv2.Rodrigues(np.radians(0.5) * axis)[0], np.zeros(3))
    on_points, across = view.motion_px(T2, T), view.across_photo(T).motion_px(T2, T)
    assert on_points < 0.5 and across > 2.0, (on_points, across)
    cfg = VerifyConfig()
    ev = {"uncertainty": {"image_px": 0.01, "translation_mm": 0.1}, "convergence": {"levels": [{"stop": "converged"}]}}
    rep = {"spread_px": on_points, "spread_photo_px": across, "spread_mm": 15.0}
    verdict, reasons = decide({**ev, "repeatability": rep}, cfg)
    assert verdict == "suspect" and "not across the photo" in reasons[0], reasons
    assert decide({**ev, "repeatability": {**rep, "spread_photo_px": on_points}}, cfg) == ("ok", [])
