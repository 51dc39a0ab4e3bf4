import numpy as np
import pytest

from conftest import assert_one_line_error, run_cli
from rgbd_gt.errors import InputError
from rgbd_gt.io import load_scan
from rgbd_gt.scan import Scan
from rgbd_gt.io.e57 import list_e57_images, read_e57, read_e57_images, write_e57


def _rotz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def test_pumpa_grid_colors_intensity(e57_dir):
    scan = load_scan(e57_dir / "pumpA.e57")
    assert len(scan) == 155_201
    assert scan.fields == ["xyz", "rgb", "intensity", "row", "col", "scan_id"]
    assert scan.xyz.dtype == np.float64 and scan.rgb.dtype == np.uint8 and scan.intensity.dtype == np.float32
    assert (scan.row.min(), scan.row.max(), scan.col.min(), scan.col.max()) == (0, 1073, 0, 344)
    assert len(np.unique(scan.row.astype(np.int64) * 345 + scan.col)) == 155_201  # every grid cell once
    assert 0.0 <= scan.intensity.min() and scan.intensity.max() <= 1.0
    assert scan.rgb.std() > 10  # real colors, not a constant
    np.testing.assert_allclose(scan.origins, [[0, 0, 0]])
    # within the file's declared cartesian bounds
    assert np.all(scan.xyz.min(0) >= [-2.904, -5.302, -1.9]) and np.all(scan.xyz.max(0) <= [1.722, -0.792, 1.844])


def test_pumpa_embedded_photo(e57_dir):
    import cv2

    (img, data), = read_e57_images(e57_dir / "pumpA.e57")
    assert img.kind == "visualReference" and img.format == "jpeg" and (img.width, img.height) == (3072, 2304)
    decoded = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    assert decoded.shape == (2304, 3072, 3)


def test_bunny_double_and_scaled_int_agree(e57_dir):
    a = load_scan(e57_dir / "bunnyDouble.e57")
    b = load_scan(e57_dir / "bunnyInt32.e57")
    assert len(a) == len(b) == 30_571
    assert np.abs(a.xyz - b.xyz).max() <= 1e-6 + 1e-12  # the integer file's scale is 1e-6 m


def test_coloured_cube_colors(e57_dir):
    scan = load_scan(e57_dir / "ColouredCubeFloat.e57")
    assert len(scan) == 7_680 and scan.rgb is not None
    assert {tuple(c) for c in np.unique(scan.rgb, axis=0)} >= {(255, 0, 0), (0, 255, 0), (0, 0, 255)}


def test_pipe_file_matches_direct_read(e57_dir):
    """pipeSpherical.e57 (as shipped) stores cartesian coordinates despite its name; its points
    must equal libE57's own values, and its intensity follows the declared limits."""
    import pye57

    scan = load_scan(e57_dir / "pipeSpherical.e57")
    raw = pye57.E57(str(e57_dir / "pipeSpherical.e57")).read_scan_raw(0)
    direct = np.stack([raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]], 1)
    np.testing.assert_allclose(scan.xyz, direct, atol=1e-12)
    lo, hi = 0.39350566267967224, 0.5554978847503662
    np.testing.assert_allclose(scan.intensity, (raw["intensity"] - lo) / (hi - lo), atol=1e-5)


def test_spherical_coordinates_convert_like_direct_computation(tmp_path):
    rng = np.random.default_rng(1)
    r = rng.uniform(0.5, 20, 500)
    az = rng.uniform(-np.pi, np.pi, 500)
    el = rng.uniform(-1.2, 1.2, 500)
    direct = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    write_e57(tmp_path / "s.e57", [Scan(xyz=direct)], spherical=True)
    import pye57

    raw = pye57.E57(str(tmp_path / "s.e57")).read_scan_raw(0)
    assert "sphericalRange" in raw and "cartesianX" not in raw
    np.testing.assert_allclose(load_scan(tmp_path / "s.e57").xyz, direct, atol=1e-9)


def test_multiscan_merges_into_world_frame(tmp_path):
    rng = np.random.default_rng(2)
    scans, poses, expected = [], [], []
    for i in range(3):
        local = rng.normal(size=(200, 3)) * 4
        T = np.eye(4)
        T[:3, :3] = _rotz(0.7 * i + 0.1) @ _rotz(0.0)
        T[:3, 3] = [10.0 * i, -3.0 * i, 0.5]
        rgb = rng.integers(0, 256, (200, 3)).astype(np.uint8)
        row = np.repeat(np.arange(20), 10).astype(np.int32)
        col = np.tile(np.arange(10), 20).astype(np.int32)
        scans.append(Scan(xyz=local, rgb=rgb, intensity=rng.random(200).astype(np.float32), row=row, col=col))
        poses.append(T)
        expected.append(local @ T[:3, :3].T + T[:3, 3])
    write_e57(tmp_path / "multi.e57", scans, poses)
    merged = load_scan(tmp_path / "multi.e57")
    np.testing.assert_allclose(merged.xyz, np.concatenate(expected), atol=1e-9)
    np.testing.assert_allclose(merged.origins, [p[:3, 3] for p in poses], atol=1e-12)
    assert np.array_equal(np.bincount(merged.scan_id), [200, 200, 200])
    assert np.array_equal(merged.rgb, np.concatenate([s.rgb for s in scans]))
    one = load_scan(tmp_path / "multi.e57", scan_index=2)
    np.testing.assert_allclose(one.xyz, expected[2], atol=1e-9)
    with pytest.raises(InputError, match="out of range"):
        load_scan(tmp_path / "multi.e57", scan_index=3)


def test_invalid_points_are_dropped(tmp_path):
    import pye57

    xyz = np.arange(30, dtype=float).reshape(10, 3)
    state = np.array([0, 2, 0, 1, 0, 0, 2, 0, 0, 0], np.int8)
    inten = np.linspace(0, 1, 10)
    row, col = np.arange(10) // 5, np.arange(10) % 5
    with pye57.E57(str(tmp_path / "inv.e57"), mode="w") as e:
        e.write_scan_raw({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2], "cartesianInvalidState": state,
                          "intensity": inten, "rowIndex": row, "columnIndex": col})
    scan = load_scan(tmp_path / "inv.e57")
    keep = state == 0
    np.testing.assert_allclose(scan.xyz, xyz[keep])  # the arrays shrunk in place keep their first rows
    np.testing.assert_allclose(scan.intensity, inten[keep], atol=1e-6)
    assert scan.row.tolist() == row[keep].tolist() and scan.col.tolist() == col[keep].tolist()
    assert len(scan.scan_id) == keep.sum()


def test_image_listing_covers_every_representation(e57_dir):
    kinds = {im.name: im.kind for im in list_e57_images(e57_dir / "tiny_pc_and_images.e57")}
    assert kinds == {"visual": "visualReference", "spherical": "spherical", "pinhole": "pinhole", "cylindrical": "cylindrical"}
    sph = [im for im in list_e57_images(e57_dir / "tiny_pc_and_images.e57") if im.kind == "spherical"][0]
    np.testing.assert_allclose(sph.pose[:3, 3], [1, 2, 3])
    R = sph.pose[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)  # the file's quaternion is not unit


@pytest.mark.parametrize("name,needle", [("empty", "empty"), ("invalid", "cannot read E57"), ("justxml", "checksum")])
def test_bad_files_give_one_line_error(e57_dir, tmp_path, name, needle):
    bad = e57_dir / "bad" / f"{name}.e57"
    proc = run_cli("ingest", bad, "-o", tmp_path / "out.ply")
    assert_one_line_error(proc, str(bad), needle)
    assert not (tmp_path / "out.ply").exists()


def test_load_memory_stays_near_one_copy(tmp_path):
    """Chunked reading: the peak of numpy allocations stays within ~3 copies of the result."""
    import tracemalloc

    n = 1_500_000
    rng = np.random.default_rng(3)
    scan = Scan(
        xyz=rng.normal(size=(n, 3)), rgb=rng.integers(0, 256, (n, 3)).astype(np.uint8),
        intensity=rng.random(n).astype(np.float32), row=(np.arange(n) // 1000).astype(np.int32),
        col=(np.arange(n) % 1000).astype(np.int32),
    )
    write_e57(tmp_path / "big.e57", [scan])
    del scan
    tracemalloc.start()
    loaded = read_e57(tmp_path / "big.e57")
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    size = sum(getattr(loaded, f).nbytes for f in loaded.fields)
    assert len(loaded) == n
    assert peak < 3 * size, (peak / 1e6, size / 1e6)
