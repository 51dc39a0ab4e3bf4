"""The benchmarks' one entry point (python -m benchmarks, which make bench runs) knows every
benchmark, and each can be run on its own as the documents say (python -m benchmarks.MODULE)."""

import subprocess
import sys

import pytest

from conftest import ROOT
from benchmarks.__main__ import BENCHMARKS


def run(*args):
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, cwd=ROOT, timeout=120)


def test_the_entry_point_lists_every_benchmark_and_refuses_unknown_ones():
    proc = run("benchmarks", "--help")
    assert proc.returncode == 0 and all(name in proc.stdout for name in BENCHMARKS)
    proc = run("benchmarks", "no-such-benchmark")
    assert proc.returncode == 2 and "unknown benchmark" in proc.stderr


@pytest.mark.parametrize("module", sorted({m for m, _, _ in BENCHMARKS.values()} | {"gpu"}))
def test_each_benchmark_runs_on_its_own(module):
    proc = run(f"benchmarks.{module}", "--help")
    assert proc.returncode == 0 and proc.stdout.startswith("usage:"), proc.stderr[-1000:]


@pytest.mark.parametrize("doc", ["trust", "lidar"])
def test_a_generated_document_ends_with_its_method_text_as_written(doc):
    """docs/trust.md and docs/lidar.md are made by their benchmarks, which append
    docs/<doc>-method.md: what is said about the method is edited there, or the next `make bench`
    drops it."""
    generated, method = (ROOT / "docs" / f"{doc}.md").read_text(), (ROOT / "docs" / f"{doc}-method.md").read_text()
    assert generated.rstrip().endswith(method.rstrip())


def test_the_lidar_page_keeps_the_rows_it_has_no_records_for(tmp_path):
    """bench_out/ is not kept: a --drives-only run on a fresh machine rewrites the drives' section
    and keeps the PJLab table and the picked pairs as the page shows them."""
    import json
    import shutil

    for name in ("lidar.md", "lidar-method.md"):
        shutil.copy(ROOT / "docs" / name, tmp_path / name)
    before = (tmp_path / "lidar.md").read_text()
    work = tmp_path / "work"
    assert run("benchmarks.lidar", "--rewrite", "--out", tmp_path, "--work", work).returncode == 0
    assert (tmp_path / "lidar.md").read_text() == before  # no records at all: the page as it was
    work.mkdir()
    (work / "drives.json").write_text(json.dumps([
        {"drive": "kitti_00", "solve": "joint, 19 frames", "size": "1 deg / 10 cm", "init": i, "machine": "a test",
         "deg": 0.1, "cm": 2.0, "verdict": "ok", "seconds": 38.0, "frames": ["f"] * 19, "verify_seconds": 5.0,
         "reasons": []} for i in range(3)]))
    assert run("benchmarks.lidar", "--rewrite", "--out", tmp_path, "--work", work).returncode == 0
    after = (tmp_path / "lidar.md").read_text()
    drives = before.index("## KITTI and Waymo"), after.index("## KITTI and Waymo")
    picks = before.index("## Picked pairs"), after.index("## Picked pairs")
    assert after[:drives[1]] == before[:drives[0]]  # the PJLab table
    assert after[picks[1]:] == before[picks[0]:]  # the picked pairs and the method
    section = after[drives[1]:picks[1]]
    assert "| kitti_00 | joint, 19 frames | 1 deg / 10 cm | 3/3 |" in section and "Machine: a test." in section
    assert "| waymo |" not in section
