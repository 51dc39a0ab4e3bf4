"""Projection, visibility and rendering of scans in a camera.

project/zbuffer (torch; CPU or CUDA) give refine its visible points; depth (grid mesh ray-cast
or surfels) gives export-depth its depth and qa-edges and overlay the scan's colors; normals
tell which side of a surface the scanner saw. Nothing is imported here: rendering a depth map
does not need torch, whose import alone costs seconds.
"""
