"""The verdict measured on a labelled set (`make bench` -> docs/trust.md).

Right results: ICL-NUIM i±1 and i±2 pairs and synthetic scenes refined from their inits, where
they land within 2 mm and 0.05 deg of the truth. Wrong results made on purpose: the photo of
another scene, the photo mirrored, its tiles shuffled, the init 20-50 cm and 5-15 deg away, the
scan cropped to a sliver of the photo, most of the photo masked, the real LiDAR scenes wherever
refine lands more than 0.3 deg from the reference, and right photos refined with a camera file
1-3% off in focal length (issue 48: the blind spot of a verdict that trusts the camera file), as
are KITTI's and Waymo's drives solved as one rig, as `run` solves them. Cases whose outcome
decides the label (far inits, slivers, masks) are right or wrong by the same rules; between the
two they are left out. Every third case is held out of the threshold choice and reported apart.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import cv2
import numpy as np

from rgbd_gt.align.config import RefineConfig, VerifyConfig
from rgbd_gt.camera import Camera, project
from rgbd_gt.scan import Scan
from rgbd_gt.pose import apply_update, rotation_error_deg, transform_points, translation_error_m
from rgbd_gt.render.normals import with_normals

RIGHT_MM, RIGHT_DEG = 2.0, 0.05  # a right result: within both
WRONG_MM, WRONG_DEG = 5.0, 0.1  # a wrong one: beyond either (the ICL benchmark's success limits)
LIDAR_WRONG_DEG = 0.3
ALWAYS_WRONG = ("other scene", "mirrored", "tiles shuffled", "wrong camera")  # a wrong camera's depth is wrong anyway


@dataclass
class TrustCase:
    name: str
    source: str  # icl | synthetic | lidar
    kind: str  # right | other scene | mirrored | tiles shuffled | far init | sliver | masked | lidar
    scan: Scan
    colors: np.ndarray
    photo: np.ndarray
    camera: Camera
    T_init: np.ndarray
    T_true: np.ndarray  # the truth (the reference extrinsic for LiDAR)
    ignore: np.ndarray | None = None
    more: list = dataclasses.field(default_factory=list)  # a drive's other frames (`RefineInputs`), solved as one rig


def label(case_kind: str, source: str, err_mm: float, err_deg: float) -> str | None:
    """'right', 'wrong' or None (between the two: left out of the table)."""
    if case_kind in ALWAYS_WRONG:
        return "wrong"
    if source == "lidar":
        return "wrong" if err_deg > LIDAR_WRONG_DEG else None
    if err_mm <= RIGHT_MM and err_deg <= RIGHT_DEG:
        return "right"
    if err_mm > WRONG_MM or err_deg > WRONG_DEG:
        return "wrong"
    return None


# -- the ways to make a wrong result ----------------------------------------------------------------
def shuffled_tiles(photo: np.ndarray, rng: np.random.Generator, n: int = 4) -> np.ndarray:
    h, w = photo.shape[0] // n * n, photo.shape[1] // n * n
    tiles = [photo[r * h // n:(r + 1) * h // n, c * w // n:(c + 1) * w // n] for r in range(n) for c in range(n)]
    order = rng.permutation(len(tiles))
    rows = [np.concatenate([tiles[order[r * n + c]] for c in range(n)], 1) for r in range(n)]
    out = photo.copy()
    out[:h, :w] = np.concatenate(rows, 0)
    return out


def far_init(T: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """T moved 20-50 cm in a random direction and turned 5-15 deg about a random axis."""
    a, b = rng.normal(size=3), rng.normal(size=3)
    return apply_update(T, np.r_[a / np.linalg.norm(a) * np.radians(rng.uniform(5, 15)),
                                 b / np.linalg.norm(b) * rng.uniform(0.2, 0.5)])


def sliver(scan: Scan, camera: Camera, T: np.ndarray, rng: np.random.Generator, fraction: float = 0.08) -> Scan:
    """The scan cropped to the points that the true camera sees in a vertical strip of the photo."""
    uv, z = project(camera, transform_points(T, scan.xyz))
    u0 = rng.uniform(0.1, 0.9 - fraction) * camera.width
    keep = (z > 0) & (uv[:, 0] >= u0) & (uv[:, 0] < u0 + fraction * camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    return scan.subset(keep)


def mostly_masked(shape: tuple[int, int], rng: np.random.Generator, keep: float = 0.12) -> np.ndarray:
    """(H, W) bool, True (ignored) everywhere but a random window of `keep` of the area."""
    h, w = shape
    kh, kw = int(h * np.sqrt(keep)), int(w * np.sqrt(keep))
    r, c = rng.integers(0, h - kh), rng.integers(0, w - kw)
    mask = np.ones((h, w), bool)
    mask[r:r + kh, c:c + kw] = False
    return mask


def perturbed(T: np.ndarray, rng: np.random.Generator, deg: float, m: float) -> np.ndarray:
    a, b = rng.normal(size=3), rng.normal(size=3)
    return apply_update(T, np.r_[a / np.linalg.norm(a) * np.radians(deg), b / np.linalg.norm(b) * m])


# -- the cases -----------------------------------------------------------------------------------------
def icl_cases(folder: Path, other_photo: np.ndarray | None, rng: np.random.Generator) -> Iterator[TrustCase]:
    from benchmarks.depth import frame_grid_scan
    from benchmarks.icl import ICL_CAMERA, make_cases

    scans: dict[int, Scan] = {}
    cases = make_cases(folder, offsets=(1, 2), effects_per_pair=2, seed=11)
    for c in cases:
        if c.i not in scans:
            scans[c.i] = with_normals(frame_grid_scan(folder, c.i, "noisy"))
        s = scans[c.i]
        yield TrustCase(f"icl {c.name}", "icl", "right", s, s.rgb, c.photo, ICL_CAMERA, c.T_init, c.T_true)
    for k, c in enumerate(cases[::4]):  # one in four pairs gives each kind of wrong case
        s = scans[c.i]
        base = dict(source="icl", scan=s, colors=s.rgb, camera=ICL_CAMERA, T_init=c.T_init, T_true=c.T_true)
        variants = [("mirrored", dict(photo=np.ascontiguousarray(c.photo[:, ::-1]))),
                    ("tiles shuffled", dict(photo=shuffled_tiles(c.photo, rng))),
                    ("far init", dict(photo=c.photo, T_init=far_init(c.T_true, rng))),
                    ("sliver", dict(photo=c.photo, scan=sliver(s, ICL_CAMERA, c.T_true, rng))),
                    ("masked", dict(photo=c.photo, ignore=mostly_masked(c.photo.shape[:2], rng)))]
        if other_photo is not None:
            variants.append(("other scene", dict(photo=other_photo)))
        for kind, change in variants[k % 2::2]:  # half of the kinds per pair, alternating
            args = {**base, **change}
            if kind == "sliver":
                args["colors"] = args["scan"].rgb
            yield TrustCase(f"icl {c.name} {kind}", kind=kind, **args)


def synthetic_scene(folder: Path, seed: int) -> Path:
    """The small synthetic scene of `seed` with two photos, made once into folder/seed<seed>."""
    from rgbd_gt.config import load_config
    from rgbd_gt.synth.generate import SynthConfig, generate

    d = folder / f"seed{seed}"
    if not (d / "photo_1.png").exists():
        generate(d, seed, "small", load_config(SynthConfig, None, "synth.yaml"), photos=2)
    return d


def synthetic_cases(folder: Path, seeds: list[int], other_photo: np.ndarray | None,
                    rng: np.random.Generator) -> Iterator[TrustCase]:
    from rgbd_gt.io import load_scan, read_camera, read_pose
    from rgbd_gt.io.image import read_image

    for seed in seeds:
        d = synthetic_scene(folder, seed)
        s = with_normals(load_scan(d / "scan.ply"))
        photo, cam = read_image(d / "photo.png"), read_camera(d / "camera.yaml")
        T_true, T_init = read_pose(d / "gt_pose.yaml")[0], read_pose(d / "init_pose.yaml")[0]
        base = dict(source="synthetic", scan=s, colors=s.rgb, camera=cam, T_init=T_init, T_true=T_true)
        yield TrustCase(f"synthetic {seed}", kind="right", photo=photo, **base)
        yield TrustCase(f"synthetic {seed} photo_1", kind="right", photo=read_image(d / "photo_1.png"),
                        **{**base, "T_init": read_pose(d / "init_pose_1.yaml")[0], "T_true": read_pose(d / "gt_pose_1.yaml")[0]})
        variants = [("mirrored", dict(photo=np.ascontiguousarray(photo[:, ::-1]))),
                    ("tiles shuffled", dict(photo=shuffled_tiles(photo, rng))),
                    ("far init", dict(photo=photo, T_init=far_init(T_true, rng))),
                    ("sliver", dict(photo=photo, scan=sliver(s, cam, T_true, rng))),
                    ("masked", dict(photo=photo, ignore=mostly_masked(photo.shape[:2], rng)))]
        if other_photo is not None and other_photo.shape == photo.shape:
            variants.append(("other scene", dict(photo=other_photo)))
        for kind, change in variants:
            args = {**base, **change}
            if kind == "sliver":
                args["colors"] = args["scan"].rgb
            yield TrustCase(f"synthetic {seed} {kind}", kind=kind, **args)


def lidar_cases(folder: Path, rng: np.random.Generator, per_scene: int = 3) -> Iterator[TrustCase]:
    from benchmarks.lidar import pjlab_scenes, refine_inputs

    for sc in pjlab_scenes(folder):
        for k in range(per_scene):
            # what refine takes: the points in view of the init, from the prepared sweep (where a
            # sweep in ring order gets the ring steps of the ring-edge term and check)
            inputs = refine_inputs(sc, perturbed(sc.T_ref, rng, 1.0, 0.10))
            yield TrustCase(f"lidar {sc.name} #{k}", "lidar", "lidar", inputs.scan, inputs.colors, sc.photo, sc.camera,
                            inputs.T_init, sc.T_ref)


def focal_off(camera: Camera, rng: np.random.Generator) -> Camera:
    """camera with its focal length 1-3% off, either way."""
    f = 1 + rng.choice([-1, 1]) * rng.uniform(0.01, 0.03)
    return dataclasses.replace(camera, fx=camera.fx * f, fy=camera.fy * f)


def wrong_camera_cases(icl: Path | None, synth_dir: Path, seeds: list[int]) -> Iterator[TrustCase]:
    """Right photos with a camera file whose focal length is 1-3% off (either way): the pose
    absorbs most of it (the camera slides along its axis) and lands tens of millimetres off."""
    from benchmarks.icl import ICL_CAMERA, make_cases
    from rgbd_gt.io import load_scan, read_camera, read_pose
    from rgbd_gt.io.image import read_image

    rng = np.random.default_rng(48)  # a stream of its own: the other cases stay as they were

    for seed in seeds:
        d = synthetic_scene(synth_dir, seed)
        s = with_normals(load_scan(d / "scan.ply"))
        cam = read_camera(d / "camera.yaml")
        for suffix in ("", "_1"):
            yield TrustCase(f"synthetic {seed}{suffix} wrong camera", "synthetic", "wrong camera", s, s.rgb,
                            read_image(d / f"photo{suffix}.png"), focal_off(cam, rng), read_pose(d / f"init_pose{suffix}.yaml")[0],
                            read_pose(d / f"gt_pose{suffix}.yaml")[0])
    if icl is not None:
        from benchmarks.depth import frame_grid_scan

        for c in make_cases(icl, offsets=(1, 2), effects_per_pair=2, seed=11)[::4]:
            s = with_normals(frame_grid_scan(icl, c.i, "noisy"))
            yield TrustCase(f"icl {c.name} wrong camera", "icl", "wrong camera", s, s.rgb, c.photo, focal_off(ICL_CAMERA, rng),
                            c.T_init, c.T_true)


def drive_camera_cases(folder: Path, per_drive: int = 2) -> Iterator[TrustCase]:
    """The drives with their own calibrations (KITTI's 19 frames, Waymo's 10) solved as one rig,
    as `run` solves them, from 1 deg / 10 cm off the reference with a camera file 1-3% off in
    focal length: the LiDAR path's wrong camera, which every frame shares."""
    from benchmarks.lidar import DRIVES, drive_scenes, refine_inputs

    rng = np.random.default_rng(50)  # a stream of its own, as the photos' wrong cameras have
    for drive in DRIVES:
        if not (folder / drive / "gt.json").exists():
            continue
        scenes = drive_scenes(folder / drive)
        for k in range(per_drive):
            T_init, camera = perturbed(scenes[0].T_ref, rng, 1.0, 0.10), focal_off(scenes[0].camera, rng)
            inputs = [refine_inputs(dataclasses.replace(s, camera=camera), T_init) for s in scenes]
            yield TrustCase(f"lidar {drive} #{k} wrong camera", "lidar", "wrong camera", inputs[0].scan, inputs[0].colors,
                            scenes[0].photo, camera, T_init, scenes[0].T_ref, more=inputs[1:])


# -- running and judging -----------------------------------------------------------------------------
def run_case(case: TrustCase, cfg: RefineConfig) -> dict:
    """Refine and verify one case; its errors, label, evidence and times."""
    from rgbd_gt.align.refine import RefineInputs, refine_verified
    from rgbd_gt.errors import InputError

    inputs = RefineInputs(case.scan.xyz, case.colors, case.photo, case.camera, case.T_init, case.ignore, case.scan)
    t = time.perf_counter()
    try:
        result, v = refine_verified(inputs, cfg, "cpu", more=case.more)
    except InputError as exc:  # nothing to align: the command's error, no pose at all
        return {"name": case.name, "source": case.source, "kind": case.kind, "error": str(exc)}
    total = time.perf_counter() - t
    err_mm = translation_error_m(result.T_cam_from_scan, case.T_true) * 1e3
    err_deg = rotation_error_deg(result.T_cam_from_scan, case.T_true)
    return {"name": case.name, "source": case.source, "kind": case.kind, "err_mm": err_mm, "err_deg": err_deg,
            "label": label(case.kind, case.source, err_mm, err_deg), "verdict": v.verdict, "reasons": v.reasons,
            "evidence": v.evidence, "refine_s": result.seconds, "verify_s": v.seconds, "total_s": total}


def collect(data: Path, work: Path, log: Callable[[str], None] = print, seeds=(0, 1, 2), cfg: RefineConfig | None = None) -> list[dict]:
    """Every case's record (bench_out/trust/cases.json keeps them for re-judging)."""
    from rgbd_gt.io.image import read_image

    cfg = cfg or RefineConfig()
    rng = np.random.default_rng(2026)
    synth_dir = work / "synthetic"
    other_for_icl = read_image(synthetic_scene(synth_dir, seeds[0]) / "photo.png")  # ICL's "other scene"
    icl = data / "icl_nuim_livingroom1"
    other_for_synth = cv2.imread(str(icl / "color_00004.jpg"))[:, :, ::-1].copy() if icl.is_dir() else None
    sources = []
    if icl.is_dir():
        sources.append(icl_cases(icl, other_for_icl, rng))
    sources.append(synthetic_cases(synth_dir, list(seeds), other_for_synth, rng))
    if (data / "lidar_camera").is_dir():
        sources.append(lidar_cases(data / "lidar_camera", rng))
    sources.append(wrong_camera_cases(icl if icl.is_dir() else None, synth_dir, list(seeds)))
    if (data / "lidar_camera").is_dir():  # last: the cases before keep their held-out thirds
        sources.append(drive_camera_cases(data / "lidar_camera"))
    records = []
    for source in sources:
        for case in source:
            rec = run_case(case, cfg)
            rec["held_out"] = len(records) % 3 == 2
            records.append(rec)
            log(f"{len(records):3d} {rec['name']:32s} " + (f"error: {rec['error']}" if "error" in rec else
                f"{rec['err_mm']:9.2f} mm {rec['err_deg']:7.3f} deg {str(rec['label']):5s} -> {rec['verdict']:7s} "
                f"{rec['refine_s']:.2f}+{rec['verify_s']:.2f} s  {'; '.join(rec['reasons'])[:120]}"))
    return records


def rejudge(records: list[dict], cfg: VerifyConfig) -> list[dict]:
    """The records with verdicts re-made from their evidence by other thresholds."""
    from rgbd_gt.align.verify import decide

    out = []
    for r in records:
        if "evidence" in r:
            verdict, reasons = decide(r["evidence"], cfg)
            r = {**r, "verdict": verdict, "reasons": reasons}
        out.append(r)
    return out


def confusion(records: list[dict]) -> dict[str, int]:
    """Counts of right/wrong x ok/flagged; an input error (no pose written) counts as flagged."""
    c = {"right ok": 0, "right flagged": 0, "wrong ok": 0, "wrong flagged": 0, "left out": 0}
    for r in records:
        lab = "wrong" if "error" in r else r["label"]
        if lab is None:
            c["left out"] += 1
        else:
            c[f"{lab} {'ok' if r.get('verdict') == 'ok' else 'flagged'}"] += 1
    return c


def run_trust_benchmark(data: Path, out_dir: Path, work: Path, log: Callable[[str], None] = print) -> list[dict]:
    from rgbd_gt.io.atomic import atomic_output

    records = collect(data, work, log)
    with atomic_output(work / "cases.json") as tmp:
        tmp.write_text(json.dumps(records, indent=1, default=float))
    write_markdown(out_dir / "trust.md", records, VerifyConfig())
    return records


def _row(name: str, c: dict) -> str:
    return f"| {name} | {c['right ok']} | {c['right flagged']} | {c['wrong ok']} | {c['wrong flagged']} | {c['left out']} |"


def write_markdown(path: Path, records: list[dict], cfg: VerifyConfig) -> None:
    from benchmarks.icl_bench import machine
    from rgbd_gt.io.atomic import atomic_output

    chosen = [r for r in records if not r["held_out"]]
    held = [r for r in records if r["held_out"]]
    icl_pairs = [r for r in records if r["source"] == "icl" and r["kind"] == "right"]
    icl_right = [r for r in icl_pairs if r.get("label") == "right"]
    icl_ok = sum(r["verdict"] == "ok" for r in icl_right)
    timed = [r for r in records if "refine_s" in r and r.get("label") == "right"]
    refine_s = np.array([r["refine_s"] for r in timed])
    verify_s = np.array([r["verify_s"] for r in timed])
    lines = [
        "# Trust: the verdict on a labelled set",
        "",
        "Made by `make bench` (`python -m benchmarks.trust`, benchmarks/trust.py). The second half of",
        "this file (from docs/trust-method.md) says what each number means and how the thresholds were chosen.",
        "",
        "Right: refined within 2 mm and 0.05 deg of the truth. Wrong: the photo of another scene, mirrored,",
        "its tiles shuffled, a camera file 1-3% off in focal length (photos, and KITTI's and Waymo's drives",
        "solved as one rig; always wrong), and far inits, slivers,",
        "masked photos and real LiDAR frames",
        "wherever refine ends more than 5 mm or 0.1 deg from the truth (LiDAR: 0.3 deg from the",
        "reference). Cases between right and wrong are left out. Flagged: `suspect` or `failed` (or the",
        "command's own error, which writes no pose). Every third case was held out of the threshold choice.",
        "",
        "| cases | right, ok | right, flagged | wrong, ok | wrong, flagged | left out |",
        "|---|---|---|---|---|---|",
        _row("chosen on", confusion(chosen)),
        _row("held out", confusion(held)),
        _row("all", confusion(records)),
        "",
        f"ICL-NUIM i±1 and i±2 pairs: {icl_ok} of {len(icl_right)} right results are `ok` "
        f"({icl_ok / max(len(icl_right), 1):.0%}; {len(icl_pairs)} pairs refined, {len(icl_right)} landed right).",
        "",
        "Per kind of case (all cases):",
        "",
        "| source | kind | cases | right | wrong | left out | ok | suspect | failed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    groups: dict[tuple[str, str], list[dict]] = {}
    for r in records:
        groups.setdefault((r["source"], r["kind"]), []).append(r)
    for (source, kind), rs in groups.items():
        lab = ["wrong" if "error" in r else r["label"] for r in rs]
        ver = ["failed" if "error" in r else r["verdict"] for r in rs]
        lines.append(f"| {source} | {kind} | {len(rs)} | {lab.count('right')} | {lab.count('wrong')} | {lab.count(None)} | "
                     f"{ver.count('ok')} | {ver.count('suspect')} | {ver.count('failed')} |")
    lines += [
        "",
        "## Cost of the evidence",
        "",
        f"On the {len(timed)} right results: refine (the aligner) median {np.median(refine_s):.2f} s, the verification",
        f"median {np.median(verify_s):.2f} s (ratio of medians {np.median(verify_s) / np.median(refine_s):.2f}; "
        f"largest ratio {np.max(verify_s / refine_s):.2f}).",
        "",
        "## Evidence by label (chosen cases)",
        "",
        "| evidence | right: min .. max | wrong: min .. max | threshold (suspect / failed) |",
        "|---|---|---|---|",
    ]
    for name, get, thr in EVIDENCE_ROWS(cfg):
        for_label = {}
        for lab in ("right", "wrong"):
            vals = [get(r["evidence"]) for r in chosen if r.get("label") == lab and "evidence" in r]
            vals = [v for v in vals if v is not None and np.isfinite(v)]
            for_label[lab] = f"{min(vals):.3g} .. {max(vals):.3g}" if vals else "-"
        lines.append(f"| {name} | {for_label['right']} | {for_label['wrong']} | {thr} |")
    flagged_right = [r for r in records if r.get("label") == "right" and r["verdict"] != "ok"]
    wrong_ok = [r for r in records if r.get("label") == "wrong" and r.get("verdict") == "ok"]
    lines += ["", "## Right results that were flagged", ""]
    lines += [f"- {r['name']} ({r['err_mm']:.2f} mm, {r['err_deg']:.3f} deg): {r['verdict']}: {'; '.join(r['reasons'])}"
              for r in flagged_right] or ["none"]
    lines += ["", "## Wrong results that were `ok`", ""]
    lines += [f"- {r['name']} ({r['err_mm']:.1f} mm, {r['err_deg']:.3f} deg)" for r in wrong_ok] or ["none"]
    lines += ["", "## Every case", "", "| case | held out | error mm | error deg | label | verdict | refine s | verify s | reasons |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        if "error" in r:
            lines.append(f"| {r['name']} | {'yes' if r['held_out'] else ''} | - | - | wrong | error | - | - | {r['error']} |")
        else:
            lines.append(f"| {r['name']} | {'yes' if r['held_out'] else ''} | {r['err_mm']:.2f} | {r['err_deg']:.3f} | "
                         f"{r['label'] or 'left out'} | {r['verdict']} | {r['refine_s']:.2f} | {r['verify_s']:.2f} | "
                         f"{'; '.join(r['reasons'])} |")
    lines += ["", f"Machine: {machine()}.", ""]
    method = Path(__file__).resolve().parents[1] / "docs" / "trust-method.md"
    if method.is_file():
        lines += ["---", "", method.read_text()]
    with atomic_output(path) as tmp:
        tmp.write_text("\n".join(lines))


def EVIDENCE_ROWS(cfg: VerifyConfig):  # noqa: N802 - a table, not a function to call elsewhere
    return [
        ("edge ratio (1 = chance)", lambda e: e["edges"]["edge_ratio"], f"< {cfg.edge_ratio_ok} / < {cfg.edge_ratio_failed}"),
        ("repeat spread (px)", lambda e: e.get("repeatability", {}).get("spread_px"), f"> {cfg.spread_ok_px} / > {cfg.spread_failed_px}"),
        ("repeat spread across the photo (px)", lambda e: e.get("repeatability", {}).get("spread_photo_px"), f"> {cfg.spread_ok_px} / -"),
        ("sharpness: smallest rise", lambda e: e.get("sharpness", {}).get("min_rise"), f"< {cfg.sharpness_ok} / -"),
        ("sharpness: median rise", lambda e: e.get("sharpness", {}).get("median_rise"), f"- / < {cfg.sharpness_failed}"),
        ("1-sigma image motion (px)", lambda e: e["uncertainty"]["image_px"], f"> {cfg.sigma_ok_px} / > {cfg.sigma_failed_px}"),
        ("1-sigma translation (mm)", lambda e: e["uncertainty"]["translation_mm"], "-"),
        ("1-sigma rotation (deg)", lambda e: e["uncertainty"]["rotation_deg"], "-"),
        ("condition number", lambda e: e["uncertainty"]["condition"], "-"),
        ("change from init (px)", lambda e: e["change_from_init"]["image_px"], "-"),
        ("camera check: focal change (%)", lambda e: abs(e["camera"]["focal_change"]) * 100 if "camera" in e else None,
         f"> {cfg.camera_min_change * 100:g} (and the next) / -"),
        ("camera check: focal change in sigmas", lambda e: e["camera"]["focal_sigmas"] if "camera" in e else None,
         f"> {cfg.camera_sigmas:g} (and the last) / -"),
    ]


def main(argv: list[str] | None = None) -> None:
    import argparse

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--out", type=Path, default=Path("docs"))
    ap.add_argument("--work", type=Path, default=Path("bench_out/trust"))
    ap.add_argument("--rejudge", action="store_true", help="re-make the verdicts of --work/cases.json with today's thresholds")
    args = ap.parse_args(argv)
    if args.rejudge:
        records = rejudge(json.loads((args.work / "cases.json").read_text()), VerifyConfig())
        write_markdown(args.out / "trust.md", records, VerifyConfig())
    else:
        records = run_trust_benchmark(args.data, args.out, args.work)
    for name, recs in (("chosen", [r for r in records if not r["held_out"]]), ("held out", [r for r in records if r["held_out"]])):
        print(name, confusion(recs))


if __name__ == "__main__":
    main()
