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
    from rgbd_gt.qa.verticals import photo_segments, roll_deg, scan_vertical, verticals_qa

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
        points, T = read_pcd(folder / "calib.pcd").xyz, read_pose(folder / "calib.txt")[0]
        segments = photo_segments(photo, camera)
        ref = verticals_qa(points, photo, camera, T, boots=400, segments=segments)
        up, _ = scan_vertical(points, -T[:3, :3].T @ T[:3, 3])
        K = np.array([[camera.fx, 0, camera.cx], [0, camera.fy, camera.cy], [0, 0, 1]])
        results = [roll_deg(segments, K, np.array(c["T"])[:3, :3], up) for c in cases
                   if c.get("objective") == "nid" and c.get("scenes") == scene]
        tail = f"{np.median(results):+.2f} ({min(results):+.2f} .. {max(results):+.2f}), {len(results)} results" if results else ""
        print(f"| {scene} | {ref.segments} | {ref.poles}; {np.degrees(np.arccos(up[2])):.2f} deg | "
              f"{ref.roll:+.2f} deg ({ref.low:+.2f} .. {ref.high:+.2f}) | {tail} |")


if __name__ == "__main__":
    main()
