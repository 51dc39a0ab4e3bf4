import numpy as np
import pytest

from rgbd_gt.errors import InputError
from rgbd_gt.io import read_pose, write_pose


def _rigid():
    a = 0.4
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [0.1, -2.0, 3.5]
    return T


def test_round_trip_keeps_other_keys(tmp_path):
    write_pose(tmp_path / "p.yaml", _rigid(), method="pnp", residuals={"rms_px": np.float64(0.25)}, iterations=12)
    T, meta = read_pose(tmp_path / "p.yaml")
    np.testing.assert_array_equal(T, _rigid())
    assert meta == {"method": "pnp", "residuals": {"rms_px": 0.25}, "iterations": 12}
    assert (tmp_path / "p.yaml").read_text().startswith("T_cam_from_scan:")


@pytest.mark.parametrize(
    "mutate,needle",
    [
        (lambda T: T * np.diag([1.01, 1, 1, 1]), "not rigid"),
        (lambda T: T @ np.diag([1, 1, -1, 1]), "reflection"),
        (lambda T: np.vstack([T[:3], [0, 0, 1, 1]]), "last row"),
        (lambda T: T[:3], "4x4"),
    ],
)
def test_rejects_non_rigid(tmp_path, mutate, needle):
    import yaml

    bad = mutate(_rigid())
    (tmp_path / "p.yaml").write_text(yaml.safe_dump({"T_cam_from_scan": bad.tolist()}))
    with pytest.raises(InputError, match=needle) as info:
        read_pose(tmp_path / "p.yaml")
    assert "p.yaml" in str(info.value)
    with pytest.raises(InputError):
        write_pose(tmp_path / "q.yaml", bad)
    assert not (tmp_path / "q.yaml").exists()


def test_missing_key_and_file(tmp_path):
    (tmp_path / "p.yaml").write_text("pose: [1, 2]\n")
    with pytest.raises(InputError, match="no 'T_cam_from_scan'"):
        read_pose(tmp_path / "p.yaml")
    with pytest.raises(InputError, match="not found"):
        read_pose(tmp_path / "none.yaml")


def test_update_of_and_through():
    """update_of inverts apply_update at the identity; update_through carries an update of B to
    the update of A @ B (to first order)."""
    from rgbd_gt.pose import apply_update, update_of, update_through

    rng = np.random.default_rng(3)
    d = np.r_[rng.normal(0, 0.3, 3), rng.normal(0, 0.5, 3)]
    np.testing.assert_allclose(update_of(apply_update(np.eye(4), d)), d, atol=1e-12)
    A, B = apply_update(np.eye(4), rng.normal(0, 0.5, 6)), apply_update(np.eye(4), rng.normal(0, 0.5, 6))
    small = 1e-6 * rng.normal(size=6)
    moved = A @ apply_update(B, small) @ np.linalg.inv(A @ B)
    np.testing.assert_allclose(update_of(moved), update_through(A) @ small, atol=1e-11)
