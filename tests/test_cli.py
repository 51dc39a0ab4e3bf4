import dataclasses

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from rgbd_gt.cli import app
from rgbd_gt.io import load_scan, save_scan

import typer


def test_help_and_version():
    proc = run_cli("--help", fresh=True)  # a fresh interpreter: nothing printed on the way in
    assert proc.returncode == 0 and "ingest" in proc.stdout and proc.stderr == ""
    proc = run_cli("--version")
    assert proc.returncode == 0 and proc.stdout.startswith("rgbd-gt ")
    for cmd in typer.main.get_command(app).commands:
        proc = run_cli(cmd, "--help")
        assert proc.returncode == 0 and "Usage" in proc.stdout, cmd


def test_ingest_pump_scan(e57_dir, tmp_path):
    out = tmp_path / "pump.ply"
    proc = run_cli("ingest", e57_dir / "pumpA.e57", "-o", out, "--extract-images", tmp_path / "img")
    assert proc.returncode == 0, proc.stderr
    assert "155,201" in proc.stdout and "pumpVisual" in proc.stdout
    back, orig = load_scan(out), load_scan(e57_dir / "pumpA.e57")
    assert back.fields == orig.fields
    np.testing.assert_allclose(back.xyz, orig.xyz, atol=1e-6)
    assert np.array_equal(back.rgb, orig.rgb) and np.array_equal(back.row, orig.row)
    import cv2

    jpg = tmp_path / "img" / "pumpA_0_pumpVisual.jpg"
    assert cv2.imread(str(jpg)).shape == (2304, 3072, 3)
    assert (tmp_path / "img" / "pumpA_images.yaml").exists()
    assert not [p for p in tmp_path.rglob(".*tmp*")]  # no temporary files left behind


def test_ingest_crop_voxel_and_merge(e57_dir, tmp_path):
    merged, small = tmp_path / "m.ply", tmp_path / "s.ply"
    proc = run_cli("ingest", e57_dir / "pumpA.e57", e57_dir / "pipeSpherical.e57", "-o", merged, "--crop=-2,-5.5,-2,0,-1,2")
    assert proc.returncode == 0, proc.stderr
    m = load_scan(merged)
    assert np.all(m.xyz >= [-2, -5.5, -2]) and np.all(m.xyz <= [0, -1, 2])
    assert np.bincount(m.scan_id)[1] == 1220  # the whole pipe lies inside the box
    assert m.row is None  # the pipe file has no grid, so the merge has none

    assert run_cli("ingest", merged, "-o", small, "--voxel", "0.02").returncode == 0
    s = load_scan(small)
    assert s.fields == ["xyz", "rgb", "intensity", "scan_id"]
    assert 0.1 * len(m) < len(s) < 0.5 * len(m)
    keys = np.floor((s.xyz - m.xyz.min(0)) / 0.02).astype(int)
    assert len(np.unique(keys, axis=0)) == len(s)  # one point per voxel


def test_ingest_spherical_pinhole_camera_file(e57_dir, tmp_path):
    proc = run_cli("ingest", e57_dir / "tiny_pc_and_images.e57", "-o", tmp_path / "t.ply", "--extract-images", tmp_path / "i")
    assert proc.returncode == 0, proc.stderr
    from rgbd_gt.io import read_camera

    cam = read_camera(tmp_path / "i" / "tiny_pc_and_images_2_pinhole.camera.yaml")
    assert cam.size == (100, 100) and cam.fx == pytest.approx(123 / 0.044) and cam.cx == 23


def test_ingest_bad_inputs(e57_dir, tmp_path):
    assert_one_line_error(run_cli("ingest", tmp_path / "nope.e57", "-o", tmp_path / "o.ply"), "nope.e57", "not found")
    assert_one_line_error(run_cli("ingest", tmp_path, "-o", tmp_path / "o.ply"), str(tmp_path), "is a folder, not a file")
    assert_one_line_error(run_cli("ingest", e57_dir / "pumpA.e57", "-o", tmp_path / "o.ply", "--crop", "1,2,3"), "--crop")
    assert_one_line_error(run_cli("ingest", e57_dir / "pumpA.e57", "-o", tmp_path / "o.ply", "--crop", "5,5,5,6,6,6"), "no points")
    assert_one_line_error(run_cli("ingest", e57_dir / "pumpA.e57", "-o", tmp_path / "o.txt"), ".ply")
    (tmp_path / "notes.xyz").write_text("1 2 3\n")
    assert_one_line_error(run_cli("ingest", tmp_path / "notes.xyz", "-o", tmp_path / "o.ply"), "unknown scan format")
    (tmp_path / "none.pcd").write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 0\nHEIGHT 1\n"
                                       "POINTS 0\nDATA ascii\n")
    assert_one_line_error(run_cli("ingest", tmp_path / "none.pcd", "-o", tmp_path / "o.ply"), "none.pcd", "no points")
    # an option that would do nothing is a mistake, said (beside an E57 it selects that file's scan)
    assert_one_line_error(run_cli("ingest", tmp_path / "none.pcd", "-o", tmp_path / "o.ply", "--scan-index", 1),
                          "--scan-index applies to E57 files only")
    # one empty file among others is refused too (merged, it would have dropped their colors)
    proc = run_cli("ingest", e57_dir / "bunnyDouble.e57", tmp_path / "none.pcd", "-o", tmp_path / "o.ply")
    assert_one_line_error(proc, "none.pcd", "no points")
    assert not (tmp_path / "o.ply").exists()


def test_ingest_says_which_fields_a_merge_drops(e57_dir, tmp_path):
    scan = load_scan(e57_dir / "pipeSpherical.e57")
    save_scan(tmp_path / "bare.ply", dataclasses.replace(scan, rgb=None, intensity=None))
    proc = run_cli("ingest", e57_dir / "pipeSpherical.e57", tmp_path / "bare.ply", "-o", tmp_path / "o.ply")
    assert proc.returncode == 0, proc.stderr
    kept = load_scan(tmp_path / "o.ply")
    assert kept.rgb is None and kept.intensity is None and len(kept) == 2 * len(scan)
    for word in ("colors", "intensity"):
        assert f"warning: {word} dropped from the merged scan: bare.ply has none" in proc.stderr


def test_ingest_never_overwrites_its_input(e57_dir, tmp_path):
    src = tmp_path / "in.ply"
    assert run_cli("ingest", e57_dir / "bunnyDouble.e57", "-o", src).returncode == 0
    before = src.read_bytes()
    assert_one_line_error(run_cli("ingest", src, "-o", src), "overwrite")
    assert src.read_bytes() == before


def test_debug_shows_traceback(tmp_path):
    proc = run_cli("--debug", "ingest", tmp_path / "nope.e57", "-o", tmp_path / "o.ply")
    assert proc.returncode != 0 and "Traceback" in proc.stderr


def test_empty_arguments(tmp_path):
    """An empty value (an unset shell variable) is named as empty; a path option took it as '.',
    the current folder ("--before: is a folder, not a file")."""
    ply = tmp_path / "s.ply"
    for args, said in ((("qa-edges", "--before", ""), "error: --before: empty (an unset shell variable?)"),
                       (("ingest", ply, "--output="), "error: --output: empty"),
                       (("export", "", "-o", tmp_path / "x"), "error: the argument after 'export': empty"),
                       # '' after a flag is not the flag's value
                       (("refine", "--strict", ""), "error: the argument after '--strict': empty")):
        proc = run_cli(*args)
        assert_one_line_error(proc, said)
    # fuzz seed 30: an option the command does not have, given '', said "--port: empty"
    proc = run_cli("ingest", ply, "--port", "")
    assert proc.returncode == 2 and "No such option: --port" in proc.stderr and "empty" not in proc.stderr
    assert not (tmp_path / "x").exists()
