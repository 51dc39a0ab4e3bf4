"""Fuzzing every command (tests/test_fuzz.py: a short run; `make bench`: docs/reliability.md).

A trial runs one command line on seed files of which one may be mutated (truncated, bytes
flipped, a header count or a value replaced, a wrong type in YAML, another format's bytes), or
with odd argument values or output paths. Each runs in a forked child of a process that has
already imported everything, so a trial costs what the command does, and a crash, a hang or an
allocation that fails cannot take the harness down. A trial is judged:

- crash: an exit code other than 0 and 2 (`run` may end 1 when every photo failed), or a
  traceback on stderr;
- hang: still running at the time limit;
- accepted: exit 0 although the mutation made the input invalid for certain;
- partial: an output exists after exit 2 that did not exist before (or changed);
- overwritten: an input file changed;
- noise: exit 2 with stderr other than one `error:` line (or click's usage message).
"""

from __future__ import annotations

import hashlib
import os
import random
import re
import shutil
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

OUTCOMES = ("crash", "hang", "accepted", "partial", "overwritten", "noise")
NUMBER = re.compile(rb"(?<![A-Za-z_.\d])-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")


@dataclass
class Trial:
    name: str  # what was done, for the report
    argv: list[str]
    inputs: list[Path]  # files that must not change
    outputs: list[Path]  # files or folders the command may write
    invalid: bool = False  # the input is certainly invalid: exit 0 is a failure
    timeout_s: float = 60.0
    serves: bool = False  # pick: a valid start serves until stopped
    kind: str = "valid"  # the class of change, for the report


@dataclass
class Result:
    trial: Trial
    code: int | None
    stderr: str
    seconds: float
    problems: list[str] = field(default_factory=list)


# ---------------------------------------------------------------- seeds


def make_seeds(folder: Path, data: Path | None) -> dict[str, Path]:
    """Seed files: a small synthetic scene (exact truth) and, when present, small real files."""
    from rgbd_gt.synth.generate import SynthConfig, generate
    from rgbd_gt.io import load_scan, read_camera, read_pose
    from rgbd_gt.camera import project
    from rgbd_gt.pose import transform_points
    from rgbd_gt.io.ply import write_ply
    from rgbd_gt.scan import Scan

    folder.mkdir(parents=True, exist_ok=True)
    scene = folder / "scene"
    if not (scene / "scene.json").is_file():
        generate(scene, 3, "small", SynthConfig())
    seeds = {k: scene / n for k, n in [("scan_e57", "scan.e57"), ("scan_ply", "scan.ply"), ("photo", "photo.png"),
                                       ("camera", "camera.yaml"), ("gt", "gt_pose.yaml"), ("init", "init_pose.yaml"),
                                       ("board", "board_corners.csv")]}
    small = folder / "small.ply"  # every 9th point: commands on it take a fraction of a second
    ascii_ply, pairs = folder / "ascii.ply", folder / "pairs.csv"
    scan = load_scan(seeds["scan_ply"]) if not (small.is_file() and ascii_ply.is_file() and pairs.is_file()) else None
    if not small.is_file():
        keep = np.arange(0, len(scan.xyz), 9)
        write_ply(small, Scan(scan.xyz[keep], scan.rgb[keep] if scan.rgb is not None else None,
                              scan.intensity[keep] if scan.intensity is not None else None, origins=scan.origins))
    seeds["scan_small"] = small
    if not ascii_ply.is_file():
        keep = np.arange(0, len(scan.xyz), 97)
        write_ply(ascii_ply, Scan(scan.xyz[keep], scan.rgb[keep] if scan.rgb is not None else None, origins=scan.origins), ascii=True)
    seeds["scan_ascii"] = ascii_ply
    velodyne = folder / "sweep.bin"  # KITTI's headerless layout: x y z reflectance, float32
    if not velodyne.is_file():
        s = scan if scan is not None else load_scan(small)
        keep = np.arange(0, len(s.xyz), 5)
        gray = (s.intensity if s.intensity is not None else s.rgb.mean(axis=1) / 255.0)[keep]
        np.hstack([s.xyz[keep], np.asarray(gray, np.float64)[:, None]]).astype("<f4").tofile(velodyne)
    seeds["scan_bin"] = velodyne
    ouster = folder / "ouster.pcd"  # as Ouster's driver saves a sweep through PCL: padding fields, all named `_`
    if not ouster.is_file():
        s = scan if scan is not None else load_scan(small)
        keep = np.arange(0, len(s.xyz), 5)
        rec = np.zeros(len(keep), [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("p0", "u1", 4), ("intensity", "<f4"),
                                   ("ring", "<u2"), ("p1", "u1", 10)])
        for i, a in enumerate("xyz"):
            rec[a] = s.xyz[keep, i]
        rec["intensity"] = 255 * (s.intensity if s.intensity is not None else s.rgb.mean(axis=1) / 255.0)[keep]
        rec["ring"] = np.arange(len(keep)) % 16
        ouster.write_bytes(
            f"VERSION 0.7\nFIELDS x y z _ intensity ring _\nSIZE 4 4 4 1 4 2 1\nTYPE F F F U F U U\nCOUNT 1 1 1 4 1 1 10\n"
            f"WIDTH {len(keep)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(keep)}\nDATA binary\n".encode() + rec.tobytes())
    seeds["scan_ouster"] = ouster
    if not pairs.is_file():
        cam = read_camera(seeds["camera"])
        T, _ = read_pose(seeds["gt"])
        rng = np.random.default_rng(0)
        xyz = scan.xyz[rng.choice(len(scan.xyz), 4000, replace=False)]
        uv, z = project(cam, transform_points(T, xyz))
        ok = (z > 0) & (uv[:, 0] > 10) & (uv[:, 1] > 10) & (uv[:, 0] < cam.width - 10) & (uv[:, 1] < cam.height - 10)
        rows = np.hstack([uv[ok][:12], xyz[ok][:12]])
        pairs.write_text("u,v,x,y,z\n" + "".join(",".join(f"{v:.6f}" for v in r) + "\n" for r in rows))
    seeds["pairs"] = pairs
    mask = folder / "mask.png"
    if not mask.is_file():
        import cv2

        m = np.zeros(cv2.imread(str(seeds["photo"])).shape[:2], np.uint8)
        m[: m.shape[0] // 5] = 255  # the top fifth ignored
        cv2.imwrite(str(mask), m)
    seeds["mask"] = mask
    xml = folder / "camera.xml"  # the same camera as an OpenCV calibration file
    if not xml.is_file():
        import cv2

        cam = read_camera(seeds["camera"])
        fs = cv2.FileStorage(str(xml), cv2.FILE_STORAGE_WRITE)
        fs.write("camera_matrix", cam.K)
        fs.write("distortion_coefficients", np.asarray(cam.distortion, float).reshape(1, -1))
        fs.write("image_width", cam.width)
        fs.write("image_height", cam.height)
        fs.release()
    seeds["camera_xml"] = xml
    # fast settings: the fuzz is about inputs, not accuracy
    fast = {"levels": 2, "iterations": 3, "max_points": 3000, "min_points": 500, "upsample": 1, "verify": {"repeats": 0}}
    refine_cfg = folder / "refine.yaml"
    refine_cfg.write_text(yaml.safe_dump(fast, sort_keys=False))
    seeds["refine_cfg"] = refine_cfg
    board = {"cols": 9, "rows": 6, "square": 0.05, "points": str(seeds["board"])}
    run_cfg = folder / "run.yaml"
    run_cfg.write_text(yaml.safe_dump({"scan": str(small), "camera": str(seeds["camera"]), "photos": [str(seeds["photo"])],
                                       "output": "run_out", "board": board, "device": "cpu", "refine": fast}, sort_keys=False))
    seeds["run_cfg"] = run_cfg
    # finished runs, export's inputs: `run` on run.yaml, and a stereo rig's shot by refine --bundle
    # (its bundle file with absolute paths, so that a mutant copy elsewhere still finds its files)
    if not (folder / "run_out" / "run.json").is_file():
        _cli(["run", str(run_cfg)], folder)
    seeds["run_dir"] = folder / "run_out"
    rig = folder / "rig_scene"
    if not (rig / "bundle.yaml").is_file():
        _cli(["synth", str(rig), "--size", "small", "--seed", "0", "--rig", "stereo"], folder)
    spec = yaml.safe_load((rig / "bundle.yaml").read_text())
    spec["scan"] = str(rig / spec["scan"])
    for c in spec["cameras"].values():
        c["file"] = str(rig / c["file"])
    for ph in spec["photos"]:
        ph["image"], ph["init"] = str(rig / ph["image"]), str(rig / ph["init"])
    bundle = folder / "bundle.yaml"
    bundle.write_text(yaml.safe_dump(spec, sort_keys=False))
    seeds["bundle"] = bundle
    if not (folder / "bundle_out" / "bundle.json").is_file():
        _cli(["refine", "--bundle", str(bundle), "-o", str(folder / "bundle_out"), "--device", "cpu", "--repeats", "0",
              "--levels", "2", "--iterations", "3"], folder)
    seeds["bundle_dir"] = folder / "bundle_out"
    run_bundle = folder / "run_bundle.yaml"  # run with a bundle file: its photos solved together first
    run_bundle.write_text(yaml.safe_dump({"bundle": str(bundle), "output": "run_bundle_out", "device": "cpu", "refine": fast}))
    run_camera = folder / "run_camera.yaml"  # run that refines one camera over its photos first
    run_camera.write_text(yaml.safe_dump({
        "scan": str(small), "camera": str(seeds["camera"]), "photos": [str(seeds["photo"])], "output": "run_camera_out",
        "init": str(seeds["init"]), "device": "cpu", "refine": {**fast, "refine_intrinsics": "focal"}}))
    seeds.update(run_bundle_cfg=run_bundle, run_camera_cfg=run_camera)
    if data is not None and (data / "lidar_camera/pjlab_1/calib.pcd").is_file():
        pjlab = data / "lidar_camera/pjlab_1"  # a site: a scan with its board, a LiDAR frame with the rig's extrinsic
        site = folder / "site.yaml"
        site.write_text(yaml.safe_dump({
            "output": "site_out", "device": "cpu", "camera": str(seeds["camera"]),
            "board": board, "refine": {**fast, "search_starts": 1},
            "scans": [{"scan": str(small), "photos": [str(seeds["photo"])], "name": "room"},
                      {"scan": str(pjlab / "calib.pcd"), "camera": str(pjlab / "calib.txt"), "init": str(pjlab / "calib.txt"),
                       "photos": [str(pjlab / "calib.jpg")], "name": "street"}]}, sort_keys=False))
        seeds["site_cfg"] = site
    synth_cfg = Path(__file__).resolve().parents[1] / "configs" / "synth.yaml"
    if synth_cfg.is_file():
        seeds["synth_cfg"] = synth_cfg
    if data is not None and data.is_dir() and (data / "lidar_camera/pjlab_1/calib.pcd").is_file():
        rig = folder / "rig.yaml"  # refine --pairs: one LiDAR frame and its photo
        rig.write_text(f"pairs:\n  - scan: {data / 'lidar_camera/pjlab_1/calib.pcd'}\n"
                       f"    image: {data / 'lidar_camera/pjlab_1/calib.jpg'}\n")
        seeds["rig"] = rig
    if data is not None and data.is_dir():
        real = {"pcd": data / "lidar_camera/pjlab_1/calib.pcd", "calib_txt": data / "lidar_camera/pjlab_1/calib.txt",
                "jpg": data / "lidar_camera/pjlab_1/calib.jpg", "e57_real": data / "e57/bunnyInt32.e57",
                "e57_images": data / "e57/tiny_pc_and_images.e57", "board_jpg": data / "checkerboard/left01.jpg",
                # a KITTI frame: a binary_compressed sweep, and gt.json as both camera and pose
                "kitti_pcd": data / "lidar_camera/kitti_00/pcd/000000.pcd", "kitti_png": data / "lidar_camera/kitti_00/img/000000.png",
                "kitti_json": data / "lidar_camera/kitti_00/gt.json"}
        seeds.update({k: p for k, p in real.items() if p.is_file()})
    if "kitti_json" in seeds:  # a drive: two KITTI frames of one rig, solved together
        kitti = data / "lidar_camera/kitti_00"
        frames = [(kitti / f"pcd/{n}.pcd", kitti / f"img/{n}.png") for n in ("000000", "000185")]
        drive_rig = folder / "drive_rig.yaml"
        drive_rig.write_text(yaml.safe_dump({"pairs": [{"scan": str(a), "image": str(b)} for a, b in frames]}))
        drive = folder / "drive.yaml"
        drive.write_text(yaml.safe_dump({
            "camera": str(seeds["kitti_json"]), "init": str(seeds["kitti_json"]), "output": "drive_out", "device": "cpu",
            "refine": {**fast, "search_starts": 1}, "scans": [{"scan": str(a), "photos": [str(b)]} for a, b in frames]},
            sort_keys=False))
        seeds.update(drive_rig=drive_rig, drive_cfg=drive)
    if "calib_txt" in seeds:  # the same rig as livox_camera_calib writes it
        from rgbd_gt.io import read_pose
        from rgbd_gt.pose import invert

        cam, T = read_camera(seeds["calib_txt"], (1920, 1200)), read_pose(seeds["calib_txt"])[0]
        livox = folder / "livox.yaml"
        livox.write_text(f"camera:\n    camera_matrix: {cam.K.ravel().tolist()}\n    dist_coeffs: {list(cam.distortion)}\n")
        matrix = folder / "extrinsic.txt"
        matrix.write_text("".join(",".join(f"{v:g}" for v in row) + "\n" for row in T))
        opencv = folder / "extrinsic.yaml"
        opencv.write_text(f"%YAML:1.0\nExtrinsicMat: !!opencv-matrix\n  rows: 4\n  cols: 4\n  dt: d\n  data: {T.ravel().tolist()}\n")
        # camera and pose in one file, the pose inverted (camera to LiDAR); without Autoware's
        # ReprojectionError, a number no command reads (a word there is no error)
        autoware = folder / "autoware.yaml"
        autoware.write_text(
            "%YAML:1.0\n---\n" + "".join(f"{name}: !!opencv-matrix\n   rows: {m.shape[0]}\n   cols: {m.shape[1]}\n   dt: d\n"
                                         f"   data: {m.ravel().tolist()}\n"
                                         for name, m in (("CameraExtrinsicMat", invert(T)), ("CameraMat", cam.K),
                                                         ("DistCoeff", np.array([cam.distortion])))) +
            f"ImageSize: [{cam.width}, {cam.height}]\nDistModel: plumb_bob\n")
        camchain = folder / "camchain.yaml"  # Kalibr's, with the extrinsic as Oxford Spires adds it
        camchain.write_text(yaml.safe_dump({"cam0": {
            "camera_model": "pinhole", "intrinsics": [cam.fx, cam.fy, cam.cx, cam.cy], "distortion_model": "radtan",
            "distortion_coeffs": list(cam.distortion[:4]), "resolution": [cam.width, cam.height], "T_cam_lidar": T.tolist()}},
            default_flow_style=None))
        seeds.update(livox_yaml=livox, extrinsic_txt=matrix, extrinsic_cv=opencv, autoware=autoware, camchain=camchain)
    return seeds


def _cli(argv: list[str], cwd: Path) -> None:
    """Run a command for a seed; raise when it fails."""
    from rgbd_gt.cli import main

    old = os.getcwd()
    os.chdir(cwd)
    try:
        main(argv)
    except SystemExit as exc:
        if exc.code:
            raise RuntimeError(f"making a fuzz seed: rgbd-gt {' '.join(argv)} exited {exc.code}") from None
    finally:
        os.chdir(old)


# ---------------------------------------------------------------- mutators


def crc32c(data: bytes) -> int:
    """CRC-32C (Castagnoli), the checksum of every E57 page (its last 4 bytes, big-endian)."""
    crc = 0xFFFFFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0x82F63B78 if crc & 1 else 0)
    return crc ^ 0xFFFFFFFF

ODD_NUMBERS = [b"nan", b"inf", b"-inf", b"-1", b"0", b"1e30", b"1e12", b"abc", b"", b"-0.5", b"99999999999999999999"]
CERTAINLY_BAD = {b"nan", b"inf", b"-inf", b"abc", b"", b"1e30", b"99999999999999999999"}
YAML_ODD = [None, "five", [1, 2], {"a": 1}, True, float("nan"), float("inf"), -1, 0, 1e12, "", 123]


def kind_of(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix in (".yaml", ".yml"):  # OpenCV's YAML is not YAML 1.1: its numbers are mutated as text's
        return "text" if path.read_bytes()[:9] == b"%YAML:1.0" else "yaml"
    if suffix in (".csv", ".txt"):
        return "text"
    if suffix == ".json":
        return "json"
    if suffix == ".ply" and path.read_bytes()[:64].find(b"format ascii") >= 0:
        return "text"
    return "binary"


def _header_end(data: bytes) -> int:
    for marker in (b"end_header\n", b"\nDATA "):
        k = data.find(marker)
        if k >= 0:
            return k + len(marker)
    return 0


def mutate(src: Path, dst: Path, rng: random.Random, yaml_keys: set[str] | None = None) -> tuple[str, str, bool]:
    """Write a mutant of `src` to `dst`. Returns (the kind of mutation, what was done, whether the
    result is certainly invalid). `yaml_keys`: the keys whose value must be right (a wrong type
    there is invalid)."""
    data = src.read_bytes()
    kind = kind_of(src)
    choices = ["truncate", "flip", "empty", "garbage", "foreign"]
    if kind == "yaml":
        choices += ["yaml_value"] * 4 + ["number"] * 2 + ["drop_line"]
    elif kind == "text":
        choices += ["number"] * 4 + ["drop_line"]
    elif kind == "json":
        choices += ["number"] * 2
    elif data[:8] == b"ASTM-E57":
        choices += ["e57_xml_number"] * 3
    elif _header_end(data):
        choices += ["header_number"] * 2
    how = rng.choice(choices)
    return (how, *_mutate(how, data, kind, src, dst, rng, yaml_keys))


def _mutate(how: str, data: bytes, kind: str, src: Path, dst: Path, rng: random.Random,
            yaml_keys: set[str] | None) -> tuple[str, bool]:
    headerless = src.suffix.lower() == ".bin"  # KITTI's sweeps: any whole number of plausible returns is one
    if how == "truncate":
        cut = rng.randint(1, max(1, len(data) - 1))
        dst.write_bytes(data[:cut])
        return f"truncated to {cut}/{len(data)} bytes", (kind == "binary" and not (headerless and cut % 16 == 0)) or (
            kind == "json" and cut < len(data.rstrip()))
    if how == "flip":
        buf = bytearray(data)
        n = rng.randint(1, 8)
        for _ in range(n):
            buf[rng.randrange(len(buf))] = rng.randrange(256)
        dst.write_bytes(bytes(buf))
        return f"{n} bytes changed", False
    if how == "empty":
        dst.write_bytes(b"")
        return "empty", not (kind == "yaml" and yaml_keys is CONFIG_KEYS)  # an empty config means the defaults
    if how == "garbage":
        dst.write_bytes(bytes(rng.randrange(256) for _ in range(rng.choice([7, 300, 5000]))))
        return "random bytes", True  # none of these lengths is a whole number of KITTI returns
    if how == "foreign":  # another format's bytes under this name
        other = {".png": b"\xff\xd8\xff\xe0" + bytes(200), ".jpg": b"\x89PNG\r\n\x1a\n" + bytes(200)}.get(
            src.suffix.lower(), b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nend_header\n")
        dst.write_bytes(other)
        return "another format's bytes", not (headerless and len(other) % 16 == 0)
    if how == "e57_xml_number":  # a value in the XML, with the page's checksum made right again
        spans = [m.span(2) for m in re.finditer(rb'<(\w+) type="Float"[^>]*>([^<\s][^<]*)<', data)
                 if m.start(2) % 1024 + (m.end(2) - m.start(2)) <= 1020]
        if not spans:
            dst.write_bytes(data)
            return "unchanged (no XML number)", False
        a, b = rng.choice(spans)
        new = rng.choice([b"nan", b"inf", b"-inf", b"abc", b"-1", b"0", b"1e30"])
        buf = bytearray(data)
        buf[a:b] = new.ljust(b - a)[: b - a] if len(new) <= b - a else new[: b - a]
        page = a - a % 1024
        buf[page + 1020:page + 1024] = crc32c(bytes(buf[page:page + 1020])).to_bytes(4, "big")
        dst.write_bytes(bytes(buf))
        return f"E57 XML number {data[a:b].decode(errors='replace')!r} -> {bytes(buf[a:b]).decode().strip()!r}", \
            bytes(buf[a:b]).strip() in (b"nan", b"inf", b"-inf", b"abc")
    if how == "drop_line":
        lines = data.splitlines(keepends=True)
        k = rng.randrange(len(lines))
        dst.write_bytes(b"".join(lines[:k] + lines[k + 1:]))
        key = lines[k].split(b":")[0].strip().decode(errors="replace")
        required = yaml_keys in (CAMERA_KEYS, POSE_KEYS) and key in yaml_keys - {"distortion"}
        return f"line {k + 1} removed ({key or 'blank'})", required  # a missing field
    if how in ("number", "header_number"):
        end = _header_end(data) if how == "header_number" else len(data)
        start = len(b"%YAML:1.0") if data.startswith(b"%YAML:1.0") else 0  # OpenCV's version line is no value
        spans = [m.span() for m in NUMBER.finditer(data[:end], start)]
        if not spans:
            dst.write_bytes(data)
            return "unchanged (no number)", False
        a, b = rng.choice(spans)
        new = rng.choice(ODD_NUMBERS + ([b"1000000000000", b"-5", b"1e30"] if how == "header_number" else []))
        dst.write_bytes(data[:a] + new + data[b:])
        bad = new in CERTAINLY_BAD and kind not in ("yaml", "json")  # a YAML number may sit in a comment or free
        # metadata, a JSON one in a string
        if how == "header_number":
            line = data[data.rfind(b"\n", 0, a) + 1:data.find(b"\n", a)]
            bad = line.startswith((b"element vertex", b"POINTS", b"WIDTH")) and new in (
                b"1000000000000", b"1e30", b"-5", b"-1", b"abc", b"", b"nan", b"inf", b"-inf", b"99999999999999999999")
        return f"number {data[a:b].decode(errors='replace')!r} at byte {a} -> {new.decode()!r}", bad
    # yaml_value: a leaf replaced by a value of another type
    doc = yaml.safe_load(data.decode(errors="replace"))
    leaves = list(_leaves(doc, ()))
    if not leaves:
        dst.write_bytes(data)
        return "unchanged (no leaf)", False
    path, old = rng.choice(leaves)
    new = rng.choice(YAML_ODD)
    _set(doc, path, new)
    dst.write_text(yaml.safe_dump(doc, sort_keys=False))
    typed_old = "num" if isinstance(old, (int, float)) and not isinstance(old, bool) else type(old).__name__
    typed_new = "num" if isinstance(new, (int, float)) and not isinstance(new, bool) else type(new).__name__
    finite_new = typed_new != "num" or np.isfinite(new)
    wrong_type = typed_old != typed_new and not (old is None or new is None)
    key = ".".join(str(p) for p in path if isinstance(p, str))
    bad = bool(yaml_keys is not None and any(key == k or key.startswith(k + ".") for k in yaml_keys)
               and (wrong_type or not finite_new))
    return f"{key or 'document'}: {old!r} -> {new!r}", bad


def _leaves(doc, path):
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, path + (k,))
    elif isinstance(doc, list) and doc and not all(isinstance(v, (int, float)) for v in doc):
        for k, v in enumerate(doc):
            yield from _leaves(v, path + (k,))
    elif path:
        yield path, doc


def _set(doc, path, value):
    for p in path[:-1]:
        doc = doc[p]
    doc[path[-1]] = value


# ---------------------------------------------------------------- trials

CAMERA_KEYS = {"fx", "fy", "cx", "cy", "width", "height", "distortion"}
POSE_KEYS = {"T_cam_from_scan"}
CONFIG_KEYS = {"levels", "iterations", "max_points", "min_points", "upsample", "verify", "scan", "camera", "photos", "output",
               "board", "refine", "device", "sizes", "board_cols", "board_rows", "square_m", "hfov_deg", "range_noise_m",
               "texel_m", "scans", "bundle", "init", "refine_intrinsics"}


def templates(seeds: dict[str, Path]) -> list[dict]:
    """Command lines over the seeds: {argv with {slot}s, the slots that are inputs, outputs}."""
    s = {k: str(v) for k, v in seeds.items()}
    t = [
        dict(argv=["ingest", s["scan_small"], "-o", "{out}/merged.ply", "--voxel", "0.05"], outs=["merged.ply"]),
        dict(argv=["ingest", s["scan_ascii"], "-o", "{out}/merged.ply"], outs=["merged.ply"]),
        dict(argv=["ingest", s["scan_ouster"], "-o", "{out}/merged.ply"], outs=["merged.ply"]),
        dict(argv=["ingest", s["scan_e57"], "-o", "{out}/merged.ply", "--voxel", "0.1", "--extract-images", "{out}/imgs"],
             outs=["merged.ply", "imgs"]),
        dict(argv=["init-pose", "--scan", s["scan_small"], "--image", s["photo"], "--camera", s["camera"],
                   "--correspondences", s["pairs"], "-o", "{out}/init.yaml", "--report", "{out}/rep"], outs=["init.yaml", "rep"]),
        dict(argv=["init-pose", "--scan", s["scan_small"], "--image", s["photo"], "--camera", s["camera"],
                   "--board-points", s["board"], "-o", "{out}/init.yaml"], outs=["init.yaml"]),
        dict(argv=["refine", "--scan", s["scan_small"], "--image", s["photo"], "--camera", s["camera"], "--init", s["init"],
                   "--config", s["refine_cfg"], "--device", "cpu", "-o", "{out}/pose.yaml"], outs=["pose.yaml"]),
        dict(argv=["refine", "--scan", s["scan_small"], "--image", s["photo"], "--camera", s["camera"], "--init", s["init"],
                   "--config", s["refine_cfg"], "--device", "cpu", "--mask", s["mask"], "--check", s["pairs"],
                   "-o", "{out}/pose.yaml", "--report", "{out}/rep"], outs=["pose.yaml", "rep"]),
        dict(argv=["qa-edges", "--scan", s["scan_small"], "--image", s["photo"], "--camera", s["camera"], "--pose", s["gt"],
                   "--before", s["init"], "-o", "{out}/qa.png"], outs=["qa.png"]),
        dict(argv=["export-depth", "--scan", s["scan_ascii"], "--camera", s["camera_xml"], "--pose", s["gt"],
                   "-o", "{out}/d.exr"], outs=["d.exr"]),
        dict(argv=["export-depth", "--scan", s["scan_bin"], "--camera", s["camera"], "--pose", s["gt"],
                   "-o", "{out}/d.exr"], outs=["d.exr"]),
        dict(argv=["ingest", s["scan_bin"], "-o", "{out}/merged.ply"], outs=["merged.ply"]),
        dict(argv=["export-depth", "--scan", s["scan_small"], "--camera", s["camera"], "--pose", s["gt"],
                   "-o", "{out}/d.exr", "--png16", "{out}/d.png", "--mask", "{out}/m.png"], outs=["d.exr", "d.png", "m.png"]),
        dict(argv=["qa-edges", "--scan", s["scan_small"], "--image", s["photo"], "--camera", s["camera"], "--pose", s["gt"],
                   "-o", "{out}/qa.png", "--json", "{out}/qa.json"], outs=["qa.png", "qa.json"]),
        dict(argv=["overlay", "--scan", s["scan_small"], "--image", s["photo"], "--camera", s["camera"], "--pose", s["gt"],
                   "-o", "{out}/ov.png"], outs=["ov.png", "ov_blend.png"]),
        dict(argv=["pick", "--scan", s["scan_small"], "--image", s["photo"], "--camera", s["camera"], "--no-browser",
                   "-o", "{out}/picks.csv"], outs=["picks.csv"], serves=True),
        dict(argv=["run", s["run_cfg"]], outs=["run_out"], slow=True, own_config=True),
        dict(argv=["run", s["run_bundle_cfg"]], outs=["run_bundle_out"], slow=True, own_config=True),
        dict(argv=["run", s["run_camera_cfg"]], outs=["run_camera_out"], slow=True, own_config=True),
        dict(argv=["export", s["run_dir"], "-o", "{out}/ds", "-f", "plain,colmap,nerfstudio", "--include", "suspect"],
             outs=["ds"]),
        dict(argv=["export", s["bundle_dir"], "-o", "{out}/ds", "-f", "plain,middlebury,kitti", "--include", "suspect"],
             outs=["ds"]),
        dict(argv=["refine", "--bundle", s["bundle"], "-o", "{out}/solved", "--device", "cpu", "--repeats", "0",
                   "--levels", "2", "--iterations", "3"], outs=["solved"], slow=True),
    ]
    if "site_cfg" in s:
        t.append(dict(argv=["run", s["site_cfg"]], outs=["site_out"], slow=True, own_config=True))
    if "synth_cfg" in s:
        t.append(dict(argv=["synth", "{out}/scene", "--size", "small", "--config", s["synth_cfg"]], outs=["scene"], slow=True))
    if "rig" in s:
        t.append(dict(argv=["refine", "--pairs", s["rig"], "--camera", s["calib_txt"], "--init", s["calib_txt"],
                            "--config", s["refine_cfg"], "--search-starts", "1", "--device", "cpu", "-o", "{out}/pose.yaml"],
                      outs=["pose.yaml"], slow=True))
    if "pcd" in s:
        t += [
            dict(argv=["ingest", s["pcd"], "-o", "{out}/merged.ply", "--voxel", "0.2"], outs=["merged.ply"]),
            dict(argv=["qa-edges", "--scan", s["pcd"], "--image", s["jpg"], "--camera", s["calib_txt"], "--pose", s["calib_txt"],
                       "-o", "{out}/qa.png"], outs=["qa.png"]),
            dict(argv=["export-depth", "--scan", s["pcd"], "--image", s["jpg"], "--camera", s["livox_yaml"],
                       "--pose", s["extrinsic_txt"], "-o", "{out}/d.exr"], outs=["d.exr"]),
            dict(argv=["overlay", "--scan", s["pcd"], "--image", s["jpg"], "--camera", s["livox_yaml"],
                       "--pose", s["extrinsic_cv"], "-o", "{out}/ov.png"], outs=["ov.png", "ov_blend.png", "ov_points.png"]),
            dict(argv=["export-depth", "--scan", s["pcd"], "--camera", s["autoware"], "--pose", s["autoware"],
                       "-o", "{out}/d.exr"], outs=["d.exr"]),
            dict(argv=["overlay", "--scan", s["pcd"], "--image", s["jpg"], "--camera", s["camchain"], "--pose", s["camchain"],
                       "-o", "{out}/ov.png"], outs=["ov.png", "ov_blend.png", "ov_points.png"]),
            dict(argv=["ingest", s["e57_real"], "-o", "{out}/merged.ply"], outs=["merged.ply"]),
            dict(argv=["ingest", s["e57_images"], "-o", "{out}/merged.ply", "--extract-images", "{out}/imgs"],
                 outs=["merged.ply", "imgs"]),
            dict(argv=["init-pose", "--scan", s["scan_small"], "--image", s["board_jpg"], "--camera", s["camera"],
                       "--correspondences", s["pairs"], "-o", "{out}/init.yaml"], outs=["init.yaml"]),
        ]
    if "kitti_json" in s:
        t.append(dict(argv=["overlay", "--scan", s["kitti_pcd"], "--image", s["kitti_png"], "--camera", s["kitti_json"],
                            "--pose", s["kitti_json"], "-o", "{out}/ov.png"], outs=["ov.png", "ov_blend.png", "ov_points.png"]))
    if "drive_cfg" in s:
        t += [dict(argv=["run", s["drive_cfg"]], outs=["drive_out"], slow=True, own_config=True),
              dict(argv=["refine", "--pairs", s["drive_rig"], "--camera", s["kitti_json"], "--init", s["kitti_json"],
                         "--config", s["refine_cfg"], "--search-starts", "1", "--device", "cpu", "-o", "{out}/rig.yaml"],
                   outs=["rig.yaml"], slow=True)]
    seed_paths = {str(v) for v in seeds.values()}
    for tpl in t:
        tpl["slots"] = [k for k, a in enumerate(tpl["argv"]) if a in seed_paths]
    return t


PHOTOS = ("photo", "jpg", "kitti_png", "board_jpg")  # the seeds that are photos
READ_BY_EXPORT = {"run.json", "bundle.json", "pose.yaml", "init.yaml", "rig.yaml", "camera.yaml", "intrinsics.json"}  # of a run's files
NEVER_VALID = ("nan", "inf", "-inf", "abc", "", "0x10", "1,2")  # of ODD_ARGS, what no option takes
# no upper bound: 1e20 m of depth means no limit, as 0 does; a color inlier threshold of 1e20
# makes every point an inlier (refine on the synthetic scene: 0.004 deg, 0.3 mm, `ok`)
UNBOUNDED = ("--max-depth", "--beta-max")
ODD_ARGS = ["nan", "inf", "-inf", "-1", "0", "abc", "", "1e308", "-0", "99999999999999999999", "0x10", "1,2"]


def other_photos(seeds: dict[str, Path], photo: Path) -> list[Path]:
    """The seeds' photos of another size than `photo` (their headers' sizes: nothing decoded)."""
    from PIL import Image

    def size(p: Path) -> tuple[int, int]:
        with Image.open(p) as im:
            return im.size

    own = size(photo)
    return [p for k, p in seeds.items() if k in PHOTOS and p != photo and size(p) != own]


def make_trial(k: int, tpls: list[dict], seeds: dict[str, Path], root: Path, rng: random.Random) -> Trial:
    """Trial k: a template with one input mutated, one argument made odd, or an odd output path."""
    tpl = rng.choice(tpls)
    folder = root / f"t{k:04d}"
    folder.mkdir(parents=True)
    argv = [a.replace("{out}", str(folder)) for a in tpl["argv"]]
    if tpl.get("own_config"):  # run writes beside its config: with one shared copy, every later trial would resume the first
        config = folder / Path(argv[tpl["slots"][0]]).name
        shutil.copyfile(argv[tpl["slots"][0]], config)
        argv[tpl["slots"][0]] = str(config)
    outs = [folder / o for o in tpl["outs"]]
    inputs = [Path(argv[i]) for i in tpl["slots"]]
    timeout = 120.0 if tpl.get("slow") else 60.0
    what = rng.choices(["file", "arg", "output"], weights=[6, 2, 2])[0]
    name, invalid, kind = " ".join(a if "/" not in a else Path(a).name for a in argv[:2]), False, "valid"
    if what == "file" and tpl["slots"]:
        i = rng.choice(tpl["slots"])
        src = Path(argv[i])
        dst = folder / ("in_" + src.name)
        others = other_photos(seeds, src) if argv[i - 1] == "--image" else []
        if others and rng.random() < 0.25:
            # a real photo of another size: the camera file is not for it (a sized one by its size;
            # KITTI's and PJLab's K, which have none, put the principal point 35 % or more of
            # another of these photos' size from its centre)
            other = rng.choice(others)
            dst = folder / ("in_" + other.name)
            shutil.copyfile(other, dst)
            how, change, invalid = "another photo", f"{other.name} instead", True
        elif src.is_dir():  # a finished run: a copy with one of the files export reads mutated
            shutil.copytree(src, dst)
            files = sorted(p for p in dst.rglob("*") if p.is_file() and (p.name in READ_BY_EXPORT or {"cameras", ".scan-cache"} & set(p.parts)))
            target = rng.choice(files)
            original = folder / ("orig_" + target.name)  # outside the run: its suffix says how to mutate it
            target.rename(original)
            how, change, invalid = mutate(original, target, rng, CAMERA_KEYS if target.parent.name == "cameras" else
                                          POSE_KEYS if target.name == "pose.yaml" else None)
            original.unlink()
            invalid = invalid and ".scan-cache" not in target.parts  # a broken cache may be made again
            # a run's camera of another size no longer fits its photos (fuzz seed 35: export took it)
            invalid = invalid or (target.parent.name == "cameras" and change.startswith(("width: ", "height: ")))
            change = f"{target.relative_to(dst)}: {change}"
        else:
            keys = None
            if src.suffix in (".yaml", ".yml"):
                keys = CAMERA_KEYS if "camera" in src.name else POSE_KEYS if "pose" in src.name else CONFIG_KEYS
            how, change, invalid = mutate(src, dst, rng, keys)
        kind = f"file: {how}"
        for j in tpl["slots"]:  # a file given for two options (calib.txt: camera and pose) is one file
            if argv[j] == str(src):
                argv[j] = str(dst)
                inputs[tpl["slots"].index(j)] = dst
        name += f" | {src.name}: {change}"
    elif what == "arg":
        opts = [j for j, a in enumerate(argv) if a.startswith("--") and j + 1 < len(argv) and not argv[j + 1].startswith("-")
                and a not in ("--scan", "--image", "--camera", "--pose", "--init", "--config", "--correspondences",
                              "--board-points", "--report", "--extract-images", "--json", "--png16", "--mask")]
        extra = rng.choice(["--levels", "--iterations", "--voxel", "--crop", "--max-depth", "--beta-max", "--square",
                            "--ransac-px", "--max-points", "--repeats", "--scan-index", "--board", "--device",
                            "--search-starts", "--upsample", "--port", "--seed", "--photos", "--size", "--marker", "--workers"])
        how = rng.choice(["value", "value", "add", "unknown", "drop", "command"])
        kind = "unknown command" if how == "command" else f"argument: {how}"
        if how == "value" and opts:
            j = rng.choice(opts)
            val = rng.choice(ODD_ARGS)
            name += f" | {argv[j]} {val!r}"
            invalid = val in NEVER_VALID or (
                val in ("1e308", "99999999999999999999") and argv[j] not in UNBOUNDED) or (
                val in ("-1",) and argv[j] not in ("--max-depth",))
            argv[j + 1] = val
        elif how in ("value", "add"):
            val = rng.choice(ODD_ARGS)
            later = extra in argv  # an option given twice takes its last value (Click's rule)
            argv[1:1] = [extra, val]
            name += f" | added {extra} {val!r}" + (" (given again later)" if later else "")
            invalid = (val in NEVER_VALID or (
                val == "99999999999999999999" and extra not in UNBOUNDED)) and not later
        elif how == "unknown":
            argv.append("--no-such-option")
            name += " | unknown option"
            invalid = True
        elif how == "drop":
            j = rng.choice([j for j, a in enumerate(argv) if a.startswith("-") and a != "--no-browser"] or [0])
            if j:
                name += f" | {argv[j]} left out"
                del argv[j:j + 2]
                invalid = tpl["argv"][j] in ("-o", "--scan", "--image", "--camera", "--pose", "--init")
        else:
            argv[0] = rng.choice(["bogus", "refin", "", "--help-me"])
            name = f"command {argv[0]!r}"
            invalid = True
    elif what == "output":
        o = [j for j, a in enumerate(argv) if a in ("-o", "--json", "--png16", "--mask", "--report", "--extract-images")
             and not (a == "--mask" and argv[0] == "refine")]  # refine's --mask is the photo's mask: an input
        how = rng.choice(["existing folder", "under a file", "missing folder", "extension", "an input", "another output"])
        kind = f"output path: {how}"
        j = rng.choice(o) if o else None
        if j is None:
            pass
        elif how == "existing folder":
            (folder / "adir").mkdir()
            argv[j + 1] = str(folder / "adir")
            invalid = argv[j] not in ("--report", "--extract-images") and argv[:1] != ["export"] and "--bundle" not in argv  # folders they write into
        elif how == "under a file":
            (folder / "afile").write_text("x")
            inputs.append(folder / "afile")
            argv[j + 1] = str(folder / "afile" / Path(argv[j + 1]).name)
            invalid = True
        elif how == "missing folder":
            argv[j + 1] = str(folder / "new" / "deeper" / Path(argv[j + 1]).name)
            outs.append(folder / "new")
        elif how == "extension":
            argv[j + 1] = str(Path(argv[j + 1]).with_suffix(rng.choice([".xyz", ".txt", "", ".png", ".exr"])))
            outs.append(Path(argv[j + 1]))
        elif how == "an input" and inputs:
            argv[j + 1] = str(rng.choice(inputs))
            invalid = True
        elif how == "another output" and len(o) > 1:
            other = rng.choice([i for i in o if i != j])
            argv[j + 1] = argv[other + 1]
            invalid = True
        name += f" | {argv[j] if j is not None else 'output'}: {how}"
    return Trial(name, argv, inputs, outs, invalid, 15.0 if tpl.get("serves") else timeout, bool(tpl.get("serves")), kind)


# ---------------------------------------------------------------- running


def _digest(path: Path) -> str:
    if path.is_dir():  # a run's scan cache may be made again: not an input overwritten
        return "dir:" + ",".join(sorted(f"{p.relative_to(path)}={_digest(p)}" for p in path.rglob("*")
                                        if p.is_file() and ".scan-cache" not in p.relative_to(path).parts))
    if not path.exists():
        return "-"
    h = hashlib.sha1()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _snapshot(folder: Path) -> dict[str, str]:
    return {str(p): _digest(p) for p in folder.rglob("*") if p.is_file()}


def run_trial(trial: Trial, folder: Path, memory_gb: float = 6.0) -> Result:
    """Run one trial in a forked child; judge it."""
    before_in = {p: _digest(p) for p in trial.inputs}
    before = _snapshot(folder)
    existed = {p for p in trial.outputs if p.exists()}
    err_path, out_path = folder / ".stderr", folder / ".stdout"
    start = time.perf_counter()
    pid = os.fork()
    if pid == 0:  # the child: run the command, exit with its code
        code = 1
        try:
            import resource

            limit = int(memory_gb * 2**30)
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
            os.chdir(folder)
            with open(err_path, "wb") as e, open(out_path, "wb") as o:
                os.dup2(e.fileno(), 2)
                os.dup2(o.fileno(), 1)
            from rgbd_gt.cli import main

            try:
                main(trial.argv)
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except BaseException:
                import traceback

                traceback.print_exc()
                code = 1
        finally:
            try:
                sys.stdout.flush()
                sys.stderr.flush()
            finally:
                os._exit(code)
    code = None
    while time.perf_counter() - start < trial.timeout_s:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            code = os.waitstatus_to_exitcode(status)
            break
        if trial.serves and out_path.exists() and b"serving the pick page" in out_path.read_bytes():
            break  # pick started its server: a valid start, stopped here
        time.sleep(0.02)
    if code is None:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    seconds = time.perf_counter() - start
    stderr = err_path.read_text(errors="replace") if err_path.exists() else ""
    stdout = out_path.read_text(errors="replace") if out_path.exists() else ""
    for p in (err_path, out_path):
        p.unlink(missing_ok=True)
    res = Result(trial, code, stderr, seconds)
    served = trial.serves and "serving the pick page" in stdout
    if code is None and not served:
        res.problems.append("hang")
    elif code is not None:
        allowed = (0, 2, 1) if trial.argv[:1] == ["run"] else (0, 2)
        if code not in allowed or "Traceback (most recent call last)" in stderr:
            res.problems.append("crash")
        if code == 0 and trial.invalid:
            res.problems.append("accepted")
        staging_left = any(folder.rglob(".rgbd-gt-*"))
        if code == 2:
            after = _snapshot(folder)
            changed = any(before.get(p) != d for p, d in after.items())
            made = any(p.exists() and p not in existed for p in trial.outputs)
            if changed or made or staging_left:
                res.problems.append("partial")
        elif staging_left:
            res.problems.append("partial")
        if code == 2:
            lines = [ln for ln in stderr.splitlines() if ln.strip()]
            usage = any("Usage:" in ln for ln in lines)
            if not usage and (len(lines) != 1 or not lines[0].startswith("error: ")):
                res.problems.append("noise")
    if any(_digest(p) != d for p, d in before_in.items()):
        res.problems.append("overwritten")
    return res


def fuzz(trials: int, seed: int, root: Path, data: Path | None, log: Callable[[str], None] = lambda s: None,
         commands: list[str] | None = None) -> list[Result]:
    """`trials` seeded trials under `root` (its trials folder emptied first); `commands`: of these
    commands only (default: every one)."""
    import rgbd_gt.cli  # noqa: F401  (imported once here, shared by every forked trial)
    import cv2  # noqa: F401
    import torch  # noqa: F401

    # each trial runs in its own folder: relative paths would break there (make bench's
    # ../shared/data made every real file "not found", and its trials tested only that)
    root, data = root.resolve(), data.resolve() if data is not None else None
    shutil.rmtree(root / "trials", ignore_errors=True)
    # the seeds are made in a child too: this process must not start torch's or OpenMP's thread
    # pools, which a forked child would inherit locked
    pid = os.fork()
    if pid == 0:
        code = 1
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, 1)  # the seed runs' tables: not the fuzz's log
            make_seeds(root / "seeds", data)
            code = 0
        finally:
            os._exit(code)
    if os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) != 0:
        raise RuntimeError("making the fuzz seeds failed")
    seeds = make_seeds(root / "seeds", data)  # made: this only names them
    tpls = [t for t in templates(seeds) if not commands or t["argv"][0] in commands]
    if not tpls:
        raise ValueError(f"no trials of {commands}")
    rng = random.Random(seed)
    results = []
    for k in range(trials):
        trial = make_trial(k, tpls, seeds, root / "trials", rng)
        res = run_trial(trial, root / "trials" / f"t{k:04d}")
        results.append(res)
        log(f"{k:4d} {res.code!s:>4} {res.seconds:5.1f}s {' '.join(res.problems) or 'fine':12s} {trial.name}")
    return results


def counts(results: list[Result]) -> dict[str, int]:
    return {o: sum(o in r.problems for r in results) for o in OUTCOMES}


def write_report(path: Path, results: list[Result], seed: int, seconds: float) -> None:
    """docs/reliability.md: counts per outcome, per command and per kind of change, and every failure."""
    import collections

    c = counts(results)
    lines = ["# Reliability: fuzzing every command", "",
             f"`make bench` runs `python -m benchmarks.fuzz` ({len(results)} trials, seed {seed}, {seconds / 60:.1f} min "
             "on this machine); tests/test_fuzz.py runs a shorter one in CI. How a trial is made and judged: "
             "benchmarks/fuzz.py.", "",
             "| outcome | trials | target |", "|---|---|---|"]
    lines += [f"| {o} | {c[o]} | 0 |" for o in OUTCOMES]
    exits = collections.Counter(("pick serving (stopped)" if r.trial.serves and "hang" not in r.problems else "hang")
                                if r.code is None else str(r.code) for r in results)
    lines += ["", "Exit codes: " + ", ".join(f"{k}: {v}" for k, v in sorted(exits.items())) + " (an exit 1 is allowed only for `run`, its code when every "
              "photo failed).", "",
              "| command | trials | exit 0 | exit 2 | failures |", "|---|---|---|---|---|"]
    by_cmd = collections.defaultdict(list)
    for r in results:
        by_cmd[r.trial.argv[0] if r.trial.argv and not r.trial.name.startswith("command ") else "(unknown command)"].append(r)
    for cmd, rs in sorted(by_cmd.items()):
        lines.append(f"| {cmd} | {len(rs)} | {sum(r.code == 0 for r in rs)} | {sum(r.code == 2 for r in rs)} | "
                     f"{sum(bool(r.problems) for r in rs)} |")
    lines += ["", "| change | trials | certainly invalid | failures |", "|---|---|---|---|"]
    by_kind = collections.defaultdict(list)
    for r in results:
        by_kind[r.trial.kind].append(r)
    for kind, rs in sorted(by_kind.items()):
        lines.append(f"| {kind} | {len(rs)} | {sum(r.trial.invalid for r in rs)} | {sum(bool(r.problems) for r in rs)} |")
    lines += ["", "What a trial is: one command line of the seeds (a small synthetic scene with exact truth, and the "
              "small real files of ../shared/data: a PJLab LiDAR frame with its calibration text and photo, a KITTI frame "
              "(a binary_compressed sweep, gt.json as camera and pose), two E57 "
              "files, a checkerboard photo; `run` on a config of one scan and on a site of two, the synthetic scan with its board "
              "and the LiDAR frame with its rig's extrinsic, a bundle file, one scan whose camera is refined over its photos, and "
              "a drive of two KITTI frames of one rig, each trial on its own copy; `refine --bundle` on a stereo rig's shot; "
              "`refine --pairs` on a PJLab frame and on those two KITTI frames; "
              "`export` of a finished `run` and of that bundle's output, on a copy of the folder with one file export reads "
              "mutated, its scan cache included) with one change: a file mutated (truncated, bytes changed, emptied, random "
              "or another format's bytes, a number, a header count or an E57 XML value replaced with its page checksum "
              "made right, a YAML value of another type, a line removed; or a photo swapped for a real photo of another size, "
              "for which the camera file is not), an odd argument (NaN, inf, negative, huge, "
              "not a number, an unknown or a missing option, an unknown command) or an odd output path (an existing "
              "folder, under a file, in a folder that does not exist, another suffix, an input, another output). "
              "'Certainly invalid' trials (a run's camera file given another width or height among them) must end "
              "with exit 2; the others may end either way but never crash, "
              "hang, leave a partial output or change an input.", "",
              "Decided here: `-o` in a folder that does not exist is created, at the end and only when the command "
              "succeeds, by every command (README, Outputs). A run's damaged scan cache is prepared again (it is a cache, "
              "not an input); export's and refine --bundle's `-o` are folders, an existing one is written into."]
    failed = [r for r in results if r.problems]
    lines += ["", "## Failures", ""]
    lines += [f"- {', '.join(r.problems)}: `{r.trial.name}` (exit {r.code}): {r.stderr.strip().splitlines()[-1][:200] if r.stderr.strip() else ''}"
              for r in failed] or ["None."]
    path.write_text("\n".join(lines) + "\n")


def main(argv: list[str] | None = None) -> int:
    """python -m benchmarks.fuzz --trials N [--seed S] [--root DIR] [--data DIR] [--json F] [--report F]"""
    import argparse
    import json

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=600)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--root", type=Path, default=Path("bench_out/fuzz"))
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--json", type=Path, help="write each trial's outcome here")
    ap.add_argument("--report", type=Path, help="write the Markdown report here (docs/reliability.md)")
    ap.add_argument("--command", action="append", help="fuzz this command only (repeatable; default: every one)")
    ap.add_argument("--quiet", action="store_true")
    args = ap.parse_args(argv)
    start = time.perf_counter()
    results = fuzz(args.trials, args.seed, args.root, args.data if args.data.is_dir() else None,
                   log=(lambda s: None) if args.quiet else (lambda s: print(s, flush=True)), commands=args.command)
    seconds = time.perf_counter() - start
    if args.json:
        args.json.write_text(json.dumps([{"name": r.trial.name, "argv": r.trial.argv, "code": r.code, "invalid": r.trial.invalid, "kind": r.trial.kind,
                                          "problems": r.problems, "stderr": r.stderr[-2000:], "seconds": r.seconds}
                                         for r in results], indent=1))
    if args.report:
        write_report(args.report, results, args.seed, seconds)
    print(f"{len(results)} trials in {seconds:.0f} s: {counts(results)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
