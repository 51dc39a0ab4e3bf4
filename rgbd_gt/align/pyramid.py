"""The photo as the aligner sees it: undistorted once, in [0, 1], as an image pyramid."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from rgbd_gt.camera import Camera, rescale, undistort_image, without_distortion


@dataclass
class PhotoLevel:
    """One pyramid level. image: (H, W, 3) float32 in [0, 1]; valid: (H, W) bool of usable
    pixels (inside the original photo and not masked), or None when all are; camera: pinhole."""

    image: torch.Tensor
    valid: torch.Tensor | None
    camera: Camera

    @property
    def K(self) -> torch.Tensor:
        return torch.as_tensor(self.camera.K, dtype=self.image.dtype, device=self.image.device)


def photo_pyramid(photo: np.ndarray, camera: Camera, levels: int, device: torch.device,
                  ignore: np.ndarray | None = None) -> list[PhotoLevel]:
    """Undistort `photo` (H, W, 3) uint8 and build `levels` levels, finest first.

    Each coarser level halves the size by 2x2 box averaging (cv2.INTER_AREA), consistent with
    `camera.rescale` (pixel centres at (c + 0.5) * s - 0.5). `ignore`: (H, W) bool of masked pixels.
    """
    import cv2

    img = undistort_image(camera, photo.astype(np.float32) / 255.0)
    valid = np.ones(photo.shape[:2], np.float32) if ignore is None else (~ignore).astype(np.float32)
    if camera.has_distortion:  # pixels that the undistortion filled from outside the photo
        valid = (undistort_image(camera, valid, cv2.INTER_LINEAR, constant_border=True) > 0.999).astype(np.float32)
    cam = without_distortion(camera)
    out = []
    for level in range(levels):
        if level:
            w, h = max(1, img.shape[1] // 2), max(1, img.shape[0] // 2)
            img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
            valid = cv2.resize(valid, (w, h), interpolation=cv2.INTER_AREA)
            cam = rescale(cam, w, h)
        all_valid = bool(valid.min() > 0.999)
        out.append(PhotoLevel(
            image=torch.as_tensor(np.ascontiguousarray(img), device=device),
            valid=None if all_valid else torch.as_tensor(valid > 0.999, device=device),
            camera=cam,
        ))
    return out
