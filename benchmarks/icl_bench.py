"""The paper's Sec. 4.1 on ICL-NUIM, for every method (`python -m benchmarks icl`, part of `make bench`).

Writes docs/benchmark.md (one table, the same cases for every method, and the machine it ran
on) and docs/benchmark_cumulative.png (cumulative error curves, as the paper's Fig. 4).
"""

from __future__ import annotations

import dataclasses
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.align.config import RefineConfig
from benchmarks.icl import ICL_CAMERA, Case, make_cases
from rgbd_gt.pose import rotation_error_deg, translation_error_m

SUCCESS_MM, SUCCESS_DEG = 5.0, 0.1
PHOTOMETRIC = {
    "quadratic (ours)": {},
    "quadratic, photo not enlarged": {"upsample": 1},
    "linear": {"color_model": "linear"},
    "none": {"color_model": "none"},
    "gray": {"color_model": "gray"},
    "gray_affine": {"color_model": "gray_affine"},
    "central differences": {"gradient": "central"},
}
FEATURES = ("ORB", "SIFT")
OTHER_SEEDS = (1, 2, 3)  # the default method again with other random point subsets: what a median's last digits mean


def photometric_method(change: dict, device: str) -> Callable[[Case], np.ndarray]:
    import torch

    from rgbd_gt.align.aligner import Aligner
    from rgbd_gt.align.photometric import Photometric
    from rgbd_gt.align.refine import photometric_pyramid

    cfg = dataclasses.replace(RefineConfig(), **change)

    def run(case: Case) -> np.ndarray:
        pyramid = photometric_pyramid(case.photo, ICL_CAMERA, cfg, torch.device(device))
        return Aligner(Photometric(case.points, case.colors, pyramid, cfg)).refine(case.T_init).T_cam_from_scan

    return run


def feature_method(kind: str) -> Callable[[Case], np.ndarray]:
    from benchmarks.baselines import feature_pose

    return lambda case: feature_pose(case.points, case.colors, case.photo, ICL_CAMERA, case.T_init, kind)


def machine() -> str:
    import torch

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (f"{cpu}, {torch.get_num_threads()} torch threads, {platform.system()} {platform.release()}, "
            f"Python {platform.python_version()}, torch {torch.__version__}")


def time_refine_command(case: Case, repeats: int = 3, device: str = "auto") -> tuple[float, float, float]:
    """Wall time of the whole `rgbd-gt refine` command on one case written to files, and the
    aligner and verification times it records (the medians of `repeats` runs)."""
    import yaml

    from rgbd_gt.io import save_scan, write_camera, write_pose

    from rgbd_gt.scan import Scan
    from rgbd_gt.io.image import write_image

    with tempfile.TemporaryDirectory() as tmp:
        d = Path(tmp)
        save_scan(d / "scan.ply", Scan(xyz=case.points, rgb=case.colors))
        write_image(d / "photo.png", case.photo)
        write_camera(d / "camera.yaml", ICL_CAMERA)
        write_pose(d / "init.yaml", case.T_init)
        walls, aligner, verify = [], [], []
        for _ in range(repeats):
            t = time.perf_counter()
            subprocess.run([sys.executable, "-m", "rgbd_gt", "refine", "--scan", d / "scan.ply", "--image", d / "photo.png",
                            "--camera", d / "camera.yaml", "--init", d / "init.yaml", "-o", d / "pose.yaml", "--device", device],
                           check=True, capture_output=True)
            walls.append(time.perf_counter() - t)
            meta = yaml.safe_load((d / "pose.yaml").read_text())
            aligner.append(meta["seconds"])
            verify.append(meta["verify_seconds"])
    return float(np.median(walls)), float(np.median(aligner)), float(np.median(verify))


def run_benchmark(data: Path, out_dir: Path, device: str = "cpu", effects_near: int = 4, effects_far: int = 5,
                  methods: list[str] | None = None, log: Callable[[str], None] = print,
                  other_seeds: tuple[int, ...] = OTHER_SEEDS, command_runs: int = 3) -> dict:
    groups = {
        "i±1": make_cases(data, offsets=(1,), effects_per_pair=effects_near, seed=1),
        "i±3": make_cases(data, offsets=(3,), effects_per_pair=effects_far, seed=3),
    }
    # timed first: after the runs below, this process's idle torch threads would compete with it
    cmd_wall, cmd_aligner, cmd_verify = time_refine_command(groups["i±1"][0], command_runs, device)
    all_methods: dict[str, Callable[[Case], np.ndarray]] = {}
    for name, change in PHOTOMETRIC.items():
        all_methods[name] = photometric_method(change, device)
    for kind in FEATURES:
        all_methods[kind] = feature_method(kind.lower())
    names = methods or list(all_methods)
    results: dict = {}
    for name in names:
        for group, cases in groups.items():
            errs = []
            for k, case in enumerate(cases):
                t = time.perf_counter()
                T = all_methods[name](case)
                errs.append((translation_error_m(T, case.T_true) * 1e3, rotation_error_deg(T, case.T_true),
                             time.perf_counter() - t))
                log(f"{name:22s} {group} {k + 1:2d}/{len(cases)} {case.name:8s} {errs[-1][0]:8.3f} mm {errs[-1][1]:7.4f} deg {errs[-1][2]:.2f} s")
            results[(name, group)] = np.array(errs)
    floor = floor_errors(data, all_methods["quadratic (ours)"])
    seeds = {seed: {g: case_errors(photometric_method({"seed": seed}, device), cases) for g, cases in groups.items()}
             for seed in other_seeds}
    report = {"results": results, "groups": {g: len(c) for g, c in groups.items()}, "machine": machine(), "seeds": seeds,
              "refine_command_s": cmd_wall, "refine_aligner_s": cmd_aligner, "refine_verify_s": cmd_verify, "command_runs": command_runs, "names": names, "floor": floor}
    write_markdown(out_dir / "benchmark.md", report)
    plot_cumulative(out_dir / "benchmark_cumulative.png", report)
    return report


def case_errors(method: Callable[[Case], np.ndarray], cases: list[Case]) -> np.ndarray:
    """(n, 2): the method's translation (mm) and rotation (degrees) error on each case."""
    return np.array([(translation_error_m(T, c.T_true) * 1e3, rotation_error_deg(T, c.T_true))
                     for c in cases for T in [method(c)]])


def success(errors: np.ndarray) -> np.ndarray:
    """(n,) bool: the cases of errors (n, >= 2; mm, degrees) within the success bounds."""
    return (errors[:, 0] < SUCCESS_MM) & (errors[:, 1] < SUCCESS_DEG)


def floor_errors(data: Path, method: Callable[[Case], np.ndarray]) -> dict[str, np.ndarray]:
    """What the data alone costs the default method on the i±3 pairs: the photos without effects,
    with the noisy depth and with the clean depth. Per condition (n, 2): mm, degrees."""
    return {depth: case_errors(method, make_cases(data, offsets=(3,), effects=False, depth=depth))
            for depth in ("noisy", "clean")}


def summary_rows(report: dict) -> list[list[str]]:
    rows = []
    for name in report["names"]:
        row = [name]
        for group in report["groups"]:
            e = report["results"][(name, group)]
            row += [f"{np.median(e[:, 0]):.3f}", f"{np.median(e[:, 1]):.4f}", f"{success(e).mean():.0%}", f"{e[:, 2].mean():.2f}"]
        rows.append(row)
    return rows


def write_markdown(path: Path, report: dict) -> None:
    from rgbd_gt.io.atomic import atomic_output

    groups = list(report["groups"])
    head = ["method"] + [f"{g} {c}" for g in groups for c in ("median t (mm)", "median R (deg)", "success", "s/case")]
    runs = f"median of {report['command_runs']} runs" if report["command_runs"] > 1 else "one run"
    lines = [
        "# Benchmark: the paper's Sec. 4.1 on ICL-NUIM livingroom1",
        "",
        "Made by `make bench` (`python -m benchmarks icl`). Cases: the point cloud of frame i (noisy depth, frame i's",
        "colors) in the world frame; the photo of frame j with random multimodal effects (brightness,",
        "contrast, saturation in [0.6, 1.4], hue in [-0.06, 0.06], gamma in [0.5, 1] or [1, 2], blur",
        "sigma in [0, 0.75] px); init = camera i's pose, truth = camera j's. "
        + ", ".join(f"{g}: {n} cases" for g, n in report["groups"].items()) + ".",
        "Same cases for every method. Translation error: distance between camera centres; rotation error:",
        "geodesic angle, 2 asin(|Ra Rb^T - I|_F / sqrt 8) on SO(3)-projected rotations. Success: < 5 mm and",
        "< 0.1 deg. s/case: the method's own time (photo pyramid, set-up and optimisation; not file I/O).",
        "",
        "| " + " | ".join(head) + " |",
        "|" + "---|" * len(head),
    ]
    lines += ["| " + " | ".join(r) + " |" for r in summary_rows(report)]
    lines += [
        "",
        "The default samples the photo enlarged 4x by bicubic interpolation at the finest level",
        "(`upsample`, rgbd_gt/align/pyramid.py says why); \"photo not enlarged\" is the same method on",
        "the photo's own pixels, as in the paper. The other rows differ from the default in one setting.",
        "",
        "The whole `rgbd-gt refine` command on one 640x480 case (reading a PLY of the frame's cloud, the",
        f"photo, camera and pose files; refining; judging the result; writing the pose): {report['refine_command_s']:.2f} s wall,",
        f"of which {report['refine_aligner_s']:.2f} s aligner time and {report['refine_verify_s']:.2f} s for the verdict's evidence",
        f"(docs/trust.md; {runs}). The s/case columns above are the aligner alone.",
        "",
        f"Machine: {report['machine']}.",
        "",
        "![cumulative errors](benchmark_cumulative.png)",
        "",
    ]
    if report.get("seeds") and ("quadratic (ours)", groups[0]) in report["results"]:
        lines += [
            "## Other random point subsets",
            "",
            "The aligner works on a random subset of the points (`seed`, rgbd_gt/align/subset.py). The default",
            "method on the same cases with other seeds (success as above):",
            "",
            "| seed | " + " | ".join(f"{g} median t (mm) | {g} median R (deg) | {g} success" for g in groups) + " |",
            "|" + "---|" * (1 + 3 * len(groups)),
        ]
        runs = {0: {g: report["results"][("quadratic (ours)", g)] for g in groups}, **report["seeds"]}
        for seed, by_group in runs.items():
            cells = []
            for g in groups:
                e = by_group[g]
                cells += [f"{np.median(e[:, 0]):.3f}", f"{np.median(e[:, 1]):.4f}", f"{success(e).mean():.0%}"]
            lines.append(f"| {seed}{' (the table above)' if seed == 0 else ''} | " + " | ".join(cells) + " |")
        lines += ["", "Differences of this size between two versions of the aligner are the choice of points, not accuracy.", ""]
    lines += [
        "## What the data costs at i±3",
        "",
        "The default method on the same i±3 pairs with the photos as they are (no effects):",
        "",
        "| depth of frame i | median t (mm) | median R (deg) |",
        "|---|---|---|",
    ] + [f"| {d} | {np.median(e[:, 0]):.3f} | {np.median(e[:, 1]):.4f} |" for d, e in report["floor"].items()] + [
        "",
        "Without any photo effect the error is already most of the i±3 figure above: it comes from the",
        "data, not from the color model. Per pair it is the same for every effect and it flips sign",
        "between i->j and j->i (the estimate falls short of the motion by about 0.5-1%). The noisy depth",
        "is biased by depth (median -7 to +5 mm per depth band against the clean depth), and frame i's",
        "colors are sampled on frame i's pixel grid and seen at another scale and blur from frame j.",
        "That grid is also why the enlarged photo helps here: at the initial pose every point falls on",
        "a pixel centre of the photo, where bilinear interpolation does not blur, and that pull towards",
        "the initial pose shrinks when the photo is enlarged.",
        "",
    ]
    with atomic_output(path) as tmp:
        tmp.write_text("\n".join(lines))


def plot_cumulative(path: Path, report: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from rgbd_gt.io.atomic import atomic_output

    groups = list(report["groups"])
    fig, axes = plt.subplots(len(groups), 2, figsize=(11, 4 * len(groups)))
    for gi, group in enumerate(groups):
        for k, (label, limit) in enumerate((("translation error (mm)", 5.0), ("rotation error (deg)", 0.1))):
            ax = axes[gi, k]
            for name in report["names"]:
                e = np.sort(report["results"][(name, group)][:, k])
                ax.step(e, np.arange(1, len(e) + 1) / len(e), where="post", label=name)
            ax.set_xscale("log")
            ax.set_xlim(limit / 100 if k == 0 else limit / 200, limit * 4)
            ax.axvline(limit, color="gray", lw=0.5)
            ax.set_xlabel(label)
            ax.set_ylabel("fraction of cases")
            ax.set_title(f"pairs {group}")
            ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=8)
    fig.tight_layout()
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    import argparse

    from rgbd_gt.align.refine import resolve_device

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data/icl_nuim_livingroom1"), help="The ICL-NUIM livingroom1 folder.")
    ap.add_argument("--out", type=Path, default=Path("docs"), help="Where benchmark.md and benchmark_cumulative.png go.")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or auto.")
    ap.add_argument("--quick", action="store_true", help="One effect per frame pair, only our method and SIFT, the command timed once (a smoke run).")
    args = ap.parse_args(argv)
    if not args.data.is_dir():
        sys.exit(f"error: {args.data}: benchmark data folder not found")
    dev = str(resolve_device(args.device))
    kw = dict(effects_near=1, effects_far=1, methods=["quadratic (ours)", "SIFT"], other_seeds=(), command_runs=1) if args.quick else {}
    report = run_benchmark(args.data, args.out, dev, log=lambda line: print(line, file=sys.stderr, flush=True), **kw)
    heads = ["method"] + [f"{g} {c}" for g in report["groups"] for c in ("t mm", "R deg", "ok", "s")]
    for row in [heads] + summary_rows(report):
        print(" | ".join(row))
    print(f"refine command: {report['refine_command_s']:.2f} s wall, aligner {report['refine_aligner_s']:.2f} s, "
          f"verdict {report['refine_verify_s']:.2f} s")
    print(f"wrote {args.out / 'benchmark.md'} and {args.out / 'benchmark_cumulative.png'}")


if __name__ == "__main__":
    main()
