"""Coarse initial poses: a checkerboard (or ChArUco board) seen in the photo and in the scan, or
hand-picked 2D-3D correspondences, solved by PnP."""
