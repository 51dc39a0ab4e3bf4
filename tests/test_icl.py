"""The aligner and the benchmark's cases on the real ICL-NUIM frames."""

import sys
import subprocess

import numpy as np

from rgbd_gt.align.config import RefineConfig
from rgbd_gt.align.refine import RefineInputs, run_refine
from benchmarks.icl import ICL_CAMERA, frame_cloud, make_cases, read_depth, read_trajectory
from rgbd_gt.pose import invert, rotation_error_deg, transform_points, translation_error_m


def test_icl_frames_are_consistent(icl_dir):
    """The loader's conventions: frame 0's clean cloud lands on frame 1's clean depth."""
    pts, _, _ = frame_cloud(icl_dir, 0, "clean")
    T1 = invert(read_trajectory(icl_dir / "trajectory.log")[1])
    p = transform_points(T1, pts)
    u = np.round(ICL_CAMERA.fx * p[:, 0] / p[:, 2] + ICL_CAMERA.cx).astype(int)
    v = np.round(ICL_CAMERA.fy * p[:, 1] / p[:, 2] + ICL_CAMERA.cy).astype(int)
    ok = (u >= 0) & (v >= 0) & (u < 640) & (v < 480)
    d1 = read_depth(icl_dir, 1, "clean")[v[ok], u[ok]]
    diff = np.abs(d1 - p[ok, 2])[d1 > 0]
    assert np.median(diff) < 0.002


def test_refine_one_icl_pair(icl_dir):
    case = make_cases(icl_dir, offsets=(1,), effects_per_pair=1, seed=5)[2]
    inputs = RefineInputs(case.points, case.colors, case.photo, ICL_CAMERA, case.T_init, None)
    res = run_refine(inputs, RefineConfig(), "cpu")
    assert translation_error_m(case.T_init, case.T_true) > 0.02
    assert translation_error_m(res.T_cam_from_scan, case.T_true) < 1e-3
    assert rotation_error_deg(res.T_cam_from_scan, case.T_true) < 0.02


def test_refine_path_does_not_import_open3d():
    """The refine command needs torch and OpenCV only (Open3D costs seconds to import)."""
    code = ("import sys, rgbd_gt.cli, rgbd_gt.config, rgbd_gt.align.refine, rgbd_gt.align.aligner, "
            "rgbd_gt.align.pyramid, rgbd_gt.align.report, rgbd_gt.io, rgbd_gt.io.image, rgbd_gt.io.e57, rgbd_gt.io.ply; "
            "print('open3d' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.stdout.strip() == "False", proc.stderr


def test_bench_quick(icl_dir, tmp_path):
    from conftest import ROOT

    proc = subprocess.run([sys.executable, "-m", "benchmarks.icl_bench", "--quick", "--data", icl_dir, "--out", tmp_path],
                          capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    text = (tmp_path / "benchmark.md").read_text()
    assert "| quadratic (ours) |" in text and "| SIFT |" in text
    assert (tmp_path / "benchmark_cumulative.png").stat().st_size > 10_000
    ours = [line for line in text.splitlines() if line.startswith("| quadratic (ours) |")][0].split("|")
    assert ours[4].strip() == "100%"  # i±1 success
    floor = text.split("## What the data costs at i±3")[1]
    rows = [line.split("|") for line in floor.splitlines() if line.startswith(("| noisy", "| clean"))]
    assert len(rows) == 2 and all(float(r[2]) < 1.5 and float(r[3]) < 0.05 for r in rows)


def test_cases_without_effects_use_the_photo_and_depth_asked_for(icl_dir):
    cases = make_cases(icl_dir, offsets=(3,), effects=False, depth="clean")
    assert [c.name for c in cases] == ["0->3#0", "1->4#0", "3->0#0", "4->1#0"]
    from benchmarks.icl import read_color

    assert np.array_equal(cases[0].photo, read_color(icl_dir, 3)) and cases[0].effects == {}
    pts, _, _ = frame_cloud(icl_dir, 0, "clean")
    assert np.array_equal(cases[0].points, pts)
