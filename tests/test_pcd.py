"""PCD scans: the real LiDAR sweeps, every DATA variant written by Open3D, and broken files."""

import numpy as np
import pytest

from conftest import DATA, assert_one_line_error, run_cli
from rgbd_gt.errors import InputError
from rgbd_gt.io import load_scan
from rgbd_gt.io.pcd import normalise_intensity


def test_real_lidar_sweeps():
    folder = DATA / "lidar_camera"
    if not folder.exists():
        pytest.skip(f"real test data not found at {folder}")
    for k, n in ((1, 101_340), (2, 98_805), (3, 85_546)):
        s = load_scan(folder / f"pjlab_{k}" / "calib.pcd")
        assert len(s) == n and s.fields == ["xyz", "intensity", "ring"]
        assert s.ring.min() == 0 and s.ring.max() == 63  # a 64-laser spinning LiDAR
        assert np.isfinite(s.xyz).all() and 0 <= s.intensity.min() and s.intensity.max() <= 1
        assert 0.2 < np.median(s.intensity) < 0.6  # raw 0-255 returns, median ~50, over their 99th percentile
        assert np.abs(s.xyz).max() < 300 and np.array_equal(s.origins, [[0, 0, 0]])


@pytest.mark.parametrize("ascii, compressed", [(True, False), (False, False), (False, True)])
def test_written_variants_read_back(tmp_path, ascii, compressed):
    import open3d as o3d

    rng = np.random.default_rng(0)
    xyz = rng.uniform(-20, 20, (500, 3)).astype(np.float32)
    raw = rng.uniform(0, 255, (500, 1)).astype(np.float32)
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(xyz)
    pc.point.intensity = o3d.core.Tensor(raw)
    path = tmp_path / "sweep.pcd"
    assert o3d.t.io.write_point_cloud(str(path), pc, write_ascii=ascii, compressed=compressed)
    assert (b"binary_compressed" in path.read_bytes()[:400]) == compressed
    s = load_scan(path)
    np.testing.assert_allclose(s.xyz, xyz, atol=1e-4)
    np.testing.assert_allclose(s.intensity, normalise_intensity(raw), atol=1e-4)


def test_intensity_already_in_unit_range_is_kept():
    v = np.array([0.0, 0.25, 1.0], np.float32)
    np.testing.assert_array_equal(normalise_intensity(v), v)
    assert normalise_intensity(np.array([0, 100, 10_000], np.float32)).max() == 1.0  # a retro-reflector clips


def test_broken_pcd_files(tmp_path):
    (tmp_path / "junk.pcd").write_bytes(b"hello\nworld\n")
    with pytest.raises(InputError, match="not a PCD file"):
        load_scan(tmp_path / "junk.pcd")
    header = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 100\nHEIGHT 1\nPOINTS 100\nDATA binary\n"
    (tmp_path / "short.pcd").write_bytes(header.encode() + np.zeros(30, np.float32).tobytes())  # 10 of 100 points
    with pytest.raises(InputError, match=r"declares 100 points of 12 bytes each \(SIZE x COUNT\) but the file cannot hold them"):
        load_scan(tmp_path / "short.pcd")
    # fuzz seed 23: a COUNT of 10^12 said only that the file cannot hold its points
    (tmp_path / "count.pcd").write_bytes(header.replace("COUNT 1 1 1", "COUNT 1 1000000000000 1").encode()
                                         + np.zeros(300, np.float32).tobytes())
    with pytest.raises(InputError, match=r"declares 100 points of 4,000,000,000,008 bytes each \(SIZE x COUNT\)"):
        load_scan(tmp_path / "count.pcd")
    (tmp_path / "noxyz.pcd").write_text(header.replace("FIELDS x y z", "FIELDS a b c"))
    with pytest.raises(InputError, match="no x y z"):
        load_scan(tmp_path / "noxyz.pcd")
    ascii_header = header.replace("DATA binary", "DATA ascii").replace("100", "2")
    (tmp_path / "word.pcd").write_text(ascii_header + "1 2 3\n1 2 x\n")  # Open3D reads the word as 0
    with pytest.raises(InputError, match="line 2: 'x'"):
        load_scan(tmp_path / "word.pcd")
    (tmp_path / "row.pcd").write_text(ascii_header + "1 2 3\n1 2\n")  # Open3D fills it from uninitialised memory
    with pytest.raises(InputError, match="5 numbers where the header declares 6"):
        load_scan(tmp_path / "row.pcd")
    (tmp_path / "width.pcd").write_text(ascii_header.replace("WIDTH 2", "WIDTH -5") + "1 2 3\n4 5 6\n")
    with pytest.raises(InputError, match="WIDTH x HEIGHT"):
        load_scan(tmp_path / "width.pcd")
    # fuzz seed 19: said "POINTS must be 0 or more, SIZE 1, 2, 4 or 8 and COUNT 1 or more" of any one
    for old, new, said in (("SIZE 4 4 4", "SIZE 4 99999999999999999999 4", "SIZE must be 1, 2, 4 or 8, got 99999999999999999999"),
                           ("COUNT 1 1 1", "COUNT 1 1 0", "COUNT must be 1 or more, got 0"),
                           ("SIZE 4 4 4", "SIZE 4 4", r"FIELDS, SIZE, TYPE and COUNT differ in length \(FIELDS 3, SIZE 2, TYPE 3, COUNT 3\)")):
        (tmp_path / "field.pcd").write_text(ascii_header.replace(old, new) + "1 2 3\n4 5 6\n")
        with pytest.raises(InputError, match=f"PCD header: {said}$"):
            load_scan(tmp_path / "field.pcd")
    (tmp_path / "nan.pcd").write_text(ascii_header + "1 2 3\nnan nan nan\n")  # PCL's 'no return'
    assert len(load_scan(tmp_path / "nan.pcd")) == 1
    with_i = ascii_header.replace("x y z", "x y z intensity").replace("4 4 4", "4 4 4 4").replace("F F F", "F F F F")
    with_i = with_i.replace("COUNT 1 1 1", "COUNT 1 1 1 1")
    (tmp_path / "no_return.pcd").write_text(with_i + "1 2 3 40\nnan nan nan nan\n")
    assert load_scan(tmp_path / "no_return.pcd").intensity.tolist() == [1.0]
    for value in ("nan", "inf"):  # a return with a broken intensity is named, not read as 0 or 1
        (tmp_path / f"i_{value}.pcd").write_text(with_i + f"1 2 3 40\n4 5 6 {value}\n")
        with pytest.raises(InputError, match=f"point 1 has an invalid intensity \\(\\[?{value}"):
            load_scan(tmp_path / f"i_{value}.pcd")
    # fuzz seed 32: a VIEWPOINT 1e30 m up was read, and export-depth called 7.6% of a sweep's view
    # seen from behind, every surface turned to face it
    (tmp_path / "view.pcd").write_text(ascii_header.replace("POINTS", "VIEWPOINT 0 0 1e30 1 0 0 0\nPOINTS") + "1 2 3\n4 5 6\n")
    with pytest.raises(InputError, match=r"scanner position 0 is \[0.0, 0.0, 1e\+30\], beyond 1e\+07 m"):
        load_scan(tmp_path / "view.pcd")
    (tmp_path / "view.pcd").write_text(ascii_header.replace("POINTS", "VIEWPOINT 0 0 1e6 1 0 0 0\nPOINTS") + "1 2 3\n4 5 6\n")
    assert load_scan(tmp_path / "view.pcd").origins.tolist() == [[0, 0, 1e6]]
    (tmp_path / "view.pcd").write_text(ascii_header.replace("POINTS", "VIEWPOINT 0 0 0 1 0 inf 0\nPOINTS") + "1 2 3\n4 5 6\n")
    with pytest.raises(InputError, match=r"VIEWPOINT must be 7 finite numbers \(tx ty tz qw qx qy qz\), got '0 0 0 1 0 inf 0'"):
        load_scan(tmp_path / "view.pcd")
    assert_one_line_error(run_cli("ingest", tmp_path / "short.pcd", "-o", tmp_path / "out.ply"), "short.pcd")
    assert not (tmp_path / "out.ply").exists()


def write_pcd(path, fields: list[tuple[str, str, int]], values: dict[str, np.ndarray], data: str) -> None:
    """A PCD file as PCL lays it out: fields (name, numpy type, COUNT) in order, each name's values
    (N,) or (N, COUNT) (names not given, such as the padding `_`, are zeros); `binary_compressed`
    as an LZF stream of literal runs (valid LZF, which any reader decodes)."""
    n = len(next(iter(values.values())))
    dtype = np.dtype([(f"f{i}", t, (c,) if c > 1 else ()) for i, (_, t, c) in enumerate(fields)])
    rec = np.zeros(n, dtype)
    for i, (name, _, _) in enumerate(fields):
        if name in values:
            rec[f"f{i}"] = values[name]
    kinds = {"f": "F", "u": "U", "i": "I"}
    header = (f"VERSION 0.7\nFIELDS {' '.join(f[0] for f in fields)}\n"
              f"SIZE {' '.join(str(np.dtype(f[1]).itemsize) for f in fields)}\n"
              f"TYPE {' '.join(kinds[np.dtype(f[1]).kind] for f in fields)}\nCOUNT {' '.join(str(f[2]) for f in fields)}\n"
              f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\nDATA {data}\n").encode()
    if data == "ascii":
        rows = [" ".join(" ".join(repr(v.item()) for v in np.ravel(r[k])) for k in dtype.names) for r in rec]
        body = ("\n".join(rows) + "\n").encode()
    elif data == "binary":
        body = rec.tobytes()
    else:  # one field after another, then LZF: a literal run is a length byte (L - 1) and L bytes
        raw = b"".join(np.ascontiguousarray(rec[k]).tobytes() for k in dtype.names)
        body = np.array([len(raw) + (len(raw) + 31) // 32, len(raw)], "<u4").tobytes()
        body += b"".join(bytes([len(raw[i:i + 32]) - 1]) + raw[i:i + 32] for i in range(0, len(raw), 32))
    path.write_bytes(header + body)


@pytest.mark.parametrize("data", ["ascii", "binary", "binary_compressed"])
def test_padding_and_field_names_that_open3d_cannot_take(tmp_path, data, monkeypatch):
    """PCL writes each run of padding bytes as a field `_`, so that files from Ouster's and
    Velodyne's drivers and PCL's own point types name `_` several times; Open3D's reader aborts
    the process on that (a repeated name of COUNT > 1), on part of a normal, on a field named
    `colors`, and reads a field named `positions` as the points. Each reads right here."""
    import tempfile

    (tmp_path / "tmp").mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))  # where the renamed copy goes
    rng = np.random.default_rng(3)
    n = 40
    xyz = rng.uniform(-30, 30, (n, 3)).astype(np.float32)
    raw = rng.integers(0, 255, n).astype(np.float32)
    ring = rng.integers(0, 64, n).astype(np.uint16)
    rgb = rng.integers(0, 256, (n, 3))
    packed = (rgb[:, 0] << 16 | rgb[:, 1] << 8 | rgb[:, 2]).astype(np.uint32)
    values = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "intensity": raw, "ring": ring, "rgb": packed.view(np.float32),
              "normal_x": np.ones(n), "colors": np.ones((n, 3)), "positions": np.ones((n, 3))}
    xyz_f = [("x", "<f4", 1), ("y", "<f4", 1), ("z", "<f4", 1)]
    layouts = {  # name: (fields, what the scan must hold)
        "ouster": (xyz_f + [("_", "u1", 4), ("intensity", "<f4", 1), ("t", "<u4", 1), ("reflectivity", "<u2", 1),
                            ("ring", "<u2", 1), ("ambient", "<u2", 1), ("_", "u1", 2), ("range", "<u4", 1), ("_", "u1", 12)],
                   {"intensity", "ring"}),
        "pcl_xyzrgb": (xyz_f + [("_", "u1", 4), ("rgb", "<f4", 1), ("_", "u1", 12)], {"rgb"}),
        "normal_x_alone": (xyz_f + [("normal_x", "<f4", 1), ("intensity", "<f4", 1)], {"intensity"}),
        "colors": (xyz_f + [("colors", "<f4", 3), ("intensity", "<f4", 1)], {"intensity"}),
        "positions": (xyz_f + [("positions", "<f4", 3)], set()),
    }
    for name, (fields, holds) in layouts.items():
        path = tmp_path / f"{name}.pcd"
        write_pcd(path, fields, values, data)
        scan = load_scan(path)
        np.testing.assert_array_equal(scan.xyz, xyz.astype(np.float64), err_msg=name)
        if "intensity" in holds:
            np.testing.assert_allclose(scan.intensity, normalise_intensity(raw), atol=1e-6, err_msg=name)
        if "ring" in holds:
            np.testing.assert_array_equal(np.unique(scan.ring, return_inverse=True)[1], np.unique(ring, return_inverse=True)[1])
        if "rgb" in holds:
            np.testing.assert_array_equal(scan.rgb, rgb, err_msg=name)
        assert not list((tmp_path / "tmp").iterdir()), "the renamed copy is removed"
    write_pcd(tmp_path / "mixed.pcd", [("x", "<f4", 1), ("y", "<f8", 1), ("z", "<f4", 1)], values, data)
    with pytest.raises(InputError, match="x, y and z differ in SIZE, TYPE or COUNT"):
        load_scan(tmp_path / "mixed.pcd")


def test_extra_fields_and_colors_are_read(tmp_path):
    """Fields as LiDAR drivers write them (ring uint16, timestamp float64) beside x y z, and colors."""
    import open3d as o3d

    rng = np.random.default_rng(1)
    xyz = rng.uniform(-20, 20, (300, 3)).astype(np.float32)
    pc = o3d.t.geometry.PointCloud()
    pc.point.positions = o3d.core.Tensor(xyz)
    pc.point.reflectivity = o3d.core.Tensor(rng.uniform(0, 65535, (300, 1)).astype(np.float32))
    pc.point.ring = o3d.core.Tensor(rng.integers(0, 64, (300, 1)).astype(np.uint16))
    pc.point.timestamp = o3d.core.Tensor(1.6e9 + rng.uniform(0, 0.1, (300, 1)))
    pc.point.colors = o3d.core.Tensor(rng.uniform(0, 1, (300, 3)).astype(np.float32))
    path = tmp_path / "driver.pcd"
    assert o3d.t.io.write_point_cloud(str(path), pc, compressed=True)
    s = load_scan(path)
    np.testing.assert_allclose(s.xyz, xyz, atol=1e-4)
    assert s.rgb is not None and s.rgb.dtype == np.uint8 and s.intensity is not None
    assert 0 <= s.intensity.min() and s.intensity.max() <= 1 and np.median(s.intensity) > 0.3
    np.testing.assert_array_equal(s.ring, np.asarray(pc.point.ring.numpy()).ravel())


def test_a_sweep_in_a_vehicle_frame_is_still_a_sweep(tmp_path):
    """A real sweep moved into a vehicle's frame (sensor 1.8 m up, 1.5 m forward, pitched 2 deg):
    its rings no longer lie on cones about the frame's z axis, but its ring field says what it
    is, through PLY (ingest) and the prepared cache too; without the field, its scan lines do."""
    import cv2

    from rgbd_gt.io import save_scan
    from rgbd_gt.prepared import prepare_scan
    from rgbd_gt.render.points import is_sweep

    folder = DATA / "lidar_camera"
    if not folder.exists():
        pytest.skip(f"real test data not found at {folder}")
    s = load_scan(folder / "pjlab_1" / "calib.pcd")
    assert is_sweep(s)
    s.xyz = s.xyz @ cv2.Rodrigues(np.radians([0.0, 2.0, 0.0]))[0].T + [1.5, 0.0, 1.8]
    assert is_sweep(s)
    save_scan(tmp_path / "vehicle.ply", s)
    again = load_scan(tmp_path / "vehicle.ply")
    np.testing.assert_array_equal(again.ring, s.ring)
    assert is_sweep(again) and is_sweep(prepare_scan(tmp_path / "vehicle.ply", tmp_path / "cache").whole())
    s.ring = None
    assert is_sweep(s)  # without the field, by its scan lines (in any frame)


def test_kitti_velodyne_bin(tmp_path):
    """KITTI's headerless .bin sweeps: x y z reflectance as float32; whatever the format cannot
    be is one clean error (a cut return, non-finite values, another layout's numbers)."""
    from rgbd_gt.render.points import is_sweep

    rng = np.random.default_rng(2)
    folder = DATA / "lidar_camera"
    if folder.exists():  # a real sweep in KITTI's layout
        real = load_scan(folder / "pjlab_3" / "calib.pcd")
        xyzi = np.hstack([real.xyz, real.intensity[:, None]]).astype("<f4")
    else:
        xyzi = np.hstack([rng.uniform(-50, 50, (3000, 3)), rng.uniform(0, 1, (3000, 1))]).astype("<f4")
    xyzi.tofile(tmp_path / "000000.bin")
    s = load_scan(tmp_path / "000000.bin")
    np.testing.assert_array_equal(s.xyz, xyzi[:, :3].astype(np.float64))
    np.testing.assert_array_equal(s.intensity, xyzi[:, 3])
    assert np.array_equal(s.origins, [[0, 0, 0]]) and s.fields == ["xyz", "intensity"]
    if folder.exists():
        assert is_sweep(s)  # in the sensor's frame, as KITTI ships them
    bad = {"cut.bin": xyzi.tobytes()[:-6], "nan.bin": np.vstack([xyzi, [[np.nan, 0, 0, 0.5]]]).astype("<f4").tobytes(),
           "nuscenes.bin": np.hstack([xyzi[:400, :3], 255 * xyzi[:400, 3:], rng.integers(0, 32, (400, 1))]).astype("<f4").tobytes(),
           "far.bin": np.array([[1e6, 0, 0, 0.5]] * 4, "<f4").tobytes()}
    for name, data in bad.items():
        (tmp_path / name).write_bytes(data)
    for name, needle in (("cut.bin", "whole number of KITTI returns"), ("nan.bin", "non-finite"),
                         ("nuscenes.bin", "not a KITTI .bin sweep"), ("far.bin", "beyond 1000 m")):
        with pytest.raises(InputError, match=needle):
            load_scan(tmp_path / name)
    assert_one_line_error(run_cli("ingest", tmp_path / "cut.bin", "-o", tmp_path / "out.ply"), "cut.bin", "KITTI")
    with pytest.raises(InputError, match="E57 files only"):
        load_scan(tmp_path / "000000.bin", scan_index=0)
