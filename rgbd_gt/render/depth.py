"""Depth as seen by a photo's camera, pixel for pixel with the original (distorted) photo."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera, project, undistort_points
from rgbd_gt.io.scan import Scan
from rgbd_gt.pose import invert, transform_points


@dataclass
class DepthMap:
    """z: (H, W) float32 z-depth in metres along the optical axis, 0 where nothing is seen;
    normals: (H, W, 3) float32 unit normals in the camera frame (0 where no depth)."""

    z: np.ndarray
    normals: np.ndarray
    method: str


def pixel_rays(camera: Camera) -> np.ndarray:
    """(H*W, 3) camera-frame directions (x/z, y/z, 1) through every pixel centre of the
    distorted photo, row by row."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    xn = undistort_points(camera, np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
    return np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)


def render_depth(scan: Scan, camera: Camera, T_cam_from_scan: np.ndarray, max_depth: float | None = None) -> DepthMap:
    """Occlusion-correct depth: a structured scan is triangulated along its grid and ray-cast
    (Open3D); a scan without a grid is splatted with discs sized by its point spacing."""
    if scan.has_grid:
        out = _raycast_mesh(scan, camera, T_cam_from_scan)
    else:
        out = _splat(scan, camera, T_cam_from_scan)
    if max_depth is not None:
        far = out.z > max_depth
        out.z[far] = 0
        out.normals[far] = 0
    return out


def _raycast_mesh(scan: Scan, camera: Camera, T: np.ndarray) -> DepthMap:
    import open3d as o3d

    from rgbd_gt.render.mesh import grid_triangles

    tris = grid_triangles(scan)
    # a local frame keeps float32 exact for georeferenced coordinates
    centre = scan.xyz.mean(axis=0)
    mesh = o3d.t.geometry.TriangleMesh()
    mesh.vertex.positions = o3d.core.Tensor((scan.xyz - centre).astype(np.float32))
    mesh.triangle.indices = o3d.core.Tensor(tris.astype(np.int32))
    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(mesh)
    d_cam = pixel_rays(camera)
    T_sc = invert(T)
    d_world = d_cam @ T_sc[:3, :3].T  # unnormalised: t_hit is then z-depth directly
    origin = T_sc[:3, 3] - centre
    rays = np.concatenate([np.broadcast_to(origin, d_world.shape), d_world], 1).astype(np.float32)
    hit = rc.cast_rays(o3d.core.Tensor(rays))
    z = hit["t_hit"].numpy()
    z = np.where(np.isfinite(z), z, 0).astype(np.float32)
    n = hit["primitive_normals"].numpy() @ T[:3, :3].T.astype(np.float32)
    n *= -np.sign(np.sum(n * d_cam.astype(np.float32), axis=1, keepdims=True) + 1e-12)
    n[z == 0] = 0
    h, w = camera.height, camera.width
    return DepthMap(z.reshape(h, w), n.reshape(h, w, 3).astype(np.float32), f"ray-cast grid mesh ({len(tris):,} triangles)")


def _splat(scan: Scan, camera: Camera, T: np.ndarray) -> DepthMap:
    import torch

    from rgbd_gt.align.aligner import estimate_spacing
    from rgbd_gt.render.splat import splat

    p = transform_points(T, scan.xyz)
    front = p[:, 2] > 1e-3
    p = p[front]
    uv, z = project(camera, p)
    spacing = estimate_spacing(torch.as_tensor(scan.xyz))
    radius = int(np.ceil(0.75 * camera.fx * spacing / max(float(np.median(z)), 1e-6)))
    img, depth, _ = splat(torch.as_tensor(uv), torch.as_tensor(z), torch.as_tensor(np.zeros((len(z), 1))),
                          camera.size, max(radius, 1))
    zz = depth.numpy().astype(np.float32)
    return DepthMap(zz, np.zeros(zz.shape + (3,), np.float32), f"splats of radius {max(radius, 1)} px")
