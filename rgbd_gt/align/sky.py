"""Where a photo shows sky: no laser return comes from there.

In a street scene the sky is the largest region of a photo and the most uniform one. A
statistical objective such as NID rewards any pose that puts one class of scan points on it
(tree points onto a bright sky make "high intensity -> bright" as tidy a relation as the true
one), and on the PJLab sweeps it drifted by degrees to such poses. A sweep has no points in the
sky, so the aligner charges for every point that lands there (`nid_objective.Nid`, cfg.sky_weight).

The sky is found in the photo, at 1/8 scale: the smooth, bright, not reddish regions that reach
into the top 15% of the photo, cover at least 1% of it, and in which the sweep at the initial
pose has almost no points (a white ceiling or wall that the scanner sees is not sky, even where
it looks like it).
"""

from __future__ import annotations

import numpy as np

from rgbd_gt.scan import LUMA

SCALE = 8  # the photo is examined at 1/SCALE
SMOOTH = 0.08  # Sobel gradient magnitude (gray in [0, 1], at 1/SCALE) below which a pixel is smooth
TOP = 0.15  # a sky region reaches into this top fraction of the photo ...
MIN_AREA = 0.01  # ... covers at least this fraction of it ...
EMPTY = 0.1  # ... and holds fewer scan points per pixel than this times the photo's average


def sky_mask(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(H, W) float32 in [0, 1]: 1 where the photo shows sky, with soft borders.

    image: (H, W, 3) float32 RGB in [0, 1], undistorted; uv: (N, 2) pixel positions of the scan's
    points at the initial pose (those outside the photo are ignored)."""
    import cv2

    h, w = image.shape[:2]
    sw, sh = max(1, w // SCALE), max(1, h // SCALE)
    small = cv2.resize(np.ascontiguousarray(image, dtype=np.float32), (sw, sh), interpolation=cv2.INTER_AREA)
    gray = small @ np.array(LUMA, np.float32)
    smooth = np.hypot(cv2.Sobel(gray, cv2.CV_32F, 1, 0), cv2.Sobel(gray, cv2.CV_32F, 0, 1)) < SMOOTH
    candidate = smooth & (gray >= np.percentile(gray, 40)) & (small[..., 2] >= small[..., 0])
    n, label = cv2.connectedComponents(candidate.astype(np.uint8), connectivity=4)
    area = np.bincount(label.ravel(), minlength=n)
    u, v = (uv[:, 0] / w * sw).astype(np.int64), (uv[:, 1] / h * sh).astype(np.int64)
    inside = (u >= 0) & (v >= 0) & (u < sw) & (v < sh)
    points = np.bincount(label[v[inside], u[inside]], minlength=n)
    average = max(int(inside.sum()), 1) / label.size
    top = np.unique(label[: max(1, int(TOP * sh))])
    sky = [k for k in top if k > 0 and area[k] >= MIN_AREA * label.size and points[k] < EMPTY * average * area[k]]
    mask = cv2.morphologyEx(np.isin(label, sky).astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    return cv2.resize(mask.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
