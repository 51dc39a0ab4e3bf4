"""`rgbd-gt export RUN_DIR -o OUT --format F`: a finished run as the layouts training code reads
(`export.formats`), every depth with its validity and 1-sigma (`export.uncertainty`)."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError
from rgbd_gt.export.source import Shot, Source
from rgbd_gt.export.stereo import Warp
from rgbd_gt.export.uncertainty import PixelSigma
from rgbd_gt.io.json_text import json_text
from rgbd_gt.render.depth import DepthMap

FORMATS = ("plain", "colmap", "nerfstudio", "middlebury", "kitti")
STEREO = ("middlebury", "kitti")
COLMAP_POINTS = 200_000  # at most this many scan points in points3D.txt (every k-th of those seen)


@dataclass
class DepthProducts:
    """A photo resampled into a pinhole camera (`export.stereo.Warp`) with its depth there:
    camera, T (4, 4) T_cam_from_scan, image (H, W, 3) uint8, depth (`render.depth.DepthMap`: z
    (H, W) metres, 0 where none, and normals (H, W, 3)), sigma (`export.uncertainty.PixelSigma`), near (H, W) bool within reach of a depth
    discontinuity, valid (H, W) bool: depth, not masked, not near a discontinuity."""

    camera: Camera
    T: np.ndarray
    image: np.ndarray
    depth: DepthMap
    sigma: PixelSigma
    near: np.ndarray
    valid: np.ndarray

    @property
    def z(self) -> np.ndarray:
        return self.depth.z

    @property
    def normals(self) -> np.ndarray:
        return self.depth.normals


@dataclass
class StereoProducts:
    """A rectified pair (`export.stereo.Pair`): the left's products, the right image (H, W, 3)
    uint8, the left's disparity (H, W) float32 px and its 1-sigma, the left pixels the right
    camera does not see (occluded)."""

    left: DepthProducts
    right: np.ndarray
    baseline: float
    disp: np.ndarray
    disp_sigma: np.ndarray
    occluded: np.ndarray
    names: tuple[str, str]


@dataclass
class Exported:
    """export's result (export.json): per photo name its products' figures, per stereo pair its
    figures, the photos left out with why, the seconds in all and of reading the scans."""

    photos: dict[str, dict] = field(default_factory=dict)
    pairs: dict[str, dict] = field(default_factory=dict)
    left_out: dict[str, str] = field(default_factory=dict)
    seconds: float = 0.0
    prepare_seconds: float = 0.0  # reading (or preparing) the scans


def products(prepared, shot: Shot, photo: np.ndarray, warp: Warp, ignore: np.ndarray | None,
             points: bool | None = None) -> DepthProducts:
    """The photo (H, W, 3) uint8 as `warp` resamples it and its depth there, rendered from the
    prepared scan (`prepared.PreparedScan`) with the one renderer; ignore: the photo's mask
    (H, W) bool of pixels not to trust, or None."""
    from rgbd_gt.export.uncertainty import discontinuities, near_discontinuity, pixel_sigma

    cam, T = warp.camera, warp.pose(shot.T)
    depth = render(prepared, shot, warp, points)
    sigma = pixel_sigma(depth.z, depth.normals, cam, warp.covariance(shot.covariance), shot.camera_sigma)
    sparse = depth.method.startswith("points")
    near = near_discontinuity(discontinuities(depth.z, depth.normals, cam, silhouettes=not sparse), sigma.image)
    valid = (depth.z > 0) & ~near & np.isfinite(sigma.depth)
    if ignore is not None:
        valid &= ~(warp.image(ignore.astype(np.uint8), nearest=True) > 0)
    return DepthProducts(cam, T, warp.image(photo), depth, sigma, near, valid)


def render(prepared, shot: Shot, warp: Warp, points: bool | None = None, normals: bool = True):
    """The depth map (`render.depth.DepthMap`) of the shot's photo as `warp` resamples it: the
    scan's view of that camera and pose, rendered by the one renderer (`steps.depth_step`)."""
    from rgbd_gt.render.renders import Renders
    from rgbd_gt.steps import depth_step

    cam, T = warp.camera, warp.pose(shot.T)
    view = Renders(prepared.subset(prepared.view_index(cam, T)))
    return depth_step(view, cam, T, normals=normals, points=points, pose_path=shot.pose_file)


def _photo(shot: Shot):
    """The shot's photo and mask (`steps.open_photo`: checked against its camera, as every step
    checks them)."""
    from rgbd_gt.steps import open_photo

    return open_photo(shot.image, shot.camera, shot.mask, camera_path=shot.camera_file)


def stereo_products(prepared, left: Shot, right: Shot, photos: dict, points: bool | None = None,
                    baseline_sigma: float = 0.0) -> StereoProducts:
    """The rectified pair of two photos of one rig shot (`export.stereo.rectify` from their
    poses, which a rig solve ties by its relative pose) with the left's disparity, its 1-sigma
    (the depth's, and the baseline's 1-sigma `baseline_sigma` metres), and occlusion. photos:
    each shot's name to its `steps.Photo` (`_photo`)."""
    from rgbd_gt.export.stereo import disparity, occluded, rectify

    try:
        pair = rectify(left.camera, left.T, right.camera, right.T)
    except InputError as exc:
        raise InputError(f"stereo pair {left.name} | {right.name} (cameras {left.camera_name}, "
                         f"{right.camera_name}): {exc}") from None
    if pair.swapped:
        left, right = right, left
    pl = products(prepared, left, photos[left.name].image, pair.left, photos[left.name].ignore, points)
    z_right = render(prepared, right, pair.right, points, normals=False).z  # for what the right camera sees
    disp = disparity(pl.z, pl.camera.fx, pair.baseline)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(pl.z > 0, np.hypot(pl.sigma.depth / np.where(pl.z > 0, pl.z, 1), baseline_sigma / pair.baseline), 0)
    return StereoProducts(pl, pair.right.image(photos[right.name].image), pair.baseline, disp, (disp * rel).astype(np.float32),
                          occluded(pl.z, z_right, disp), (left.name, right.name))


def _is_rig(source: Source) -> bool:
    """Whether the source was solved as a rig of two or more cameras (its rig.yaml)."""
    return bool(source.rig) and len(source.rig.get("cameras", [])) >= 2


def stereo_pairs(source: Source, chosen: list[Shot]) -> list[tuple[Shot, Shot, float]]:
    """(left, right, baseline 1-sigma m) of each rig shot whose photos by the rig's first two
    cameras are both chosen."""
    if not _is_rig(source):
        return []
    first, second = source.rig["cameras"][:2]
    rel = source.rig["relative"][second]
    sigma_b = float(np.linalg.norm(rel["sigma"]["translation_mm"])) / 1e3  # `source._rig` checked them
    by_shot: dict = {}
    for s in chosen:
        if s.shot is not None:
            by_shot.setdefault(s.shot, {})[s.camera_name] = s
    return [(shots[first], shots[second], sigma_b) for _, shots in sorted(by_shot.items())
            if first in shots and second in shots]


def export_run(run: Path, out: Path, formats: list[str], include: tuple[str, ...] = ("ok",), cache: Path | None = None,
               points: bool | None = None, progress: Callable[[str, int, int], None] = lambda what, done, total: None,
               sources: list[Source] | None = None) -> Exported:
    """Export the finished run in `run` (`export.source.read_run`, or its `sources` when read)
    into the folder `out`: one sub-folder per format, export.json and report.html; photos whose
    verdict is in `include`. points: depth of the points alone (True), of surfaces (False), as
    export-depth chooses (None); progress: called with (what, done, total) before each photo
    and pair."""
    from rgbd_gt.export.report import write_report
    from rgbd_gt.export.source import read_run
    from rgbd_gt.prepared import prepare_scan

    start = time.perf_counter()
    run, out = Path(run), Path(out)
    bad = [f for f in formats if f not in FORMATS]
    if bad or not formats:
        raise InputError(f"--format must be one or more of {', '.join(FORMATS)}; got {', '.join(bad) or 'none'}")
    sources = sources if sources is not None else read_run(run)
    out.mkdir(parents=True, exist_ok=True)
    result, plain, frames = Exported(), {}, {}
    with ThreadPoolExecutor(1) as writer:  # a photo's files are written while the next one renders
        for source in sources:
            prefix = f"{source.name}_" if len(sources) > 1 else ""  # a site's photos are named SCAN_PHOTO
            chosen = [s for s in source.photos if s.verdict in include]
            result.left_out |= {prefix + s.name: f"verdict {s.verdict}" + (f": {s.reasons[0]}" if s.reasons else "")
                                for s in source.photos if s.verdict not in include}
            if not chosen:
                continue
            t0 = time.perf_counter()
            prepared = prepare_scan(source.scan, cache, key=source.scan_key)
            result.prepare_seconds += time.perf_counter() - t0
            result.photos |= {prefix + s.name: {"verdict": s.verdict, "camera": s.camera_name} for s in chosen}
            if {"plain", "nerfstudio"} & set(formats):
                _photos(prepared, source, chosen, prefix, out, formats, points, writer, result, plain, frames, progress)
            if "colmap" in formats:
                _colmap(prepared, chosen, out / "colmap" / prefix.rstrip("_"))
            if set(STEREO) & set(formats):
                _pairs(prepared, source, chosen, out, formats, points, result, progress)
    if not result.photos:
        raise InputError(f"no photo of the run has a verdict in {', '.join(include)} (use --include suspect)", run)
    if set(STEREO) & set(formats) and not result.pairs:
        if not any(_is_rig(s) for s in sources):
            why = "this run has no solved rig"
        else:  # say which photos the verdicts kept out, the likely cause
            left = ", ".join(f"{k} ({v.split(':')[0]})" for k, v in result.left_out.items())
            why = "no shot has both of its photos exported" + (f" (left out: {left}; see --include)" if left else "")
        raise InputError(f"middlebury and kitti need stereo pairs, from a refine --bundle output with a rig: {why}", run)
    if plain:
        from rgbd_gt.export.formats import CONVENTION

        (out / "plain" / "cameras.json").write_text(json_text({"convention": CONVENTION, "photos": plain}))
    from rgbd_gt.export.formats import write_transforms

    for folder, frames_of_scan in frames.items():  # a scene per scan: each scan is its own world frame
        write_transforms(folder, frames_of_scan)
    result.seconds = time.perf_counter() - start
    (out / "export.json").write_text(json_text({
        "run": str(run), "formats": formats, "include": list(include), "photos": result.photos, "pairs": result.pairs,
        "left_out": result.left_out, "seconds": round(result.seconds, 3),
        "prepare_seconds": round(result.prepare_seconds, 3)}))
    write_report(out / "report.html", sources, out, result)
    return result


def _photos(prepared, source: Source, chosen: list[Shot], prefix: str, out: Path, formats: list[str], points, writer, result: Exported,
            plain: dict, frames: dict, progress) -> None:
    """plain and nerfstudio: each photo undistorted with its depth products, written by `writer`
    (one photo in flight) while the next renders."""
    from rgbd_gt.export.formats import nerfstudio_folder
    from rgbd_gt.export.stereo import pinhole

    writing = None
    nerf = nerfstudio_folder(out, source.name if prefix else None)

    def collect(done) -> None:
        name, entry, frame = done.result()
        if entry is not None:
            plain[name] = entry
        if frame is not None:
            frames.setdefault(nerf, []).append(frame)

    for k, s in enumerate(chosen):
        name = prefix + s.name
        progress(name, k, len(chosen))
        t0 = time.perf_counter()
        photo = _photo(s)
        p = products(prepared, s, photo.image, pinhole(s.camera), photo.ignore, points)
        result.photos[name] |= _figures(p) | {"seconds": round(time.perf_counter() - t0, 3)}
        if writing is not None:
            collect(writing)  # one photo's files in flight at a time: memory stays one photo's
        writing = writer.submit(_write_photo, out, formats, name, s, p, source.scan, nerf)
    if writing is not None:
        collect(writing)


def _colmap(prepared, chosen: list[Shot], folder: Path) -> None:
    """The COLMAP model of the photos: the scan points each sees (refine's visibility rule), every
    k-th of their union beyond COLMAP_POINTS."""
    from rgbd_gt.export.formats import write_colmap
    from rgbd_gt.render.points import seen_points

    seen = []
    for s in chosen:
        gi = prepared.view_index(s.camera, s.T)
        idx, uv, _ = seen_points(prepared.subset(gi), s.camera, s.T)
        seen.append((gi[idx], uv))
    ids = np.unique(np.concatenate([g for g, _ in seen]))
    keep = ids[::max(1, int(np.ceil(len(ids) / COLMAP_POINTS)))]
    pts = prepared.subset(keep)
    kept = []  # each photo's observations of the kept points, by their position in `keep`
    for gids, uv in seen:
        pos = np.minimum(np.searchsorted(keep, gids), len(keep) - 1)
        hit = keep[pos] == gids
        kept.append((pos[hit], uv[hit]))
    write_colmap(folder, chosen, kept, pts.xyz, pts.rgb)


def _pairs(prepared, source: Source, chosen: list[Shot], out: Path, formats: list[str], points, result: Exported,
           progress) -> None:
    """middlebury and kitti: each rig shot's rectified pair."""
    from rgbd_gt.export import formats as fm

    pairs = stereo_pairs(source, chosen)
    for k, (left, right, sigma_b) in enumerate(pairs):
        progress(f"pair {left.name} | {right.name}", k, len(pairs))
        t0 = time.perf_counter()
        photos = {s.name: _photo(s) for s in (left, right)}
        sp = stereo_products(prepared, left, right, photos, points, sigma_b)
        index = len(result.pairs)
        key = f"{left.shot:06d}" if left.shot is not None else f"{index:06d}"
        if "middlebury" in formats:
            fm.write_middlebury(out / "middlebury" / key, sp)
        if "kitti" in formats:
            fm.write_kitti(out / "kitti", index, sp)
        result.pairs[key] = {"left": sp.names[0], "right": sp.names[1], "baseline_m": sp.baseline, "kitti_index": index,
                             **_pair_figures(sp), "seconds": round(time.perf_counter() - t0, 3)}


def _write_photo(out: Path, formats: list[str], name: str, shot: Shot, p: DepthProducts, scan: Path,
                 nerf: Path) -> tuple[str, dict | None, dict | None]:
    """A photo's plain files and its nerfstudio files in `nerf`: (name, its cameras.json entry
    (with the scan whose frame its poses are in), its transforms.json frame), None for a format
    not asked for."""
    from rgbd_gt.export import formats as fm

    entry = fm.write_plain(out / "plain" / name, shot, p, scan.name) | {"scan": str(scan)} if "plain" in formats else None
    return name, entry, fm.nerfstudio_frame(nerf, name, p) if "nerfstudio" in formats else None


def _figures(p: DepthProducts) -> dict:
    s = p.sigma.depth[p.valid]
    # none valid (a pose of unknown uncertainty): null, as strict JSON readers take it (not NaN)
    q = np.percentile(s, [50, 90, 99]) * 1e3 if len(s) else None
    return {"method": p.depth.method, "pixels": int(p.z.size), "with_depth": int((p.z > 0).sum()), "valid": int(p.valid.sum()),
            "near_edge": int(p.near.sum()),
            "depth_sigma_mm": dict(zip(("p50", "p90", "p99"), map(float, q))) if q is not None else None}


def _pair_figures(s: StereoProducts) -> dict:
    v = s.left.valid
    q = np.percentile(s.disp_sigma[v], [50, 90]) if v.any() else None
    return {"valid": int(v.sum()), "occluded": int((v & s.occluded).sum()),
            "disparity_px": [float(s.disp[v].min()), float(s.disp[v].max())] if v.any() else None,
            "disparity_sigma_px": {"p50": float(q[0]), "p90": float(q[1])} if q is not None else None}
