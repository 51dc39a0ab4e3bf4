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
    colors: np.ndarray | None = None  # (H, W, C) the scan's colors where seen (0 elsewhere)
    splat_radius: int = 0  # pixels, for a scan rendered as splats (0: a mesh, sharp to the pixel)


def pixel_rays(camera: Camera) -> np.ndarray:
    """(H*W, 3) camera-frame directions (x/z, y/z, 1) through every pixel centre of the
    distorted photo, row by row."""
    v, u = np.mgrid[0 : camera.height, 0 : camera.width]
    xn = undistort_points(camera, np.stack([u.ravel(), v.ravel()], 1).astype(np.float64))
    return np.concatenate([xn, np.ones((xn.shape[0], 1))], axis=1)


def render_depth(scan: Scan, camera: Camera, T_cam_from_scan: np.ndarray, max_depth: float | None = None,
                 values: np.ndarray | None = None) -> DepthMap:
    """Occlusion-correct depth: a structured scan is triangulated along its grid and ray-cast
    (Open3D); a scan without a grid is splatted with discs sized by its point spacing.
    values: optional per-point (N, C) values (colors) rendered along, as DepthMap.colors."""
    if scan.has_grid:
        out = _raycast_mesh(scan, camera, T_cam_from_scan, values)
    else:
        out = _splat(scan, camera, T_cam_from_scan, values)
    if max_depth is not None:
        far = out.z > max_depth
        out.z[far] = 0
        out.normals[far] = 0
    return out


def _raycast_mesh(scan: Scan, camera: Camera, T: np.ndarray, values: np.ndarray | None) -> DepthMap:
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
    colors = None
    if values is not None:  # barycentric interpolation of the hit triangle's vertex values
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        bary = hit["primitive_uvs"].numpy()
        ok = z > 0
        tri = tris[np.where(ok, prim, 0)]
        vals = values.astype(np.float32)
        c = (1 - bary[:, :1] - bary[:, 1:]) * vals[tri[:, 0]] + bary[:, :1] * vals[tri[:, 1]] + bary[:, 1:] * vals[tri[:, 2]]
        c[~ok] = 0
        colors = c.reshape(h, w, -1)
    return DepthMap(z.reshape(h, w), n.reshape(h, w, 3).astype(np.float32),
                    f"ray-cast grid mesh ({len(tris):,} triangles)", colors)


def _splat(scan: Scan, camera: Camera, T: np.ndarray, values: np.ndarray | None) -> DepthMap:
    import torch

    from rgbd_gt.render.splat import splat
    from rgbd_gt.render.zbuffer import estimate_spacing

    p = transform_points(T, scan.xyz)
    uv, z = project(camera, p)
    # what the camera sees (with a margin for the splats' reach) sizes the splats: the spacing of
    # the whole scan, or the depth of points behind the image, says nothing about them
    m = 0.05 * max(camera.size)
    seen = (z > 1e-3) & (uv[:, 0] > -m) & (uv[:, 1] > -m) & (uv[:, 0] < camera.width + m) & (uv[:, 1] < camera.height + m)
    uv, z = uv[seen], z[seen]
    if len(z) < 4:
        zz = np.zeros((camera.height, camera.width), np.float32)
        return DepthMap(zz, np.zeros(zz.shape + (3,), np.float32), "splats (nothing in view)")
    spacing = estimate_spacing(torch.as_tensor(p[seen]))
    radius = max(1, int(np.ceil(0.75 * camera.fx * spacing / max(float(np.median(z)), 1e-6))))
    vals = values[seen].astype(np.float32) if values is not None else np.zeros((len(z), 1), np.float32)
    img, depth, _ = splat(torch.as_tensor(uv), torch.as_tensor(z), torch.as_tensor(vals), camera.size, radius)
    zz = depth.numpy().astype(np.float32)
    return DepthMap(zz, np.zeros(zz.shape + (3,), np.float32), f"splats of radius {radius} px",
                    img.numpy() if values is not None else None, radius)
