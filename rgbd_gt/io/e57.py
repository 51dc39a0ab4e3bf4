"""E57 (ASTM E2807) scans and embedded images, through pye57's libE57 bindings.

Points are read in chunks straight into preallocated output arrays, so a 40-million-point
scan is loaded without a Python loop per point and with about one copy of the data in
memory (plus one chunk).
"""

from __future__ import annotations

import os
import re
import struct
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.errors import InputError
from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.scan import Scan
from rgbd_gt.io.native import native_output
from rgbd_gt.pose import matrix_to_quat, quat_to_matrix

CHUNK = 1 << 18  # points per read: bounds the extra memory to a few tens of MB
CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
COLORS = ("colorRed", "colorGreen", "colorBlue")
IMAGE_KINDS = ("pinhole", "spherical", "cylindrical", "visualReference")


def _libe57():
    from pye57 import libe57

    return libe57


def _first_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


def _open(path: Path):
    libe57 = _libe57()
    if path.stat().st_size == 0:
        raise InputError("not an E57 file (empty)", path)
    try:
        with native_output():
            imf = libe57.ImageFile(str(path), "r")
            imf.root()
    except Exception as exc:  # libE57 raises its own exception type for every failure
        raise InputError(f"cannot read E57: {_first_line(exc)}", path) from None
    _check_xml_floats(path)
    return imf


FLOAT_ELEMENT = re.compile(r'<(\w+) type="Float"[^>]*>([^<]*)<')


def _xml(path: Path) -> str:
    """The file's XML section (libE57 has checked the page checksums by now). An E57 file is
    pages of `pageSize` bytes, the last 4 of each a CRC; the header (48 bytes) says where the XML
    starts and how long it is."""
    with open(path, "rb") as f:
        head = f.read(48)
        _, _, _, offset, length, page = struct.unpack("<IIQQQQ", head[8:48])
        out, pos = bytearray(), offset
        while len(out) < length:
            start = pos - pos % page
            f.seek(pos)
            chunk = f.read(min(page - 4 - (pos - start), length - len(out)))
            if not chunk:
                break
            out += chunk
            pos = start + page
    return out.decode("utf-8", errors="replace")


def _check_xml_floats(path: Path) -> None:
    """Every Float element's text must be a finite number: libE57 reads the text 'nan' in a pose
    as 0, which turns a rotation into another one without a word."""
    for m in FLOAT_ELEMENT.finditer(_xml(path)):
        text = m.group(2).strip()
        if not text:
            continue
        try:
            ok = np.isfinite(float(text))
        except ValueError:
            ok = False
        if not ok:
            raise InputError(f"the E57 XML holds {m.group(1)} = {text!r}, not a finite number", path)


def _child(node, name):
    """The typed child `name` of a structure node, or None when it is absent."""
    from pye57.utils import get_node

    if not node.isDefined(name):
        return None
    return get_node(node, name)


def _number(node) -> float:
    libe57 = _libe57()
    if isinstance(node, libe57.ScaledIntegerNode):
        return float(node.scaledValue())
    return float(node.value())


def _struct_numbers(node, names) -> list[float] | None:
    if node is None or not all(node.isDefined(n) for n in names):
        return None
    return [_number(_child(node, n)) for n in names]


def _pose(node, path: object = None) -> np.ndarray:
    """4x4 local-to-world transform of a data3D or images2D entry (identity when absent)."""
    T = np.eye(4)
    pose = _child(node, "pose")
    if pose is None:
        return T
    q = _struct_numbers(_child(pose, "rotation"), ("w", "x", "y", "z"))
    t = _struct_numbers(_child(pose, "translation"), ("x", "y", "z"))
    if q is not None and not (np.isfinite(q).all() and np.linalg.norm(q) > 1e-6):
        raise InputError(f"pose rotation quaternion {q} is not a rotation (zero or not finite)", path)
    if t is not None and not np.isfinite(t).all():
        raise InputError(f"pose translation {t} is not finite", path)
    if q is not None:
        T[:3, :3] = quat_to_matrix(q)
    if t is not None:
        T[:3, 3] = t
    return T


def _limits(scan_node, group: str, lo: str, hi: str, proto_node) -> tuple[float, float] | None:
    """Declared value limits: the scan's `group` structure first, else the prototype's bounds."""
    declared = _struct_numbers(_child(scan_node, group), (lo, hi))
    if declared is not None and declared[1] > declared[0]:
        return declared[0], declared[1]
    libe57 = _libe57()
    if isinstance(proto_node, libe57.IntegerNode):
        return float(proto_node.minimum()), float(proto_node.maximum())
    if isinstance(proto_node, libe57.ScaledIntegerNode):
        return float(proto_node.scaledMinimum()), float(proto_node.scaledMaximum())
    if isinstance(proto_node, libe57.FloatNode) and max(abs(proto_node.minimum()), abs(proto_node.maximum())) < 1e30:
        return float(proto_node.minimum()), float(proto_node.maximum())
    return None  # float field with the default +-FLT_MAX bounds: nothing declared


@dataclass
class _ScanLayout:
    node: object
    count: int
    spherical: bool
    names: list[str]
    pose: np.ndarray


def _layout(path: Path, node) -> _ScanLayout:
    libe57 = _libe57()
    points = _child(node, "points")
    if points is None:
        raise InputError("a data3D entry has no points", path)
    proto = libe57.StructureNode(points.prototype())
    names = [proto.get(i).elementName() for i in range(proto.childCount())]
    if all(n in names for n in CARTESIAN):
        spherical = False
    elif all(n in names for n in SPHERICAL):
        spherical = True
    else:
        raise InputError(f"scan has neither cartesian nor spherical coordinates (fields: {names})", path)
    return _ScanLayout(node, int(points.childCount()), spherical, names, _pose(node, path))


def read_e57(
    path: str | os.PathLike,
    scan_index: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Scan:
    """Read every scan of an E57 file (or only `scan_index`) into one world-frame `Scan`.

    Each scan is moved by its pose (quaternion + translation). Points whose cartesian or
    spherical invalid-state is non-zero are dropped. Colors and intensity are scaled by their
    declared limits (colorLimits / intensityLimits, else the field's own bounds; intensity
    with no declared bounds uses the data's range). Raises InputError on any unreadable file.
    """
    path = Path(path)
    imf = _open(path)
    try:
        data3d = imf.root()["data3D"]
        n_scans = int(data3d.childCount())
        if n_scans == 0:
            raise InputError("the file holds no scans (data3D is empty)", path)
        if scan_index is not None and not 0 <= scan_index < n_scans:
            raise InputError(f"scan index {scan_index} out of range: the file has {n_scans} scan(s)", path)
        picked = range(n_scans) if scan_index is None else [scan_index]
        layouts = [_layout(path, data3d[i]) for i in picked]
        with native_output():
            try:
                return _read_points(imf, layouts, progress)
            except InputError:
                raise
            except Exception as exc:
                raise InputError(f"cannot read E57 points: {_first_line(exc)}", path) from None
    finally:
        imf.close()


def _read_points(imf, layouts: list[_ScanLayout], progress) -> Scan:
    libe57 = _libe57()
    total = sum(s.count for s in layouts)
    has = {
        "rgb": all(all(c in s.names for c in COLORS) for s in layouts),
        "intensity": all("intensity" in s.names for s in layouts),
        "grid": all("rowIndex" in s.names and "columnIndex" in s.names for s in layouts),
    }
    xyz = np.empty((total, 3), np.float64)
    rgb = np.empty((total, 3), np.uint8) if has["rgb"] else None
    inten = np.empty(total, np.float32) if has["intensity"] else None
    row = np.empty(total, np.int32) if has["grid"] else None
    col = np.empty(total, np.int32) if has["grid"] else None
    scan_id = np.empty(total, np.int32)
    origins = np.array([s.pose[:3, 3] for s in layouts])
    inten_limits: list[tuple[float, float] | None] = []
    inten_ranges: list[slice] = []

    k = 0  # number of valid points written so far
    done = 0
    for sid, s in enumerate(layouts):
        points = _child(s.node, "points")
        proto = libe57.StructureNode(points.prototype())
        coords = SPHERICAL if s.spherical else CARTESIAN
        state_name = "sphericalInvalidState" if s.spherical else "cartesianInvalidState"
        wanted = list(coords)
        if has["rgb"]:
            wanted += COLORS
        if has["intensity"]:
            wanted.append("intensity")
        if has["grid"]:
            wanted += ["rowIndex", "columnIndex"]
        if state_name in s.names:
            wanted.append(state_name)
        cap = max(1, min(CHUNK, s.count))
        bufs = {}
        vec = libe57.VectorSourceDestBuffer()
        for name in wanted:
            # int8 for the state and float64 (exact for integers) for the rest: the bindings
            # take numpy int64 as a 32-bit C long and would garble it.
            dtype = np.int8 if name == state_name else np.float64
            bufs[name] = np.empty(cap, dtype)
            vec.append(libe57.SourceDestBuffer(imf, name, bufs[name], cap, True, True))
        color_lims = (
            [_limits(s.node, "colorLimits", f"{c}Minimum", f"{c}Maximum", _child(proto, c)) or (0.0, 255.0) for c in COLORS]
            if has["rgb"]
            else []
        )
        if has["intensity"]:
            inten_limits.append(_limits(s.node, "intensityLimits", "intensityMinimum", "intensityMaximum", _child(proto, "intensity")))
        start = k
        R, t = s.pose[:3, :3], s.pose[:3, 3]
        reader = points.reader(vec)
        try:
            while (n := int(reader.read())) > 0:
                keep = bufs[state_name][:n] == 0 if state_name in bufs else slice(0, n)
                a, b, c = (bufs[name][:n][keep] for name in coords)
                if s.spherical:  # E57 convention: azimuth from +x towards +y, elevation from the xy-plane
                    a, b, c = a * np.cos(c) * np.cos(b), a * np.cos(c) * np.sin(b), a * np.sin(c)
                m = a.shape[0]
                local = np.stack([a, b, c], axis=1)
                xyz[k : k + m] = local @ R.T + t
                if rgb is not None:
                    for j, (name, (lo, hi)) in enumerate(zip(COLORS, color_lims)):
                        v = (bufs[name][:n][keep] - lo) * (255.0 / (hi - lo))
                        rgb[k : k + m, j] = np.clip(np.rint(v), 0, 255)
                if inten is not None:
                    inten[k : k + m] = bufs["intensity"][:n][keep]
                if row is not None:
                    row[k : k + m] = bufs["rowIndex"][:n][keep]
                    col[k : k + m] = bufs["columnIndex"][:n][keep]
                k += m
                done += n
                if progress is not None:
                    progress(done, total)
        finally:
            reader.close()
        scan_id[start:k] = sid
        inten_ranges.append(slice(start, k))

    if inten is not None:
        for lims, sl in zip(inten_limits, inten_ranges):
            part = inten[sl]
            if lims is None:  # nothing declared: the data's own range
                lims = (float(part.min()), float(part.max())) if part.size else (0.0, 1.0)
            lo, hi = lims
            part -= lo
            part *= 1.0 / (hi - lo) if hi > lo else 0.0
            np.clip(part, 0.0, 1.0, out=part)
        part = None  # no view of `inten` may be left when it is resized below

    if k < total:  # invalid points left out: shrink in place, as a copy would double a big scan's peak
        for a in (xyz, rgb, inten, row, col, scan_id):
            if a is not None:
                a.resize((k,) + a.shape[1:], refcheck=False)  # no views of these arrays exist
    return Scan(xyz=xyz, rgb=rgb, intensity=inten, row=row, col=col, scan_id=scan_id, origins=origins)


@dataclass
class E57Image:
    """One Image2D entry of an E57 file.

    kind: 'pinhole' | 'spherical' | 'cylindrical' | 'visualReference'.
    format: 'jpeg' | 'png'. pose: 4x4 image-to-world transform, or None when the file has none.
    params: the representation's numbers (focalLength, pixelWidth, ... as the file names them).
    """

    index: int
    name: str
    kind: str
    format: str
    width: int
    height: int
    nbytes: int
    pose: np.ndarray | None = None
    params: dict = field(default_factory=dict)

    @property
    def suffix(self) -> str:
        return ".jpg" if self.format == "jpeg" else ".png"


def _image_entry(index: int, node) -> tuple[E57Image, object] | None:
    libe57 = _libe57()
    for kind in IMAGE_KINDS:
        rep = _child(node, f"{kind}Representation")
        if rep is None:
            continue
        blob, fmt = None, None
        for fmt_name, blob_name in (("jpeg", "jpegImage"), ("png", "pngImage")):
            blob = _child(rep, blob_name)
            if blob is not None:
                fmt = fmt_name
                break
        if blob is None:
            return None
        params = {}
        for i in range(rep.childCount()):
            name = rep.get(i).elementName()
            child = _child(rep, name)
            if isinstance(child, (libe57.FloatNode, libe57.IntegerNode, libe57.ScaledIntegerNode)):
                params[name] = _number(child)
        name_node = _child(node, "name")
        return (
            E57Image(
                index=index,
                name=name_node.value() if name_node is not None else f"image{index}",
                kind=kind,
                format=fmt,
                width=int(params.pop("imageWidth", 0)),
                height=int(params.pop("imageHeight", 0)),
                nbytes=int(blob.byteCount()),
                pose=_pose(node) if node.isDefined("pose") else None,
                params=params,
            ),
            blob,
        )
    return None


def list_e57_images(path: str | os.PathLike) -> list[E57Image]:
    """The Image2D entries of an E57 file (entries without image data are skipped)."""
    return [img for img, _ in _images(Path(path), with_data=False)]


def read_e57_images(path: str | os.PathLike) -> list[tuple[E57Image, bytes]]:
    """Every Image2D entry with its encoded image bytes (JPEG or PNG, as stored)."""
    return list(_images(Path(path), with_data=True))


def _images(path: Path, with_data: bool):
    imf = _open(path)
    try:
        root = imf.root()
        if not root.isDefined("images2D"):
            return []
        images2d = root["images2D"]
        out = []
        for i in range(int(images2d.childCount())):
            entry = _image_entry(i, images2d[i])
            if entry is None:
                continue
            img, blob = entry
            if with_data:
                buf = np.empty(img.nbytes, np.uint8)
                with native_output():
                    blob.read(buf, 0, img.nbytes)
                out.append((img, buf.tobytes()))
            else:
                out.append((img, None))
        return out
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"cannot read E57 images: {_first_line(exc)}", path) from None
    finally:
        imf.close()


def pinhole_intrinsics(image: E57Image) -> dict | None:
    """Camera-file values (width, height, fx, fy, cx, cy) of a pinhole Image2D, else None.

    E57 stores the focal length and pixel pitch in metres and the principal point in pixels.
    """
    p = image.params
    if image.kind != "pinhole" or not all(k in p for k in ("focalLength", "pixelWidth", "pixelHeight")):
        return None
    if not all(np.isfinite(p[k]) and p[k] > 0 for k in ("focalLength", "pixelWidth", "pixelHeight")) or not all(
            np.isfinite(p.get(k, 0.0)) for k in ("principalPointX", "principalPointY")):
        return None  # the caller says so
    return {
        "width": image.width,
        "height": image.height,
        "fx": p["focalLength"] / p["pixelWidth"],
        "fy": p["focalLength"] / p["pixelHeight"],
        "cx": p.get("principalPointX", (image.width - 1) / 2),
        "cy": p.get("principalPointY", (image.height - 1) / 2),
    }


def write_e57(
    path: str | os.PathLike,
    scans: list[Scan],
    poses: list[np.ndarray] | None = None,
    spherical: bool = False,
    names: list[str] | None = None,
) -> None:
    """Write scans to an E57 file (atomically), one data3D entry per scan.

    Each scan's `xyz` is in its own sensor frame; `poses[i]` (4x4) maps it to the world frame.
    Coordinates are stored as doubles, cartesian or (spherical=True) range/azimuth/elevation.
    Colors (0..255), intensity (0..1) and row/column indices are written when present.
    GUIDs are derived from the data, so the same scans give a byte-identical file.
    """
    libe57 = _libe57()
    poses = poses if poses is not None else [np.eye(4)] * len(scans)
    with atomic_output(path) as tmp:
        imf = libe57.ImageFile(str(tmp), "w")
        try:
            root = imf.root()
            imf.extensionsAdd("", libe57.E57_V1_0_URI)
            root.set("formatName", libe57.StringNode(imf, "ASTM E57 3D Imaging Data File"))
            root.set("guid", libe57.StringNode(imf, _guid("file", *[_digest(s) for s in scans])))
            root.set("versionMajor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MAJOR))
            root.set("versionMinor", libe57.IntegerNode(imf, libe57.E57_FORMAT_MINOR))
            root.set("e57LibraryVersion", libe57.StringNode(imf, libe57.E57_LIBRARY_ID))
            root.set("coordinateMetadata", libe57.StringNode(imf, ""))
            data3d = libe57.VectorNode(imf, True)
            root.set("data3D", data3d)
            root.set("images2D", libe57.VectorNode(imf, True))
            for i, (scan, T) in enumerate(zip(scans, poses)):
                name = names[i] if names else f"scan{i}"
                _write_scan(imf, data3d, scan, np.asarray(T, float), spherical, name)
        finally:
            imf.close()


def _digest(scan: Scan) -> str:
    import hashlib

    h = hashlib.sha1()
    for name in scan.fields:
        h.update(np.ascontiguousarray(getattr(scan, name)).tobytes())
    return h.hexdigest()


def _guid(*parts: str) -> str:
    return f"{{{uuid.uuid5(uuid.NAMESPACE_URL, 'rgbd-gt/' + '/'.join(parts))}}}"


def _write_scan(imf, data3d, scan: Scan, T: np.ndarray, spherical: bool, name: str) -> None:
    libe57 = _libe57()
    node = libe57.StructureNode(imf)
    node.set("guid", libe57.StringNode(imf, _guid("scan", name, _digest(scan), T.tobytes().hex())))
    node.set("name", libe57.StringNode(imf, name))
    node.set("description", libe57.StringNode(imf, "written by rgbd-gt"))

    pose = libe57.StructureNode(imf)
    rot, trans = libe57.StructureNode(imf), libe57.StructureNode(imf)
    for key, v in zip("wxyz", matrix_to_quat(T[:3, :3])):
        rot.set(key, libe57.FloatNode(imf, float(v)))
    for key, v in zip("xyz", T[:3, 3]):
        trans.set(key, libe57.FloatNode(imf, float(v)))
    pose.set("rotation", rot)
    pose.set("translation", trans)
    node.set("pose", pose)

    xyz = scan.xyz
    columns: dict[str, np.ndarray] = {}
    if spherical:
        rng = np.linalg.norm(xyz, axis=1)
        columns["sphericalRange"] = rng
        columns["sphericalAzimuth"] = np.arctan2(xyz[:, 1], xyz[:, 0])
        columns["sphericalElevation"] = np.arcsin(np.divide(xyz[:, 2], rng, out=np.zeros_like(rng), where=rng > 0))
    else:
        columns.update(zip(CARTESIAN, xyz.T))
    proto = libe57.StructureNode(imf)
    for key, v in columns.items():
        lo, hi = (float(v.min()), float(v.max())) if v.size else (0.0, 0.0)
        proto.set(key, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE, min(lo, 0.0), max(hi, 0.0)))
    if scan.rgb is not None:
        limits = libe57.StructureNode(imf)
        for j, c in enumerate(COLORS):
            columns[c] = scan.rgb[:, j]
            proto.set(c, libe57.IntegerNode(imf, 0, 0, 255))
            limits.set(f"{c}Minimum", libe57.IntegerNode(imf, 0))
            limits.set(f"{c}Maximum", libe57.IntegerNode(imf, 255))
        node.set("colorLimits", limits)
    if scan.intensity is not None:
        columns["intensity"] = scan.intensity
        proto.set("intensity", libe57.FloatNode(imf, 0.0, libe57.E57_SINGLE, 0.0, 1.0))
        limits = libe57.StructureNode(imf)
        limits.set("intensityMinimum", libe57.FloatNode(imf, 0.0))
        limits.set("intensityMaximum", libe57.FloatNode(imf, 1.0))
        node.set("intensityLimits", limits)
    if scan.has_grid:
        bounds = libe57.StructureNode(imf)
        for key, v in (("row", scan.row), ("column", scan.col)):
            lo, hi = (int(v.min()), int(v.max())) if v.size else (0, 0)
            columns[f"{key}Index"] = v
            proto.set(f"{key}Index", libe57.IntegerNode(imf, lo, lo, hi))
            bounds.set(f"{key}Minimum", libe57.IntegerNode(imf, lo))
            bounds.set(f"{key}Maximum", libe57.IntegerNode(imf, hi))
        node.set("indexBounds", bounds)

    points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
    node.set("points", points)
    data3d.append(node)

    n = len(scan)
    cap = max(1, min(CHUNK, n))
    bufs = {key: np.empty(cap, np.float64) for key in columns}
    vec = libe57.VectorSourceDestBuffer()
    for key, buf in bufs.items():
        vec.append(libe57.SourceDestBuffer(imf, key, buf, cap, True, True))
    writer = points.writer(vec)
    try:
        for start in range(0, n, cap):
            m = min(cap, n - start)
            for key, buf in bufs.items():
                buf[:m] = columns[key][start : start + m]
            writer.write(m)
    finally:
        writer.close()
