"""rgbd-gt pick in a real headless browser: Debian's chromium driven by Playwright clicks pairs of
points on a synthetic scene (photo pixel, scan grid pixel); the page's live pose and the
written PAIRS.csv are checked against the truth."""

import csv
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import _need, assert_one_line_error, run_cli
from rgbd_gt.camera import project
from rgbd_gt.init.pick import grid_panorama
from rgbd_gt.io import load_scan, read_camera, read_pose
from rgbd_gt.pose import rotation_error_deg, transform_points, translation_error_m
from rgbd_gt.render.depth import render_depth

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
playwright = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (apt-get install chromium)")


def _start_pick(*args) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-c", "from rgbd_gt.cli import main; main()", "pick", *map(str, args), "--no-browser"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    assert "serving the pick page on http://127.0.0.1:" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
    return proc, line.split(" on ")[1].split()[0]


def _chosen_pairs(scene: Path, n: int = 9):
    """n scan grid points seen in the photo, spread over it: (photo uv, panorama pixel, xyz)."""
    scan = load_scan(scene / "scan.ply")
    cam = read_camera(scene / "camera.yaml")
    T = read_pose(scene / "gt_pose.yaml")[0]
    view = grid_panorama(scan)
    uv, z = project(cam, transform_points(T, scan.xyz))
    depth = render_depth(scan, cam, T).z
    px = np.round(uv).astype(int)
    inside = (z > 0) & np.all(px >= 20, 1) & (px[:, 0] < cam.width - 20) & (px[:, 1] < cam.height - 20)
    seen = np.zeros(len(z), bool)
    seen[inside] = np.abs(depth[px[inside, 1], px[inside, 0]] - z[inside]) < 0.01
    rng = np.random.default_rng(0)
    # one point per cell of a 3 x 3 grid over the photo
    out = []
    for gy in range(3):
        for gx in range(3):
            cell = np.nonzero(seen & (px[:, 0] * 3 // cam.width == gx) & (px[:, 1] * 3 // cam.height == gy))[0]
            k = rng.choice(cell)
            y, x = np.argwhere(np.all(view.xyz == scan.xyz[k].astype(np.float32), axis=2))[0]
            out.append((uv[k], (x + 0.5, y + 0.5), scan.xyz[k]))
    return out[:n]


def _pick_in_browser(args: list, clicks: list, shot: Path, label: str | None = None) -> tuple[dict, subprocess.CompletedProcess]:
    """Start `rgbd-gt pick` with args, click each pair (photo pixel uv, scan image pixel) in a
    headless chromium, optionally label the first pair, show the overlay, take a screenshot and
    'Save and close'. Returns the page's live solution and the finished command."""
    proc, url = _start_pick(*args)
    try:
        with playwright.sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=[
                "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
                "--disable-sync", "--no-first-run"])
            page = browser.new_page(viewport={"width": 1600, "height": 1000})
            page.goto(url)
            page.wait_for_function("window.picker && window.picker.ready")
            for k, (uv, scan_px) in enumerate(clicks):
                x, y = page.evaluate(f"window.picker.photo.toScreen({uv[0] + 0.5}, {uv[1] + 0.5})")
                page.mouse.click(x, y)
                x, y = page.evaluate(f"window.picker.scan.toScreen({scan_px[0]}, {scan_px[1]})")
                page.mouse.click(x, y)
                page.wait_for_function(f"window.picker.pairs.length === {k + 1}")
            page.wait_for_function("window.picker.solution !== null")
            solution = page.evaluate("window.picker.solution")
            solution["rows"] = page.locator("#pairs tbody tr").count()
            if label is not None:
                page.locator("#pairs tbody tr input").first.fill(label)
                page.locator("#pairs tbody tr input").first.dispatch_event("change")
            page.click("#show-overlay")
            page.screenshot(path=str(shot))
            page.click("#done")
            proc.wait(timeout=30)
            browser.close()
    finally:
        if proc.poll() is None:
            proc.kill()
    return solution, subprocess.CompletedProcess(proc.args, proc.returncode, proc.stdout.read(), proc.stderr.read())


def test_pick_pairs_in_a_browser(tmp_path, synth_scene):
    scene = tmp_path / "scene"
    synth_scene(scene, 6)
    pairs = _chosen_pairs(scene)
    out = tmp_path / "pairs.csv"
    solution, proc = _pick_in_browser(["--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera",
                                       scene / "camera.yaml", "-o", out], [(uv, px) for uv, px, _ in pairs],
                                      tmp_path / "page.png", label="corner A")
    assert proc.returncode == 0, proc.stderr
    assert solution["rows"] == len(pairs)
    # the live pose is the truth's, to what clicks on whole screen pixels allow
    T_true = read_pose(scene / "gt_pose.yaml")[0]
    T = np.array(solution["T_cam_from_scan"])
    assert translation_error_m(T, T_true) < 0.02 and rotation_error_deg(T, T_true) < 0.3
    assert solution["inliers"] == len(pairs) and solution["rms_px"] < 1.0
    # the CSV: every pair, its scan point exactly the grid point clicked, its photo pixel within a pixel
    rows = list(csv.DictReader(open(out)))
    assert [r["label"] for r in rows] == ["corner A"] + [str(k) for k in range(2, len(pairs) + 1)]
    for r, (uv, _, xyz) in zip(rows, pairs):
        np.testing.assert_allclose([float(r[c]) for c in "xyz"], xyz, atol=1e-5)
        assert np.hypot(float(r["u"]) - uv[0], float(r["v"]) - uv[1]) < 1.0
    # and init-pose takes it as it is
    assert run_cli("init-pose", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera",
                   scene / "camera.yaml", "--correspondences", out, "-o", tmp_path / "init.yaml").returncode == 0


def test_pick_on_a_real_sweep(tmp_path):
    """A real LiDAR sweep (PJLab scene 3) from a rough extrinsic (the reference 1 deg and 10 cm
    off): the scan image shows the points seen from it as dots, a click lands on a laser return,
    and pairs whose photo pixels are the reference's projections of those returns give the
    reference back."""
    import yaml

    from benchmarks.lidar import init_poses
    from rgbd_gt.init.pick import click_view
    from rgbd_gt.prepared import whole_scan

    folder = _need("lidar_camera") / "pjlab_3"
    cam = read_camera(folder / "calib.txt", (1920, 1200))
    T_ref = read_pose(folder / "calib.txt")[0]
    init = tmp_path / "rough.yaml"
    init.write_text(yaml.safe_dump({"T_cam_from_scan": init_poses(T_ref, 1.0, 0.10, 1, seed=3)[0].tolist()}))
    view = click_view(whole_scan(folder / "calib.pcd", None), "auto", cam, read_pose(init)[0])
    assert view.kind == "the scan's points seen from the initial pose"
    # 12 returns spread over the photo (a 4 x 3 grid), each at the centre of its dot
    ys, xs = np.nonzero(np.isfinite(view.xyz[..., 0]))
    xyz = view.xyz[ys, xs].astype(float)
    uv, z = project(cam, transform_points(T_ref, xyz))
    inside = (z > 0) & np.all(uv > 30, 1) & (uv[:, 0] < cam.width - 30) & (uv[:, 1] < cam.height - 30)
    rng = np.random.default_rng(0)
    clicks, points = [], []
    for gy in range(3):
        for gx in range(4):
            cell = np.nonzero(inside & (uv[:, 0] * 4 // cam.width == gx) & (uv[:, 1] * 3 // cam.height == gy))[0]
            if len(cell) == 0:
                continue
            k = rng.choice(cell)
            dot = np.all(view.xyz == view.xyz[ys[k], xs[k]], axis=2)  # the return's whole square
            dy, dx = np.argwhere(dot).mean(0)
            clicks.append((uv[k], (dx + 0.5, dy + 0.5)))
            points.append(xyz[k])
    assert len(clicks) >= 9
    out = tmp_path / "pairs.csv"
    solution, proc = _pick_in_browser(["--scan", folder / "calib.pcd", "--image", folder / "calib.png", "--camera",
                                       folder / "calib.txt", "--init", init, "-o", out], clicks, tmp_path / "page.png")
    assert proc.returncode == 0, proc.stderr
    rows = list(csv.DictReader(open(out)))
    np.testing.assert_allclose([[float(r[c]) for c in "xyz"] for r in rows], points, atol=1e-5)  # the returns clicked
    T = np.array(solution["T_cam_from_scan"])
    # clicks land on whole screen pixels (about 2.4 photo pixels here) and the points lie 5-60 m away
    assert rotation_error_deg(T, T_ref) < 0.1 and translation_error_m(T, T_ref) < 0.05, (rotation_error_deg(T, T_ref), translation_error_m(T, T_ref))
    assert solution["inliers"] == len(clicks)


def test_pick_errors(tmp_path, synth_scene):
    scene = tmp_path / "scene"
    synth_scene(scene, 7)
    args = ["pick", "--scan", scene / "scan.ply", "--image", scene / "photo.png", "--no-browser"]
    assert_one_line_error(run_cli(*args, "-o", tmp_path / "p.txt"), "p.txt", ".csv")
    (tmp_path / "a_file").write_text("x")
    assert_one_line_error(run_cli(*args, "-o", tmp_path / "a_file" / "p.csv"), "it is a file, not a folder")
    assert_one_line_error(run_cli(*args, "-o", tmp_path / "p.csv", "--view", "sideways"), "--view")
    assert_one_line_error(run_cli(*args, "-o", tmp_path / "p.csv", "--init", scene / "gt_pose.yaml"), "--init needs --camera")
    assert not (tmp_path / "p.csv").exists()


def test_pick_server_answers_bad_requests_with_errors(tmp_path, synth_scene):
    """Requests the page never sends (made by hand, or by another tool): an error answer each,
    no traceback in the terminal, and no pair that is not finite saved."""
    import json
    import urllib.error
    import urllib.request

    scene = tmp_path / "scene"
    synth_scene(scene, 7)
    out = tmp_path / "p.csv"
    proc, url = _start_pick("--scan", scene / "scan.ply", "--image", scene / "photo.png", "--camera", scene / "camera.yaml",
                            "-o", out)

    def ask(path: str, body: bytes | None = None, headers: dict | None = None) -> tuple[int, dict]:
        request = urllib.request.Request(url + path, data=body, headers=headers or {})
        try:
            with urllib.request.urlopen(request, timeout=30) as r:
                return r.status, json.loads(r.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    try:
        pair = {"u": 1, "v": 2, "x": 0.5, "y": 1.5, "z": 1.0}
        for body in ([1], {"pairs": "abc"}, {"pairs": [1, 2]}, {"pairs": [{**pair, "u": "a"}]}, {"pairs": [{**pair, "x": True}]}):
            for api in ("solve", "save"):
                code, answer = ask(f"api/{api}", json.dumps(body).encode())
                assert code == 200 and answer["ok"] is False and "pair" in answer["error"], (api, body, answer)
        code, answer = ask("api/save", b'{"pairs": [{"u": 1e400, "v": 2, "x": 0.5, "y": 1.5, "z": 1.0}]}')
        assert answer["error"] == "pair 1: u must be a finite number, got inf"
        assert ask("api/solve", b"\xff\xfe")[0] == 400
        assert ask("api/solve", b"{}", {"Content-Length": "abc"})[0] == 400
        for query in ("x=inf&y=1", "x=nan&y=1", "x=1", "x=a&y=2"):
            assert ask(f"api/point?{query}")[0] == 400, query
        assert ask("api/point?x=10&y=10")[0] == 200
        assert ask("api/quit", b"{}")[1] == {"ok": True}
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and proc.stderr.read() == ""
    assert not out.exists()


def test_click_views_know_their_points(tmp_path, synth_scene):
    """Each scan image (grid, panorama from the origin, view at a pose) gives, under a pixel, a
    scan point that the view itself put there (no browser needed)."""
    from rgbd_gt.init.pick import click_view
    from rgbd_gt.scan import Scan

    scene = tmp_path / "scene"
    synth_scene(scene, 9)
    scan = load_scan(scene / "scan.ply")
    cam = read_camera(scene / "camera.yaml")
    T = read_pose(scene / "gt_pose.yaml")[0]
    loose = Scan(xyz=scan.xyz, rgb=scan.rgb, origins=scan.origins)
    views = {"grid": click_view(scan, "auto"), "panorama": click_view(loose, "auto"), "pose": click_view(scan, "auto", cam, T)}
    assert [v.kind.split()[0] for v in views.values()] == ["the", "a", "the"] and "grid" in views["grid"].kind
    for name, view in views.items():
        have = np.argwhere(np.isfinite(view.xyz[..., 0]))
        assert len(have) > 0.2 * view.xyz[..., 0].size, name
        rng = np.random.default_rng(0)
        for y, x in have[rng.choice(len(have), 50)]:
            p = view.point_at(x + 0.5, y + 0.5)
            np.testing.assert_allclose(p, view.xyz[y, x], atol=1e-6)
            px, py = view.pixel_of(p)  # the same point, possibly at another pixel that holds it too
            np.testing.assert_allclose(view.xyz[int(py), int(px)], p, atol=1e-6)
    # the pose view's points are where the camera sees them: a pixel's point projects back onto it
    pose = views["pose"]
    ys, xs = np.nonzero(np.isfinite(pose.xyz[..., 0]))
    uv, _ = project(cam, transform_points(T, pose.xyz[ys, xs].astype(float)))
    assert np.median(np.hypot(uv[:, 0] - xs, uv[:, 1] - ys)) < 0.5
    # the grid's points are the scan's own; the panorama's too
    own = set(map(tuple, scan.xyz.astype(np.float32).tolist()))
    for name in ("grid", "panorama"):
        pts = views[name].xyz[np.isfinite(views[name].xyz[..., 0])]
        assert all(tuple(p) in own for p in pts[:: max(1, len(pts) // 500)].tolist()), name
