"""What a finished run holds, as plain data: per scan its photos with their poses, cameras,
covariances and verdicts, and a rig's relative poses. Two kinds of folder: a `run`'s OUTPUT
(run.json) and a `refine --bundle` output (bundle.json: several cameras, rigs)."""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError, read_yaml


@dataclass
class Shot:
    """One photo of the run and what export needs of it."""

    name: str  # its folder's name in the run (the photo's stem), unique in the run
    image: Path
    camera: Camera  # as the run solved it (a shared or bundle camera) or as its file said
    camera_name: str
    camera_file: Path  # what the camera was read from, for the messages
    T: np.ndarray  # (4, 4) T_cam_from_scan
    covariance: np.ndarray  # (6, 6) of the pose update (`align.aligner.RefineResult.covariance`)
    verdict: str
    reasons: list[str]
    pose_file: Path
    camera_sigma: dict = field(default_factory=dict)  # {focal_px, cx_px, cy_px}: 1-sigma; {} taken as exact
    shot: int | None = None  # a rig's shot
    mask: Path | None = None
    evidence: dict = field(default_factory=dict)


@dataclass
class Source:
    """One scan's part of a run: its file, its photos, the rig when the photos came from one."""

    name: str
    scan: Path
    folder: Path  # where its photos' folders lie
    photos: list[Shot]
    rig: dict | None = None  # rig.yaml: reference, relative {camera: {T_cam_from_reference, baseline_m, sigma}}
    missing: dict[str, str] = field(default_factory=dict)  # photos without a refined pose: why (summary.csv's error)
    scan_key: dict | None = None  # the scan file's `prepared.file_key`, where checking it took one


def read_run(folder: Path, stale_missing: bool = False, known: dict[Path, dict] | None = None) -> list[Source]:
    """The scans of a finished `run` (OUTPUT/run.json) or `refine --bundle` output
    (bundle.json) in `folder`, every photo that has a refined pose. A photo whose scan, photo or
    camera file changed since its pose was solved (`_changed`) is an error, or with stale_missing
    (the run's own page, after a rerun that refused that photo) missing, with why. known: files'
    `file_key`s the caller took (the run, of its scans), used where still of the file as it is."""
    from rgbd_gt.prepared import still_of

    folder = Path(folder)
    file_keys = {Path(p): k for p, k in (known or {}).items() if still_of(Path(p), k)}
    if (folder / "bundle.json").is_file() and not (folder / "run.json").is_file():
        try:
            return [_bundle_source(folder, Path(_json(folder / "bundle.json")["bundle"]), stale_missing=stale_missing,
                                   file_keys=file_keys)]
        except (KeyError, TypeError, AttributeError) as exc:
            raise InputError(f"not a bundle record rgbd-gt wrote ({_why(exc)})", folder / "bundle.json") from None
    if not (folder / "run.json").is_file():
        raise InputError("not a finished run: it holds neither run.json (rgbd-gt run) nor bundle.json "
                         "(rgbd-gt refine --bundle)", folder)
    record = _json(folder / "run.json")
    scans = record.get("scans")
    if (folder / "bundle.json").is_file() and not any(isinstance(e, dict) and "bundle" in e for e in scans or []):
        raise InputError("holds both run.json (rgbd-gt run) and bundle.json (rgbd-gt refine --bundle): two runs "
                         "wrote into one folder; give each its own", folder)
    try:
        return _run_sources(folder, record, stale_missing, file_keys)
    except (KeyError, TypeError, AttributeError) as exc:
        raise InputError(f"not a run record rgbd-gt wrote ({_why(exc)})", folder / "run.json") from None


def _why(exc: Exception) -> str:
    return f"no {exc}" if isinstance(exc, KeyError) else str(exc)


def _run_sources(folder: Path, record: dict, stale_missing: bool, file_keys: dict[Path, dict]) -> list[Source]:
    from rgbd_gt.io import read_camera
    from rgbd_gt.io.image import read_image

    sources, errors = [], _errors(folder / "summary.csv")
    for entry in record["scans"]:
        if "photos" not in entry:
            raise InputError("run.json lists no photos (made by an older rgbd-gt): run it again", folder / "run.json")
        out = folder / entry.get("folder", ".")
        if "bundle" in entry:  # its photos solved together (run's `bundle:`), with their cameras as solved
            sources.append(_bundle_source(out, Path(entry["bundle"]), entry.get("name", "bundle"), errors, stale_missing,
                                          file_keys))
            continue
        camera_file = Path(entry["camera"])
        shared, sigma = out / "camera.yaml", {}
        if shared.is_file():  # the run's joint solve of the camera (refine_intrinsics)
            camera_file = shared
            cam, s = read_camera(shared), _json(out / "intrinsics.json").get("shared_sigma") or []
            # q's focal and principal point are in units of the focal length (as bundle_step's cameras/ files)
            sigma = {key: float(v) * f for key, v, f in zip(("focal_px", "cx_px", "cy_px"), s, (cam.fx, cam.fx, cam.fy))
                     if v is not None and np.isfinite(v)}
        photos, missing = [], {}
        camera = None
        for image in map(Path, entry["photos"]):
            pose, made = out / image.stem / "pose.yaml", out / image.stem / "init.yaml"  # init.yaml: `steps.made_from`
            keys = read_yaml(made) if pose.is_file() and made.is_file() else {}
            if not isinstance(keys, dict):
                raise InputError("not a pose file rgbd-gt wrote (no keys)", made)
            stale = _changed(keys, image.stem, {"photo": image, "camera": Path(entry["camera"]), "scan": Path(entry["scan"])},
                             file_keys, made)
            if stale is not None and not stale_missing:
                raise stale
            if pose.is_file() and stale is None:
                if camera is None:  # a calibration text or JSON file has no size: the photos' (as run's job_camera)
                    camera = read_camera(camera_file, lambda: read_image(image).shape[1::-1], image)
                photos.append(_shot(image.stem, image, camera, "camera", camera_file, pose, sigma))
            else:
                missing[image.stem] = errors.get(image.name) or entry.get("error") or str(stale or "no refined pose")
        sources.append(Source(entry.get("name", "scan"), Path(entry["scan"]), out, photos, missing=missing,
                              scan_key=file_keys.get(Path(entry["scan"]))))
    return sources


def _is_sha1(value) -> bool:
    return isinstance(value, str) and re.fullmatch("[0-9a-f]{40}", value) is not None


def _changed(keys: dict, photo: str, files: dict[str, Path], file_keys: dict[Path, dict], record: Path) -> InputError | None:
    """The error when one of `files` ({kind: path}) is not the file that photo's pose was solved
    from: the SHA-1 recorded beside it (keys' KIND_sha1 in `record`: `steps.made_from` in a run
    photo's init.yaml, bundle.json's) differs, so that a camera file calibrated again, a photo or
    a scan replaced, is not exported with a pose solved for the old one (or one naming a damaged
    record, whose SHA-1 is none); else None. file_keys: the files' `file_key`s taken so far,
    shared by the photos (and the scan's by its preparation)."""
    from rgbd_gt.prepared import file_key
    from rgbd_gt.steps import made_from_other

    for kind, path in files.items():
        sha1 = keys.get(f"{kind}_sha1")
        if sha1 is None:
            continue
        if not _is_sha1(sha1):
            # a damaged record, not a changed file: saying the file changed would send the user the wrong way
            return InputError(f"{kind}_sha1: not a SHA-1 ({sha1!r:.50})", record)
        if path not in file_keys:
            try:
                file_keys[path] = file_key(path)
            except OSError as exc:
                raise InputError(f"cannot read ({exc.strerror or exc})", path) from None
    kind = made_from_other(keys, {f"{kind}_sha1": file_keys[path]["sha1"] for kind, path in files.items() if path in file_keys})
    if kind is None:
        return None
    return InputError(f"changed since photo {photo} was solved from it (the {kind} then had SHA-1 "
                      f"{str(keys[kind + '_sha1'])[:12]}): solve it again, or put that {kind} back", files[kind])


def _bundle_source(folder: Path, bundle: Path, name: str = "bundle", errors: dict[str, str] | None = None,
                   stale_missing: bool = False, file_keys: dict[Path, dict] | None = None) -> Source:
    """The photos of the bundle file `bundle` solved into `folder` (`steps.write_bundled`); a
    photo without a pose file is missing, with its error in `errors` (summary.csv's) when given."""
    from rgbd_gt.io import read_camera
    from rgbd_gt.io.bundle_file import read_bundle
    from rgbd_gt.prepared import file_key

    spec = read_bundle(bundle)
    record = _json(folder / "bundle.json")
    solved = record.get("bundle_sha1")
    if solved is not None and not _is_sha1(solved):  # damaged, not changed (as `_changed`)
        raise InputError(f"bundle_sha1: not a SHA-1 ({solved!r:.50})", folder / "bundle.json")
    if solved is not None and solved != file_key(bundle)["sha1"]:  # its photos, cameras or shots may be others now
        raise InputError(f"changed since the photos in {folder} were solved from it (bundle.json holds another "
                         "SHA-1): solve them again", bundle)
    photos, missing = [], {}
    file_keys = {} if file_keys is None else file_keys
    by_pose = {p.get("pose"): p for p in record.get("photos") or [] if isinstance(p, dict)}
    for entry in spec.photos:
        pose = folder / entry.image.stem / "pose.yaml"
        keys = {"scan_sha1": record.get("scan_sha1"), **by_pose.get(f"{entry.image.stem}/pose.yaml", {})}
        stale = _changed(keys, entry.image.stem, {"photo": entry.image, "scan": spec.scan}, file_keys, folder / "bundle.json")
        if stale is not None and not stale_missing:
            raise stale
        if stale is not None or (errors is not None and not pose.is_file()):
            missing[entry.image.stem] = (errors or {}).get(entry.image.name) or str(stale or "no refined pose")
            continue
        cam_file = folder / "cameras" / f"{entry.camera}.yaml"
        shot = _shot(entry.image.stem, entry.image, read_camera(cam_file), entry.camera, cam_file, pose,
                     _camera_sigma(cam_file))
        shot.shot, shot.mask = entry.shot, entry.mask
        photos.append(shot)
    # an earlier solve's rig.yaml may lie beside a solve without a rig: read only the bundle's own
    rig = _rig(folder / "rig.yaml") if spec.rig and (folder / "rig.yaml").is_file() else None
    if rig is not None and rig["cameras"] != spec.rig:
        raise InputError(f"is a rig of {', '.join(rig['cameras'])}, not the bundle's {', '.join(spec.rig)}: "
                         "written by another solve", folder / "rig.yaml")
    return Source(name, spec.scan, folder, photos, rig, missing, file_keys.get(spec.scan))


def _camera_sigma(path: Path) -> dict[str, float]:
    """{focal_px, cx_px, cy_px}: the 1-sigmas of a bundle's solved camera file (`sigma:`)."""
    keys = read_yaml(path)
    sigma = (keys.get("sigma") if isinstance(keys, dict) else None) or {}
    picked = {k: v for k, v in sigma.items() if k in ("focal_px", "cx_px", "cy_px")} if isinstance(sigma, dict) else None
    if picked is None or not all(_nonnegative(v) for v in picked.values()):
        raise InputError(f"sigma: not 1-sigmas in pixels ({sigma!r})", path)
    return {k: float(v) for k, v in picked.items()}


def _rig(path: Path) -> dict:
    """rig.yaml (`steps.write_bundled`), checked for what export reads of it: the cameras in
    order and each later camera's `relative` entry with its translation 1-sigma (mm, 3 numbers)."""
    rig = read_yaml(path)
    try:
        if not isinstance(rig, dict):
            raise TypeError(f"not a mapping of keys ({type(rig).__name__})")
        cameras = rig["cameras"]
        if not isinstance(cameras, list) or not all(isinstance(c, str) for c in cameras):
            raise TypeError(f"cameras: not a list of names ({cameras!r})")
        relative = rig["relative"] if len(cameras) > 1 else {}
        if not isinstance(relative, dict):
            raise TypeError(f"relative: not a mapping of cameras ({relative!r:.40})")
        for c in cameras[1:]:
            entry = relative[c]
            sigma = entry.get("sigma") if isinstance(entry, dict) else None
            if not isinstance(sigma, dict):  # a sigma left out is unknown, not zero
                raise TypeError(f"relative.{c}: not a relative pose with its sigma ({entry!r:.40})")
            mm = sigma["translation_mm"]
            if not (isinstance(mm, list) and len(mm) == 3 and all(_nonnegative(v) for v in mm)):
                raise TypeError(f"relative.{c}.sigma.translation_mm: not 3 numbers ({mm!r})")
    except (KeyError, TypeError, AttributeError) as exc:
        raise InputError(f"not a rig record rgbd-gt wrote ({_why(exc)})", path) from None
    return rig


def _nonnegative(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) and v >= 0


def _shot(name: str, image: Path, camera: Camera, camera_name: str, camera_file: Path, pose_file: Path,
          sigma: dict) -> Shot:
    from rgbd_gt.io import read_pose

    T, keys = read_pose(pose_file)
    # what export and the report read of it, as refine writes it
    verdict, reasons, evidence = keys.get("verdict", "failed"), keys.get("reasons") or [], keys.get("evidence") or {}
    if verdict not in ("ok", "suspect", "failed"):
        raise InputError(f"verdict: not ok, suspect or failed ({verdict!r:.40})", pose_file)
    if not isinstance(reasons, list) or not all(isinstance(r, str) for r in reasons):
        raise InputError(f"reasons: not a list of text ({reasons!r:.40})", pose_file)
    try:
        stated = stated_uncertainty(evidence)
        if not isinstance(stated, dict):
            raise AttributeError("uncertainty")
    except AttributeError as exc:
        raise InputError(f"evidence: not as refine writes it ({exc})", pose_file) from None
    # refine writes a verdict with its uncertainty: a file cut short after the verdict would be
    # exported with none (a zero covariance), as if the pose were exact
    if "verdict" in keys and not stated and "covariance" not in keys:
        raise InputError("states a verdict but no uncertainty (no evidence or covariance): cut short, not as refine "
                         "writes it", pose_file)
    try:
        cov = pose_covariance(keys)
    except (TypeError, ValueError) as exc:
        # numpy's own words on a ragged list ("setting an array element with a sequence ...") do
        # not say which row
        why = _not_rows(keys["covariance"], 6) if "covariance" in keys else None
        raise InputError(f"covariance: not a 6 x 6 matrix of numbers ({why or exc})", pose_file) from None
    if "covariance" in keys and not np.isfinite(cov).all():  # refine writes it only when determined
        raise InputError("covariance: not finite", pose_file)
    return Shot(name, image, camera, camera_name, camera_file, T, cov, verdict, reasons, pose_file, sigma,
                evidence=evidence)


def stated_uncertainty(evidence: dict) -> dict:
    """The worst-direction 1-sigmas (`align.verify.uncertainty`) of the covariance a pose file
    states: with the photos' tiles as the samples (`tiles.uncertainty`, for a joint solve the
    wider of its frames' and its tiles'), else with the frames as the samples (`frames.uncertainty`,
    pose files of earlier releases), else the aligner's (`uncertainty`); {} when there are none."""
    return ((evidence.get("tiles") or {}).get("uncertainty") or (evidence.get("frames") or {}).get("uncertainty")
            or evidence.get("uncertainty") or {})


def _not_rows(value, n: int) -> str | None:
    """What keeps a YAML value from being n rows of n numbers, in words (None: nothing found)."""
    if not isinstance(value, list):
        return f"got {value!r:.60}"
    if len(value) != n:
        return None if len(value) == n * n else f"{len(value)} rows"
    for k, row in enumerate(value, 1):
        if not isinstance(row, list) or len(row) != n:
            return f"row {k} is {row!r:.60}"
    return None


def pose_covariance(keys: dict) -> np.ndarray:
    """(6, 6) the pose file's `covariance`; from a file without one, the worst-direction 1-sigmas
    of its evidence (`uncertainty`) on every axis (larger than the covariance says; inf where the
    pose is undetermined or its file states no uncertainty)."""
    if "covariance" in keys:
        return np.asarray(keys["covariance"], np.float64).reshape(6, 6)
    u = stated_uncertainty(keys.get("evidence") or {})
    # a pose written by hand (read as failed, exported with --include failed) states no
    # uncertainty: unknown, not exact
    rot, trans = np.radians(float(u.get("rotation_deg", np.inf))), float(u.get("translation_mm", np.inf)) / 1e3
    return np.diag([rot ** 2] * 3 + [trans ** 2] * 3)


def _errors(summary: Path) -> dict[str, str]:
    """{photo file name: its error} of a run's summary.csv (a site's names are SCAN/PHOTO: the
    photo's part is kept)."""
    import csv

    try:
        with open(summary, newline="") as f:
            return {r["photo"].split("/")[-1]: r.get("error") or "" for r in csv.DictReader(f) if r.get("error")}
    except (OSError, KeyError, csv.Error):
        return {}


def _json(path: Path) -> dict:
    try:
        text = Path(path).read_text(errors="replace")
    except FileNotFoundError:
        return {}
    except OSError as exc:
        raise InputError(f"cannot read ({exc.strerror or exc})", path) from None
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError("empty: not a record rgbd-gt wrote" if not text.strip() else
                         f"invalid JSON ({exc.msg}, line {exc.lineno})", path) from None
    if not isinstance(data, dict):
        raise InputError(f"not a record rgbd-gt wrote (a JSON {type(data).__name__}, not an object)", path)
    return data
