"""Surface normals of a scan, oriented toward the scanner that saw each point, and the test
that uses them: a camera sees a surface's front only.

A laser scanner sees a surface from its front. A photo taken from the other side sees that
surface's back, where the scan has nothing: those points must neither be drawn nor matched,
but they still hide what lies behind them.
"""

from __future__ import annotations

import numpy as np

from rgbd_gt.scan import Scan

def scan_origin_per_point(scan: Scan) -> np.ndarray | None:
    """(N, 3) position of the scanner that saw each point, or None when the scan records none."""
    if len(scan.origins) == 0:
        return None
    sid = scan.scan_id if scan.scan_id is not None else np.zeros(len(scan), np.int64)
    return scan.origins[np.minimum(sid, len(scan.origins) - 1)]


def knn_normals(xyz: np.ndarray, k: int = 16, chunk: int = 1 << 20) -> np.ndarray:
    """(N, 3) float32 unit normals of a scan without a grid: the least-variance direction of each
    point's k nearest neighbours (unoriented). 0 where the neighbourhood is not a surface patch:
    a line (one ring of a LiDAR sweep, an edge) or a blob says nothing about which side faces
    the camera, and a wrong normal would hide a point that is seen."""
    import open3d as o3d

    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(xyz, np.float64)))
    pcd.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(k))
    cov = np.asarray(pcd.covariances)
    out = np.zeros((len(xyz), 3), np.float32)
    for s in range(0, len(xyz), chunk):
        lam, vec = np.linalg.eigh(cov[s:s + chunk])  # ascending eigenvalues
        flat = lam[:, 0] < 0.1 * lam[:, 1]  # much thinner than wide
        wide = lam[:, 1] > 0.05 * lam[:, 2]  # not a line
        out[s:s + chunk] = np.where((flat & wide)[:, None], vec[:, :, 0], 0)
    return out


def sides_known(scan: Scan) -> bool:
    """Whether the side of the scan's surfaces that was seen is known: it has normals (a PLY's
    nx ny nz, or as a prepared scan's) or a scanner position to turn them to (`scan_normals` is
    None exactly where not)."""
    return scan.normals is not None or len(scan.origins) > 0


def scan_normals(scan: Scan) -> np.ndarray | None:
    """(N, 3) float32 unit normals facing the scanner that saw each point (0 where unknown):
    the scan's own (a PLY's nx ny nz) when it has them, else from its grid triangles, else from
    its k nearest neighbours. None when the scan records no scanner position and no normals:
    which side was seen is then unknown."""
    if scan.normals is not None:
        n = np.asarray(scan.normals, np.float32)
    elif len(scan.origins) == 0:
        return None
    elif scan.has_grid:  # oriented as they are summed: no per-point origins (1 GB at 40 M points)
        from rgbd_gt.render.mesh import grid_normals

        return grid_normals(scan)[0]
    else:
        n = knn_normals(scan.xyz)
    origin = scan_origin_per_point(scan)
    if origin is not None:
        n = np.where((np.einsum("ij,ij->i", n, origin - scan.xyz) < 0)[:, None], -n, n).astype(np.float32)
    return n


def oriented(scan: Scan) -> Scan:
    """The scan with the normals it was read with (a PLY's nx ny nz, which may point either way)
    turned to face the scanner that saw each point (`scan_normals`); as it is without normals."""
    import dataclasses

    return scan if scan.normals is None else dataclasses.replace(scan, normals=scan_normals(scan))


def with_normals(scan: Scan) -> Scan:
    """The scan with `normals` filled in (`scan_normals`) when it can be; scan work done once per
    scan and shared by every photo and step."""
    import dataclasses

    if scan.normals is not None:
        return scan
    n = scan_normals(scan)
    return scan if n is None else dataclasses.replace(scan, normals=n)


def facing_camera(points_cam, normals_cam, tolerance: float = 0.05):
    """(N,) bool: camera-frame points (N, 3) whose camera-frame normals (N, 3) face the camera:
    n . p <= tolerance |p|, p the ray from the camera to the point; the tolerance (the cosine
    past perpendicular, about 3 degrees) keeps grazing surfaces whose normals are a little off
    (a triangle's own normal is not off: the grid mesh takes 0). A zero normal (unknown) counts
    as facing. The one test of sides for points, splats and the mesh: numpy arrays or torch
    tensors in, the same out."""
    return (normals_cam * points_cam).sum(1) <= tolerance * ((points_cam * points_cam).sum(1)) ** 0.5
