"""Scale: the prepared scan (cache, spatial index, views) gives what the whole scan gives, and a
site of several scans runs the same in this process, in local workers and on a Ray cluster
started on loopback."""

import csv
import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import assert_one_line_error, run_cli
from rgbd_gt.init.detect import BoardSpec
from rgbd_gt.init.run import board_in_scan
from rgbd_gt.io import load_scan, read_camera, read_pose, save_scan
from rgbd_gt.prepared import prepare_scan
from rgbd_gt.render.blocks import block_points, points_in_view
from rgbd_gt.render.depth import render_depth
from rgbd_gt.render.normals import with_normals


@pytest.fixture(scope="module")
def scenes(tmp_path_factory, synth_scene):
    root = tmp_path_factory.mktemp("scale")
    for seed, photos in ((2, 2), (5, 1)):
        synth_scene(root / f"s{seed}", seed, photos)
    return root


def test_prepared_scan_gives_what_the_whole_scan_gives(scenes, tmp_path):
    path = scenes / "s2" / "scan.e57"
    scan = with_normals(load_scan(path))
    cache = tmp_path / "cache"
    p = prepare_scan(path, cache)
    assert len(p) == len(scan) and p.arrays["xyz"].dtype == np.float32
    # the same points, block-ordered: matched through their grid cells
    whole = p.subset(slice(None))
    a, b = np.lexsort((scan.col, scan.row)), np.lexsort((whole.col, whole.row))
    np.testing.assert_allclose(whole.xyz[b], scan.xyz[a], atol=2e-6)
    np.testing.assert_array_equal(whole.rgb[b], scan.rgb[a])
    np.testing.assert_allclose(whole.normals[b], scan.normals[a], atol=1e-6)
    # reopening reads the cache; nothing is rebuilt
    stamp = (p.folder / "xyz.npy").stat().st_mtime_ns
    assert prepare_scan(path, cache).folder == p.folder and (p.folder / "xyz.npy").stat().st_mtime_ns == stamp

    camera = read_camera(scenes / "s2" / "camera.yaml")
    T = read_pose(scenes / "s2" / "gt_pose.yaml")[0]
    view = p.view(camera, T)
    inside = points_in_view(scan.xyz, camera, T)
    assert len(view) == inside.sum() and 0 < len(view) < len(scan)
    # the photo's depth from its view is the depth from the whole scan
    d_view, d_all = render_depth(view, camera, T, normals=False), render_depth(scan, camera, T, normals=False)
    # (a ray through a shared triangle edge may hit or miss by float rounding: a few pixels in 10^5)
    both = (d_view.z > 0) & (d_all.z > 0)
    assert both.sum() > 0.9999 * (d_all.z > 0).sum() and abs(int((d_view.z > 0).sum()) - int((d_all.z > 0).sum())) < 20
    # float32 rounding of the cached coordinates and of the two meshes' local frames: microns,
    # tens of microns where a ray grazes a crease between two triangles
    diff = np.abs(d_view.z[both] - d_all.z[both])
    assert np.median(diff) < 1e-6 and diff.max() < 5e-5
    assert d_view.back_facing == d_all.back_facing

    # the board: found once, the same as the search on the loaded scan, then read from the cache
    spec = BoardSpec(9, 6, 0.05)
    board = p.board(spec)
    direct = board_in_scan(scan, spec)
    np.testing.assert_allclose(board.corners, direct.corners, atol=1e-4)
    assert len(board.near_xyz) == len(direct.near_xyz)
    np.testing.assert_allclose(p.board(spec).corners, board.corners)

    # the points around a camera (the verticals check): the blocks within reach, every k-th point
    centre = -T[:3, :3].T @ T[:3, 3]
    near = p.xyz_around(centre, 2.0, 10**9)
    box = np.all(np.abs(scan.xyz - centre) <= 2.0, axis=1)
    assert box.sum() <= len(near) < len(scan)  # whole blocks: a few points beyond the box too
    meet = p._meeting(centre - 2.0, centre + 2.0)
    for step in (1, 7, 1000):
        np.testing.assert_array_equal(block_points(p.blocks, meet, step), block_points(p.blocks, meet)[::step])
    assert len(p.xyz_around(centre, 2.0, 1000)) <= 1000


def test_single_commands_read_the_prepared_scan(scenes, tmp_path):
    """init-pose and export-depth with --cache: the same pose and depth as from the scan file; the
    board is searched once and read from the cache by the next init-pose; a cache path that is a
    file is a one-line error."""
    from rgbd_gt.io.depth_file import read_depth_exr

    d, cache = scenes / "s2", tmp_path / "cache"
    common = ["--scan", d / "scan.e57", "--camera", d / "camera.yaml"]
    for name, extra in (("plain", []), ("cached", ["--cache", cache]), ("again", ["--cache", cache])):
        proc = run_cli("init-pose", *common, "--image", d / "photo.png", "-o", tmp_path / f"init_{name}.yaml", *extra)
        assert proc.returncode == 0, proc.stderr
        if name != "again":
            proc = run_cli("export-depth", *common, "--pose", d / "gt_pose.yaml", "-o", tmp_path / f"depth_{name}.exr", *extra)
            assert proc.returncode == 0, proc.stderr
    (folder,) = cache.iterdir()
    assert list(folder.glob("board-*.npz")) and (folder / "cells.npy").exists()
    T = read_pose(tmp_path / "init_plain.yaml")[0]
    for name in ("cached", "again"):
        np.testing.assert_allclose(read_pose(tmp_path / f"init_{name}.yaml")[0], T, atol=1e-6)
    z = read_depth_exr(tmp_path / "depth_plain.exr")[0]
    zc = read_depth_exr(tmp_path / "depth_cached.exr")[0]
    assert (z > 0).mean() > 0.5 and np.array_equal(zc, z)  # the same points, normals and triangles
    (tmp_path / "afile").write_text("x")
    proc = run_cli("export-depth", *common, "--pose", d / "gt_pose.yaml", "-o", tmp_path / "d.exr", "--cache", tmp_path / "afile")
    assert proc.returncode == 2 and proc.stderr.startswith("error: ") and "--cache" in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_stored_coordinates_keep_microns_whatever_the_file_says():
    """The cache's float32 coordinates are measured from the scanner when it stands among its
    points, else from their median: a stray point or a wrong origin in a header far away must not
    take the precision of the others (a fuzzed header origin of 1e20 once emptied every view)."""
    from rgbd_gt.scan import Scan
    from rgbd_gt.prepared import storage_centre

    rng = np.random.default_rng(0)
    xyz = rng.uniform(-20, 20, (5000, 3)) + [4.5e5, 5.4e6, 300.0]  # georeferenced metres
    stray = np.vstack([xyz, [1e12, 0.0, 0.0]])
    for origins, centre in (([[4.5e5, 5.4e6, 301.0]], [4.5e5, 5.4e6, 301.0]),  # the scanner, among its points
                            ([[1e20, 0.0, 0.0]], None), ([], None)):  # a wrong header, none: the median
        scan = Scan(xyz=stray, origins=np.array(origins, float).reshape(-1, 3))
        c = storage_centre(scan)
        if centre is not None:
            np.testing.assert_array_equal(c, centre)
        stored = (xyz - c).astype(np.float32).astype(np.float64) + c  # as the prepared scan holds them
        assert np.abs(stored - xyz).max() < 5e-6  # float32 of metres within 40 m of c


def test_a_changed_scan_file_is_prepared_again(scenes, tmp_path):
    path = tmp_path / "scan.ply"
    shutil.copy(scenes / "s5" / "scan.ply", path)
    cache = tmp_path / "cache"
    first = prepare_scan(path, cache)
    scan = load_scan(path)
    scan.xyz = scan.xyz + [0.01, 0, 0]
    save_scan(path, scan)
    second = prepare_scan(path, cache)
    assert second.folder != first.folder and not first.folder.exists()  # the stale cache is gone
    np.testing.assert_allclose(np.sort(second.subset(slice(None)).xyz[:, 0]), np.sort(scan.xyz[:, 0]), atol=2e-6)


def test_a_key_taken_of_the_file_as_it_is_spares_hashing_it_again(scenes, tmp_path):
    """export checks a scan against its solve by its SHA-1 (`file_key`) and hands that key to
    prepare_scan, which then reads the file only to prepare it; a key of the file before it was
    rewritten (another size or time) is not trusted: the file is hashed and prepared anew."""
    from rgbd_gt.prepared import file_key

    path = tmp_path / "scan.ply"
    shutil.copy(scenes / "s5" / "scan.ply", path)
    cache, said = tmp_path / "cache", []
    key = file_key(path)
    first = prepare_scan(path, cache, said.append, key=key)
    assert "hashing the scan file" not in said and first.sha1 == key["sha1"]
    scan = load_scan(path)
    scan.xyz = scan.xyz + [0.01, 0, 0]
    save_scan(path, scan)
    said.clear()
    second = prepare_scan(path, cache, said.append, key=key)  # the key of the file before
    assert "hashing the scan file" in said and second.sha1 == file_key(path)["sha1"] != key["sha1"]
    np.testing.assert_allclose(np.sort(second.subset(slice(None)).xyz[:, 0]), np.sort(scan.xyz[:, 0]), atol=2e-6)


def test_a_damaged_cache_is_prepared_again(scenes, tmp_path):
    """A cache file cut short, emptied or overwritten (a full disk, a copy stopped halfway) is not
    read as the scan: prepare_scan makes the cache again; a caller that opens it without checking
    (open_prepared) gets one `error:` naming the folder."""
    from rgbd_gt.errors import InputError
    from rgbd_gt.prepared import open_prepared

    path = scenes / "s5" / "scan.ply"
    first = prepare_scan(path, tmp_path / "cache")
    folder, xyz = first.folder, np.array(first.arrays["xyz"])
    del first
    for name, damage in (("xyz.npy", lambda b: b[: len(b) // 2]), ("normals.npy", lambda b: b""),
                         ("blocks.npz", lambda b: b"\x00" * 300), ("blocks.npz", lambda b: b[:1000])):
        f = folder / name
        f.write_bytes(damage(f.read_bytes()))
        with pytest.raises(InputError, match="damaged") as exc:
            open_prepared(folder, path)
        assert str(exc.value).startswith(f"{folder}: ")
        again = prepare_scan(path, tmp_path / "cache")
        assert again.folder == folder
        np.testing.assert_array_equal(again.arrays["xyz"], xyz)
        assert len(again.arrays["normals"]) == len(xyz)
    # fuzz seed 15: a number of meta.json changed (the points' centre) moved every point, and export
    # said the photo had no scan points in view; its digest no longer matches, so it is made again
    meta = json.loads((folder / "meta.json").read_text())
    (folder / "meta.json").write_text(json.dumps({**meta, "centre": [1e12, *meta["centre"][1:]]}))
    again = prepare_scan(path, tmp_path / "cache")
    assert json.loads((folder / "meta.json").read_text())["centre"] == meta["centre"]
    np.testing.assert_array_equal(again.whole().xyz, prepare_scan(path).whole().xyz)


def test_a_run_that_prepared_the_same_scan_meanwhile_keeps_its_cache(scenes, tmp_path):
    """Two runs started together on one output folder both prepare the scan: the second to finish
    keeps the first's cache (which the first has open) instead of replacing it under it."""
    from rgbd_gt.prepared import _build, file_key

    path = scenes / "s5" / "scan.ply"
    first = prepare_scan(path, tmp_path / "cache")
    meta = first.folder / "meta.json"
    stamp, xyz = meta.stat().st_mtime_ns, np.array(first.arrays["xyz"])
    _build(path, first.folder, file_key(path), lambda msg: None)  # the other run, which began before this one finished
    assert meta.stat().st_mtime_ns == stamp
    assert [p.name for p in (tmp_path / "cache").iterdir()] == [first.folder.name]  # its staging folder is gone
    np.testing.assert_array_equal(first.arrays["xyz"], xyz)
    first.board(BoardSpec(9, 6, 0.05), path)
    assert [p.name for p in first.folder.glob(".*")] == []  # the board written through a temporary file of its own


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _rows(out: Path) -> dict:
    drop = ("seconds", "steps", "skipped")  # how long it took (and, resumed, what was done) differs; what it found must not
    return {(r["scan"], r["photo"]): {k: v for k, v in r.items() if k not in drop}
            for r in csv.DictReader(open(out / "summary.csv"))}


def _outputs(out: Path) -> set:
    return {p.relative_to(out) for p in out.rglob("*") if p.is_file() and ".scan-cache" not in p.parts}


def test_site_runs_the_same_locally_in_workers_and_on_ray(scenes, tmp_path):
    pytest.importorskip("ray")
    site = {"camera": str(scenes / "s2" / "camera.yaml"), "refine": {"max_points": 20000},
            "scans": [{"scan": str(scenes / "s2" / "scan.e57"), "photos": [str(scenes / "s2" / "photo*.png")], "name": "room_a"},
                      {"scan": str(scenes / "s5" / "scan.ply"), "camera": str(scenes / "s5" / "camera.yaml"),
                       "photos": [str(scenes / "s5" / "photo.png")], "name": "room_b"}]}
    outs = {}
    for name, extra in (("local", []), ("workers", ["--workers", "2"])):
        (tmp_path / f"{name}.yaml").write_text(yaml.safe_dump({**site, "output": f"out_{name}"}))
        proc = run_cli("run", tmp_path / f"{name}.yaml", *extra)
        assert proc.returncode == 0, proc.stderr
        outs[name] = tmp_path / f"out_{name}"

    port = _free_port()
    assert_one_line_error(run_cli("run", tmp_path / "local.yaml", "--ray", "127.0.0.1:99999"), "give HOST:PORT", "port 1-65535")
    assert_one_line_error(run_cli("run", tmp_path / "local.yaml", "--ray", f"127.0.0.1:{port}"), "no Ray cluster answers there")
    temp = Path(f"/tmp/rgbd-gt-ray-{os.getpid()}")
    ray_cli = [sys.executable, "-m", "ray.scripts.scripts"]
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    subprocess.run(ray_cli + ["start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port), "--num-cpus", "2",
                              "--include-dashboard", "false", "--temp-dir", str(temp), "--disable-usage-stats"],
                   check=True, capture_output=True, env=env, timeout=180)
    try:
        (tmp_path / "ray.yaml").write_text(yaml.safe_dump({**site, "output": "out_ray"}))
        proc = run_cli("run", tmp_path / "ray.yaml", "--ray", f"127.0.0.1:{port}")
        assert proc.returncode == 0, proc.stderr
        outs["ray"] = tmp_path / "out_ray"
        again = run_cli("run", tmp_path / "ray.yaml", "--ray", f"127.0.0.1:{port}")  # resumes: nothing left to do
        assert again.returncode == 0, again.stderr
    finally:
        subprocess.run(ray_cli + ["stop", "--force"], capture_output=True, env=env, timeout=120)
        shutil.rmtree(temp, ignore_errors=True)
    assert "ray" in outs

    rows = _rows(outs["local"])
    assert {k[0] for k in rows if k[0]} == {"room_a", "room_b"} and len([k for k in rows if k[0]]) == 3
    assert all(r["verdict"] == "ok" for k, r in rows.items() if k[0]), rows
    for name in ("workers", "ray"):
        assert _outputs(outs[name]) == _outputs(outs["local"]), name
        other = _rows(outs[name])
        assert other.keys() == rows.keys()
        for key, r in rows.items():  # torch's thread count differs: sums in another order
            for col, v in r.items():
                try:
                    assert abs(float(v) - float(other[key][col])) <= 1e-3 * max(1.0, abs(float(v))), (name, key, col)
                except ValueError:
                    assert v == other[key][col], (name, key, col)
        for scan, photo in (("room_a", "photo"), ("room_a", "photo_1"), ("room_b", "photo")):
            T = read_pose(outs["local"] / scan / photo / "pose.yaml")[0]
            np.testing.assert_allclose(read_pose(outs[name] / scan / photo / "pose.yaml")[0], T, atol=1e-5)
    resumed = {r["photo"]: r["skipped"] for r in csv.DictReader(open(outs["ray"] / "summary.csv"))}
    assert resumed["photo_1.png"] == "init refine depth qa overlay"
    # both scans have a photo.png: the lines under the table name the scan too
    assert "room_a/photo.png: skipped" in again.stdout and "room_b/photo.png: skipped" in again.stdout
    # the site as a data set: each scan its own world frame, so a COLMAP model and a nerfstudio
    # scene per scan; plain's photos named SCAN_PHOTO with their scan
    proc = run_cli("export", outs["local"], "-o", tmp_path / "ds", "-f", "plain,colmap,nerfstudio")
    assert proc.returncode == 0, proc.stderr
    cams = __import__("json").loads((tmp_path / "ds" / "plain" / "cameras.json").read_text())["photos"]
    assert sorted(cams) == ["room_a_photo", "room_a_photo_1", "room_b_photo"]
    assert cams["room_b_photo"]["scan"] == str(scenes / "s5" / "scan.ply")
    for scan, n in (("room_a", 2), ("room_b", 1)):
        t = __import__("json").loads((tmp_path / "ds" / "nerfstudio" / scan / "transforms.json").read_text())
        assert len(t["frames"]) == n and (tmp_path / "ds" / "colmap" / scan / "images.txt").is_file()


def test_a_view_without_the_cache_has_the_cached_normals_and_mesh(tmp_path):
    """A real grid scan (pumpA): the view that commands take from the file (no --cache) carries
    the normals and grid triangles of the whole scan, as the prepared scan's view does; made on
    the view alone they differed at depth edges (the stretch test's limit followed the view's grid)."""
    from conftest import _need
    from rgbd_gt.camera import Camera
    from rgbd_gt.prepared import scan_in_view

    path = _need("e57") / "pumpA.e57"
    origin = load_scan(path).origins[0]
    z = np.array([0.0, -1.0, 0.0])  # looking along -y, level: most of the scan's points
    x = np.cross(z, [0.0, 0.0, 1.0])
    R = np.stack([x, np.cross(z, x), z])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, -R @ origin
    camera = Camera(640, 480, 400, 400, 320, 240)
    plain, cached = scan_in_view(path, camera, [T]), scan_in_view(path, camera, [T], tmp_path / "cache")
    assert len(plain) == len(cached) > 50_000
    a, b = np.lexsort((plain.col, plain.row)), np.lexsort((cached.col, cached.row))
    np.testing.assert_array_equal(plain.xyz[a], cached.xyz[b])
    np.testing.assert_allclose(plain.normals[a], cached.normals[b], atol=1e-6)
    np.testing.assert_array_equal(plain.cell_bits[a], cached.cell_bits[b])


def test_big_temporaries_reuse_the_heap_instead_of_fresh_pages():
    """A 40 MB tensor made and freed over and over (as the aligner's windows at every
    evaluation): with `keep_freed_memory` the kernel maps and zeroes its pages a few times while
    the heap settles, then never; by default every time. Each case in a fresh interpreter, whose
    heap nothing else has shaped. (torch's, not numpy's: numpy asks for huge pages, which fault
    in 2 MB at a time.)"""
    if not sys.platform.startswith("linux"):
        pytest.skip("glibc's malloc settings: Linux only")
    thp = Path("/sys/kernel/mm/transparent_hugepage/enabled")
    if thp.exists() and "[always]" in thp.read_text():
        pytest.skip("this kernel gives every mapping huge pages: fresh blocks fault 2 MB at a time, too few to count")
    # the heap settles within 7 such blocks here: each asks a little more than the hole the last
    # one left (torch aligns them) until the holes have merged
    code = ("import resource, sys, torch\n"
            "from rgbd_gt.heap import keep_freed_memory\n"
            "kept = keep_freed_memory() if sys.argv[1] == 'keep' else None\n"
            "for k in range(30):\n"
            "    if k == 20:\n"
            "        before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
            "    torch.ones(5_000_000, dtype=torch.float64)\n"
            "print(kept, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)\n")
    faults = {}
    for case in ("keep", "default"):
        proc = subprocess.run([sys.executable, "-c", code, case], capture_output=True, text=True, cwd=Path(__file__).parents[1])
        assert proc.returncode == 0, proc.stderr
        kept, faults[case] = proc.stdout.split()
        if case == "keep" and kept != "True":
            pytest.skip("this C library is not glibc: nothing to set")
    # the last 10 blocks: about 100k pages of 4 KB faulted in afresh by default, none when kept
    assert int(faults["default"]) > 50_000 and int(faults["keep"]) < 1_000, faults
