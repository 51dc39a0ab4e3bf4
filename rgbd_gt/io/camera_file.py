"""Camera files: the project's YAML, ROS camera_info YAML, Kalibr's camchain YAML, OpenCV
calibration files (cv2.FileStorage; Autoware's camera-LiDAR calibration YAML among them), and the
calibration files of LiDAR-camera tools (`io.calib_txt`, `io.calib_json`, livox_camera_calib's
calib.yaml), which hold no image size."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError, read_yaml, require_file, yaml_number
from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.io.checked import camera_from_values

def is_opencv_file(path: Path, text: str) -> bool:
    """Whether a file (its text given) is OpenCV FileStorage YAML or XML, not plain YAML."""
    return text.lstrip().startswith("%YAML:1.0") or "opencv-matrix" in text or path.suffix.lower() == ".xml"


# OpenCV's failed checks in reading a matrix, in words
OPENCV_CHECKS = {"nelems": "a matrix's data does not hold rows x cols values",
                 "sizes_node": "a matrix lacks its rows or cols",
                 "readRawData": "a matrix's data is not a list of numbers",
                 "dt.empty": "a matrix lacks its dt (the type of its values)"}


def opencv_nodes(path: Path, names: tuple[str, ...]) -> dict[str, np.ndarray | float | str | None]:
    """The named nodes of an OpenCV FileStorage file (YAML or XML): a matrix as an array, a
    sequence of numbers as a 1-D array, a number as a float, a string as a str, None where absent
    or of another kind; OpenCV's errors as one InputError."""
    import cv2

    def unreadable(why: str) -> InputError:
        return InputError(f"not a readable OpenCV calibration file ({why})", path)

    def matrix(node):
        # counted before node.mat(): cv2 5.0 writes a matrix's data into a buffer of rows x cols
        # before it compares the counts, so a matrix without its cols corrupted the heap (an abort
        # or a segfault later, at random: the fuzz's "line 4 removed (cols)")
        rows, cols, dt, data = (node.getNode(k) for k in ("rows", "cols", "dt", "data"))
        if not (rows.isInt() and cols.isInt() and rows.real() >= 1 and cols.real() >= 1):
            raise unreadable(OPENCV_CHECKS["sizes_node"])
        channels = int(re.match(r"\d*", dt.string() if dt.isString() else "").group() or 1)
        if not data.isSeq() or data.size() != rows.real() * cols.real() * channels:
            raise unreadable(OPENCV_CHECKS["nelems"])
        return node.mat()

    def value(node):
        if node.isMap():  # an !!opencv-matrix
            return matrix(node)
        if node.isSeq():  # Autoware's ImageSize: [w, h]
            items = [node.at(i) for i in range(node.size())]
            return np.array([i.real() for i in items]) if all(i.isReal() or i.isInt() for i in items) else None
        if node.isString():
            return node.string()
        return node.real() if node.isReal() or node.isInt() else None

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        try:
            return {name: value(fs.getNode(name)) for name in names}
        finally:
            fs.release()
    except cv2.error as exc:  # its text names OpenCV's own source file; the check that failed says more
        err = exc.err or "unreadable"
        why = next((words for check, words in OPENCV_CHECKS.items() if check in err), err)
        raise unreadable(why) from None
    except SystemError:  # a truncated file ends in SystemError inside the binding, which says only that
        raise unreadable("truncated or corrupt") from None
    except UnicodeDecodeError:  # a string node's bytes; the binding decodes them only when asked
        raise unreadable("a value that is not UTF-8 text") from None


# OpenCV's calibration sample's node names, then livox_camera_calib's camera.yaml's (ORB-SLAM's
# style), then Autoware's (DistCoeff; its size is ImageSize: [w, h])
OPENCV_NAMES = (("camera_matrix", "CameraMat"), ("distortion_coefficients", "DistCoeffs", "DistCoeff"),
                ("image_width", "Camera.width"), ("image_height", "Camera.height"))
OPENCV_MODELS = ("plumb_bob", "rational_polynomial")  # the names ROS and Autoware give OpenCV's model


def _read_opencv(path: Path) -> Camera:
    nodes = opencv_nodes(path, tuple(name for names in OPENCV_NAMES for name in names) + ("ImageSize", "DistModel"))
    K, dist, w, h = (next((nodes[n] for n in names if nodes[n] is not None), None) for names in OPENCV_NAMES)
    if not isinstance(K, np.ndarray) or K.shape != (3, 3):
        raise InputError("OpenCV calibration file has no 3x3 'camera_matrix' (or 'CameraMat')", path)
    size = nodes["ImageSize"]
    if (w is None or h is None) and isinstance(size, np.ndarray):
        if size.shape != (2,):
            raise InputError(f"ImageSize must be [width, height], got {size.tolist()}", path)
        w, h = size
    if w is None or h is None:
        raise InputError("OpenCV calibration file has no 'image_width'/'image_height' (or 'Camera.width'/'Camera.height', "
                         "or 'ImageSize')", path)
    model = nodes["DistModel"]
    if model is not None and model not in OPENCV_MODELS:
        raise InputError(f"DistModel {model!r} is not supported (plumb_bob or rational_polynomial: OpenCV's model)", path)
    return camera_from_values(path, w, h, K, dist)


def _read_ros(path: Path, data: dict) -> Camera:
    """ROS camera_info YAML (camera_calibration's ost.yaml): matrices as {rows, cols, data}."""
    def matrix(key: str):
        m = data.get(key)
        return m.get("data") if isinstance(m, dict) else m

    model = data.get("distortion_model", "plumb_bob")
    if model not in OPENCV_MODELS:
        raise InputError(f"distortion_model {model!r} is not supported (plumb_bob or rational_polynomial: OpenCV's model)", path)
    try:
        K = np.array(matrix("camera_matrix"), float).reshape(3, 3)
    except (TypeError, ValueError):
        raise InputError("camera_matrix.data must be 9 numbers (3x3, rows)", path) from None
    return camera_from_values(path, data.get("image_width"), data.get("image_height"), K,
                              matrix("distortion_coefficients"))


def kalibr_camera(path: Path, data: dict) -> dict | None:
    """The camera block (cam0) of a Kalibr camchain YAML; None when `data` is not one. A chain of
    several cameras is an InputError: which of them took the photo is not in the file."""
    cams = [k for k in data if isinstance(k, str) and re.fullmatch(r"cam\d+", k)]
    if not cams:
        return None
    if len(cams) > 1:
        raise InputError(f"a Kalibr camchain of {len(cams)} cameras ({', '.join(cams)}): keep only the block of the "
                         "camera that took the photo", path)
    if not isinstance(data[cams[0]], dict):
        raise InputError(f"{cams[0]} must be a mapping (Kalibr's camchain)", path)
    return data[cams[0]]


def _read_kalibr(path: Path, cam: dict) -> Camera:
    """Kalibr's camera block: camera_model pinhole, intrinsics [fu, fv, pu, pv], resolution
    [width, height], distortion_model radtan (OpenCV's k1 k2 p1 p2) or none."""
    model, distortion = cam.get("camera_model", "pinhole"), cam.get("distortion_model", "none")
    if model != "pinhole":
        raise InputError(f"camera_model {model!r} is not supported (pinhole: OpenCV's model)", path)
    if distortion not in ("radtan", "none"):
        raise InputError(f"distortion_model {distortion!r} is not supported (radtan or none: OpenCV's model)", path)
    try:
        fx, fy, cx, cy = (float(v) for v in cam.get("intrinsics"))
        w, h = cam.get("resolution")
    except (TypeError, ValueError):
        raise InputError("intrinsics must be [fu, fv, pu, pv] and resolution [width, height], got "
                         f"{cam.get('intrinsics')!r:.60} and {cam.get('resolution')!r:.40}", path) from None
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return camera_from_values(path, w, h, K, cam.get("distortion_coeffs") if distortion == "radtan" else None)


def _read_livox(path: Path, camera: dict, size: tuple[int, int]) -> Camera:
    """livox_camera_calib's calib.yaml: camera.camera_matrix (9 numbers, rows) and
    camera.dist_coeffs (OpenCV's); no image size."""
    try:
        K = np.array(camera["camera_matrix"], float).reshape(3, 3)
    except (TypeError, ValueError):
        raise InputError("camera.camera_matrix must be 9 numbers (3x3, rows)", path) from None
    return camera_from_values(path, size[0], size[1], K, camera.get("dist_coeffs"))


def read_camera(path: str | os.PathLike,
                size: tuple[int, int] | Callable[[], tuple[int, int]] | None = None,
                photo: str | os.PathLike | None = None) -> Camera:
    """Read a camera file: the project's YAML (width, height, fx, fy, cx, cy[, distortion]),
    ROS camera_info YAML (image_width, image_height, camera_matrix.data, distortion_coefficients.data),
    Kalibr's camchain YAML of one camera (cam0: intrinsics, resolution, distortion_coeffs), an
    OpenCV calibration file (camera_matrix, distortion_coefficients, image_width, image_height; or
    Autoware's CameraMat, DistCoeff, ImageSize), or one without an image size: a calibration text file (`io.calib_txt`: K and D lines),
    koide3's calib.json (`io.calib_json`) or livox_camera_calib's calib.yaml (camera.camera_matrix,
    camera.dist_coeffs). size: the photo's (width, height), or a function that gives it, for the
    files without one; photo: that photo's file, named in the messages.
    """
    from rgbd_gt.io.calib_json import is_calib_json, read_json_camera
    from rgbd_gt.io.calib_txt import is_calib_txt, read_calib_camera

    def sized(read: Callable[[tuple[int, int]], Camera]) -> Camera:
        if size is None:
            raise InputError("this camera file has no image size: give the photo too (export-depth: --image) or "
                             "write a camera YAML", path)
        cam = read(size() if callable(size) else size)
        # the photo's size is taken on trust here. Lenses put the principal point within a few
        # percent of the centre, so one more than 20 % of the photo away gives a resized photo or
        # another camera's away (KITTI's K on a Waymo photo: 36 %; PJLab's on its photo enlarged
        # twice: 25 %)
        at = np.array([cam.cx / cam.width, cam.cy / cam.height])
        off = np.abs(at - 0.5).max()
        if off > 0.2:
            named = f"the {cam.width}x{cam.height} photo" + (f" {photo}" if photo else "")
            x, y = (round(100 * float(v)) for v in at)  # whole percents: never "-0%"
            raise InputError(f"the principal point ({cam.cx:g}, {cam.cy:g}) lies {off:.0%} of the photo's size from the "
                             f"centre of {named} (at {x}% of its width, {y}% of its height; lenses keep "
                             "it within 20 %): is this file for that photo (a resized photo needs K scaled)? A photo "
                             "cropped off its centre needs a camera YAML with its size", path)
        return cam

    path = require_file(path)
    if is_calib_json(path):
        return sized(lambda wh: read_json_camera(path, wh))
    if is_calib_txt(path):
        return sized(lambda wh: read_calib_camera(path, wh))
    text = path.read_text(errors="replace")
    if is_opencv_file(path, text):
        return _read_opencv(path)
    data = read_yaml(path, text)
    if not isinstance(data, dict):
        raise InputError("camera file must be a YAML mapping", path)
    if "camera_matrix" in data and "image_width" in data:
        return _read_ros(path, data)
    kalibr = kalibr_camera(path, data)
    if kalibr is not None:
        return _read_kalibr(path, kalibr)
    if isinstance(data.get("camera"), dict) and "camera_matrix" in data["camera"]:
        return sized(lambda wh: _read_livox(path, data["camera"], wh))
    missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in data]
    if missing:
        raise InputError(f"camera file lacks {', '.join(missing)}", path)
    data = {**data, **{k: yaml_number(data[k]) for k in ("width", "height", "fx", "fy", "cx", "cy")}}
    bad = [k for k in ("fx", "fy", "cx", "cy") if isinstance(data[k], bool) or not isinstance(data[k], (int, float))]
    if bad:
        raise InputError(f"{bad[0]} must be a number, got {data[bad[0]]!r:.40}", path)
    K = np.array([[data["fx"], 0, data["cx"]], [0, data["fy"], data["cy"]], [0, 0, 1]], float)
    return camera_from_values(path, data["width"], data["height"], K, data.get("distortion"))


def camera_to_dict(camera: Camera) -> dict:
    # plain Python numbers: a camera built from numpy values would not serialise
    d = {"width": int(camera.width), "height": int(camera.height), "fx": float(camera.fx), "fy": float(camera.fy),
         "cx": float(camera.cx), "cy": float(camera.cy)}
    if camera.distortion:
        d["distortion"] = [float(x) for x in camera.distortion]
    return d


def write_camera(path: str | os.PathLike, camera: Camera, **extra) -> None:
    """Write the project's camera YAML (atomically); `extra`: further keys after the camera's
    (readers ignore them: a solved camera's 1-sigma)."""
    with atomic_output(path) as tmp:
        tmp.write_text(yaml.safe_dump(camera_to_dict(camera) | extra, sort_keys=False, default_flow_style=None))


def check_image_matches(camera: Camera, image_shape: tuple[int, ...], image_path, camera_path) -> None:
    """Raise InputError when an image's size is not the camera file's size."""
    h, w = image_shape[:2]
    if (w, h) != (camera.width, camera.height):
        turned = " (turned by 90 deg: a camera calibrated on the photo on its side?)" if (h, w) == camera.size else ""
        raise InputError(
            f"image is {w}x{h} but camera file {camera_path} is for {camera.width}x{camera.height}{turned}", image_path
        )
