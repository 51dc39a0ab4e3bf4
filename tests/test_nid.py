"""The NID objective for scans whose values relate to the photo only statistically: its value and
gradient, the aligner on a synthetic intensity-only scan with exact truth and on a real LiDAR
sweep, the joint solve of several pairs, calibration text files, and the sweep helpers."""

import dataclasses

import numpy as np
import pytest
import torch
import yaml

from conftest import DATA, assert_one_line_error, run_cli
from rgbd_gt.align import lbfgs
from rgbd_gt.align.config import RefineConfig
from rgbd_gt.align.nid import joint_histogram, nid, nid_of_windows, nid_with_gradient, parzen_windows
from rgbd_gt.align.aligner import Aligner
from rgbd_gt.align.nid_objective import Frame, Nid
from rgbd_gt.align.pyramid import photo_pyramid
from rgbd_gt.errors import InputError
from rgbd_gt.io import load_scan, read_camera, read_pose, save_scan
from rgbd_gt.io.image import read_image
from rgbd_gt.scan import Scan, colors_to_gray
from rgbd_gt.pose import apply_update, rotation_error_deg, so3_exp, translated, translation_error_m, worst_sigmas
from rgbd_gt.render.cells import cell_for_density
from rgbd_gt.render.zbuffer import depth_edges, visible_points


def test_nid_is_zero_for_dependent_values_and_near_one_for_independent_ones():
    rng = np.random.default_rng(0)
    a = torch.as_tensor(rng.uniform(0, 1, 20_000))
    p = joint_histogram(a, a, 16)
    assert abs(float(p.sum()) - 1) < 1e-9 and float(p.min()) >= 0
    noise = torch.as_tensor(rng.normal(size=20_000))
    same, inverted, bent = float(nid(a, a)), float(nid(a, 1 - a)), float(nid(a, (1 - a) ** 2))
    noisy = float(nid(a, (a + 0.1 * noise).clamp(0, 1)))
    independent = float(nid(a, torch.as_tensor(rng.uniform(0, 1, 20_000))))
    # the B-spline windows blur even an exact relation (0.62 with 16 bins), whatever its form
    assert abs(inverted - same) < 1e-9 and same < bent < noisy < independent
    assert same < 0.7 and bent < 0.7 and independent > 0.99


def test_nid_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    a = torch.as_tensor(rng.uniform(0, 1, 3000))
    b0 = (0.3 * a + 0.5 * torch.as_tensor(rng.uniform(0, 1, 3000))).clamp(0, 1)
    b = b0.clone().requires_grad_(True)
    nid(a, b).backward()
    value, _, closed, _ = nid_with_gradient(parzen_windows(a, 16), b0, 16)
    assert float(value) == float(nid(a, b0))
    np.testing.assert_allclose(closed.numpy(), b.grad.numpy(), rtol=1e-9, atol=1e-15)
    idx = rng.choice(3000, 20, replace=False)
    h = 1e-6
    for i in idx:
        plus, minus = b0.clone(), b0.clone()
        plus[i] += h
        minus[i] -= h
        fd = (float(nid(a, plus)) - float(nid(a, minus))) / (2 * h)
        assert abs(float(b.grad[i]) - fd) <= 1e-4 * max(abs(fd), 1e-3), (i, float(b.grad[i]), fd)


def test_nid_gradient_with_a_mask_equals_it_on_the_masked_windows():
    # the objective masks the samples off the photo on the photo's side; the same numbers to the bit
    rng = np.random.default_rng(2)
    a, b = (torch.as_tensor(rng.uniform(0, 1, (2, 3000))) for _ in range(2))
    use = torch.as_tensor(rng.uniform(size=(2, 3000)) < 0.7).double()
    wa = parzen_windows(a, 16)
    masked = nid_with_gradient(wa * use[..., None], b, 16)
    value, h_ab, d_b, _ = nid_with_gradient(wa, b, 16, use)
    assert torch.equal(value, masked[0]) and torch.equal(h_ab, masked[1])
    assert torch.equal(d_b, masked[2] * use) and bool((d_b[use == 0] == 0).all())
    # ... and without the gradient (`parzen_windows` with use), as they are
    plain = nid_of_windows(wa * use[..., None], parzen_windows(b, 16))
    assert all(torch.equal(x, y) for x, y in zip(nid_of_windows(wa, parzen_windows(b, 16, use)), plain))


def test_nid_gradient_with_respect_to_the_samples_weights_matches_autograd():
    # the weights fall to 0 at the photo's border (`_Stack.inside`): their slope enters the pose's gradient
    rng = np.random.default_rng(3)
    a, b = (torch.as_tensor(rng.uniform(0, 1, 3000)) for _ in range(2))
    b = (0.4 * a + 0.6 * b).clamp(0, 1)
    use0 = torch.as_tensor(rng.uniform(0, 1, 3000))
    use = use0.clone().requires_grad_(True)
    nid_of_windows(parzen_windows(a, 16), parzen_windows(b, 16, use))[0].backward()
    value, _, _, d_use = nid_with_gradient(parzen_windows(a, 16), b, 16, use0)
    assert float(value) == pytest.approx(float(nid_of_windows(parzen_windows(a, 16), parzen_windows(b, 16, use0))[0]), abs=1e-12)
    np.testing.assert_allclose(d_use.numpy(), use.grad.numpy(), rtol=1e-9, atol=1e-15)


def test_differentiable_rotation_matches_rodrigues():
    for w in (np.zeros(3), np.array([1e-7, 0, 0]), np.array([0.3, -0.2, 0.9])):
        np.testing.assert_allclose(so3_exp(torch.as_tensor(w)).numpy(), so3_exp(w), atol=1e-12)


@pytest.fixture(scope="module")
def intensity_scene(tmp_path_factory, synth_scene):
    """A synthetic scene whose scan keeps only an 'intensity': a non-monotonic function of its
    gray, which no per-point regression from the photo's colors recovers, but NID does."""
    d = tmp_path_factory.mktemp("nid_scene")
    synth_scene(d, 2)
    scan = load_scan(d / "scan.ply")
    gray = colors_to_gray(scan.rgb) / 255.0
    save_scan(d / "intensity.ply", Scan(xyz=scan.xyz, intensity=(np.sin(3 * np.pi * gray) ** 2).astype(np.float32),
                                        origins=scan.origins))
    return d


def test_own_lbfgs_takes_torch_optim_lbfgs_steps():
    """align/lbfgs.py is torch.optim.LBFGS with the strong Wolfe line search without its 0.9 s
    import of torch._dynamo: the same iterates, cut off after each iteration count."""
    def rosenbrock(x):
        return (100 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2).sum()

    def value_and_gradient(x_np):
        x = torch.tensor(x_np, requires_grad=True)
        f = rosenbrock(x)
        f.backward()
        return float(f.detach()), x.grad.numpy().copy()

    for seed in range(3):
        x0 = np.random.default_rng(seed).normal(size=6)
        for max_iter in (3, 12, 200):
            x, n_iter = lbfgs.minimize(value_and_gradient, x0, max_iter)
            xt = torch.tensor(x0, requires_grad=True)
            opt = torch.optim.LBFGS([xt], lr=1, max_iter=max_iter, line_search_fn="strong_wolfe",
                                    tolerance_grad=1e-9, tolerance_change=1e-9)

            def closure():
                opt.zero_grad()
                f = rosenbrock(xt)
                f.backward()
                return f

            opt.step(closure)
            assert n_iter == opt.state[xt]["n_iter"]
            assert np.abs(x - xt.detach().numpy()).max() < 1e-9
    assert np.abs(x - 1).max() < 1e-5 and n_iter < 200  # converged to the minimum at (1, ..., 1)


def test_lockstep_lbfgs_takes_each_starts_own_steps():
    """`lbfgs.minimize_many` runs several starts in lockstep (their points evaluated in one call):
    each start's iterates are those it takes alone, and a start whose value turns NaN (a pose
    that left the scan) drops out without moving the others."""
    def rosenbrock(x):
        return float((100 * (x[1:] - x[:-1] ** 2) ** 2 + (1 - x[:-1]) ** 2).sum())

    def gradient(x):
        g = np.zeros_like(x)
        g[:-1] = -400 * x[:-1] * (x[1:] - x[:-1] ** 2) - 2 * (1 - x[:-1])
        g[1:] += 200 * (x[1:] - x[:-1] ** 2)
        return g

    x0s = np.random.default_rng(0).normal(size=(4, 6))
    calls = []

    def batched(X, which):
        calls.append(len(which))
        values = np.array([rosenbrock(x) for x in X])
        values[np.array(which) == 2] = np.nan  # start 2 leaves the scan at once
        return values, np.stack([gradient(x) for x in X])

    together = lbfgs.minimize_many(batched, x0s, 40)
    assert together[2] is None and max(calls) == 4 and min(calls) < 4  # finished starts leave the batch
    for i in (0, 1, 3):
        x, n_iter = lbfgs.minimize(lambda x: (rosenbrock(x), gradient(x)), x0s[i], 40)
        assert together[i][1] == n_iter and np.array_equal(together[i][0], x)

    # a start stops where its next quasi-Newton step is small (`small`: the aligner's stop
    # thresholds), on the way the full run takes and near the minimum at (1, ..., 1)
    full = lbfgs.minimize_many(batched, x0s, 200)
    steps: dict[int, list] = {0: [], 1: [], 3: []}

    def small(k, d):
        steps[k].append(np.abs(d).max())
        return steps[k][-1] < 1e-3

    early = lbfgs.minimize_many(batched, x0s, 200, small)
    for i in (0, 1, 3):
        assert early[i][1] == len(steps[i]) < full[i][1] and steps[i][-1] < 1e-3 <= min(steps[i][:-1])
        assert np.abs(early[i][0] - 1).max() < 1e-2 and np.abs(full[i][0] - 1).max() < 1e-5


def test_lockstep_groups_hold_at_most_their_points():
    """The starts of a level are dealt into lockstep groups of bounded size (the joined arrays of a
    19-frame solve's 17 search starts took 1.8 GB): in order, a start larger than the bound
    alone, a start that lost the scan (None) in none."""
    from rgbd_gt.align.objective import lockstep

    assert lockstep([10, None, 5, 300, 400, 1, 2], most=300) == [[0, 2], [3], [4], [5, 6]]
    assert lockstep([100] * 5, most=300) == [[0, 1, 2], [3, 4]]
    assert lockstep([None, None]) == []


def test_poses_evaluated_together_are_each_alone(intensity_scene):
    """The starts of a level are evaluated together (`Nid.batch`: their parts joined, one
    evaluation): three poses, each on the points it sees, give together each one's value and
    gradient alone; one moved off the scan is NaN and leaves the others as they are."""
    d = intensity_scene
    scan, photo, camera = load_scan(d / "intensity.ply"), read_image(d / "photo.png"), read_camera(d / "camera.yaml")
    T = read_pose(d / "init_pose.yaml")[0]
    obj = Nid([Frame(scan.xyz, scan.intensity, photo_pyramid(photo, camera, 3, torch.device("cpu")))],
              RefineConfig(objective="nid", levels=3, nid_edges=True))
    T_local = translated(T, obj.centre)
    obj.prepare(T_local)
    Ts = [apply_update(T_local, np.r_[np.radians(w), v]) for w, v in
          (([0, 0, 0], [0, 0, 0]), ([1, -0.5, 0.3], [0.05, 0, -0.1]), ([-0.8, 0.2, 0.6], [-0.1, 0.05, 0.1]))]
    terms = [obj.evaluate(1, [T1]) for T1 in Ts]
    assert len({int(t.parts.real.sum()) for t in terms}) == 3  # each on its own points: padded when joined
    delta = torch.as_tensor([[2e-3, -1e-3, 5e-4, 3e-3, -2e-3, 1e-3]] * 3, dtype=torch.float64)
    values, gradients = obj.value_and_gradient(1, Ts, delta, obj.batch(terms))
    for g, (T1, at) in enumerate(zip(Ts, terms)):
        (alone,), grad = obj.value_and_gradient(1, [T1], delta[g:g + 1], obj.batch([at]))
        np.testing.assert_allclose(values[g], alone, rtol=1e-9)
        np.testing.assert_allclose(gradients[g].numpy(), grad[0].numpy(), rtol=1e-6, atol=1e-9 * float(grad.abs().max()))
    away = delta.clone()
    away[1, 3] = 1e4  # 10 km sideways
    moved, moved_gradients = obj.value_and_gradient(1, Ts, away, obj.batch(terms))
    assert np.isnan(moved[1]) and np.array_equal(moved[[0, 2]], values[[0, 2]])
    assert torch.equal(moved_gradients[[0, 2]], gradients[[0, 2]])


def _gradients(aligner, level, T, delta):
    """Of sum(weights * NID) on `level` at apply_update(T, delta) (delta (6,)), unequal weights
    per channel pair: (closed-form gradient, autograd's, functions of delta giving the value and
    the closed-form gradient, the size of each parameter that moves the level's points by one pixel)."""
    aligner = aligner.objective
    T_local = translated(T, aligner.centre)
    parts = aligner._parts(level, T_local)
    zero = torch.zeros(1, 6, dtype=torch.float64)
    weights = torch.linspace(1.0, 2.0, len(aligner._evaluate(parts, [T_local], zero).nid), dtype=torch.float64)
    d = torch.as_tensor(delta, dtype=torch.float64).requires_grad_(True)
    at = aligner._evaluate(parts, [T_local], d[None], weights)
    (at.nid * weights).sum().backward()

    def value(x):
        return float((aligner._evaluate(parts, [T_local], torch.as_tensor(x, dtype=torch.float64)[None]).nid * weights).sum())

    def gradient(x):
        return aligner._evaluate(parts, [T_local], torch.as_tensor(x, dtype=torch.float64)[None], weights).gradient[0].numpy()

    return at.gradient[0].detach().numpy(), d.grad.numpy(), value, gradient, aligner.units(level, T_local, aligner.evaluate(level, [T_local])).numpy()


@pytest.mark.parametrize("edges", [False, True])
def test_pose_gradient_matches_autograd_and_finite_differences(intensity_scene, edges):
    d = intensity_scene
    scan, photo, camera = load_scan(d / "intensity.ply"), read_image(d / "photo.png"), read_camera(d / "camera.yaml")
    T = read_pose(d / "init_pose.yaml")[0]
    cfg = RefineConfig(objective="nid", levels=3, nid_edges=edges)
    al = Aligner(Nid([Frame(scan.xyz, scan.intensity, photo_pyramid(photo, camera, 3, torch.device("cpu")))], cfg))
    al.prepare(T)
    d0 = np.array([2e-3, -1e-3, 5e-4, 3e-3, -2e-3, 1e-3])
    closed, auto, value, gradient, units = _gradients(al, 1, T, d0)
    np.testing.assert_allclose(closed, auto, rtol=1e-5, atol=1e-6 * np.abs(auto).max())  # autograd: float32 geometry
    # central differences over +-0.1 px against the closed form's mean over the same interval:
    # the derivative jumps where a point crosses a pixel border, and the difference quotient is
    # its mean, not its value at d0 (what is left: points that enter or leave the photo, and
    # float32 points)
    t = np.linspace(-0.1, 0.1, 41)
    fd = np.array([(value(d0 + 0.1 * u * e) - value(d0 - 0.1 * u * e)) / 0.2 for u, e in zip(units, np.eye(6))])
    mean = np.array([np.trapezoid([gradient(d0 + s * u * e) @ e for s in t], t) / 0.2 * u for u, e in zip(units, np.eye(6))])
    # (measured 3.5% and 2.6% without and with edges; against the derivative at d0 itself 4% and 12%)
    assert np.linalg.norm(fd - mean) < 0.06 * np.linalg.norm(closed * units), (fd, mean, closed * units)


def test_points_crossing_the_photos_border_make_no_steps(intensity_scene):
    # a point that stepped onto the photo at full weight made NID jump by what 0.02 px of motion
    # moves it, and L-BFGS stopped on those steps (docs/lidar-method.md, "The photo's border")
    d = intensity_scene
    scan, photo, camera = load_scan(d / "intensity.ply"), read_image(d / "photo.png"), read_camera(d / "camera.yaml")
    T = read_pose(d / "init_pose.yaml")[0]
    al = Aligner(Nid([Frame(scan.xyz, scan.intensity, photo_pyramid(photo, camera, 3, torch.device("cpu")))],
                     RefineConfig(objective="nid", levels=3)))
    al.prepare(T)
    _, _, value, gradient, units = _gradients(al, 1, T, np.zeros(6))
    obj, T_local = al.objective, translated(T, al.objective.centre)
    parts = obj._parts(1, T_local)
    sideways = np.eye(6)[3] * units[3]  # the rows of points at the left and right borders cross them
    s = np.linspace(0, 0.2, 101)  # level pixels
    crossed = [obj._evaluate(parts, [T_local], torch.as_tensor(x * sideways)[None]).counts[0] for x in s]
    assert len(set(crossed)) > 5, crossed  # points do cross the border here
    v = np.array([value(x * sideways) for x in s])
    g = np.array([gradient(x * sideways) @ sideways for x in s])
    steps, slope = np.diff(v), (g[1:] + g[:-1]) / 2 * np.diff(s)
    # measured: 0.014 of the mean step, 0.40 with points at full weight the moment they cross
    assert np.abs(steps - slope).max() < 0.1 * np.abs(slope).mean(), (steps, slope)


def _two_frames(d) -> tuple[list[Frame], np.ndarray]:
    """Two frames of the intensity scene: its photo with the sweep, and the photo at 3/4 size with
    a third of the points; and the init pose."""
    import cv2

    from rgbd_gt.camera import rescale

    scan, photo, camera = load_scan(d / "intensity.ply"), read_image(d / "photo.png"), read_camera(d / "camera.yaml")
    w, h = camera.size
    small = cv2.resize(photo, (w * 3 // 4, h * 3 // 4), interpolation=cv2.INTER_AREA)
    cpu = torch.device("cpu")
    return ([Frame(scan.xyz, scan.intensity, photo_pyramid(photo, camera, 3, cpu)),
             Frame(scan.xyz[::3], scan.intensity[::3], photo_pyramid(small, rescale(camera, *small.shape[1::-1]), 3, cpu))],
            read_pose(d / "init_pose.yaml")[0])


def test_frames_evaluated_together_are_each_alone(intensity_scene):
    """A rig's frames are evaluated stacked (`_Parts`, one gather for all): two frames with photos
    of different sizes and different point counts give together each one's NID, counts and
    joint entropy alone, and the sum of their gradients (what each adds to the objective)."""
    frames, T = _two_frames(intensity_scene)
    cfg = RefineConfig(objective="nid", levels=3, nid_edges=True)
    delta = torch.as_tensor([2e-3, -1e-3, 5e-4, 3e-3, -2e-3, 1e-3], dtype=torch.float64)
    results = []
    for obj in (Nid(frames, cfg), Nid(frames[:1], cfg), Nid(frames[1:], cfg)):
        T_local = translated(T, obj.centre)
        obj.prepare(T_local)
        parts = obj._parts(1, T_local)
        results.append(obj._evaluate(parts, [T_local], delta[None], torch.ones(2 * len(obj.frames), dtype=torch.float64)))
    together, first, second = results
    assert together.counts == first.counts + second.counts and first.counts[0] > second.counts[0] > 0  # padded
    np.testing.assert_allclose(together.nid.numpy(), np.r_[first.nid.numpy(), second.nid.numpy()], rtol=1e-5)
    np.testing.assert_allclose(together.entropies, first.entropies + second.entropies, rtol=1e-5)
    np.testing.assert_allclose(together.gradient.numpy(), (first.gradient + second.gradient).numpy(), rtol=1e-3,
                               atol=1e-4 * float(together.gradient.abs().max()))


def test_a_sweep_without_ring_edges_on_the_photo_refines_as_one_without_the_term(intensity_scene):
    """A sweep whose rings step by less than EDGE_MIN_STEP_M everywhere (a room, a tunnel: no
    returns for the ring-edge term) used to crash the term's sampling of zero points; it refines
    exactly as a scan without ring steps, alone and beside a frame that has none either."""
    frames, T = _two_frames(intensity_scene)
    flat = [dataclasses.replace(f, edges=np.full(len(f.points), 0.5, np.float32)) for f in frames]
    cfg = RefineConfig(objective="nid", levels=2, search_starts=0, iterations=5)
    for with_steps, without in ((flat[:1], frames[:1]), (flat, frames)):
        a, b = (Aligner(Nid(fs, cfg)).refine(T) for fs in (with_steps, without))
        np.testing.assert_array_equal(a.T_cam_from_scan, b.T_cam_from_scan)
        assert a.loss == b.loss


def test_frame_quadratics_are_central_differences_of_each_frames_share(intensity_scene):
    """The covariance's 72 steps are evaluated together (`Nid._per_frame_at`): each frame's
    gradient and Hessian are the central differences over one pixel of its share of the
    objective, taken one step at a time."""
    frames, T = _two_frames(intensity_scene)
    obj = Nid(frames, RefineConfig(objective="nid", levels=3))
    T_local = translated(T, obj.centre)
    obj.prepare(T_local)
    terms = obj.evaluate(0, [T_local])
    g, H, units = obj.frame_quadratics(0, T_local, terms)
    weights = terms.evaluation.weights()

    def f(x: np.ndarray) -> np.ndarray:
        return obj._at(terms.parts, T_local, torch.as_tensor(x * units)).per_frame(weights).numpy()

    E, f0 = np.eye(6), f(np.zeros(6))
    tol = 1e-9 * np.abs(f0).max()
    assert g.shape == (2, 6) and H.shape == (2, 6, 6) and np.array_equal(H, H.transpose(0, 2, 1))
    for i in range(6):
        np.testing.assert_allclose(g[:, i], (f(E[i]) - f(-E[i])) / 2, rtol=0, atol=tol)
        np.testing.assert_allclose(H[:, i, i], f(E[i]) - 2 * f0 + f(-E[i]), rtol=0, atol=tol)
    for i, j in ((0, 1), (2, 5), (3, 4)):
        a, b = E[i], E[j]
        np.testing.assert_allclose(H[:, i, j], (f(a + b) - f(a - b) - f(b - a) + f(-a - b)) / 4, rtol=0, atol=tol)


def test_closed_form_pose_gradient_on_real_sweeps_with_their_sky():
    """pjlab_1 and pjlab_2 as one rig on level 2, where the sky is charged, at an update with a
    rotation of 1 deg (whose Jacobian the closed form carries) and 10 cm."""
    from rgbd_gt.align.refine import RefineInputs, make_aligner
    from rgbd_gt.scan import scan_colors

    inputs = []
    for k in (1, 2):
        folder = _pjlab(k)
        photo = read_image(folder / "calib.jpg")
        camera = read_camera(folder / "calib.txt", (photo.shape[1], photo.shape[0]))
        scan = load_scan(folder / "calib.pcd")
        T = read_pose(folder / "calib.txt")[0]
        inputs.append(RefineInputs(scan.xyz, scan_colors(scan), photo, camera, T, None, scan))
    al = make_aligner(inputs[0], RefineConfig(objective="nid"), "cpu", inputs[1:])
    al.prepare(T)
    assert al.objective._sky == [True, True]
    closed, auto, _, _, _ = _gradients(al, 2, T, np.r_[np.radians([0.6, -0.5, 0.6]), 0.05, -0.03, 0.08])
    np.testing.assert_allclose(closed, auto, rtol=1e-5, atol=1e-6 * np.abs(auto).max())  # autograd: float32 geometry


def test_repeat_runs_are_refine_itself_and_the_covariance_is_a_minimum(intensity_scene):
    """The verdict's repeats (`refine_many`, in lockstep) must ask what refine did, wide search
    included: from the init they reproduce its result. At that result the Hessian from values over 1 px is
    positive definite and its 1-sigma is below a pixel (the result is 1.9 mm / 0.03 deg off)."""
    d = intensity_scene
    scan, photo, camera = load_scan(d / "intensity.ply"), read_image(d / "photo.png"), read_camera(d / "camera.yaml")
    T0 = read_pose(d / "init_pose.yaml")[0]
    cfg = RefineConfig(objective="nid", levels=3)
    al = Aligner(Nid([Frame(scan.xyz, scan.intensity, photo_pyramid(photo, camera, 3, torch.device("cpu")))], cfg))
    result = al.refine(T0)
    # in lockstep with another start (their searches' 34 starts and 6 candidates evaluated
    # together), each ends where refine takes it alone
    T1 = apply_update(T0, np.r_[np.radians([0.5, -0.3, 0.2]), 0.02, 0.01, -0.02])
    ends = al.refine_many([T0, T1])
    np.testing.assert_allclose(ends[0], result.T_cam_from_scan, atol=1e-9)
    np.testing.assert_allclose(ends[1], al.refine(T1).T_cam_from_scan, atol=1e-9)
    cov = result.covariance
    assert np.isfinite(cov).all() and np.linalg.eigvalsh(cov)[0] > 0
    from rgbd_gt.align.verify import _View, uncertainty
    from rgbd_gt.camera import without_distortion

    view = _View(al.visible_scan_points(result.T_cam_from_scan), without_distortion(camera))
    sigma = uncertainty(result.covariance, view.motion_metric(result.T_cam_from_scan))
    assert 0 < sigma["image_px"] < 1.0, sigma
    # with the photo's tiles as the samples: wider (measured 4.7 times along the worst
    # direction of the camera's position on this scene)
    from rgbd_gt.align.covariance import wider

    tiles = wider(cov, result.tiles[0])
    assert result.tiles[1] > 32 and worst_sigmas(tiles)["translation_mm"] > 2 * worst_sigmas(cov)["translation_mm"]


def test_nid_refines_an_intensity_only_scan_where_photometric_cannot(intensity_scene, tmp_path):
    d = intensity_scene
    gt, init = read_pose(d / "gt_pose.yaml")[0], read_pose(d / "init_pose.yaml")[0]
    errs = {}
    for objective in ("nid", "photometric"):
        out = tmp_path / f"{objective}.yaml"
        proc = run_cli("refine", "--scan", d / "intensity.ply", "--image", d / "photo.png", "--camera", d / "camera.yaml",
                       "--init", d / "init_pose.yaml", "-o", out, "--objective", objective, "--repeats", "0",
                       "--report", tmp_path / f"report_{objective}")
        assert proc.returncode == 0, proc.stderr
        assert (tmp_path / f"report_{objective}" / "convergence.png").stat().st_size > 0
        T, meta = read_pose(out)
        assert meta["objective"] == objective and meta["verdict"] in ("ok", "suspect", "failed")
        errs[objective] = (translation_error_m(T, gt) * 1e3, rotation_error_deg(T, gt))
    init_err = (translation_error_m(init, gt) * 1e3, rotation_error_deg(init, gt))
    print("synthetic intensity-only (mm, deg): init", init_err, "after", errs)
    assert errs["nid"][0] < 3.0 and errs["nid"][1] < 0.06, (errs, init_err)  # measured 1.9 mm, 0.031 deg: docs/lidar.md
    assert errs["photometric"][0] > 2 * errs["nid"][0], errs


def _pjlab(k: int):
    folder = DATA / "lidar_camera" / f"pjlab_{k}"
    if not folder.exists():
        pytest.skip(f"real test data not found at {folder}")
    return folder


def test_real_sweep_converges_from_a_one_degree_init(tmp_path):
    """pjlab_3 (the scene where NID agrees with the reference; docs/lidar.md): 1 degree and 10 cm off.
    The reference has its own error: NID's minimum lies 2-6 cm from it (docs/lidar.md)."""
    d = _pjlab(3)
    T_ref = read_pose(d / "calib.txt")[0]
    T0 = apply_update(T_ref, np.r_[np.radians(1.0) * np.array([0.6, 0.0, 0.8]), 0.10 * np.array([0.0, 0.6, 0.8])])
    from rgbd_gt.io import write_pose

    write_pose(tmp_path / "init.yaml", T0)
    out = tmp_path / "pose.yaml"
    proc = run_cli("refine", "--scan", d / "calib.pcd", "--image", d / "calib.png", "--camera", d / "calib.txt",
                   "--init", tmp_path / "init.yaml", "-o", out, "--repeats", "0")
    assert proc.returncode == 0, proc.stderr
    T, meta = read_pose(out)
    assert meta["objective"] == "nid"  # auto: the sweep has intensity only
    print("pjlab_3 from 1 deg / 10 cm:", rotation_error_deg(T, T_ref), translation_error_m(T, T_ref))
    assert rotation_error_deg(T, T_ref) < 0.25 and translation_error_m(T, T_ref) < 0.08, (
        rotation_error_deg(T, T_ref), translation_error_m(T, T_ref))
    assert meta["verdict"] != "ok"  # a sweep this sparse cannot be checked against the photo's edges
    # The Hessian from the objective's values over 1 px is positive definite here (its 1-sigma
    # image motion 0.25-0.5 px at right pjlab_3 results; docs/lidar-method.md).
    assert meta["evidence"]["uncertainty"]["image_px"] < 1.0, meta["evidence"]["uncertainty"]
    # the pose file states the covariance with the photo's tiles as the samples, never narrower
    tiles = meta["evidence"]["tiles"]
    assert 16 < tiles["count"] <= 64 and tiles["uncertainty"]["translation_mm"] >= meta["evidence"]["uncertainty"]["translation_mm"]
    # it stands for the sharpness probe, whose 1e-5..1e-3 rises called every nid result flat
    assert "sharpness" not in meta["evidence"] and not any("flat" in r for r in meta["reasons"]), meta["reasons"]


def test_search_results_are_judged_on_a_finer_level():
    """pjlab_3, two of the benchmark's inits 1 deg / 10 cm off (docs/lidar.md) where the search
    result of lowest NID on the coarsest level (1/16 scale) lay in a wrong basin: taken alone it
    ended 1.7 and 0.36 deg off (and from an init 1e-6 away from the first, right: near ties at that
    scale). With the best three carried down to level 1 and judged there, both end at NID's
    minimum near the reference (docs/lidar-method.md, "Which search result goes on")."""
    from rgbd_gt.align.refine import RefineInputs, make_aligner
    from benchmarks.lidar import init_poses, pjlab_scene

    s = pjlab_scene(_pjlab(3))
    inits = init_poses(s.T_ref, 1.0, 0.10, 10, seed=sum(map(ord, "pjlab_3")))
    for i in (3, 7):
        inputs = RefineInputs(s.scan.xyz, s.colors, s.photo, s.camera, inits[i], None, s.scan)
        T = make_aligner(inputs, RefineConfig(objective="nid"), "cpu").refine(inits[i]).T_cam_from_scan
        errors = (rotation_error_deg(T, s.T_ref), translation_error_m(T, s.T_ref))
        print(f"pjlab_3, benchmark init #{i} (deg, m):", errors)
        assert errors[0] < 0.25 and errors[1] < 0.08, (i, errors)  # measured 0.16-0.20 deg, 2.9-3.5 cm


def test_joint_solve_of_two_frames_and_calibration_files(tmp_path):
    d1, d2 = _pjlab(1), _pjlab(2)
    (tmp_path / "pairs.yaml").write_text(yaml.safe_dump({"pairs": [
        {"scan": str(d1 / "calib.pcd"), "image": str(d1 / "calib.jpg")},
        {"scan": str(d2 / "calib.pcd"), "image": str(d2 / "calib.jpg"), "camera": str(d2 / "calib.txt")}]}))
    out = tmp_path / "rig.yaml"
    proc = run_cli("refine", "--pairs", tmp_path / "pairs.yaml", "--camera", d1 / "calib.txt", "--init", d1 / "calib.txt",
                   "-o", out, "--repeats", "0", "--search-starts", "0", "--levels", "1")
    assert proc.returncode == 0, proc.stderr
    T, meta = read_pose(out)
    assert meta["pairs"] == 2 and meta["objective"] == "nid" and meta["visible_points"] > 12_000
    # from the reference, on full resolution only: the joint minimum lies near it (docs/lidar.md)
    T_ref = read_pose(d1 / "calib.txt")[0]
    assert rotation_error_deg(T, T_ref) < 0.3 and translation_error_m(T, T_ref) < 0.1
    # the photometric objective has no joint form
    proc = run_cli("refine", "--pairs", tmp_path / "pairs.yaml", "--camera", d1 / "calib.txt", "--init", d1 / "calib.txt",
                   "-o", tmp_path / "x.yaml", "--objective", "photometric")
    assert_one_line_error(proc, "jointly")


def test_pairs_and_scan_arguments_are_checked(tmp_path):
    (tmp_path / "bad.yaml").write_text("pairs: [{scan: a.pcd}]\n")
    cam = tmp_path / "cam.yaml"
    cam.write_text("width: 10\nheight: 10\nfx: 10\nfy: 10\ncx: 5\ncy: 5\n")
    pose = tmp_path / "pose.yaml"
    pose.write_text(yaml.safe_dump({"T_cam_from_scan": np.eye(4).tolist()}))
    base = ("refine", "--camera", cam, "--init", pose, "-o", tmp_path / "out.yaml")
    assert_one_line_error(run_cli(*base, "--pairs", tmp_path / "bad.yaml"), "pair 1", "scan and image")
    (tmp_path / "empty.yaml").write_text("pairs: [{scan: a.pcd, image: a.png}, {scan: '', image: a.png}]\n")
    assert_one_line_error(run_cli(*base, "--pairs", tmp_path / "empty.yaml"), "pair 2", "scan and image")  # not the folder
    assert_one_line_error(run_cli(*base, "--scan", tmp_path / "a.pcd"), "--scan and --image")
    assert_one_line_error(run_cli(*base), "--pairs")
    assert_one_line_error(run_cli(*base, "--scan", "a.pcd", "--image", "a.png"), "a.pcd: --scan: file not found")
    # fuzz seed 13: the list itself missing said "inf: file not found", naming no option
    assert_one_line_error(run_cli(*base, "--pairs", "inf"), "inf: --pairs: file not found")
    (tmp_path / "a.pcd").touch()
    (tmp_path / "a.png").touch()
    assert_one_line_error(run_cli(*base, "--scan", tmp_path / "a.pcd", "--image", tmp_path / "a.png", "--objective", "mi"),
                          "objective")
    assert not (tmp_path / "out.yaml").exists()
    from rgbd_gt.align.refine import read_pairs  # paths relative to the file, `~` the user's home

    (tmp_path / "rig.yaml").write_text("pairs: [{scan: a.pcd, image: ~/b.png, camera: ~/c.yaml}, {scan: a.pcd, image: d.png}]\n")
    home = tmp_path / "home"
    home.mkdir()
    for name in ("a.pcd", "d.png", "home/b.png", "home/c.yaml"):
        (tmp_path / name).touch()
    with pytest.MonkeyPatch.context() as env:
        env.setenv("HOME", str(home))
        assert read_pairs(tmp_path / "rig.yaml", cam) == [
            {"scan": tmp_path / "a.pcd", "image": home / "b.png", "camera": home / "c.yaml"},
            {"scan": tmp_path / "a.pcd", "image": tmp_path / "d.png", "camera": cam}]
        # fuzz seed 11: a pair's missing photo was named without the list or the pair
        (tmp_path / "d.png").unlink()
        assert_one_line_error(run_cli(*base, "--pairs", tmp_path / "rig.yaml"), str(tmp_path / "rig.yaml"),
                              f"pair 2: image {tmp_path / 'd.png'}: file not found")


def test_nothing_to_align_by_is_an_input_error(tmp_path):
    """A sweep whose points in view all have one intensity, or a photo of one value, is refused
    before any work (a refine of either once ran 13 s and moved the pose 2.5 deg)."""
    import cv2
    import open3d as o3d

    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(-4, 4, (5000, 2)), np.full(5000, 5.0)].astype(np.float32)  # a wall 5 m ahead
    cam = tmp_path / "cam.yaml"
    cam.write_text("width: 64\nheight: 48\nfx: 40\nfy: 40\ncx: 32\ncy: 24\n")
    pose = tmp_path / "pose.yaml"
    pose.write_text(yaml.safe_dump({"T_cam_from_scan": np.eye(4).tolist()}))
    photo = rng.integers(0, 255, (48, 64, 3), dtype=np.uint8)
    cv2.imwrite(str(tmp_path / "photo.png"), photo)
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros_like(photo))
    for name, intensity in (("flat", np.full(5000, 7.0)), ("varied", rng.uniform(0, 255, 5000))):
        pc = o3d.t.geometry.PointCloud(o3d.core.Tensor(xyz))
        pc.point.intensity = o3d.core.Tensor(intensity.astype(np.float32)[:, None])
        o3d.t.io.write_point_cloud(str(tmp_path / f"{name}.pcd"), pc)
    base = ("refine", "--camera", cam, "--init", pose, "-o", tmp_path / "out.yaml")
    assert_one_line_error(run_cli(*base, "--scan", tmp_path / "flat.pcd", "--image", tmp_path / "photo.png"),
                          "flat.pcd", "same intensity")
    assert_one_line_error(run_cli(*base, "--scan", tmp_path / "varied.pcd", "--image", tmp_path / "black.png"),
                          "black.png", "every pixel")
    assert not (tmp_path / "out.yaml").exists()


def test_calibration_text_files(tmp_path):
    R = so3_exp(np.array([0.01, -0.02, 1.5]))
    rows = np.round(np.hstack([R, [[0.1], [-0.4], [0.2]]]), 6)  # printed with 6 digits: not quite orthonormal
    pjlab = tmp_path / "calib.txt"
    pjlab.write_text("K: 2000 0 960 0 2010 600 0 0 1\nD: -0.1 0.1 0.001 0.002\nT: " + " ".join(map(str, rows.ravel())) + "\n")
    cam = read_camera(pjlab, (1920, 1200))
    assert (cam.width, cam.fx, cam.fy, cam.cy) == (1920, 2000, 2010, 600) and cam.distortion == (-0.1, 0.1, 0.001, 0.002)
    T, meta = read_pose(pjlab)
    np.testing.assert_allclose(T[:3], rows, atol=2e-6)
    assert meta == {}
    assert abs(np.linalg.det(T[:3, :3]) - 1) < 1e-12
    kitti = tmp_path / "kitti.txt"
    kitti.write_text("P2: 700 0 600 0 0 700 180 0 0 0 1 0\nTr_velo_to_cam: " + " ".join(map(str, rows.ravel())) + "\n")
    assert read_camera(kitti, (1242, 375)).cx == 600 and read_camera(kitti, (1242, 375)).distortion == ()
    np.testing.assert_allclose(read_pose(kitti)[0], T)  # camera 2 at camera 0, no rectification: Tr itself
    (tmp_path / "nan.txt").write_text("K: nan 0 1 0 1 1 0 0 1\n")
    (tmp_path / "short.txt").write_text("T: 1 0 0\n")
    (tmp_path / "d3.txt").write_text("K: 10 0 5 0 10 5 0 0 1\nD: 0.1 0.2 0.3\n")
    for path, needle in ((tmp_path / "nan.txt", "non-finite"), (tmp_path / "short.txt", "12"),
                         (tmp_path / "d3.txt", "4, 5, 8, 12 or 14 coefficients, got 3")):
        with pytest.raises(InputError, match=needle):
            read_pose(path) if "short" in path.name else read_camera(path, (10, 10))
    with pytest.raises(Exception, match="no image size"):
        read_camera(pjlab)
    with pytest.raises(InputError, match="from the centre of the 960x600 photo"):  # a half-size photo
        read_camera(pjlab, (960, 600))
    with pytest.raises(InputError, match="25% of the photo's size from the centre of the 3840x2400 photo"):  # enlarged twice: inside it, off its middle
        read_camera(pjlab, (3840, 2400))
    # KITTI's K on a Waymo-size photo: the principal point lies inside it, at 14 % of its height
    with pytest.raises(InputError, match=r"36% of the photo's size from the centre of the 1242x1280 photo \(at 48% of its width, 14% of its height"):
        read_camera(kitti, (1242, 1280))
    # a principal point just left of the photo is at 0 % of its width, not "-0%"
    (tmp_path / "left.txt").write_text("P2: 700 0 -0.4 0 0 700 180 0 0 0 1 0\n")
    with pytest.raises(InputError, match=r"\(at 0% of its width, 48% of its height"):
        read_camera(tmp_path / "left.txt", (1242, 375))


# KITTI object detection, training/calib/000000.txt (the 2011_09_26 calibration), as shipped
KITTI_OBJECT = """P0: 7.215377000000e+02 0.000000000000e+00 6.095593000000e+02 0.000000000000e+00 0.000000000000e+00 7.215377000000e+02 1.728540000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P1: 7.215377000000e+02 0.000000000000e+00 6.095593000000e+02 -3.875744000000e+02 0.000000000000e+00 7.215377000000e+02 1.728540000000e+02 0.000000000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 0.000000000000e+00
P2: 7.215377000000e+02 0.000000000000e+00 6.095593000000e+02 4.485728000000e+01 0.000000000000e+00 7.215377000000e+02 1.728540000000e+02 2.163791000000e-01 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 2.745884000000e-03
P3: 7.215377000000e+02 0.000000000000e+00 6.095593000000e+02 -3.395242000000e+02 0.000000000000e+00 7.215377000000e+02 1.728540000000e+02 2.199936000000e+00 0.000000000000e+00 0.000000000000e+00 1.000000000000e+00 2.729905000000e-03
R0_rect: 9.999239000000e-01 9.837760000000e-03 -7.445048000000e-03 -9.869795000000e-03 9.999421000000e-01 -4.278459000000e-03 7.402527000000e-03 4.351614000000e-03 9.999631000000e-01
Tr_velo_to_cam: 7.533745000000e-03 -9.999714000000e-01 -6.166020000000e-04 -4.069766000000e-03 1.480249000000e-02 7.280733000000e-04 -9.998902000000e-01 -7.631618000000e-02 9.998621000000e-01 7.523790000000e-03 1.480755000000e-02 -2.717806000000e-01
Tr_imu_to_velo: 9.999976000000e-01 7.553071000000e-04 -2.035826000000e-03 -8.086759000000e-01 -7.854027000000e-04 9.998898000000e-01 -1.482298000000e-02 3.195559000000e-01 2.024406000000e-03 1.482454000000e-02 9.998881000000e-01 -7.997231000000e-01
"""


def _kitti(text: str, key: str) -> np.ndarray:
    line = next(ln for ln in text.splitlines() if ln.startswith(key + ":"))
    return np.array(line.split(":", 1)[1].split(), float)


def test_kitti_calibration_files_project_as_the_devkit(tmp_path):
    """x = P2 R0_rect Tr_velo_to_cam X (KITTI's object devkit; odometry: P2 Tr X; raw: P_rect_02
    R_rect_00 [R | T] X): the camera and pose read from one calibration file project LiDAR
    points onto the same pixels of image_2. Tr alone would be 0.75 deg and 6 cm off."""
    from rgbd_gt.camera import project
    from rgbd_gt.pose import transform_points

    P2 = _kitti(KITTI_OBJECT, "P2").reshape(3, 4)
    R0 = np.eye(4)
    R0[:3, :3] = _kitti(KITTI_OBJECT, "R0_rect").reshape(3, 3)
    Tr = np.vstack([_kitti(KITTI_OBJECT, "Tr_velo_to_cam").reshape(3, 4), [0, 0, 0, 1]])
    X = np.random.default_rng(0).uniform([5, -10, -1.5], [40, 10, 2], (200, 3))  # ahead of the car, LiDAR frame
    Xh = np.hstack([X, np.ones((200, 1))])

    def devkit(M: np.ndarray) -> np.ndarray:
        x = (P2 @ M @ Xh.T).T
        return x[:, :2] / x[:, 2:]

    obj = tmp_path / "000000.txt"
    obj.write_text(KITTI_OBJECT)
    odo = tmp_path / "calib.txt"  # odometry: Tr already maps into the rectified camera 0
    odo.write_text("".join(ln + "\n" for ln in KITTI_OBJECT.splitlines() if ln[:2] in ("P0", "P1", "P2", "P3"))
                   + "Tr: " + " ".join(map(str, (R0 @ Tr)[:3].ravel())) + "\n")
    raw = tmp_path / "calib_raw.txt"  # calib_velo_to_cam.txt and calib_cam_to_cam.txt's lines in one file
    raw.write_text("calib_time: 15-Mar-2012 11:37:16\nR: " + " ".join(map(str, Tr[:3, :3].ravel()))
                   + "\nT: " + " ".join(map(str, Tr[:3, 3])) + "\ndelta_f: 0 0\nR_rect_00: "
                   + " ".join(map(str, R0[:3, :3].ravel())) + "\nP_rect_02: " + " ".join(map(str, P2.ravel())) + "\n")
    for path in (obj, odo, raw):
        cam, T = read_camera(path, (1242, 375)), read_pose(path)[0]
        uv, z = project(cam, transform_points(T, X))
        # to 1e-3 px: the files' rotations, orthonormal to about 1e-7, are projected onto SO(3)
        np.testing.assert_allclose(uv, devkit(R0 @ Tr), atol=1e-3, err_msg=path.name)
    assert 0.7 < rotation_error_deg(T, Tr) < 0.8 and 0.05 < translation_error_m(T, Tr) < 0.07
    (tmp_path / "singular.txt").write_text("P2: 0 0 0 0 0 0 0 0 0 0 0 0\nTr: " + " ".join(map(str, Tr[:3].ravel())) + "\n")
    (tmp_path / "skew.txt").write_text("R0_rect: 1 0 0 0 2 0 0 0 1\nTr: " + " ".join(map(str, Tr[:3].ravel())) + "\n")
    for name, needle in (("singular.txt", "P2: its first three columns"), ("skew.txt", "R0_rect is not rigid")):
        with pytest.raises(InputError, match=needle):
            read_pose(tmp_path / name)


def test_sweep_density_cell_and_depth_edges():
    # rings: rows 16 px apart, points 2 px apart along each row
    u, v = np.meshgrid(np.arange(0, 640, 2.0), np.arange(8, 480, 16.0))
    uv = torch.as_tensor(np.stack([u.ravel(), v.ravel()], 1))
    assert cell_for_density(uv, (640, 480)) == 8  # 4 points share an 8-px cell of a ring; dense clouds get 1
    dense = torch.as_tensor(np.random.default_rng(0).uniform(0, 100, (40_000, 2)))
    assert cell_for_density(dense, (100, 100)) == 1
    # a pole 4 m away in front of a wall 20 m away: its points stand out, the wall's do not
    z = torch.where((uv[:, 0] >= 300) & (uv[:, 0] < 340), torch.tensor(4.0, dtype=torch.float64), torch.tensor(20.0, dtype=torch.float64))
    e = depth_edges(uv, z, (640, 480), 8)
    pole_edge = (z == 4) & ((uv[:, 0] < 304) | (uv[:, 0] >= 336))  # in the cells (8 px) that border the wall's
    assert bool((e[pole_edge] == 1).all()) and float(e[z == 20].max()) == 0 and float(e[(z == 4) & ~pole_edge].max()) == 0


def silhouettes(uv, z, size, cell, ratio, group=None):
    """The points `visible_points` leaves out for `silhouette=ratio` alone."""
    return visible_points(uv, z, size, cell, group=group) & ~visible_points(uv, z, size, cell, group=group, silhouette=ratio)


def test_silhouettes_are_the_foreground_points_beside_a_farther_surface():
    # a board 2 m away (u 200..399, v 100..299) before a wall 3 m away, points every 2 px; cells of 8 px
    u, v = np.meshgrid(np.arange(0, 640, 2.0), np.arange(0, 480, 2.0))
    uv = torch.as_tensor(np.stack([u.ravel(), v.ravel()], 1))
    board = (uv[:, 0] >= 200) & (uv[:, 0] < 400) & (uv[:, 1] >= 100) & (uv[:, 1] < 300)
    z = torch.where(board, torch.tensor(2.0, dtype=torch.float64), torch.tensor(3.0, dtype=torch.float64))
    s = silhouettes(uv, z, (640, 480), 8, 0.1)
    # the board's points in the cells bordering the wall's cells, and none other
    inner = board & (uv[:, 0] >= 208) & (uv[:, 0] < 392) & (uv[:, 1] >= 104) & (uv[:, 1] < 296)
    assert bool(s[board & ~inner].all()) and not bool(s[inner].any()) and not bool(s[~board].any())
    # a surface only 5 % farther is no silhouette at 10 %; two poses (groups) keep their own Z-buffers
    assert not bool(silhouettes(uv, torch.where(board, z, z.new_tensor(2.1)), (640, 480), 8, 0.1).any())
    both = silhouettes(torch.cat([uv, uv]), torch.cat([z, torch.full_like(z, 3.0)]), (640, 480), 8, 0.1,
                       group=torch.cat([torch.zeros(len(z), dtype=torch.long), torch.ones(len(z), dtype=torch.long)]))
    assert torch.equal(both[:len(z)], s) and not bool(both[len(z):].any())


def _sky_photo() -> np.ndarray:
    """(120, 160, 3) float32: a smooth bright bluish sky over the top 40%, a dark textured ground
    below, and a bright bluish smooth patch in the ground that does not reach the top."""
    rng = np.random.default_rng(3)
    img = np.repeat(rng.uniform(0.05, 0.35, (120, 160, 1)), 3, axis=2).astype(np.float32)
    img[:48] = np.linspace(0.8, 0.85, 48, dtype=np.float32)[:, None, None] * np.array([0.85, 0.95, 1.0], np.float32)
    img[80:110, 20:70] = (0.8, 0.85, 0.9)
    return img


def test_sky_is_the_empty_smooth_bright_top_of_the_photo():
    from rgbd_gt.align.sky import sky_mask

    img = _sky_photo()
    ground = np.stack(np.meshgrid(np.arange(0, 160, 2.0), np.arange(50, 120, 2.0)), -1).reshape(-1, 2)
    mask = sky_mask(img, ground)
    assert mask.shape == (120, 160) and mask.dtype == np.float32
    # sky to within two 8-pixel cells of the horizon (row 48); the bright patch below is not sky
    assert mask[:32].min() > 0.99 and mask[56:].max() == 0
    # where the scan has points, a region that looks like sky is not: a white ceiling
    ceiling = np.stack(np.meshgrid(np.arange(0, 160, 4.0), np.arange(0, 48, 4.0)), -1).reshape(-1, 2)
    assert sky_mask(img, np.concatenate([ground, ceiling])).max() == 0


def test_real_sweeps_land_off_the_sky_at_the_reference():
    """The sky found in each PJLab photo covers its top, and the reference pose puts almost no
    sweep point there (the laser has no returns from the sky)."""
    from rgbd_gt.align.pyramid import photo_pyramid
    from rgbd_gt.align.sky import sky_mask
    from rgbd_gt.render.project import project_pinhole

    for k in (1, 2, 3):
        d = _pjlab(k)
        photo = read_image(next(p for p in sorted(d.glob("calib.*")) if p.suffix in (".jpg", ".png")))
        camera = read_camera(d / "calib.txt", (photo.shape[1], photo.shape[0]))
        level = photo_pyramid(photo, camera, 1, torch.device("cpu"))[0]
        T = read_pose(d / "calib.txt")[0]
        p = load_scan(d / "calib.pcd").xyz @ T[:3, :3].T + T[:3, 3]
        uv, z = project_pinhole(torch.as_tensor(p), level.K.double())
        w, h = camera.size
        inside = ((z > 0) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] < w) & (uv[:, 1] < h)).numpy()
        uv = uv.numpy()[inside]
        mask = sky_mask(level.image.numpy(), uv)
        on_sky = mask[uv[:, 1].astype(int), uv[:, 0].astype(int)] > 0.5
        assert 0.15 < (mask > 0.5).mean() < 0.5, (k, (mask > 0.5).mean())  # measured 0.23, 0.25, 0.36
        assert mask[: h // 4].mean() > 0.5, k  # measured 0.61, 0.63, 0.80
        assert on_sky.mean() < 0.005, (k, on_sky.mean())  # measured 0, 7 of 11k, 0


def test_the_sky_is_charged_on_the_coarse_levels_only():
    """The sky is found at 1/8 scale: its rough border must not steer the fine levels (pjlab_3
    succeeded 6 + 8 times of 20 with the charge on every level, 9 + 10 with it on levels 2 and
    coarser: docs/lidar-method.md). Turned 4 deg about the camera's x axis, pjlab_1's sweep points
    rise into its sky: the coarse levels pay for that, the fine ones see NID alone."""
    from dataclasses import replace

    from rgbd_gt.align.refine import RefineInputs, make_aligner
    from rgbd_gt.scan import scan_colors

    d = _pjlab(1)
    photo = read_image(d / "calib.jpg")
    camera = read_camera(d / "calib.txt", (photo.shape[1], photo.shape[0]))
    scan = load_scan(d / "calib.pcd")
    T_ref = read_pose(d / "calib.txt")[0]
    T_up = apply_update(T_ref, np.r_[np.radians(4.0), 0, 0, 0, 0, 0])
    losses = {}
    for weight in (0.0, 0.5):
        cfg = replace(RefineConfig(), objective="nid", sky_weight=weight)
        aligner = make_aligner(RefineInputs(scan.xyz, scan_colors(scan), photo, camera, T_ref, None, scan), cfg, "cpu")
        aligner.prepare(T_ref)  # as refine does from its init: the sky is found there
        losses[weight] = [aligner.loss_profile(T_up, np.zeros((0, 6)), level)[0] for level in range(4)]
    assert losses[0.5][:2] == losses[0.0][:2]  # levels 0 and 1: no charge
    for level in (2, 3):
        assert losses[0.5][level] > losses[0.0][level] + 0.01, losses  # the points on the sky cost (measured 0.03)


def test_auto_device_runs_nid_on_the_cpu_unless_many_frames():
    """NID's few thousand points per level of one frame leave a GPU waiting on kernel launches
    (slower than the CPU on an H100 machine, docs/gpu.md): 'auto' keeps a frame on the CPU and
    takes CUDA, when present, from NID_CUDA_FRAMES frames solved together."""
    from rgbd_gt.align.refine import NID_CUDA_FRAMES, resolve_device
    from rgbd_gt.errors import InputError

    gpu = "cuda" if torch.cuda.is_available() else "cpu"
    assert resolve_device("auto", "nid").type == "cpu"
    assert resolve_device("auto", "nid", NID_CUDA_FRAMES - 1).type == "cpu"
    assert resolve_device("auto", "nid", NID_CUDA_FRAMES).type == gpu
    assert resolve_device("auto", "photometric").type == gpu
    assert resolve_device("cpu", "nid").type == "cpu"
    with pytest.raises(InputError, match="--device"):
        resolve_device("tpu")


def test_gpu_benchmark_compares_each_case_with_its_twin_on_the_cpu():
    from benchmarks.gpu import compare

    T = np.eye(4)
    moved = T.copy()
    moved[0, 3] = 0.002
    recs = [{"device": d, "kind": k, "case": "a", "T": (moved if d == "cuda" and k == "nid" else T).tolist(),
             "deg": 0.1, "cm": 1.0, "seconds": s} for d, s in (("cpu", 1.0), ("cuda", 3.0)) for k in ("nid", "photometric")]
    recs.append({"device": "cuda", "kind": "nid", "case": "b", "error": "boom"})
    rows = {(r["kind"], r["device"]): r for r in compare(recs, "cpu")}
    assert rows["nid", "cuda"]["worst_apart_mm"] == pytest.approx(2.0)
    assert rows["photometric", "cuda"]["worst_apart_mm"] == 0
    assert rows["nid", "cuda"]["errors"] == 1 and rows["nid", "cuda"]["cases"] == 2
    assert rows["nid", "cuda"]["aligner_s"] == 3.0 and rows["nid", "cpu"]["worst_apart_mm"] == 0
