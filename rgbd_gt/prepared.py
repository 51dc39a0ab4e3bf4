"""A scan prepared once and shared by every photo and step: the one way every command and `run`
reach a scan, cached on disk (--cache, `run`'s OUTPUT/.scan-cache) or held in memory.

Preparing reads the scan file, computes what depends on the scan alone (normals facing the
scanner, the grid mesh, the voxel-block index, the board) and writes it as plain .npy files in
a folder keyed by the file's size, time and content hash, or keeps the same arrays in memory.
Reopening maps those files (seconds for 40 million points), and each photo then gathers only
the blocks its view can reach (`PreparedScan.view`), so that its steps scale with what it sees. The grid mesh is stored as a
byte a point (`render.mesh.grid_cell_bits`: which of the grid's triangles are kept), from which
a view makes its triangles without measuring an edge; its ray-casting scene depends on the
camera and pose (`render.depth.grid_mesh`), so it is made per photo from the view's triangles.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import shutil
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError, require_file
from rgbd_gt.io.atomic import atomic_output
from rgbd_gt.scan import Scan
from rgbd_gt.render.blocks import VIEW_MARGIN, Blocks, block_order, block_points, blocks_in_view, points_in_view, thinning_step

CACHE_VERSION = 5
ARRAYS = Scan.PER_POINT + ("cells",)  # per point, block-ordered
# "cells": `render.mesh.grid_cell_bits` (grid scans), a subset's Scan.cell_bits


def file_key(path: Path) -> dict:
    """What identifies a scan file's content: its size, modification time and SHA-1."""
    st = path.stat()
    with open(path, "rb") as f:
        digest = hashlib.file_digest(f, "sha1").hexdigest()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns, "sha1": digest}


def still_of(path: Path, key: dict | None) -> bool:
    """Whether `key` (a `file_key` taken earlier, or None) was taken of the file as it is now: the
    same size and modification time, so that its SHA-1 stands without reading the file again."""
    try:
        st = path.stat()
    except OSError:  # gone or unreadable: whoever reads it next says so
        return False
    return key is not None and (key.get("size"), key.get("mtime_ns")) == (st.st_size, st.st_mtime_ns)


@dataclass
class PreparedScan:
    """A block-ordered scan: arrays (memory-mapped .npy of the cache `folder`, or in memory when
    folder is None) with xyz as float32 metres from `centre` (float64, `storage_centre`: float32
    is then exact to microns within a few hundred metres); blocks in the scan's frame; origins
    (S, 3) the scanner positions."""

    folder: Path | None
    source: Path | None
    centre: np.ndarray
    origins: np.ndarray
    arrays: dict[str, np.ndarray]
    blocks: Blocks
    angular_step: float | None  # radians between neighbouring points seen from the scanner (`scan_step`)
    key: dict | None = None  # the `file_key` of the scan file it was prepared from (None: in memory)

    @property
    def sha1(self) -> str:
        """The SHA-1 of the scan file it was prepared from ("" in memory)."""
        return self.key["sha1"] if self.key else ""

    def __len__(self) -> int:
        return len(self.arrays["xyz"])

    def subset(self, index: np.ndarray) -> Scan:
        """The points `index` (into the block order) as a `Scan` in the scan's frame (float64)."""
        fields = {k: np.asarray(a[index]) for k, a in self.arrays.items() if k not in ("xyz", "cells")}
        xyz = self.arrays["xyz"][index].astype(np.float64) + self.centre
        scan = Scan(xyz=xyz, origins=self.origins, **fields)
        if "cells" in self.arrays:
            scan.cell_bits = np.asarray(self.arrays["cells"][index])
        return scan

    def view(self, camera: Camera, T_cam_from_scan: np.ndarray, margin: float = VIEW_MARGIN,
             far: float | None = None) -> Scan:
        """The points a photo can see from about T_cam_from_scan (`render.blocks.points_in_view`),
        found through the blocks: every step of that photo works on this subset."""
        return self.subset(self.view_index(camera, T_cam_from_scan, margin, far))

    def views(self, camera: Camera, poses: list[np.ndarray], margin: float = VIEW_MARGIN) -> Scan:
        """The points in view of any of the poses (`view`)."""
        return self.subset(np.unique(np.concatenate([self.view_index(camera, T, margin) for T in poses])))

    def view_index(self, camera: Camera, T_cam_from_scan: np.ndarray, margin: float = VIEW_MARGIN,
                   far: float | None = None) -> np.ndarray:
        """(n,) int64 ascending indices (block order) of the points `view` returns."""
        idx = block_points(self.blocks, blocks_in_view(self.blocks, camera, T_cam_from_scan, margin, far))
        T_local = T_cam_from_scan.copy()
        T_local[:3, 3] += T_local[:3, :3] @ self.centre  # the pose of the local (float32) frame
        return idx[points_in_view(np.asarray(self.arrays["xyz"][idx]), camera, T_local, margin, far)]

    def bounds(self) -> np.ndarray:
        """(2, 3) the lowest and highest corner of the box around every point, metres in the scan's
        frame (from its blocks: no point is read)."""
        return np.stack([self.blocks.lo.min(axis=0), self.blocks.hi.max(axis=0)])

    def whole(self) -> Scan:
        """Every point, as a `Scan` (block-ordered)."""
        return self.subset(slice(None))

    def is_sweep(self) -> bool:
        """Whether the scan is a LiDAR sweep (`render.points.is_sweep`), asked of the stored
        arrays as they are (a dense scan's are not all read into memory for it)."""
        from rgbd_gt.render.points import is_sweep

        a = self.arrays
        return is_sweep(Scan(xyz=a["xyz"], **{k: a[k] for k in ("row", "col", "scan_id", "ring") if k in a},
                             origins=self.origins - self.centre))

    def near(self, lo: np.ndarray, hi: np.ndarray) -> Scan:
        """The points of the blocks that meet the box [lo, hi] (metres, scan frame)."""
        return self.subset(block_points(self.blocks, self._meeting(lo, hi)))

    def xyz_around(self, centre: np.ndarray, reach: float, max_points: int) -> np.ndarray:
        """(n, 3) scan-frame coordinates (metres, float64) of the points of the blocks that meet
        the box `reach` metres around `centre` (3,), every k-th of them beyond `max_points`: for
        work that wants the scan around a camera, behind it too, not its view."""
        meet = self._meeting(centre - reach, centre + reach)
        total = int(np.diff(self.blocks.start)[meet].sum())
        idx = block_points(self.blocks, meet, thinning_step(total, max_points))
        return self.arrays["xyz"][idx].astype(np.float64) + self.centre

    def _meeting(self, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
        """(B,) bool: the blocks that meet the box [lo, hi]."""
        return np.all((self.blocks.hi >= lo) & (self.blocks.lo <= hi), axis=1)

    def board(self, spec, scan_path=None):
        """The board (`init.run.BoardInScan`) found in the scan: searched once, then read from
        the cache folder."""
        from rgbd_gt.init.run import BoardInScan, board_in_scan, board_neighbourhood
        from rgbd_gt.init.scan_board import find_board_in_scan
        from rgbd_gt.scan import colors_to_gray, scan_colors

        name = f"board-{spec.cols}x{spec.rows}-{spec.square:g}-{spec.charuco or 'chess'}-{spec.marker or 0:g}.npz"
        path = self.folder / name if self.folder is not None else None
        if path is not None and path.exists():
            with np.load(path) as z:
                return BoardInScan(z["corners"], z["ids"], z["near_xyz"], z["near_gray"], str(z["method"]),
                                   float(z["plane_rms_m"]))
        if len(self.origins) == 0:  # no scanner position to render views from: the error it gives
            board = board_in_scan(self.whole(), spec, None, scan_path)
        else:
            xyz = np.asarray(self.arrays["xyz"])  # local float32: the search needs no float64 copy
            colors = scan_colors(Scan(xyz=xyz, rgb=self.arrays.get("rgb"), intensity=self.arrays.get("intensity")), scan_path)
            sb = find_board_in_scan(xyz, colors, self.origins[0] - self.centre, spec, self.angular_step, scan_path)
            sb.corners = sb.corners + self.centre
            sb.view.origin = sb.view.origin + self.centre
            pad = 2 * spec.square + 0.02
            local = self.near(sb.corners.min(0) - pad, sb.corners.max(0) + pad)
            near = board_neighbourhood(local, sb.corners, spec.square)
            board = BoardInScan(sb.corners, sb.ids, local.xyz[near], colors_to_gray(scan_colors(local, scan_path)[near]),
                                "board found in the scan's virtual views", sb.plane_rms_m, sb)
        if path is None:  # prepared in memory: nowhere to keep it
            return board
        with atomic_output(path) as tmp:  # a temporary file of its own: two runs may write it at once
            np.savez(tmp, corners=board.corners, ids=board.ids, near_xyz=board.near_xyz, near_gray=board.near_gray,
                     method=np.array(board.method), plane_rms_m=np.array(board.plane_rms_m or np.nan))
        return board


def cache_folder(root: Path, scan_path: Path, key: dict) -> Path:
    """Where the scan's prepared files live under `root`: one folder per scan content."""
    return root / f"{scan_path.stem}-{key['sha1'][:16]}"


def prepare_scan(scan_path: Path, root: Path | None = None,
                 progress: Callable[[str], None] = lambda msg: None, key: dict | None = None) -> PreparedScan:
    """The prepared scan of `scan_path`: the one way every command and `run` reach a scan. With a
    cache folder `root`, from the cache there when its key matches, else built there (and the
    folders of earlier versions of this file removed); without, built in memory for this process
    (the same arrays, so a command sees what it would see through the cache). key: the file's
    `file_key` where the caller has just taken it (export, checking the scan against its solve),
    so that a large scan is not read through twice (taken again if the file's size or time differ)."""
    from rgbd_gt.io.scan import load_scan

    scan_path = require_file(scan_path)
    if root is None:
        progress("reading the scan")
        return prepared_in_memory(load_scan(scan_path, require_points=True), scan_path, progress)
    if not still_of(scan_path, key):
        progress("hashing the scan file")
        key = file_key(scan_path)
    folder = cache_folder(root, scan_path, key)
    meta = _current_meta(folder, key)
    if meta is not None:
        try:
            return _open(folder, scan_path, meta)
        except DAMAGED:  # a file of it lost or cut short (a full disk, a copy stopped halfway): made again
            progress("the scan's cache is damaged: preparing the scan again")
            shutil.rmtree(folder, ignore_errors=True)
    progress("preparing the scan (once)")
    _build(scan_path, folder, key, progress)
    for old in root.glob(f"{scan_path.stem}-*/meta.json"):  # this file's earlier contents: stale
        try:
            stale = old.parent != folder and json.loads(old.read_text()).get("source") == str(scan_path.absolute())
        except (OSError, ValueError):
            stale = False
        if stale:
            shutil.rmtree(old.parent, ignore_errors=True)
    return _open(folder, scan_path, json.loads((folder / "meta.json").read_text()))


def _current_meta(folder: Path, key: dict) -> dict | None:
    """The meta.json of the cache in `folder` when it is of `key` and this version; else None (an
    unreadable cache is rebuilt)."""
    try:
        meta = json.loads((folder / "meta.json").read_text())
    except (OSError, ValueError):
        return None
    return meta if isinstance(meta, dict) and meta.get("key") == key and meta.get("version") == CACHE_VERSION \
        and meta.get("digest") == _digest(meta) else None


def _digest(meta: dict) -> str:
    """SHA-1 of meta.json's other entries: a number in it changed (its centre, a bit flipped on
    disk) would move every point, so that a view found nothing, and is made again instead."""
    rest = {k: v for k, v in meta.items() if k != "digest"}
    return hashlib.sha1(json.dumps(rest, sort_keys=True).encode()).hexdigest()


def storage_centre(scan: Scan) -> np.ndarray:
    """(3,) float64: where the prepared scan's float32 coordinates are measured from: the first
    scanner position when it lies within the points' bounds (a scanner is surrounded by what it
    sees), else the median of every k-th point in file order. Not the bounds' centre, and not a
    stated origin far outside: one stray point or a wrong header would leave float32 no precision."""
    if len(scan.origins) and np.all((scan.origins[0] >= scan.xyz.min(0)) & (scan.origins[0] <= scan.xyz.max(0))):
        return scan.origins[0].copy()
    return np.median(scan.xyz[:: max(1, len(scan) // 100_000)], axis=0)


def scan_in_view(scan_path: Path, camera: Camera, poses: list[np.ndarray], cache: Path | None = None) -> Scan:
    """The scan's points in view of the camera at any of the poses (`PreparedScan.views`), from the
    prepared scan (under `cache`, or in memory)."""
    return prepare_scan(scan_path, cache).views(camera, poses)


def view_and_around(scan_path: Path, camera: Camera, poses: list[np.ndarray], reach: float, max_points: int,
                    cache: Path | None = None) -> tuple[Scan, np.ndarray]:
    """`scan_in_view`, and the coordinates (n, 3) of the scan's points around the first pose's
    camera (`PreparedScan.xyz_around`), the scan prepared once."""
    from rgbd_gt.pose import camera_centre

    prepared = prepare_scan(scan_path, cache)
    return prepared.views(camera, poses), prepared.xyz_around(camera_centre(poses[0]), reach, max_points)


def whole_scan(scan_path: Path, cache: Path | None = None) -> Scan:
    """Every point of the prepared scan (under `cache`, or in memory)."""
    return prepare_scan(scan_path, cache).whole()


def whole_scan_geometry(read: Scan) -> Scan:
    """The scan with its normals (`with_normals`) and, for a grid scan, its grid mesh's
    `cell_bits` (`grid_cell_bits`), both made on these points: a view takes them along. Made on
    a view alone they differ at depth edges: the stretch test's limit follows the angular step,
    which a view's own grid gives a few percent off (pumpA: 4%; normals of 1% of the points in a
    view more than 5 deg apart, 167 pixels of its depth map up to 5 m apart). A sweep in ring
    order and without color gets its depth steps along the rings (`Scan.edge`), for the nid
    objective's edge term (a colored scan is aligned by its colors: asking whether it is a sweep
    would cost a dense scan's refine a nearest-neighbour search, open3d's import among it)."""
    from rgbd_gt.render.mesh import grid_cell_bits, grid_normals
    from rgbd_gt.render.normals import oriented, with_normals
    from rgbd_gt.render.points import is_sweep
    from rgbd_gt.render.rings import ring_steps

    scan = oriented(read)
    if scan.has_grid and scan.normals is None and len(scan.origins):  # the normals' pass makes the bits too
        normals, bits = grid_normals(scan)
        return dataclasses.replace(scan, normals=normals, cell_bits=bits)
    scan = with_normals(scan)
    if scan.has_grid:
        return dataclasses.replace(scan, cell_bits=grid_cell_bits(scan))
    if scan.edge is None and scan.rgb is None and is_sweep(scan):  # a view's points are block-ordered: the rings' order is lost there
        scan = dataclasses.replace(scan, edge=ring_steps(scan.xyz, scan.origins[0] if len(scan.origins) else None))
    return scan


def open_prepared(folder: Path, scan_path: Path) -> PreparedScan:
    """A prepared scan's cache folder, opened without checking it against the scan file (the
    caller prepared it: `prepare_scan`)."""
    try:
        return _open(folder, scan_path, json.loads((folder / "meta.json").read_text()))
    except DAMAGED as exc:
        raise InputError(f"the scan's cache is damaged ({exc}); remove the folder to prepare the scan again", folder) from None


# what reading a cut-short, emptied or foreign cache file raises (zipfile.BadZipFile: blocks.npz)
DAMAGED = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile)


def _open(folder: Path, scan_path: Path, meta: dict) -> PreparedScan:
    """The cache in `folder` as its meta.json `meta` describes it; DAMAGED when a file of it
    does not read back as written."""
    arrays = {k: np.load(folder / f"{k}.npy", mmap_mode="r") for k in meta["arrays"]}
    with np.load(folder / "blocks.npz") as z:
        blocks = Blocks(z["start"], z["lo"], z["hi"])
    short = [k for k, a in arrays.items() if len(a) != meta["points"]] + (["blocks"] if len(blocks) != meta["blocks"] else [])
    if short:
        raise ValueError(f"{', '.join(short)}: not as many entries as meta.json says")
    return PreparedScan(folder, scan_path, np.array(meta["centre"]), np.array(meta["origins"]).reshape(-1, 3), arrays,
                        blocks, meta.get("angular_step"), meta["key"])


@dataclass
class _Layout:
    """What preparing makes besides the arrays: the float32 coordinates' origin (3,), the scanner
    positions (S, 3), the angular step (`scan_step`, or None), the blocks (in the scan's frame)
    and the points' count."""

    centre: np.ndarray
    origins: np.ndarray
    angular_step: float | None
    blocks: Blocks
    points: int


def _prepared_arrays(read: Scan, progress: Callable[[str], None], phase: Callable[[str], None]):
    """Make what depends on the scan `read` alone (its normals facing the scanner, the grid mesh's
    cell bits, the block order): yields its `_Layout` first, then (name, array) of each of ARRAYS
    the scan has, block-ordered, one at a time and each freed from the scan as it goes, so that
    memory stays near the scan's own whether they are written to a cache or kept."""
    from rgbd_gt.init.scan_board import scan_step

    progress("normals")
    scan = whole_scan_geometry(read)
    del read
    step = scan_step(scan) if len(scan.origins) else None
    scan = dataclasses.replace(scan)  # a Scan of its own, whose fields are let go below: not the caller's
    cells, scan.cell_bits = scan.cell_bits, None
    phase("normals")
    centre = storage_centre(scan)
    progress("spatial index")
    local = np.empty(scan.xyz.shape, np.float32)  # = (xyz - centre).astype(float32), without a float64 temporary
    np.subtract(scan.xyz, centre, out=local, casting="same_kind")
    scan.xyz = None  # the float64 copy is no longer needed
    order, blocks = block_order(local)
    phase("index")
    yield _Layout(centre, scan.origins, step, Blocks(blocks.start, blocks.lo + centre, blocks.hi + centre), len(order))
    for name in ARRAYS:
        values = local if name == "xyz" else cells if name == "cells" else getattr(scan, name)
        if values is None:
            continue
        ordered = values[order]
        if name == "xyz":
            del local, values
        elif name == "cells":
            cells = None
        else:
            setattr(scan, name, None)
        yield name, ordered


def prepared_in_memory(read: Scan, source: Path | None = None,
                       progress: Callable[[str], None] = lambda msg: None) -> PreparedScan:
    """The prepared scan of `read` (a `Scan` as read from `source`), in memory: what a cache
    folder would hold, for one process."""
    arrays = _prepared_arrays(read, progress, lambda name: None)
    layout = next(arrays)
    return PreparedScan(None, source, layout.centre, layout.origins, dict(arrays), layout.blocks, layout.angular_step)


def _build(scan_path: Path, folder: Path, key: dict, progress: Callable[[str], None]) -> None:
    """Read the scan, prepare it (`_prepared_arrays`), write every array into a staging folder
    and move it into place (a crash leaves no half-written cache)."""
    import time

    from rgbd_gt.io.scan import load_scan

    seconds: dict[str, float] = {}
    clock = [time.perf_counter()]

    def phase(name: str) -> None:  # what each part of preparing costs, kept in meta.json
        now = time.perf_counter()
        seconds[name] = round(now - clock[0], 2)
        clock[0] = now

    progress("reading the scan")
    read = load_scan(scan_path, require_points=True)
    phase("read")
    arrays = _prepared_arrays(read, progress, phase)
    del read
    layout = next(arrays)
    folder.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=".rgbd-gt-", dir=folder.parent))
    try:
        progress("writing the cache")
        names = []
        for name, values in arrays:
            np.save(stage / f"{name}.npy", values)
            names.append(name)
            del values
        blocks = layout.blocks
        np.savez(stage / "blocks.npz", start=blocks.start, lo=blocks.lo, hi=blocks.hi)
        phase("write")
        meta = {"seconds": seconds, "version": CACHE_VERSION, "key": key, "source": str(scan_path.absolute()),
                "points": layout.points, "arrays": names, "centre": layout.centre.tolist(),
                "origins": layout.origins.tolist(), "angular_step": layout.angular_step, "blocks": len(blocks)}
        (stage / "meta.json").write_text(json.dumps({**meta, "digest": _digest(meta)}, indent=1))
        # another run that prepared the same scan meanwhile has put an equal cache in place, which it
        # may be reading: keep that one
        if _current_meta(folder, key) is None:
            shutil.rmtree(folder, ignore_errors=True)
            try:
                os.replace(stage, folder)
            except OSError:
                if _current_meta(folder, key) is None:
                    raise
        shutil.rmtree(stage, ignore_errors=True)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
