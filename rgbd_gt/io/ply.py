"""PLY point clouds: read binary (either endianness) and ascii; write binary little-endian.

Vertex properties understood: x y z (float or double); red green blue (uchar, ushort or
float in [0,1]; also r g b and diffuse_*); intensity or CloudCompare's scalar_Intensity;
row col scan_id; nx ny nz (normals, turned to face the scan origin when there is one). Scan origins travel in header comments: `comment rgbd_gt origin ID X Y Z`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from rgbd_gt.errors import InputError, numpy_text_problem
from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.scan import Scan, ring_ids

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
COLOR_NAMES = (("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue"))
INTENSITY_NAMES = ("intensity", "scalar_intensity", "scalar_Intensity", "Intensity")
WRITE_CHUNK = 1 << 20
# float32 resolves 15 um at 256 m; beyond that (georeferenced scans) store doubles.
DOUBLE_ABOVE_M = 256.0


def _parse_header(path: Path, f) -> tuple[str, list[tuple[str, int, list]], list[str]]:
    """Returns (format, elements [(name, count, [(prop, type or ('list', ...))])], comments)."""
    if f.readline().strip() != b"ply":
        raise InputError("not a PLY file (no 'ply' magic)", path)
    fmt, elements, comments = None, [], []
    while True:
        line = f.readline()
        if not line:
            raise InputError("PLY header has no end_header", path)
        words = line.decode("ascii", errors="replace").split()
        if not words:
            continue
        key = words[0]
        if key == "end_header":
            break
        if key == "format" and len(words) >= 2:
            fmt = words[1]
        elif key == "comment":
            comments.append(line.decode("utf-8", errors="replace").strip()[len("comment") :].strip())
        elif key == "element" and len(words) == 3:
            if not words[2].isdigit():
                raise InputError(f"PLY element '{words[1]}' has count {words[2]!r}, not a whole number of 0 or more", path)
            count = int(words[2])
            elements.append((words[1], count, []))
        elif key == "property" and elements:
            if words[1] == "list" and len(words) == 5:
                elements[-1][2].append((words[4], ("list", words[2], words[3])))
            elif len(words) == 3 and words[1] in PLY_TYPES:
                elements[-1][2].append((words[2], PLY_TYPES[words[1]]))
            else:
                raise InputError(f"unsupported PLY property line: {line.decode(errors='replace').strip()}", path)
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(f"unknown PLY format '{fmt}'", path)
    return fmt, elements, comments


def _vertex_table(path: Path) -> tuple[np.ndarray, list[str]]:
    """The vertex element as a structured array (native byte order), and the header comments."""
    try:
        with open(path, "rb") as f:
            fmt, elements, comments = _parse_header(path, f)
            names = [e[0] for e in elements]
            if "vertex" not in names:
                raise InputError("PLY file has no vertex element", path)
            before = elements[: names.index("vertex")]
            _, count, props = elements[names.index("vertex")]
            if any(isinstance(t, tuple) for _, t in props):
                raise InputError("PLY vertex element has list properties", path)
            if fmt == "ascii":
                left = os.fstat(f.fileno()).st_size - f.tell()
                # a value takes at least 2 bytes ("0 "): a count beyond that is a truncated (or lying) file,
                # found before anything is allocated or skipped
                if sum(n * max(1, len(p)) for _, n, p in before) + count * len(props) > (left + 1) / 2:
                    raise InputError(f"PLY file is truncated: {left:,} bytes of data cannot hold {count:,} vertices", path)
                for _, n, _p in before:  # skip the lines of earlier elements
                    for _i in range(n):
                        f.readline()
                dtype = np.dtype([(p, t) for p, t in props])
                raw = np.loadtxt(f, dtype=np.float64, max_rows=count, ndmin=2) if count else np.zeros((0, len(props)))
                if raw.shape != (count, len(props)):
                    raise InputError(f"PLY ascii vertex data has shape {raw.shape}, expected ({count}, {len(props)})", path)
                table = np.empty(count, dtype)
                for j, (p, t) in enumerate(props):
                    column = raw[:, j]
                    bad = ~np.isfinite(column)
                    if np.dtype(t).kind in "ui":
                        info = np.iinfo(t)
                        bad |= (column < info.min) | (column > info.max) | (column != np.round(column))
                    if bad.any():
                        k = int(np.flatnonzero(bad)[0])
                        raise InputError(f"PLY vertex {k}: {p} = {column[k]} is not a valid {t}", path)
                    table[p] = column
                return table, comments
            order = "<" if fmt == "binary_little_endian" else ">"
            for name, n, p in before:
                if any(isinstance(t, tuple) for _, t in p):
                    raise InputError(f"PLY element '{name}' with list properties precedes the vertices", path)
                f.seek(n * np.dtype([(q, order + t) for q, t in p]).itemsize, os.SEEK_CUR)
            dtype = np.dtype([(p, order + t) for p, t in props])
            if count * dtype.itemsize > os.fstat(f.fileno()).st_size - f.tell():
                raise InputError(f"PLY file is truncated: it cannot hold the {count:,} vertices it declares", path)
            table = np.fromfile(f, dtype=dtype, count=count)
            if table.shape[0] != count:
                raise InputError(f"PLY file is truncated: {table.shape[0]} of {count} vertices", path)
            if order == ">":
                table = table.astype(table.dtype.newbyteorder("="))
            return table, comments
    except InputError:
        raise
    except (OSError, ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read PLY: {numpy_text_problem(exc)}", path) from None


def _colors(table: np.ndarray) -> np.ndarray | None:
    names = table.dtype.names
    for triple in COLOR_NAMES:
        if all(c in names for c in triple):
            kind = table.dtype[triple[0]]
            out = np.empty((table.shape[0], 3), np.uint8)
            for j, c in enumerate(triple):
                v = table[c]
                if kind == np.uint8:
                    out[:, j] = v
                elif kind.kind in "ui":  # 16-bit (or wider) integer colors
                    out[:, j] = np.clip(np.rint(v * (255.0 / np.iinfo(kind).max)), 0, 255)
                else:  # float colors: [0, 1] by convention, 0..255 if they exceed 1
                    scale = 255.0 if (v.size == 0 or v.max() <= 1.0) else 1.0
                    out[:, j] = np.clip(np.rint(v * scale), 0, 255)
            return out
    return None


def _intensity(table: np.ndarray) -> np.ndarray | None:
    for name in INTENSITY_NAMES:
        if name in table.dtype.names:
            v = table[name]
            if v.dtype.kind in "ui":
                return (v / np.iinfo(v.dtype).max).astype(np.float32)
            v = v.astype(np.float32)
            lo, hi = (float(v.min()), float(v.max())) if v.size else (0.0, 1.0)
            # no declared limits in PLY: the data's range (a non-finite value is left for
            # `check_values` to name)
            if np.isfinite(lo) and np.isfinite(hi) and (lo < 0 or hi > 1):
                v = (v - lo) / (hi - lo) if hi > lo else np.zeros_like(v)
            return v
    return None


def _origins(path: Path, comments: list[str]) -> np.ndarray:
    """The scanner positions of `comment rgbd_gt origin K x y z` lines, (S, 3) metres."""
    rows = {}
    for c in comments:
        w = c.split()
        if len(w) == 6 and w[0] == "rgbd_gt" and w[1] == "origin":
            try:
                k, xyz = int(w[2]), [float(x) for x in w[3:6]]
            except ValueError:
                raise InputError(f"PLY comment 'rgbd_gt origin' is not 'K x y z': {c}", path) from None
            if not (0 <= k < 100_000 and np.isfinite(xyz).all()):
                raise InputError(f"PLY comment 'rgbd_gt origin' has an invalid index or value: {c}", path)
            rows[k] = xyz
    if sorted(rows) != list(range(len(rows))):
        raise InputError(f"PLY comments 'rgbd_gt origin' are not numbered 0..{len(rows) - 1}", path)
    return np.array([rows[k] for k in sorted(rows)], float).reshape(-1, 3)


def _scan_ids(path: Path, table: np.ndarray, origins: np.ndarray) -> np.ndarray | None:
    """The scan_id property: indices into the origins when they are given, else labels (made 0..S-1)."""
    if "scan_id" not in table.dtype.names:
        return None
    ids = table["scan_id"]
    if not np.isfinite(ids).all() or (ids.size and ids.min() < 0):
        raise InputError("PLY scan_id must be whole numbers of 0 or more", path)
    if len(origins):
        if ids.size and ids.max() >= len(origins):
            raise InputError(f"PLY scan_id {int(ids.max())} has no 'rgbd_gt origin' comment ({len(origins)} given)", path)
        return ids.astype(np.int32)
    return np.unique(ids, return_inverse=True)[1].astype(np.int32).ravel()


def read_ply(path: str | os.PathLike) -> Scan:
    """Read a PLY point cloud into a Scan (see the module docstring for the fields)."""
    path = Path(path)
    table, comments = _vertex_table(path)
    names = table.dtype.names
    if not all(c in names for c in "xyz"):
        raise InputError("PLY vertices have no x, y, z properties", path)
    xyz = np.empty((table.shape[0], 3), np.float64)
    for j, c in enumerate("xyz"):
        xyz[:, j] = table[c]
    grid = "row" in names and "col" in names
    origins = _origins(path, comments)
    scan = Scan(
        xyz=xyz,
        rgb=_colors(table),
        intensity=_intensity(table),
        row=table["row"].astype(np.int32) if grid else None,
        col=table["col"].astype(np.int32) if grid else None,
        scan_id=_scan_ids(path, table, origins),
        origins=origins,
        ring=ring_ids(table["ring"]) if "ring" in names else None,
    )
    if all(c in names for c in ("nx", "ny", "nz")):  # as the file has them: preparing orients them (`oriented`)
        n = np.stack([table[c] for c in ("nx", "ny", "nz")], 1).astype(np.float32)
        length = np.linalg.norm(n, axis=1, keepdims=True)
        scan.normals = np.where(np.isfinite(length) & (length > 0), n / np.where(length > 0, length, 1), 0).astype(np.float32)
    del table
    return scan


def write_ply(path: str | os.PathLike, scan: Scan, ascii: bool = False, double: bool | None = None) -> None:
    """Write a Scan as PLY (atomically); binary little-endian unless `ascii`.

    double: store coordinates as double (None: only when some |coordinate| > 256 m).
    """
    xyz = scan.xyz
    if double is None:
        double = bool(xyz.size) and float(np.abs(xyz).max()) > DOUBLE_ABOVE_M
    ct = "f8" if double else "f4"
    fields = [("x", ct), ("y", ct), ("z", ct)]
    if scan.rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if scan.intensity is not None:
        fields.append(("intensity", "f4"))
    if scan.has_grid:
        fields += [("row", "i4"), ("col", "i4")]
    if scan.scan_id is not None:
        fields.append(("scan_id", "i4"))
    if scan.normals is not None:
        fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    if scan.ring is not None:
        fields.append(("ring", "i2"))
    dtype = np.dtype([(n, "<" + t) for n, t in fields])
    type_names = {"f8": "double", "f4": "float", "u1": "uchar", "i4": "int", "i2": "short"}
    header = ["ply", f"format {'ascii' if ascii else 'binary_little_endian'} 1.0", "comment written by rgbd-gt"]
    header += [f"comment rgbd_gt origin {i} " + " ".join(repr(float(v)) for v in o) for i, o in enumerate(np.asarray(scan.origins, float))]
    header += [f"element vertex {len(scan)}"]
    header += [f"property {type_names[t]} {n}" for n, t in fields]
    header += ["end_header"]
    with atomic_output(path) as tmp, open(tmp, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        for start in range(0, len(scan), WRITE_CHUNK):  # chunks bound the extra memory
            stop = min(start + WRITE_CHUNK, len(scan))
            block = np.empty(stop - start, dtype)
            for j, c in enumerate("xyz"):
                block[c] = xyz[start:stop, j]
            if scan.rgb is not None:
                for j, c in enumerate(("red", "green", "blue")):
                    block[c] = scan.rgb[start:stop, j]
            if scan.intensity is not None:
                block["intensity"] = scan.intensity[start:stop]
            if scan.has_grid:
                block["row"] = scan.row[start:stop]
                block["col"] = scan.col[start:stop]
            if scan.scan_id is not None:
                block["scan_id"] = scan.scan_id[start:stop]
            if scan.normals is not None:
                for j, c in enumerate(("nx", "ny", "nz")):
                    block[c] = scan.normals[start:stop, j]
            if scan.ring is not None:
                block["ring"] = scan.ring[start:stop]
            if ascii:
                fmts = ["%.17g" if t.startswith("f") else "%d" for _, t in fields]
                np.savetxt(f, block.tolist(), fmt=fmts)
            else:
                f.write(block.tobytes())
