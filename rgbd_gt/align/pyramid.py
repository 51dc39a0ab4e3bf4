"""The photo as the aligner sees it: undistorted once (or kept as taken, for refined
intrinsics), in [0, 1], as an image pyramid."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from rgbd_gt.camera import Camera, rescale, undistort_image, without_distortion


@dataclass
class PhotoLevel:
    """One pyramid level. image: (H, W, 3) float32 in [0, 1] (an enlarged level overshoots a
    little at edges); valid: (H, W) bool of usable pixels (inside the original photo and not
    masked), or None when all are; camera: pinhole, or the photo's own with its distortion when
    the pyramid keeps it (`photo_pyramid`'s `distorted`)."""

    image: torch.Tensor
    valid: torch.Tensor | None
    camera: Camera
    zoom: int = 1  # level pixels per photo pixel (> 1 on an upsampled finest level)

    def to_photo_pixels(self, uv: torch.Tensor) -> torch.Tensor:
        """(N, 2) pixel coordinates on this level -> on the photo (for levels at zoom >= 1)."""
        return (uv + 0.5) / self.zoom - 0.5

    @property
    def K(self) -> torch.Tensor:
        return torch.as_tensor(self.camera.K, dtype=self.image.dtype, device=self.image.device)


MAX_UPSAMPLED_PIXELS = 20_000_000  # ~240 MB as float32 RGB: large photos are not enlarged


def upsample_factor(size: tuple[int, int], upsample: int) -> int:
    """`upsample`, lowered so that the enlarged photo of `size` (W, H) stays within
    MAX_UPSAMPLED_PIXELS (never below 1)."""
    w, h = size
    return max(1, min(upsample, int(math.sqrt(MAX_UPSAMPLED_PIXELS / (w * h)))))


COARSEST_SIDE = 40  # px: the coarsest level's longer side is 40-79 px at any photo size


def pyramid_levels(size: tuple[int, int], levels: int | str = "auto") -> int:
    """`levels`, or for "auto" as many levels as bring a photo of `size` (W, H) down to a
    coarsest level whose longer side is COARSEST_SIDE to twice that (640x480: 5, 1280x960: 6,
    3072x2304: 7). Why: an init's error is a fixed angle, so its size in coarsest-level pixels,
    which decides whether the coarsest level's basin holds it, must not grow with the photo. With
    a fixed 5 levels a 1280x960 photo's coarsest level was 80x60 and inits 1 deg off ended 1.2-1.4
    deg off where 6 levels bring them to the truth (docs/trust.md, "Right poses refused on 1280x960 photos")."""
    if levels != "auto":
        return int(levels)
    return int(min(12, 1 + max(0, math.floor(math.log2(max(size) / COARSEST_SIDE)))))


def photo_pyramid(photo: np.ndarray, camera: Camera, levels: int | str, device: torch.device,
                  ignore: np.ndarray | None = None, upsample: int = 1, distorted: bool = False) -> list[PhotoLevel]:
    """Undistort `photo` (H, W, 3) uint8 and build `levels` levels (or "auto": `pyramid_levels`),
    finest first.

    distorted: keep the photo as taken, the levels' cameras with its distortion, for refined
    intrinsics. The objective then projects through the file's distortion plus its corrections,
    exactly the camera `camera.corrected` writes. (Undistorted with the file, the corrections were
    a first-order model of that camera: with a focal 2 % off, `focal` ended photos 2.4 mm off in
    the median where it now ends them 0.9 mm off: docs/intrinsics.md.)

    Each coarser level halves the size by 2x2 box averaging (cv2.INTER_AREA), consistent with
    `camera.rescale` (pixel centres at (c + 0.5) * s - 0.5). `ignore`: (H, W) bool of masked pixels.

    `upsample` > 1 replaces the finest level by the photo enlarged that much by bicubic
    interpolation (see `upsample_factor`). Bilinear interpolation at a sub-pixel point averages
    its pixel neighbours, a blur that changes with the sub-pixel position; the residual is then
    smallest where points fall on pixel centres, which pulls the pose towards such positions (on
    ICL-NUIM, where the scan is a depth image's pixel grid, towards the initial pose). On an
    enlarged photo the bilinear interpolant stays close to the bicubic one and that pull shrinks.
    """
    import cv2

    distorted = distorted and not any(camera.distortion[5:])  # the corrections' model ends at k3
    undistort = camera.has_distortion and not distorted
    img = photo.astype(np.float32) / 255.0
    valid = np.ones(photo.shape[:2], np.float32) if ignore is None else (~ignore).astype(np.float32)
    if undistort:  # and the pixels that the undistortion fills from outside the photo are not valid
        img = undistort_image(camera, img)
        valid = (undistort_image(camera, valid, cv2.INTER_LINEAR, constant_border=True) > 0.999).astype(np.float32)
    cam = camera if distorted else without_distortion(camera)
    zoom = upsample_factor(cam.size, upsample)
    out = []
    for level in range(pyramid_levels(cam.size, levels)):
        if level:
            w, h = max(1, img.shape[1] // 2), max(1, img.shape[0] // 2)
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            valid = cv2.resize(valid, (w, h), interpolation=cv2.INTER_AREA)
            cam = rescale(cam, w, h)
        out.append(_level(img, valid, cam, device) if level or zoom == 1 else _enlarged(img, valid, cam, zoom, device))
    return out


def _level(img: np.ndarray, valid: np.ndarray, cam: Camera, device: torch.device, zoom: int = 1) -> PhotoLevel:
    all_valid = bool(valid.min() > 0.999)
    return PhotoLevel(
        image=torch.as_tensor(np.ascontiguousarray(img), device=device),
        valid=None if all_valid else torch.as_tensor(valid > 0.999, device=device),
        camera=cam, zoom=zoom,
    )


def _enlarged(img: np.ndarray, valid: np.ndarray, cam: Camera, zoom: int, device: torch.device) -> PhotoLevel:
    import cv2

    w, h = cam.size[0] * zoom, cam.size[1] * zoom
    return _level(cv2.resize(img, (w, h), interpolation=cv2.INTER_CUBIC),
                  cv2.resize(valid, (w, h), interpolation=cv2.INTER_LINEAR), rescale(cam, w, h), device, zoom)
