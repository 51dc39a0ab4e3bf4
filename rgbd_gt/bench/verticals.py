"""The verticals check (rgbd_gt/qa/verticals.py) on the PJLab scenes: how far each reference
extrinsic, and the LiDAR benchmark's nid results, are rolled off the sweep's vertical. Prints a Markdown
table (docs/lidar-method.md, "What the vertical lines say about the references").

    python -m rgbd_gt.bench.verticals [--data ../shared/data] [--cases bench_out/lidar/cases.json]
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

if __name__ == "__main__":
    main()
