"""The classes of bad input the fuzzing run of issue 14 found, one case each: usage errors,
outputs checked before work and committed together, values checked at the readers and in the
configs, sizes checked against the file, degenerate geometry stopped before the solvers."""

import struct

import numpy as np
import pytest
import yaml

from conftest import assert_one_line_error, run_cli
from benchmarks.fuzz import crc32c
from rgbd_gt.errors import InputError
from rgbd_gt.io.ply import write_ply
from rgbd_gt.scan import Scan
from rgbd_gt.synth.generate import SynthConfig, generate


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("scene")
    generate(d, 5, "small", SynthConfig())
    return d


def _files(folder):
    return sorted(p.relative_to(folder) for p in folder.rglob("*"))


@pytest.mark.parametrize("args,needle", [
    (["bogus"], "No such command"),
    (["refine", "--levels", "abc"], "--levels"),
    (["ingest", "--no-such-option"], "No such option"),
    (["export-depth"], "Missing option"),
])
def test_usage_errors_are_clicks_message(args, needle):
    proc = run_cli(*args)
    assert proc.returncode == 2, proc.stderr
    assert "Usage:" in proc.stderr and needle in proc.stderr
    assert "Traceback" not in proc.stderr


def test_outputs_are_checked_before_work_and_committed_together(scene, tmp_path):
    base = ["--scan", scene / "scan.ply", "--camera", scene / "camera.yaml", "--pose", scene / "gt_pose.yaml"]
    (tmp_path / "a_file").write_text("x")
    # the second output is unusable: the first is not written either
    assert_one_line_error(run_cli("export-depth", *base, "-o", tmp_path / "d.exr", "--png16", tmp_path / "a_file" / "d.png"),
                          "--png16", "is a file")
    assert _files(tmp_path) == [tmp_path.joinpath("a_file").relative_to(tmp_path)]
    # one output may not overwrite another, nor an input
    assert_one_line_error(run_cli("export-depth", *base, "-o", tmp_path / "d.exr", "--png16", tmp_path / "d.png",
                                  "--mask", tmp_path / "d.png"), "--mask", "two outputs")
    qa = ["qa-edges", *base, "--image", scene / "photo.png"]
    assert_one_line_error(run_cli(*qa, "-o", tmp_path / "qa.png", "--json", tmp_path / "qa.png"), "--json", "two outputs")
    assert_one_line_error(run_cli(*qa, "-o", tmp_path / "qa.xyz"), "-o", ".png")
    assert_one_line_error(run_cli(*qa, "-o", tmp_path), "is a folder")
    # a folder the file system will not write in, though access() says it may (root, /proc)
    assert_one_line_error(run_cli("export-depth", *base, "-o", "/proc/d.exr"), "-o", "cannot write in /proc")
    assert_one_line_error(run_cli("export-depth", *base, "-o", tmp_path / "d.exr", "--cache", "/proc/cache"),
                          "--cache", "cannot write in /proc")
    config = tmp_path / "refine.yaml"
    config.write_text("levels: 2\n")
    assert_one_line_error(run_cli("refine", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera",
                                  scene / "camera.yaml", "--init", scene / "init_pose.yaml", "--config", config,
                                  "-o", config), "overwrite the input")
    assert config.read_text() == "levels: 2\n"
    # a folder that does not exist is made, at the end, and only when the command succeeds
    far = yaml.safe_load((scene / "gt_pose.yaml").read_text())
    far["T_cam_from_scan"][2][3] -= 500.0  # the scan is now behind the camera
    (tmp_path / "far.yaml").write_text(yaml.safe_dump(far))
    proc = run_cli("export-depth", *base[:4], "--pose", tmp_path / "far.yaml", "-o", tmp_path / "new" / "d.exr")
    assert_one_line_error(proc, "no scan points in view")
    assert not (tmp_path / "new").exists()
    proc = run_cli("export-depth", *base, "-o", tmp_path / "new" / "deeper" / "d.exr", "--mask", tmp_path / "new" / "m.png")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "new" / "deeper" / "d.exr").is_file() and (tmp_path / "new" / "m.png").is_file()
    assert not [p for p in tmp_path.rglob(".rgbd-gt-*")]  # no staging left behind


def test_values_are_checked_where_they_are_read(scene, tmp_path):
    refine = ["refine", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera", scene / "camera.yaml",
              "--init", scene / "init_pose.yaml", "-o", tmp_path / "pose.yaml"]
    for text, needle in [("iterations: five\n", "iterations: expected a whole number"), ("levels: five\n", "levels must be a number or 'auto'"), ("levels: .inf\n", "levels: expected a whole number or a string, got float inf"),
                         ("nu: -1\n", "nu must be positive"),
                         ("beta_max: .nan\n", "beta_max: must be a finite number"), ("verify: [1]\n", "verify: expected a mapping"),
                         ("max_depth: -1\n", "max_depth")]:
        (tmp_path / "c.yaml").write_text(text)
        assert_one_line_error(run_cli(*refine, "--config", tmp_path / "c.yaml"), "c.yaml", needle)
    assert_one_line_error(run_cli(*refine, "--beta-max", "nan"), "--beta-max must be a finite number")
    assert_one_line_error(run_cli(*refine, "--levels", "13"), "levels must be 1..12 or 'auto', got 13", "(options given: --levels 13)")
    (tmp_path / "c.yaml").write_bytes(bytes(range(256)) * 4)
    assert_one_line_error(run_cli(*refine, "--config", tmp_path / "c.yaml"), "invalid YAML")
    # fuzz seed 13: a line removed said only "invalid YAML (while parsing a block mapping)"
    (tmp_path / "c.yaml").write_text("verify:\n  repeats: 2\n folds: 3\n")
    assert_one_line_error(run_cli(*refine, "--config", tmp_path / "c.yaml"), "c.yaml: invalid YAML (line 3: expected <block end>")
    run_cfg = tmp_path / "run.yaml"
    run_cfg.write_text(f"scan: {scene / 'scan.ply'}\ncamera: {scene / 'camera.yaml'}\nphotos: [1]\noutput: null\n")
    assert_one_line_error(run_cli("run", run_cfg), "expected a string")
    # fuzz seed 14: a square of 0 said "... and marker between 0 and square, got 0.0, None"
    for board, needle in (("{square: 0.0}", "board: square must lie between 0 and 10 m, got 0.0"),
                          ("{square: 0.05, marker: 0.06}", "board: marker must lie between 0 and the square (0.05 m), got 0.06")):
        run_cfg.write_text(f"scan: {scene / 'scan.ply'}\ncamera: {scene / 'camera.yaml'}\nphotos: [{scene / 'photo.png'}]\n"
                           f"board: {board}\n")
        assert_one_line_error(run_cli("run", run_cfg), "run.yaml", needle)
    cam = yaml.safe_load((scene / "camera.yaml").read_text())
    for change, needle in [({"fx": 1e12}, "fx must lie between"), ({"distortion": "abc"}, "must be numbers"),
                           ({"distortion": [float("nan")] * 5}, "finite"), ({"width": 640.5}, "width must be a whole")]:
        (tmp_path / "cam.yaml").write_text(yaml.safe_dump({**cam, **change}))
        proc = run_cli("export-depth", "--scan", scene / "scan.ply", "--camera", tmp_path / "cam.yaml", "--pose",
                       scene / "gt_pose.yaml", "-o", tmp_path / "d.exr")
        assert_one_line_error(proc, "cam.yaml", needle)
    (tmp_path / "cam.xml").write_text('<?xml version="1.0"?>\n<opencv_storage>\n<camera_matrix type_id="opencv-matrix">\n<rows>3')
    proc = run_cli("export-depth", "--scan", scene / "scan.ply", "--camera", tmp_path / "cam.xml", "--pose",
                   scene / "gt_pose.yaml", "-o", tmp_path / "d.exr")
    assert_one_line_error(proc, "cam.xml", "OpenCV calibration")
    assert not (tmp_path / "d.exr").exists()


def test_files_are_checked_against_their_length(scene, tmp_path):
    data = (scene / "scan.ply").read_bytes()
    head, body = data.split(b"end_header\n", 1)
    lied = head.replace(b"element vertex", b"element vertex 1000000000000 %") + b"end_header\n" + body[:1000]
    lied = b"\n".join(ln.split(b" %")[0] if b"%" in ln else ln for ln in lied.split(b"\n"))
    (tmp_path / "lied.ply").write_bytes(lied)
    assert_one_line_error(run_cli("ingest", tmp_path / "lied.ply", "-o", tmp_path / "out.ply"), "lied.ply", "truncated")
    # a PNG header claiming 100000 x 100000 pixels
    png = bytearray((scene / "photo.png").read_bytes())
    png[16:24] = struct.pack(">II", 100_000, 100_000)
    (tmp_path / "huge.png").write_bytes(bytes(png))
    proc = run_cli("overlay", "--scan", scene / "scan.ply", "--image", tmp_path / "huge.png", "--camera",
                   scene / "camera.yaml", "--pose", scene / "gt_pose.yaml", "-o", tmp_path / "ov.png")
    assert_one_line_error(proc, "huge.png")
    # a truncated JPEG is not a photo, although OpenCV decodes what it can
    import cv2

    ok, jpg = cv2.imencode(".jpg", cv2.imread(str(scene / "photo.png")))
    (tmp_path / "cut.jpg").write_bytes(jpg.tobytes()[: len(jpg) // 2])
    proc = run_cli("overlay", "--scan", scene / "scan.ply", "--image", tmp_path / "cut.jpg", "--camera",
                   scene / "camera.yaml", "--pose", scene / "gt_pose.yaml", "-o", tmp_path / "ov.png")
    assert_one_line_error(proc, "cut.jpg", "Premature end")
    # a PNG whose first chunk is not IHDR: the decoder's complaint, without its log line's prefix
    from rgbd_gt.io.image import read_image

    png = bytearray((scene / "photo.png").read_bytes())
    png[12:16] = b"IDAT"
    (tmp_path / "ihdr.png").write_bytes(bytes(png))
    with pytest.raises(InputError, match=r"ihdr.png: not a readable image \(IHDR chunk shall be first"):
        read_image(tmp_path / "ihdr.png")
    # one scan id of 2e9 is a label, not 2e9 scans to summarise
    xyz = np.random.default_rng(0).uniform(-1, 1, (1000, 3))
    write_ply(tmp_path / "ids.ply", Scan(xyz, scan_id=np.where(np.arange(1000) < 500, 0, 2_000_000_000).astype(np.int32)))
    proc = run_cli("ingest", tmp_path / "ids.ply", "-o", tmp_path / "merged.ply")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("ids.ply") <= 3


def test_non_finite_and_degenerate_input(scene, tmp_path):
    init = ["init-pose", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera", scene / "camera.yaml",
            "-o", tmp_path / "init.yaml"]
    corners = np.loadtxt(scene / "board_corners.csv", delimiter=",", ndmin=2, skiprows=1)
    bad = corners.copy()
    bad[3, 1] = np.nan
    np.savetxt(tmp_path / "nan.csv", bad, delimiter=",")
    assert_one_line_error(run_cli(*init, "--board-points", tmp_path / "nan.csv"), "nan.csv", "row 4")
    np.savetxt(tmp_path / "same.csv", np.repeat(corners[:1], len(corners), 0), delimiter=",")
    assert_one_line_error(run_cli(*init, "--board-points", tmp_path / "same.csv"), "same.csv", "at one point, not on a board")
    far = corners.copy()
    far[5, 2] = 1e12  # the file names the fault, not PnP later (fuzz seed 10)
    np.savetxt(tmp_path / "far.csv", far, delimiter=",")
    assert_one_line_error(run_cli(*init, "--board-points", tmp_path / "far.csv"), "far.csv", "lie on one line")
    (tmp_path / "empty.csv").write_text("x,y,z\n")  # fuzz seed 17: an empty file had "got 1 values per row"
    assert_one_line_error(run_cli(*init, "--board-points", tmp_path / "empty.csv"), "empty.csv: holds no x,y,z rows")
    # the scan with a non-finite coordinate: ingest does not write it on
    scan_xyz = np.random.default_rng(1).uniform(-1, 1, (100, 3))
    scan_xyz[7, 2] = np.inf
    write_ply(tmp_path / "inf.ply", Scan(scan_xyz))
    assert_one_line_error(run_cli("ingest", tmp_path / "inf.ply", "-o", tmp_path / "out.ply"), "inf.ply", "point 7")
    assert not (tmp_path / "out.ply").exists()
    # 1000 identical points cannot be aligned to
    colors = np.random.default_rng(0).integers(0, 256, (1000, 3), dtype=np.uint8)  # one color is refused first
    write_ply(tmp_path / "same.ply", Scan(np.tile([[0.1, 0.0, 2.0]], (1000, 1)), rgb=colors))
    (tmp_path / "eye.yaml").write_text(yaml.safe_dump({"T_cam_from_scan": np.eye(4).tolist()}))
    proc = run_cli("refine", "--scan", tmp_path / "same.ply", "--image", scene / "photo.png", "--camera",
                   scene / "camera.yaml", "--init", tmp_path / "eye.yaml", "-o", tmp_path / "pose.yaml")
    assert_one_line_error(proc, "pixels")
    assert not (tmp_path / "pose.yaml").exists()


def test_e57_pose_must_be_a_rotation(tmp_path):
    pye57 = pytest.importorskip("pye57")
    xyz = np.random.default_rng(2).uniform(-1, 1, (200, 3))
    e57 = pye57.E57(str(tmp_path / "zero_q.e57"), mode="w")
    e57.write_scan_raw({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2]},
                       rotation=np.zeros(4), translation=np.zeros(3))
    e57.close()
    assert_one_line_error(run_cli("ingest", tmp_path / "zero_q.e57", "-o", tmp_path / "out.ply"), "zero_q.e57", "quaternion")


def test_e57_nan_text_in_pose_is_refused(scene, tmp_path):
    # libE57 reads the text 'nan' as 0; the page keeps a valid checksum, as a writer's bug would
    raw = bytearray((scene / "scan.e57").read_bytes())
    start = raw.index(b"<translation")
    m = __import__("re").compile(rb'<x type="Float">([^<]+)<').search(bytes(raw), start)
    a, b = m.span(1)
    raw[a:b] = b"nan".ljust(b - a)
    page = a - a % 1024
    raw[page + 1020:page + 1024] = struct.pack(">I", crc32c(bytes(raw[page:page + 1020])))
    (tmp_path / "nan.e57").write_bytes(bytes(raw))
    assert_one_line_error(run_cli("ingest", tmp_path / "nan.e57", "-o", tmp_path / "out.ply"), "nan.e57", "'nan'")


def test_picked_scanner_position_is_a_fair_pick():
    # pumpA's picks include the scanner head, seen in the photo, at the scan origin: outside the
    # points' bounding box, inside the scan's (points and scanner positions)
    from rgbd_gt.camera import Camera
    from rgbd_gt.errors import InputError
    from rgbd_gt.init.run import Picks, check_picks

    points = np.random.default_rng(3).uniform([-3, -5, -2], [2, -1, 2], (500, 3))
    picks = Picks(np.array([[100.0, 200.0], [300.0, 50.0]]), np.array([[0.5, -3.0, 0.1], [0.0, 0.0, 0.0]]),
                  ["flange", "scanner head"])
    cam = Camera(640, 480, 500.0, 500.0, 320.0, 240.0, ())
    check_picks(picks, cam, points, "picks.csv", origins=np.zeros((1, 3)))
    with pytest.raises(InputError, match="scanner head"):
        check_picks(picks, cam, points, "picks.csv")
