"""One render per camera and pose: what the steps of one photo (the verdict's edge check, depth,
qa, the overlay) take their view of the scan from, so that none renders what another has.

A step asks `Renders` for the surfaces (`surfaces`: depth, and along with it normals, the
scan's colors, which pixels are seen from behind, the splat size) or the seen points (`seen`)
at a camera and pose; the first ask renders, the others take that render. The checks work at a
reduced camera (`qa.edges.working_camera`) and the overlay at its render scale, so one photo has
up to three cameras; a 640 x 480 photo has one, rendered once for all four steps.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.render.depth import DepthMap, GridMesh, grid_mesh, render_depth
from rgbd_gt.render.normals import sides_known
from rgbd_gt.scan import Scan, scan_colors


def _key(camera: Camera, T: np.ndarray) -> tuple:
    return camera, np.asarray(T, np.float64).tobytes()


class Renders:
    """The renders of one view of the scan for one photo's steps.

    scan: the view (`Scan`); colors: its `scan.scan_colors` (N, C) (made when first asked for,
    when not given), rendered along as float32 where a step asks for colors (the overlay's
    pictures, the edge checks' gray); poses: poses
    other than the one asked that renders will come at (a photo's init, which qa draws beside
    the result): a grid scan's ray-casting scene for a camera is then built once for all of
    them. A different view of the scan takes new Renders. mesh_seconds: the time the
    ray-casting scenes took to build (within the step that asked first)."""

    def __init__(self, scan: Scan, colors: np.ndarray | None = None, poses: list[np.ndarray] = ()):
        self.scan = scan
        self.colors = None if colors is None else np.asarray(colors, np.float32)
        self.poses = [np.asarray(T, np.float64) for T in poses]
        self.mesh_seconds = 0.0
        self._surfaces: dict[tuple, DepthMap] = {}
        self._seen: dict[tuple, tuple] = {}
        self._meshes: dict[Camera, tuple[set, GridMesh]] = {}  # per camera: the poses its scene serves
        self._cells = None

    def surfaces(self, camera: Camera, T: np.ndarray, max_depth: float | None = None, colors: bool = False,
                 normals: bool = False, max_splat_px: int | None = None, planes: bool = True) -> DepthMap:
        """`render.depth.render_depth` of the view at (camera, T), with colors (`self.colors`) and
        normals when asked, cut at max_depth; not drawn (`DepthMap.drawn`) where splats would be
        wider than max_splat_px; `planes` as render_depth's (it matters only to a scan without a
        grid or a scanner position: the two are two renders). Rendered once: a later ask for more
        than the render holds renders again with all of it."""
        key = (*_key(camera, T), planes or self.scan.has_grid or sides_known(self.scan))
        have = self._surfaces.get(key)
        if colors and self.colors is None:  # InputError for a scan with neither colors nor intensity
            self.colors = np.asarray(scan_colors(self.scan), np.float32)
        if have is None or (colors and have.colors is None) or (normals and have.normals is None) or (
                not have.drawn and (max_splat_px is None or have.splat_radius > max_splat_px)):
            keep = have is not None
            have = render_depth(self.scan, camera, T, None,
                                values=self.colors if colors or (keep and have.colors is not None) else None,
                                normals=normals or (keep and have.normals is not None),
                                max_splat_px=None if keep and have.drawn else max_splat_px,  # drawn stays drawn
                                mesh=self._mesh(camera, T) if self.scan.has_grid else None, planes=planes)
            self._surfaces[key] = have
        return _cut(have, max_depth, max_splat_px)

    def seen(self, camera: Camera, T: np.ndarray,
             max_depth: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, int | None]:
        """`render.points.seen_and_behind` of the view at (camera, T): the indices, pixels and
        depths of the points the camera sees, and how many face away; found once."""
        from rgbd_gt.render.points import seen_and_behind

        key = (*_key(camera, T), max_depth or None)  # 0 is no limit too: one entry for both
        if key not in self._seen:
            self._seen[key] = seen_and_behind(self.scan, camera, T, max_depth)
        return self._seen[key]

    def _mesh(self, camera: Camera, T: np.ndarray) -> GridMesh:
        from rgbd_gt.render.mesh import grid_cells

        serves, mesh = self._meshes.get(camera, (set(), None))
        if _key(camera, T)[1] in serves:
            return mesh
        start = time.perf_counter()
        if self._cells is None:
            self._cells = grid_cells(self.scan)
        poses = {np.asarray(P, np.float64).tobytes(): P for P in [T, *self.poses]}
        mesh = grid_mesh(self.scan, camera, list(poses.values()), self._cells)
        self._meshes[camera] = set(poses), mesh
        self.mesh_seconds += time.perf_counter() - start
        return mesh


def _cut(render: DepthMap, max_depth: float | None, max_splat_px: int | None) -> DepthMap:
    """The render as asked: nothing beyond max_depth, nothing drawn where its splats are wider
    than max_splat_px. The render itself is left as it is (other steps take it)."""
    if max_splat_px is not None and render.drawn and render.splat_radius > max_splat_px:
        zero = np.zeros_like(render.z)
        return dataclasses.replace(render, z=zero, drawn=False,
                                   normals=None if render.normals is None else np.zeros_like(render.normals),
                                   colors=None if render.colors is None else np.zeros_like(render.colors),
                                   method=f"splats of radius {render.splat_radius} px (over {max_splat_px}: not drawn)")
    if not max_depth or not (render.z > max_depth).any():  # 0: no limit
        return render
    far = render.z > max_depth
    out = dataclasses.replace(render, z=np.where(far, 0, render.z))
    if render.normals is not None:
        out.normals = np.where(far[..., None], 0, render.normals)
    if render.colors is not None:
        out.colors = np.where(far[..., None], 0, render.colors).astype(render.colors.dtype)
    return out
