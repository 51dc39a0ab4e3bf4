"""The verticals check (rgbd_gt/qa/verticals.py) on the PJLab scenes: how far each reference
extrinsic, and the LiDAR benchmark's nid results, are rolled off the sweep's vertical; and on
synthetic scenes with exact truth, how often its interval at the true pose holds 0. Prints
Markdown tables (docs/lidar-method.md, "What the vertical lines say about the references").

    python -m benchmarks.verticals [--data ../shared/data] [--cases bench_out/lidar/cases.json] [--synthetic 42]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main(argv: list[str] | None = None) -> None:
    from rgbd_gt.io import read_camera, read_pose
    from rgbd_gt.io.image import read_image
    from rgbd_gt.io.pcd import read_pcd
    from rgbd_gt.pose import camera_centre
    from rgbd_gt.qa.verticals import scan_vertical, verticals_qa

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--cases", type=Path, default=Path("bench_out/lidar/cases.json"),
                    help="benchmarks/lidar.py's results: the roll of its nid results too")
    ap.add_argument("--synthetic", type=int, default=42, help="synthetic scenes (seeds 0..N-1) for the coverage table; 0: none")
    args = ap.parse_args(argv)
    cases = json.loads(args.cases.read_text()) if args.cases.exists() else []
    print("| scene | vertical lines | sweep's poles; their vertical from z | roll of the reference (95%) | "
          "roll of the nid results: median (range) |")
    print("|---|---|---|---|---|")
    for scene in ("pjlab_1", "pjlab_2", "pjlab_3"):
        folder = args.data / "lidar_camera" / scene
        photo = read_image(next(p for p in (folder / "calib.png", folder / "calib.jpg") if p.exists()))
        camera = read_camera(folder / "calib.txt", (photo.shape[1], photo.shape[0]))
        T_ref = read_pose(folder / "calib.txt")[0]
        points = read_pcd(folder / "calib.pcd").xyz
        ref, *results = verticals_qa(points, photo, camera,
                                     [T_ref] + [np.array(c["T"]) for c in cases
                                                if c.get("objective") == "nid" and c.get("scenes") == scene], boots=400)
        rolls = [r.roll for r in results]
        up = scan_vertical(points, camera_centre(T_ref))[0]
        tail = f"{np.median(rolls):+.2f} ({min(rolls):+.2f} .. {max(rolls):+.2f}), {len(rolls)} results" if rolls else ""
        print(f"| {scene} | {ref.segments} | {ref.poles}; {np.degrees(np.arccos(up[2])):.2f} deg | "
              f"{ref.roll:+.2f} deg ({ref.low:+.2f} .. {ref.high:+.2f}) | {tail} |")
    if args.synthetic:
        coverage(args.synthetic)


def coverage(seeds: int) -> None:
    """On `seeds` small synthetic scenes (the scan's z up, as a levelled scanner's), the check at
    the true pose: whether it says anything, and whether its interval holds 0, the truth."""
    import tempfile

    from rgbd_gt.config import load_config
    from rgbd_gt.io import load_scan, read_camera, read_pose
    from rgbd_gt.io.image import read_image
    from rgbd_gt.qa.verticals import SYSTEMATIC_DEG, verticals_qa
    from rgbd_gt.synth.generate import SynthConfig, generate

    rows, cfg = [], load_config(SynthConfig, None, "synth.yaml")  # as `rgbd-gt synth` makes them
    with tempfile.TemporaryDirectory() as tmp:
        for seed in range(seeds):
            d = Path(tmp) / str(seed)
            generate(d, seed, "small", cfg)
            photo = read_image(d / "photo.png")
            camera = read_camera(d / "camera.yaml", (photo.shape[1], photo.shape[0]))
            r, = verticals_qa(load_scan(d / "scan.ply").xyz, photo, camera, [read_pose(d / "gt_pose.yaml")[0]])
            rows.append(r)
    usable = [r for r in rows if r.usable]
    held = sum(r.low <= 0 <= r.high for r in usable)
    bare = sum(r.low + SYSTEMATIC_DEG <= 0 <= r.high - SYSTEMATIC_DEG for r in usable)
    rolls = np.abs([r.roll for r in usable])
    print(f"\n| synthetic scenes | check usable | interval holds 0 (without the {SYSTEMATIC_DEG} deg allowance) | "
          f"abs roll at the truth: median, largest | interval width: median |")
    print("|---|---|---|---|---|")
    print(f"| {seeds} (seeds 0-{seeds - 1}) | {len(usable)} | {held} of {len(usable)} ({bare}) | "
          f"{np.median(rolls):.3f}, {rolls.max():.3f} deg | {np.median([r.high - r.low for r in usable]):.2f} deg |")


if __name__ == "__main__":
    main()
