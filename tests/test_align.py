"""The aligner's parts against their definitions, and the whole refine on a synthetic scene."""

import dataclasses

import numpy as np
import pytest
import torch
import yaml

from conftest import assert_one_line_error, run_cli
from rgbd_gt.align.color_models import ColorModel, fit_transform, fit_with_inliers, unclipped
from rgbd_gt.align.config import RefineConfig
from rgbd_gt.align.pyramid import photo_pyramid, pyramid_levels, upsample_factor
from rgbd_gt.align.refine import run_refine
from rgbd_gt.steps import load_inputs
from rgbd_gt.align.sampling import bilinear, bilinear_with_gradient
from rgbd_gt.camera import Camera
from rgbd_gt.io import load_scan, read_pose, save_scan, write_pose
from rgbd_gt.scan import Scan
from rgbd_gt.pose import rotation_error_deg, translation_error_m
from rgbd_gt.render.project import project_pinhole

torch.set_default_dtype(torch.float64)


def test_direct_gradient_is_the_derivative_of_the_bilinear_interpolant():
    g = torch.Generator().manual_seed(0)
    image = torch.rand(12, 15, 3, generator=g, dtype=torch.float64)
    # stay off the integer grid lines, where the interpolant has kinks
    uv = torch.rand(200, 2, generator=g, dtype=torch.float64) * torch.tensor([12.0, 9.0]) + 1
    uv = uv.floor() + 0.05 + 0.9 * (uv - uv.floor())
    value, du, dv = bilinear_with_gradient(image, uv, "direct")
    h = 1e-6
    fd_u = (bilinear(image, uv + torch.tensor([h, 0])) - bilinear(image, uv - torch.tensor([h, 0]))) / (2 * h)
    fd_v = (bilinear(image, uv + torch.tensor([0, h])) - bilinear(image, uv - torch.tensor([0, h]))) / (2 * h)
    torch.testing.assert_close(du, fd_u, atol=1e-8, rtol=0)
    torch.testing.assert_close(dv, fd_v, atol=1e-8, rtol=0)
    torch.testing.assert_close(value, bilinear(image, uv))


def test_central_gradient_is_the_direct_one_blurred_by_the_box_window():
    """1-D (one image row): g_B(x) = 1/2 * integral_{x-1}^{x+1} g_A = (f(x+1) - f(x-1)) / 2,
    with f the linear interpolant, i.e. g_A convolved with the box of width 2 and height 1/2."""
    g = torch.Generator().manual_seed(1)
    signal = torch.rand(1, 40, 1, generator=g, dtype=torch.float64).expand(2, 40, 1).contiguous()
    x = torch.linspace(1.01, 37.99, 301, dtype=torch.float64)
    uv = torch.stack([x, torch.zeros_like(x)], 1)
    _, g_b, _ = bilinear_with_gradient(signal, uv, "central")
    f = lambda xs: bilinear(signal, torch.stack([xs, torch.zeros_like(xs)], 1))  # noqa: E731
    torch.testing.assert_close(g_b, (f(x + 1) - f(x - 1)) / 2, atol=1e-12, rtol=0)
    # and the same by numerically convolving g_A with the box
    s = torch.linspace(-1, 1, 20001, dtype=torch.float64)
    xs = (x[:, None] + s[None, :]).reshape(-1)
    _, g_a, _ = bilinear_with_gradient(signal, torch.stack([xs, torch.zeros_like(xs)], 1), "direct")
    conv = torch.trapezoid(0.5 * g_a.reshape(len(x), -1), s, dim=1)
    torch.testing.assert_close(g_b[:, 0], conv, atol=2e-4, rtol=0)


def test_enlarged_finest_level_matches_the_photo_and_interpolates_it_better():
    """The enlarged level's camera puts a point on the enlarged pixel that shows the photo there,
    and its bilinear samples follow the smooth image behind the photo more closely."""
    w, h = 64, 48
    scene = lambda u, v: 0.5 + 0.4 * np.sin(0.9 * u + 0.3) * np.cos(0.7 * v - 0.2)  # noqa: E731
    v, u = np.mgrid[0:h, 0:w]
    photo = np.round(np.repeat(scene(u, v)[..., None], 3, 2) * 255).astype(np.uint8)
    cam = Camera(w, h, 60.0, 60.0, 31.5, 23.5)
    pyr = photo_pyramid(photo, cam, 2, torch.device("cpu"), upsample=4)
    assert pyr[0].zoom == 4 and pyr[0].image.shape == (4 * h, 4 * w, 3) and pyr[1].image.shape == (h // 2, w // 2, 3)
    g = torch.Generator().manual_seed(5)
    p = torch.rand(2000, 3, generator=g, dtype=torch.float64) * torch.tensor([1.6, 1.2, 0.0]) - torch.tensor([0.8, 0.6, -2.0])
    uv_big, _ = project_pinhole(p, torch.as_tensor(pyr[0].camera.K))
    uv, _ = project_pinhole(p, torch.as_tensor(cam.K))
    torch.testing.assert_close(pyr[0].to_photo_pixels(uv_big), uv)
    inside = ((uv > 3) & (uv < torch.tensor([w - 4.0, h - 4.0]))).all(1)
    truth = torch.as_tensor(scene(uv[inside, 0].numpy(), uv[inside, 1].numpy()))
    err_big = (bilinear(pyr[0].image.double(), uv_big[inside])[:, 0] - truth).abs().mean()
    err_plain = (bilinear(torch.as_tensor(photo / 255.0), uv[inside])[:, 0] - truth).abs().mean()
    assert err_big < 0.5 * err_plain, (err_big, err_plain)
    assert upsample_factor((640, 480), 4) == 4 and upsample_factor((1920, 1080), 4) == 3
    assert upsample_factor((6000, 4000), 4) == 1 and upsample_factor((640, 480), 1) == 1


def test_color_fit_recovers_a_quadratic_transform_and_ignores_outliers():
    g = torch.Generator().manual_seed(2)
    I = torch.rand(5000, 3, generator=g, dtype=torch.float64)
    model = ColorModel("quadratic")
    K = model.kernel(I)
    assert K.shape == (5000, 10)
    D_true = torch.randn(3, 10, generator=g, dtype=torch.float64) * 0.3
    target = K @ D_true.T
    D, inliers = fit_with_inliers(K, target, beta_max=0.1)
    torch.testing.assert_close(D, D_true, atol=1e-6, rtol=0)
    assert inliers.all()
    noisy = target.clone()
    bad = torch.randperm(5000, generator=g)[:1000]
    noisy[bad] += torch.rand(1000, 3, generator=g, dtype=torch.float64) + 0.5  # 20% gross outliers
    D, inliers = fit_with_inliers(K, noisy, beta_max=0.1)
    torch.testing.assert_close(D, D_true, atol=1e-6, rtol=0)
    assert not inliers[bad].any() and inliers.sum() == 4000
    # the kernels' directional derivatives are right
    h = 1e-6
    direction = torch.randn(5000, 3, generator=g, dtype=torch.float64)
    for name in ("quadratic", "quadratic_rgb", "linear", "none", "gray", "gray_affine"):
        m = ColorModel(name)
        fd = (m.kernel(I + h * direction) - m.kernel(I - h * direction)) / (2 * h)
        torch.testing.assert_close(m.kernel_derivative(I, direction), fd, atol=1e-7, rtol=0)


def test_clipped_photo_colors_are_left_out_of_the_color_fit():
    """An over-exposed photo: the scan colors follow a quadratic transform of the true photo
    colors, but the photo saturates. Fitting on the unclipped samples recovers the transform."""
    g = torch.Generator().manual_seed(3)
    scene = torch.rand(20000, 3, generator=g, dtype=torch.float64)
    model = ColorModel("quadratic")
    D_true = torch.randn(3, 10, generator=g, dtype=torch.float64) * 0.3
    target = model.kernel(scene) @ D_true.T
    photo = torch.round((1.6 * scene).clamp(0, 1) * 255) / 255  # ~80% of the samples clip a channel
    ok = unclipped(photo)
    assert torch.equal(ok, (1.6 * scene < 1 - 0.5 / 255).all(1) & (1.6 * scene > 0.5 / 255).all(1))
    assert 0.1 < ok.double().mean() < 0.3
    D_ok = fit_transform(model.kernel(photo[ok]), target[ok])
    D_all = fit_transform(model.kernel(photo), target)
    err_ok = (model.kernel(photo[ok]) @ D_ok.T - target[ok]).abs().max()
    err_all = (model.kernel(photo[ok]) @ D_all.T - target[ok]).abs().max()
    assert err_ok < 0.005 and err_all > 0.05  # 8-bit rounding only, against a fit bent by the clipped samples


def test_coarse_levels_blur_the_scan_colors_as_the_pyramid_blurs_the_photo():
    """Points on every pixel centre of an image: their targets on pyramid level 2 at that level's
    pixel centres are the level's own pixels (4x4 box averages), and between them its bilinear
    interpolant, as the photo's samples are."""
    import cv2

    from rgbd_gt.align.photometric import blurred_targets, pixel_sums
    from rgbd_gt.align.sampling import bilinear_sparse

    rng = np.random.default_rng(3)
    image = rng.random((48, 64, 3))
    v, u = np.mgrid[0:48, 0:64]
    uv = torch.as_tensor(np.stack([u.ravel(), v.ravel()], 1), dtype=torch.float64)
    cells = pixel_sums(uv * 0.25 - 0.375, torch.as_tensor(image.reshape(-1, 3)), (16, 12))  # level 2's pixels
    assert cells[0].numel() == 16 * 12 and torch.all(cells[1][:, 3] == 16)
    expected = torch.as_tensor(cv2.resize(cv2.resize(image, (32, 24), interpolation=cv2.INTER_AREA), (16, 12),
                                          interpolation=cv2.INTER_AREA))
    v2, u2 = np.mgrid[0:12, 0:16]
    centres = torch.as_tensor(np.stack([u2.ravel(), v2.ravel()], 1), dtype=torch.float64)
    got = blurred_targets(cells, (16, 12), centres, torch.zeros(len(centres), 3))
    torch.testing.assert_close(got, expected.reshape(-1, 3), atol=1e-12, rtol=0)
    between = centres[:40] + torch.tensor([0.3, 0.6], dtype=torch.float64)
    torch.testing.assert_close(blurred_targets(cells, (16, 12), between, torch.zeros(40, 3)), bilinear(expected, between))
    # the sparse sampler equals the dense one where half the pixels are empty
    dense = torch.as_tensor(image) * torch.as_tensor(rng.random((48, 64, 1)) < 0.5)
    keys = torch.nonzero(dense.reshape(-1, 3).abs().sum(1)).squeeze(1)
    at = torch.as_tensor(rng.uniform([0, 0], [63, 47], (300, 2)))
    torch.testing.assert_close(bilinear_sparse(keys, dense.reshape(-1, 3)[keys], (48, 64), at), bilinear(dense, at))


@pytest.fixture(scope="module")
def scene(tmp_path_factory, synth_scene):
    d = tmp_path_factory.mktemp("refine_scene")
    synth_scene(d, 0)
    return d


def _errors(pose_path, scene):
    T, meta = read_pose(pose_path)
    gt, _ = read_pose(scene / "gt_pose.yaml")
    return translation_error_m(T, gt) * 1e3, rotation_error_deg(T, gt), meta


def test_refine_converges_on_a_synthetic_scene(scene, tmp_path):
    out = tmp_path / "pose.yaml"
    proc = run_cli("refine", "--scan", scene / "scan.e57", "--image", scene / "photo.png", "--camera",
                   scene / "camera.yaml", "--init", scene / "init_pose.yaml", "-o", out, "--report", tmp_path / "rep")
    assert proc.returncode == 0, proc.stderr
    mm, deg, meta = _errors(out, scene)
    init_mm, init_deg, _ = _errors(scene / "init_pose.yaml", scene)
    assert init_mm > 15 and init_deg > 0.5
    assert mm < 1.0 and deg < 0.02, (mm, deg)
    assert np.array(meta["color_transform"]).shape == (3, 10)
    for key in ("iterations", "final_loss", "inlier_fraction", "visible_points", "seconds"):
        assert key in meta
    assert meta["visible_points"] > 10_000 and 0.5 < meta["inlier_fraction"] <= 1
    for name in ("convergence.png", "residuals_start.png", "residuals_end.png"):
        assert (tmp_path / "rep" / name).stat().st_size > 1000


@pytest.mark.parametrize("change", [
    {"upsample": 1},
    {"gradient": "central"},
    {"color_model": "linear"},
    {"color_model": "quadratic_rgb"},
    {"fit_sharpness": False},
    {"depth_edge_ratio": 0.1},
])
def test_refine_variants_converge(scene, change):
    inputs = load_inputs(scene / "scan.ply", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml")
    res = run_refine(inputs, dataclasses.replace(RefineConfig(), **change), "cpu")
    gt, _ = read_pose(scene / "gt_pose.yaml")
    assert translation_error_m(res.T_cam_from_scan, gt) < 2e-3
    assert rotation_error_deg(res.T_cam_from_scan, gt) < 0.05


def test_the_color_fit_sharpens_a_blurred_photo_and_blurs_a_sharpened_one(scene):
    """At the true pose the fit's weights on the photo's high pass undo what was done to the photo:
    positive (sharpening) on a photo blurred further, negative on one sharpened, and either way the
    residuals' robust scale is smaller than without them. The pose's Jacobian includes them (the refine from the
    init converges on the blurred photo)."""
    import cv2

    from rgbd_gt.align.aligner import Aligner
    from rgbd_gt.align.photometric import Photometric

    inputs = load_inputs(scene / "scan.ply", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml")
    gt, _ = read_pose(scene / "gt_pose.yaml")
    photo = inputs.photo.astype(np.float32)
    blurred = cv2.GaussianBlur(photo, (0, 0), 1.2)
    sharpened = np.clip(photo + 1.5 * (photo - cv2.GaussianBlur(photo, (0, 0), 1.0)), 0, 255)
    sign = {}
    for name, image in (("blurred", blurred), ("sharpened", sharpened)):
        losses = []
        for fit in (True, False):
            cfg = dataclasses.replace(RefineConfig(), fit_sharpness=fit)
            obj = Photometric(inputs.points, inputs.colors, photo_pyramid(image, inputs.camera, cfg.levels,
                                                                              torch.device("cpu"), upsample=cfg.upsample), cfg)
            aligner = Aligner(obj)
            T = aligner._local(gt)
            obj.prepare(T)
            terms = obj.evaluate(0, [T], aligner._q(None), jacobian=False)
            losses.append(float(terms.sigma2.reshape(-1)[0]))  # the residuals' robust scale
            if fit:
                assert terms.D.shape[2] == 11  # the kernel's 10, then the gray's high pass
                sign[name] = float(terms.D[0][:, 10].mean())
                if name == "blurred":
                    res = aligner.refine(inputs.T_init)
                    assert translation_error_m(res.T_cam_from_scan, gt) < 2e-3
                    assert rotation_error_deg(res.T_cam_from_scan, gt) < 0.05
                    assert res.color_transform.shape == (3, 10)
        assert losses[0] < losses[1], (name, losses)
    assert sign["blurred"] > 0.2 and sign["sharpened"] < -0.1, sign


@pytest.mark.parametrize("objective,max_points", [("photometric", 20_000), ("photometric", 5_000), ("nid", 20_000)])
def test_the_pose_does_not_depend_on_the_order_of_the_points(scene, objective, max_points):
    """`run` reads a scan block by block and `refine` whole: the aligners' random subsets are
    drawn from the points themselves (align/subset.py), so both give the same pose. (5,000
    points: the view's 100k exceed the pool of 16 x max_points drawn before anything else.)"""
    inputs = load_inputs(scene / "scan.ply", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml")
    assert len(inputs.points) > 16 * 5_000
    order = np.random.default_rng(5).permutation(len(inputs.points))
    shuffled = dataclasses.replace(inputs, points=inputs.points[order], colors=inputs.colors[order],
                                   scan=inputs.scan.subset(order))
    cfg = RefineConfig(objective=objective, max_points=max_points, levels=3)
    a, b = (run_refine(i, cfg, "cpu").T_cam_from_scan for i in (inputs, shuffled))
    # float32 sums in another order (up to 10 microns, 0.0002 deg with the 5,000-point subsets):
    # far below what refine resolves (0.1 mm, 0.002 deg here; subsets by an index permutation: 0.12 mm)
    assert translation_error_m(a, b) < 3e-5 and rotation_error_deg(a, b) < 5e-4, (translation_error_m(a, b),
                                                                                rotation_error_deg(a, b))
    other = run_refine(inputs, dataclasses.replace(cfg, seed=1), "cpu").T_cam_from_scan
    assert translation_error_m(a, other) > 1e-6  # the seed does pick other points


def test_auto_levels_keep_the_coarsest_level_40_to_79_px_across():
    assert [pyramid_levels(s) for s in ((640, 480), (1280, 960), (1241, 376), (3072, 2304), (79, 60), (30, 20))] == [5, 6, 5, 7, 1, 1]
    assert pyramid_levels((1280, 960), 3) == 3
    cam = Camera(fx=900.0, fy=900.0, cx=639.5, cy=479.5, width=1280, height=960)
    pyr = photo_pyramid(np.zeros((960, 1280, 3), np.uint8), cam, "auto", torch.device("cpu"))
    assert pyr[-1].camera.size == (40, 30)


def test_a_1280x960_photo_refines_from_a_degree_off(tmp_path):
    """The default-size stereo scene's right camera, 0.85 deg / 32 mm off at its init, refines to
    the truth with the levels the photo's size asks for (6: coarsest 40x30). On this scene's 2-shot
    form (1 deg / 36 mm off) a fixed 5 levels (coarsest 80x60) once ended 126 mm / 1.35 deg off,
    `failed`; the aligner of 2026-12 reaches the truth with 5 as well. One shot: the scene's size
    costs most of this test."""
    from rgbd_gt.config import load_config
    from rgbd_gt.synth.generate import SynthConfig, generate

    generate(tmp_path, 0, "default", load_config(SynthConfig, None, "synth.yaml"), photos=1, rig="stereo")
    inputs = load_inputs(tmp_path / "scan.ply", tmp_path / "right.png", tmp_path / "camera_right.yaml",
                         tmp_path / "init_pose_right.yaml")
    T = run_refine(inputs, RefineConfig(), "cpu").T_cam_from_scan
    gt, _ = read_pose(tmp_path / "gt_pose_right.yaml")
    assert translation_error_m(T, gt) < 3e-3 and rotation_error_deg(T, gt) < 0.03, (translation_error_m(T, gt),
                                                                                    rotation_error_deg(T, gt))


def test_the_coarsest_level_moves_towards_the_truth(tmp_path, synth_scene):
    """The coarsest level (40x30) resolves neither the checkerboard's 15 px squares nor the
    wall's text in seed 3's scene. Against the scan's sharp colors it hardly moved the pose
    (8 point subsets: median 25 mm / 0.36 deg from the init's 30 mm / 0.95 deg; on another init
    of this scene some subsets then ended 108 mm off, docs/intrinsics.md); against colors
    blurred as the level blurs the photo it brings every subset nearer (12 mm / 0.24 deg)."""
    from rgbd_gt.align.refine import make_aligner

    synth_scene(tmp_path, 3)
    inputs = load_inputs(tmp_path / "scan.ply", tmp_path / "photo.png", tmp_path / "camera.yaml", tmp_path / "init_pose.yaml")
    gt, _ = read_pose(tmp_path / "gt_pose.yaml")
    init_mm, init_deg = translation_error_m(inputs.T_init, gt) * 1e3, rotation_error_deg(inputs.T_init, gt)
    coarse = []
    for seed in range(8):
        aligner = make_aligner(inputs, dataclasses.replace(RefineConfig(), seed=seed), "cpu")
        T = aligner.refine(inputs.T_init, coarsest=4, finest=4).T_cam_from_scan
        coarse.append((translation_error_m(T, gt) * 1e3, rotation_error_deg(T, gt)))
        T = aligner.refine(inputs.T_init).T_cam_from_scan
        assert translation_error_m(T, gt) < 1e-3 and rotation_error_deg(T, gt) < 0.02, seed
    mm, deg = np.median(coarse, axis=0)
    assert mm < 0.5 * init_mm and deg < 0.3 * init_deg, (coarse, init_mm, init_deg)


def test_a_big_views_pool_leaves_the_subsets_random(scene):
    """Beyond 16 x max_points the aligner keeps a random pool of the view. The keys that order
    the pool's points into the levels' subsets must still be uniform: the pool drawn as the
    lowest keys of the same stream squeezed them into (0, 0.04) here, and the subsets then
    followed texture alone (the verdict's repeats ended 7-14 px apart on a 7-million-point view)."""
    from rgbd_gt.align.photometric import Photometric
    from rgbd_gt.align.pyramid import photo_pyramid

    inputs = load_inputs(scene / "scan.ply", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml")
    cfg = RefineConfig(max_points=400, levels=3)
    assert len(inputs.points) > 16 * 400 * 10
    objective = Photometric(inputs.points, inputs.colors, photo_pyramid(inputs.photo, inputs.camera, 3, torch.device("cpu")),
                            cfg, inputs.normals)
    keys = np.sort(objective.keys.numpy())
    assert len(keys) == 16 * 400
    uniform = (np.arange(len(keys)) + 0.5) / len(keys)
    assert np.abs(keys - uniform).max() < 0.03  # Kolmogorov-Smirnov: 0.017 at the 1% level for 6,400 keys


def test_adam_moves_towards_the_truth(scene):
    inputs = load_inputs(scene / "scan.ply", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml")
    cfg = dataclasses.replace(RefineConfig(), optimizer="adam", adam_iterations=60, levels=3,
                              adam_lr_rotation=1e-3, adam_lr_translation=2e-3)
    res = run_refine(inputs, cfg, "cpu")
    gt, _ = read_pose(scene / "gt_pose.yaml")
    assert translation_error_m(res.T_cam_from_scan, gt) < 0.25 * translation_error_m(inputs.T_init, gt)
    assert rotation_error_deg(res.T_cam_from_scan, gt) < 0.25 * rotation_error_deg(inputs.T_init, gt)


def test_intensity_only_scan(scene, tmp_path):
    scan = load_scan(scene / "scan.ply")
    save_scan(tmp_path / "gray.ply", dataclasses.replace(scan, rgb=None))
    inputs = load_inputs(tmp_path / "gray.ply", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml")
    assert inputs.colors.shape[1] == 1
    res = run_refine(inputs, RefineConfig(objective="photometric"), "cpu")  # auto would take nid (tests/test_nid.py)
    assert res.color_transform.shape == (1, 10)
    gt, _ = read_pose(scene / "gt_pose.yaml")
    assert translation_error_m(res.T_cam_from_scan, gt) < 3e-3
    assert rotation_error_deg(res.T_cam_from_scan, gt) < 0.1


def test_mask_removes_pixels(scene, tmp_path):
    import cv2

    mask = np.zeros((480, 640), np.uint8)
    mask[:, :320] = 255  # ignore the left half of the photo
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    full = load_inputs(scene / "scan.ply", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml")
    half = load_inputs(scene / "scan.ply", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml",
                       tmp_path / "mask.png")
    r_full, r_half = run_refine(full, RefineConfig(), "cpu"), run_refine(half, RefineConfig(), "cpu")
    assert r_half.visible_points < 0.7 * r_full.visible_points
    gt, _ = read_pose(scene / "gt_pose.yaml")
    assert translation_error_m(r_half.T_cam_from_scan, gt) < 3e-3


def test_refine_bad_inputs(scene, tmp_path):
    args = ["--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera", scene / "camera.yaml",
            "--init", scene / "init_pose.yaml", "-o", tmp_path / "o.yaml"]

    def swap(flag, value):
        a = list(args)
        a[a.index(flag) + 1] = value
        return a

    cam = yaml.safe_load((scene / "camera.yaml").read_text())
    cam["width"] = 800
    (tmp_path / "cam.yaml").write_text(yaml.safe_dump(cam))
    assert_one_line_error(run_cli("refine", *swap("--camera", tmp_path / "cam.yaml")), "photo.png", "640x480", "800x480")

    T, _ = read_pose(scene / "init_pose.yaml")
    (tmp_path / "shear.yaml").write_text(yaml.safe_dump({"T_cam_from_scan": (T @ np.diag([1, 1.05, 1, 1])).tolist()}))
    assert_one_line_error(run_cli("refine", *swap("--init", tmp_path / "shear.yaml")), "shear.yaml", "not rigid")

    away = np.diag([-1.0, 1, -1, 1]) @ T  # turned around in place: the camera looks away from the scan
    write_pose(tmp_path / "away.yaml", away)
    assert_one_line_error(run_cli("refine", *swap("--init", tmp_path / "away.yaml")), "in view")

    save_scan(tmp_path / "empty.ply", Scan(xyz=np.zeros((0, 3))))
    assert_one_line_error(run_cli("refine", *swap("--scan", tmp_path / "empty.ply")), "empty.ply", "no points")
    assert_one_line_error(run_cli("refine", *args, "--color-model", "cubic"), "color_model")
    assert not (tmp_path / "o.yaml").exists()


def test_no_state_survives_between_two_refines(tmp_path, synth_scene):
    """One aligner refined twice (the camera freed too) gives the same result both times, and
    its batched repeat runs work before any refine."""
    from rgbd_gt.align.refine import make_aligner

    synth_scene(tmp_path, 3)
    inputs = load_inputs(tmp_path / "scan.ply", tmp_path / "photo.png", tmp_path / "camera.yaml", tmp_path / "init_pose.yaml")
    cfg = dataclasses.replace(RefineConfig(), refine_intrinsics="focal", max_points=20000, levels=3)
    aligner = make_aligner(inputs, cfg, "cpu")
    fresh = make_aligner(inputs, cfg, "cpu").refine_many([inputs.T_init], coarsest=2, finest=2, iterations=3)
    assert fresh[0] is not None and fresh[0].shape == (4, 4)
    first, second = aligner.refine(inputs.T_init), aligner.refine(inputs.T_init)
    np.testing.assert_array_equal(first.T_cam_from_scan, second.T_cam_from_scan)
    np.testing.assert_array_equal(first.intrinsics, second.intrinsics)
    assert first.intrinsics[0] != 0  # the focal was refined: the second run started from the file again


def test_a_single_photos_covariance_takes_the_photos_tiles_as_the_samples(tmp_path, synth_scene):
    """The gradient of the objective summed per tile of the photo (at most 8 x 8 tiles) adds up to
    its whole gradient at the result, with the same Gauss-Newton matrix; the result's covariance
    with the tiles as the samples is their sandwich, and, kept where wider than the aligner's, the
    truth lies far fewer of its sigmas away (measured on synthetic scenes: a Mahalanobis^2 of
    490-14000 under the aligner's, 49-276 under the tiles')."""
    from rgbd_gt.align.covariance import sandwich, wider
    from rgbd_gt.align.refine import make_aligner
    from rgbd_gt.pose import invert, translated, update_of

    synth_scene(tmp_path, 3)
    inputs = load_inputs(tmp_path / "scan.ply", tmp_path / "photo.png", tmp_path / "camera.yaml", tmp_path / "init_pose.yaml")
    aligner = make_aligner(inputs, dataclasses.replace(RefineConfig(), max_points=20000, levels=3), "cpu")
    result = aligner.refine(inputs.T_init)
    objective = aligner.objective
    at = objective.evaluate(0, [translated(result.T_cam_from_scan, objective.centre)], torch.zeros(5))
    g, H = objective.tile_scores(0, at)
    assert 2 <= len(g) <= 64 and result.tiles[1] == len(g)
    np.testing.assert_allclose(g.sum(0), at.g[0], rtol=1e-6, atol=1e-9 * np.abs(at.g[0]).max())
    np.testing.assert_allclose(H, at.H[0])
    np.testing.assert_allclose(result.tiles[0], sandwich(g, H)[:6, :6], rtol=1e-6)
    laplace, tiles = result.covariance, wider(result.covariance, result.tiles[0])
    L = np.linalg.cholesky(laplace)
    widened = np.linalg.eigvalsh(np.linalg.solve(L, np.linalg.solve(L, tiles).T))
    assert widened.min() > 1 - 1e-9 and widened.max() > 4
    e = update_of(result.T_cam_from_scan @ invert(read_pose(tmp_path / "gt_pose.yaml")[0]))
    assert e @ np.linalg.solve(tiles, e) < e @ np.linalg.solve(laplace, e) / 4


def test_a_pose_is_a_batch_of_one(tmp_path, synth_scene):
    """The objective evaluates a batch of poses as it evaluates each alone (each pose its own
    Z-buffer, color fit and scale), and the driver's one Levenberg-Marquardt loop gives a refine
    and each run of a batch of repeats the same pose."""
    from rgbd_gt.align.refine import make_aligner
    from rgbd_gt.pose import apply_update, translated

    synth_scene(tmp_path, 3)
    inputs = load_inputs(tmp_path / "scan.ply", tmp_path / "photo.png", tmp_path / "camera.yaml", tmp_path / "init_pose.yaml")
    aligner = make_aligner(inputs, dataclasses.replace(RefineConfig(), max_points=20000, levels=3), "cpu")
    other = apply_update(inputs.T_init, np.r_[0.004, -0.003, 0.002, 0.01, 0.02, -0.01])
    aligner.prepare(inputs.T_init)
    objective = aligner.objective
    Ts = [translated(T, objective.centre) for T in (inputs.T_init, other)]
    q = torch.zeros(5)
    both = objective.evaluate(1, Ts, q)
    for b, T in enumerate(Ts):
        alone = objective.evaluate(1, [T], q)
        assert both.visible[b] == alone.visible[0] > 1000
        np.testing.assert_allclose(both.loss[b], alone.loss[0], rtol=1e-5)
        np.testing.assert_allclose(both.H[b], alone.H[0], rtol=1e-4, atol=1e-6 * np.abs(alone.H[0]).max())
        np.testing.assert_allclose(objective.trial(1, [Ts[1 - b]], q, alone), objective.trial(1, Ts[::-1], q, both)[b:b + 1],
                                   rtol=1e-5)
    refined = [aligner.refine(T) for T in (inputs.T_init, other)]
    for T_many, one in zip(aligner.refine_many([inputs.T_init, other]), refined):
        # float32 sums in another order can end a level one update earlier or later, and a level
        # that runs to its iteration cap somewhere else: apart by less than the result's own
        # 1-sigma (measured 0.05-14 um and 3e-8 to 2.3e-4 deg; 57 um and 6.8e-4 deg on a CPU where
        # the init's level 2 ran to its cap, against 1-sigma 78 um and 1.4e-3 deg)
        sigma = np.sqrt(np.diag(one.covariance))
        assert translation_error_m(T_many, one.T_cam_from_scan) < np.linalg.norm(sigma[3:])
        assert rotation_error_deg(T_many, one.T_cam_from_scan) < np.rad2deg(np.linalg.norm(sigma[:3]))
