"""PCD point clouds (PCL's format: ascii, binary, binary_compressed), read with Open3D.

Open3D reads the data; the header is checked here first, because Open3D answers a broken file
with a console warning and an empty cloud.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rgbd_gt.errors import InputError
from rgbd_gt.io.scan import Scan

INTENSITY_FIELDS = ("intensity", "reflectivity")


def read_header(path: Path) -> dict[str, list[str]]:
    """The header lines of a PCD file as {KEY: values}, up to and including DATA."""
    header: dict[str, list[str]] = {}
    with open(path, "rb") as f:
        for _ in range(64):
            line = f.readline()
            if not line:
                break
            text = line.decode("ascii", errors="replace").strip()
            if not text or text.startswith("#"):
                continue
            key, *values = text.split()
            header[key.upper()] = values
            if key.upper() == "DATA":
                break
    for key in ("FIELDS", "POINTS", "DATA"):
        if key not in header:
            raise InputError(f"not a PCD file (no {key} line in its header)", path)
    if header["DATA"][:1] not in (["ascii"], ["binary"], ["binary_compressed"]):
        raise InputError(f"unknown PCD DATA kind {' '.join(header['DATA'])!r}", path)
    if not {"x", "y", "z"} <= set(header["FIELDS"]):
        raise InputError(f"PCD has no x y z fields (fields: {' '.join(header['FIELDS'])})", path)
    return header


def normalise_intensity(raw: np.ndarray) -> np.ndarray:
    """Intensity in [0, 1]: kept when it already is, else divided by its 99th percentile and
    clipped (raw returns are 0-255 or 0-65535 with a few very bright retro-reflectors)."""
    raw = np.asarray(raw, np.float32).ravel()
    finite = raw[np.isfinite(raw)]
    if finite.size == 0 or finite.max() <= 1.0:
        return np.clip(np.nan_to_num(raw), 0, 1)
    scale = max(float(np.percentile(finite, 99)), 1e-6)
    return np.clip(np.nan_to_num(raw) / scale, 0, 1).astype(np.float32)


def read_pcd(path: str | Path) -> Scan:
    """A PCD file as a Scan: xyz (float64), intensity (from `intensity` or `reflectivity`,
    normalised), rgb (when the file has colors); the origin from VIEWPOINT. Points with
    non-finite coordinates (PCL's 'no return') are dropped."""
    import open3d as o3d

    path = Path(path)
    header = read_header(path)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        cloud = o3d.t.io.read_point_cloud(str(path))
    declared = int(header["POINTS"][0]) if header["POINTS"] and header["POINTS"][0].isdigit() else -1
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        if declared == 0:
            return Scan(xyz=np.zeros((0, 3)))
        raise InputError("could not read the PCD data (truncated or corrupt)", path)
    xyz = cloud.point.positions.numpy().astype(np.float64)
    if declared >= 0 and len(xyz) != declared:
        raise InputError(f"PCD declares {declared} points but holds {len(xyz)}", path)
    ok = np.isfinite(xyz).all(axis=1)
    intensity = rgb = None
    for name in INTENSITY_FIELDS:
        if name in cloud.point:
            intensity = normalise_intensity(cloud.point[name].numpy())[ok]
            break
    if "colors" in cloud.point:
        c = cloud.point.colors.numpy()
        rgb = (np.clip(c, 0, 1) * 255).round().astype(np.uint8) if c.dtype.kind == "f" else c.astype(np.uint8)
        rgb = rgb[ok]
    view = [float(v) for v in header.get("VIEWPOINT", ["0"] * 7)[:3]]
    return Scan(xyz=xyz[ok], rgb=rgb, intensity=intensity, origins=np.array([view]))
