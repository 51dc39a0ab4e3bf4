"""refine --refine-intrinsics: a camera file whose focal is 2% off no longer drags the pose away."""

import numpy as np
import pytest
import torch
import yaml

from conftest import assert_one_line_error, run_cli
from rgbd_gt.io import read_camera, read_pose
from rgbd_gt.pose import rotation_error_deg, translation_error_m
from rgbd_gt.render.project import corrected_jacobian, project_corrected


def test_corrected_projection_jacobian():
    """The analytic Jacobian of the corrected projection (the full OpenCV model) against finite
    differences, and the model against OpenCV's own projection."""
    from rgbd_gt.pose import apply_update

    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-1, 1, (50, 2)), rng.uniform(2, 4, 50)]
    K = torch.tensor([[500.0, 0, 320], [0, 510.0, 240], [0, 0, 1]], dtype=torch.float64)
    q = torch.tensor([0.01, 0.002, -0.003, -0.05, 0.01, 0.002, -0.003, 0.004], dtype=torch.float64)
    du, dv = corrected_jacobian(torch.as_tensor(p), K, q, 8)
    h = 1e-6
    for k in range(14):
        e = np.zeros(14)
        e[k] = h
        moved = []
        for s in (1, -1):
            T = apply_update(np.eye(4), s * e[:6])
            pk = torch.as_tensor(p @ T[:3, :3].T + T[:3, 3])
            moved.append(project_corrected(pk, K, q + s * torch.as_tensor(e[6:]))[0])
        num = (moved[0] - moved[1]) / (2 * h)
        torch.testing.assert_close(du[:, k], num[:, 0], rtol=1e-5, atol=1e-4)
        torch.testing.assert_close(dv[:, k], num[:, 1], rtol=1e-5, atol=1e-4)
    import cv2

    Kq = K.numpy().copy()
    Kq[:2, :2] *= 1 + float(q[0])
    Kq[0, 2] += float(K[0, 0] * q[1])
    Kq[1, 2] += float(K[1, 1] * q[2])
    dist = np.array([q[3], q[4], q[5], q[6], q[7]], dtype=np.float64)  # OpenCV: k1 k2 p1 p2 k3
    ours = project_corrected(torch.as_tensor(p), K, q)[0].numpy()
    theirs = cv2.projectPoints(p, np.zeros(3), np.zeros(3), Kq, dist)[0][:, 0]
    np.testing.assert_allclose(ours, theirs, atol=1e-6)


def test_refined_intrinsics_project_through_the_photo_as_taken():
    """With refined intrinsics the photo keeps its distortion and the objective projects through
    the file's distortion plus the corrections: exactly the camera `corrected` writes (on a photo
    undistorted with the file, the corrections were only a first-order model of that camera)."""
    from rgbd_gt.align.config import RefineConfig
    from rgbd_gt.align.photometric import Photometric
    from rgbd_gt.align.pyramid import photo_pyramid
    from rgbd_gt.camera import Camera, corrected, project

    rng = np.random.default_rng(1)
    camera = Camera(640, 480, 500.0, 500.0, 320.0, 240.0, (0.1, -0.05, 0.001, -0.002, 0.01))
    photo = rng.integers(0, 255, (480, 640, 3), dtype=np.uint8)
    p = np.c_[rng.uniform(-1, 1, (200, 2)), rng.uniform(2, 4, 200)]
    q = np.array([0.02, 0.003, -0.002, -0.05, 0.02, 0.0, 0.0, 0.0])
    cfg = RefineConfig(refine_intrinsics="focal+principal+k1k2", levels=1, upsample=1)
    kept = Photometric(p, rng.integers(0, 255, (200, 3), dtype=np.uint8),
                       photo_pyramid(photo, camera, 1, torch.device("cpu"), distorted=True), cfg)
    assert kept.pyramid[0].camera.distortion == camera.distortion and kept.pyramid[0].valid is None
    uv = kept._uv(torch.as_tensor(p, dtype=torch.float32), kept.pyramid[0].K, torch.as_tensor(q, dtype=torch.float32))[0]
    np.testing.assert_allclose(uv.numpy(), project(corrected(camera, q), p)[0], atol=2e-3)
    # a barrel lens's model turns back beyond its fold: points there land on no pixel
    barrel = Camera(640, 480, 500.0, 500.0, 320.0, 240.0, (-0.3, 0.0, 0.0, 0.0, 0.0))
    ghosts = Photometric(p, rng.integers(0, 255, (200, 3), dtype=np.uint8),
                         photo_pyramid(photo, barrel, 1, torch.device("cpu"), distorted=True), cfg)
    far = torch.tensor([[1.5, 0.0, 1.0], [0.2, 0.1, 1.0]])
    uv = ghosts._uv(far, ghosts.pyramid[0].K, None)[0].numpy()
    assert (uv[0] < -1e5).all() and np.allclose(uv[1], project(barrel, far.numpy())[0][1], atol=1e-3)
    # undistorted, the photo's camera is a pinhole and the objective adds the corrections alone
    flat = Photometric(p, rng.integers(0, 255, (200, 3), dtype=np.uint8),
                       photo_pyramid(photo, camera, 1, torch.device("cpu")), cfg)
    assert not flat.pyramid[0].camera.distortion and not flat.distorted


@pytest.fixture(scope="module")
def scene(tmp_path_factory, synth_scene):
    d = tmp_path_factory.mktemp("intr")
    synth_scene(d, 3)
    cam = yaml.safe_load((d / "camera.yaml").read_text())
    cam["fx"] *= 1.02
    cam["fy"] *= 1.02
    (d / "cam_off.yaml").write_text(yaml.safe_dump(cam))
    return d


def _err(path, d):
    T, meta = read_pose(path)
    gt = read_pose(d / "gt_pose.yaml")[0]
    return translation_error_m(T, gt) * 1e3, rotation_error_deg(T, gt), meta


def test_refine_intrinsics_recovers_the_focal(scene, tmp_path):
    d = scene
    args = ["refine", "--scan", d / "scan.ply", "--image", d / "photo.png", "--camera", d / "cam_off.yaml",
            "--init", d / "init_pose.yaml", "--repeats", "0"]
    assert run_cli(*args, "-o", tmp_path / "plain.yaml").returncode == 0
    proc = run_cli(*args, "-o", tmp_path / "intr.yaml", "--refine-intrinsics", "focal", "--camera-out", tmp_path / "cam.yaml")
    assert proc.returncode == 0, proc.stderr
    assert "camera refined" in proc.stdout
    plain_mm, _, _ = _err(tmp_path / "plain.yaml", d)
    mm, deg, meta = _err(tmp_path / "intr.yaml", d)
    truth, refined = read_camera(d / "camera.yaml"), read_camera(tmp_path / "cam.yaml")
    # the pose no longer absorbs the focal (tens of mm without); the focal comes back within 0.3%
    assert plain_mm > 20 and mm < 5 and deg < 0.05, (plain_mm, mm, deg)
    assert abs(refined.fx / truth.fx - 1) < 0.003 and refined.cx == pytest.approx(truth.cx)
    assert meta["intrinsics"]["fx"] == pytest.approx(refined.fx) and meta["intrinsics"]["sigma"]["focal_px"] > 0
    assert meta["refine_intrinsics"] == "focal" and meta["verdict"] in ("ok", "suspect")


def test_refine_intrinsics_errors(scene, tmp_path):
    d = scene
    args = ["refine", "--scan", d / "scan.ply", "--image", d / "photo.png", "--camera", d / "camera.yaml",
            "--init", d / "init_pose.yaml", "-o", tmp_path / "o.yaml"]
    assert_one_line_error(run_cli(*args, "--camera-out", tmp_path / "c.yaml"), "--camera-out", "--refine-intrinsics")
    assert_one_line_error(run_cli(*args, "--refine-intrinsics", "zoom"), "refine_intrinsics")
    assert_one_line_error(run_cli(*args, "--refine-intrinsics", "focal", "--objective", "nid"), "photometric")
    assert_one_line_error(run_cli(*args, "--refine-intrinsics", "focal", "--camera-out", d / "camera.yaml"), "overwrite")
    assert not (tmp_path / "o.yaml").exists() and not (tmp_path / "c.yaml").exists()
