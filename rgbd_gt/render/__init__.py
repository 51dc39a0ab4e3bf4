"""Projection and visibility of scan points in a camera (torch; CPU or CUDA).

One renderer serves refine (visible points), export-depth and qa-edges.
"""

from rgbd_gt.render.project import project_pinhole, transform
from rgbd_gt.render.zbuffer import visible_points

__all__ = ["project_pinhole", "transform", "visible_points"]
