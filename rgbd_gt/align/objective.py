"""What the driver (align/aligner.py) asks of an objective: the interface that
align/photometric.py (`Photometric`) and align/nid_objective.py (`Nid`) implement. Poses are
4x4 float64 in the objective's local frame (scan points minus `centre`); q (Q_SIZE,) is the camera
corrections every pose of a batch shares (`render.project.project_corrected`)."""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Terms(Protocol):
    """An evaluation of a batch of B poses at one level."""

    loss: object  # (B,) the objective's value per pose
    visible: object  # (B,) scan points seen per pose
    H: object  # (B, P, P) Gauss-Newton matrix over 6 pose parameters and the free q (LM only)
    g: object  # (B, P) its gradient (LM only)

    def where(self, keep: np.ndarray, other: "Terms") -> "Terms":
        """Per pose: these terms where keep (B,) is True, `other`'s elsewhere."""

    def record(self, b: int = 0) -> dict:
        """Pose b's figures for the level's log."""


class Objective(Protocol):
    name: str  # "photometric" | "nid": the pose file's `objective`
    method: str  # "lm" | "adam" | "lbfgs": how the driver minimises it
    wide_search: bool  # whether far spurious minima call for the coarse level's wide search
    free: int  # how many of q are refined (0: none)
    centre: np.ndarray  # (3,) the local frame's origin in the scan frame, metres
    cfg: object  # align.config.RefineConfig
    device: object  # torch.device

    def prepare(self, T_local: np.ndarray) -> int:
        """Choose every level's points once, around this pose; the number of levels."""

    def evaluate(self, level: int, Ts: list[np.ndarray], q, prev: Terms | None = None, jacobian: bool = False,
                 free: int | None = None, lost_is_error: bool = True) -> Terms:
        """Terms at the poses Ts; with jacobian the Gauss-Newton system over the pose and the
        first `free` of q; prev: the terms the poses moved from (what an objective keeps of
        them: its fits, the points; an objective may ignore it); lost_is_error: InputError when
        a pose sees nothing."""

    def trial(self, level: int, Ts: list[np.ndarray], q, at: Terms) -> np.ndarray:
        """(B,) the loss at the poses Ts on the points and fits of `at` (LM's step test)."""

    def covariance(self, level: int, T_local: np.ndarray, q, at: Terms) -> np.ndarray | None:
        """(6 + free, 6 + free) the result's covariance (radians, metres, q), or None."""

    def summary(self, at: Terms) -> dict:
        """The result's figures (inlier fraction, color transform, ...) for the pose file."""

    def residuals(self, level: int, at: Terms):
        """Per-point residuals for the report, or None."""

    def visible_scan_points(self, T_local: np.ndarray, q) -> np.ndarray:
        """(n, 3) local-frame scan points seen at the pose (the verdict's motion metric)."""


# the poses evaluated together (`Aligner._lbfgs`'s starts, `Nid.frame_quadratics`' steps) see at
# most this many points together (unless one sees more alone): the joined arrays cost about 0.6 kB
# a point, and past a few hundred thousand points an evaluation is memory traffic, not overhead (a
# KITTI 19-frame solve's 17 search starts together took 1.8 GB where one after another took 1.3,
# and no less time)
LOCKSTEP_POINTS = 300_000


def lockstep(sizes: list[int | None], most: int = LOCKSTEP_POINTS) -> list[list[int]]:
    """Indices of the poses with sizes (points seen; None: none, left out) dealt in order into
    groups of at most `most` points together (a pose larger alone is a group of its own)."""
    groups: list[list[int]] = []
    total = most + 1
    for i, n in enumerate(sizes):
        if n is None:
            continue
        if total + n > most:
            groups.append([])
            total = 0
        groups[-1].append(i)
        total += n
    return groups
