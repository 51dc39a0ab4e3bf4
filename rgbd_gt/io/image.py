"""Photos and masks."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from rgbd_gt.errors import InputError, require_file
from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.io.native import native_output


IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")  # what the image outputs may be
OPENCV_LOG_PREFIX = re.compile(r"^\[\w+:[\d@.]+\]\s+global\s+\S+:\d+\s+\w+\s+")
MAX_PIXELS = 400_000_000  # a header claiming more is corrupt (or a photo no camera takes)


def _imread(path: Path, flags: int) -> np.ndarray:
    """cv2.imread with the header's size checked first and the decoder's complaints as errors."""
    import cv2

    try:
        import warnings

        from PIL import Image

        # Pillow's own guard, at this limit: it warns past MAX_IMAGE_PIXELS (the check below says
        # it in one line) and refuses past twice that before it gives the size
        Image.MAX_IMAGE_PIXELS = MAX_PIXELS
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            try:
                with Image.open(path) as im:
                    w, h = im.size
            except Image.DecompressionBombError:
                raise InputError(f"image header claims more than {2 * MAX_PIXELS:,} pixels", path) from None
        if w * h > MAX_PIXELS:
            raise InputError(f"image header claims {w}x{h} pixels (more than {MAX_PIXELS:,})", path)
    except (ImportError, OSError, SyntaxError, ValueError):
        pass  # not a format Pillow knows: OpenCV decides
    with native_output((2,)) as said:
        try:
            img = cv2.imread(str(path), flags)
        except cv2.error:
            img = None
    bad = [line for line in said if "Premature end" in line or "Corrupt JPEG" in line or "error" in line.lower()]
    if img is None or img.size == 0 or bad:
        # OpenCV's log lines start with where it logged: "[ERROR:0@94.036] global grfmt_png.cpp:297 readHeader "
        why = f" ({OPENCV_LOG_PREFIX.sub('', bad[0].strip())})" if bad else ""
        raise InputError(f"not a readable image{why}", path)
    return img


def read_image(path: str | os.PathLike, to_align: bool = False) -> np.ndarray:
    """Read a photo as (H, W, 3) uint8 RGB (grayscale and 16-bit images are converted, alpha
    dropped), turned as its EXIF orientation says: the photo as viewers show it and as OpenCV's
    imread gives it by default, so that a camera calibrated with OpenCV on it fits (a phone's
    portrait JPEG is stored on its side).
    `to_align`: InputError for a photo of one value (a lens cap, a failed exposure): nothing to
    align a scan to."""
    import cv2

    path = require_file(path)
    img = _imread(path, cv2.IMREAD_ANYDEPTH | cv2.IMREAD_ANYCOLOR)  # IMREAD_UNCHANGED ignores the orientation
    if img.dtype == np.uint16:
        img = (img / 257.0 + 0.5).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InputError(f"unsupported image type {img.dtype}", path)
    if to_align and img.size and img.min() == img.max():
        raise InputError(f"every pixel of the photo is {int(img.flat[0])}: nothing to align the scan to", path)
    if img.ndim == 2:
        return np.repeat(img[:, :, None], 3, axis=2)
    return np.ascontiguousarray(img[:, :, ::-1])


def read_mask(path: str | os.PathLike, shape: tuple[int, int]) -> np.ndarray:
    """Read a mask image: (H, W) bool, True where pixels are to be IGNORED (non-zero pixels).

    shape: (H, W) the mask must have (the photo's).
    """
    import cv2

    path = require_file(path)
    m = _imread(path, cv2.IMREAD_GRAYSCALE)
    if m.shape != tuple(shape):
        raise InputError(f"mask is {m.shape[1]}x{m.shape[0]} but the photo is {shape[1]}x{shape[0]}", path)
    return m > 0


def write_image(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write an (H, W, 3) uint8 RGB or (H, W) image, atomically; format from the suffix."""
    import cv2

    img = rgb[:, :, ::-1] if rgb.ndim == 3 else rgb
    with atomic_output(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(img)):
            raise InputError("could not write image", path)
