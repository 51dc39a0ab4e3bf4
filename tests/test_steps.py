"""One step, one content: each command and `run` call the same steps (rgbd_gt/steps.py), so the
files of one name that they write hold the same keys and values."""

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

from conftest import _made_once, run_cli
from rgbd_gt.io.depth_file import read_depth_exr

TIMINGS = ("seconds", "verify_seconds")  # how long a step took: the one thing two runs may differ in


def without_timings(value):
    """`value` (parsed YAML or JSON) without the keys that hold seconds."""
    if isinstance(value, dict):
        return {k: without_timings(v) for k, v in value.items() if k not in TIMINGS}
    if isinstance(value, list):
        return [without_timings(v) for v in value]
    return value


@pytest.fixture(scope="module")
def run_and_commands(tmp_path_factory, synth_scene):
    """A `run` of one synthetic photo, and each command on the same inputs (run's init and its
    prepared scan) writing the files of the same names into cmd/."""

    def make(tmp: Path) -> None:
        scene = synth_scene(tmp / "scene", 5)
        config = {"scan": "scene/scan.e57", "camera": "scene/camera.yaml", "photos": ["scene/photo.png"],
                  "output": "out", "refine": {"max_points": 30000}}
        (tmp / "run.yaml").write_text(yaml.safe_dump(config))
        proc = run_cli("run", tmp / "run.yaml")
        assert proc.returncode == 0, proc.stderr
        ran, cmd, cache = tmp / "out" / "photo", tmp / "cmd", tmp / "out" / ".scan-cache"
        common = ["--scan", scene / "scan.e57", "--cache", cache]
        photo = ["--image", scene / "photo.png", "--camera", scene / "camera.yaml"]
        for args in (["init-pose", *common, *photo, "-o", cmd / "init.yaml"],
                     ["refine", *common, *photo, "--init", ran / "init.yaml", "--max-points", 30000, "-o", cmd / "pose.yaml"],
                     ["export-depth", *common, "--camera", scene / "camera.yaml", "--pose", ran / "pose.yaml",
                      "-o", cmd / "depth.exr", "--png16", cmd / "depth.png"],
                     ["qa-edges", *common, *photo, "--pose", ran / "pose.yaml", "--before", ran / "init.yaml",
                      "-o", cmd / "qa.png", "--json", cmd / "qa.json"],
                     ["overlay", *common, *photo, "--pose", ran / "pose.yaml", "-o", cmd / "overlay.png"]):
            proc = run_cli(*args)
            assert proc.returncode == 0, (args[0], proc.stderr)

    tmp = _made_once(tmp_path_factory, "steps", make)
    return tmp / "out" / "photo", tmp / "cmd"


def test_init_files_are_the_same(run_and_commands):
    """init-pose records what run's init.yaml records: the board's pose and the SHA-1 of each input."""
    ran, cmd = run_and_commands
    a, b = (without_timings(yaml.safe_load((d / "init.yaml").read_text())) for d in (ran, cmd))
    assert "photo_sha1" in a and "scan_sha1" in a and "board_sha1" in a
    assert a == b


def test_pose_files_are_the_same(run_and_commands):
    ran, cmd = run_and_commands
    a, b = (without_timings(yaml.safe_load((d / "pose.yaml").read_text())) for d in (ran, cmd))
    assert a.keys() == b.keys()
    assert "verticals_roll_deg" in a and "init_verticals_roll_deg" in a  # refine's verticals check, in run's too
    assert a == b


def test_qa_files_are_the_same(run_and_commands):
    ran, cmd = run_and_commands
    a, b = (json.loads((d / "qa.json").read_text()) for d in (ran, cmd))
    for prefix in ("", "before_"):  # structural, Canny and verticals, for the pose and its init
        assert {f"{prefix}edge_ratio", f"{prefix}mean_distance_px", f"{prefix}verticals_roll_deg"} <= a.keys()
    assert a == b
    np.testing.assert_array_equal(cv2.imread(str(ran / "qa.png")), cv2.imread(str(cmd / "qa.png")))


def test_depth_files_are_the_same(run_and_commands):
    ran, cmd = run_and_commands
    (za, ha), (zb, hb) = read_depth_exr(ran / "depth.exr"), read_depth_exr(cmd / "depth.exr")
    assert "rgbd_gt_seen_from_behind" in ha
    keys = sorted(k for k in ha if k.startswith("rgbd_gt_"))
    assert keys == sorted(k for k in hb if k.startswith("rgbd_gt_"))
    for k in keys:
        np.testing.assert_array_equal(np.asarray(ha[k]), np.asarray(hb[k]), err_msg=k)
    np.testing.assert_array_equal(za, zb)
    np.testing.assert_array_equal(cv2.imread(str(ran / "depth.png"), cv2.IMREAD_UNCHANGED),
                                  cv2.imread(str(cmd / "depth.png"), cv2.IMREAD_UNCHANGED))


@pytest.mark.parametrize("name", ["overlay.png", "overlay_blend.png"])
def test_overlays_are_the_same(run_and_commands, name):
    ran, cmd = run_and_commands
    np.testing.assert_array_equal(cv2.imread(str(ran / name)), cv2.imread(str(cmd / name)))


def test_a_nan_on_its_way_to_an_output_is_an_error_of_its_step():
    from rgbd_gt.errors import InputError
    from rgbd_gt.steps import finite

    finite("depth", "the depth map", np.zeros((4, 4)))
    with pytest.raises(InputError, match=r"^depth: the depth map holds 2 NaN or inf value\(s\)"):
        finite("depth", "the depth map", np.array([[0.0, np.nan], [np.inf, 1.0]]))
