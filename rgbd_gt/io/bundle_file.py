"""The bundle file of `refine --bundle` (docs/bundle.md): several photos of one scan, their
cameras (and which corrections each camera's photos share), optionally a rig.

    scan: scan.ply
    cameras:
      left: {file: camera.yaml, refine: focal}     # refine: none | focal | focal+principal | focal+principal+k1k2 | full
      right: {file: camera_right.yaml}             # refine: none by default
    rig:                                           # optional: cameras fixed to each other
      cameras: [left, right]                       # the first is the rig's reference
      prior:                                       # optional, per camera after the first
        right: {pose: stereo.yaml, sigma_rotation_deg: 0.05, sigma_translation_mm: 1.0}
    photos:
      - {image: photo.png, camera: left, init: init_pose.yaml, shot: 0}   # shot: rigs only
      - {image: right.png, camera: right, init: init_pose_right.yaml, shot: 0, mask: people.png}

Paths are relative to the file's folder (`~`: the user's home).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from rgbd_gt.camera import INTRINSICS
from rgbd_gt.errors import InputError, read_yaml, require_file

MODES = tuple(INTRINSICS)


@dataclass
class BundleCamera:
    file: Path
    refine: str = "none"


@dataclass
class BundleEntry:
    image: Path
    camera: str
    init: Path
    shot: int | None = None
    mask: Path | None = None


@dataclass
class RigPriorEntry:
    pose: Path  # a pose file of T_cam_from_rig (this camera from the rig's first)
    sigma_rotation_deg: float
    sigma_translation_mm: float


@dataclass
class BundleSpec:
    scan: Path
    cameras: dict[str, BundleCamera]
    photos: list[BundleEntry]
    rig: list[str] = field(default_factory=list)
    priors: dict[str, RigPriorEntry] = field(default_factory=dict)

    def named_files(self) -> dict[str, Path]:
        """Every file the bundle names, by where the bundle file names it ("photo 2: init")."""
        return {"scan": self.scan, **{f"cameras.{n}.file": c.file for n, c in self.cameras.items()},
                **{f"photo {k}: {what}": p for k, e in enumerate(self.photos, 1)
                   for what, p in (("image", e.image), ("init", e.init), ("mask", e.mask)) if p is not None},
                **{f"rig.prior.{n}.pose": p.pose for n, p in self.priors.items()}}

    def files(self) -> list[Path]:
        """Every file the bundle names: the inputs that no output may overwrite."""
        return list(self.named_files().values())


def _number(value, what: str, path: Path) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < float(value) < float("inf"):
        raise InputError(f"{what} must be a positive number, got {value!r}", path)
    return float(value)


def read_bundle(path: str | os.PathLike) -> BundleSpec:
    """The bundle file at path, checked: every camera named exists, every path a string, each
    rig shot has at most one photo per camera."""
    path = require_file(path)
    data = read_yaml(path)
    if not isinstance(data, dict):
        raise InputError("a bundle file is a mapping with scan, cameras and photos (docs/bundle.md)", path)

    def at(value, what: str) -> Path:
        if not isinstance(value, str) or not value:
            raise InputError(f"{what} must be a path", path)
        return path.parent / os.path.expanduser(value)

    cams = data.get("cameras")
    if not isinstance(cams, dict) or not cams:
        raise InputError("needs `cameras:`, a mapping of names to {file, refine}", path)
    cameras = {}
    for name, c in cams.items():
        c = {"file": c} if isinstance(c, str) else c
        if not isinstance(c, dict):
            raise InputError(f"cameras.{name} must be {{file, refine}}", path)
        mode = c.get("refine", "none")
        if mode not in MODES:
            raise InputError(f"cameras.{name}.refine must be one of {', '.join(MODES)}, got {mode!r}", path)
        cameras[str(name)] = BundleCamera(at(c.get("file"), f"cameras.{name}.file"), mode)
    rig, priors = [], {}
    if data.get("rig") is not None:
        r = data["rig"]
        if not isinstance(r, dict) or not isinstance(r.get("cameras"), list) or len(r["cameras"]) < 2:
            raise InputError("rig.cameras must list two or more of the cameras, the reference first", path)
        odd = [c for c in r["cameras"] if not isinstance(c, (str, int)) or isinstance(c, bool)]
        if odd:
            raise InputError(f"rig.cameras must list camera names, got {odd[0]!r}", path)
        rig = [str(c) for c in r["cameras"]]
        unknown = [c for c in rig if c not in cameras]
        if unknown or len(set(rig)) != len(rig):
            detail = f"{', '.join(map(repr, unknown))} not among them" if unknown else "a repeat"
            raise InputError(f"rig.cameras must name distinct cameras of `cameras:` ({detail})", path)
        prior = {} if r.get("prior") is None else r["prior"]  # '' or [] is a mistake, not "no prior"
        if not isinstance(prior, dict):
            raise InputError("rig.prior must map rig cameras after the first to {pose, sigma_rotation_deg, "
                             f"sigma_translation_mm}}, got {prior!r:.40}", path)
        for name, p in prior.items():
            if name not in rig[1:] or not isinstance(p, dict):
                raise InputError(f"rig.prior.{name}: a prior is given per rig camera after the first, as "
                                 "{pose, sigma_rotation_deg, sigma_translation_mm}", path)
            priors[str(name)] = RigPriorEntry(at(p.get("pose"), f"rig.prior.{name}.pose"),
                                              _number(p.get("sigma_rotation_deg"), f"rig.prior.{name}.sigma_rotation_deg", path),
                                              _number(p.get("sigma_translation_mm"), f"rig.prior.{name}.sigma_translation_mm", path))
    items = data.get("photos")
    if not isinstance(items, list) or not items:
        raise InputError("needs `photos:`, a list of {image, camera, init[, shot][, mask]}", path)
    photos, taken = [], set()
    for k, item in enumerate(items, 1):
        if not isinstance(item, dict):
            raise InputError(f"photo {k}: must be {{image, camera, init[, shot][, mask]}}", path)
        camera = item.get("camera", next(iter(cameras)) if len(cameras) == 1 else None)
        if isinstance(camera, (list, dict)) or str(camera) not in cameras:
            raise InputError(f"photo {k}: camera must name one of {', '.join(cameras)}", path)
        camera = str(camera)
        shot = item.get("shot")
        if rig and camera in rig:
            if isinstance(shot, bool) or not isinstance(shot, int):
                raise InputError(f"photo {k}: a rig camera's photo needs `shot:` (an integer: the photos taken together)", path)
            if (shot, camera) in taken:
                raise InputError(f"photo {k}: shot {shot} has two photos of camera {camera}", path)
            taken.add((shot, camera))
        else:
            shot = None
        photos.append(BundleEntry(at(item.get("image"), f"photo {k}: image"), str(camera), at(item.get("init"), f"photo {k}: init"),
                                  shot, at(item["mask"], f"photo {k}: mask") if item.get("mask") is not None else None))
    for cam in rig[1:]:  # the rig's relative pose comes from a shot of both cameras, or from its prior
        if cam not in priors and not any((shot, rig[0]) in taken for shot, c in taken if c == cam):
            raise InputError(f"rig camera {cam}: no shot has photos of it and of {rig[0]} (the rig's first camera), "
                             "and rig.prior gives none for it", path)
    stems = [p.image.stem for p in photos]
    twins = sorted({s for s in stems if stems.count(s) > 1})
    if twins:
        raise InputError(f"two photos named {twins[0]}: each photo's results go to a folder of its name", path)
    return BundleSpec(at(data.get("scan"), "scan"), cameras, photos, rig, priors)
