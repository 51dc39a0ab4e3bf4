"""The scan's points as points: which of them a camera sees (the aligner's visibility rule), and
the pixels each covers when drawn as a small square. For LiDAR sweeps, whose rings leave gaps
that rendered surfaces could only fill with invented blobs, pictures, pick views and depth maps
show the points themselves.
"""

from __future__ import annotations

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.scan import Scan


RING_BIN_DEG = 0.02  # finer than a spinning LiDAR's ring spacing (0.1-2 deg), coarser than its ring's spread
RING_BINS_MOST = 0.25  # rings put 90% of the far points into 3-8% of the elevation bins; a scanner's grid, 60-70%
RING_SAMPLE = 200_000  # points enough to see rings; keeps the test cheap on scans of millions
# scan lines: of a point's LINE_K nearest neighbours, a sweep's lie on one ring (a line) for 18-43%
# of its points (KITTI, Waymo, PJLab frames), a dense scan's for 0.7-4.4% (ICL-NUIM, pumpA, synth)
LINE_K, LINE_SHARE, LINE_PROBES = 10, 0.1, 4000
LINE_MOST = 4_000_000  # no spinning LiDAR's sweep holds more points


def is_sweep(scan: Scan) -> bool:
    """A spinning LiDAR's sweep: no row/column grid, and either its file names each return's
    ring (`Scan.ring`: in any frame) or, seen from its sensor (the first scan's origin, else 0,
    0, 0; its axis the frame's z, as in a sweep's own frame), its points lie on a few cones of
    fixed elevation, its rings, or (`on_scan_lines`) most points' nearest neighbours lie on one
    line, their ring: KITTI's HDL-64E (whose lasers sit apart, so its rings are not cones about
    one point) and Waymo's sweeps (stored in the vehicle's frame). Their gaps are degrees wide, and rendered surfaces
    could only fill them with invented blobs: so the default for drawing and exporting points,
    not surfaces (`overlay`'s points picture, pick's view, `export-depth`'s sparse depth). A scan
    with a grid, or a dense one stripped of its grid (elevations continuous), renders as
    surfaces, whatever its fields.

    Measured on the far half of the points (a laser's own offset from the sensor smears the
    elevations of near returns): the share of `RING_BIN_DEG` elevation bins, between the 1st
    and 99th percentile, that hold 90% of them."""
    if scan.has_grid or len(scan) < 100:
        return False
    if scan.ring is not None:
        return True
    pick, sid = slice(None, None, max(1, len(scan) // RING_SAMPLE)), 0
    xyz = scan.xyz[pick]
    if scan.scan_id is not None:
        ids = scan.scan_id[pick]
        sid = int(ids.min())
        xyz = xyz[ids == sid]
    d = xyz - (scan.origins[min(sid, len(scan.origins) - 1)] if len(scan.origins) else 0.0)
    r = np.linalg.norm(d, axis=1)
    far = r >= np.median(r)
    el = np.degrees(np.arcsin(np.clip(d[far, 2] / np.maximum(r[far], 1e-9), -1, 1)))
    lo, hi = np.percentile(el, [1, 99])
    counts = np.sort(np.histogram(el, bins=max(1, int((hi - lo) / RING_BIN_DEG)), range=(lo, hi))[0])[::-1]
    needed = int(np.searchsorted(np.cumsum(counts), 0.9 * counts.sum())) + 1
    return needed / len(counts) < RING_BINS_MOST or on_scan_lines(scan.xyz)


def on_scan_lines(xyz: np.ndarray) -> bool:
    """Whether the points (N, 3) are a sweep's scan lines: at LINE_PROBES points drawn at random,
    more than LINE_SHARE of the LINE_K nearest neighbourhoods are lines (their second spread
    under 5% of their first), as a ring's are where rings lie farther apart than a ring's own
    returns; a dense scan's neighbourhoods are patches of surface. Independent of the frame the
    points are in. Over LINE_MOST points: no."""
    import open3d as o3d

    if len(xyz) > LINE_MOST or len(xyz) <= LINE_K:
        return False
    probe = np.random.default_rng(0).choice(len(xyz), min(LINE_PROBES, len(xyz)), replace=False)
    nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.ascontiguousarray(xyz, np.float64)))
    nns.knn_index()
    idx, _ = nns.knn_search(o3d.core.Tensor(np.ascontiguousarray(xyz[probe], np.float64)), LINE_K)
    nb = xyz[idx.numpy()]
    nb = nb - nb.mean(axis=1, keepdims=True)
    lam = np.linalg.eigvalsh(np.einsum("pki,pkj->pij", nb, nb))  # ascending
    return float(np.mean(lam[:, 1] < 0.05 * lam[:, 2])) > LINE_SHARE


def as_points(scan: Scan, choice: bool | None) -> bool:
    """Whether to draw or export the scan as points: the user's choice, else for a sweep."""
    return is_sweep(scan) if choice is None else choice


def seen_points(scan: Scan, camera: Camera, T: np.ndarray,
                max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scan points the camera sees at T: their indices (n,), pixels uv (n, 2) and depths z
    (n,) in metres. Visibility is the aligner's (`visible_points` with cells sized where the
    points land, and surfaces seen from behind left out), so these are the points refine compares."""
    idx, uv, z, _ = seen_and_behind(scan, camera, T, max_depth)
    return idx, uv, z


def seen_and_behind(scan: Scan, camera: Camera, T: np.ndarray,
                    max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int | None]:
    """`seen_points`, and how many points the Z-buffer lets through that face away from the
    camera (left out; None without normals). Those still hide what lies behind them, so the
    visible ones are the ones that pass and face the camera."""
    import torch

    from rgbd_gt.camera import project
    from rgbd_gt.render.normals import facing_camera
    from rgbd_gt.render.cells import cell_for_density
    from rgbd_gt.render.zbuffer import visible_points

    p = scan.xyz @ T[:3, :3].T + T[:3, 3]
    uv, z = project(camera, p)
    w, h = camera.size
    near = (z > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] <= h - 1)
    if max_depth:
        near &= z <= max_depth
    idx = np.flatnonzero(near)
    uv_t, z_t = torch.as_tensor(uv[idx]), torch.as_tensor(z[idx])
    passed = visible_points(uv_t, z_t, camera.size, cell_for_density(uv_t, camera.size)).numpy()
    behind = None
    if scan.normals is not None:
        facing = facing_camera(p[idx], scan.normals[idx] @ T[:3, :3].T)
        behind = int((passed & ~facing).sum())
        passed &= facing
    idx = idx[passed]
    return idx, uv[idx], z[idx], behind


def dot_pixels(uv: np.ndarray, z: np.ndarray, size: tuple[int, int], dot_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The pixels of squares of side 2 dot_px + 1 around the points uv (n, 2) with depth z (n,):
    flat pixel indices (m,) into an image of size (width, height), each with the index (m,) of the
    nearest point whose square covers it. Memory and time follow the points, not the image (a
    24-megapixel photo would need 1 GB of per-pixel buffers)."""
    w, h = size
    r = np.arange(-dot_px, dot_px + 1)
    dx, dy = (a.ravel()[:, None] for a in np.meshgrid(r, r))
    x, y = np.rint(uv[:, 0]).astype(np.int64) + dx, np.rint(uv[:, 1]).astype(np.int64) + dy  # (k, n)
    inside = (x >= 0) & (y >= 0) & (x < w) & (y < h)
    key, depth = (y * w + x)[inside], np.broadcast_to(z, x.shape)[inside]
    owner = np.broadcast_to(np.arange(len(z)), x.shape)[inside]
    order = np.lexsort((depth, key))  # by pixel, nearest first
    key, owner = key[order], owner[order]
    first = np.ones(len(key), bool)
    first[1:] = key[1:] != key[:-1]
    return key[first], owner[first]
