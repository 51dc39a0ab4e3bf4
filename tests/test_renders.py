"""One render per camera and pose: the steps of one photo (the verdict's edge check, depth, qa,
the overlay) share `render.renders.Renders`, and each (camera, pose) is rendered once."""

import dataclasses

import numpy as np
import pytest

import rgbd_gt.render.renders as renders_module
from rgbd_gt.camera import Camera
from rgbd_gt.render.depth import render_depth
from rgbd_gt.render.renders import Renders
from rgbd_gt.scan import Scan


def _wall_scan() -> Scan:
    """A grid scan of a wall 4 m ahead and a box before it, from the origin, colored by position."""
    el, az = np.meshgrid(np.radians(np.arange(-20, 20, 0.25)), np.radians(np.arange(-25, 25, 0.25)), indexing="ij")
    d = np.stack([np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)], -1)
    t = 4.0 / d[..., 2]
    box = (np.abs(az) < np.radians(6)) & (np.abs(el) < np.radians(6))
    t = np.where(box, 2.5 / d[..., 2], t)
    xyz = (d * t[..., None]).reshape(-1, 3)
    row, col = np.indices(el.shape)
    rgb = np.stack([(xyz[:, 0] * 40 + 128) % 256, (xyz[:, 1] * 40 + 128) % 256, 200 * box.ravel() + 20], 1)
    return Scan(xyz=xyz, rgb=rgb.astype(np.uint8), row=row.ravel().astype(np.int32), col=col.ravel().astype(np.int32),
                scan_id=np.zeros(len(xyz), np.int32), origins=np.zeros((1, 3)))


CAMERA = Camera(160, 120, 150.0, 150.0, 79.5, 59.5, (-0.1, 0.01, 0.0, 0.0, 0.0))


def _pose(dx: float) -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = dx
    return T


def test_a_camera_and_pose_render_once_with_what_any_step_asks(monkeypatch):
    scan = _wall_scan()
    calls = []
    real = renders_module.render_depth
    monkeypatch.setattr(renders_module, "render_depth", lambda *a, **k: calls.append(k) or real(*a, **k))
    renders = Renders(scan, poses=[_pose(0.05)])
    T = _pose(0.0)
    depth = renders.surfaces(CAMERA, T)
    assert renders.surfaces(CAMERA, T) is depth and len(calls) == 1
    # more than the render holds: rendered again, with all of it (a third ask takes that one)
    colored = renders.surfaces(CAMERA, T, colors=True)
    assert len(calls) == 2 and colored.colors is not None and colored.normals is None
    both = renders.surfaces(CAMERA, T, normals=True)
    assert len(calls) == 3 and both.colors is not None and both.normals is not None
    assert renders.surfaces(CAMERA, T, colors=True, normals=True) is both and len(calls) == 3
    np.testing.assert_array_equal(both.z, depth.z)
    # as render_depth gives it alone (the scene built for two poses leaves every hit as it is)
    alone = render_depth(scan, CAMERA, T, values=scan.rgb.astype(np.float32), normals=True)
    np.testing.assert_array_equal(alone.z, both.z)
    np.testing.assert_array_equal(alone.colors, both.colors)
    # a max depth cuts what is handed out, not the render the other steps take
    near = renders.surfaces(CAMERA, T, max_depth=3.0)
    assert (near.z > 0).sum() < (both.z > 0).sum() and (near.z <= 3.0).all()
    assert renders.surfaces(CAMERA, T) is both
    # 0 is no limit, as every command's --max-depth says (fuzz seed 27: export-depth and overlay
    # with --max-depth 0 drew nothing and blamed the pose)
    assert renders.surfaces(CAMERA, T, max_depth=0.0) is both
    np.testing.assert_array_equal(render_depth(scan, CAMERA, T, max_depth=0.0).z, alone.z)
    # the other pose the scene was built for: no new scene; another camera: its own
    scenes = renders.mesh_seconds
    renders.surfaces(CAMERA, _pose(0.05))
    assert renders.mesh_seconds == scenes and len(calls) == 4
    renders.surfaces(dataclasses.replace(CAMERA, fx=140.0), T)
    assert renders.mesh_seconds > scenes and len(calls) == 5


def test_splats_too_wide_are_drawn_when_a_step_can_use_them(monkeypatch):
    """The verdict's edge check leaves out splats wider than its shift (a sweep's: seconds for
    nothing); qa, which draws them, then renders; a later edge check takes that render, cut."""
    scan = dataclasses.replace(_wall_scan(), row=None, col=None)
    renders = Renders(scan)
    T = _pose(0.0)
    skipped = renders.surfaces(CAMERA, T, colors=True, max_splat_px=0)
    assert not skipped.drawn and not skipped.z.any() and skipped.splat_radius >= 1
    drawn = renders.surfaces(CAMERA, T, colors=True)
    assert drawn.drawn and drawn.z.any()
    cut = renders.surfaces(CAMERA, T, colors=True, max_splat_px=0)
    assert not cut.drawn and not cut.z.any() and renders.surfaces(CAMERA, T, colors=True) is drawn


@pytest.fixture(scope="module")
def refined_photo(tmp_path_factory, synth_scene):
    import rgbd_gt

    scene = synth_scene(tmp_path_factory.mktemp("renders") / "scene", 5)
    inputs = rgbd_gt.load_inputs(scene / "scan.e57", scene / "photo.png", scene / "camera.yaml", scene / "init_pose.yaml")
    return scene, inputs


def test_a_photos_steps_render_each_camera_and_pose_once(monkeypatch, refined_photo):
    """refine's verdict, depth, qa (result and init) and the overlay of one photo, as `run` calls
    them: no camera and pose is rendered twice."""
    import rgbd_gt

    scene, inputs = refined_photo
    asked = []
    real = renders_module.render_depth
    monkeypatch.setattr(renders_module, "render_depth",
                        lambda scan, camera, T, *a, **k: asked.append((camera, np.asarray(T).tobytes())) or
                        real(scan, camera, T, *a, **k))
    refined = rgbd_gt.refine_step(inputs, rgbd_gt.refine_config(max_points=30000, repeats=1), scene / "init_pose.yaml")
    renders = inputs.renders
    rgbd_gt.depth_step(renders, inputs.camera, refined.T)
    rgbd_gt.qa_step(renders, inputs.photo, inputs.camera, refined.T, inputs.around, inputs.T_init)
    rgbd_gt.overlay_step(renders, inputs.photo, inputs.camera, refined.T)
    assert len(asked) >= 2 and len(asked) == len(set(asked)), asked


def test_a_drawn_render_asked_for_more_stays_drawn():
    """Depth first (splats drawn, no colors), then the edge check (colors, narrow splats only):
    the render made again with colors keeps its splats, and the edge check is handed it cut."""
    scan = dataclasses.replace(_wall_scan(), row=None, col=None)
    renders = Renders(scan)
    T = _pose(0.0)
    depth = renders.surfaces(CAMERA, T)
    cut = renders.surfaces(CAMERA, T, colors=True, max_splat_px=0)
    assert not cut.drawn and not cut.z.any()
    both = renders.surfaces(CAMERA, T)
    assert both.drawn and both.colors is not None
    np.testing.assert_array_equal(both.z, depth.z)
