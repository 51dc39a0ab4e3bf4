"""A result's covariance with groups of its points as the samples. The aligners' own (Laplace:
the inverse of the objective's curvature) take every point as an independent sample, but
neighbouring points share pixels, and a scan and a photo differ in patches (sampling, blur,
shading) and, for a drive, frame by frame (timing, distortion). The sandwich H^-1 B H^-1 of the
groups' shares of the gradient (a cluster-robust covariance) sees how far they pull apart."""

from __future__ import annotations

import numpy as np

# a photo in this many x this many tiles, each a sample of the pose's covariance (`tile_scores` of
# the objectives): residuals of neighbouring points are not independent (they share pixels, and the
# scan's colors and the photo differ in patches); on ICL-NUIM and synthetic scenes 4 x 4 to 16 x 16
# gave about the same widening (docs/trust.md, "The covariance a single photo states")
TILES = 8


def sandwich(g: np.ndarray, H: np.ndarray, units: np.ndarray | None = None) -> np.ndarray | None:
    """(P, P) H^-1 B H^-1, B = K / (K - 1) times the scatter of g: g (K, P) the K samples' shares
    of the objective's gradient at the result, H (P, P) the objective's Hessian (Gauss-Newton
    matrix) there, both in parameters scaled by units (P,) (default 1), the result in the
    parameters' own units. None for fewer than 2 samples or where H is not positive definite."""
    if len(g) < 2 or not np.isfinite(H).all() or np.linalg.eigvalsh(H)[0] <= 0:
        return None
    gc = g - g.mean(0)
    A = np.linalg.solve(H, gc.T)  # (P, K) each sample's pull on the minimum
    if units is not None:
        A = A * units[:, None]
    return len(g) / (len(g) - 1) * A @ A.T


def wider(cov: np.ndarray | None, other: np.ndarray | None) -> np.ndarray | None:
    """cov (P, P) widened wherever `other` is wider: the larger of the two along each axis of cov
    whitened (never narrower than cov). None where cov is not finite and positive definite or
    other is None."""
    if cov is None or other is None or not np.isfinite(cov).all() or not np.isfinite(other).all():
        return None
    try:
        L = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        return None
    Li = np.linalg.inv(L)
    lam, V = np.linalg.eigh(Li @ other @ Li.T)
    return L @ (V * np.maximum(lam, 1.0)) @ V.T @ L.T
