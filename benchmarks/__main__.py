"""The one entry point of the benchmarks: `python -m benchmarks [NAME ...] [--out DIR] [--data DIR]`
from the repository's root (`make bench` runs them all into docs/). Each writes its document into
--out and its work files under bench_out/; each is also `python -m benchmarks.MODULE --help` for
its own options."""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path

# name: (module, what it measures, its arguments given the output folder and the data folder)
BENCHMARKS = {
    "icl": ("icl_bench", "the paper's ICL-NUIM experiment, every method: benchmark.md",
            lambda out, data: ["--out", out, "--data", data / "icl_nuim_livingroom1"]),
    "depth": ("export_depth", "export-depth against ICL-NUIM's true depth: depth_benchmark.md",
              lambda out, data: ["--out", out / "depth_benchmark.md", "--data", data / "icl_nuim_livingroom1", "--e57", data / "e57"]),
    "init": ("init_pose", "init-pose on synthetic scenes: init_benchmark.md",
             lambda out, data: ["--out", out / "init_benchmark.md"]),
    "load": ("load_large_scan", "reading a 40-million-point scan (printed)", lambda out, data: []),
    "trust": ("trust", "the verdict on a labelled set: trust.md", lambda out, data: ["--out", out, "--data", data]),
    "lidar": ("lidar", "real LiDAR-camera frames: lidar.md", lambda out, data: ["--out", out, "--data", data]),
    "synthetic_drive": ("synthetic_drive", "sweeps with exact truth, single and joint: synthetic_drive.md",
                        lambda out, data: ["--out", out / "synthetic_drive.md"]),
    "verticals": ("verticals", "the verticals check against the references (printed)", lambda out, data: ["--data", data]),
    "intrinsics": ("intrinsics", "refining the camera with the pose: intrinsics.md",
                   lambda out, data: ["--out", out / "intrinsics.md"]),
    "bundle": ("bundle", "the joint solve against per-photo refines: bundle.md",
               lambda out, data: ["--out", out / "bundle.md", "--icl", data / "icl_nuim_livingroom1"]),
    "export": ("export", "export's disparity against the truth, its depth 1-sigma, its cost: export.md",
               lambda out, data: ["--out", out / "export.md"]),
    "big_photo": ("big_photo", "every command on a 24-megapixel photo: big_photo.md",
                  lambda out, data: ["--out", out / "big_photo.md"]),
    "scale": ("scale", "a 40-million-point scan with ten photos, workers and Ray: scale.md",
              lambda out, data: ["--out", out / "scale.md"]),
    "fuzz": ("fuzz", "600 fuzzing trials over every command: reliability.md",
             lambda out, data: ["--trials", "600", "--seed", "1", "--root", "bench_out/fuzz", "--quiet", "--data", data,
                                "--report", out / "reliability.md"]),
}
BY_HAND = {"gpu": "the aligner on CUDA against the CPU (gpu.md): `python -m benchmarks.gpu --help`, on a GPU machine"}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__.split("\n\n")[0],
                                 epilog="benchmarks: " + "; ".join(f"{k}: {v[1]}" for k, v in BENCHMARKS.items())
                                 + "; by hand: " + "; ".join(f"{k}: {v}" for k, v in BY_HAND.items()))
    ap.add_argument("names", nargs="*", metavar="NAME", help="Which to run (default: all). " + ", ".join(BENCHMARKS))
    ap.add_argument("--out", type=Path, default=Path("docs"), help="Folder for the documents (default: docs).")
    ap.add_argument("--data", type=Path, default=Path("../shared/data"), help="The real data folder (default: ../shared/data).")
    args = ap.parse_args(argv)
    unknown = [n for n in args.names if n not in BENCHMARKS]
    if unknown:
        ap.error(f"unknown benchmark(s) {', '.join(unknown)}; choose from {', '.join(BENCHMARKS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    for name in args.names or list(BENCHMARKS):
        module, what, arguments = BENCHMARKS[name]
        start = time.perf_counter()
        print(f"== {name}: {what}", file=sys.stderr, flush=True)
        code = importlib.import_module(f"benchmarks.{module}").main([str(a) for a in arguments(args.out, args.data)])
        print(f"== {name}: {time.perf_counter() - start:.0f} s", file=sys.stderr, flush=True)
        if code:
            return int(code)
    return 0


if __name__ == "__main__":
    sys.exit(main())
