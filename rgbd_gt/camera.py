"""Pinhole camera with OpenCV lens distortion: project, back-project, undistort, rescale.

Pixel convention (OpenCV): pixel (u, v) = (column, row), the centre of the top-left pixel is
(0, 0). The camera frame is OpenCV's: x right, y down, z forward; units are metres.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

# Camera corrections refined with the pose (`refine --refine-intrinsics`), per mode: how many of
# q = (focal scale - 1, principal point shift x and y in normalised units, k1, k2, p1, p2, k3)
# are free; `full` is OpenCV's model of five distortion coefficients (`render.project.project_corrected`).
INTRINSICS = {"none": 0, "focal": 1, "focal+principal": 3, "focal+principal+k1k2": 5, "full": 8}
Q_SIZE = 8


@dataclass(frozen=True)
class Camera:
    """Intrinsics of one camera at one resolution.

    distortion: OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6[, ...]]]); () for none.
    """

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...] = ()

    def __post_init__(self):
        # plain Python numbers, whatever made them (numpy scalars would turn the float32 arithmetic
        # they meet into float64, and they key the renders of a camera: render/renders.py)
        for name in ("width", "height"):
            object.__setattr__(self, name, int(getattr(self, name)))
        for name in ("fx", "fy", "cx", "cy"):
            object.__setattr__(self, name, float(getattr(self, name)))
        object.__setattr__(self, "distortion", tuple(float(d) for d in self.distortion))

    @property
    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return any(abs(d) > 0 for d in self.distortion)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height) in pixels."""
        return self.width, self.height


def without_distortion(camera: Camera) -> Camera:
    """The same intrinsics with no lens distortion (the model of an undistorted image)."""
    return dataclasses.replace(camera, distortion=())


def project(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project camera-frame points to pixels, applying the lens distortion.

    Args:
        points: (N, 3) float, metres, camera frame.
    Returns:
        uv: (N, 2) float64 pixel coordinates; z: (N,) depth along the optical axis (metres).
        Points with z <= 0 get uv = nan.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    z = pts[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = np.where(z[:, None] > 0, pts[:, :2] / z[:, None], np.nan)
    return distort(camera, xn), z


def _radial(d: list[float], r2: np.ndarray) -> np.ndarray:
    """OpenCV's radial factor (1 + k1 r^2 + k2 r^4 + k3 r^6) / (1 + k4 r^2 + k5 r^4 + k6 r^6)."""
    k1, k2, _, _, k3, k4, k5, k6 = (d + [0.0] * 8)[:8]
    return (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / (1 + r2 * (k4 + r2 * (k5 + r2 * k6)))


def fold_radius(distortion: tuple[float, ...]) -> float:
    """The normalised radius (x/z, y/z) up to which the lens model's radial part maps radius one
    to one; inf where it does up to 89.9 deg off the axis. Beyond it the distorted radius falls
    again: a barrel lens's coefficients, fitted inside the photo, put points 50-60 deg off the axis
    back inside it (with KITTI's raw camera, 14% of a sweep's points in the photo are such ghosts)."""
    d = list(distortion)
    if not any(d[:2] + d[4:8]):
        return float("inf")
    r = np.geomspace(1e-3, 600.0, 30_000)  # steps of 0.04%
    f = r * _radial(d, r * r)
    falls = np.flatnonzero(~(np.diff(f) > 0))
    return float(r[falls[0]]) if len(falls) else float("inf")


def lens_reach(camera: Camera) -> tuple[float, float]:
    """(reach, corner): the farthest normalised distorted radius the lens model maps to (at its
    `fold_radius`; inf without a fold) and that of the photo's farthest corner. reach < corner:
    the model turns back inside the photo, and its outer pixels have no ray."""
    fold = fold_radius(camera.distortion)
    reach = fold * float(_radial(list(camera.distortion), np.float64(fold * fold))) if np.isfinite(fold) else np.inf
    u = max(camera.cx + 0.5, camera.width - 0.5 - camera.cx) / camera.fx  # the outer edges of the corner pixels
    v = max(camera.cy + 0.5, camera.height - 0.5 - camera.cy) / camera.fy
    return float(reach), float(np.hypot(u, v))


def distort(camera: Camera, xn: np.ndarray) -> np.ndarray:
    """Normalised image coordinates (N, 2) (x/z, y/z) -> distorted pixels (N, 2) float64, OpenCV's
    model: radial (k1, k2, k3 over k4, k5, k6), tangential (p1, p2) and thin prism (s1..s4), the
    pinhole alone without coefficients; nan stays nan, and points beyond the model's
    `fold_radius` become nan (no pixel images them). In numpy (cv2.projectPoints takes about
    1.6 s per million points); the tilted models (14 coefficients) go to OpenCV."""
    xn = np.asarray(xn, np.float64).reshape(-1, 2)
    d = list(camera.distortion)
    limit = fold_radius(camera.distortion)
    if np.isfinite(limit):
        xn = np.where((np.hypot(xn[:, 0], xn[:, 1]) < limit)[:, None], xn, np.nan)
    if len(d) > 12:
        import cv2

        uv = np.full_like(xn, np.nan)
        ok = np.isfinite(xn).all(axis=1)
        if ok.any():
            obj = np.concatenate([xn[ok], np.ones((ok.sum(), 1))], axis=1)
            uv[ok] = cv2.projectPoints(obj, np.zeros(3), np.zeros(3), camera.K, np.asarray(d, float))[0].reshape(-1, 2)
        return uv
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = d + [0.0] * (12 - len(d))
    x, y = xn[:, 0], xn[:, 1]
    r2 = x * x + y * y
    r4 = r2 * r2
    radial = _radial(d, r2)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) + s1 * r2 + s2 * r4
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y + s3 * r2 + s4 * r4
    return np.stack([camera.fx * xd + camera.cx, camera.fy * yd + camera.cy], axis=1)


def undistort_points(camera: Camera, uv: np.ndarray) -> np.ndarray:
    """Distorted pixels (N, 2) -> normalised image coordinates (N, 2) (x/z, y/z)."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    if not camera.has_distortion:
        return np.stack([(uv[:, 0] - camera.cx) / camera.fx, (uv[:, 1] - camera.cy) / camera.fy], axis=1)
    import cv2

    # the default 5 iterations leave ~0.1 px errors near the image corners
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    out = cv2.undistortPoints(uv.reshape(-1, 1, 2), camera.K, np.asarray(camera.distortion, float), None, None, None, crit)
    return out.reshape(-1, 2)


def backproject(camera: Camera, uv: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) with z-depth (N,) in metres -> camera-frame points (N, 3)."""
    xn = undistort_points(camera, uv)
    d = np.asarray(depth, np.float64).reshape(-1, 1)
    return np.concatenate([xn * d, d], axis=1)


def undistort_image(camera: Camera, image: np.ndarray, interpolation: int | None = None,
                    constant_border: bool = False) -> np.ndarray:
    """Remove lens distortion; the result follows `without_distortion(camera)` (same K).

    image: (H, W[, C]) array of the camera's size. Returns an array of the same shape/dtype.
    constant_border: fill pixels that come from outside the photo with 0 (else replicate).
    """
    if not camera.has_distortion:
        return image
    import cv2

    interp = cv2.INTER_LINEAR if interpolation is None else interpolation
    map1, map2 = cv2.initUndistortRectifyMap(
        camera.K, np.asarray(camera.distortion, float), None, camera.K, camera.size, cv2.CV_32FC1
    )
    border = cv2.BORDER_CONSTANT if constant_border else cv2.BORDER_REPLICATE
    return cv2.remap(image, map1, map2, interp, borderMode=border, borderValue=0)


def rescale(camera: Camera, width: int, height: int) -> Camera:
    """The camera for the same optics at another resolution (e.g. an image pyramid level).

    Scales about pixel corners, so pixel centres keep the OpenCV convention:
    c' = (c + 0.5) * s - 0.5. Distortion acts on normalised coordinates and is unchanged.
    """
    sx, sy = width / camera.width, height / camera.height
    return dataclasses.replace(
        camera,
        width=int(width),
        height=int(height),
        fx=camera.fx * sx,
        fy=camera.fy * sy,
        cx=(camera.cx + 0.5) * sx - 0.5,
        cy=(camera.cy + 0.5) * sy - 0.5,
    )


def corrected(camera: Camera, q) -> Camera:
    """The camera with the corrections q of `render.project.project_corrected` applied (5 or 8
    values): focal scaled by 1 + q0, principal point moved by (fx q1, fy q2), k1, k2 (and p1, p2,
    k3) added to the file's (OpenCV's order: k1, k2, p1, p2, k3)."""
    q = [float(v) for v in q] + [0.0] * max(0, 8 - len(q))
    dist = list(camera.distortion) + [0.0] * max(0, 5 - len(camera.distortion))
    if any(q[3:8]):
        for k, v in enumerate(q[3:8]):  # q's order is OpenCV's
            dist[k] += v
    else:
        dist = list(camera.distortion)
    return dataclasses.replace(camera, fx=camera.fx * (1 + q[0]), fy=camera.fy * (1 + q[0]),
                               cx=camera.cx + camera.fx * q[1], cy=camera.cy + camera.fy * q[2],
                               distortion=tuple(dist))
