"""The CUDA path against the CPU path on the same cases: the real PJLab scenes (nid, with the
verdict unless --no-verdict), ICL-NUIM pairs (photometric), the KITTI and Waymo drives (nid, one
frame and every frame jointly, with the verdict) and a stereo rig's intensity-only bundle (nid).
Writes docs/gpu.md.

A GPU machine may lack open3d (it reads PCD files and makes a sweep's normals), so the work is
split: `prepare` reads the scenes where the package is installed and writes them, normals made,
into pickles; `run` refines them on each device asked for. Both devices run the same code on
the same inputs, so what differs is the device alone.
"""

from __future__ import annotations

import gzip
import json
import pickle
import shutil
import subprocess
import time
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.align.config import RefineConfig
from benchmarks.lidar import DRIVES, JOINT, SIZES, group_inits, init_poses, pjlab_scenes, run_case, run_inputs
from rgbd_gt.pose import rotation_error_deg, translation_error_m

SCENES = "pjlab.pickle.gz"
DRIVE_INPUTS = "drives.pickle.gz"  # per drive: its frames' refine inputs from one init, the photos beside
STEREO = "stereo.pickle.gz"  # the bundle benchmark's stereo scene, seed 0, small, its scan with normals
ICL = "icl_nuim_livingroom1"


def prepare(data: Path, out: Path) -> None:
    """The PJLab scenes (`bench.lidar.pjlab_scenes`) as one pickle, and the ICL-NUIM folder, in out."""
    out.mkdir(parents=True, exist_ok=True)
    with gzip.open(out / SCENES, "wb", compresslevel=3) as f:
        pickle.dump(pjlab_scenes(data / "lidar_camera"), f)
    shutil.copytree(data / ICL, out / ICL, dirs_exist_ok=True)
    prepare_drives(data, out)
    prepare_stereo(out)


def prepare_drives(data: Path, out: Path) -> None:
    """Per drive of DRIVES: the refine inputs of every frame from the drives benchmark's first
    1 deg / 10 cm draw (`bench.lidar.collect_drives`), the points in view only; each photo as
    its file beside (the pickle holds its name), which keeps the whole small enough to travel."""
    from benchmarks.lidar import drive_scenes, refine_inputs

    drives = {}
    for drive in DRIVES:
        folder = data / "lidar_camera" / drive
        scenes = drive_scenes(folder)
        T0 = init_poses(scenes[0].T_ref, *SIZES[0], 1, seed=sum(map(ord, drive)))[0]
        inputs = [refine_inputs(s, T0) for s in scenes]
        for s, i in zip(scenes, inputs):
            photo = next(p for p in (folder / "img").iterdir() if p.stem == s.name)
            i.photo = f"{drive}_{photo.name}"
            shutil.copyfile(photo, out / i.photo)
        drives[drive] = {"T_ref": scenes[0].T_ref, "inputs": inputs}
    with gzip.open(out / DRIVE_INPUTS, "wb", compresslevel=3) as f:
        pickle.dump(drives, f)


def prepare_stereo(out: Path) -> None:
    """The stereo rig of docs/bundle.md (seed 0, 4 shots, small), its scan's normals made."""
    from benchmarks.bundle import load, scene
    from rgbd_gt.io import read_pose

    d = scene(0, 4, "stereo")
    scan, shots = load(d, rig=True)
    with gzip.open(out / STEREO, "wb", compresslevel=3) as f:
        pickle.dump({"scan": scan, "shots": shots, "T_rl": read_pose(d / "rig_gt.yaml")[0]}, f)


def lidar_cases(inputs: Path, inits: int) -> list[tuple[str, list, np.ndarray]]:
    """(name, scenes, T_init): the LiDAR benchmark's first `inits` inits of each size per scene
    (`bench.lidar.group_inits`), and the joint solve of JOINT from its 1 deg / 10 cm ones."""
    with gzip.open(inputs / SCENES, "rb") as f:
        scenes = pickle.load(f)
    by_name = {s.name: s for s in scenes}
    groups = [[s] for s in scenes] + [[by_name[n] for n in JOINT]]
    return [(f"{' + '.join(s.name for s in group)} {deg:g} deg #{i}", group, T0) for group in groups
            for deg, _, i, T0 in group_inits(group, inits, SIZES[:1] if len(group) > 1 else SIZES)]


def drive_cases(inputs: Path) -> list[tuple[str, str, list, np.ndarray, bool]]:
    """(kind, case, refine inputs, T_ref, judged): per drive its first frame alone (the aligner
    alone: a frame's verdict is four more refines of the same kind) and every frame jointly."""
    from rgbd_gt.io.image import read_image

    with gzip.open(inputs / DRIVE_INPUTS, "rb") as f:
        drives = pickle.load(f)
    cases = []
    for drive, d in drives.items():
        for i in d["inputs"]:
            i.photo = read_image(inputs / i.photo)
        n = len(d["inputs"])
        cases += [(f"nid ({drive}, single frame)", f"{drive} frame 0", d["inputs"][:1], d["T_ref"], False),
                  (f"nid ({drive}, joint over {n} frames)", f"{drive} joint", d["inputs"], d["T_ref"], True)]
    return cases


def stereo_case(inputs: Path, device: str) -> dict:
    """The stereo rig's intensity-only bundle (`bench.bundle.joint`, nid) on device: its worst
    pose error and its baseline error against the truth."""
    from benchmarks.bundle import errors, joint, rig_errors

    with gzip.open(inputs / STEREO, "rb") as f:
        st = pickle.load(f)
    result, seconds = joint(st["scan"], st["shots"], "none", rig=2, nid=True, device=device)
    errs = [errors(T, sh) for T, sh in zip(result.poses, st["shots"])]
    worst = max(range(len(errs)), key=lambda k: errs[k][0])
    T = result.poses[worst]
    return {"deg": errs[worst][1], "cm": errs[worst][0] / 10, "T": T.tolist(), "seconds": seconds,
            "baseline_mm": abs(rig_errors(result.rig[1], st["T_rl"])[0])}


def spacing_without_open3d() -> bool:
    """Where open3d is missing (the GPU machine's image), the verdict's point spacing
    (`render.depth.local_spacing`, open3d's nearest-neighbour search) by an exact torch search
    instead, so that the verdict runs there too. True when it was replaced."""
    import importlib.util

    import torch

    if importlib.util.find_spec("open3d") is not None:
        return False

    import rgbd_gt.render.depth as depth

    def local_spacing(points: np.ndarray, k: int = 3) -> np.ndarray:
        p = torch.as_tensor(np.ascontiguousarray(points), dtype=torch.float64,
                            device="cuda" if torch.cuda.is_available() else "cpu")
        # the (k+1)-th smallest distance: the point itself is the first
        return torch.cat([torch.cdist(a, p).kthvalue(k + 1, dim=1).values for a in p.split(2048)]).cpu().numpy()

    depth.local_spacing = local_spacing
    return True


def _guarded(fn, *args) -> dict:
    """fn(*args), or {"error": the exception's last traceback lines}: a device's failure is a
    finding of this benchmark, not the end of it."""
    import traceback

    try:
        return fn(*args)
    except Exception:  # noqa: BLE001
        return {"error": " | ".join(traceback.format_exc().strip().splitlines()[-3:])}


def profile(fn, *args, rows: int = 25) -> str:
    """torch.profiler's table of fn(*args): the operators by their own host time."""
    import torch
    from torch.profiler import ProfilerActivity, profile as torch_profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if torch.cuda.is_available() else [])
    with torch_profile(activities=acts) as prof:
        fn(*args)
    return prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=rows)


def run(inputs: Path, devices: list[str], inits: int = 3, icl_cases: int = 8, verdict: bool = True,
        profiled: bool = False, log: Callable[[str], None] = print, partial: Path | None = None) -> list[dict]:
    """Every case on every device: pose, errors against the reference, verdict and seconds.
    devices: cpu, cuda, or cpu@N (the CPU with N torch threads). partial: the records so far are
    written there after each case (a run cut short by its machine's time keeps them)."""
    import torch

    from benchmarks.icl import make_cases
    from benchmarks.icl_bench import photometric_method, time_refine_command

    lidar = lidar_cases(inputs, inits) if inits else []
    drives = drive_cases(inputs) if (inputs / DRIVE_INPUTS).exists() else []
    stereo = (inputs / STEREO).exists()
    if verdict and spacing_without_open3d():
        log("no open3d here: the verdict's point spacing by a torch nearest-neighbour search")
    icl = make_cases(inputs / ICL, offsets=(1,), effects_per_pair=1, seed=1)[:icl_cases]
    all_threads = torch.get_num_threads()
    records = []
    for label in devices:
        device, _, threads = label.partition("@")
        torch.set_num_threads(int(threads) if threads else all_threads)
        cfg = RefineConfig(objective="nid")
        photometric = {"photometric (ICL-NUIM)": photometric_method({}, device),
                       "photometric (ICL-NUIM, every point)": photometric_method({"max_points": 10**7}, device)}

        def icl_case(method, case) -> dict:
            t = time.perf_counter()
            T = method(case)  # a numpy pose: the device's work is done
            return {"deg": rotation_error_deg(T, case.T_true), "cm": translation_error_m(T, case.T_true) * 100,
                    "T": T.tolist(), "seconds": time.perf_counter() - t}

        def command() -> dict:
            try:
                wall, aligner, verify = time_refine_command(icl[0], repeats=2, device=device)
            except subprocess.CalledProcessError as exc:
                return {"error": exc.stderr.decode(errors="replace")[-600:]}
            return {"seconds": aligner, "verify_seconds": verify, "wall_seconds": wall}

        # the first run on a device pays its start (CUDA context, kernels' first loads): not timed
        t = time.perf_counter()
        if drives:
            _guarded(run_inputs, drives[0][2], drives[0][3], cfg, device, False)
        elif lidar:
            _guarded(run_case, lidar[0][1], lidar[0][2], cfg, device, False)
        for method in photometric.values():
            _guarded(icl_case, method, icl[0])
        log(f"{label:6s} first runs (not timed): {time.perf_counter() - t:.1f} s")
        if profiled and lidar:
            log(profile(run_case, lidar[0][1], lidar[0][2], cfg, device, False))
            log(profile(icl_case, photometric["photometric (ICL-NUIM)"], icl[0]))

        def record(kind: str, case: str, fn, *args) -> None:
            t = time.perf_counter()
            rec = {"device": label, "case": case, "kind": kind, **_guarded(fn, *args), "elapsed": time.perf_counter() - t}
            records.append(rec)
            if partial is not None:
                partial.write_text(json.dumps(records, indent=1, default=float))
            log(f"{label:6s} {case:28s} {rec['elapsed']:6.1f} s " + (rec["error"] if "error" in rec else " ".join(
                f"{key} {rec[key]:.4g}" for key in ("deg", "cm", "seconds", "verify_seconds", "wall_seconds", "baseline_mm") if key in rec)
                + f" {rec.get('verdict', '')}"))

        for name, group, T0 in lidar:
            record("nid (PJLab)", name, run_case, group, T0, cfg, device, verdict)
        for kind, case, ins, T_ref, judged in drives:
            record(kind, case, run_inputs, ins, T_ref, cfg, device, verdict and judged)
        if stereo:
            record("nid bundle (stereo rig, 4 shots, intensity only)", "stereo seed 0", stereo_case, inputs, device)
        if not threads:  # a process of its own: it takes every thread
            record("`rgbd-gt refine` on an ICL-NUIM pair", "refine command", command)
        for kind, method in photometric.items():
            for case in icl:
                record(kind, f"ICL {case.name}", icl_case, method, case)
    torch.set_num_threads(all_threads)
    return records


def compare(records: list[dict], base: str = "cpu") -> list[dict]:
    """Per kind and device: median and worst seconds, median errors, the verdicts, and how far
    each pose is from the same case's pose on `base`."""
    by = {(r["device"], r["kind"], r["case"]): r for r in records if "T" in r or "verdict" in r}
    median = lambda rs, key, scale=1: float(np.median([r[key] for r in rs])) * scale if rs else None  # noqa: E731
    rows = []
    for kind in dict.fromkeys(r["kind"] for r in records):
        for device in dict.fromkeys(r["device"] for r in records):
            rs = [r for r in records if r["kind"] == kind and r["device"] == device]
            if not rs:
                continue
            ran = [r for r in rs if "error" not in r]
            posed = [r for r in ran if "T" in r]
            judged = [r for r in ran if "verdict" in r]
            twin = lambda r: by.get((base, kind, r["case"]))  # noqa: E731 - the same case on base
            apart = [(rotation_error_deg(np.array(r["T"]), np.array(twin(r)["T"])),
                      translation_error_m(np.array(r["T"]), np.array(twin(r)["T"])) * 1e3) for r in posed if twin(r)]
            rows.append({
                "kind": kind, "device": device, "cases": len(rs), "errors": len(rs) - len(ran),
                "aligner_s": median(ran, "seconds"),
                "aligner_worst_s": max((r["seconds"] for r in ran), default=None),
                "verify_s": median([r for r in ran if "verify_seconds" in r], "verify_seconds"),
                "wall_s": median([r for r in ran if "wall_seconds" in r], "wall_seconds"),
                "median_deg": median(posed, "deg"), "median_mm": median(posed, "cm", 10),
                "verdicts": {v: [r["verdict"] for r in judged].count(v) for v in dict.fromkeys(r["verdict"] for r in judged)},
                "verdicts_as_base": sum(r["verdict"] == twin(r)["verdict"] for r in judged if twin(r)),
                "worst_apart_deg": max((a for a, _ in apart), default=None),
                "worst_apart_mm": max((b for _, b in apart), default=None),
            })
    return rows


def write_markdown(path: Path, rows: list[dict], machine: str, base: str = "cpu") -> None:
    """The table between the file's `<!-- results -->` and `<!-- end results -->` lines (the
    text above and below is kept)."""
    fmt = lambda v, f, unit="": "" if v is None else format(v, f) + unit  # noqa: E731
    lines = [f"| cases | device | aligner s (median / worst) | verdict s | command s | median error | verdicts "
             f"(same as {base}) | furthest from {base}'s pose |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        verdicts = ", ".join(f"{n} {v}" for v, n in r["verdicts"].items())
        same = f" ({r['verdicts_as_base']} same)" if verdicts and r["device"] != base else ""
        apart = "" if r["device"] == base or r["worst_apart_deg"] is None else \
            f"{r['worst_apart_deg']:.2g} deg / {r['worst_apart_mm']:.2g} mm"
        error = "" if r["median_deg"] is None else f"{r['median_deg']:.4f} deg / {r['median_mm']:.3f} mm"
        errors = f" ({r['errors']} errors)" if r["errors"] else ""
        lines.append(f"| {r['kind']}: {r['cases']}{errors} | {r['device']} | {fmt(r['aligner_s'], '.2f')} / "
                     f"{fmt(r['aligner_worst_s'], '.2f')} | {fmt(r['verify_s'], '.2f')} | {fmt(r['wall_s'], '.2f')} | "
                     f"{error} | {verdicts}{same} | {apart} |")
    text = path.read_text() if path.exists() else ""
    head, _, rest = text.partition("<!-- results -->")
    tail = rest.partition("<!-- end results -->")[2]
    path.write_text(head + "<!-- results -->\n" + f"Machine: {machine}.\n\n" + "\n".join(lines)
                    + "\n<!-- end results -->" + tail)


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="step", required=True)
    p = sub.add_parser("prepare", help="read the scenes (needs open3d) into --inputs")
    p.add_argument("--data", type=Path, default=Path("../shared/data"))
    p.add_argument("--inputs", type=Path, default=Path("bench_out/gpu"))
    r = sub.add_parser("run", help="refine every case on every device")
    r.add_argument("--inputs", type=Path, default=Path("bench_out/gpu"))
    r.add_argument("--devices", nargs="+", default=["cuda", "cpu"], help="cpu, cuda or cpu@N (N torch threads); compared with the first cpu's poses")
    r.add_argument("--inits", type=int, default=3, help="inits per PJLab scene and init size (0: no PJLab cases)")
    r.add_argument("--icl-cases", type=int, default=8)
    r.add_argument("--no-verdict", action="store_true", help="the aligner alone (the verdict's edge check needs open3d)")
    r.add_argument("--profile", action="store_true", help="print torch.profiler's table of one case of each kind")
    r.add_argument("--json", type=Path, default=Path("bench_out/gpu/records.json"))
    r.add_argument("--doc", type=Path, default=Path("docs/gpu.md"))
    args = ap.parse_args(argv)
    if args.step == "prepare":
        prepare(args.data, args.inputs)
        return
    from benchmarks.icl_bench import machine

    args.json.parent.mkdir(parents=True, exist_ok=True)
    records = run(args.inputs, args.devices, args.inits, args.icl_cases, not args.no_verdict, args.profile,
                  partial=args.json)
    args.json.write_text(json.dumps(records, indent=1, default=float))
    base = next((d for d in args.devices if d.startswith("cpu")), args.devices[0])
    rows = compare(records, base)
    import torch

    desc = machine() + (f", {torch.cuda.get_device_name()}" if torch.cuda.is_available() else "")
    write_markdown(args.doc, rows, desc, base)
    for row in rows:
        print(json.dumps(row))


if __name__ == "__main__":
    main()
