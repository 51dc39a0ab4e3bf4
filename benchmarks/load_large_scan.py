"""Benchmark: load a FARO-sized structured scan (default 40 million points) from E57 and PLY.

Writes a synthetic scan with colors, intensity and a row/column grid once (cached in
bench_out/), then measures load time and peak resident memory of `load_scan` in a fresh
process, relative to the size of the loaded arrays ("copies").

    python -m benchmarks.load_large_scan [--points 40000000]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from rgbd_gt.io import save_scan

from rgbd_gt.scan import Scan
from rgbd_gt.io.e57 import write_e57

MEASURE = r"""
import json, sys, time
from rgbd_gt.io import load_scan
def hwm_kb():  # VmHWM restarts at exec; ru_maxrss would carry the parent's peak over
    return int(open("/proc/self/status").read().split("VmHWM:")[1].split()[0])
base = hwm_kb()
t = time.perf_counter()
s = load_scan(sys.argv[1])
dt = time.perf_counter() - t
peak = hwm_kb()
size = sum(getattr(s, f).nbytes for f in s.fields)
print(json.dumps({"points": len(s), "seconds": dt, "data_mb": size / 1e6, "peak_extra_mb": (peak - base) / 1e3}))
"""


def make_scan(n: int) -> Scan:
    cols = 10240
    rows = -(-n // cols)
    idx = np.arange(n)
    row, col = (idx // cols).astype(np.int32), (idx % cols).astype(np.int32)
    az = col * (2 * np.pi / cols)
    el = (row / rows - 0.5) * np.pi * 0.8
    r = 3.0 + np.sin(az * 7) * np.cos(el * 5)
    xyz = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    rgb = (np.stack([np.sin(az * 13), np.cos(el * 11), np.sin(az + el)], 1) * 127 + 128).astype(np.uint8)
    return Scan(xyz=xyz, rgb=rgb, intensity=((r - 2) / 2).astype(np.float32), row=row, col=col,
                origins=np.zeros((1, 3)))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=int, default=40_000_000)
    ap.add_argument("--dir", type=Path, default=Path("bench_out"))
    args = ap.parse_args(argv)
    args.dir.mkdir(exist_ok=True)
    paths = [args.dir / f"large_{args.points}.e57", args.dir / f"large_{args.points}.ply"]
    if not all(p.exists() for p in paths):
        t = time.perf_counter()
        scan = make_scan(args.points)
        write_e57(paths[0], [scan])
        save_scan(paths[1], scan)
        print(f"wrote test scans in {time.perf_counter() - t:.1f} s", file=sys.stderr)
        del scan
    for p in paths:
        res = json.loads(subprocess.run([sys.executable, "-c", MEASURE, str(p)], check=True, capture_output=True, text=True).stdout)
        print(f"{p.suffix[1:].upper():4s} {res['points']:,} points: {res['seconds']:.1f} s, "
              f"{res['data_mb']:.0f} MB of arrays, peak +{res['peak_extra_mb']:.0f} MB "
              f"({res['peak_extra_mb'] / res['data_mb']:.2f} copies)")


if __name__ == "__main__":
    main()
