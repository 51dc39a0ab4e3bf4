"""A short seeded fuzz of every command (benchmarks/fuzz.py; `make bench` runs a long one):
mutated real and synthetic inputs, odd arguments and output paths. Every trial must end with
exit 0 or 2, no traceback, nothing half-written, no input changed, and exit 2 (never 0) for
input that is certainly invalid."""

import json
import os
import subprocess
import sys

import pytest

from conftest import DATA, ROOT

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="the fuzz runs each trial in a forked child")


def test_fuzz_every_command(tmp_path):
    # a fresh process: the forked trials must not inherit thread pools this one has started;
    # 80 trials of seed 7 reach every command and kind below (`make bench` and the seeds of each
    # session's note run 600 a seed)
    report = tmp_path / "trials.json"
    proc = subprocess.run([sys.executable, "-m", "benchmarks.fuzz", "--trials", "80", "--seed", "7", "--quiet",
                           "--root", str(tmp_path / "fuzz"), "--data", str(DATA), "--json", str(report)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-3000:]
    trials = json.loads(report.read_text())
    failures = [f"{t['problems']} exit {t['code']}: {t['name']}\n{t['stderr'][-600:]}" for t in trials if t["problems"]]
    assert not failures, "\n\n".join(failures)
    # the run covered every command, certainly invalid input and valid runs
    commands = {t["argv"][0] for t in trials if not t["name"].startswith("command ")}
    assert {"ingest", "init-pose", "refine", "export-depth", "qa-edges", "overlay", "pick", "export"} <= commands
    assert sum(t["invalid"] for t in trials) > 30
    assert sum(t["code"] == 0 for t in trials) > 10
    assert any(t["code"] == 2 and "Usage:" in t["stderr"] for t in trials)  # argument errors: click's usage message
    kinds = {t["kind"].split(":")[0] for t in trials}
    assert {"file", "argument", "output path"} <= kinds
