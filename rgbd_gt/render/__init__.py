"""Projection, visibility and rendering of scans in a camera.

project/zbuffer (torch; CPU or CUDA) give refine its visible points; depth (grid mesh ray-cast
or splats) gives export-depth its depth and qa-edges the scan's colors.
"""

from rgbd_gt.render.project import project_pinhole
from rgbd_gt.render.zbuffer import visible_points

__all__ = ["project_pinhole", "visible_points"]
