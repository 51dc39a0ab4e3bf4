import re
import warnings

import numpy as np
import pytest

from rgbd_gt.errors import InputError
from rgbd_gt.io import load_scan, save_scan
from rgbd_gt.scan import Scan
from rgbd_gt.io.ply import read_ply, write_ply
from rgbd_gt.io.scan import check_values


def _scan(n=500, offset=0.0, seed=0):
    rng = np.random.default_rng(seed)
    return Scan(
        xyz=rng.normal(size=(n, 3)) * 3 + offset,
        rgb=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        intensity=rng.random(n).astype(np.float32),
        row=(np.arange(n) // 25).astype(np.int32),
        col=(np.arange(n) % 25).astype(np.int32),
        scan_id=(np.arange(n) % 2).astype(np.int32),
        origins=np.array([[0.5, 1.5, 2.5], [offset, -1.0, 1e-3]]),
    )


@pytest.mark.parametrize("ascii", [False, True])
@pytest.mark.parametrize("double", [False, True])
def test_round_trip(tmp_path, ascii, double):
    s = _scan()
    write_ply(tmp_path / "a.ply", s, ascii=ascii, double=double)
    header = (tmp_path / "a.ply").read_bytes()[:400].decode("latin-1")
    assert ("binary_little_endian" in header) != ascii
    assert ("property double x" in header) == double
    r = read_ply(tmp_path / "a.ply")
    tol = 0 if double else 1e-6 * 20
    np.testing.assert_allclose(r.xyz, s.xyz, atol=tol, rtol=0)
    for name in ("rgb", "row", "col", "scan_id"):
        assert np.array_equal(getattr(r, name), getattr(s, name)), name
    np.testing.assert_array_equal(r.intensity, s.intensity)
    np.testing.assert_array_equal(r.origins, s.origins)


def test_large_coordinates_are_written_as_double(tmp_path):
    s = _scan(offset=4.2e5)  # georeferenced: float32 would lose centimetres
    save_scan(tmp_path / "g.ply", s)
    assert b"property double x" in (tmp_path / "g.ply").read_bytes()[:400]
    np.testing.assert_array_equal(load_scan(tmp_path / "g.ply").xyz, s.xyz)


def _write_raw(path, fmt, props, rows, pre=""):
    """A PLY written by hand, as other tools write them."""
    header = f"ply\nformat {fmt} 1.0\n{pre}element vertex {len(rows)}\n"
    header += "".join(f"property {t} {n}\n" for n, t in props) + "end_header\n"
    dt = np.dtype([(n, {"float": "f4", "double": "f8", "uchar": "u1", "ushort": "u2", "int": "i4"}[t]) for n, t in props])
    if fmt == "ascii":
        body = "".join(" ".join(repr(v) for v in r) + "\n" for r in rows).encode()
    else:
        arr = np.array([tuple(r) for r in rows], dt.newbyteorder("<" if fmt == "binary_little_endian" else ">"))
        body = arr.tobytes()
    path.write_bytes(header.encode() + body)


def test_big_endian_ushort_colors_and_cloudcompare_intensity(tmp_path):
    props = [("x", "float"), ("y", "float"), ("z", "float"), ("red", "ushort"), ("green", "ushort"),
             ("blue", "ushort"), ("scalar_Intensity", "float")]
    rows = [(1.0, 2.0, 3.0, 65535, 0, 32768, 10.0), (4.0, 5.0, 6.0, 0, 65535, 257, 30.0), (7, 8, 9, 257, 514, 0, 20.0)]
    _write_raw(tmp_path / "be.ply", "binary_big_endian", props, rows)
    s = read_ply(tmp_path / "be.ply")
    np.testing.assert_allclose(s.xyz, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    assert s.rgb.tolist() == [[255, 0, 128], [0, 255, 1], [1, 2, 0]]
    np.testing.assert_allclose(s.intensity, [0.0, 1.0, 0.5])  # no declared limits: the data's range


def test_ascii_file_with_an_element_before_vertices(tmp_path):
    props = [("x", "double"), ("y", "double"), ("z", "double"), ("red", "uchar"), ("green", "uchar"), ("blue", "uchar")]
    path = tmp_path / "a.ply"
    header = "ply\nformat ascii 1.0\nelement camera 1\nproperty float f\nelement vertex 2\n"
    header += "".join(f"property {t} {n}\n" for n, t in props) + "element face 0\nproperty list uchar int vertex_indices\nend_header\n"
    path.write_text(header + "1.5\n0.1 0.2 0.3 1 2 3\n4 5 6 7 8 9\n")
    s = read_ply(path)
    np.testing.assert_allclose(s.xyz, [[0.1, 0.2, 0.3], [4, 5, 6]])
    assert s.rgb.tolist() == [[1, 2, 3], [7, 8, 9]]
    assert s.intensity is None and s.row is None


@pytest.mark.parametrize(
    "content,needle",
    [
        (b"", "magic"),
        (b"solid cube\n", "magic"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\nproperty float y\nproperty float z\nend_header\n" + b"\0" * 20, "truncated"),
        (b"ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n3 0 1 2\n", "no vertex"),
        (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float a\nend_header\n1\n", "no x, y, z"),
        (b"ply\nformat ascii 1.0\nelement vertex 1e3\nproperty float x\nend_header\n1\n", "count '1e3', not a whole number"),
        # numpy's own words, less its advice to a programmer
        (b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
         b"1.5 2.5 3.5\n4.5 5.5\n1.5 2.5 3.5\n", r"number of columns changed from 3 to 2 at row 2\.?$"),
    ],
)
def test_corrupt_files_raise_input_error(tmp_path, content, needle):
    (tmp_path / "bad.ply").write_bytes(content)
    with pytest.raises(InputError, match=needle) as info:
        load_scan(tmp_path / "bad.ply")
    assert "bad.ply" in str(info.value)


@pytest.mark.parametrize("field, value, needle", [
    ("xyz", np.nan, "invalid coordinate"), ("xyz", -np.inf, "invalid coordinate"),
    ("xyz", 2e7, "invalid coordinate"), ("intensity", np.inf, "invalid intensity (inf)"),
    ("intensity", np.nan, "invalid intensity")])
def test_bad_values_are_named_by_point(tmp_path, field, value, needle):
    s = _scan()
    values = getattr(s, field)
    values.reshape(len(s), -1)[37, -1] = value
    write_ply(tmp_path / "a.ply", s, double=True)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # named, without numpy's noise on the way
        with pytest.raises(InputError, match=f"point 37 has an {re.escape(needle)}"):
            load_scan(tmp_path / "a.ply")
    values.reshape(len(s), -1)[37, -1] = 1e6 if field == "xyz" else 0.5  # in range: read as it is
    write_ply(tmp_path / "b.ply", s, double=True)
    assert np.array_equal(getattr(load_scan(tmp_path / "b.ply"), field), values)


def test_a_scanner_position_beyond_reach_is_named(tmp_path):
    """fuzz seed 32: an origin comment 1e30 m up was read, and overlay drew the scan with every
    surface turned to face it."""
    s = _scan()
    s.origins[1, 2] = 1e30
    write_ply(tmp_path / "a.ply", s)
    with pytest.raises(InputError, match=r"a.ply: scanner position 1 is \[0.0, -1.0, 1e\+30\], beyond 1e\+07 m"):
        load_scan(tmp_path / "a.ply")


def test_non_finite_normals_are_named():
    s = _scan()
    s.normals = np.tile(np.float32([0, 0, 1]), (len(s), 1))
    check_values(s, "scan")
    s.normals[12, 1] = np.nan
    with pytest.raises(InputError, match="point 12 has an invalid normal"):
        check_values(s, "scan")
