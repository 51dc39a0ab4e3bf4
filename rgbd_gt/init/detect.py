"""Board corner detection in an 8-bit gray image (a photo or a rendered view of the scan)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


MAX_SQUARE_M = 10.0  # a board square larger than this is a typo (or millimetres given as metres)


@dataclass(frozen=True)
class BoardSpec:
    """cols x rows inner corners, `square` metres. For ChArUco, `charuco` names the ArUco
    dictionary (e.g. DICT_5X5_100) and `marker` is the marker side in metres."""

    cols: int = 9
    rows: int = 6
    square: float = 0.05
    charuco: str | None = None
    marker: float | None = None

    def object_points(self) -> np.ndarray:
        """(cols*rows, 3) inner corners in the board frame, x fastest (OpenCV's order), metres;
        for ChArUco, indexed by corner id."""
        if self.charuco:
            return np.asarray(self.charuco_board().getChessboardCorners(), np.float64).reshape(-1, 3)
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        return np.stack([i.ravel(), j.ravel(), np.zeros(i.size)], 1) * self.square

    def charuco_board(self):
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.charuco))
        marker = self.marker or 0.75 * self.square
        return cv2.aruco.CharucoBoard((self.cols + 1, self.rows + 1), self.square, marker, d)


def detect_corners(gray: np.ndarray, spec: BoardSpec) -> tuple[np.ndarray, np.ndarray] | None:
    """Sub-pixel inner corners (n, 2) and their ids (n,) into spec.object_points(), or None.

    Chessboards: cv2.findChessboardCornersSB (all corners, ids 0..n-1 in OpenCV's order, which
    may be the board's order or its 180-degree turn). ChArUco: ids are unambiguous.
    """
    if spec.charuco:
        det = cv2.aruco.CharucoDetector(spec.charuco_board())
        corners, ids, _, _ = det.detectBoard(gray)
        if ids is None or len(ids) < 6:
            return None
        return corners.reshape(-1, 2).astype(np.float64), ids.ravel().astype(np.int64)
    flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY | cv2.CALIB_CB_NORMALIZE_IMAGE
    found, corners = cv2.findChessboardCornersSB(gray, (spec.cols, spec.rows), flags=flags)
    if not found:
        return None
    # the saddle-point refinement over a 9x9 window: on small boards (squares of ~15-20 px)
    # it halves the worst PnP errors of the synthetic benchmark
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    corners = cv2.cornerSubPix(gray, corners.astype(np.float32), (4, 4), (-1, -1), crit)
    return corners.reshape(-1, 2).astype(np.float64), np.arange(spec.cols * spec.rows)
