"""Depth as seen by a photo's camera, pixel for pixel with the original (distorted) photo."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera, distort, project, undistort_points
from rgbd_gt.scan import Scan
from rgbd_gt.pose import invert, transform_points


@dataclass
class DepthMap:
    """z: (H, W) float32 z-depth in metres along the optical axis, 0 where nothing is seen;
    normals: (H, W, 3) float32 unit normals in the camera frame (0 where no depth), or None when
    not asked for."""

    z: np.ndarray
    normals: np.ndarray | None
    method: str
    colors: np.ndarray | None = None  # (H, W, C) the scan's colors where seen (0 elsewhere)
    splat_radius: int = 0  # pixels, for a scan rendered as splats (0: a mesh, sharp to the pixel)
    # pixels whose nearest surface the camera sees from behind (z is 0 there: the scan has
    # nothing of the side the camera sees); None when the scan's normals are unknown
    back_facing: int | None = None
    drawn: bool = True  # False: splats wider than the render's max_splat_px were not drawn (z all 0)


BACK_FACING_WARN = 0.03  # of the view: more, and the photo was taken from the other side of much of the scan


def back_facing_fraction(depth: DepthMap) -> float | None:
    """Of the pixels where the scan has a surface, the fraction seen only from behind (None when
    the scan's sides are unknown)."""
    if depth.back_facing is None:
        return None
    return depth.back_facing / max(int((depth.z > 0).sum()) + depth.back_facing, 1)


def back_facing_warning(depth: DepthMap) -> str | None:
    """A sentence for the user when more than BACK_FACING_WARN of the view is seen from behind."""
    f = back_facing_fraction(depth)
    if f is None or f <= BACK_FACING_WARN:
        return None
    return (f"{f:.1%} of what the scan shows in this view is seen from behind (the photo sees the back of surfaces "
            "the scanner saw from the front): those pixels have no depth (0)")


def normalised_map(camera: Camera, step: int | None = None) -> np.ndarray:
    """(H, W, 2) float32 normalised image coordinates (x/z, y/z) of every pixel centre of the
    distorted photo. With distortion the exact inverse is computed at the centres of step x step
    blocks (and one block beyond the border) and interpolated bilinearly, steps of fx / 650 pixels
    (distortion is smooth: at most 0.002 px off on a 24-megapixel photo with k1 = -0.1), so that
    such a photo costs no 24 million iterative undistortions."""
    w, h = camera.width, camera.height
    if not camera.has_distortion:
        x = ((np.arange(w, dtype=np.float32) - camera.cx) / camera.fx)[None, :].repeat(h, 0)
        y = ((np.arange(h, dtype=np.float32) - camera.cy) / camera.fy)[:, None].repeat(w, 1)
        return np.stack([x, y], -1)
    import cv2

    # the interpolation error grows with (step / focal)^2: 1 px steps (exact) for small photos
    step = step or int(np.clip(camera.fx // 650, 1, 16))
    # node k sits at pixel step k + (step - 1) / 2 - step: cv2.resize by `step` then puts node k's
    # value at output pixel step k + (step - 1) / 2, i.e. image pixel (output pixel - step)
    gu = step * np.arange(-1, w // step + 2) + (step - 1) / 2
    gv = step * np.arange(-1, h // step + 2) + (step - 1) / 2
    g = undistort_points(camera, np.stack(np.meshgrid(gu, gv), -1).reshape(-1, 2)).reshape(len(gv), len(gu), 2)
    full = cv2.resize(g.astype(np.float32), (len(gu) * step, len(gv) * step), interpolation=cv2.INTER_LINEAR)
    return full[step:step + h, step:step + w]


def pixel_rays(camera: Camera, rows: tuple[int, int] | None = None, normalised: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) float32 camera-frame directions (x/z, y/z, 1) through the pixel centres of the
    distorted photo's rows [r0, r1) (all rows by default), row by row; `normalised` is
    `normalised_map(camera)` when already made."""
    r0, r1 = rows if rows is not None else (0, camera.height)
    xy = (normalised if normalised is not None else normalised_map(camera))[r0:r1].reshape(-1, 2)
    return np.concatenate([xy, np.ones((len(xy), 1), np.float32)], axis=1)


def render_depth(scan: Scan, camera: Camera, T_cam_from_scan: np.ndarray, max_depth: float | None = None,
                 values: np.ndarray | None = None, normals: bool = True, max_splat_px: int | None = None,
                 mesh: GridMesh | None = None, planes: bool = True) -> DepthMap:
    """Occlusion-correct depth: a structured scan is triangulated along its grid and ray-cast
    (Open3D); a scan without a grid is splatted with discs sized by its point spacing.
    max_depth: metres, depths beyond it left out (None or 0: no limit). values: optional
    per-point (N, C) values (colors) rendered along, as DepthMap.colors (of the values' dtype:
    uint8 colors stay uint8). normals: also the camera-frame normals (else
    DepthMap.normals is None, which saves 12 bytes a pixel). max_splat_px: splats wider than
    this are not drawn (z all 0; splat_radius says how wide they would be), for a check that
    cannot use them (a sweep's are tens of pixels and take seconds). mesh: a grid scan's
    `grid_mesh` for this camera and pose, when made (else made here). planes: a scan without a
    grid or a scanner position is drawn as surfels from the unoriented normals of the points in
    view (True) or as squares (False: ten times quicker, for the edge checks, whose thresholds were
    measured on squares).

    Surfaces seen from behind (their normals, `render.normals`, facing away from the camera)
    render as 0 and are counted in DepthMap.back_facing; they still hide what lies behind them."""
    if scan.has_grid:
        out = _raycast_mesh(scan, camera, T_cam_from_scan, values, normals,
                            mesh or grid_mesh(scan, camera, [T_cam_from_scan]))
    else:
        out = _splat(scan, camera, T_cam_from_scan, values, max_splat_px, planes)
        if not normals:
            out.normals = None
    if max_depth:  # 0: no limit, as everywhere
        far = out.z > max_depth
        out.z[far] = 0
        if out.normals is not None:
            out.normals[far] = 0
        if out.colors is not None:
            out.colors[far] = 0
    return out


def point_depth(scan: Scan, camera: Camera, T_cam_from_scan: np.ndarray, max_depth: float | None = None,
                normals: bool = True, seen: tuple | None = None) -> DepthMap:
    """Sparse depth: the z of each point the camera sees (`render.points.seen_points`, the
    aligner's visibility rule) at the pixel it falls in, the nearest where several do, 0 elsewhere;
    nothing is interpolated. For a sweep (`render.points.is_sweep`) the only honest depth: its
    rings are metres apart at range, and surfaces rendered from it fill the gaps with discs
    sized by those gaps (on a pole, discs wider than the pole). back_facing counts the points
    that would be seen but face away (left out). seen: that rule's result when found
    (`render.renders.Renders.seen`)."""
    from rgbd_gt.render.normals import with_normals
    from rgbd_gt.render.points import dot_pixels, seen_and_behind

    scan = with_normals(scan)
    idx, uv, z, back = seen or seen_and_behind(scan, camera, T_cam_from_scan, max_depth)
    key, owner = dot_pixels(uv, z, camera.size, 0)
    w, h = camera.size
    zz = np.zeros(h * w, np.float32)
    zz[key] = z[owner]
    nn = None
    if normals:
        nn = np.zeros((h * w, 3), np.float32)
        if scan.normals is not None:
            nn[key] = scan.normals[idx[owner]] @ T_cam_from_scan[:3, :3].T
    return DepthMap(zz.reshape(h, w), None if nn is None else nn.reshape(h, w, 3),
                    f"points ({len(key):,} pixels, sparse)", None, 0, back)


@dataclass
class GridMesh:
    """A structured scan's grid mesh, ready to ray-cast: tris (T, 3) int32 into the scan's
    points, the Open3D scene of them in a local frame around `centre` (float32 stays exact for
    georeferenced coordinates), and the scanner of each triangle's first vertex (None when the
    scan records none)."""

    tris: np.ndarray
    scene: object
    centre: np.ndarray
    origin: np.ndarray | None


HIT_MARGIN_PX = 0.01  # 5 x the pixel rays' own error (normalised_map: <= 0.002 px; float32 pixels: 1e-4 px)


def grid_mesh(scan: Scan, camera: Camera, poses: list[np.ndarray], cells: list | None = None) -> GridMesh:
    """The scan's grid mesh as the rays through `camera`'s pixel centres at any of `poses` can hit
    it: the ray-casting scene holds only the triangles whose projection holds a pixel centre
    (`hittable_cells`) at one of the poses, which leaves every ray's hit as it is. A dense scan
    has several points per pixel, so most of its triangles hold no pixel centre, and the scene's
    build (which grows with its triangles) costs a fraction of the whole mesh's. cells: the
    scan's `render.mesh.grid_cells` when already made (`render.renders.Renders` makes them once)."""
    import open3d as o3d

    from rgbd_gt.render.mesh import cell_triangles, grid_cells

    corners = [_corner_pixels(scan.xyz, camera, T) for T in poses]
    bands = []
    for band in (cells if cells is not None else grid_cells(scan)):
        for grid, keep1, keep2 in _row_bands(*band):
            hit1, hit2 = False, False
            for uv, out in corners:
                h1, h2 = hittable_cells(grid, uv, out, camera)
                hit1, hit2 = hit1 | h1, hit2 | h2
            bands.append(cell_triangles(grid, keep1 & hit1, keep2 & hit2))
    tris = np.concatenate(bands) if bands else np.zeros((0, 3), np.int32)
    origin = None
    if len(scan.origins):
        sid = scan.scan_id[tris[:, 0]] if scan.scan_id is not None else np.zeros(len(tris), np.int64)
        origin = np.minimum(sid, len(scan.origins) - 1)
    # float32 about the scanner where known (exact for georeferenced coordinates): every view of
    # one scan then renders to the same bits, whatever else it holds (run's view of a result and
    # its init, export-depth's of the result alone)
    centre = scan.origins[0] if len(scan.origins) else scan.xyz.mean(axis=0) if len(scan) else np.zeros(3)
    scene = o3d.t.geometry.RaycastingScene()
    if len(tris):
        mesh = o3d.t.geometry.TriangleMesh()
        mesh.vertex.positions = o3d.core.Tensor((scan.xyz - centre).astype(np.float32))
        mesh.triangle.indices = o3d.core.Tensor(tris)
        scene.add_triangles(mesh)
        scene.cast_rays(o3d.core.Tensor(np.array([[0, 0, 0, 0, 0, 1]], np.float32)))  # builds the hierarchy now
    return GridMesh(tris, scene, centre, origin)


def _row_bands(grid: np.ndarray, keep1: np.ndarray, keep2: np.ndarray, cells: int = 1 << 19):
    """(grid, keep1, keep2) of `render.mesh.grid_cells` in bands of about `cells` cells (sharing
    their boundary row): the tests' temporaries then stay small (and in the processor's cache)."""
    step = max(1, cells // max(grid.shape[1], 1))
    for r0 in range(0, grid.shape[0] - 1, step):
        yield grid[r0:r0 + step + 1], keep1[r0:r0 + step], keep2[r0:r0 + step]


def _corner_pixels(xyz: np.ndarray, camera: Camera, T_cam_from_scan: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(uv (N, 2) float32 distorted pixels, out (N,) uint8) of the points xyz (N, 3). out is 0
    where the point is in front of the camera and within the lens model's reliable reach
    (`view_bounds` with a 10% margin: beyond it distortion may fold back), else a bit per side
    it lies beyond (1, 2: x/z below, above; 4, 8: y/z; 16: behind the camera, or past the lens
    model's fold); uv 0 there."""
    from rgbd_gt.render.blocks import view_bounds

    x0, x1, y0, y1 = view_bounds(camera, 0.1)
    uv = np.zeros((len(xyz), 2), np.float32)
    out = np.empty(len(xyz), np.uint8)
    for a in range(0, len(xyz), 1 << 18):  # in slices that stay in the allocator's reuse (and cache)
        p = transform_points(T_cam_from_scan, xyz[a:a + (1 << 18)])
        z = p[:, 2]
        front = z > 1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            xn = p[:, :2] / z[:, None]
        o = np.where(front, (xn[:, 0] < x0) * 1 + (xn[:, 0] > x1) * 2 + (xn[:, 1] < y0) * 4 + (xn[:, 1] > y1) * 8, 16)
        sure = np.flatnonzero(o == 0)
        d = distort(camera, xn[sure])
        imaged = np.isfinite(d).all(axis=1)  # within the reach, but past a lens model folding inside it
        o[sure[~imaged]] = 16
        out[a:a + len(p)] = o
        uv[a + sure[imaged]] = d[imaged]
    return uv, out


def hittable_cells(grid: np.ndarray, uv: np.ndarray, out: np.ndarray, camera: Camera,
                   margin: float = HIT_MARGIN_PX) -> tuple[np.ndarray, np.ndarray]:
    """(hit1, hit2) (r-1, c-1) bool: the cells of the grid band (r, c) (`render.mesh.grid_cells`)
    whose triangle (a, b, c), resp. (c, b, d), a ray through a pixel centre (integer u, v of the
    distorted photo) may hit, given the corners' `_corner_pixels` uv, out (N, ...).

    A triangle projects to the triangle of its projected corners, bent slightly by the lens
    (allowed for by a margin of 2% of its extent plus `margin` pixels). Left out: those whose
    bounding box holds no pixel centre, and those whose box holds at most 2 x 2 that all lie
    outside them (most triangles of a dense scan, several to a pixel, are either); of those with a
    corner beyond the lens model's reach, those with every corner behind the camera or, in
    front of it, beyond one side of the view; the rest of those are kept."""
    idx = np.maximum(grid, 0)
    u, v, o = uv[idx, 0], uv[idx, 1], out[idx]

    def corners(a):
        return a[:-1, :-1], a[:-1, 1:], a[1:, :-1], a[1:, 1:]

    (ua, ub, uc, ud), (va, vb, vc, vd), (oa, ob, oc, od) = corners(u), corners(v), corners(o)
    return (_hit((ua, va), (ub, vb), (uc, vc), camera, margin, (oa, ob, oc)),
            _hit((uc, vc), (ub, vb), (ud, vd), camera, margin, (oc, ob, od)))


def _hit(p0, p1, p2, camera: Camera, margin: float, out) -> np.ndarray:
    """Whether a pixel centre may lie in the triangles (p0, p1, p2), each corner a (u, v) pair of
    arrays of one shape, out their `_corner_pixels` codes (`hittable_cells`)."""
    (u0, v0), (u1, v1), (u2, v2) = p0, p1, p2
    ulo, uhi = np.minimum(np.minimum(u0, u1), u2), np.maximum(np.maximum(u0, u1), u2)
    vlo, vhi = np.minimum(np.minimum(v0, v1), v2), np.maximum(np.maximum(v0, v1), v2)
    m = margin + 0.02 * np.maximum(uhi - ulo, vhi - vlo)
    uf, ul, vf, vl = np.ceil(ulo - m), np.floor(uhi + m), np.ceil(vlo - m), np.floor(vhi + m)  # the centres boxed
    boxed = (uf <= ul) & (vf <= vl) & (ul >= 0) & (vl >= 0) & (uf <= camera.width - 1) & (vf <= camera.height - 1)
    # a box around at most 2 x 2 centres (most triangles of a dense scan): is one of them inside,
    # within the margin of each edge? (a triangle of no area, or a larger one, is kept)
    sign = np.sign((u1 - u0) * (v2 - v0) - (v1 - v0) * (u2 - u0))
    edges = [(a, b, c - a, d - b) for (a, b), (c, d) in ((p0, p1), (p1, p2), (p2, p0))]
    tolerance = [m * np.hypot(eu, ev) for _, _, eu, ev in edges]
    inside = np.zeros(sign.shape, bool)
    for cu in (uf, uf + 1):
        for cv in (vf, vf + 1):
            ok = (cu <= ul) & (cv <= vl) & (cu >= 0) & (cv >= 0) & (cu <= camera.width - 1) & (cv <= camera.height - 1)
            for (a, b, eu, ev), tol in zip(edges, tolerance):
                ok &= sign * (eu * (cv - b) - ev * (cu - a)) >= -tol
            inside |= ok
    hit = boxed & ((sign == 0) | inside | (ul - uf > 1) | (vl - vf > 1))
    both, either = out[0] & out[1] & out[2], out[0] | out[1] | out[2]
    beyond = ((both & 16) > 0) | (((both & 15) > 0) & ((either & 16) == 0))  # culled as a whole
    return np.where(either == 0, hit, ~beyond)


def _raycast_mesh(scan: Scan, camera: Camera, T: np.ndarray, values: np.ndarray | None, want_normals: bool,
                  mesh: GridMesh, block: int = 1 << 20) -> DepthMap:
    """Ray-cast the grid mesh pixel by pixel, `block` pixels at a time so that memory stays near
    the outputs' own. A hit triangle whose front (the side its scanner saw) faces away from the
    camera is seen from behind."""
    import open3d as o3d

    tris = mesh.tris
    knows_sides = mesh.origin is not None
    h, w = camera.height, camera.width
    if len(tris) == 0:
        return DepthMap(np.zeros((h, w), np.float32), np.zeros((h, w, 3), np.float32) if want_normals else None,
                        "ray-cast grid mesh (nothing in view)",
                        np.zeros((h, w, values.shape[1]), values.dtype) if values is not None else None,
                        back_facing=0 if knows_sides else None)
    T_sc = invert(T)
    origin = (T_sc[:3, 3] - mesh.centre).astype(np.float32)
    R = T_sc[:3, :3]
    if knows_sides:  # each scanner, from the camera, in the scene's frame
        scanners = (scan.origins - mesh.centre).astype(np.float32) - origin
    z = np.zeros(h * w, np.float32)
    n = np.zeros((h * w, 3), np.float32) if want_normals else None
    colors = np.zeros((h * w, values.shape[1]), values.dtype) if values is not None else None
    vals = values.astype(np.float32, copy=False) if values is not None else None
    back = 0
    rows = max(1, block // w)
    xy = normalised_map(camera)
    for r0 in range(0, h, rows):
        r1 = min(h, r0 + rows)
        d_cam = pixel_rays(camera, (r0, r1), xy)
        d_world = d_cam @ R.T.astype(np.float32)  # unnormalised: t_hit is then z-depth directly
        rays = np.concatenate([np.broadcast_to(origin, d_world.shape), d_world], 1)
        hit = mesh.scene.cast_rays(o3d.core.Tensor(rays))
        zb = hit["t_hit"].numpy()
        on = np.flatnonzero(np.isfinite(zb) & (zb > 0))
        normal = hit["primitive_normals"].numpy()  # (n, 3) in the scene's frame, 0 where nothing was hit
        # the normal along the ray: the camera sees the triangle's back (taken on every ray: a
        # product over all is cheaper than gathering the hits' rays)
        facing = np.einsum("ij,ij->i", normal, d_world)[on]
        if knows_sides:  # is the camera on the side of the hit triangle that its scanner saw?
            # `render.normals.facing_camera` at tolerance 0 on the normal turned to its scanner, the
            # triangle's plane taken at the hit point (camera + t d): n.(scanner - hit)
            if len(scanners) == 1:
                side = (normal @ scanners[0])[on]
            else:
                side = np.einsum("ij,ij->i", normal[on], scanners[mesh.origin[hit["primitive_ids"].numpy()[on]]])
            behind = facing * np.sign(side - zb[on] * facing) > 0
            if behind.any():
                back += int(behind.sum())
                on, facing = on[~behind], facing[~behind]
        sl = slice(r0 * w, r1 * w)
        z[sl][on] = zb[on]
        if n is not None:  # in the camera's frame, turned towards it; 0 where there is no depth
            turn = np.zeros(len(zb), np.float32)
            turn[on] = -np.sign(facing + 1e-12)
            n[sl] = normal @ T[:3, :3].T.astype(np.float32)
            n[sl] *= turn[:, None]
        if colors is not None and len(on):  # barycentric interpolation of the hit triangle's vertex values
            tri = tris[hit["primitive_ids"].numpy()[on].astype(np.int64)]  # on: hits seen from the front
            bary = hit["primitive_uvs"].numpy()[on]
            v0 = vals[tri[:, 0]]
            c = v0 + bary[:, :1] * (vals[tri[:, 1]] - v0) + bary[:, 1:] * (vals[tri[:, 2]] - v0)
            colors[r0 * w + on] = np.rint(c) if np.issubdtype(colors.dtype, np.integer) else c
    return DepthMap(z.reshape(h, w), n.reshape(h, w, 3) if n is not None else None,
                    f"ray-cast grid mesh ({len(tris):,} triangles)",
                    colors.reshape(h, w, -1) if colors is not None else None, back_facing=back if knows_sides else None)


def local_spacing(points: np.ndarray, k: int = 3) -> np.ndarray:
    """(N,) distance (metres) from each point to its k-th nearest other point: the sampling step
    around it (3: a grid-like sampling's step along both directions, even where they differ)."""
    import open3d as o3d

    pts = o3d.core.Tensor(np.ascontiguousarray(points, np.float64))
    nns = o3d.core.nns.NearestNeighborSearch(pts)
    nns.knn_index()
    _, d2 = nns.knn_search(pts, k + 1)
    return np.sqrt(d2.numpy()[:, k])


def surfel_slope(p: np.ndarray, n: np.ndarray, z: np.ndarray, camera: Camera, radius: int,
                 most: float = 0.5) -> np.ndarray:
    """(N, 2) d(1/z)/d(u, v) (1/m per pixel) of the tangent planes of camera-frame points p (N, 3)
    with normals n (N, 3) and depths z (N,): 1/z = (n . ray) / (n . p), ray = ((u - cx)/fx,
    (v - cy)/fy, 1) (the local scale of distortion left out). Clipped so that the inverse depth
    changes by at most `most` of its value over a footprint of `radius` pixels: a surface seen
    edge-on would otherwise reach out to infinity. 0 where the normal is unknown."""
    a = np.sum(n * p, axis=1)
    ok = np.abs(a) > 1e-9
    a = np.where(ok, a, 1.0)
    s = np.stack([n[:, 0] / (camera.fx * a), n[:, 1] / (camera.fy * a)], 1)
    s[~ok] = 0
    limit = most / (np.maximum(z, 1e-6) * max(radius, 1) * np.sqrt(2))
    scale = np.minimum(1.0, limit / np.maximum(np.linalg.norm(s, axis=1), 1e-30))
    return (s * scale[:, None]).astype(np.float32)


def _splat(scan: Scan, camera: Camera, T: np.ndarray, values: np.ndarray | None,
           max_splat_px: int | None = None, planes: bool = True) -> DepthMap:
    import torch

    from rgbd_gt.render.normals import facing_camera, knn_normals, sides_known, with_normals
    from rgbd_gt.render.splat import Surfels, close_gaps, splat, values_at
    from rgbd_gt.render.zbuffer import estimate_spacing

    p = transform_points(T, scan.xyz)
    uv, z = project(camera, p)
    # what the camera sees (with a margin for the splats' reach) sizes the splats: the spacing of
    # the whole scan, or the depth of points behind the image, says nothing about them
    m = 0.05 * max(camera.size)
    seen = (z > 1e-3) & (uv[:, 0] > -m) & (uv[:, 1] > -m) & (uv[:, 0] < camera.width + m) & (uv[:, 1] < camera.height + m)
    p, uv, z = p[seen], uv[seen], z[seen]

    def nothing(why: str, radius: int = 0) -> DepthMap:
        zz = np.zeros((camera.height, camera.width), np.float32)
        colors = None if values is None else np.zeros(zz.shape + (values.shape[1],), values.dtype)
        return DepthMap(zz, np.zeros(zz.shape + (3,), np.float32), why, colors, radius)

    if len(z) < 4:
        return nothing("splats (nothing in view)")
    vals = values[seen].astype(np.float32) if values is not None else np.zeros((len(z), 1), np.float32)
    sided = sides_known(scan)
    normals = with_normals(scan).normals if sided else None
    surfels, back = None, None
    discs = sided or (planes and len(z) >= 16)
    if not discs:  # squares at the typical spacing
        spacing = estimate_spacing(torch.as_tensor(p))
        radius = max(1, int(np.ceil(0.75 * camera.fx * spacing / max(float(np.median(z)), 1e-6))))
    else:
        # discs of the local spacing (a scanner's grows with range and on surfaces seen at a
        # slant), just closing the gaps of a square sampling (s / sqrt 2) with a 6% margin: a larger
        # disc grows every silhouette (docs/depth_benchmark.md)
        reach = 0.75 * local_spacing(p)
        reach_px = reach * camera.fx / z
        radius = max(1, int(np.ceil(min(np.quantile(reach_px, 0.99), 4 * np.median(reach_px)))))
    if max_splat_px is not None and radius > max_splat_px:
        skipped = nothing(f"splats of radius {radius} px (over {max_splat_px}: not drawn)", radius)
        skipped.drawn = False
        return skipped
    if discs:
        # without a scanner position the side seen is unknown, but a disc needs a plane, not a
        # side: the unoriented normals of the points in view (a surfel's slope is the same for n
        # and -n); back faces then cannot be culled (back_facing stays None)
        n_cam = normals[seen] @ T[:3, :3].T if sided else knn_normals(p)
        slope = surfel_slope(p, n_cam, z, camera, radius)
        surfels = Surfels(torch.as_tensor(slope), torch.as_tensor(reach), camera.fx, camera.fy)
    img, depth, index = splat(torch.as_tensor(uv), torch.as_tensor(z), torch.as_tensor(vals), camera.size, radius, surfels)
    zz = depth.numpy().astype(np.float32)
    if surfels is not None:
        # the gaps between a scanner's columns, on one surface
        zz, idx = close_gaps(zz, index.numpy(), reach_px)
        img = values_at(torch.as_tensor(vals), torch.as_tensor(idx))
    if sided:
        # a pixel whose nearest point faces away is seen from behind
        away = ~facing_camera(p.astype(np.float32), n_cam.astype(np.float32))
        behind = (idx >= 0) & away[np.maximum(idx, 0)]
        zz[behind] = 0
        back = int(behind.sum())
        if values is not None:
            img[torch.as_tensor(behind)] = 0
    colors = None
    if values is not None:  # in the values' own type, as the mesh path gives them
        colors = img.numpy()
        colors = np.rint(colors).astype(values.dtype) if np.issubdtype(values.dtype, np.integer) else colors.astype(values.dtype)
    nn = np.zeros(zz.shape + (3,), np.float32)
    if surfels is not None:  # the winning disc's normal, turned to the camera
        hit = (idx >= 0) & (zz > 0)
        n = n_cam[idx[hit]].astype(np.float32)
        n *= -np.sign(np.sum(n * p[idx[hit]], axis=1) + 1e-12)[:, None]
        nn[hit] = n
    kind = "surfels of radius up to" if surfels is not None else "splats of radius"
    return DepthMap(zz, nn, f"{kind} {radius} px", colors, radius, back)
