"""`rgbd-gt ingest`: merge scan files, crop, downsample, write one PLY, extract embedded images."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import yaml

from rgbd_gt.errors import InputError
from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.io.scan import load_scan, merge_scans, save_scan
from rgbd_gt.scan import Scan
from rgbd_gt.scan_ops import crop, median_spacing, voxel_downsample

IMAGE_MAGIC = {"jpeg": b"\xff\xd8", "png": b"\x89PNG"}


@dataclass
class ScanSummary:
    """Numbers for one scan: `label` names its file and index; bounds are (2, 3) metres."""

    label: str
    points: int
    fields: list[str]
    bounds: np.ndarray
    spacing_m: float


@dataclass
class ImageSummary:
    source: str
    name: str
    kind: str
    format: str
    width: int
    height: int
    has_pose: bool
    saved_to: str | None = None
    problem: str | None = None


@dataclass
class IngestResult:
    inputs: list[ScanSummary]
    output: ScanSummary
    images: list[ImageSummary] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)


def summarize(label: str, scan: Scan) -> ScanSummary:
    bounds = np.stack([scan.xyz.min(axis=0), scan.xyz.max(axis=0)]) if len(scan) else np.full((2, 3), np.nan)
    return ScanSummary(label, len(scan), scan.fields, bounds, median_spacing(scan))


MAX_SCAN_ROWS = 50  # a file of more scans is summarised as one row


def _per_scan_summaries(path: Path, scan: Scan) -> list[ScanSummary]:
    ids = np.unique(scan.scan_id) if scan.scan_id is not None and len(scan) else np.zeros(1, np.int32)
    if len(ids) == 1 or len(ids) > MAX_SCAN_ROWS:
        return [summarize(path.name if len(ids) == 1 else f"{path.name} ({len(ids)} scans)", scan)]
    return [summarize(f"{path.name}#{i}", scan.subset(scan.scan_id == i)) for i in ids]


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("._") or "image"


def extract_images(path: Path, out_dir: Path | None) -> list[ImageSummary]:
    """List an E57 file's Image2D entries; with `out_dir`, write each image, a camera file for
    pinhole ones, and an `images.yaml` index with every entry's metadata."""
    from rgbd_gt.io.e57 import list_e57_images, pinhole_intrinsics, read_e57_images

    if out_dir is None:
        return [
            ImageSummary(str(path.name), im.name, im.kind, im.format, im.width, im.height, im.pose is not None)
            for im in list_e57_images(path)
        ]
    out_dir.mkdir(parents=True, exist_ok=True)
    summaries, index = [], []
    for im, data in read_e57_images(path):
        s = ImageSummary(str(path.name), im.name, im.kind, im.format, im.width, im.height, im.pose is not None)
        stem = _safe_name(f"{path.stem}_{im.index}_{im.name}")
        if not data.startswith(IMAGE_MAGIC[im.format]):
            s.problem = f"blob is not a valid {im.format.upper()} image"
        target = out_dir / f"{stem}{im.suffix}"
        with atomic_output(target) as tmp:
            tmp.write_bytes(data)
        s.saved_to = str(target)
        entry = {
            "file": target.name, "source": str(path), "name": im.name, "kind": im.kind, "format": im.format,
            "width": im.width, "height": im.height, "params": im.params,
        }
        if im.pose is not None:
            entry["T_world_from_image"] = im.pose.tolist()
        intr = pinhole_intrinsics(im)
        if intr is None and im.kind == "pinhole":
            s.problem = "its pinhole parameters are missing or not positive: no camera file"
        if intr is not None:
            cam_path = out_dir / f"{stem}.camera.yaml"
            with atomic_output(cam_path) as tmp:
                tmp.write_text(yaml.safe_dump(intr, sort_keys=False))
            entry["camera"] = cam_path.name
        if s.problem:
            entry["problem"] = s.problem
        index.append(entry)
        summaries.append(s)
    if index:
        with atomic_output(out_dir / f"{_safe_name(path.stem)}_images.yaml") as tmp:
            tmp.write_text(yaml.safe_dump({"images": index}, sort_keys=False))
    return summaries


def ingest(
    paths: list[Path],
    output: Path,
    scan_index: int | None = None,
    voxel: float | None = None,
    box: tuple[np.ndarray, np.ndarray] | None = None,
    images_dir: Path | None = None,
    progress: Callable[[Path, int, int], None] | None = None,
) -> IngestResult:
    """Load, merge, crop, downsample and write scans; returns the numbers for the summary.

    progress: optional callable(path, done_points, total_points) while reading.
    """
    if scan_index is not None and not any(p.suffix.lower() == ".e57" for p in paths):  # it would do nothing
        raise InputError("--scan-index applies to E57 files only, and no input is one")
    scans, inputs, images = [], [], []
    for path in paths:
        cb = (lambda done, total, p=path: progress(p, done, total)) if progress else None
        scan = load_scan(path, scan_index=scan_index if path.suffix.lower() == ".e57" else None, progress=cb,
                         require_points=True)
        inputs += _per_scan_summaries(path, scan)
        scans.append(scan)
        if path.suffix.lower() == ".e57":
            images += extract_images(path, images_dir)
    warnings = dropped_fields(paths, scans)
    merged = merge_scans(scans)
    del scans
    if box is not None:
        merged = crop(merged, *box)
        if len(merged) == 0:
            raise InputError(f"no points inside the crop box {box[0].tolist()} .. {box[1].tolist()}")
    if voxel:
        diagonal = float(np.linalg.norm(np.ptp(merged.xyz, axis=0))) if len(merged) else 0.0
        if voxel > diagonal:
            raise InputError(f"--voxel {voxel} m is larger than the whole scan ({diagonal:.2f} m across): "
                             "one point would remain")
        merged = voxel_downsample(merged, voxel)
    save_scan(output, merged)
    return IngestResult(inputs, summarize(output.name, merged), images, warnings)


def dropped_fields(paths: list[Path], scans: list[Scan]) -> list[str]:
    """One line per field that some inputs have and others lack: merging keeps only the fields
    every input has, and colors lost to a file without them are worth a word."""
    lines = []
    for name, what, then in (("rgb", "colors", ""), ("intensity", "intensity", ""), ("normals", "normals", ""),
                             ("row", "the scan grid", " (its surfaces are rendered as surfels)"),
                             ("ring", "the LiDAR rings", "")):
        lack = [p.name for p, s in zip(paths, scans) if getattr(s, name) is None]
        if 0 < len(lack) < len(scans):
            lines.append(f"{what} dropped from the merged scan{then}: {', '.join(lack)} "
                         f"{'has' if len(lack) == 1 else 'have'} none")
    return lines
