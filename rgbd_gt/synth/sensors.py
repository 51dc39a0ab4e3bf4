"""The two simulated sensors: a photo by supersampled ray casting through a distorted pinhole
camera, and a FARO-like spherical-grid laser scan. Both ray-cast the same scene with Open3D."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera, undistort_points
from rgbd_gt.synth.scene import Scene, surface_albedo, surface_mesh

CHUNK = 1 << 21  # rays per cast: bounds memory


def build_raycaster(scene: Scene):
    """An Open3D RaycastingScene whose geometry ids are the indices of scene.surfaces."""
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    for k, s in enumerate(scene.surfaces):
        gid = rc.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(surface_mesh(s)))
        assert gid == k
    return rc


def cast(rc, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays (N, 3) origins and unit directions -> t_hit (N,) metres (inf on a miss),
    geometry id (N,) int64 (-1 on a miss), unit normals (N, 3) facing the ray."""
    import open3d as o3d

    rays = np.concatenate([np.broadcast_to(origins, dirs.shape), dirs], axis=1).astype(np.float32)
    hit = rc.cast_rays(o3d.core.Tensor(rays))
    t = hit["t_hit"].numpy()
    gid = hit["geometry_ids"].numpy().astype(np.int64)
    gid[~np.isfinite(t)] = -1
    n = hit["primitive_normals"].numpy()
    n *= -np.sign(np.einsum("ij,ij->i", n, rays[:, 3:]) + 1e-12)[:, None]
    return t.astype(np.float64), gid, n


def radiance(scene: Scene, points: np.ndarray, normals: np.ndarray, gid: np.ndarray, blurred: bool) -> np.ndarray:
    """Linear radiance (N, 3): albedo times Lambertian shading from the scene's point light.

    The shading does not depend on the viewer, so camera and scanner see the same radiance.
    """
    albedo = surface_albedo(scene, gid, points, normals, blurred)
    to_light = (scene.light - points).astype(np.float32)
    dist = np.sqrt(np.einsum("ij,ij->i", to_light, to_light))
    lambert = np.clip(np.einsum("ij,ij->i", normals, to_light) / dist, 0, 1)
    return albedo * (0.45 + 0.55 * lambert * np.sqrt(3.0 / np.maximum(dist, 1.0)))[:, None]


def _undistorted_samples(camera: Camera, ss: int, rng: np.random.Generator) -> np.ndarray:
    """Normalised ray coordinates (H, ss, W, ss, 2) of every sub-pixel sample.

    Samples are stratified and jittered: one at a random place in each of the ss x ss cells of
    a pixel. A regular grid would quantise edge positions to 1/ss px and bias corners by up to
    1/(2 ss) px; jitter turns that into noise that averages out.
    Undistorts the pixel centres only and moves to the samples along the local Jacobian: the
    distortion is smooth, so the second-order error is far below 1e-4 px.
    """
    h, w = camera.height, camera.width
    v, u = np.mgrid[0:h, 0:w]
    xn = undistort_points(camera, np.stack([u.ravel(), v.ravel()], 1)).reshape(h, w, 2)
    d_du = np.gradient(xn, axis=1)
    d_dv = np.gradient(xn, axis=0)
    cells = np.arange(ss)
    du = (cells[None, None, None, :] + rng.random((h, ss, w, ss))) / ss - 0.5
    dv = (cells[None, :, None, None] + rng.random((h, ss, w, ss))) / ss - 0.5
    return (xn[:, None, :, None] + dv[..., None] * d_dv[:, None, :, None]
            + du[..., None] * d_du[:, None, :, None])


def render_photo_radiance(scene: Scene, rc, camera: Camera, world_from_cam: np.ndarray, supersample: int,
                          rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) float32 radiance seen through `camera` (with its distortion), each pixel the
    mean of supersample x supersample jittered rays (anti-aliasing)."""
    w, h, ss = camera.width, camera.height, supersample
    xn = _undistorted_samples(camera, ss, rng)  # (H, ss, W, ss, 2)
    out = np.empty((h, w, 3), np.float32)
    rows_per = max(1, CHUNK // (w * ss * ss))
    R, c = world_from_cam[:3, :3], world_from_cam[:3, 3]
    for r0 in range(0, h, rows_per):
        r1 = min(h, r0 + rows_per)
        x = xn[r0:r1].reshape(-1, 2)
        d = np.concatenate([x, np.ones((x.shape[0], 1))], 1) @ R.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        t, gid, n = cast(rc, c, d)
        rad = radiance(scene, c + t[:, None] * d, n, gid, blurred=False)
        rad[gid < 0] = 0
        out[r0:r1] = rad.reshape(r1 - r0, ss, w, ss, 3).mean(axis=(1, 3))
    return out


@dataclass
class ScanGrid:
    """The scanner's angular grid: azimuth (columns) and elevation (rows), radians, in the
    scanner frame. Row 0 is the highest elevation."""

    az0: float
    el0: float
    step: float
    cols: int
    rows: int

    def angles(self, start: int = 0, stop: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(row, col, azimuth, elevation) of the grid's cells [start, stop) in row-major order,
        row and col int32 (a 40-million-cell grid is cast in chunks)."""
        idx = np.arange(start, self.rows * self.cols if stop is None else stop, dtype=np.int64)
        row, col = (idx // self.cols).astype(np.int32), (idx % self.cols).astype(np.int32)
        return row, col, self.az0 + col * self.step, self.el0 - row * self.step


def grid_covering(points_scanner: np.ndarray, step: float, margin: float) -> ScanGrid:
    """The smallest grid of angular `step` covering the directions of `points_scanner` (N, 3)
    (scanner frame) with `margin` radians to spare."""
    az = np.arctan2(points_scanner[:, 1], points_scanner[:, 0])
    el = np.arctan2(points_scanner[:, 2], np.linalg.norm(points_scanner[:, :2], axis=1))
    centre = np.angle(np.mean(np.exp(1j * az)))
    rel = np.angle(np.exp(1j * (az - centre)))  # unwrapped around the centre
    a0, a1 = rel.min() - margin, rel.max() + margin
    e0, e1 = el.min() - margin, min(el.max() + margin, np.pi / 2)
    return ScanGrid(centre + a0, e1, step, int(np.ceil((a1 - a0) / step)) + 1, int(np.ceil((e1 - e0) / step)) + 1)


def laser_scan(scene: Scene, rc, grid: ScanGrid, range_noise: float, rng: np.random.Generator):
    """Cast the scanner's grid. Returns per hit: local xyz (N, 3) in the scanner frame (with
    Gaussian range noise), world xyz (N, 3) without noise, radiance (N, 3), incidence cosine
    (N,), row (N,), col (N,)."""
    Rws, s = scene.scanner_pose[:3, :3], scene.scanner_pose[:3, 3]
    parts = []
    for i0 in range(0, grid.rows * grid.cols, CHUNK):
        row, col, az, el = grid.angles(i0, min(i0 + CHUNK, grid.rows * grid.cols))
        dl = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
        d = dl @ Rws.T
        t, gid, n = cast(rc, s, d)
        ok = gid >= 0
        world = s + t[ok, None] * d[ok]
        rad = radiance(scene, world, n[ok], gid[ok], blurred=True)
        cos_inc = np.abs(np.sum(n[ok] * d[ok], axis=1))
        noisy = t[ok] + rng.normal(0, range_noise, ok.sum())
        parts.append((noisy[:, None] * dl[ok], world, rad, cos_inc, row[ok], col[ok]))
    return tuple(np.concatenate(p) for p in zip(*parts))


def blur_over_grid(values: np.ndarray, row: np.ndarray, col: np.ndarray, shape: tuple[int, int],
                   sigma_cells: float) -> np.ndarray:
    """values (N, C) of the returns at grid cells (row, col) (N,), blurred over the grid (rows,
    cols) by a Gaussian of sigma_cells, across depth edges, as a camera at the scanner sees them:
    a return beside a silhouette takes on the color of what lies behind it. Cells without a
    return do not count (the blur is normalised by the cells that hold one). Returns (N, C)."""
    import cv2

    rows, cols = shape
    image = np.zeros((rows, cols, values.shape[1]), np.float32)
    held = np.zeros((rows, cols), np.float32)
    image[row, col] = values
    held[row, col] = 1.0
    k = 2 * int(np.ceil(3 * sigma_cells)) + 1
    # reshaped: cv2 returns a one-channel image without its channel axis
    blurred = cv2.GaussianBlur(image, (k, k), sigma_cells, borderType=cv2.BORDER_CONSTANT).reshape(rows, cols, -1)
    weight = cv2.GaussianBlur(held, (k, k), sigma_cells, borderType=cv2.BORDER_CONSTANT)
    return (blurred[row, col] / weight[row, col, None]).astype(values.dtype)
