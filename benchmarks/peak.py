"""Wall time and peak resident memory of one `rgbd-gt` command in a child process.

The peak is the child's own high-water mark (VmHWM), written by the child as it exits. Not
getrusage's ru_maxrss: Linux carries into a child's ru_maxrss the resident memory its parent
held when it forked, so a benchmark that has just made a 40-million-point scene would report
that scene as every command's peak.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = r"""
import atexit, runpy, sys
report = sys.argv.pop(1)


def peak():
    status = open("/proc/self/status").read()
    open(report, "w").write(status.split("VmHWM:")[1].split()[0])


atexit.register(peak)
runpy.run_module("rgbd_gt", run_name="__main__", alter_sys=True)
"""


def run_measured(args: list[str]) -> tuple[float, float]:
    """(wall seconds, peak resident GB of the command's own process; workers it starts are not
    counted) of `rgbd-gt args`. Raises SystemExit with the command's stderr when it fails."""
    with tempfile.TemporaryDirectory() as tmp:
        report = Path(tmp) / "peak"
        start = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", CHILD, str(report), *args], stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, text=True)
        wall = time.perf_counter() - start
        if proc.returncode != 0:
            raise SystemExit(f"rgbd-gt {' '.join(args)} failed: {proc.stderr}")
        return wall, int(report.read_text()) * 1024 / 1e9  # kB (KiB) -> GB
