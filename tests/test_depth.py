"""export-depth: the file format, and depth against ICL-NUIM's ground truth."""

import dataclasses

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from rgbd_gt.bench.depth import depth_errors, frame_grid_scan, seen_by_both
from rgbd_gt.bench.icl import ICL_CAMERA, read_depth, read_trajectory
from rgbd_gt.io import read_pose, save_scan, write_camera, write_pose
from rgbd_gt.io.depth_file import read_depth_exr
from rgbd_gt.pose import invert
from rgbd_gt.render.depth import render_depth


def test_icl_grid_depth_meets_the_figures(icl_dir):
    r = depth_errors(icl_dir, 0, 1)
    assert r["median_abs_error_m"] < 0.002
    assert r["leak_fraction"] < 0.005
    assert r["filled_fraction"] > 0.95


def test_unstructured_scan_is_rendered_as_surfels(icl_dir):
    """Without its grid the frame-0 cloud renders as surfels at frame 1's pose: depth from each
    point's tangent plane (median 0.3 mm measured, docs/depth_benchmark.md), few leaks."""
    scan = dataclasses.replace(frame_grid_scan(icl_dir, 0), row=None, col=None)
    out = render_depth(scan, ICL_CAMERA, invert(read_trajectory(icl_dir / "trajectory.log")[1]))
    assert out.method.startswith("surfels")
    both = seen_by_both(icl_dir, 0, 1)
    truth = read_depth(icl_dir, 1, "clean")
    filled = both & (out.z > 0)
    assert filled.sum() > 0.95 * both.sum()
    err = np.abs(out.z[filled] - truth[filled])
    assert np.median(err) < 0.002 and np.mean(err > 0.05) < 0.01


@pytest.fixture
def icl_files(icl_dir, tmp_path):
    save_scan(tmp_path / "scan.ply", frame_grid_scan(icl_dir, 0))
    write_camera(tmp_path / "camera.yaml", ICL_CAMERA)
    write_pose(tmp_path / "pose.yaml", invert(read_trajectory(icl_dir / "trajectory.log")[1]))
    return tmp_path


def test_export_depth_files(icl_dir, icl_files):
    d = icl_files
    proc = run_cli("export-depth", "--scan", d / "scan.ply", "--camera", d / "camera.yaml", "--pose", d / "pose.yaml",
                   "-o", d / "depth.exr", "--png16", d / "depth.png", "--normals", d / "normals.exr", "--mask", d / "valid.png")
    assert proc.returncode == 0, proc.stderr
    z, header = read_depth_exr(d / "depth.exr")
    assert z.shape == (480, 640) and z.dtype == np.float32
    T, _ = read_pose(d / "pose.yaml")
    np.testing.assert_allclose(header["rgbd_gt_T_cam_from_scan"], T)
    np.testing.assert_allclose(header["rgbd_gt_K"], ICL_CAMERA.K)
    assert header["rgbd_gt_scan"] == "scan.ply"
    direct = render_depth(frame_grid_scan(icl_dir, 0), ICL_CAMERA, T).z
    np.testing.assert_allclose(z, direct, atol=1e-6)
    import cv2

    png = cv2.imread(str(d / "depth.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16
    np.testing.assert_allclose(png / 1000.0, z, atol=0.0006)
    assert ((cv2.imread(str(d / "valid.png"), cv2.IMREAD_GRAYSCALE) > 0) == (z > 0)).all()
    import OpenEXR

    with OpenEXR.File(str(d / "normals.exr")) as f:
        ch = f.channels()
        n = np.stack([ch["N.X"].pixels, ch["N.Y"].pixels, ch["N.Z"].pixels], -1)
    valid = z > 0
    np.testing.assert_allclose(np.linalg.norm(n[valid], axis=1), 1, atol=1e-4)
    from rgbd_gt.render.depth import pixel_rays

    rays = pixel_rays(ICL_CAMERA).reshape(480, 640, 3)
    assert np.all(np.sum(n[valid] * rays[valid], axis=1) <= 1e-6)  # they face the camera


def test_export_depth_errors(icl_files):
    d = icl_files
    away = np.diag([-1.0, 1, -1, 1]) @ read_pose(d / "pose.yaml")[0]
    write_pose(d / "away.yaml", away)
    args = ["--scan", d / "scan.ply", "--camera", d / "camera.yaml", "-o", d / "o.exr"]
    assert_one_line_error(run_cli("export-depth", *args, "--pose", d / "away.yaml"), "away.yaml", "no scan points in view")
    assert_one_line_error(run_cli("export-depth", *args, "--pose", d / "missing.yaml"), "missing.yaml", "not found")
    assert_one_line_error(run_cli("export-depth", "--scan", d / "scan.ply", "--camera", d / "camera.yaml",
                                  "--pose", d / "pose.yaml", "-o", d / "o.png"), ".exr")
    assert not (d / "o.exr").exists()
