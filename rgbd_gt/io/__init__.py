"""Reading and writing every file rgbd-gt uses: scans, images, camera and pose files."""

from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.io.camera_file import read_camera, write_camera
from rgbd_gt.io.pose_file import read_pose, write_pose
from rgbd_gt.io.scan import load_scan, save_scan

__all__ = [
    "atomic_output",
    "load_scan",
    "read_camera",
    "read_pose",
    "save_scan",
    "write_camera",
    "write_pose",
]
