"""The joint solve (`refine --bundle`, rgbd_gt/align/bundle.py) against per-photo refines, on
synthetic scenes with exact truth: one camera whose file is wrong shared by 8 photos, a stereo
rig over 4 shots, and a bundle with one photo whose zoom differs from the camera file's (the
cross-photo evidence).

    python -m benchmarks.bundle [--seeds 0 1] [--out docs/bundle.md]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

WORK = Path("bench_out/bundle")
AGREEMENT = 0.2  # configs/refine.yaml's bundle_agreement
SILHOUETTES = 0.1  # a `depth_edge_ratio` for the rig's row with silhouettes left out (off by default: the Notes)
SCANNER_BLUR = 0.7  # `synth`'s scanner_color_blur_cells for the rig scenes colored through the scanner's camera
MODE = "focal+principal+k1k2"


def scene(seed: int, photos: int, rig: str | None = None, size: str = "small", blur: float = 0.0) -> Path:
    """The synthetic scene of seed and size with `photos` photos (shots), made once under WORK;
    blur: its scan's colors blurred over the scanner's grid (`SynthConfig.scanner_color_blur_cells`)."""
    from rgbd_gt.config import load_config
    from rgbd_gt.synth.generate import SynthConfig, generate

    d = WORK / f"seed{seed}_{photos}{'_' + rig if rig else ''}{'' if size == 'small' else '_' + size}{f'_blur{blur:g}' if blur else ''}"
    if not (d / "scene.json").exists():
        cfg = dataclasses.replace(load_config(SynthConfig, None, "synth.yaml"), scanner_color_blur_cells=blur)
        generate(d, seed, size, cfg, photos=photos, rig=rig)
    return d


@dataclasses.dataclass
class Shot:
    image: np.ndarray
    camera: object
    T_init: np.ndarray
    T_true: np.ndarray
    name: str
    camera_index: int = 0
    shot: int | None = None


def objective(scan, shot: Shot, mode: str, camera=None, agreement: float = 0.0, device: str = "cpu",
              silhouettes: float = 0.0):
    """The photometric objective of the shot's photo against the scan (points, rgb, normals) on
    device, as refine builds it (`make_aligner`); agreement: the bundle's agreement weight (rigs);
    silhouettes: `RefineConfig.depth_edge_ratio`."""
    from rgbd_gt.align.config import RefineConfig

    cfg = dataclasses.replace(RefineConfig(), refine_intrinsics=mode, bundle_agreement=agreement, depth_edge_ratio=silhouettes)
    return _made(scan, scan.rgb, shot, camera or shot.camera, cfg, device)


def nid_objective(scan, shot: Shot, device: str = "cpu"):
    """The nid objective of the shot's photo against the scan's intensity alone (its colors
    dropped: an uncolored scanner), as refine builds it for such a scan (`make_aligner`), on device."""
    from rgbd_gt.align.config import RefineConfig

    return _made(scan, scan.intensity.reshape(-1, 1), shot, shot.camera, dataclasses.replace(RefineConfig(), objective="nid"), device)


def _made(scan, colors: np.ndarray, shot: Shot, camera, cfg, device: str):
    from rgbd_gt.align.refine import RefineInputs, make_aligner

    return make_aligner(RefineInputs(scan.xyz, colors, shot.image, camera, shot.T_init, None, scan=scan), cfg, device).objective


def errors(T: np.ndarray, shot: Shot) -> tuple[float, float]:
    from rgbd_gt.pose import rotation_error_deg, translation_error_m

    return translation_error_m(T, shot.T_true) * 1e3, rotation_error_deg(T, shot.T_true)


def singles(scan, shots: list[Shot], mode: str, cameras: list | None = None, nid: bool = False) -> tuple[list[dict], float]:
    """Each photo refined alone: per photo its errors and camera corrections; the seconds of all.
    nid: against the scan's intensity alone (`nid_objective`; mode "none")."""
    from rgbd_gt.align.aligner import Aligner

    rows, start = [], time.perf_counter()
    for k, s in enumerate(shots):
        obj = nid_objective(scan, s) if nid else objective(scan, s, mode, cameras[k] if cameras else None)
        r = Aligner(obj).refine(s.T_init)
        rows.append({"err": errors(r.T_cam_from_scan, s), "q": r.intrinsics, "T": r.T_cam_from_scan})
    return rows, time.perf_counter() - start


def joint(scan, shots: list[Shot], mode: str, camera=None, rig: int = 0, photos_out: list | None = None,
          agreement: float = 0.0, nid: bool = False, device: str = "cpu", silhouettes: float = 0.0):
    """The bundle of the shots on device; returns (result, seconds); photos_out gets the bundle's
    photos. nid: against the scan's intensity alone (`nid_objective`; mode "none"); silhouettes:
    as `objective`."""
    from rgbd_gt.align.bundle import Bundle, BundlePhoto

    start = time.perf_counter()
    photos = [BundlePhoto(nid_objective(scan, s, device) if nid else objective(scan, s, mode, camera, agreement, device, silhouettes), s.T_init,
                          s.camera_index, s.shot, s.name) for s in shots]
    result = Bundle(photos, max(s.camera_index for s in shots) + 1, rig).solve()
    if photos_out is not None:
        photos_out += photos
    return result, time.perf_counter() - start


def camera_checks(result, photos, shots) -> list[float | None]:
    """Per photo the verdict's camera check against the camera as solved (`verify.camera_check`,
    shared): the relative focal change when freed, or None where it does not flag the photo."""
    from types import SimpleNamespace

    from rgbd_gt.align.aligner import Aligner
    from rgbd_gt.align.config import VerifyConfig
    from rgbd_gt.align.verify import _View, camera_check
    from rgbd_gt.camera import without_distortion

    cfg, out = VerifyConfig(), []
    for k, (p, s) in enumerate(zip(photos, shots)):
        aligner = Aligner(p.objective)
        q = result.q[p.camera] if p.objective.free else None
        view = _View(aligner.visible_scan_points(result.poses[k], q), without_distortion(s.camera))
        ev = camera_check(aligner, SimpleNamespace(T_cam_from_scan=result.poses[k], intrinsics=q), view, cfg, shared=True)
        flagged = ev["focal_sigmas"] > cfg.camera_sigmas and abs(ev["focal_change"]) > cfg.camera_min_change
        out.append(ev["focal_change"] if flagged else None)
    return out


def camera_sigmas(result, truth, bad) -> tuple[np.ndarray, np.ndarray]:
    """|error| / 1-sigma of camera 0's focal, cx, cy (px), k1 and k2 in a bundle solved from the
    file `bad`, against `truth`: with the aligner's 1-sigmas and with those the bundle states."""
    from rgbd_gt.camera import corrected

    cam = corrected(bad, result.q[0])
    err = np.abs([cam.fx - truth.fx, cam.cx - truth.cx, cam.cy - truth.cy, cam.distortion[0] - truth.distortion[0],
                  cam.distortion[1] - truth.distortion[1]])
    px = np.array([bad.fx, bad.fx, bad.fy, 1.0, 1.0])  # q's focal and principal point are in units of the focal length
    return err / (result.q_sigma[0][:5] * px), err / (result.stated_q_sigma(0)[:5] * px)


def load(d: Path, rig: bool = False) -> tuple[object, list[Shot]]:
    from rgbd_gt.io import load_scan, read_camera, read_pose
    from rgbd_gt.io.image import read_image
    from rgbd_gt.render.normals import with_normals

    import yaml

    listed = yaml.safe_load((d / "bundle.yaml").read_text())
    cams = {name: read_camera(d / c["file"]) for name, c in listed["cameras"].items()}
    shots = []
    for p in listed["photos"]:
        init = d / p["init"]
        shots.append(Shot(read_image(d / p["image"]), cams[p["camera"]], read_pose(init)[0],
                          read_pose(d / p["init"].replace("init_pose", "gt_pose"))[0], p["image"],
                          list(cams).index(p["camera"]), p.get("shot") if rig else None))
    return with_normals(load_scan(d / "scan.ply")), shots


def wrong(camera, scale: float = 1.02, dk1: float = 0.05):
    dist = list(camera.distortion) or [0.0] * 5
    dist[0] += dk1
    return dataclasses.replace(camera, fx=camera.fx * scale, fy=camera.fy * scale, distortion=tuple(dist))


def zoomed(image: np.ndarray, camera, scale: float) -> np.ndarray:
    """The photo a camera of focal x scale would take (same lens otherwise): enlarged about the
    principal point."""
    import cv2

    M = np.array([[scale, 0, (1 - scale) * camera.cx], [0, scale, (1 - scale) * camera.cy]])
    return cv2.warpAffine(image, M, (image.shape[1], image.shape[0]), flags=cv2.INTER_CUBIC)


def cv2_shift(image: np.ndarray, px: float) -> np.ndarray:
    """The photo moved px pixels to the right (edge pixels repeated)."""
    import cv2

    M = np.array([[1.0, 0.0, px], [0.0, 1.0, 0.0]])
    return cv2.warpAffine(image, M, (image.shape[1], image.shape[0]), flags=cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def stats(errs: list[tuple[float, float]]) -> str:
    mm, deg = np.array([e[0] for e in errs]), np.array([e[1] for e in errs])
    return f"{np.median(mm):.2f} mm, {np.median(deg):.4f} deg | {mm.max():.2f} mm, {deg.max():.4f} deg"


def rig_errors(T_rl: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(baseline error mm, relative rotation error deg) of a T_right_from_left."""
    from rgbd_gt.pose import invert, rotation_error_deg

    return ((np.linalg.norm(invert(T_rl)[:3, 3]) - np.linalg.norm(invert(truth)[:3, 3])) * 1e3,
            rotation_error_deg(T_rl, truth))


def icl_section(folder: Path) -> list[str]:
    """ICL-NUIM: frame 2's depth and colors as the scan, frames 0, 1, 3, 4 as the photos, each
    from frame 2's pose (the paper's init, 24-50 mm and 0.75-1.5 deg off): per photo against
    the bundle, with the true camera and with a file 2 % off in focal."""
    from benchmarks.icl import ICL_CAMERA, frame_cloud, read_color, read_trajectory
    from rgbd_gt.pose import invert
    from rgbd_gt.scan import Scan

    poses = read_trajectory(folder / "trajectory.log")
    xyz, rgb, _ = frame_cloud(folder, 2)
    scan = Scan(xyz=xyz, rgb=rgb)
    shots = [Shot(read_color(folder, j), ICL_CAMERA, invert(poses[2]), invert(poses[j]), f"frame {j}") for j in (0, 1, 3, 4)]
    off = dataclasses.replace(ICL_CAMERA, fx=ICL_CAMERA.fx * 1.02, fy=ICL_CAMERA.fy * 1.02)
    rows = []
    for label, mode, cam, solve in (("per photo", "none", None, "single"), ("bundle", "none", None, "joint"),
                                    ("bundle, focal shared", "focal", None, "joint"),
                                    ("per photo, focal", "focal", off, "single"), ("bundle, focal shared", "focal", off, "joint")):
        if solve == "single":
            res, s = singles(scan, shots, mode, [cam or ICL_CAMERA] * len(shots))
            errs, focal = [r["err"] for r in res], [r["q"][0] for r in res] if mode != "none" else None
        else:
            r, s = joint(scan, shots, mode, cam)
            errs, focal = [errors(T, sh) for T, sh in zip(r.poses, shots)], [r.q[0, 0]] if mode != "none" else None
        fe = "-" if focal is None else ", ".join(f"{(1 + f) * (cam or ICL_CAMERA).fx / ICL_CAMERA.fx * 100 - 100:+.2f}%" for f in focal)
        rows.append(f"| {label} | {'2 % off' if cam is not None else 'true'} | {stats(errs)} | {fe} | {s:.1f} |")
        print(rows[-1], flush=True)
    return ["## ICL-NUIM: 4 frames against frame 2's depth", "",
            "The paper's setting (docs/benchmark.md) with the photos as they are: the scan is frame 2's noisy depth with "
            "its colors, the photos frames 0, 1, 3 and 4, each refined from frame 2's pose.", "",
            "| solve | camera file | pose error, median | pose error, worst | focal error (per photo, or shared) | aligner s |",
            "|---|---|---|---|---|---|", *rows, ""]


def stereo_rows(seeds: list[int], size: str) -> list[str]:
    """The stereo table's rows for the scenes of `seeds` at `size`: each photo alone, the bundle
    with its rig, and the bundle with the agreement term; then the same scan's intensity alone
    (nid): each photo alone and the bundle with its rig."""
    from rgbd_gt.io import read_pose

    blurred = size == "small"  # the rows on scans colored through the scanner's camera: small scenes only
    acc = {k: [] for k in ("single", "joint", "agree", "silhouettes", "nid single", "nid joint")
           + (("blur agree", "blur silhouettes") if blurred else ())}
    rig = {k: [] for k in acc}
    secs = {k: 0.0 for k in acc}
    for seed in seeds:
        d = scene(seed, 4, "stereo", size)
        scan, shots = load(d, rig=True)
        T_rl = read_pose(d / "rig_gt.yaml")[0]
        for key, nid in (("single", False), ("nid single", True)):
            rows, s = singles(scan, shots, "none", nid=nid)
            secs[key] += s
            acc[key] += [r["err"] for r in rows]
            by = {(sh.shot, sh.camera_index): r["T"] for sh, r in zip(shots, rows)}
            rig[key] += [rig_errors(by[(k, 1)] @ np.linalg.inv(by[(k, 0)]), T_rl) for k in range(4)]
        solves = [("joint", 0.0, False, 0.0), ("agree", AGREEMENT, False, 0.0), ("silhouettes", AGREEMENT, False, SILHOUETTES),
                  ("nid joint", 0.0, True, 0.0)]
        if blurred:
            solves += [("blur agree", AGREEMENT, False, 0.0), ("blur silhouettes", AGREEMENT, False, SILHOUETTES)]
            blur_scan = load(scene(seed, 4, "stereo", size, SCANNER_BLUR), rig=True)[0]  # the same photos and truth
        for key, weight, nid, edges in solves:
            result, s = joint(blur_scan if key.startswith("blur") else scan, shots, "none", rig=2, agreement=weight,
                              nid=nid, silhouettes=edges)
            secs[key] += s
            acc[key] += [errors(T, sh) for T, sh in zip(result.poses, shots)]
            rig[key].append(rig_errors(result.rig[1], T_rl))
        print(size, seed, {k: stats(v) for k, v in acc.items()}, rig, flush=True)

    def rig_text(rows):
        b, r = np.abs([x[0] for x in rows]), np.array([x[1] for x in rows])
        return f"{np.median(b):.2f} / {b.max():.2f} mm | {np.median(r):.4f} / {r.max():.4f} deg"

    names = {"single": "per photo", "joint": "bundle (rig)",
             "agree": f"bundle (rig) with the agreement term, weight {AGREEMENT} (the default)",
             "silhouettes": f"the same, silhouettes left out (`depth_edge_ratio: {SILHOUETTES}`)",
             "nid single": "intensity only: per photo (nid, its wide search)", "nid joint": "intensity only: bundle (rig, nid)",
             "blur agree": f"scan colored through the scanner's camera ({SCANNER_BLUR} cells): bundle (rig) with the agreement term",
             "blur silhouettes": f"the same, silhouettes left out (`depth_edge_ratio: {SILHOUETTES}`)"}
    return [f"| {size} | {names[k]} | {stats(acc[k])} | {rig_text(rig[k])} | {secs[k] / len(seeds):.1f} |" for k in acc]


def main(argv: list[str] | None = None) -> None:
    from rgbd_gt.align.config import VerifyConfig
    from rgbd_gt.align.verify import bundle_reasons
    from benchmarks import write_keeping

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    ap.add_argument("--out", type=Path, default=Path("docs/bundle.md"))
    ap.add_argument("--icl", type=Path, default=Path("../shared/data/icl_nuim_livingroom1"),
                    help="ICL-NUIM frames (the section on them is left out when absent)")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    lines = ["# Several photos in one solve (`refine --bundle`)", "",
             "Made by `python -m benchmarks.bundle`: small synthetic scenes (640x480) with exact truth, seeds "
             f"{', '.join(map(str, args.seeds))}. Pose errors against the truth: median | worst over the photos of all "
             "seeds. Aligner time only (no verdicts), on this machine's CPU.", ""]

    # 1. one camera, 8 photos, its file 2% off in focal and 0.05 off in k1
    acc = {k: [] for k in ("true", "single", "joint")}
    qs = {k: [] for k in ("single", "joint")}
    secs = {k: 0.0 for k in ("true", "single", "joint")}
    truths, sigmas = [], []
    for seed in args.seeds:
        scan, shots = load(scene(seed, 8))
        truth = shots[0].camera
        bad = wrong(truth)
        rows, s = singles(scan, shots, "none")
        secs["true"] += s
        acc["true"] += [r["err"] for r in rows]
        rows, s = singles(scan, shots, MODE, [bad] * len(shots))
        secs["single"] += s
        acc["single"] += [r["err"] for r in rows]
        qs["single"] += [(r["q"], truth, bad) for r in rows]
        result, s = joint(scan, shots, MODE, bad)
        secs["joint"] += s
        acc["joint"] += [errors(T, sh) for T, sh in zip(result.poses, shots)]
        qs["joint"].append((result.q[0], truth, bad))
        sigmas.append(camera_sigmas(result, truth, bad))
        truths.append(truth)
        print(seed, {k: stats(v) for k, v in acc.items()}, secs, flush=True)

    def cam(rows):
        from rgbd_gt.camera import corrected

        fe = [abs(corrected(bad_, q).fx / tr.fx - 1) * 100 for q, tr, bad_ in rows]
        ke = [abs(corrected(bad_, q).distortion[0] - tr.distortion[0]) for q, tr, bad_ in rows]
        return f"{np.median(fe):.3f}% / {max(fe):.3f}% | {np.median(ke):.4f} / {max(ke):.4f}"

    n = 8 * len(args.seeds)
    lines += ["## One camera, 8 photos, its file 2 % off in focal and 0.05 off in k1", "",
              f"Per seed 8 photos of one camera from places 0.15-0.4 m apart ({n} photos in all). `{MODE}` refined "
              "per photo (today's `refine --refine-intrinsics`) or shared by all 8 (the bundle).", "",
              "| solve | camera file | pose error, median | pose error, worst | focal error, median / worst | k1 error, median / worst | aligner s per 8 photos |",
              "|---|---|---|---|---|---|---|",
              f"| per photo, camera held | true | {stats(acc['true'])} | - | - | {secs['true'] / len(args.seeds):.1f} |",
              f"| per photo, `{MODE}` | 2 % and k1 off | {stats(acc['single'])} | {cam(qs['single'])} | {secs['single'] / len(args.seeds):.1f} |",
              f"| bundle, `{MODE}` shared | 2 % and k1 off | {stats(acc['joint'])} | {cam(qs['joint'])} | {secs['joint'] / len(args.seeds):.1f} |",
              "", f"The bundle costs {secs['joint'] / secs['single']:.2f}x the 8 per-photo refines of the same mode and "
              f"{secs['joint'] / secs['true']:.2f}x those with the camera held.", "",
              "The 1-sigmas the bundle states for the shared camera (cameras/NAME.yaml: focal, cx, cy, k1, k2) against the "
              "truth, |error| / 1-sigma over the seeds' " + str(sum(len(a) for a, _ in sigmas)) + " values: " +
              "; ".join(f"{what} median {np.median(v):.1f}, within 1 sigma {np.sum(v <= 1)}, within 3 sigma {np.sum(v <= 3)}"
                        for what, v in (("the aligner's (Laplace)", np.concatenate([a for a, _ in sigmas])),
                                        ("as stated (the photos' 8 x 8 tiles as the samples where wider)",
                                         np.concatenate([b for _, b in sigmas])))) + ".", ""]

    # 2. a stereo rig, 4 shots, on the small scenes and on the default-size ones
    lines += ["## A stereo rig, 4 shots", "",
              "`synth --rig stereo --photos 4`: a 0.12 m baseline, the right camera turned by a few tenths of a degree, "
              "with its own lens and color response; both camera files true. Per photo: each of the 8 photos alone, the "
              "rig then taken per shot from its two poses. Bundle: the rig's relative pose shared by the 4 shots, "
              "initialised (no prior) from the shots' own refines as `Bundle._initial` takes them. Small: 640x480 photos of a scan 0.15 deg apart; "
              "default: 1280x960 photos of a scan 0.1 deg apart (`synth`'s default size). Intensity only: the same scan "
              "with its colors dropped (its synthetic laser intensity), solved with nid (the Notes below). Silhouettes left out: "
              "the points on the photos' foreground silhouettes not compared on the finest level (`depth_edge_ratio`; off by "
              "default, as it costs ICL-NUIM a third of its accuracy: the Notes). Scan colored through the scanner's camera (small "
              f"scenes): the same scenes, photos and truth, the scan's colors blurred over the scanner's own grid by {SCANNER_BLUR} "
              "cells across depth edges (`synth`'s `scanner_color_blur_cells`), so that they mix at the scanner's silhouettes as "
              "a real scanner's camera mixes them.", "",
              "| size | solve | pose error, median | pose error, worst | baseline error, median / worst | relative rotation error, median / worst | aligner s |",
              "|---|---|---|---|---|---|---|"]
    for size in ("small", "default"):
        lines += stereo_rows(args.seeds, size)
    lines += [""]

    # 2b. a shot that disagrees with the rig
    rows_rig = []
    for seed in args.seeds:
        scan, shots = load(scene(seed, 4, "stereo"), rig=True)
        k = next(i for i, sh in enumerate(shots) if sh.shot == 2 and sh.camera_index == 1)
        other = next(sh for sh in shots if sh.shot == 3 and sh.camera_index == 1)
        shifted = cv2_shift(shots[k].image, 2.0)
        for label, image in (("shot 2's right photo is shot 3's", other.image), ("shot 2's right photo moved 2 px", shifted)):
            group = list(shots)
            group[k] = dataclasses.replace(shots[k], image=image)
            result, _ = joint(scan, group, "none", rig=2, agreement=AGREEMENT)
            ev = result.evidence
            bad = [i for i, sh in enumerate(group) if sh.shot == 2]
            good = [i for i in range(len(group)) if i not in bad]
            flagged = [group[i].name for i in range(len(group)) if bundle_reasons(ev[i], VerifyConfig())]
            rows_rig.append((seed, label, max(ev[i]["freed_from_rig_sigmas"] for i in good),
                             [ev[i]["freed_from_rig_sigmas"] for i in bad], max(ev[i]["residual_vs_others"] for i in good),
                             [ev[i]["residual_vs_others"] for i in bad], max(ev[i]["leave_one_out_sigmas"] or 0 for i in good),
                             ev[bad[0]]["leave_one_out_sigmas"], flagged))
            print(rows_rig[-1], flush=True)
    lines += ["## A shot that disagrees with the rig", "",
              "The stereo scenes above, with shot 2's right photo replaced: by shot 3's (a frame mixed up), or by itself "
              "moved 2 px to the right (the rig turned by 0.25 deg for that shot, as a camera knocked or a frame out of "
              "sync would). The other shots' maximum against shot 2's photos (left, right). Freed from the rig: the "
              "Newton step of the photo's own pose away from the rig, in its sigmas; leave one shot out: the rig "
              "re-solved without the shot.", "",
              "| seed | shot 2 | freed from the rig, other shots (max) | shot 2 (left, right) | residual vs others, other shots (max) | shot 2 | leave one shot out, others (max) | shot 2 | suspect by the cross-photo evidence |",
              "|---|---|---|---|---|---|---|---|---|"]
    for seed, label, fg, fb, rg, rb, lg, lb, flagged in rows_rig:
        lines.append(f"| {seed} | {label} | {fg:.1f} | {fb[0]:.1f}, {fb[1]:.1f} | {rg:.2f} | {rb[0]:.2f}, {rb[1]:.2f} | "
                     f"{lg:.1f} | {lb:.1f} | {', '.join(flagged) or 'none'} |")
    lines.append("")

    # 3. the cross-photo evidence: one photo of 8 taken with a focal 2% longer than the file's
    rows3 = []
    for seed in args.seeds:
        scan, shots = load(scene(seed, 8))
        odd = dataclasses.replace(shots[-1], image=zoomed(shots[-1].image, shots[-1].camera, 1.02))
        for label, mode, group in (("focal shared", "focal", shots[:-1] + [odd]),
                                   ("camera held", "none", shots[:-1] + [odd])):
            made: list = []
            result, _ = joint(scan, group, mode, photos_out=made)
            ev = result.evidence
            loo = [e.get("leave_one_out_sigmas") for e in ev]
            flags = camera_checks(result, made, group)
            rows3.append((seed, label, loo[:-1], loo[-1], [e["residual_vs_others"] for e in ev],
                          errors(result.poses[-1], group[-1]), flags))
            print(rows3[-1], flush=True)
    lines += ["## The cross-photo evidence: one photo zoomed 2 %", "",
              "8 photos of one camera; the last enlarged 2 % about the principal point (the photo a focal 2 % longer "
              "takes) but declared with the same camera file. Leave-one-out: the shared parameters re-solved without "
              "the photo (linearised), and how far its pose then moves, in its sigmas (none: nothing is shared). "
              "Residual scale: the photo's robust residual scale over the median of the others'.", "",
              "| seed | bundle | leave-one-out sigmas, the 7 others (max) | the zoomed photo | residual scale vs others, others (max) | the zoomed photo | its pose error | camera check flags (focal change when freed) |",
              "|---|---|---|---|---|---|---|---|"]
    for seed, label, others, odd_loo, resid, err, flags in rows3:
        o = [x for x in others if x is not None]
        flagged = ", ".join(f"{'the zoomed photo' if k == len(flags) - 1 else f'photo {k}'} {f:+.2%}"
                            for k, f in enumerate(flags) if f is not None) or "none"
        loo_text = f"{max(o):.1f} | {odd_loo:.1f}" if o else "- | -"
        lines.append(f"| {seed} | {label} | {loo_text} | {max(resid[:-1]):.2f} | {resid[-1]:.2f} | "
                     f"{err[0]:.1f} mm, {err[1]:.3f} deg | {flagged} |")
    lines.append("")
    if args.icl is not None and (args.icl / "trajectory.log").exists():
        lines += icl_section(args.icl)
    lines += [f"{time.perf_counter() - start:.0f} s in all.", ""]
    write_keeping(args.out, "\n".join(lines), "\n## Notes")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
