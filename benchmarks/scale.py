"""Benchmark: `rgbd-gt run` on a FARO-sized structured scan (a synthetic 40.8-million-point dome
of 190 x 150 degrees, made once into bench_out/scale/) with ten 1280x960 photos, on this
machine. Measures: preparing the scan (fresh cache), reopening the cache, every step per photo
(from summary.csv), the run's peak memory against the scan's arrays, and the speed-up of
--workers 2 over one worker. Writes the tables to docs/scale.md's results section.

    python -m benchmarks.scale [--points 40.8e6] [--photos 10] [--skip-workers]
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from benchmarks.peak import run_measured
from benchmarks.icl_bench import machine
from benchmarks.dome import dome_scene

RELOAD = r"""
import sys, time
t = time.perf_counter()
from rgbd_gt.prepared import prepare_scan
from pathlib import Path
p = prepare_scan(Path(sys.argv[1]), Path(sys.argv[2]))
print(time.perf_counter() - t)
"""


def run(config: Path, *extra: str) -> tuple[float, float]:
    """(wall seconds, peak resident GB of the command's own process) of one `rgbd-gt run`."""
    return run_measured(["run", str(config), *extra])


def ray_run(config: Path, out: Path, cpus: int) -> float:
    """Wall seconds of the photos (cache reused) on a local Ray cluster of `cpus` CPUs."""
    import os
    import socket

    for d in out.iterdir():
        if d.is_dir() and not d.name.startswith("."):
            shutil.rmtree(d)
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    ray = [sys.executable, "-m", "ray.scripts.scripts"]
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    subprocess.run(ray + ["start", "--head", "--node-ip-address", "127.0.0.1", "--port", str(port), "--num-cpus", str(cpus),
                          "--include-dashboard", "false", "--disable-usage-stats"], check=True, capture_output=True, env=env)
    try:
        return run(config, "--ray", f"127.0.0.1:{port}")[0]
    finally:
        subprocess.run(ray + ["stop", "--force"], capture_output=True, env=env)


def photo_rows(out: Path) -> list[dict]:
    return [r for r in csv.DictReader(open(out / "summary.csv")) if not r["photo"].startswith("#")]


def pose_errors(scene: Path, out: Path, photo: str) -> tuple[float, float, float, float]:
    """(refined mm, deg, initial mm, deg) of a photo's poses against the scene's truth."""
    from rgbd_gt.io import read_pose
    from rgbd_gt.pose import rotation_error_deg, translation_error_m

    stem = Path(photo).stem
    truth = read_pose(scene / f"gt_pose{stem[len('photo'):]}.yaml")[0]  # photo_3 -> gt_pose_3
    T, T0 = read_pose(out / stem / "pose.yaml")[0], read_pose(out / stem / "init.yaml")[0]
    return (translation_error_m(T, truth) * 1e3, rotation_error_deg(T, truth),
            translation_error_m(T0, truth) * 1e3, rotation_error_deg(T0, truth))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--points", type=float, default=40.8e6)
    ap.add_argument("--photos", type=int, default=10)
    ap.add_argument("--dir", type=Path, default=Path("bench_out/scale"))
    ap.add_argument("--out", type=Path, default=Path("docs/scale.md"), help="The document whose results section gets the tables.")
    ap.add_argument("--skip-workers", action="store_true")
    ap.add_argument("--skip-ray", action="store_true", help="Leave out the run on a local Ray cluster of 1 and of 2 CPUs.")
    args = ap.parse_args(argv)
    scene = dome_scene(args.dir / f"dome_{args.points:.3g}_{args.photos}", args.points, args.photos)
    out = args.dir / "out"
    config = args.dir / "run.yaml"
    config.write_text(f"scan: {scene.name}/scan.e57\ncamera: {scene.name}/camera.yaml\nphotos: [{scene.name}/photo*.png]\n"
                      "output: out\nboard: {cols: 9, rows: 6, square: 0.05}\n")
    shutil.rmtree(out, ignore_errors=True)
    wall1, peak1 = run(config)
    record = json.loads((out / "run.json").read_text())
    prep = record["scans"][0]
    rows = photo_rows(out)
    # the scan's arrays as loaded (xyz float64, rgb, intensity, row, col, scan_id)
    n = prep["points"]
    arrays_gb = n * (24 + 3 + 4 + 4 + 4 + 4) / 1e9
    reload = float(subprocess.run([sys.executable, "-c", RELOAD, str(scene / "scan.e57"), str(out / ".scan-cache")],
                                  check=True, capture_output=True, text=True).stdout)
    lines = [f"Scan: {n:,} points (a 190 x 150 degree grid), {len(rows)} photos of 1280x960; "
             f"the scan's arrays as loaded: {arrays_gb:.2f} GB.", "",
             "| what | seconds |", "|---|---|",
             f"| preparing the scan (once): all | {prep['steps'].get('scan', 0):.1f} |"]
    lines += [f"| ... {k} | {v:.1f} |" for k, v in (prep.get("prepare_seconds") or {}).items()]
    lines += [f"| ... hashing the file, the rest | {prep['steps'].get('scan', 0) - sum((prep.get('prepare_seconds') or {}).values()):.1f} |",
              f"| finding the board (once) | {prep['steps'].get('board', 0):.1f} |",
              f"| reopening the cache (a new process, with the hash) | {reload:.1f} |", ""]
    steps = [dict(kv.split("=") for kv in r["steps"].split()) for r in rows]
    names = ["init", "view", "aligner", "refine", "mesh", "depth", "qa", "overlay"]
    lines += ["Per photo (seconds; `refine` is the whole step: the aligner, then the verdict's evidence; `mesh` is "
              "the view's ray-casting scene, one for the refined and the initial pose, built by the first render: "
              "within refine (the verdict's edge check)):", "",
              "| photo | view points | " + " | ".join(names) + " | total | verdict |", "|---" * (len(names) + 4) + "|"]
    for r, s in zip(rows, steps):
        lines.append(f"| {r['photo']} | {int(r['view_points']):,} | " + " | ".join(f"{float(s.get(k, 'nan')):.1f}" for k in names)
                     + f" | {float(r['seconds']):.1f} | {r['verdict']} |")
    med = {k: float(np.median([float(s.get(k, "nan")) for s in steps])) for k in names}
    lines.append("| **median** | | " + " | ".join(f"**{med[k]:.1f}**" for k in names)
                 + f" | **{np.median([float(r['seconds']) for r in rows]):.1f}** | |")
    errors = np.array([pose_errors(scene, out, r["photo"]) for r in rows])
    lines += ["", f"Poses against the truth: refined median {np.median(errors[:, 0]):.2f} mm / {np.median(errors[:, 1]):.4f} deg, "
              f"worst {errors[:, 0].max():.2f} mm / {errors[:, 1].max():.4f} deg (from the board's PnP: median "
              f"{np.median(errors[:, 2]):.1f} mm / {np.median(errors[:, 3]):.3f} deg)."]
    lines += ["", f"Whole run (fresh cache): {wall1:.0f} s wall, peak resident memory {peak1:.2f} GB = "
              f"{peak1 / arrays_gb:.2f} x the scan's arrays."]
    if not args.skip_workers:
        photos_s = {}
        for workers in (1, 2):
            for d in out.iterdir():  # keep the cache and the board: photos only
                if d.is_dir() and not d.name.startswith("."):
                    shutil.rmtree(d)
            wall, _ = run(config, "--workers", str(workers))
            photos_s[workers] = wall
        lines += ["", f"Photos only (cache reused), whole command wall time: 1 worker {photos_s[1]:.0f} s, "
                  f"2 workers {photos_s[2]:.0f} s: speed-up {photos_s[1] / photos_s[2]:.2f}x on this machine."]
    if not args.skip_ray:
        ray_s = {cpus: ray_run(config, out, cpus) for cpus in (1, 2)}
        lines += ["", f"The same on a Ray cluster started on loopback (`--ray`, one task per photo): 1 CPU {ray_s[1]:.0f} s, "
                  f"2 CPUs {ray_s[2]:.0f} s: speed-up {ray_s[1] / ray_s[2]:.2f}x."]
    lines += ["", f"Machine: {machine()}."]
    text = "\n".join(lines)
    print(text)
    (args.dir / "results.md").write_text(text + "\n")
    doc = args.out
    if doc.exists():
        body = doc.read_text()
        start, end = "<!-- results -->", "<!-- /results -->"
        if start in body and end in body:
            doc.write_text(body[:body.index(start) + len(start)] + "\n" + text + "\n" + body[body.index(end):])


if __name__ == "__main__":
    main()
