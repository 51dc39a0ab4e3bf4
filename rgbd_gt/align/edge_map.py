"""The photo's side of the ring-edge term (Levinson and Thrun, RSS 2013): an edge image that
falls off with the distance to the nearest strong intensity edge, so that a sweep's depth
discontinuities (`render.rings.ring_steps`) score by how near they land to one. The fall-off is
in level pixels: a few pixels on the finest level, some tens of the photo's on the coarsest
level the term applies to. Levinson and Thrun's slow one (0.98 a pixel out to 40) held a
19-frame KITTI solve 4 cm back along the optical axis, where NID's own minimum lies, though
the sharp edges' score peaks within 2 cm of the reference (docs/lidar-method.md)."""

from __future__ import annotations

import numpy as np
import torch

from rgbd_gt.scan import LUMA

# the ring-edge check (the verdict's and qa's image check of a sweep): returns whose step along
# the ring is this large (on KITTI and Waymo their ratio is the clearest) ...
CHECK_MIN_STEP_M = 1.0
EDGE_NEAR_M = 1.0  # ... and this far in front of the camera (the edge term's too)
DECAY = 0.8  # per level pixel of chessboard distance from an edge (Levinson and Thrun's gamma) ...
REACH_PX = 8  # ... out to this far
OWN_SHARE = 1 / 3  # the edge's own strength in the map, the rest its spread (their alpha)


def edge_strength(image: torch.Tensor) -> np.ndarray:
    """(H, W, 3) photo in [0, 1] -> (H, W) float32 in [0, 1]: the largest gray difference to the
    8 neighbours, scaled by its 99th percentile."""
    import cv2

    gray = (image.detach().cpu().double() * torch.tensor(LUMA, dtype=torch.float64)).sum(2).numpy().astype(np.float32)
    box = np.ones((3, 3), np.uint8)
    e = np.maximum(cv2.dilate(gray, box) - gray, gray - cv2.erode(gray, box))
    scale = max(float(np.percentile(e[:: max(1, e.shape[0] // 400), :: max(1, e.shape[1] // 400)], 99)), 1e-6)
    return np.clip(e / scale, 0, 1)


def edge_distance_map(image: torch.Tensor) -> torch.Tensor:
    """(H, W, 3) photo in [0, 1] -> (H, W, 1) in [0, 1]: OWN_SHARE E + (1 - OWN_SHARE) max over
    pixels q within REACH_PX of E(q) DECAY^d(p, q), E the `edge_strength` (chessboard distance:
    REACH_PX dilations)."""
    import cv2

    e = edge_strength(image)
    spread = e.copy()
    box = np.ones((3, 3), np.uint8)
    for _ in range(REACH_PX):
        spread = np.maximum(e, DECAY * cv2.dilate(spread, box))
    out = OWN_SHARE * e + (1 - OWN_SHARE) * spread
    return torch.as_tensor(out[:, :, None], device=image.device, dtype=image.dtype)


def against_chance(edges: torch.Tensor, uv: torch.Tensor, weights: torch.Tensor, shift_px: float) -> tuple[float, float]:
    """The ring-edge check's score of points at uv (n, 2) pixels with weights (n,) on an edge
    image (H, W, 1) (`edge_strength`): the weighted sum of the edges there, and the mean of the
    same with the points shifted shift_px in the 8 directions (chance; a shift past the border
    samples the border: `bilinear` clamps)."""
    from rgbd_gt.align.sampling import bilinear

    shifts = shift_px * torch.tensor([[a, b] for a in (-1, 0, 1) for b in (-1, 0, 1) if a or b],
                                     dtype=torch.float32, device=uv.device)
    score = float((weights * bilinear(edges, uv)[:, 0]).sum())
    chance = float(np.mean([float((weights * bilinear(edges, uv + d)[:, 0]).sum()) for d in shifts]))
    return score, chance
