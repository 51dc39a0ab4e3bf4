"""Per-pixel uncertainty of a depth map: the pose's (and the camera's) covariance carried to
each pixel's depth and image position to first order, and the pixels a small pose error could
move across a depth discontinuity (they may then see another surface)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera

# neighbours whose depths differ by more than this fraction (beyond what their surface's slant
# explains) are on two surfaces
JUMP = 0.02
REACH_SIGMAS = 2.0  # a pixel within this many of its image-position sigmas of a discontinuity is flagged


@dataclass
class PixelSigma:
    """depth (H, W) float32: 1-sigma of z (metres), 0 where there is no depth; image (H, W)
    float32: 1-sigma (pixels, the worst direction) of where the pixel's surface point appears."""

    depth: np.ndarray
    image: np.ndarray


def pixel_sigma(z: np.ndarray, normals: np.ndarray | None, camera: Camera, covariance: np.ndarray,
                camera_sigma: dict | None = None, rays: np.ndarray | None = None) -> PixelSigma:
    """First-order 1-sigma of each pixel's depth and image position.

    z (H, W) metres (0: none); normals (H, W, 3) unit camera-frame normals facing the camera (0
    or None where unknown: taken facing along the ray); covariance (6, 6) of the pose update
    (rotation vector rad, translation m; p' = exp(w) p + v in the camera frame,
    `pose.apply_update`); camera_sigma: the camera's 1-sigmas {focal_px, cx_px, cy_px} (missing
    keys: exact), taken independent of the pose; rays (H*W, 3) `render.depth.pixel_rays` when made.

    The surface's tangent plane n.p = d moves with the pose to n'.p = d + n.v (n' = n + w x n),
    so the depth along the fixed ray r (r_z = 1) moves by dz = (n.v - z w.(n x r)) / (n.r); a
    change of the ray r (the intrinsics) moves it by -z n.dr / (n.r)."""
    from rgbd_gt.render.depth import normalised_map

    h, w = z.shape
    if not np.isfinite(covariance).all():  # an undetermined pose: no pixel's depth is known to any sigma
        inf = np.where(z > 0, np.inf, 0).astype(np.float32)
        return PixelSigma(inf, inf.copy())
    on = np.flatnonzero(z.ravel() > 0)
    # float32 throughout: a sigma needs no more, and 1.2 million pixels cost half as much
    ray_xy = (rays[:, :2] if rays is not None else normalised_map(camera).reshape(-1, 2))[on].astype(np.float32)
    x, y = ray_xy[:, 0], ray_xy[:, 1]
    zz = z.ravel()[on].astype(np.float32)
    n = normals.reshape(-1, 3)[on].astype(np.float32) if normals is not None else np.zeros((len(on), 3), np.float32)
    nx, ny, nz = n.T
    unknown = np.flatnonzero((nx == 0) & (ny == 0) & (nz == 0))
    if len(unknown):
        r = np.stack([x[unknown], y[unknown], np.ones(len(unknown), np.float32)], 1)
        n[unknown] = -r / np.linalg.norm(r, axis=1, keepdims=True)
    nr = nx * x + ny * y + nz
    nr = np.where(np.abs(nr) < 1e-6, -1e-6, nr)  # a surface seen edge-on: its depth is undetermined
    lam, vec = np.linalg.eigh(0.5 * (covariance + covariance.T))
    L = (vec * np.sqrt(np.maximum(lam, 0))).astype(np.float32)  # covariance = L L^T: J cov J^T is |J L|^2
    # the Jacobians by the update (w, v), one row per pixel, of z: [-z (n x r), n] / (n.r), and of
    # the image position of the surface point p = z r: f/z [[1, 0, -x], [0, 1, -y]] (w x p + v)
    # (r_z = 1), as rows of 6 in a (3, 6, N) block so that one product with L takes all three
    k, iz = -zz / nr, 1 / zz
    J = np.empty((3, 6, len(on)), np.float32)
    J[0, 0], J[0, 1], J[0, 2] = (ny - nz * y) * k, (nz * x - nx) * k, (nx * y - ny * x) * k
    J[0, 3], J[0, 4], J[0, 5] = nx / nr, ny / nr, nz / nr
    xy = x * y
    J[1, 0], J[1, 1], J[1, 2], J[1, 3], J[1, 4], J[1, 5] = -xy, 1 + x * x, -y, iz, 0, -x * iz
    J[2, 0], J[2, 1], J[2, 2], J[2, 3], J[2, 4], J[2, 5] = -1 - y * y, xy, x, 0, iz, -y * iz
    J[1] *= camera.fx
    J[2] *= camera.fy
    JL = np.matmul(L.T, J)  # (3, 6, N)
    var_z = np.einsum("ij,ij->j", JL[0], JL[0])
    uu, vv, uv = (np.einsum("ij,ij->j", JL[a], JL[b]) for a, b in ((1, 1), (2, 2), (1, 2)))
    var_px = 0.5 * (uu + vv) + np.sqrt(np.maximum(0.25 * (uu - vv) ** 2 + uv * uv, 0))  # the larger eigenvalue
    cs = camera_sigma or {}
    # r = ((u - cx) / f, (v - cy) / f, 1): dr/df = -(x, y, 0) / f, dr/dcx = (-1/f, 0, 0), dr/dcy = (0, -1/f, 0)
    terms = {"focal_px": lambda: (-(nx * x + ny * y) / camera.fx, np.hypot(x, y)),
             "cx_px": lambda: (-nx / camera.fx, 1.0), "cy_px": lambda: (-ny / camera.fy, 1.0)}
    for key, term in terms.items():
        s = float(cs.get(key, 0.0))
        if s > 0:
            n_dr, dpx = term()
            var_z += (zz * n_dr / nr * s) ** 2
            var_px += (dpx * s) ** 2
    out_z, out_px = np.zeros(h * w, np.float32), np.zeros(h * w, np.float32)
    out_z[on], out_px[on] = np.sqrt(np.maximum(var_z, 0)), np.sqrt(np.maximum(var_px, 0))
    return PixelSigma(out_z.reshape(h, w), out_px.reshape(h, w))


def discontinuities(z: np.ndarray, normals: np.ndarray | None, camera: Camera, silhouettes: bool = True) -> np.ndarray:
    """(H, W) bool: pixels beside a neighbour (4-connected) on another surface: depths apart by
    more than JUMP of the nearer beyond what the nearer's tangent plane explains over one pixel,
    or (silhouettes) a neighbour with no depth. A sparse (point) depth map has no surfaces
    between its points: silhouettes=False then."""
    out = np.zeros(z.shape, bool)
    n = normals if normals is not None else np.zeros(z.shape + (3,), np.float32)
    for axis, f in ((0, camera.fy), (1, camera.fx)):
        a = z.take(range(z.shape[axis] - 1), axis)
        b = z.take(range(1, z.shape[axis]), axis)
        na = n.take(range(z.shape[axis] - 1), axis)
        # along this axis a plane through p with normal n changes z by z n_axis / (f n.r) per pixel;
        # n.r is taken as n_z (the ray's slant matters little at this tolerance)
        comp = 1 - axis  # image axis 0 (rows) moves y, axis 1 moves x
        slope = np.abs(na[..., comp]) / np.maximum(np.abs(na[..., 2]), 0.05) / f
        near = np.minimum(a, b)
        both = (a > 0) & (b > 0)
        jump = both & (np.abs(a - b) > near * (JUMP + 3 * slope))
        if silhouettes:
            jump |= (a > 0) != (b > 0)
        lo = [slice(None)] * 2
        hi = [slice(None)] * 2
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        out[tuple(lo)] |= jump & (a > 0)
        out[tuple(hi)] |= jump & (b > 0)
    return out


def near_discontinuity(edges: np.ndarray, sigma_px: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels within REACH_SIGMAS of their image-position sigma (and at least the
    edge pixels themselves) of a discontinuity (`discontinuities`)."""
    import cv2

    if not edges.any():
        return edges.copy()
    dist = cv2.distanceTransform((~edges).astype(np.uint8), cv2.DIST_L2, 3)
    return dist <= np.maximum(REACH_SIGMAS * sigma_px, 0.5)
