"""rgbd-gt run: the whole workflow on a synthetic scene with two photos, resumable."""

import csv
import html
import hashlib
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from conftest import ROOT, assert_one_line_error, run_cli
from rgbd_gt.io import load_scan, read_pose, save_scan
from rgbd_gt.io.depth_file import read_depth_exr
from rgbd_gt.pose import rotation_error_deg, translation_error_m


def test_run_two_photos_then_resume(tmp_path, synth_scene):
    scene = tmp_path / "scene"
    synth_scene(scene, 2, 2)
    noise = np.random.default_rng(0).integers(0, 256, (480, 640, 3), dtype=np.uint8)
    cv2.imwrite(str(scene / "photo_blank.png"), noise)  # a photo without the board
    cv2.imwrite(str(scene / "photo_small.png"), noise[:240, :320])  # not the camera's size
    config = {"scan": "scene/scan.e57", "camera": "scene/camera.yaml", "photos": ["scene/photo*.png"],
              "output": "out", "refine": {"max_points": 40000}}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    proc = run_cli("run", tmp_path / "run.yaml")
    assert proc.returncode == 0, proc.stderr
    assert "photo_blank.png: failed" in proc.stderr  # reported, and the others went on
    rows = {r["photo"]: r for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))}
    assert rows["photo_blank.png"]["status"] == "failed" and "checkerboard" in rows["photo_blank.png"]["error"]
    assert rows["# verdicts"]["verdict"] == "2 ok, 0 suspect, 2 failed"  # those two failed before refine
    assert "verdicts: 2 ok, 0 suspect, 2 failed" in proc.stdout
    small = f"{scene / 'photo_small.png'}: image is 320x240 but camera file {scene / 'camera.yaml'} is for 640x480"
    assert rows["photo_small.png"]["error"] == small
    assert f"photo_small.png: failed: {small}\n" in proc.stdout  # under the table, one line
    assert "…" not in proc.stdout  # the table wraps its cells at 80 columns (a log), it does not cut them
    for photo, truth in (("photo", "gt_pose.yaml"), ("photo_1", "gt_pose_1.yaml")):
        r = rows[f"{photo}.png"]
        assert r["status"] == "ok" and r["verdict"] == "ok", r
        assert float(r["edge_ratio"]) > 1.25
        assert yaml.safe_load((tmp_path / "out" / photo / "pose.yaml").read_text())["verdict"] == "ok"
        assert float(r["edge_after_px"]) < float(r["edge_before_px"])
        gt = read_pose(scene / truth)[0]
        T = read_pose(tmp_path / "out" / photo / "pose.yaml")[0]
        assert translation_error_m(T, gt) < 0.003 and rotation_error_deg(T, gt) < 0.05
        z, header = read_depth_exr(tmp_path / "out" / photo / "depth.exr")
        assert z.shape == (480, 640) and (z > 0).mean() > 0.5
        np.testing.assert_allclose(header["rgbd_gt_T_cam_from_scan"], T)
        assert float(r["seen_from_behind"]) < 0.03  # the camera is on the scanner's side
        for name in ("overlay.png", "overlay_blend.png"):
            assert cv2.imread(str(tmp_path / "out" / photo / name)).shape == (480, 640, 3)
        assert not (tmp_path / "out" / photo / "overlay_points.png").exists()  # for sweeps only
    # the refine command on the same inputs gives run's pose: it prepares the scan in memory as
    # run prepares it on disk, so the aligner is handed the same points (align/subset.py)
    alone = tmp_path / "alone.yaml"
    assert run_cli("refine", "--scan", scene / "scan.e57", "--image", scene / "photo.png", "--camera", scene / "camera.yaml",
                   "--init", tmp_path / "out" / "photo" / "init.yaml", "-o", alone, "--max-points", 40000,
                   "--repeats", 0).returncode == 0
    T, T_run = read_pose(alone)[0], read_pose(tmp_path / "out" / "photo" / "pose.yaml")[0]
    # 0 to 1 micron when the file's points went to the aligner in file order; 0.12 mm apart when
    # the subsets followed point order
    np.testing.assert_allclose(T, T_run, atol=1e-9)
    # on run's cache, refine is handed run's very points and normals
    assert run_cli("refine", "--scan", scene / "scan.e57", "--image", scene / "photo.png", "--camera", scene / "camera.yaml",
                   "--init", tmp_path / "out" / "photo" / "init.yaml", "-o", alone, "--max-points", 40000,
                   "--repeats", 0, "--cache", tmp_path / "out" / ".scan-cache").returncode == 0
    np.testing.assert_allclose(read_pose(alone)[0], T_run, atol=1e-9)
    # the run's page (report.html): every photo, those without a pose with why
    page = (tmp_path / "out" / "report.html").read_text()
    assert "4 photos: 2 ok, 0 suspect, 0 failed, 2 without a pose" in page and html.escape(small) in page
    assert all((tmp_path / "out" / "report" / f"{n}_{kind}").is_file() for n in ("photo", "photo_1")
               for kind in ("photo.png", "depth.png", "overlay_blend.png", "qa.png"))
    # like summary.csv, run.json and the page are the run's own: written again by a rerun
    stamps = {p: p.stat().st_mtime_ns for p in (tmp_path / "out").rglob("*") if p.is_file()
              and p.name not in ("summary.csv", "run.json", ".run.lock", "report.html") and p.parent.name != "report"}
    again = run_cli("run", tmp_path / "run.yaml")
    assert again.returncode == 0, again.stderr
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps  # nothing recomputed
    rows = {r["photo"]: r for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))}
    assert rows["photo.png"]["skipped"] == "init refine depth qa overlay"
    # another photo under a name already done is not given that photo's pose; nor is a second
    # photo of the same name in another folder
    (scene / "photo.png").write_bytes((scene / "photo_1.png").read_bytes())
    again = run_cli("run", tmp_path / "run.yaml")
    rows = {r["photo"]: r for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))}
    assert rows["photo.png"]["status"] == "failed" and "holds outputs made from another photo" in rows["photo.png"]["error"]
    assert rows["photo_1.png"]["verdict"] == "ok"
    moved = load_scan(scene / "scan.e57")  # a scan registered again: the poses of the old one do not hold
    moved.xyz = moved.xyz + [0.01, 0.0, 0.0]
    save_scan(scene / "moved.ply", moved)
    config["scan"] = "scene/moved.ply"
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    assert run_cli("run", tmp_path / "run.yaml").returncode == 1  # every photo failed
    rows = {r["photo"]: r for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))}
    assert "holds outputs made from another scan" in rows["photo_1.png"]["error"], rows["photo_1.png"]
    config["scan"] = "scene/scan.e57"
    (tmp_path / "run.yaml").write_text(yaml.safe_dump({**config, "board": {"square": 0.06}}))  # the board measured again
    run_cli("run", tmp_path / "run.yaml")
    rows = {r["photo"]: r for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))}
    assert "holds outputs made from another board (9x6 inner corners, square 0.05 m" in rows["photo_1.png"]["error"], rows
    camera = yaml.safe_load((scene / "camera.yaml").read_text())
    (scene / "camera.yaml").write_text(yaml.safe_dump({**camera, "fx": camera["fx"] * 1.01}))  # calibrated again
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    run_cli("run", tmp_path / "run.yaml")
    rows = {r["photo"]: r for r in csv.DictReader(open(tmp_path / "out" / "summary.csv"))}
    assert "holds outputs made from another camera" in rows["photo_1.png"]["error"], rows["photo_1.png"]
    (tmp_path / "b").mkdir()
    (tmp_path / "b" / "photo_1.png").write_bytes(b"")
    config["photos"].append("b/photo*.png")
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    assert_one_line_error(run_cli("run", tmp_path / "run.yaml"), "would write to the same folder 'photo_1'")


def test_run_bad_config(tmp_path):
    (tmp_path / "bad.yaml").write_text("scan: x.ply\nphotos: [a.png]\ncamera: c.yaml\nwhatever: 1\n")
    assert_one_line_error(run_cli("run", tmp_path / "bad.yaml"), "bad.yaml", "whatever")
    (tmp_path / "noscan.yaml").write_text("scan: x.ply\ncamera: c.yaml\nphotos: [a.png]\n")
    assert_one_line_error(run_cli("run", tmp_path / "noscan.yaml"), "noscan.yaml", f"scan: {tmp_path / 'x.ply'}: scan file not found")
    (tmp_path / "x.ply").write_bytes(b"")  # read only when its scan is prepared
    (tmp_path / "nophotos.yaml").write_text("scan: x.ply\ncamera: c.yaml\nphotos: [none*.png]\n")
    assert_one_line_error(run_cli("run", tmp_path / "nophotos.yaml"), "no photo matches")
    (tmp_path / "folder.yaml").write_text(f"scan: x.ply\ncamera: c.yaml\nphotos: ['{tmp_path}/']\n")  # a path cut short
    assert_one_line_error(run_cli("run", tmp_path / "folder.yaml"), "folder.yaml", "names a folder, not photos")
    (tmp_path / "empty.yaml").write_text("scan: x.ply\ncamera: c.yaml\nphotos: ['']\n")  # cut to nothing
    assert_one_line_error(run_cli("run", tmp_path / "empty.yaml"), "empty.yaml", "photos: an empty path")
    (tmp_path / "scandir.yaml").write_text("scan: .\ncamera: c.yaml\nphotos: [a.png]\n")
    assert_one_line_error(run_cli("run", tmp_path / "scandir.yaml"), "scandir.yaml", "scan:", "is a folder, not a scan file")
    (tmp_path / "a.png").write_bytes(b"")
    (tmp_path / "emptyinit.yaml").write_text("scan: x.ply\ncamera: c.yaml\nphotos: [a.png]\ninit: ''\n")  # fuzz seed 9
    assert_one_line_error(run_cli("run", tmp_path / "emptyinit.yaml"), "emptyinit.yaml", "init: an empty path; give a pose file")
    # fuzz seed 36: a scan's empty camera (or init) took the config's own, without a word
    for key in ("camera", "init"):
        (tmp_path / "emptyown.yaml").write_text(f"camera: c.yaml\nscans:\n  - {{scan: x.ply, photos: [a.png], {key}: ''}}\n")
        assert_one_line_error(run_cli("run", tmp_path / "emptyown.yaml"), "emptyown.yaml",
                              f"scans[0].{key}: an empty path; give a file, or leave it out for the config's own")
    (tmp_path / "noinit.yaml").write_text("scan: x.ply\ncamera: c.yaml\nphotos: [a.png]\ninit: rig.yaml\n")
    assert_one_line_error(run_cli("run", tmp_path / "noinit.yaml"), "noinit.yaml", f"init: {tmp_path / 'rig.yaml'}: pose file not found")
    (tmp_path / "nocorners.yaml").write_text("scan: x.ply\ncamera: c.yaml\nphotos: [a.png]\nboard:\n  points: corners.csv\n")
    assert_one_line_error(run_cli("run", tmp_path / "nocorners.yaml"), f"board.points: {tmp_path / 'corners.csv'}: corners file not found")
    import torch

    if not torch.cuda.is_available():  # one error before any work, not every photo failing on it
        (tmp_path / "cuda.yaml").write_text("scan: x.ply\ncamera: c.yaml\nphotos: [a.png]\ndevice: cuda\n")
        assert_one_line_error(run_cli("run", tmp_path / "cuda.yaml"), "cuda.yaml", "device: cuda, but this machine has no CUDA")
    # the corners, as every path of a config, are found beside the config, wherever the run starts
    from rgbd_gt.config import load_config
    from rgbd_gt.workflow import RunConfig, resolve

    (tmp_path / "corners.csv").write_text("x,y,z\n")
    jobs, _ = resolve(tmp_path / "nocorners.yaml", load_config(RunConfig, tmp_path / "nocorners.yaml"))
    assert jobs[0].board.points == str(tmp_path / "corners.csv")
    # and `~` is the user's home, in every path of a config
    home = tmp_path / "home"
    (home / "photos").mkdir(parents=True)
    (home / "photos" / "a.png").write_bytes(b"")
    (tmp_path / "home.yaml").write_text("scan: ~/../x.ply\ncamera: ~/../c.yaml\nphotos: [~/photos/*.png]\noutput: ~/out\n"
                                        "init: ~/../rig.yaml\n")
    (tmp_path / "rig.yaml").write_bytes(b"")
    with pytest.MonkeyPatch.context() as env:
        env.setenv("HOME", str(home))
        jobs, output = resolve(tmp_path / "home.yaml", load_config(RunConfig, tmp_path / "home.yaml"))
    assert (jobs[0].scan, jobs[0].photos, jobs[0].init, output) == (
        tmp_path / "x.ply", [home / "photos" / "a.png"], tmp_path / "rig.yaml", home / "out")
    # a second run on an output folder that a run is writing is refused before any work
    import fcntl

    (tmp_path / "c.yaml").write_bytes((ROOT / "docs" / "real-data" / "cam3346.yaml").read_bytes())
    (tmp_path / "busy.yaml").write_text("scan: x.ply\ncamera: c.yaml\nphotos: [a.png]\noutput: busy\n")
    (tmp_path / "busy").mkdir()
    with open(tmp_path / "busy" / ".run.lock", "a+") as lock:
        lock.write("4242\n")
        lock.flush()
        fcntl.flock(lock, fcntl.LOCK_EX)
        assert_one_line_error(run_cli("run", tmp_path / "busy.yaml"), "busy: output: another rgbd-gt run (pid 4242) is writing")
    assert not (tmp_path / "busy" / "summary.csv").exists()


def test_run_refines_one_camera_for_all_photos(tmp_path, synth_scene):
    """refine_intrinsics in a run: one camera from all photos (one solve of every pose and the
    camera), then every pose with it; the camera file's focal is 2% off."""
    scene = tmp_path / "scene"
    synth_scene(scene, 8, 2)
    cam = yaml.safe_load((scene / "camera.yaml").read_text())
    (scene / "camera_off.yaml").write_text(yaml.safe_dump({**cam, "fx": cam["fx"] * 1.02, "fy": cam["fy"] * 1.02}))
    config = {"scan": "scene/scan.ply", "camera": "scene/camera_off.yaml", "photos": ["scene/photo*.png"],
              "output": "out", "refine": {"max_points": 40000, "refine_intrinsics": "focal"}}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    proc = run_cli("run", tmp_path / "run.yaml")
    assert proc.returncode == 0, proc.stderr
    assert "camera refined over the photos" in proc.stdout
    shared = yaml.safe_load((tmp_path / "out" / "camera.yaml").read_text())
    assert abs(shared["fx"] / cam["fx"] - 1) < 0.003, (shared["fx"], cam["fx"])
    estimates = __import__("json").loads((tmp_path / "out" / "intrinsics.json").read_text())
    assert [e["photo"] for e in estimates["photos"]] == ["photo.png", "photo_1.png"]
    assert estimates["solve"] == "joint" and all(e["residual_vs_others"] > 0 for e in estimates["photos"])
    assert estimates["shared_sigma"][0] > 0 and estimates["shared_sigma"][1] is None  # focal alone was free
    for photo, truth in (("photo", "gt_pose.yaml"), ("photo_1", "gt_pose_1.yaml")):
        T = read_pose(tmp_path / "out" / photo / "pose.yaml")[0]
        gt = read_pose(scene / truth)[0]
        assert translation_error_m(T, gt) < 0.005 and rotation_error_deg(T, gt) < 0.05
        assert (tmp_path / "out" / photo / "depth.exr").exists()
    made = __import__("json").loads((tmp_path / "out" / "intrinsics.json").read_text())["made_from"]
    assert made["camera_sha1"] == hashlib.sha1((scene / "camera_off.yaml").read_bytes()).hexdigest()
    # the run's page reads the run with the scans' keys as the run prepared them (`read_run(known=)`):
    # a key still of the file as it is stands for its SHA-1, read no more; one of another time does not
    from rgbd_gt.errors import InputError
    from rgbd_gt.export.source import read_run
    from rgbd_gt.prepared import file_key

    scan = Path(__import__("json").loads((tmp_path / "out" / "run.json").read_text())["scans"][0]["scan"])
    key = file_key(scan)
    assert read_run(tmp_path / "out", known={scan: key})[0].scan_key is key
    with pytest.raises(InputError, match="changed since photo"):
        read_run(tmp_path / "out", known={scan: {**key, "sha1": "0" * 40}})
    assert read_run(tmp_path / "out", known={scan: {**key, "sha1": "0" * 40, "mtime_ns": 1}})[0].scan_key == key
    # a damaged record is named as such: the scan did not change
    made_file = tmp_path / "out" / "photo" / "init.yaml"
    text = made_file.read_text()
    made_file.write_text(text.replace(f"scan_sha1: {key['sha1']}", "scan_sha1: 12", 1))
    with pytest.raises(InputError, match=rf"^{made_file}: scan_sha1: not a SHA-1 \(12\)$"):
        read_run(tmp_path / "out")
    made_file.write_text(text)
    # the camera calibrated again: the shared camera is not reused but refined again, from photos
    # whose folders were made with the old one, which say so (remove them to redo them)
    (scene / "camera_off.yaml").write_text((scene / "camera_off.yaml").read_text() + "# calibrated again\n")
    assert_one_line_error(run_cli("run", tmp_path / "run.yaml"), "no photo gave a camera estimate", "made from another camera")
    # nor is the run exported with it: its poses were solved with the old camera
    assert_one_line_error(run_cli("export", tmp_path / "out", "-o", tmp_path / "ds", "-f", "plain"),
                          str(scene / "camera_off.yaml"), "changed since photo photo was solved")
    assert not (tmp_path / "ds").exists()


def test_run_on_a_real_lidar_frame_with_the_rigs_extrinsic(tmp_path):
    """A real sweep and photo (PJLab scene 3) with no board: the config's `init` (the calibration
    text file's extrinsic) is the photo's initial pose and the calibration file its camera (its
    size from the photo); the depth map holds the sweep's own points, each pixel the nearest
    point that falls in it, nothing between them."""
    from conftest import _need
    from rgbd_gt.camera import project
    from rgbd_gt.io import load_scan, read_camera
    from rgbd_gt.pose import transform_points

    folder = _need("lidar_camera") / "pjlab_3"
    rig = tmp_path / "rig.txt"
    rig.write_text((folder / "calib.txt").read_text())
    config = {"scan": str(folder / "calib.pcd"), "camera": str(folder / "calib.txt"), "init": str(rig),
              "photos": [str(folder / "calib.png")], "output": "out"}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    proc = run_cli("run", tmp_path / "run.yaml", "--export-failed")
    assert proc.returncode == 0, proc.stderr
    out = tmp_path / "out" / "calib"
    T_ref = read_pose(folder / "calib.txt")[0]
    T_init, meta = read_pose(out / "init.yaml")
    np.testing.assert_allclose(T_init, T_ref, atol=1e-12)
    assert meta["method"].startswith("the config's init")
    row = next(csv.DictReader(open(tmp_path / "out" / "summary.csv")))
    assert row["status"] == "ok" and row["verdict"] in ("ok", "suspect", "failed")
    assert (out / "overlay_points.png").exists()
    z, header = read_depth_exr(out / "depth.exr")
    T = np.array(header["rgbd_gt_T_cam_from_scan"])
    assert 0.001 < (z > 0).mean() < 0.02  # about 1 pixel per visible return of a 1920 x 1200 photo
    cam = read_camera(folder / "calib.txt", (1920, 1200))
    uv, zp = project(cam, transform_points(T, load_scan(folder / "calib.pcd").xyz))
    front = (zp > 0.1) & (np.abs(uv) < 1e6).all(1)
    px, zp = np.rint(uv[front]).astype(np.int64), zp[front]
    inside = np.all(px >= 0, 1) & (px[:, 0] < 1920) & (px[:, 1] < 1200)
    nearest = np.full(1920 * 1200, np.inf)
    np.minimum.at(nearest, px[inside, 1] * 1920 + px[inside, 0], zp[inside])
    have = np.flatnonzero(z.ravel() > 0)
    assert np.mean(np.abs(nearest[have] - z.ravel()[have]) < 1e-3) > 0.99
    qa = yaml.safe_load((out / "qa.json").read_text())  # geometry checks a sweep: the photo's poles stand upright
    assert qa["verticals_usable"] and abs(qa["verticals_roll_deg"]) < 0.6 and abs(qa["before_verticals_roll_deg"]) < 0.6, qa
    assert qa["verticals_poles"] > 100  # from the sweep around the camera, not the 10-20 poles in view
    assert float(row["verticals_roll_before_deg"]) == pytest.approx(qa["before_verticals_roll_deg"], abs=1e-5)
    # the rig calibrated again: the photo's outputs are not resumed from the old extrinsic
    rig.write_text(rig.read_text() + "\n")
    proc = run_cli("run", tmp_path / "run.yaml")
    row = next(csv.DictReader(open(tmp_path / "out" / "summary.csv")))
    assert row["status"] == "failed" and "holds outputs made from another init" in row["error"], row


def test_run_depth_covers_what_the_refined_pose_sees(tmp_path, synth_scene):
    """A refined pose 4 deg from its init (beyond the initial view's margin): run's depth map is
    export-depth's at that pose, border included (refine is skipped: its pose file is given)."""
    import cv2 as _cv2

    from rgbd_gt.io import write_pose

    scene = tmp_path / "scene"
    synth_scene(scene, 2)
    gt = read_pose(scene / "gt_pose.yaml")[0]
    turn = np.eye(4)
    turn[:3, :3] = _cv2.Rodrigues(np.radians([0.0, 4.0, 0.0]))[0]
    write_pose(tmp_path / "out" / "photo" / "init.yaml", turn @ gt)
    write_pose(tmp_path / "out" / "photo" / "pose.yaml", gt)
    config = {"scan": "scene/scan.e57", "camera": "scene/camera.yaml", "photos": ["scene/photo.png"], "output": "out"}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    proc = run_cli("run", tmp_path / "run.yaml")
    assert proc.returncode == 0, proc.stderr
    assert run_cli("export-depth", "--scan", scene / "scan.e57", "--camera", scene / "camera.yaml", "--pose",
                   scene / "gt_pose.yaml", "-o", tmp_path / "alone.exr").returncode == 0
    z, alone = read_depth_exr(tmp_path / "out" / "photo" / "depth.exr")[0], read_depth_exr(tmp_path / "alone.exr")[0]
    assert (alone > 0).mean() > 0.5
    np.testing.assert_allclose(z, alone, atol=1e-4)


def test_local_workers_size_their_thread_pools(monkeypatch):
    """Local workers start with OpenMP and BLAS pools of their share of the cores (a user's own
    setting wins), and the run's own environment is left as it was."""
    from rgbd_gt.engine import _thread_pools_of

    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setenv("MKL_NUM_THREADS", "3")
    child = [sys.executable, "-c", "import os; print(os.environ.get('OMP_NUM_THREADS'), os.environ.get('OPENBLAS_NUM_THREADS'), "
             "os.environ.get('MKL_NUM_THREADS'))"]
    with _thread_pools_of(1):
        assert subprocess.run(child, capture_output=True, text=True).stdout.split() == ["1", "1", "3"]
    assert "OMP_NUM_THREADS" not in os.environ and os.environ["MKL_NUM_THREADS"] == "3"
