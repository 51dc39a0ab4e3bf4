"""The one boundary: inputs found wrong only deep inside a step end as one `error:` line naming
the file, exit 2, as every other bad input does."""

import struct
import zlib

import numpy as np
import pytest
import yaml

from conftest import assert_one_line_error, run_cli
from rgbd_gt.io import read_pose, write_pose


@pytest.fixture(scope="module")
def scene(tmp_path_factory, synth_scene):
    return synth_scene(tmp_path_factory.mktemp("boundaries") / "scene", 3)


def png_header_only(path, width: int, height: int) -> None:
    """A PNG whose header declares width x height RGB pixels and whose data holds almost none."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 100)) + chunk(b"IEND", b""))


@pytest.mark.parametrize("side", [100_000, 25_000])  # past Pillow's refusal, and past only its warning
def test_an_image_header_of_too_many_pixels(scene, tmp_path, side):
    png_header_only(tmp_path / "bomb.png", side, side)
    proc = run_cli("refine", "--scan", scene / "scan.e57", "--image", tmp_path / "bomb.png", "--camera",
                   scene / "camera.yaml", "--init", scene / "init_pose.yaml", "-o", tmp_path / "pose.yaml")
    assert_one_line_error(proc, str(tmp_path / "bomb.png"), "image header claims")


def test_qa_with_a_before_pose_that_sees_nothing(scene, tmp_path):
    T, _ = read_pose(scene / "init_pose.yaml")
    away = np.diag([-1.0, 1.0, -1.0, 1.0]) @ T  # turned about the camera's y axis: looking the other way
    away[:3, 3] += [0, 0, -1e3]  # and a kilometre back: nothing of the room in front of it
    write_pose(tmp_path / "away.yaml", away)
    proc = run_cli("qa-edges", "--scan", scene / "scan.e57", "--image", scene / "photo.png", "--camera",
                   scene / "camera.yaml", "--pose", scene / "gt_pose.yaml", "--before", tmp_path / "away.yaml",
                   "-o", tmp_path / "qa.png")
    assert_one_line_error(proc, str(tmp_path / "away.yaml"), "no scan edges in view")
    assert not (tmp_path / "qa.png").exists()


@pytest.mark.parametrize("body, problem", [
    ("element vertex 0\nproperty float x\nproperty float y\nproperty float z\nend_header\n", "no points"),
    ("element vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n0 0 0\nnan 1 2\n", "nan"),
])
def test_run_on_a_scan_it_cannot_read_is_one_error(scene, tmp_path, body, problem):
    (tmp_path / "bad.ply").write_text("ply\nformat ascii 1.0\n" + body)
    config = {"scan": str(tmp_path / "bad.ply"), "camera": str(scene / "camera.yaml"),
              "photos": [str(scene / "photo.png")], "output": str(tmp_path / "out")}
    (tmp_path / "run.yaml").write_text(yaml.safe_dump(config))
    proc = run_cli("run", tmp_path / "run.yaml")
    assert_one_line_error(proc, str(tmp_path / "bad.ply"), problem)
    assert not (tmp_path / "out" / "summary.csv").exists()
