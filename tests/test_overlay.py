"""rgbd-gt overlay: the scan rendered at a pose over the photo, at full resolution, and its points."""

import cv2
import numpy as np
import pytest

from conftest import DATA, assert_one_line_error, run_cli
from rgbd_gt.io import read_pose, write_pose
from rgbd_gt.pose import apply_update


def _agreement(photo: np.ndarray, blend: np.ndarray) -> float:
    """Correlation of the photo's gray with the rendering's where the scan covers the photo:
    the blend is (photo + rendering) / 2, so rendering = 2 blend - photo."""
    p = cv2.cvtColor(photo, cv2.COLOR_BGR2GRAY).astype(float)
    r = 2 * cv2.cvtColor(blend, cv2.COLOR_BGR2GRAY).astype(float) - p
    covered = np.abs(cv2.cvtColor(blend, cv2.COLOR_BGR2GRAY).astype(float) - p) > 0
    return float(np.corrcoef(p[covered], r[covered])[0, 1])


def _dots_agreement(photo: np.ndarray, points: np.ndarray) -> float:
    """Correlation of the photo's gray with the dots' where there are dots: elsewhere the points
    picture is the photo dimmed to 60%."""
    p = cv2.cvtColor(photo, cv2.COLOR_BGR2GRAY).astype(float)
    d = cv2.cvtColor(points, cv2.COLOR_BGR2GRAY).astype(float)
    dimmed = cv2.cvtColor(cv2.convertScaleAbs(photo, alpha=0.6), cv2.COLOR_BGR2GRAY).astype(float)
    drawn = np.abs(d - dimmed) > 2
    return float(np.corrcoef(p[drawn], d[drawn])[0, 1])


def test_overlay_at_the_true_pose_agrees_with_the_photo(tmp_path, synth_scene):
    scene = tmp_path / "scene"
    synth_scene(scene, 4)
    T = read_pose(scene / "gt_pose.yaml")[0]
    write_pose(tmp_path / "off.yaml", apply_update(T, np.r_[0.0, 0.01, 0.0, 0.02, 0.0, 0.0]))  # 0.6 deg, 2 cm
    photo = cv2.imread(str(scene / "photo.png"))
    scores, dots = {}, {}
    for name, pose in (("true", scene / "gt_pose.yaml"), ("off", tmp_path / "off.yaml")):
        proc = run_cli("overlay", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera",
                       scene / "camera.yaml", "--pose", pose, "-o", tmp_path / f"{name}.png", "--points")
        assert proc.returncode == 0, proc.stderr
        checker, blend = cv2.imread(str(tmp_path / f"{name}.png")), cv2.imread(str(tmp_path / f"{name}_blend.png"))
        points = cv2.imread(str(tmp_path / f"{name}_points.png"))
        assert checker.shape == blend.shape == points.shape == photo.shape
        # the checkerboard's photo squares are the photo itself
        assert (checker == photo).all(axis=2).mean() > 0.4
        scores[name] = _agreement(photo, blend)
        dots[name] = _dots_agreement(photo, points)
    assert scores["true"] > 0.8 and scores["true"] > scores["off"] + 0.1, scores
    # the dots are the scan's colors where its points land: like the photo at the true pose only
    assert dots["true"] > 0.8 and dots["true"] > dots["off"] + 0.1, dots
    # a scan without a grid (surfels) gives the same kind of picture
    from rgbd_gt.io import load_scan, save_scan
    from rgbd_gt.scan import Scan

    scan = load_scan(scene / "scan.ply")
    save_scan(tmp_path / "loose.ply", Scan(xyz=scan.xyz, rgb=scan.rgb, origins=scan.origins))
    # (written over the true pose's pictures: its points picture, by default not redrawn for a
    # colored scan, is named as left from an earlier run, not passed off as this one's)
    proc = run_cli("overlay", "--scan", tmp_path / "loose.ply", "--image", scene / "photo.png", "--camera",
                   scene / "camera.yaml", "--pose", scene / "gt_pose.yaml", "-o", tmp_path / "true.png")
    assert proc.returncode == 0, proc.stderr
    assert _agreement(photo, cv2.imread(str(tmp_path / "true_blend.png"))) > 0.7
    assert "true_points.png is left from an earlier run" in proc.stderr, proc.stderr


def test_overlay_errors(tmp_path, synth_scene):
    scene = tmp_path / "scene"
    synth_scene(scene, 5)
    args = ["overlay", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera", scene / "camera.yaml"]
    T = read_pose(scene / "gt_pose.yaml")[0]
    away = T.copy()
    away[:3, :3] = away[:3, :3] @ np.diag([-1.0, 1.0, -1.0])  # looking the other way,
    away[2, 3] -= 100.0  # from 100 m beyond the scene (from where it stood, a wall's front edge was in view)
    write_pose(tmp_path / "away.yaml", away)
    assert_one_line_error(run_cli(*args, "--pose", tmp_path / "away.yaml", "-o", tmp_path / "o.png"), "away.yaml", "no scan surface")
    assert_one_line_error(run_cli(*args, "--pose", scene / "gt_pose.yaml", "-o", tmp_path / "o.jpg"), "o.jpg", ".png")
    assert_one_line_error(run_cli(*args, "--pose", scene / "gt_pose.yaml", "-o", scene / "photo.png"), "overwrite")
    assert not list(tmp_path.glob("o*"))


def test_overlay_of_a_real_lidar_sweep_draws_its_visible_points(tmp_path):
    """A sparse sweep (pjlab_3) at its reference pose: the points picture shows the sweep's rings
    as dots colored by intensity over the dimmed photo."""
    folder = DATA / "lidar_camera" / "pjlab_3"
    if not folder.exists():
        pytest.skip(f"real test data not found at {folder}")
    from rgbd_gt.io import load_scan, read_camera
    from rgbd_gt.io.image import read_image
    from rgbd_gt.qa.overlay import points_image
    from rgbd_gt.render.normals import with_normals
    from rgbd_gt.render.renders import Renders

    photo = read_image(folder / "calib.png")
    camera = read_camera(folder / "calib.txt", (photo.shape[1], photo.shape[0]))
    scan = with_normals(load_scan(folder / "calib.pcd"))
    T = read_pose(folder / "calib.txt")[0]
    img, drawn = points_image(Renders(scan), photo, camera, T)
    assert img.shape == photo.shape
    assert 5_000 < drawn < 12_000, drawn  # about 10.5k points fall inside the photo; some are hidden
    changed = (img != cv2.convertScaleAbs(photo, alpha=0.6)).any(axis=2)
    assert 0.01 < changed.mean() < 0.1, changed.mean()  # 3x3 dots, overlapping where rings are dense
    # intensities span the colormap: both blue (low) and red (high) dots
    dots = img[changed].astype(int)
    assert ((dots[:, 2] > dots[:, 0] + 60).mean() > 0.01) and ((dots[:, 0] > dots[:, 2] + 60).mean() > 0.01)
    # beyond --max-depth nothing is drawn
    assert points_image(Renders(scan), photo, camera, T, max_depth=10.0)[1] < drawn / 2


def test_dots_cover_their_squares_and_the_nearest_point_wins():
    from rgbd_gt.render.points import dot_pixels

    # a far point at (5, 5) and a near one at (6, 5): their 3x3 squares share 6 pixels; one at the
    # corner (0, 0) keeps only the 4 pixels of its square inside the 10 x 8 image
    uv = np.array([[5.2, 4.9], [6.0, 5.0], [0.0, 0.0]])
    key, owner = dot_pixels(uv, np.array([20.0, 5.0, 1.0]), (10, 8), 1)
    assert len(key) == len(np.unique(key)) == 9 + 3 + 4
    got = dict(zip(key.tolist(), owner.tolist()))
    assert all(got[y * 10 + x] == 1 for y in (4, 5, 6) for x in (5, 6, 7))  # the shared ones are the near point's
    assert all(got[y * 10 + 4] == 0 for y in (4, 5, 6))
    assert sorted(k for k, o in got.items() if o == 2) == [0, 1, 10, 11]
