"""Surfaces seen from behind: a scanner sees a wall (and a panel in front of it) from one side,
the camera looks at the wall's back. Nothing the camera sees from behind may be drawn or
matched, and it must still hide what lies behind it (the panel, the floor behind the wall)."""

import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from rgbd_gt.align.config import RefineConfig
from rgbd_gt.align.pyramid import photo_pyramid
from rgbd_gt.align.aligner import Aligner
from rgbd_gt.align.photometric import Photometric
from rgbd_gt.camera import Camera
from rgbd_gt.io import read_pose, save_scan, write_pose
from rgbd_gt.io.camera_file import write_camera
from rgbd_gt.io.depth_file import read_depth_exr
from rgbd_gt.io.image import write_image
from rgbd_gt.scan import Scan
from rgbd_gt.render.depth import render_depth
from rgbd_gt.render.normals import knn_normals, scan_normals, with_normals
from rgbd_gt.synth.scene import look_at

SCANNER = np.array([0.0, 0.0, 1.5])
WALL_X, PANEL_X = 3.0, 2.0
CAMERA = Camera(320, 240, 250.0, 250.0, 159.5, 119.5)


def _boxes():
    import open3d as o3d

    def box(lo, hi):
        m = o3d.geometry.TriangleMesh.create_box(*(np.subtract(hi, lo)))
        return m.translate(lo)

    return [box((WALL_X, -1.2, 0.0), (WALL_X + 0.02, 1.2, 2.2)),   # the wall (the scanner sees its x = 3 side)
            box((PANEL_X, 0.4, 0.5), (PANEL_X + 0.02, 1.0, 1.4)),  # a panel between scanner and wall
            box((0.3, -4.0, -0.02), (9.0, 4.0, 0.0))]               # the floor


def backside_scan() -> Scan:
    """A grid scan of the scene from SCANNER (row = elevation, col = azimuth, 0.25 deg steps),
    colored with a checker texture."""
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    for m in _boxes():
        rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(m))
    az = np.radians(np.arange(-70, 70, 0.25))
    el = np.radians(np.arange(-55, 50, 0.25))
    E, A = np.meshgrid(el, az, indexing="ij")
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    rays = np.concatenate([np.broadcast_to(SCANNER, d.shape), d], 1).astype(np.float32)
    t = rc.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    ok = np.isfinite(t)
    xyz = SCANNER + d[ok] * t[ok, None]
    row, col = np.nonzero(ok.reshape(E.shape))
    checker = ((np.floor(xyz[:, 0] * 4) + np.floor(xyz[:, 1] * 4) + np.floor(xyz[:, 2] * 4)) % 2).astype(np.uint8)
    rgb = np.stack([40 + 180 * checker] * 3, 1).astype(np.uint8)
    return Scan(xyz=xyz, rgb=rgb, row=row.astype(np.int32), col=col.astype(np.int32),
                scan_id=np.zeros(len(xyz), np.int32), origins=SCANNER[None])


def camera_pose(eye=(9.0, 0.0, 1.5), target=(0.0, 0.0, 0.5)) -> np.ndarray:
    return np.linalg.inv(look_at(np.array(eye), np.array(target)))


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("backside")
    scan = backside_scan()
    save_scan(d / "grid.ply", scan)
    save_scan(d / "points.ply", Scan(xyz=scan.xyz, rgb=scan.rgb, origins=scan.origins))
    write_camera(d / "camera.yaml", CAMERA)
    write_pose(d / "behind.yaml", camera_pose())
    write_pose(d / "wall_only.yaml", camera_pose(eye=(4.0, 0.0, 1.8), target=(0.0, 0.0, 2.5)))
    noise = np.random.default_rng(0).integers(0, 256, (CAMERA.height, CAMERA.width, 3), dtype=np.uint8)
    write_image(d / "photo.png", noise)  # a photo of one value is refused before the view is looked at
    return d, scan


def _wall_pixels(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) bool each: pixels whose ray meets the wall's plane x = 3 within the wall where the
    scanner saw it, and where the panel hid the wall from the scanner (a hole in the scan, which
    the camera sees through: nothing tells that a wall was there)."""
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    d_cam = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones_like(u, float)], -1)
    Tw = np.linalg.inv(T)
    d = d_cam @ Tw[:3, :3].T
    s = (WALL_X - Tw[0, 3]) / d[..., 0]
    hit = Tw[:3, 3] + s[..., None] * d
    wall = (s > 0) & (np.abs(hit[..., 1]) < 1.15) & (hit[..., 2] > 0.05) & (hit[..., 2] < 2.15)
    shadow = (hit[..., 1] > 0.55) & (hit[..., 1] < 1.55) & (hit[..., 2] < 1.4)
    return wall & ~shadow, (s > 0) & shadow


def _floor_depth(T: np.ndarray) -> np.ndarray:
    """(H, W) z-depth of the floor plane z = 0 per pixel (inf where the ray does not go down)."""
    v, u = np.mgrid[0:CAMERA.height, 0:CAMERA.width]
    d_cam = np.stack([(u - CAMERA.cx) / CAMERA.fx, (v - CAMERA.cy) / CAMERA.fy, np.ones_like(u, float)], -1)
    Tw = np.linalg.inv(T)
    dz = d_cam @ Tw[2, :3]
    return np.where(dz < 0, -Tw[2, 3] / np.where(dz < 0, dz, -1), np.inf)


def test_normals_face_the_scanner(scene):
    _, scan = scene
    for n in (scan_normals(scan), knn_normals(scan.xyz)):
        assert n.shape == scan.xyz.shape
    n = scan_normals(scan)
    wall = np.abs(scan.xyz[:, 0] - WALL_X) < 1e-3
    floor = np.abs(scan.xyz[:, 2]) < 1e-3
    assert np.median(n[wall, 0]) < -0.99 and np.median(n[floor, 2]) > 0.99
    # without a grid: k-nearest-neighbour planes, turned toward the scanner
    loose = with_normals(Scan(xyz=scan.xyz, origins=scan.origins)).normals
    assert np.median(loose[wall, 0]) < -0.99 and np.median(loose[floor, 2]) > 0.99


@pytest.mark.parametrize("kind", ["grid", "points"])
def test_export_depth_writes_nothing_seen_from_behind(scene, tmp_path, kind):
    d, _ = scene
    proc = run_cli("export-depth", "--scan", d / f"{kind}.ply", "--camera", d / "camera.yaml", "--pose", d / "behind.yaml",
                   "-o", tmp_path / "depth.exr")
    assert proc.returncode == 0, proc.stderr
    assert "warning:" in proc.stderr and "seen from behind" in proc.stderr
    assert "seen from behind" in proc.stdout
    z = read_depth_exr(tmp_path / "depth.exr")[0]
    T = read_pose(d / "behind.yaml")[0]
    wall, hole = _wall_pixels(T)
    # the wall's back has no depth, and nothing behind it (the panel, the floor on the scanner's
    # side) reads through it
    inner = wall & (np.abs(np.gradient(wall.astype(float))[0]) + np.abs(np.gradient(wall.astype(float))[1]) == 0)
    assert inner.sum() > 0.05 * z.size and (z[inner] == 0).mean() > 0.99
    # the floor, which both see from above, keeps its depth
    floor = (z > 0) & ~wall & ~hole
    assert floor.sum() > 0.05 * z.size
    err = np.abs(z[floor] - _floor_depth(T)[floor])
    assert np.median(err) < (0.002 if kind == "grid" else 0.03), np.median(err)
    # with its sides unknown (no scanner position), the same scan renders the wall as before
    plain = render_depth(Scan(xyz=backside_scan().xyz, row=None, col=None), CAMERA, T)
    assert plain.back_facing is None


def test_refine_matches_no_point_seen_from_behind(scene):
    d, scan = scene
    scan = with_normals(scan)
    photo = np.full((CAMERA.height, CAMERA.width, 3), 128, np.uint8)
    cfg = RefineConfig(levels=1)
    T = read_pose(d / "behind.yaml")[0]
    aligner = Aligner(Photometric(scan.xyz, scan.rgb, photo_pyramid(photo, CAMERA, 1, "cpu"), cfg, scan.normals))
    aligner.prepare(T)
    seen = aligner.visible_scan_points(T)
    assert len(seen) > 100
    assert np.all(np.abs(seen[:, 2]) < 1e-3)  # only the floor: nothing of the wall's or the panel's backs
    # and none of the floor that the wall's back hides
    from rgbd_gt.camera import project
    from rgbd_gt.pose import transform_points

    uv = np.round(project(CAMERA, transform_points(T, seen))[0]).astype(int)
    wall, _ = _wall_pixels(T)
    assert wall[uv[:, 1], uv[:, 0]].mean() < 0.01
    # without normals the same aligner matches the wall's back
    blind = Aligner(Photometric(scan.xyz, scan.rgb, photo_pyramid(photo, CAMERA, 1, "cpu"), cfg))
    blind.prepare(T)
    assert (np.abs(blind.visible_scan_points(T)[:, 0] - WALL_X) < 1e-3).sum() > 100


def test_commands_refuse_a_view_of_backs_only(scene, tmp_path):
    d, _ = scene
    common = ["--scan", d / "grid.ply", "--camera", d / "camera.yaml"]
    assert_one_line_error(run_cli("export-depth", *common, "--pose", d / "wall_only.yaml", "-o", tmp_path / "z.exr"),
                          "wall_only.yaml", "back of the scan's surfaces")
    assert_one_line_error(run_cli("refine", *common, "--image", d / "photo.png", "--init", d / "wall_only.yaml",
                                  "-o", tmp_path / "r.yaml"), "back of what the scanner saw")
    assert not (tmp_path / "z.exr").exists() and not (tmp_path / "r.yaml").exists()
