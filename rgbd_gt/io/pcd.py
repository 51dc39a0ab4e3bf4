"""PCD point clouds (PCL's format: ascii, binary, binary_compressed), read with Open3D.

Open3D reads the data; the header is checked here first, because Open3D answers a broken file
with a console warning and an empty cloud.
"""

from __future__ import annotations

import os
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

from rgbd_gt.errors import InputError
from rgbd_gt.io.native import native_output
from rgbd_gt.scan import Scan, ring_ids

INTENSITY_FIELDS = ("intensity", "reflectivity")
RING_FIELDS = ("ring", "channel", "laser_id")  # the laser of each return, as LiDAR drivers name it


def read_header(path: Path) -> dict[str, list[str]]:
    """The header lines of a PCD file as {KEY: values}, up to and including DATA."""
    header: dict[str, list[str]] = {}
    f_tell = 0
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
                f_tell = f.tell()
                break
    for key in ("FIELDS", "POINTS", "DATA"):
        if key not in header:
            raise InputError(f"not a PCD file (no {key} line in its header)", path)
    if header["DATA"][:1] not in (["ascii"], ["binary"], ["binary_compressed"]):
        raise InputError(f"unknown PCD DATA kind {' '.join(header['DATA'])!r}", path)
    if not {"x", "y", "z"} <= set(header["FIELDS"]):
        raise InputError(f"PCD has no x y z fields (fields: {' '.join(header['FIELDS'])})", path)
    _check_sizes(path, header, f_tell)
    kinds = {key: [header[key][header["FIELDS"].index(a)] for a in "xyz"] for key in ("SIZE", "TYPE", "COUNT") if key in header}
    if any(len(set(v)) > 1 for v in kinds.values()):
        raise InputError("PCD fields x, y and z differ in SIZE, TYPE or COUNT ("
                         + "; ".join(f"{k} {' '.join(v)}" for k, v in kinds.items()) + ")", path)
    try:
        view = [float(v) for v in header.get("VIEWPOINT", ["0"] * 7)]
    except ValueError:
        view = []
    if len(view) != 7 or not np.isfinite(view).all():
        raise InputError(f"PCD VIEWPOINT must be 7 finite numbers (tx ty tz qw qx qy qz), got {' '.join(header['VIEWPOINT'])!r}", path)
    return header


def _check_sizes(path: Path, header: dict[str, list[str]], data_offset: int) -> None:
    """The declared point count and field sizes against the file's length, before Open3D
    allocates for them (a header may claim 10^12 points)."""
    n_fields = len(header["FIELDS"])
    try:
        points = int(header["POINTS"][0])
        sizes = [int(v) for v in header.get("SIZE", ["4"] * n_fields)]
        counts = [int(v) for v in header.get("COUNT", ["1"] * n_fields)]
        shape = [int(header[k][0]) for k in ("WIDTH", "HEIGHT") if k in header]
    except (ValueError, IndexError):
        raise InputError("PCD header: POINTS, WIDTH, HEIGHT, SIZE and COUNT must be whole numbers", path) from None
    if len(shape) == 2 and (min(shape) < 0 or shape[0] * shape[1] != points):
        raise InputError(f"PCD header: WIDTH x HEIGHT ({shape[0]} x {shape[1]}) is not POINTS ({points})", path)
    lengths = {"FIELDS": n_fields, "SIZE": len(sizes), "TYPE": len(header.get("TYPE", ["F"] * n_fields)), "COUNT": len(counts)}
    if len(set(lengths.values())) > 1:
        raise InputError("PCD header: FIELDS, SIZE, TYPE and COUNT differ in length ("
                         + ", ".join(f"{k} {v}" for k, v in lengths.items()) + ")", path)
    bad = ([f"POINTS must be 0 or more, got {points}"] * (points < 0)
           + [f"SIZE must be 1, 2, 4 or 8, got {s}" for s in sizes if s not in (1, 2, 4, 8)]
           + [f"COUNT must be 1 or more, got {c}" for c in counts if c < 1])
    if bad:
        raise InputError(f"PCD header: {bad[0]}", path)
    row = sum(s * c for s, c in zip(sizes, counts))
    left = path.stat().st_size - data_offset
    kind = header["DATA"][0]
    room = left // row if kind == "binary" else (left + 1) // 2 if kind == "ascii" else (2**32 - 1) // row
    if points > room:
        each = f" of {row:,} bytes each (SIZE x COUNT)" if kind != "ascii" else ""
        raise InputError(f"PCD declares {points:,} points{each} but the file cannot hold them (truncated?)", path)
    if kind == "ascii":
        _check_ascii(path, data_offset, points * sum(counts))


_NUMBER_BYTES = np.zeros(256, bool)
_NUMBER_BYTES[list(b"0123456789+-.eEnaNAifIF")] = True
_SPACE_BYTES = np.zeros(256, bool)
_SPACE_BYTES[list(b" \t\r\n")] = True


def _check_ascii(path: Path, data_offset: int, values: int, chunk: int = 1 << 26) -> None:
    """ASCII data holds numbers only, as many as the header declares. Open3D reads a word as 0
    and fills a short row from uninitialised memory, without a word of warning. Read in chunks
    of `chunk` bytes: an ascii scan of millions of points is gigabytes."""
    data = np.memmap(path, np.uint8, mode="r", offset=data_offset) if path.stat().st_size > data_offset else np.zeros(0, np.uint8)
    found, lines, after_space = 0, 1, True
    for start in range(0, data.size, chunk):
        part = np.asarray(data[start:start + chunk])
        space = _SPACE_BYTES[part]
        bad = ~(_NUMBER_BYTES[part] | space)
        if bad.any():
            at = int(np.argmax(bad))
            line = lines + int(np.count_nonzero(part[:at] == ord("\n")))
            raise InputError(f"PCD data line {line}: {chr(part[at])!r} is not part of a number", path)
        found += int(np.count_nonzero(~space[1:] & space[:-1])) + int(after_space and not space[0])
        lines += int(np.count_nonzero(part == ord("\n")))
        after_space = bool(space[-1])
    if found != values:
        raise InputError(f"PCD data holds {found:,} numbers where the header declares {values:,} (rows short or long?)", path)


def normalise_intensity(raw: np.ndarray) -> np.ndarray:
    """Intensity in [0, 1]: kept when it already is, else divided by its 99th percentile and
    clipped (raw returns are 0-255 or 0-65535 with a few very bright retro-reflectors).
    raw: (N,) any numeric type; returns (N,) float32, NaN and inf where raw has them."""
    raw = np.asarray(raw, np.float32).ravel()
    finite = np.isfinite(raw)
    if not finite.any():
        return raw
    kept = raw[finite]
    scale = 1.0 if kept.max() <= 1.0 else max(float(np.percentile(kept, 99)), 1e-6)
    # a non-finite value is left as it is for `check_values` to name, as the PLY reader does
    return np.where(finite, np.clip(raw / np.float32(scale), 0, 1), raw).astype(np.float32)


NORMAL_FIELDS = ("normal_x", "normal_y", "normal_z")
OPEN3D_NAMES = ("positions", "colors", "normals")  # Open3D's own attributes: a field of that name replaces them


def names_for_open3d(header: dict[str, list[str]]) -> list[str] | None:
    """The FIELDS names to show Open3D, or None when the file's own are safe. Open3D's reader
    overruns its buffers and the process aborts on a repeated name of COUNT > 1 (PCL names each
    run of padding bytes `_`, and files from Ouster's and Velodyne's drivers hold several:
    `x y z _ intensity _ ring _`), on some but not all of normal_x, normal_y, normal_z, and on a
    field named `colors`; one named `positions` takes the points' place. Such names get a number;
    the fields keep their bytes, and the names read here (x y z, intensity, rgb, ring) stay."""
    fields = header["FIELDS"]
    n = len(fields)
    shape = list(zip(header.get("SIZE", ["4"] * n), header.get("TYPE", ["F"] * n), header.get("COUNT", ["1"] * n)))
    normals = [shape[fields.index(f)] for f in NORMAL_FIELDS if f in fields]
    odd = set(OPEN3D_NAMES)
    if normals and (len(normals) < 3 or len(set(normals)) > 1 or normals[0][2] != "1"):
        odd |= set(NORMAL_FIELDS)
    if len(set(fields)) == n and not odd & set(fields):
        return None
    shown: list[str] = []
    for name in fields:
        new, k = name, 0
        while new in shown or new in odd or (new != name and new in fields):
            k += 1
            new = f"{name}{k}"
        shown.append(new)
    return shown


def _renamed_copy(path: Path, names: list[str]) -> Path:
    """A temporary copy of a PCD file with another FIELDS line: the same data bytes."""
    fd, tmp = tempfile.mkstemp(suffix=".pcd")
    try:
        with open(path, "rb") as src, os.fdopen(fd, "wb") as dst:
            for line in iter(src.readline, b""):  # the header: read_header found its DATA line
                key = line.split()[:1]
                dst.write(b"FIELDS " + " ".join(names).encode() + b"\n" if key == [b"FIELDS"] else line)
                if key == [b"DATA"]:
                    break
            shutil.copyfileobj(src, dst, 1 << 24)
    except OSError as exc:  # a full temporary folder is no bug of the file's
        Path(tmp).unlink(missing_ok=True)
        raise InputError(f"its field names make Open3D read a copy, which {tempfile.gettempdir()} has no room for "
                         f"({exc.strerror}): set TMPDIR to a folder with room", path) from None
    return Path(tmp)


def read_pcd(path: str | Path) -> Scan:
    """A PCD file as a Scan: xyz (float64), intensity (from `intensity` or `reflectivity`,
    normalised), rgb (when the file has colors); the origin from VIEWPOINT. Points with
    non-finite coordinates (PCL's 'no return') are dropped."""
    import open3d as o3d

    path = Path(path)
    header = read_header(path)
    names = names_for_open3d(header)
    readable = _renamed_copy(path, names) if names else None
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error), native_output() as said:
        try:
            cloud = o3d.t.io.read_point_cloud(str(readable or path))
        except RuntimeError as exc:  # Open3D's error text carries its C++ function name and colour codes
            said.append(str(exc))
            cloud = None
        finally:
            if readable is not None:
                readable.unlink()
    if cloud is None:
        lines = [re.sub(r"\x1b\[[0-9;]*m|.*\.cpp:\d+:\s*|\[[0-9;]*m", "", ln).strip() for ln in said if "Error" in ln]
        why = next((ln for ln in lines if ln), "unreadable")
        raise InputError(f"could not read the PCD data ({why[:200]})", path)
    declared = int(header["POINTS"][0])  # a whole number of 0 or more: read_header checked it
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        if declared == 0:
            return Scan(xyz=np.zeros((0, 3)))
        raise InputError("could not read the PCD data (truncated or corrupt)", path)
    xyz = cloud.point.positions.numpy().astype(np.float64)
    if len(xyz) != declared:
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
    ring = next((ring_ids(cloud.point[name].numpy())[ok] for name in RING_FIELDS if name in cloud.point), None)
    view = [float(v) for v in header.get("VIEWPOINT", ["0"] * 7)[:3]]
    return Scan(xyz=xyz[ok], rgb=rgb, intensity=intensity, origins=np.array([view]), ring=ring)
