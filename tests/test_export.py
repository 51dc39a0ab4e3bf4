"""rgbd-gt export: every format from a solved stereo rig (`refine --bundle` on the synthetic
rig, exact truth), read back by its consumer's reader; the per-pixel uncertainty against finite
differences; report.html in a real headless browser."""

from __future__ import annotations

import json
import re
import shutil

import numpy as np
import pytest
import yaml

from benchmarks.export import disparity_errors, truth_pose
from conftest import assert_one_line_error, run_cli
from rgbd_gt.camera import Camera
from rgbd_gt.io import read_camera, read_pose, write_pose
from rgbd_gt.io.depth_file import read_depth_exr, read_exr, read_pfm, read_png16, write_pfm
from rgbd_gt.io.image import read_image

PHOTOS = ("photo", "photo_1", "right", "right_1")


@pytest.fixture(scope="module")
def exported(rig_run, tmp_path_factory):
    """(scene, the bundle's output, the export folder, the command's result): every format."""
    d, bout = rig_run
    out = tmp_path_factory.mktemp("export") / "dataset"
    proc = run_cli("export", bout, "-o", out, "--format", "plain,colmap", "--format", "nerfstudio", "-f", "middlebury,kitti")
    assert proc.returncode == 0, proc.stderr + proc.stdout
    return d, bout, out, proc


def test_plain_files_and_depth_against_the_truth(exported):
    d, bout, out, proc = exported
    cams = json.loads((out / "plain" / "cameras.json").read_text())
    assert "OpenCV" in cams["convention"] and sorted(cams["photos"]) == sorted(PHOTOS)
    for name in PHOTOS:
        e, folder = cams["photos"][name], out / "plain" / name
        T = read_pose(bout / name / "pose.yaml")[0]
        np.testing.assert_allclose(e["T_cam_from_scan_original"], T)
        assert e["original_camera"]["distortion"] and e["camera"]["model"] == "pinhole"
        assert (folder / "original.png").read_bytes() == (d / f"{name}.png").read_bytes()
        z, header = read_depth_exr(folder / "depth.exr")
        cam = Camera(**{k: e["camera"][k] for k in ("width", "height", "fx", "fy", "cx", "cy")})
        np.testing.assert_allclose(header["rgbd_gt_K"], cam.K)
        assert read_image(folder / "image.png").shape == (cam.height, cam.width, 3)
        mm = read_png16(folder / "depth.png")
        np.testing.assert_array_equal(mm, np.round(z.astype(np.float64) * 1000).astype(np.uint16))
        valid = read_image(folder / "valid.png")[..., 0] == 255
        near = read_image(folder / "near_edge.png")[..., 0] == 255
        assert not (valid & ((z == 0) | near)).any() and valid.mean() > 0.6 and near.any()
        normals = read_exr(folder / "normals.exr")[0]  # as export-depth --normals writes it
        np.testing.assert_array_equal(normals["Z"], z)
        n = np.stack([normals[f"N.{c}"] for c in "XYZ"], -1)[z > 0]
        assert np.allclose(np.linalg.norm(n, axis=1), 1, atol=1e-3) and set(read_exr(folder / "depth.exr")[0]) == {"Z"}
        sigma = read_exr(folder / "depth_sigma.exr")[0]
        assert (sigma["Z"][z > 0] > 0).all() and (sigma["Z"][z == 0] == 0).all()
        # the exported depth against the depth at the true pose (the pinhole camera turned by the
        # identity: the true pose is the original camera's)
        from rgbd_gt.prepared import prepare_scan
        from rgbd_gt.render.depth import render_depth

        prepared = prepare_scan(d / "scan.ply")
        T_true = truth_pose(d, name)
        truth = render_depth(prepared.subset(prepared.view_index(cam, T_true)), cam, T_true, normals=False).z
        both = valid & (truth > 0)
        err = np.abs(z[both] - truth[both])
        assert both.mean() > 0.6 and np.median(err) < 0.002 and np.mean(err > 0.02) < 0.005, (np.median(err), np.mean(err > 0.02))
    assert "export: 4 photos, 2 stereo pairs" in proc.stdout


def test_colmap_model_read_by_pycolmap(exported):
    pycolmap = pytest.importorskip("pycolmap", reason="pycolmap is not installed (pip install pycolmap)")
    d, bout, out, _ = exported
    model = pycolmap.Reconstruction(str(out / "colmap"))
    assert len(model.images) == 4 and len(model.cameras) == 2 and len(model.points3D) > 10000
    for image in model.images.values():
        name = image.name.rsplit(".", 1)[0]
        T = read_pose(bout / name / "pose.yaml")[0]
        np.testing.assert_allclose(image.cam_from_world().matrix(), T[:3], atol=1e-12)
        assert (out / "colmap" / "images" / image.name).is_file()
        # every observation is where COLMAP's own camera model projects its point
        cam = model.cameras[image.camera_id]
        obs = [p for p in image.points2D if p.has_point3D()][:500]
        xyz = np.array([model.points3D[p.point3D_id].xyz for p in obs])
        uv = np.array([cam.img_from_cam(T[:3, :3] @ x + T[:3, 3]) for x in xyz])
        xy = np.array([p.xy for p in obs])
        np.testing.assert_allclose(uv, xy, atol=2e-4)
        # and where ours puts it, in COLMAP's pixel convention (the top-left pixel's centre at 0.5)
        from rgbd_gt.camera import project

        ours = project(read_camera(bout / "cameras" / f"{'right' if name.startswith('right') else 'left'}.yaml"),
                       xyz @ T[:3, :3].T + T[:3, 3])[0]
        np.testing.assert_allclose(ours + 0.5, xy, atol=2e-4)


def test_nerfstudio_transforms_follow_its_conventions(exported):
    """transforms.json: camera-to-world with OpenGL axes (x right, y up, z back: nerfstudio's
    documented convention), depth PNGs in millimetres scaled by depth_unit_scale_factor. A pixel
    back-projected nerfstudio's way lands where the pose file's OpenCV camera puts it."""
    d, bout, out, _ = exported
    t = json.loads((out / "nerfstudio" / "transforms.json").read_text())
    assert t["camera_model"] == "PINHOLE" and t["depth_unit_scale_factor"] == 0.001 and len(t["frames"]) == 4
    for f in t["frames"]:
        name = f["file_path"].split("/")[-1].rsplit(".", 1)[0]
        depth = read_png16(out / "nerfstudio" / f["depth_file_path"]) * t["depth_unit_scale_factor"]
        assert read_image(out / "nerfstudio" / f["file_path"]).shape[:2] == depth.shape == (f["h"], f["w"])
        v, u = np.argwhere(depth > 0)[:: 997].T
        z = depth[v, u]
        # nerfstudio casts the ray of pixel (u, v) through (u + 0.5, v + 0.5) as (x, -y, -1) in
        # OpenGL camera axes, and depth is along the optical axis
        p_gl = np.stack([(u + 0.5 - f["cx"]) / f["fl_x"] * z, -(v + 0.5 - f["cy"]) / f["fl_y"] * z, -z, np.ones_like(z)])
        world = (np.array(f["transform_matrix"]) @ p_gl)[:3].T
        plain = json.loads((out / "plain" / "cameras.json").read_text())["photos"][name]
        T_pin, c = np.array(plain["T_cam_from_scan"]), plain["camera"]  # OpenCV's: pixel centres at integers
        cam = T_pin[:3, :3] @ world.T + T_pin[:3, 3:]
        np.testing.assert_allclose(cam[0] / cam[2] * c["fx"] + c["cx"], u, atol=1e-6)
        np.testing.assert_allclose(cam[1] / cam[2] * c["fy"] + c["cy"], v, atol=1e-6)
        np.testing.assert_allclose(cam[2], z, rtol=1e-9)


def test_stereo_pairs_against_the_truth(exported):
    """middlebury and kitti: the disparity of the solved rig against the truth (the targets:
    bad-0.5px at most 1 %, mean at most 0.1 px; measured 0.0004 % / 0.017 px)."""
    d, bout, out, _ = exported
    done = json.loads((out / "export.json").read_text())
    assert sorted(done["pairs"]) == ["000000", "000001"]
    rig = read_pose(d / "rig_gt.yaml")[0]
    for key, pair in done["pairs"].items():
        r = disparity_errors(d, bout, out, key, pair)
        assert r["bad_0_5"] <= 0.01 and r["mean_px"] <= 0.1 and r["kitti_noc_matches_mask"], r
        calib = dict(line.split("=", 1) for line in (out / "middlebury" / key / "calib.txt").read_text().splitlines())
        assert abs(float(calib["baseline"]) - np.linalg.norm(rig[:3, 3]) * 1e3) < 1.0
        assert float(calib["doffs"]) == 0 and int(calib["ndisp"]) % 16 == 0
        disp = read_pfm(out / "middlebury" / key / "disp0GT.pfm")
        mask = read_image(out / "middlebury" / key / "mask0nocc.png")[..., 0]
        assert set(np.unique(mask)) == {0, 128, 255} and np.isinf(disp[mask == 0]).all() and np.isfinite(disp[mask > 0]).all()
        occ = read_png16(out / "kitti" / "disp_occ_0" / f"{pair['kitti_index']:06d}_10.png")
        np.testing.assert_allclose(occ[mask > 0] / 256, disp[mask > 0], atol=1 / 512 + 1e-6)
        assert (occ[mask == 0] == 0).all()
        sigma = read_pfm(out / "middlebury" / key / "disp0GT_sigma.pfm")
        assert np.isinf(sigma[mask == 0]).all() and (sigma[mask > 0] > 0).all() and np.median(sigma[mask > 0]) < 0.05
        np.testing.assert_array_equal(read_pfm(out / "kitti" / "disp_sigma_0" / f"{pair['kitti_index']:06d}_10.pfm"), sigma)
        p3 = [l for l in (out / "kitti" / "calib_cam_to_cam" / f"{pair['kitti_index']:06d}.txt").read_text().splitlines()
              if l.startswith("P_rect_03")][0]
        P3 = np.array(p3.split()[1:], float).reshape(3, 4)
        assert abs(-P3[0, 3] / P3[0, 0] - float(calib["baseline"]) / 1e3) < 1e-9


def test_a_pair_that_rectifies_to_nothing_is_named():
    """fuzz seed 33: a left camera's principal point moved to x = 0 (a broken camera file of the
    run) rectified to a focal length of 1.1 million px that saw nothing, and export blamed the
    left photo's pose; it now names the pair. The same rig with its own camera rectifies."""
    from rgbd_gt.errors import InputError
    from rgbd_gt.export.stereo import rectify

    right = Camera(640, 480, 524.26, 524.68, 326.22, 244.99, (-0.1288, 0.0098, -0.0006, 0.0007, 0.0))
    left = Camera(640, 480, 459.79, 459.23, 319.0, 231.80, (-0.0792, 0.0056, -0.0005, 0.0003, 0.0))
    T_right = np.eye(4)
    T_right[:3, 3] = [-0.12, 0.0, 0.0]
    pair = rectify(left, np.eye(4), right, T_right)
    assert 459 < pair.left.camera.fx < 600 and abs(pair.baseline - 0.12) < 1e-9
    with pytest.raises(InputError, match=r"rectified, the two photos share almost no view \(a focal length of \d+ px"):
        rectify(Camera(640, 480, 459.79, 459.23, 0.0, 231.80, left.distortion), np.eye(4), right, T_right)


def test_pfm_round_trip_and_byte_order(tmp_path):
    a = np.random.default_rng(0).normal(size=(7, 5)).astype(np.float32)
    a[2, 3] = np.inf
    write_pfm(tmp_path / "a.pfm", a)
    np.testing.assert_array_equal(read_pfm(tmp_path / "a.pfm"), a)
    # a big-endian file (scale > 0), rows bottom to top, as the spec allows
    (tmp_path / "b.pfm").write_bytes(b"Pf\n5 7\n1.0\n" + a[::-1].astype(">f4").tobytes())
    np.testing.assert_array_equal(read_pfm(tmp_path / "b.pfm"), a)


def test_pixel_sigma_against_finite_differences():
    """The first-order depth and image-position sigma of pixels on a slanted plane against
    central differences of the exact depth along each pixel's ray under pose updates."""
    from rgbd_gt.export.uncertainty import pixel_sigma
    from rgbd_gt.pose import apply_update

    cam = Camera(40, 30, 50.0, 52.0, 19.0, 15.5)
    n_scan, d = np.array([0.3, -0.2, -1.0]), -2.0  # the plane n.p = d in the scan (= camera) frame
    n_scan, d = n_scan / np.linalg.norm(n_scan), d / np.linalg.norm(n_scan)
    u, v = np.meshgrid(np.arange(40.0), np.arange(30.0))
    rays = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1).reshape(-1, 3)

    def depth_at(T):  # the plane moved by T, met by each pixel's ray
        n = T[:3, :3] @ n_scan
        return ((d + n @ T[:3, 3]) / (rays @ n)).reshape(30, 40)

    z = depth_at(np.eye(4))
    normals = np.broadcast_to(n_scan * -np.sign(rays @ n_scan)[:, None], rays.shape).reshape(30, 40, 3)
    L = np.random.default_rng(1).normal(size=(6, 6)) * np.r_[[1e-3] * 3, [2e-3] * 3][:, None]
    cov = L @ L.T
    s = pixel_sigma(z.astype(np.float32), normals.astype(np.float32), cam, cov)
    h = 1e-6
    J = np.stack([(depth_at(apply_update(np.eye(4), h * e)) - depth_at(apply_update(np.eye(4), -h * e))) / (2 * h)
                  for e in np.eye(6)], -1)
    expect = np.sqrt(np.einsum("hwi,ij,hwj->hw", J, cov, J))
    np.testing.assert_allclose(s.depth, expect, rtol=1e-3)
    # image position: the point seen at the pixel, moved with the pose, reprojected
    p = rays.reshape(30, 40, 3) * z[..., None]

    def uv_at(T):
        q = p @ T[:3, :3].T + T[:3, 3]
        return np.stack([cam.fx * q[..., 0] / q[..., 2], cam.fy * q[..., 1] / q[..., 2]], -1)

    Juv = np.stack([(uv_at(apply_update(np.eye(4), h * e)) - uv_at(apply_update(np.eye(4), -h * e))) / (2 * h)
                    for e in np.eye(6)], -1)  # (H, W, 2, 6)
    M = np.einsum("hwai,ij,hwbj->hwab", Juv, cov, Juv)
    np.testing.assert_allclose(s.image, np.sqrt(np.linalg.eigvalsh(M)[..., -1]), rtol=1e-3)
    # the camera's: a focal length 1-sigma moves every ray but the principal point's
    def depth_f(f):
        r = np.stack([(u - cam.cx) / f, (v - cam.cy) / (f * cam.fy / cam.fx), np.ones_like(u)], -1)
        return d / (r @ n_scan)

    sf = pixel_sigma(z.astype(np.float32), normals.astype(np.float32), cam, np.zeros((6, 6)), {"focal_px": 0.7})
    expect = np.abs(depth_f(cam.fx + 1e-4) - depth_f(cam.fx - 1e-4)) / 2e-4 * 0.7
    np.testing.assert_allclose(sf.depth, expect, rtol=2e-3, atol=1e-7)


def test_pose_covariance_of_a_pose_file():
    """A pose file's covariance as written; else its stated uncertainty on every axis; a file that
    states none (written by hand, read as failed) is unknown, never exact."""
    from rgbd_gt.export.source import pose_covariance

    cov = np.diag(np.arange(1.0, 7.0))
    np.testing.assert_array_equal(pose_covariance({"covariance": cov.tolist()}), cov)
    stated = pose_covariance({"evidence": {"uncertainty": {"rotation_deg": 0.1, "translation_mm": 2.0}}})
    np.testing.assert_allclose(np.diag(stated), [np.radians(0.1) ** 2] * 3 + [0.002 ** 2] * 3)
    assert np.isposinf(np.diag(pose_covariance({}))).all()
    assert np.isposinf(np.diag(pose_covariance({"verdict": "failed", "evidence": {}}))).all()


def test_export_a_pose_of_unknown_uncertainty(rig_run, tmp_path):
    """A pose file written by hand (no verdict, no uncertainty) is exported only with --include
    failed, with no pixel valid; export.json stays strict JSON (null, not NaN)."""
    _, bout = rig_run
    run = tmp_path / "run"
    shutil.copytree(bout, run)
    write_pose(run / "right" / "pose.yaml", read_pose(bout / "right" / "pose.yaml")[0])
    proc = run_cli("export", run, "-o", tmp_path / "ds", "-f", "plain,middlebury", "--include", "failed")
    assert proc.returncode == 0, proc.stderr

    def strict(constant):
        raise AssertionError(f"export.json holds {constant}")

    photos = json.loads((tmp_path / "ds" / "export.json").read_text(), parse_constant=strict)["photos"]
    assert photos["right"]["verdict"] == "failed" and photos["right"]["valid"] == 0 and photos["right"]["depth_sigma_mm"] is None
    assert photos["photo"]["valid"] > 0 and photos["photo"]["depth_sigma_mm"]["p50"] > 0
    assert not read_image(tmp_path / "ds" / "plain" / "right" / "valid.png").any()
    assert "unknown (no pixel valid)" in proc.stdout


def test_export_again_replaces_its_formats(rig_run, tmp_path):
    """An export into the folder of an earlier one replaces each format's folder wholesale: no
    photo of the earlier data set stays among the new (a training loader globs the folders);
    what it does not write stays, and it says which formats those are."""
    _, bout = rig_run
    out = tmp_path / "dataset"
    assert run_cli("export", bout, "-o", out, "-f", "plain,colmap").returncode == 0
    (out / "plain" / "stale").mkdir()
    (out / "plain" / "stale" / "depth.exr").write_bytes(b"old")
    (out / "notes.txt").write_text("mine")
    proc = run_cli("export", bout, "-o", out, "-f", "plain")
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in (out / "plain").iterdir() if p.is_dir()) == sorted(PHOTOS)
    assert (out / "notes.txt").read_text() == "mine" and (out / "colmap").is_dir()
    assert "kept from an earlier export: colmap" in proc.stdout
    assert json.loads((out / "export.json").read_text())["formats"] == ["plain"]
    assert not [p for p in out.parent.iterdir() if p.name.startswith(".rgbd-gt")]


def test_export_errors(rig_run, tmp_path, synth_scene):
    d, bout = rig_run
    assert_one_line_error(run_cli("export", d, "-o", tmp_path / "x", "--format", "plain"), "not a finished run", str(d))
    assert_one_line_error(run_cli("export", bout, "-o", tmp_path / "x", "--format", "hdf5"), "--format", "hdf5")
    assert_one_line_error(run_cli("export", bout, "-o", tmp_path / "x", "-f", "plain", "--include", "maybe"), "--include", "got 'maybe'")
    assert_one_line_error(run_cli("export", bout, "-o", tmp_path / "x", "-f", "plain", "--include", "suspect", "--include", ""),
                          "--include: empty")
    # a bundle without a rig has no stereo pairs
    norig = tmp_path / "norig"
    shutil.copytree(bout, norig)
    (norig / "rig.yaml").unlink()
    assert_one_line_error(run_cli("export", norig, "-o", tmp_path / "x", "-f", "middlebury"), "stereo pairs",
                          "this run has no solved rig")
    # fuzz seed 25: a rig whose right photos are all left out said only what pairs need
    unpaired = tmp_path / "unpaired"
    shutil.copytree(bout, unpaired)
    for name in ("right", "right_1"):
        write_pose(unpaired / name / "pose.yaml", read_pose(bout / name / "pose.yaml")[0])  # no verdict: failed
    assert_one_line_error(run_cli("export", unpaired, "-o", tmp_path / "x", "-f", "middlebury"), "no shot has both of its "
                          "photos exported (left out: right (verdict failed), right_1 (verdict failed); see --include)")
    assert not (tmp_path / "x").exists()  # nothing half-written
    # broken files of the run: each named
    broken = tmp_path / "broken"
    shutil.copytree(bout, broken)
    pose = broken / "photo" / "pose.yaml"
    text = pose.read_text()
    # cut inside a flow collection ({...} or [...]), so the rest cannot read as whole YAML: a cut
    # at a line's end can (one run's digits put a third of the file just after "edges:")
    pose.write_text(text[:text.rfind(",", 0, len(text) // 3)])
    assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(pose))
    # cut at a line's end after the verdict: it read as whole YAML, and was exported as exact
    pose.write_text(text[:text.index("\nevidence:") + 1])
    assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(pose),
                          "states a verdict but no uncertainty")
    pose.write_text(re.sub(r"(covariance:\n- \[)[^,]+", r"\1.nan", text))
    assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(pose), "covariance: not finite")
    # fuzz seed 29: a row that is no row said numpy's "setting an array element with a sequence ..."
    doc = yaml.safe_load(text)
    doc["covariance"][1] = float("inf")
    pose.write_text(yaml.safe_dump(doc))
    assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(pose),
                          "covariance: not a 6 x 6 matrix of numbers (row 2 is inf)")
    for bad, said in ((text.replace("\nverdict: ok\n", "\nverdict: <b>ok</b>\n", 1), "verdict"),
                      (re.sub(r"\nreasons: .*\n", "\nreasons: [.inf]\n", text, count=1), "reasons"),
                      (re.sub(r"\nevidence:\n", "\nevidence: [1, 2]\nwas_evidence:\n", text, count=1), "evidence")):
        pose.write_text(bad)
        assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(pose), said)
    pose.write_text(text)
    rig = (broken / "rig.yaml").read_text()
    nan = yaml.safe_load(rig)
    nan["relative"]["right"]["sigma"]["translation_mm"][0] = float("nan")
    # fuzz seed 11: a rig.yaml of another format said "(string indices must be integers, not 'str')"
    for bad, said in ((b"\x92\x00garbage", "invalid YAML"), (b"ply format ascii", "not a mapping of keys (str)"),
                      (b"- 1\n- 2\n", "not a mapping of keys (list)"),
                      (yaml.safe_dump(nan).encode(), "translation_mm: not 3 numbers")):
        (broken / "rig.yaml").write_bytes(bad)
        assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(broken / "rig.yaml"), said)
    for bad, said in (("relative: null", "relative: not a mapping of cameras (None)"),
                      ("relative: {right: [1, 2]}", "relative.right: not a relative pose with its sigma ([1, 2])"),
                      # fuzz seed 43: a rig.yaml cut after `sigma:` was read as sigma 0, and stereo_pairs raised
                      ("relative: {right: {baseline_m: 0.12, sigma: null}}", "relative.right: not a relative pose with its sigma"),
                      ("relative: {right: {sigma: {rotation_deg: [0, 0, 0]}}}", "no 'translation_mm'")):
        (broken / "rig.yaml").write_text(f"cameras: [left, right]\n{bad}\n")
        assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(broken / "rig.yaml"),
                              "not a rig record rgbd-gt wrote", said)
    (broken / "rig.yaml").write_text(rig)
    camera = broken / "cameras" / "right.yaml"
    keys = yaml.safe_load(camera.read_text())
    camera.write_text(yaml.safe_dump({**keys, "sigma": {"focal_px": "many"}}))
    assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(camera), "sigma")
    # fuzz seed 35: a camera for another photo size was taken, and plain's image.png resampled to it
    camera.write_text(yaml.safe_dump({**keys, "height": 123}))
    for fmt in ("plain", "kitti"):
        assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", fmt), str(camera), "is for 640x123")
    camera.write_text(yaml.safe_dump(keys))
    record = (broken / "bundle.json").read_text()
    # a damaged SHA-1 is the record's fault, not a changed scan's (fuzz seed 9: "the scan then had SHA-1 ):")
    (broken / "bundle.json").write_text(json.dumps({**json.loads(record), "scan_sha1": ""}))
    assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(broken / "bundle.json"),
                          "scan_sha1: not a SHA-1 ('')")
    # fuzz seed 24: a damaged bundle_sha1 said the bundle file had changed since the solve
    (broken / "bundle.json").write_text(json.dumps({**json.loads(record), "bundle_sha1": "378e-inf"}))
    assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(broken / "bundle.json"),
                          "bundle_sha1: not a SHA-1 ('378e-inf')")
    # fuzz seed 11: an empty record said "cannot read (Expecting value: line 1 column 1 (char 0))"
    for bad, said in (("{", "invalid JSON (Expecting property name enclosed in double quotes, line 1)"),
                      ("", "empty: not a record rgbd-gt wrote"), ("[1]", "(a JSON list, not an object)")):
        (broken / "bundle.json").write_text(bad)
        assert_one_line_error(run_cli("export", broken, "-o", tmp_path / "x", "-f", "plain"), str(broken / "bundle.json"),
                              said)
    assert_one_line_error(run_cli("export", bout, "-o", bout / "photo" / "pose.yaml", "-f", "plain"), "-o")
    assert_one_line_error(run_cli("export", bout, "-o", bout, "-f", "plain"), "-o", "the run's own folder")
    assert not (tmp_path / "x").exists()


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (apt-get install chromium)")
def test_report_in_a_headless_browser(exported, tmp_path):
    """report.html in chromium: every image loads, the table sorts by verdict, the page's numbers
    equal the pose files'."""
    from rgbd_gt.export.report import write_report
    from rgbd_gt.export.source import read_run, stated_uncertainty

    playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    d, bout, out, _ = exported
    pose = {n: yaml.safe_load((bout / n / "pose.yaml").read_text()) for n in PHOTOS}
    # a copy of the run whose verdicts differ, for the sort
    mixed = tmp_path / "mixed"
    shutil.copytree(bout, mixed)
    for name, verdict in (("photo_1", "failed"), ("right", "suspect")):
        f = mixed / name / "pose.yaml"
        f.write_text(f.read_text().replace("\nverdict: ok\n", f"\nverdict: {verdict}\n", 1))
    write_report(mixed / "report.html", read_run(mixed))
    with playwright.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"])
        try:
            page = browser.new_page()
            page.goto((out / "report.html").as_uri())
            page.wait_for_load_state("load")
            sizes = page.evaluate("Array.from(document.images).map(i => [i.complete, i.naturalWidth])")
            # per photo: its thumbnail and the depth preview (a bundle has no overlays); a pair each shot
            assert len(sizes) == 2 * 4 + 2 and all(ok and w > 0 for ok, w in sizes), sizes
            for name in PHOTOS:
                u = pose[name]["evidence"]["tiles"]["uncertainty"]  # what the pose file's covariance states
                assert u == stated_uncertainty(pose[name]["evidence"])
                for key in ("rotation_deg", "translation_mm", "image_px"):
                    text = page.inner_text(f'[id="{name}"] [data-key="{key}"]')
                    assert text == format(u[key], ".4g"), (name, key, text)
                assert page.inner_text(f'[id="{name}"] [data-key="verdict"]') == pose[name]["verdict"]
            names = lambda: page.eval_on_selector_all("#photos tbody tr", "rs => rs.map(r => r.cells[0].innerText)")
            before = names()
            page.click("#photos th[data-col='0']")
            assert names() == sorted(before)
            page.click("#photos th[data-col='0']")
            assert names() == sorted(before, reverse=True)
            page.goto((mixed / "report.html").as_uri())
            page.wait_for_load_state("load")
            verdicts = lambda: page.eval_on_selector_all("#photos tbody tr", "rs => rs.map(r => r.cells[1].innerText)")
            assert sorted(verdicts()) == ["failed", "ok", "ok", "suspect"]
            page.click("#photos th[data-col='1']")
            assert verdicts() == ["ok", "ok", "suspect", "failed"]
            page.click("#photos th[data-col='1']")
            assert verdicts() == ["failed", "suspect", "ok", "ok"]
            assert page.inner_text('[id="photo_1"] [data-key="verdict"]') == "failed"
        finally:
            browser.close()
