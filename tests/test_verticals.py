"""rgbd_gt.qa.verticals: how upright a pose holds a photo, against exact synthetic truth and on the
real PJLab scenes (docs/lidar-method.md, "What the vertical lines say about the references")."""

import cv2
import numpy as np
import pytest

from rgbd_gt.qa.verticals import photo_segments, residuals_deg, roll_deg, scan_vertical, verticals_qa
from rgbd_gt.camera import Camera

K = np.array([[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]])
LEVEL = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])  # camera from world: looking along +x, z up


def _turn(axis, deg):
    return cv2.Rodrigues(np.asarray(axis, float) * np.radians(deg))[0]


def _pole_segments(R, rng, count=30):
    """Segments of vertical poles 5-30 m ahead, seen with camera rotation R."""
    foot = np.c_[rng.uniform(5, 30, count), rng.uniform(-8, 8, count), rng.uniform(-1.5, -1, count)]
    seg = []
    for a in foot:
        uv = [(K @ (R @ p))[:2] / (K @ (R @ p))[2] for p in (a, a + [0, 0, 3.0])]
        seg.append(np.r_[uv[0], uv[1]])
    return np.array(seg)


def test_roll_of_vertical_poles():
    rng = np.random.default_rng(3)
    R = _turn([0, 1, 0], 2.0) @ LEVEL  # a little pitched, upright
    seg = _pole_segments(R, rng)
    up = np.array([0, 0, 1.0])
    assert np.abs(residuals_deg(seg, K, R, up)).max() < 1e-6
    for roll in (-1.5, 0.4, 2.0):
        tilted = _turn([0, 0, 1], roll) @ R  # rolled about the optical axis
        assert roll_deg(seg, K, tilted, up) == pytest.approx(-roll, abs=1e-3)
    assert roll_deg(seg[:, [2, 3, 0, 1]], K, R, up) == pytest.approx(0, abs=1e-6)  # either end first


def test_segments_of_a_photo_and_the_vertical_of_a_sweep():
    image = np.full((480, 640, 3), 230, np.uint8)
    for x in (100, 250, 400, 550):  # dark bars leaning 3 deg, and a horizontal one
        top, bottom = (x + int(round(300 * np.tan(np.radians(3)))), 60), (x, 360)
        cv2.line(image, top, bottom, (20, 20, 20), 9)
    cv2.line(image, (50, 420), (600, 420), (20, 20, 20), 9)
    seg = photo_segments(image, Camera(640, 480, 500, 500, 320, 240))
    d = seg[:, 2:] - seg[:, :2]
    lean = np.degrees(np.arctan2(np.abs(d[:, 0]), np.abs(d[:, 1])))
    assert len(seg) >= 4 and np.all(np.abs(lean - 3) < 0.5), (seg, lean)

    rng = np.random.default_rng(0)
    true_up = _turn([1, 0, 0], 0.7) @ np.array([0, 0, 1.0])
    poles = [np.array([x, y, -1.8]) + np.outer(rng.uniform(0, 4, 40), true_up) + rng.normal(0, 0.01, (40, 3))
             for x, y in rng.uniform(-25, 25, (12, 2))]
    ground = np.c_[rng.uniform(-30, 30, (20000, 2)), rng.normal(-1.8, 0.02, 20000)]
    up, dirs = scan_vertical(np.concatenate(poles + [ground]), np.zeros(3))
    assert len(dirs) >= 10
    assert np.degrees(np.arccos(np.clip(up @ true_up, -1, 1))) < 0.1


def test_the_real_scenes_references_held_upright():
    """pjlab_3's reference holds its photo upright to a few tenths of a degree; the reference that
    pjlab_2 shares with pjlab_1 is rolled by more than a degree against its photo's poles and
    traffic lights (which is why no objective can land within 0.2 deg of it there)."""
    from conftest import _need
    from rgbd_gt.io import read_camera, read_pose
    from rgbd_gt.io.image import read_image
    from rgbd_gt.io.pcd import read_pcd

    rolls = {}
    for scene, photo in (("pjlab_2", "calib.jpg"), ("pjlab_3", "calib.png")):
        folder = _need("lidar_camera") / scene
        image = read_image(folder / photo)
        camera = read_camera(folder / "calib.txt", (image.shape[1], image.shape[0]))
        points, T = read_pcd(folder / "calib.pcd").xyz, read_pose(folder / "calib.txt")[0]
        up, dirs = scan_vertical(points, np.zeros(3))
        assert len(dirs) > 50 and np.degrees(np.arccos(up[2])) < 0.5  # the sensor stands upright
        rolls[scene] = verticals_qa(points, image, camera, [T])[0]
    assert abs(rolls["pjlab_3"].roll) < 0.4 and rolls["pjlab_3"].low < 0.15, rolls
    assert rolls["pjlab_2"].high < -1.0, rolls
    # where the column grid's borders fall does not decide it (one grid at the camera: up to 0.3 deg)
    shift = np.array([0.1, 0.03, 0.0])
    moved = T.copy()
    moved[:3, 3] -= T[:3, :3] @ shift
    assert abs(verticals_qa(points + shift, image, camera, [moved])[0].roll - rolls["pjlab_3"].roll) < 0.15
    assert "off the scan's vertical" in rolls["pjlab_2"].summary()
    few = verticals_qa(points[:100], image, camera, [T])[0]  # no poles among 100 points: says nothing
    assert not few.usable and np.isnan(few.roll) and "says nothing" in few.summary()
