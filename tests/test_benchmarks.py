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
