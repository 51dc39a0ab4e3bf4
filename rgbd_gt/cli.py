"""Command-line interface. Thin: parse options, call the library, report.

Every command turns bad input (InputError) into one line `error: ...` on stderr and exit
code 2; `--debug` shows the traceback instead.
"""

from __future__ import annotations

import os
import re
import sys
import time
from pathlib import Path
from typing import List, Optional

# numpy's OpenBLAS, before numpy loads it: one thread (unless the user says otherwise). Its
# products here are skinny ((N, 3) by (3, 3)) and gain nothing from a second thread, whose idle
# spinning then takes the core that torch, Open3D and export's writer need: refine's verdict
# took 0.79 s with it and 0.55 s without, an export 1.8 CPU seconds a photo instead of 1.1.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from rgbd_gt.heap import keep_freed_memory  # noqa: E402 - nothing heavy

keep_freed_memory()  # the aligner's big temporaries reused, not mapped afresh at every evaluation (rgbd_gt/heap.py)

import click
import numpy as np
import typer
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from rgbd_gt import __version__
from rgbd_gt.errors import InputError, require_listed

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Ground-truth RGB-D data from a terrestrial laser scan and photos.",
)
# a message is one line however long (logs and tools read them by line); tables wrap their cells
out = Console(soft_wrap=True)
err = Console(stderr=True, soft_wrap=True)
CACHE_HELP = ("Prepare the scan once into this folder (or reuse it: `run` keeps its own in OUTPUT/.scan-cache) and read "
              "only what this view needs: seconds instead of reading a large scan file again.")


def _version(value: bool) -> None:
    if value:
        out.print(f"rgbd-gt {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
    debug: bool = typer.Option(False, "--debug", help="Show full tracebacks and library diagnostics on errors."),
) -> None:
    """Ground-truth RGB-D data from a terrestrial laser scan and photos."""


def _parse_floats(text: str, n: int, what: str) -> list[float]:
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != n or not all(np.isfinite(values)):
        raise InputError(f"{what} must be {n} comma-separated numbers, got {text!r}")
    return values


def _check_ransac_px(value: float) -> None:
    # beyond a photo's size a threshold rejects nothing: a typo, not a choice
    if not (np.isfinite(value) and 0 < value <= 1000):
        raise InputError(f"--ransac-px must be over 0 and at most 1000 pixels, got {value:g}")


def _progress(*extra_columns) -> Progress:
    """A progress bar on stderr that leaves nothing behind (and prints nothing when not a terminal)."""
    return Progress(
        TextColumn("{task.description}"), BarColumn(), *extra_columns, TimeElapsedColumn(),
        console=err, transient=True, disable=not err.is_terminal,
    )


def _warn(message: str) -> None:
    err.print(f"warning: {message}", markup=False, highlight=False)


def _summary(title: str, rows: list[tuple[str, str]], output: Path, report: Optional[Path]) -> None:
    """The closing table of a command and where its outputs went."""
    table = Table(title=title, show_header=False)
    for key, value in rows:
        table.add_row(key, value)
    out.print(table)
    out.print(f"wrote {output}" + (f" and a report in {report}" if report else ""))


POSE_SUFFIXES = (".yaml", ".yml")  # pose and camera files are YAML

VERDICT_STYLE = {"ok": "green", "suspect": "yellow", "failed": "bold red"}


def _verdict_text(verdict: str | None) -> str:
    """A verdict as colored rich markup ('-' when there is none)."""
    return f"[{VERDICT_STYLE[verdict]}]{verdict}[/]" if verdict in VERDICT_STYLE else "-"


def _sigma_text(sigma: dict) -> str:
    """An evidence `uncertainty` (`verify.uncertainty`) as one line."""
    return f"{sigma['translation_mm']:.3f} mm, {sigma['rotation_deg']:.4f} deg, {sigma['image_px']:.3f} px"


def _fmt_bounds(b: np.ndarray) -> str:
    if not np.isfinite(b).all():
        return "-"
    return " .. ".join("(" + ", ".join(f"{v:.2f}" for v in row) + ")" for row in b)


@app.command()
def ingest(
    scans: List[Path] = typer.Argument(..., help="Scan files (.e57, .ply, .pcd or KITTI .bin); several are merged in one world frame, keeping the fields (colors, intensity, grid, normals) that every one has."),
    output: Path = typer.Option(..., "-o", "--output", help="Output PLY (binary little-endian)."),
    scan_index: Optional[int] = typer.Option(None, "--scan-index", help="Read only this scan (0-based) of each E57 file."),
    voxel: Optional[float] = typer.Option(None, "--voxel", help="Voxel size in metres for downsampling (averages colors and intensity)."),
    crop: Optional[str] = typer.Option(None, "--crop", help="Keep points in the box xmin,ymin,zmin,xmax,ymax,zmax (metres)."),
    extract_images: Optional[Path] = typer.Option(None, "--extract-images", help="Folder for the images embedded in E57 files."),
) -> None:
    """Merge scans, optionally crop and downsample, write a PLY and extract embedded images."""
    from rgbd_gt.ingest import ingest as run_ingest
    from rgbd_gt.io.outputs import Outputs

    outs = Outputs(scans)
    staged = outs.file(output, "-o", (".ply",))
    images_dir = outs.folder(extract_images, "--extract-images") if extract_images else None
    box = None
    if crop is not None:
        v = _parse_floats(crop, 6, "--crop")
        box = (np.array(v[:3]), np.array(v[3:]))
        if np.any(box[0] > box[1]):
            raise InputError(f"--crop minimum exceeds maximum: {crop}")
    if voxel is not None and not voxel > 0:
        raise InputError(f"--voxel must be positive, got {voxel}")

    with _progress(TextColumn("{task.completed:,.0f}/{task.total:,.0f} points")) as bar:
        tasks: dict[Path, int] = {}

        def progress(path: Path, done: int, total: int) -> None:
            if path not in tasks:
                tasks[path] = bar.add_task(f"reading {path.name}", total=total)
            bar.update(tasks[path], completed=done)

        with outs:
            result = run_ingest(list(scans), staged, scan_index, voxel, box, images_dir, progress)
    for im in result.images:
        if im.saved_to:
            im.saved_to = str(extract_images / Path(im.saved_to).relative_to(images_dir))

    table = Table(title="Scans")
    for col in ("scan", "points", "fields", "bounds min .. max (m)", "spacing (mm)"):
        table.add_column(col, justify="right" if col in ("points", "spacing (mm)") else "left")
    for s in result.inputs + [result.output]:
        style = "bold" if s is result.output else None
        table.add_row(s.label, f"{s.points:,}", " ".join(s.fields), _fmt_bounds(s.bounds), f"{s.spacing_m * 1e3:.2f}", style=style)
    out.print(table)
    if result.images:
        it = Table(title="Embedded images")
        for col in ("file", "name", "kind", "size", "format", "pose", "saved to"):
            it.add_column(col)
        for im in result.images:
            saved = im.saved_to or "(use --extract-images)"
            if im.problem:
                saved += f" [yellow]({im.problem})[/]"
            it.add_row(im.source, im.name, im.kind, f"{im.width}x{im.height}", im.format, "yes" if im.has_pose else "no", saved)
        out.print(it)
    else:
        out.print("Embedded images: none")
    for w in result.warnings:
        _warn(w)
    out.print(f"wrote {output} ({result.output.points:,} points)")


@app.command()
def synth(
    out_dir: Path = typer.Argument(..., help="Folder for the scene files (created if missing)."),
    seed: int = typer.Option(0, "--seed", help="Random seed: the same seed gives the same files."),
    size: str = typer.Option("default", "--size", help="'default' (1280x960 photo, 0.1 deg scan) or 'small' (640x480, 0.15 deg)."),
    config: Optional[Path] = typer.Option(None, "--config", help="Scene settings YAML (default: configs/synth.yaml)."),
    photos: int = typer.Option(1, "--photos", help="Photos of the scan from nearby places (photo.png, photo_1.png, ...); with --rig, shots of the rig."),
    rig: Optional[str] = typer.Option(None, "--rig", help="'stereo': every shot is taken by a stereo rig, whose second camera (camera_right.yaml, right.png, right_1.png, ...) has its own lens and colors; rig_gt.yaml holds the true T_right_from_left."),
    baseline: float = typer.Option(0.12, "--baseline", help="With --rig stereo: the distance between the rig's cameras, metres."),
) -> None:
    """Generate a synthetic scene with exact ground truth: a laser scan (E57 + PLY), a photo,
    its camera file, the true and a rough initial pose, and the board's 3D corners. With several
    photos or a rig, bundle.yaml lists them for `refine --bundle` (docs/bundle.md)."""
    from rgbd_gt.config import load_config
    from rgbd_gt.io.outputs import Outputs
    from rgbd_gt.synth.generate import FILES, SynthConfig, generate

    outs = Outputs({"--config": config})
    staged = outs.folder(out_dir, "OUT_DIR")
    cfg = load_config(SynthConfig, config, "synth.yaml")
    if size not in cfg.sizes:  # checked here too, to name the option and the config that lacks it
        raise InputError(f"--size '{size}' is not among the sizes {config or 'configs/synth.yaml'} defines "
                         f"({', '.join(cfg.sizes) or 'none'})")
    if photos < 1:
        raise InputError(f"--photos must be at least 1, got {photos}")
    if seed < 0:
        raise InputError(f"--seed must be 0 or more, got {seed}")
    if not 0.01 <= baseline <= 2.0:
        raise InputError(f"--baseline must lie in 0.01..2 m, got {baseline}")
    start = time.perf_counter()
    with _progress() as bar, outs:
        task = bar.add_task("synth", total=None)
        info = generate(staged, seed, size, cfg, progress=lambda stage: bar.update(task, description=stage), photos=photos,
                        rig=rig, baseline_m=baseline)
    table = Table(title=f"Synthetic scene (seed {seed}, {size})", show_header=False)
    table.add_row("scan points", f"{info['scanner']['points']:,} ({info['scanner']['grid']['rows']} x {info['scanner']['grid']['cols']} grid, {info['scanner']['step_deg']} deg)")
    table.add_row("photo", f"{info['image']['width']} x {info['image']['height']}")
    table.add_row("camera to scanner", f"{info['camera']['distance_to_scanner_m']:.2f} m")
    table.add_row("camera to board", f"{info['camera']['distance_to_board_m']:.2f} m")
    table.add_row("time", f"{time.perf_counter() - start:.1f} s")
    out.print(table)
    out.print(f"wrote {', '.join(FILES)} in {out_dir}")


def _board_shape(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--board must look like 9x6 (inner corners), got '{text}'") from None
    if not (2 <= cols <= 100 and 2 <= rows <= 100):
        raise InputError(f"--board needs 2..100 inner corners each way, got '{text}'")
    return cols, rows


@app.command("init-pose")
def init_pose(
    scan: Path = typer.Option(..., "--scan", help="The colored (or intensity) scan, .ply or .e57."),
    image: Path = typer.Option(..., "--image", help="The photo."),
    camera: Path = typer.Option(..., "--camera", help="Camera file (with --estimate-focal, its focal length is ignored)."),
    output: Path = typer.Option(..., "-o", "--output", help="Initial pose file to write (T_cam_from_scan)."),
    board: str = typer.Option("9x6", "--board", help="Inner corners of the checkerboard, COLSxROWS."),
    square: float = typer.Option(0.05, "--square", help="Checkerboard square size in metres."),
    board_points: Optional[Path] = typer.Option(None, "--board-points", help="CSV x,y,z of the board's inner corners in the scan frame (OpenCV order), instead of finding them in the scan."),
    correspondences: Optional[Path] = typer.Option(None, "--correspondences", help="CSV u,v,x,y,z of hand-picked photo pixels and scan points (>= 6): RANSAC PnP, no board needed."),
    charuco: Optional[str] = typer.Option(None, "--charuco", help="A ChArUco board of this ArUco dictionary (e.g. DICT_5X5_100) instead of a checkerboard."),
    marker: Optional[float] = typer.Option(None, "--marker", help="ChArUco marker side in metres (default 0.75 x square)."),
    estimate_focal: bool = typer.Option(False, "--estimate-focal", help="With --correspondences: also estimate the focal length (fx = fy; principal point from the camera file, no distortion), for photos without calibration."),
    camera_out: Optional[Path] = typer.Option(None, "--camera-out", help="With --estimate-focal: write the camera with the estimated focal here (YAML), for refine and export-depth."),
    ransac_px: float = typer.Option(4.0, "--ransac-px", help="With --correspondences: a pair farther than this (pixels) from where the pose puts its scan point is an outlier. Hand picks on a photo of several megapixels may need 10-40."),
    report: Optional[Path] = typer.Option(None, "--report", help="Folder for the photo with its corners or picks (used / dropped) and their reprojections, and the virtual scan view."),
    cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP + " The board found in the scan is kept there too: the next photo of this scan skips the search."),
) -> None:
    """Coarse pose of a photo from a checkerboard seen in both the photo and the scan (PnP), or
    from hand-picked correspondences (RANSAC PnP)."""
    from rgbd_gt.init.detect import MAX_SQUARE_M, BoardSpec
    from rgbd_gt.init.run import read_board_corners, write_report
    from rgbd_gt.io import write_pose
    from rgbd_gt.io.outputs import Outputs
    from rgbd_gt.prepared import prepare_scan
    from rgbd_gt.steps import init_step, made_from, open_photo

    outs = Outputs({"--scan": scan, "--image": image, "--camera": camera, "--board-points": board_points,
                    "--correspondences": correspondences})
    pose_out = outs.file(output, "-o", POSE_SUFFIXES)
    if camera_out is not None:
        if not estimate_focal:
            raise InputError("--camera-out writes the camera of --estimate-focal: give both")
        staged_camera = outs.file(camera_out, "--camera-out", POSE_SUFFIXES)
    report_dir = outs.folder(report, "--report") if report is not None else None
    outs.checked_folder(cache, "--cache")
    _check_ransac_px(ransac_px)
    cols, rows = _board_shape(board)
    if not 0 < square <= MAX_SQUARE_M:
        raise InputError(f"--square must lie between 0 and {MAX_SQUARE_M:g} m, got {square}")
    if marker is not None and not 0 < marker < square:  # OpenCV's board raises a SystemError on it
        raise InputError(f"--marker must lie between 0 and --square ({square:g} m), got {marker:g}")
    if charuco is not None:
        import cv2

        if not hasattr(cv2.aruco, charuco):
            raise InputError(f"--charuco: unknown ArUco dictionary '{charuco}' (e.g. DICT_5X5_100)")
    if estimate_focal and correspondences is None:
        raise InputError("--estimate-focal needs --correspondences")
    opened = open_photo(image, camera)
    corners = read_board_corners(board_points) if board_points and correspondences is None else None
    with _progress() as bar:
        bar.add_task("init-pose", total=None)
        prepared = prepare_scan(scan, cache)
        result, upright = init_step(prepared, opened, image, BoardSpec(cols, rows, square, charuco, marker), corners,
                                    correspondences, estimate_focal, ransac_px)
    files = {"photo": image, "camera": camera} | ({"board_points": board_points} if board_points else {})
    board_layout = None
    if correspondences is not None:
        files["correspondences"] = correspondences
    else:
        board_layout = (cols, rows, square, charuco, marker)
    made = made_from(scan, prepared.sha1, files, board_layout)
    meta = result.pose_meta() | (upright.as_dict() if upright is not None else {}) | made
    with outs:
        if camera_out is not None:
            from rgbd_gt.io.camera_file import write_camera

            write_camera(staged_camera, result.camera)
            meta["camera_out"] = str(camera_out)
        write_pose(pose_out, result.T_cam_from_scan, **meta)
        if report is not None:
            write_report(report_dir, result, opened.image)
    rows = [("method", result.method), ("points used", str(result.n_points)),
            ("reprojection RMS", f"{result.reprojection_rms_px:.3f} px")]
    dropped = [p for p in result.extra.get("pairs", []) if not p["inlier"]]
    if dropped:
        rows.append((f"dropped ({len(dropped)})", ", ".join(
            f"{p['label']} ({p['residual_px']:.1f} px)" if p["residual_px"] is not None else p["label"] for p in dropped)))
    if result.color_agreement is not None:
        rows.append(("color agreement", f"{result.color_agreement:.2f}"))
    if result.extra.get("estimated_focal_px"):
        sigma = (result.uncertainty or {}).get("focal_px")
        rows.append(("estimated focal", f"{result.extra['estimated_focal_px']:.1f} px" + (f" (1 sigma {sigma:.1f} px)" if sigma else "")))
    if upright is not None:
        rows.append(("verticals", upright.summary()))
    rows.append(("time", f"{result.seconds:.1f} s"))
    _summary("init-pose", rows, output, report)
    if camera_out is not None:
        out.print(f"wrote {camera_out}")


@app.command()
def pick(
    scan: Path = typer.Option(..., "--scan", help="The scan (.ply, .e57, .pcd or KITTI .bin)."),
    image: Path = typer.Option(..., "--image", help="The photo."),
    output: Path = typer.Option(..., "-o", "--output", help="PAIRS.csv to write (u,v,x,y,z,label; init-pose --correspondences and refine --check read it). When it exists, its pairs are loaded to go on with."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Camera file of the photo: with 6 or more pairs the page then solves the pose live (RANSAC PnP, as init-pose) and shows the scan over the photo."),
    init: Optional[Path] = typer.Option(None, "--init", help="A pose to render the scan from with the photo's camera (the view closest to the photo)."),
    view: str = typer.Option("auto", "--view", help="The scan image to click on: grid (the structured scan's own grid), panorama (rendered from the scan origin), pose (rendered at --init; for LiDAR sweeps (no grid; a ring field, or points on rings of fixed elevation about the sensor) the points seen from it as dots) or auto (pose with --init, else grid, else panorama)."),
    estimate_focal: bool = typer.Option(False, "--estimate-focal", help="Estimate the focal length in the live solve (photos without calibration; --camera then gives the image size and principal point)."),
    ransac_px: float = typer.Option(4.0, "--ransac-px", help="Outlier threshold of the live solve (pixels)."),
    port: int = typer.Option(0, "--port", help="Port on 127.0.0.1 (0: any free one)."),
    no_browser: bool = typer.Option(False, "--no-browser", help="Do not open the page in a browser (the address is printed)."),
    cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP),
) -> None:
    """Pick correspondences between the photo and the scan in a local web page: the photo on the
    left, the scan as an image on the right; a click in each makes a pair. Saving writes
    PAIRS.csv; the command ends when the page says 'Save and close' (or on Ctrl-C)."""
    from rgbd_gt.init.pick import click_view
    from rgbd_gt.init.pick_server import PickSession, serve
    from rgbd_gt.init.run import read_correspondences
    from rgbd_gt.io import read_pose
    from rgbd_gt.io.image import read_image
    from rgbd_gt.io.outputs import Outputs
    from rgbd_gt.steps import open_photo

    # checked only: the page saves the file itself (atomically) each time it is asked to
    outs = Outputs({"--scan": scan, "--image": image, "--camera": camera, "--init": init})
    outs.file(output, "-o", (".csv",))
    outs.checked_folder(cache, "--cache")
    _check_ransac_px(ransac_px)
    if estimate_focal and camera is None:
        raise InputError("--estimate-focal needs --camera (for the image size and principal point)")
    if camera is None:
        photo, cam = read_image(image), None
    else:
        opened = open_photo(image, camera)
        photo, cam = opened.image, opened.camera
    T_init = read_pose(init)[0] if init is not None else None
    if T_init is not None and cam is None:
        raise InputError("--init needs --camera (the view is rendered with the photo's camera)")
    pairs = []
    if output.exists():
        picks = read_correspondences(output, minimum=1)
        pairs = [{"u": a[0], "v": a[1], "x": b[0], "y": b[1], "z": b[2], "label": lab}
                 for a, b, lab in zip(picks.img.tolist(), picks.obj.tolist(), picks.labels)]
    with _progress() as bar:
        bar.add_task("preparing the scan image", total=None)
        from rgbd_gt.prepared import whole_scan

        the_scan = whole_scan(scan, cache)
        clicks = click_view(the_scan, view, cam, T_init)
        for pair in pairs:  # draw loaded pairs where their scan points are in the scan image
            px = clicks.pixel_of([pair["x"], pair["y"], pair["z"]])
            if px is not None:
                pair["sx"], pair["sy"] = px
    session = PickSession(the_scan, photo, clicks, output, cam, estimate_focal, ransac_px, pairs)

    def ready(url: str) -> None:
        out.print(f"serving the pick page on {url} (Ctrl-C to stop)")
        sys.stdout.flush()
        if not no_browser:
            import webbrowser

            webbrowser.open(url)

    try:
        serve(session, port, ready)
    except OSError as exc:
        raise InputError(f"--port {port}: cannot listen ({exc.strerror})") from None
    except KeyboardInterrupt:
        pass
    out.print(f"wrote {output} ({session.saved} pairs)" if session.saved else "no pairs saved")


@app.command()
def refine(
    scan: Optional[Path] = typer.Option(None, "--scan", help="The scan (.ply, .e57, .pcd or KITTI .bin; colored, or with intensity only), in the scan/world frame. Required unless --pairs lists the pairs."),
    image: Optional[Path] = typer.Option(None, "--image", help="The photo (its size must match the camera file). Required with --scan."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Camera file: YAML, ROS camera_info YAML, OpenCV calibration (Autoware's too), Kalibr's camchain of one camera, a calibration text file with K and D lines (PJLab, KITTI P2) or koide3's calib.json (docs/formats.md). Required unless --bundle."),
    init: Optional[Path] = typer.Option(None, "--init", help="Initial pose file (T_cam_from_scan), e.g. from init-pose, or a calibration text file with a T / Tr_velo_to_cam line, koide3's calib.json (results.T_lidar_camera), Autoware's calibration YAML (CameraExtrinsicMat) or a camchain with T_cam_lidar (docs/formats.md). Required unless --bundle."),
    output: Path = typer.Option(..., "-o", "--output", help="Refined pose file to write (with --bundle: a folder)."),
    bundle: Optional[Path] = typer.Option(None, "--bundle", help="A bundle file: several photos of one scan with their cameras, inits and (optionally) a rig, solved together: every pose, the camera corrections each camera's photos share, the rig's relative poses (docs/bundle.md). -o is then a folder: PHOTO/pose.yaml per photo, cameras/NAME.yaml, rig.yaml, bundle.json."),
    objective: Optional[str] = typer.Option(None, "--objective", help="photometric (the colored-scan aligner), nid (normalised information distance of intensity or gray against the photo's gray, for scans whose values relate to the photo only statistically: intensity-only LiDAR and laser scans) or auto (default: nid for intensity-only scans)."),
    pairs: Optional[Path] = typer.Option(None, "--pairs", help="YAML listing further (scan, image[, camera]) pairs that share the one pose (a LiDAR-camera rig over several frames): `pairs: [{scan: a.pcd, image: a.jpg}, ...]`, paths relative to the file. Solved jointly (nid)."),
    max_depth: Optional[float] = typer.Option(None, "--max-depth", help="Leave out scan points farther than this from the initial camera (metres; 0 = none)."),
    search_starts: Optional[int] = typer.Option(None, "--search-starts", help="nid: before the coarsest level, also run it from this many random starts around the init; the 3 of lowest NID (search_keep in the config) go on to level 1, where the lowest NID wins (default 16; 0 = none)."),
    config: Optional[Path] = typer.Option(None, "--config", help="Aligner settings (default: configs/refine.yaml)."),
    device: str = typer.Option("auto", "--device", help="auto (CUDA when present, but the CPU for nid on fewer than 5 frames solved together, which is faster there: docs/gpu.md), cpu or cuda."),
    report: Optional[Path] = typer.Option(None, "--report", help="Folder for a convergence plot and color-difference images."),
    mask: Optional[Path] = typer.Option(None, "--mask", help="Image of the photo's size: non-zero pixels are ignored (people, reflections)."),
    color_model: Optional[str] = typer.Option(None, "--color-model", help="quadratic (default), quadratic_rgb, linear, none, gray or gray_affine."),
    gradient: Optional[str] = typer.Option(None, "--gradient", help="direct (the bilinear interpolant's own derivative) or central."),
    optimizer: Optional[str] = typer.Option(None, "--optimizer", help="lm (Levenberg-Marquardt) or adam (the paper's)."),
    levels: Optional[int] = typer.Option(None, "--levels", help="Image pyramid levels (1 = full resolution only; default: as many as bring the coarsest level to 40-79 px across, 5 for nid)."),
    upsample: Optional[int] = typer.Option(None, "--upsample", help="Sample the photo enlarged this much (bicubic) at the finest level; 1 = as it is."),
    iterations: Optional[int] = typer.Option(None, "--iterations", help="Maximum iterations per pyramid level."),
    max_points: Optional[int] = typer.Option(None, "--max-points", help="Scan points used at full resolution."),
    beta_max: Optional[float] = typer.Option(None, "--beta-max", help="Color inlier threshold of the color fit."),
    check: Optional[Path] = typer.Option(None, "--check", help="CSV u,v,x,y,z of held-out picked pairs: their reprojection error at the init and after refine goes into the verdict."),
    repeats: Optional[int] = typer.Option(None, "--repeats", help="Refine again from this many starts around the init to check the result is reproduced (default 4; 0 skips it). Several frames of one rig (--pairs) are instead refined in groups apart from the result (verify.folds in the config); 0 skips that too."),
    strict: bool = typer.Option(False, "--strict", help="Exit with code 3 when the verdict is 'failed' (the pose file is still written, with the verdict)."),
    refine_intrinsics: Optional[str] = typer.Option(None, "--refine-intrinsics", help="Also refine the camera, for photos whose calibration is rough: focal, focal+principal, focal+principal+k1k2 or full (OpenCV's five distortion coefficients: k1 k2 p1 p2 k3) (default none). The refined camera goes into the pose file (intrinsics) and, with --camera-out, into a camera file."),
    camera_out: Optional[Path] = typer.Option(None, "--camera-out", help="With --refine-intrinsics: write the refined camera here (YAML), for export-depth and overlay."),
    cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP + " With `run`'s cache, refine is handed exactly the points (and normals) `run` refines on."),
) -> None:
    """Refine a photo's pose against the scan, then judge the result. Colored scans: multimodal
    photometric alignment; intensity-only scans (LiDAR sweeps, laser scans without color): NID
    between intensity and gray (--objective; docs/lidar.md measures both); several frames of
    one rig: --pairs. The verdict: the pose file gets `verdict` (ok | suspect | failed), `reasons` and
    `evidence` (uncertainty, convergence, repeatability, sharpness, a structural edge check
    against chance, and the --check pairs). See docs/trust.md."""
    from rgbd_gt.align.refine import read_pairs
    from rgbd_gt.init.run import check_picks, read_correspondences
    from rgbd_gt.io import write_pose
    from rgbd_gt.io.outputs import Outputs
    from rgbd_gt.prepared import prepare_scan
    from rgbd_gt.steps import load_inputs, refine_config, refine_step

    start = time.perf_counter()
    if bundle is not None:
        given = [name for name, v in (("--scan", scan), ("--image", image), ("--camera", camera), ("--init", init),
                                      ("--pairs", pairs), ("--check", check), ("--camera-out", camera_out), ("--mask", mask),
                                      ("--report", report), ("--refine-intrinsics", refine_intrinsics)) if v is not None]
        if given:
            raise InputError(f"--bundle lists the photos, cameras and inits: leave out {', '.join(given)} (a camera's "
                             "refine: and a photo's mask: go in the bundle file)")
        cfg = refine_config(config, repeats, color_model=color_model, gradient=gradient, optimizer=optimizer, levels=levels,
                            upsample=upsample, iterations=iterations, max_points=max_points, beta_max=beta_max,
                            objective=objective, max_depth=max_depth)
        return _refine_bundle(bundle, output, cfg, device, cache, strict, start)
    for name, value in (("--camera", camera), ("--init", init)):
        if value is None:
            raise InputError(f"{name} is required (or give --bundle)")
    if (scan is None) != (image is None):
        raise InputError("--scan and --image go together" + ("" if pairs else " (or list the pairs in --pairs)"))
    if scan is None and pairs is None:
        raise InputError("give --scan and --image, or --pairs")
    named = {"--scan": scan, "--image": image, "--camera": camera, "--init": init, "--mask": mask, "--check": check,
             "--config": config, "--pairs": pairs}
    Outputs(named)  # each named file checked before the --pairs list is read
    listed = read_pairs(pairs, camera) if pairs is not None else []
    outs = Outputs({**named, **{f"--pairs (pair {k}'s {key})": p for k, pair in enumerate(listed, 1) for key, p in pair.items()}})
    pose_out = outs.file(output, "-o", POSE_SUFFIXES)
    if camera_out is not None:
        if refine_intrinsics in (None, "none"):
            raise InputError("--camera-out writes the camera of --refine-intrinsics: give both")
        staged_camera = outs.file(camera_out, "--camera-out", POSE_SUFFIXES)
    report_dir = outs.folder(report, "--report") if report is not None else None
    outs.checked_folder(cache, "--cache")
    cfg = refine_config(config, repeats, color_model=color_model, gradient=gradient, optimizer=optimizer, levels=levels,
                        upsample=upsample, iterations=iterations, max_points=max_points, beta_max=beta_max,
                        objective=objective, max_depth=max_depth, search_starts=search_starts,
                        refine_intrinsics=refine_intrinsics)
    everything = ([dict(scan=scan, image=image, camera=camera)] if scan is not None else []) + listed
    # the check's picks may lie anywhere in the first scan, not only in the photo's view of the init
    first = prepare_scan(Path(everything[0]["scan"]), cache) if check is not None else None
    inputs = [load_inputs(p["scan"], p["image"], p["camera"], init, mask if k == 0 else None, cache,
                          first if k == 0 else None) for k, p in enumerate(everything)]
    held_out = None
    if check is not None:
        picks = read_correspondences(check, minimum=1)
        check_picks(picks, inputs[0].camera, first.bounds(), check, first.origins)
        held_out = (picks.img, picks.obj)
    with _progress(TextColumn("{task.fields[info]}")) as bar:
        task = bar.add_task("refine", total=None, info="")

        def progress(rec: dict) -> None:
            bar.update(task, description=f"level {rec['level']} iteration {rec['iteration']}",
                       info=f"loss {rec['loss']:.4f}  step {rec['rotation_update_deg']:.1e} deg {rec['translation_update_m'] * 1e3:.1e} mm")

        refined = refine_step(inputs[0], cfg, init, device, camera, progress, keep_residuals=report is not None,
                              check=held_out, more=inputs[1:])
    for w in refined.warnings:
        _warn(w)
    result, verification, meta = refined.result, refined.verification, refined.meta
    upright, upright_init = refined.verticals, refined.init_verticals
    with outs:
        if camera_out is not None:
            from rgbd_gt.io.camera_file import write_camera

            write_camera(staged_camera, refined.camera)
            meta["camera_out"] = str(camera_out)
        write_pose(pose_out, result.T_cam_from_scan, **meta)
        if report is not None:
            from rgbd_gt.align.report import write_report

            write_report(report_dir, result, inputs[0].camera.size)
    moved_mm, moved_deg = meta["change_from_init"]["translation_mm"], meta["change_from_init"]["rotation_deg"]
    ev = verification.evidence
    rows = [
        ("verdict", _verdict_text(verification.verdict)),
        *[("", reason) for reason in verification.reasons],
        ("moved from init", f"{moved_mm:.2f} mm, {moved_deg:.4f} deg"),
        ("uncertainty (1 sigma)", _sigma_text(ev["uncertainty"])),
        *([("uncertainty, photo tiles as samples", _sigma_text(ev["tiles"]["uncertainty"]))] if "tiles" in ev else []),
        ("edges vs chance", f"not usable: the scan is drawn with {ev['edges']['splat_radius_px']} px splats"
         if not ev["edges"]["edge_check_usable"] else f"{ev['edges']['edge_ratio']:.2f} (1.0 = chance)"
         if ev["edges"]["structural_edge_pixels"] else "not usable: no structural edges in view"),
    ]
    if "ring_edges" in ev:
        from rgbd_gt.align.edge_map import CHECK_MIN_STEP_M
        from rgbd_gt.align.verify import frame_verdict

        rings = ev["ring_edges"]
        rows.append(("ring edges vs chance", f"{rings['ratio']:.2f} over {rings['ring_edges']:,} depth steps (1.0 = chance)"
                     if rings["ring_edges"] else f"not usable: no depth steps of {CHECK_MIN_STEP_M:g} m or more along the rings in view"))
        for k in range(len(rings.get("frames") or [])):  # each frame of --pairs judged on its own edges too
            mine, why = frame_verdict("ok", [], rings, k, cfg.verify)
            if mine != "ok":
                rows.append((f"frame {k + 1}", f"{mine}: {why[0]}"))
    if "repeatability" in ev:
        rows.append(("repeat runs", f"{ev['repeatability']['starts']} starts, spread {ev['repeatability']['spread_px']:.3f} px"))
    if "frames" in ev:
        rows.append(("frames apart", f"{ev['frames']['folds']} groups end up to {ev['frames']['spread_px']:.2f} px "
                                     f"({ev['frames']['spread_mm']:.0f} mm, {ev['frames']['spread_deg']:.3f} deg) from the result"))
        if "uncertainty" in ev["frames"]:  # what the pose file's covariance states
            rows.append(("uncertainty, frames as samples", _sigma_text(ev["frames"]["uncertainty"])))
        loo = ev["frames"].get("leave_one_out")
        if loo is not None:
            rows.append(("each frame left out", f"the result moves up to {loo['worst_left_out_px']:.2f} px (frame "
                                                f"{loo['worst_frame'] + 1}); {loo['frames_with_minimum']} of "
                                                f"{len(loo['left_out_px'])} frames alone have a minimum, median "
                                                f"{loo['median_own_minimum_px']:.1f} px from it"))
    if "check" in ev:
        rows.append(("check pairs", f"{ev['check']['rms_init_px']:.2f} px at the init -> {ev['check']['rms_px']:.2f} px"))
    if "camera_unchecked" in ev:
        rows.append(("camera file", f"not checked (nid): each 1% off in focal moves the pose about "
                                    f"{ev['camera_unchecked']['axis_mm_per_focal_percent']:.0f} mm along the camera's axis"))
    rows += [("verticals at init", upright_init.summary()), ("verticals", upright.summary())]
    if "intrinsics" in meta:
        intr, sig = meta["intrinsics"], meta["intrinsics"]["sigma"]
        rows.append(("camera refined", f"fx {intr['fx']:.2f} px ({intr['change']['focal_percent']:+.2f}%, 1 sigma "
                                       f"{sig['focal_px']:.2f} px), cx {intr['cx']:.1f}, cy {intr['cy']:.1f}"
                     + (f", k1 {intr['distortion'][0]:.4f}, k2 {intr['distortion'][1]:.4f}" if "k1" in sig else "")))
    rows += [
        ("iterations", str(result.iterations)),
        ("visible points", f"{result.visible_points:,} (inliers {result.inlier_fraction:.0%})" if result.objective == "photometric"
         else f"{result.visible_points:,} over {len(inputs)} pair(s), NID {result.loss:.4f}"),
        ("aligner time", f"{result.seconds:.2f} s + verification {verification.seconds:.2f} s (total {time.perf_counter() - start:.2f} s)"),
    ]
    _summary("refine", rows, output, report)
    if camera_out is not None:
        out.print(f"wrote {camera_out}")
    if strict and verification.verdict == "failed":
        raise typer.Exit(3)


def _refine_bundle(bundle: Path, output: Path, cfg, device: str, cache: Optional[Path], strict: bool, start: float) -> None:
    """refine --bundle: the photos solved together (`steps.bundle_step`), their files into the folder `output`."""
    from rgbd_gt.io.bundle_file import read_bundle
    from rgbd_gt.io.outputs import Outputs
    from rgbd_gt.steps import bundle_step, write_bundled

    Outputs({"--bundle": bundle})  # checked before it is read, as its files are before any work
    spec = read_bundle(bundle)
    require_listed(spec.named_files(), bundle)  # here, not in read_bundle: export reads it without its inits
    outs = Outputs([bundle] + spec.files())
    staged = outs.folder(output, "-o", whole=True)  # each photo's folder and cameras/ replaced, not mixed in
    outs.checked_folder(cache, "--cache")
    stems = {e.image.stem for e in spec.photos}
    earlier = sorted(f"{f.parent.name}/" for f in output.glob("*/pose.yaml") if f.parent.name not in stems)
    earlier += ["rig.yaml"] * (not spec.rig and (output / "rig.yaml").is_file())
    with _progress() as bar:
        task = bar.add_task("bundle", total=None)
        done = bundle_step(spec, cfg, device, cache, progress=lambda message: bar.update(task, description=message))
    with outs:
        write_bundled(staged, spec, done, bundle, time.perf_counter() - start)
    r = done.result
    table = Table(title=f"refine --bundle: {len(spec.photos)} photos", show_lines=False)
    for col in ("photo", "verdict", "moved from init", "left out", "residual vs others"):
        table.add_column(col)
    for e, d in zip(spec.photos, done.photos):
        ev, moved = d.verification.evidence["bundle"], d.meta["change_from_init"]
        loo = ev.get("leave_one_out_sigmas")
        table.add_row(e.image.name, _verdict_text(d.verification.verdict),
                      f"{moved['translation_mm']:.2f} mm, {moved['rotation_deg']:.4f} deg",
                      "-" if loo is None else f"{loo:.1f} sigma",
                      f"{ev['residual_vs_others']:.2f}" if "residual_vs_others" in ev else "-")
    out.print(table)
    for e, d in zip(spec.photos, done.photos):
        for reason in d.verification.reasons:
            out.print(f"  {e.image.name}: {reason}")
    for name, (camera, keys) in done.cameras.items():
        if keys["refined"] != "none":
            out.print(f"camera {name}: fx {camera.fx:.2f} px (1 sigma {keys['sigma'].get('focal_px', float('nan')):.2f}), "
                      f"cx {camera.cx:.1f}, cy {camera.cy:.1f}, distortion {[round(v, 4) for v in camera.distortion]}")
    if done.rig is not None:
        for name, rel in done.rig["relative"].items():
            out.print(f"rig {name} from {done.rig['reference']}: baseline {rel['baseline_m'] * 1e3:.2f} mm "
                      f"(1 sigma {max(rel['sigma']['translation_mm']):.3f} mm)")
    if earlier:
        out.print(f"kept from an earlier solve: {', '.join(earlier)} (bundle.json lists only this bundle's photos)")
    out.print(f"solved in {r.seconds:.1f} s ({r.iterations} iterations), {time.perf_counter() - start:.1f} s in all; wrote {output}")
    if strict and any(d.verification.verdict == "failed" for d in done.photos):
        raise typer.Exit(3)


@app.command("export-depth")
def export_depth(
    scan: Path = typer.Option(..., "--scan", help="The scan (.ply, .e57, .pcd or KITTI .bin)."),
    camera: Path = typer.Option(..., "--camera", help="Camera file of the photo (the depth map has its size and distortion)."),
    pose: Path = typer.Option(..., "--pose", help="Pose file (T_cam_from_scan), e.g. from refine."),
    output: Path = typer.Option(..., "-o", "--output", help="Depth map to write (.exr, channel Z, metres, 0 = no depth)."),
    image: Optional[Path] = typer.Option(None, "--image", help="The photo: its size is taken for a camera file that holds none (a calibration text or JSON file) and checked against one that does."),
    png16: Optional[Path] = typer.Option(None, "--png16", help="Also a 16-bit PNG in millimetres (0 = no depth)."),
    normals: Optional[Path] = typer.Option(None, "--normals", help="Also the camera-frame normals as an EXR (N.X, N.Y, N.Z)."),
    mask: Optional[Path] = typer.Option(None, "--mask", help="Also a validity mask PNG (255 where there is depth)."),
    max_depth: Optional[float] = typer.Option(None, "--max-depth", help="Depths beyond this (metres) are left out (0: no limit)."),
    points: Optional[bool] = typer.Option(None, "--points/--surfaces", help="Depth of the scan's points alone, each at its own pixel (sparse: nothing between them), or of the surfaces rendered from them. Default: points for LiDAR sweeps (no grid; a ring field, or points on rings of fixed elevation about the sensor), whose rings are too far apart for surfaces; surfaces otherwise (a dense scan without its grid included)."),
    cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP),
) -> None:
    """Depth of the scan as the photo's camera sees it, pixel for pixel with the original photo:
    z-depth in metres, occlusion-correct (a grid mesh ray-cast, or surfels for unstructured scans;
    a LiDAR sweep's own points, sparse)."""
    from rgbd_gt.io import read_camera, read_pose
    from rgbd_gt.io.outputs import Outputs
    from rgbd_gt.prepared import scan_in_view
    from rgbd_gt.render.depth import back_facing_fraction, back_facing_warning
    from rgbd_gt.steps import depth_step, open_photo, write_depth

    outs = Outputs({"--scan": scan, "--camera": camera, "--pose": pose, "--image": image})
    staged = {name: outs.file(p, option, suffixes) for name, p, option, suffixes in [
        ("exr", output, "-o", (".exr",)), ("png16", png16, "--png16", (".png",)),
        ("normals", normals, "--normals", (".exr",)), ("mask", mask, "--mask", (".png",))] if p is not None}
    outs.checked_folder(cache, "--cache")
    if max_depth is not None and max_depth < 0:
        raise InputError(f"--max-depth must be positive (0: no limit), got {max_depth}")
    start = time.perf_counter()
    cam = open_photo(image, camera).camera if image else read_camera(camera)
    T, _ = read_pose(pose)
    the_scan = scan_in_view(scan, cam, [T], cache)
    with _progress() as bar:
        bar.add_task("rendering depth", total=None)
        depth = depth_step(the_scan, cam, T, max_depth, points, normals is not None, pose)
    valid = depth.z > 0
    warning = back_facing_warning(depth)
    if warning:
        _warn(warning)
    with outs:
        write_depth(depth, cam, T, scan.name, **staged)
    zs = depth.z[valid]
    _summary("export-depth", [
        ("method", depth.method),
        ("size", f"{cam.width} x {cam.height}"),
        ("pixels with depth", f"{valid.mean():.1%}"),
        ("seen from behind", "not culled: the scan records no scanner position, so its surfaces have no known side" if depth.back_facing is None
         else f"{depth.back_facing:,} pixels ({back_facing_fraction(depth):.1%} of the scan's view), written as 0"),
        ("depth range", f"{zs.min():.3f} .. {zs.max():.3f} m (median {np.median(zs):.3f})"),
        ("time", f"{time.perf_counter() - start:.1f} s"),
    ], output, None)


@app.command("qa-edges")
def qa_edges(
    scan: Path = typer.Option(..., "--scan", help="The scan (.ply, .e57, .pcd or KITTI .bin)."),
    image: Path = typer.Option(..., "--image", help="The photo."),
    camera: Path = typer.Option(..., "--camera", help="Camera file of the photo."),
    pose: Path = typer.Option(..., "--pose", help="The pose to check (T_cam_from_scan)."),
    output: Path = typer.Option(..., "-o", "--output", help="Overlay PNG (longer side at most 1280 px): red = the photo's strongest gradients, blue = the scan's structural edges, white = both."),
    before: Optional[Path] = typer.Option(None, "--before", help="Another pose (e.g. the initial one): a before/after panel."),
    json_out: Optional[Path] = typer.Option(None, "--json", help="Also write the scores as JSON."),
    cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP),
) -> None:
    """How well the scan rendered at the pose lines up with the photo. The structural score: the
    photo's gradient strength at the scan's structural edges (depth discontinuities, strong color
    edges) against the same with those edges shifted by 6 px (edge_ratio; 1.0 = no better than
    chance). The Canny score: how far the scan's Canny edges lie from the photo's (median/mean
    distance in pixels, fraction within 1 px); on busy real photos it is close to chance. Both
    say nothing for a scan too sparse for its splats (a LiDAR sweep): they are then marked
    unusable (null in --json). The verticals check measures geometry alone, sweeps included: how
    far the pose is rolled about the optical axis off the scan's vertical: the photo's vertical
    lines (poles, building and door edges, within 12 deg of the image's vertical) against the
    scan's own (its pole-like columns, with z roughly up); null where either has too few. For a
    sweep, the ring-edge check the verdict takes for each frame: the photo's edge strength at the
    sweep's depth steps of 1 m and more along its rings against the same shifted by 6 px
    (ring_edge_ratio; 1.0 = chance)."""
    from rgbd_gt.io import read_pose
    from rgbd_gt.io.image import IMAGE_SUFFIXES, write_image
    from rgbd_gt.io.outputs import Outputs
    from rgbd_gt.scan import scan_colors
    from rgbd_gt.prepared import view_and_around
    from rgbd_gt.io.json_text import json_text
    from rgbd_gt.qa.verticals import MAX_POINTS, REACH
    from rgbd_gt.render.renders import Renders
    from rgbd_gt.steps import open_photo, qa_step

    outs = Outputs({"--scan": scan, "--image": image, "--camera": camera, "--pose": pose, "--before": before})
    staged = outs.file(output, "-o", IMAGE_SUFFIXES)
    staged_json = outs.file(json_out, "--json", (".json",)) if json_out else None
    outs.checked_folder(cache, "--cache")
    photo = open_photo(image, camera)
    T, _ = read_pose(pose)
    poses = [T] + ([read_pose(before)[0]] if before else [])
    the_scan, around = view_and_around(scan, photo.camera, poses, REACH, MAX_POINTS, cache)
    renders = Renders(the_scan, scan_colors(the_scan, scan), poses)  # one ray-casting scene for both poses
    with _progress() as bar:
        bar.add_task("edges", total=None)
        result = qa_step(renders, photo.image, photo.camera, T, around, poses[1] if before else None, pose, before)
    with outs:
        write_image(staged, result.image)
        if json_out:
            staged_json.write_text(json_text(result.scores))
    _summary("qa-edges", result.rows, output, None)


@app.command()
def overlay(
    scan: Path = typer.Option(..., "--scan", help="The scan (.ply, .e57, .pcd or KITTI .bin)."),
    image: Path = typer.Option(..., "--image", help="The photo."),
    camera: Path = typer.Option(..., "--camera", help="Camera file of the photo."),
    pose: Path = typer.Option(..., "--pose", help="The pose to show (T_cam_from_scan), e.g. from refine."),
    output: Path = typer.Option(..., "-o", "--output", help="Checkerboard PNG at the photo's resolution: squares alternate between the photo and the scan rendered at the pose (edges must run on across square borders). The 50% blend goes beside it as OVERLAY_blend.png, and (see --points) the visible scan points as dots as OVERLAY_points.png."),
    points: Optional[bool] = typer.Option(None, "--points/--no-points", help="Also draw the visible scan points as dots of their color or intensity over the dimmed photo (OVERLAY_points.png): the picture to read for a sparse LiDAR sweep, whose rendered surfaces are blobs between its rings. Default: for LiDAR sweeps (no grid; a ring field, or points on rings of fixed elevation about the sensor)."),
    max_depth: Optional[float] = typer.Option(None, "--max-depth", help="Leave out scan surfaces farther than this (metres; 0: no limit)."),
    cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP),
) -> None:
    """The scan rendered at the pose over the photo, as a checkerboard, as a 50% blend and (for
    sweeps, or with --points) as dots of the visible points, full resolution (crop to inspect):
    the most direct check of a pose. Surfaces the camera would see from behind are not drawn."""
    from concurrent.futures import ThreadPoolExecutor

    from rgbd_gt.io import read_pose
    from rgbd_gt.io.image import write_image
    from rgbd_gt.io.outputs import Outputs
    from rgbd_gt.prepared import scan_in_view
    from rgbd_gt.render.renders import Renders
    from rgbd_gt.scan import scan_colors
    from rgbd_gt.steps import open_photo, overlay_paths, overlay_step

    start = time.perf_counter()
    paths = overlay_paths(output)
    outs = Outputs({"--scan": scan, "--image": image, "--camera": camera, "--pose": pose})
    staged = {k: outs.file(p, "-o" if k == "checker" else f"-o (its {k})", (".png",)) for k, p in paths.items()}
    outs.checked_folder(cache, "--cache")
    if max_depth is not None and max_depth < 0:
        raise InputError(f"--max-depth must be positive (0: no limit), got {max_depth}")
    photo = open_photo(image, camera)
    T, _ = read_pose(pose)
    the_scan = scan_in_view(scan, photo.camera, [T], cache)
    with _progress() as bar:
        bar.add_task("rendering the scan", total=None)
        pictures = overlay_step(Renders(the_scan, scan_colors(the_scan, scan)), photo.image, photo.camera, T, max_depth,
                                points, pose)
    images = {k: getattr(pictures, k) for k in paths if getattr(pictures, k) is not None}
    with outs, ThreadPoolExecutor(3) as pool:  # PNG encoding releases the GIL: the images at once
        list(pool.map(lambda k: write_image(staged[k], images[k]), images))
    rows = [("size", f"{photo.camera.width} x {photo.camera.height}"), ("scan covers", f"{pictures.covered:.1%} of the photo")]
    if pictures.points is not None:
        rows.append(("points drawn", f"{pictures.drawn:,}"))
    _summary("overlay", rows + [("time", f"{time.perf_counter() - start:.1f} s")], output, None)
    for k in images:
        if k != "checker":
            out.print(f"wrote {paths[k]}")
    if pictures.points is None and paths["points"].exists():
        _warn(f"{paths['points']} is left from an earlier run and may show another pose (--points redraws it)")


@app.command("export")
def export_dataset(
    run_dir: Path = typer.Argument(..., help="A finished run: the output folder of `rgbd-gt run` (run.json) or of `rgbd-gt refine --bundle` (bundle.json; rigs give stereo pairs)."),
    output: Path = typer.Option(..., "-o", "--output", help="Folder to write the data set into, one sub-folder per format, with export.json and report.html."),
    formats: list[str] = typer.Option(..., "--format", "-f", help="plain | colmap | nerfstudio | middlebury | kitti; repeat the option or separate by commas for several (docs/export.md)."),
    include: list[str] = typer.Option([], "--include", help="Also export photos with this verdict: suspect (or failed); repeatable. Only `ok` photos by default."),
    points: Optional[bool] = typer.Option(None, "--points/--surfaces", help="Depth of the scan's points alone (sparse) or of the surfaces rendered from them; by default as export-depth chooses (points for LiDAR sweeps)."),
    cache: Optional[Path] = typer.Option(None, "--cache", help=CACHE_HELP + " Default: the run's own cache when it has one."),
) -> None:
    """A finished run as a data set: per photo the undistorted pinhole photo beside the original,
    depth (EXR metres, PNG millimetres), a validity mask, the depth's 1-sigma per pixel (the
    pose's and camera's covariance carried to each pixel) and normals (plain); a COLMAP text
    model; nerfstudio's transforms.json; rectified stereo pairs with disparity (middlebury,
    kitti) from a rig. Also report.html, a page to judge the run by eye."""
    from rgbd_gt.engine import CACHE_FOLDER
    from rgbd_gt.export.dataset import FORMATS, export_run
    from rgbd_gt.export.source import read_run
    from rgbd_gt.io.outputs import Outputs

    start = time.perf_counter()
    chosen = [f.strip() for f in ",".join(formats).split(",") if f.strip()]
    verdicts = ("ok", *[v for v in include if v != "ok"])
    bad = [v for v in verdicts[1:] if v not in ("suspect", "failed")]
    if bad:  # quoted: an empty value reads as one
        raise InputError(f"--include takes suspect or failed, got {', '.join(map(repr, bad))}")
    sources = read_run(run_dir)
    if output.resolve() == run_dir.resolve():
        raise InputError("-o: is the run's own folder (its report.html would be replaced); give another", output)
    outs = Outputs([run_dir / n for n in ("run.json", "bundle.json")] + [s.scan for s in sources]
                   + [p.image for s in sources for p in s.photos])
    staged = outs.folder(output, "-o", whole=True)  # an earlier export's format folders are replaced, not mixed in
    if cache is None and (run_dir / CACHE_FOLDER).is_dir():
        cache = run_dir / CACHE_FOLDER
    outs.checked_folder(cache, "--cache")
    with outs, _progress() as bar:
        task = bar.add_task("export", total=None)

        def progress(what: str, done: int, total: int) -> None:
            bar.update(task, description=f"export {what}", completed=done, total=total)

        done = export_run(run_dir, staged, chosen, verdicts, cache, points, progress, sources)
    table = Table(title=f"export: {len(done.photos)} photo{'s' * (len(done.photos) != 1)}"
                  + (f", {len(done.pairs)} stereo pair{'s' * (len(done.pairs) != 1)}" if done.pairs else ""))
    for col in ("photo", "verdict", "valid pixels", "near an edge", "depth 1-sigma p50 / p90 / p99"):
        table.add_column(col)
    for name, e in done.photos.items():
        if "valid" in e:
            s = e["depth_sigma_mm"]
            table.add_row(name, _verdict_text(e["verdict"]), f"{e['valid'] / e['pixels']:.1%}", f"{e['near_edge'] / e['pixels']:.2%}",
                          f"{s['p50']:.3f} / {s['p90']:.3f} / {s['p99']:.3f} mm" if s else "unknown (no pixel valid)")
        else:
            table.add_row(name, _verdict_text(e["verdict"]), "-", "-", "-")
    out.print(table)
    for key, p in done.pairs.items():
        d = p["disparity_px"] or [0, 0]
        sigma = f"{p['disparity_sigma_px']['p50']:.4f} px median" if p["disparity_sigma_px"] else "unknown (no pixel valid)"
        out.print(f"pair {key} ({p['left']} | {p['right']}): baseline {p['baseline_m'] * 1e3:.2f} mm, disparity "
                  f"{d[0]:.1f}..{d[1]:.1f} px, 1-sigma {sigma}, {p['occluded'] / max(p['valid'], 1):.1%} occluded")
    for name, why in done.left_out.items():
        out.print(f"left out {name}: {why}")
    earlier = [f for f in FORMATS if f not in chosen and (output / f).is_dir()]
    if earlier:
        out.print(f"kept from an earlier export: {', '.join(earlier)} (export.json lists only {', '.join(chosen)})")
    out.print(f"wrote {', '.join(chosen)} and report.html into {output} in {time.perf_counter() - start:.1f} s")


@app.command("run")
def run_workflow(
    config: Path = typer.Argument(..., help="Workflow config: one scan with its photos (configs/example.yaml), a site, several scans each with its photos (configs/site.yaml), or `bundle: BUNDLE.yaml` (several cameras, a stereo rig: docs/bundle.md)."),
    export_failed: bool = typer.Option(False, "--export-failed", help="Also write depth maps for photos whose pose verdict is 'failed'."),
    workers: int = typer.Option(1, "--workers", min=1, max=256, help="Local worker processes, one photo each at a time (the cores are shared out among them)."),
    ray_address: Optional[str] = typer.Option(None, "--ray", help="Run one task per photo on a Ray cluster: 'auto' (the cluster running on this machine) or its ADDRESS (host:port). Every node must see the config's files and the output folder at the same paths (docs/scale.md)."),
) -> None:
    """The whole workflow for one scan or a site of scans, many photos each: init-pose -> refine ->
    export-depth -> qa-edges -> overlay per photo (the initial pose from the board, or from the
    config's `init`: a rig's extrinsic). Each scan is prepared once (normals, spatial
    index, board; cached in OUTPUT/.scan-cache and reused while the scan file is unchanged) and
    every photo works on the part of it its view reaches. Every refined pose gets a verdict
    (ok | suspect | failed); depth maps are written for ok and suspect poses only (unless
    --export-failed). Steps whose outputs exist are skipped (a rerun resumes, with any engine); a
    photo that fails is reported and the others go on. A site whose scans are the frames of one
    LiDAR-camera rig (sweeps, a photo each, one init and camera; `rig:` in the config) gets one
    pose solved over all frames first (OUTPUT/rig.yaml), as refine --pairs does. A config's
    `bundle:` (a bundle file: several cameras, a rig) gets its photos solved together first, as
    refine --bundle does (OUTPUT/bundle.json, cameras/, rig.yaml). Writes
    OUTPUT/<photo>/... (a site: OUTPUT/<scan>/<photo>/...) and OUTPUT/summary.csv."""
    import dataclasses

    from rgbd_gt.config import load_config
    from rgbd_gt.engine import CACHE_FOLDER, PhotoTask, check_ray_address, failed, prepare_job, rig_first, run_local, run_ray
    from rgbd_gt.io.bundle_file import read_bundle
    from rgbd_gt.io.outputs import Outputs, hold_folder
    from rgbd_gt.workflow import (RunConfig, job_camera, not_a_rig, resolve, shared_camera, solve_bundle, verdict_counts,
                                  write_run_record, write_summary)

    if ray_address is not None and workers != 1:
        raise InputError("--workers is for local runs; on Ray every photo is a task (give one or the other)")
    cfg = load_config(RunConfig, config)  # checked there
    if ray_address is None:  # on Ray, the nodes that run the photos may have CUDA where this one has none
        from rgbd_gt.align.refine import resolve_device

        try:
            resolve_device(cfg.device)
        except InputError:
            raise InputError("device: cuda, but this machine has no CUDA device (auto takes it when there is one)",
                             config) from None
    jobs, out_dir = resolve(config, cfg)
    inputs = [config] + [p for j in jobs for p in (j.scan, j.camera, *j.photos)]
    inputs += [p for j in jobs if j.bundle is not None for p in (j.bundle, *read_bundle(j.bundle).files())]
    # checked only: each step commits its own files, so that a rerun resumes where one stopped
    Outputs(inputs).folder(out_dir, "output")
    cameras = {j.name: job_camera(j) for j in jobs}
    why_not = not_a_rig(jobs) if cfg.rig is not False else "rig: false"
    if cfg.rig and why_not:
        raise InputError(f"rig: {why_not}", config)
    if ray_address is not None:
        check_ray_address(ray_address)
    held = hold_folder(out_dir, "output")  # noqa: F841 (held until the process ends)
    cache_root = out_dir / CACHE_FOLDER
    site = len(jobs) > 1 or bool(cfg.scans)

    def name(r) -> str:
        return f"{r.scan}/{r.photo}" if site else r.photo  # two scans' photos may share a name

    results: list = []
    prepared: list = []
    start = time.perf_counter()
    with _progress(TextColumn("{task.fields[step]}")) as bar:
        task = bar.add_task("photos", total=sum(len(j.photos) for j in jobs), step="")

        def step(text: str) -> None:
            bar.update(task, step=text)

        def done(r) -> None:
            bar.advance(task)
            if r.error:
                err.print(f"{name(r)}: failed: {r.error}", markup=False, highlight=False)

        def report(p) -> None:
            prepared.append(p)
            if p.unreadable:  # bad input of the run, not of its photos: one error, as every command gives
                raise InputError(p.error)
            if p.error:
                err.print(f"{p.job.name}: failed: {p.error}", markup=False, highlight=False)
            else:
                out.print(f"{p.job.name}: {p.points:,} points {'reopened from the cache' if p.cached else 'prepared'} "
                          f"in {p.seconds:.1f} s", highlight=False)

        def tasks_of(p) -> list[PhotoTask]:
            if p.job.name in rig_failed:
                return []
            camera, run_cfg = cameras[p.job.name], cfg
            if p.job.bundle is not None:  # every photo's pose first, solved together
                solved, rig = solve_bundle(p.job, cfg, cache_root, step)
                out.print(f"bundle: {len(solved)} photos solved together"
                          + "".join(f"; rig {n} from {rig['reference']}: baseline {v['baseline_m'] * 1e3:.2f} mm"
                                    for n, v in (rig or {}).get("relative", {}).items())
                          + f"; wrote {p.job.out / 'bundle.json'}", highlight=False)
                return [PhotoTask(photo, job, p.folder, cam, cfg, export_failed) for photo, job, cam in solved]
            if cfg.refine.refine_intrinsics != "none":  # one camera for all photos, then their poses with it
                from rgbd_gt.prepared import open_prepared

                p.job.out.mkdir(parents=True, exist_ok=True)
                camera = shared_camera(p.job, open_prepared(p.folder, p.job.scan), camera, cfg, step)
                out.print(f"camera refined over the photos ({cfg.refine.refine_intrinsics}): fx {camera.fx:.2f} px, "
                          f"cx {camera.cx:.1f}, cy {camera.cy:.1f}; wrote {p.job.out / 'camera.yaml'}")
                run_cfg = dataclasses.replace(cfg, refine=dataclasses.replace(cfg.refine, refine_intrinsics="none"))
            return [PhotoTask(photo, p.job, p.folder, camera, run_cfg, export_failed) for photo in p.job.photos]

        ready, rig_failed = {}, {}  # the jobs prepared here already; the frames of a rig that failed: the error
        if why_not is None:  # a rig's frames, or sweeps that may be
            bar.update(task, description="rig")
            ready, rig = rig_first(jobs, cfg, cameras[jobs[0].name], cache_root, out_dir, report, step)
            if rig is not None and rig.error:
                err.print(f"rig: failed: {rig.error}", markup=False, highlight=False)
                rig_failed = {name: f"the rig's joint solve: {rig.error}" for name in rig.frames}
            elif rig is not None:
                out.print(f"rig: one pose over {len(rig.frames)} frames, {rig.verdict}; wrote {out_dir / 'rig.yaml'}",
                          highlight=False)
        if ray_address is not None:
            results = run_ray(jobs, tasks_of, cache_root, ray_address, lambda p: p.job.name in ready or report(p), done)
            for job in jobs:
                for r in failed(job, rig_failed[job.name]) if job.name in rig_failed else []:
                    results.append(r)
                    done(r)
        else:
            for job in jobs:
                bar.update(task, description=job.name)
                p = ready.get(job.name) or prepare_job(job, cache_root, step)
                if job.name not in ready:
                    report(p)
                if p.error or job.name in rig_failed:
                    for r in failed(job, p.error or rig_failed[job.name]):
                        results.append(r)
                        done(r)
                    continue
                results += run_local(tasks_of(p), workers, done, step)
    write_summary(out_dir / "summary.csv", results)
    seconds = time.perf_counter() - start
    write_run_record(out_dir / "run.json", prepared, seconds, "ray" if ray_address is not None else "local", workers)
    from rgbd_gt.export.report import write_report
    from rgbd_gt.export.source import read_run

    # a photo refused by this run among them; the scans' SHA-1s as this run prepared them, not read again
    write_report(out_dir / "report.html", read_run(out_dir, stale_missing=True,
                                                   known={p.job.scan: p.scan_key for p in prepared if p.scan_key}))
    table = Table(title=f"rgbd-gt run: {len(results)} photo(s) in {seconds:.0f} s")
    wide = out.width >= 110  # on a narrow terminal or in a log (80 columns) the Canny and roll columns go (summary.csv has them)

    def f(v, fmt):
        return "-" if v is None else format(v, fmt)

    columns = {"scan": lambda r: r.scan, "photo": lambda r: r.photo,
               "status": lambda r: r.status,
               "verdict": lambda r: _verdict_text(r.verdict), "init rms px": lambda r: f(r.init_rms_px, ".3f"),
               "edges / chance": lambda r: f(r.ring_edge_ratio if r.edge_ratio is None else r.edge_ratio, ".2f"),
               "Canny px before -> after": lambda r: f"{f(r.edge_before_px, '.2f')} -> {f(r.edge_after_px, '.2f')}",
               "within 1 px": lambda r: f"{f(r.within_1px_before, '.0%')} -> {f(r.within_1px_after, '.0%')}",
               "roll deg": lambda r: f(r.verticals_roll_after_deg, "+.2f"),
               "s": lambda r: f(r.seconds, ".1f")}
    shown = [c for c in columns if (c != "scan" or site) and (wide or c not in ("Canny px before -> after", "within 1 px", "roll deg"))]
    for col in shown:  # cells wrap, never cut: a verdict is never "suspe…"
        table.add_column(col, overflow="fold", min_width=7 if col in ("status", "verdict") else None)
    for r in results:
        table.add_row(*(columns[c](r) for c in shown))
    out.print(table)
    for r in results:  # below the table, where a cell would wrap a long line into a column
        if r.error:
            out.print(f"{name(r)}: failed: {r.error}", markup=False, highlight=False)
        if r.reasons:
            out.print(f"{name(r)}: {r.verdict}: {r.reasons}", markup=False, highlight=False)
        if r.skipped:
            out.print(f"{name(r)}: skipped {' '.join(r.skipped)}", markup=False, highlight=False)
    out.print(f"verdicts: {verdict_counts(results)}")
    where = "<scan>/<photo>" if site else "<photo>"
    out.print(f"outputs in {out_dir}/{where}/ (init.yaml, pose.yaml, depth.exr, depth.png, qa.png, qa.json, overlay*.png); "
              f"summary in {out_dir / 'summary.csv'}, a page to judge it by eye in {out_dir / 'report.html'}")
    if all(r.status == "failed" for r in results):
        raise typer.Exit(1)


def _click_exceptions() -> tuple[tuple, tuple, tuple]:
    """(ClickException, Exit, Abort) classes of click and of the copy of click that Typer may carry:
    Typer >= 0.20 raises its own, which `except click.ClickException` does not catch."""
    modules = [click.exceptions]
    try:
        from typer._click import exceptions as vendored

        modules.append(vendored)
    except ImportError:
        pass
    return tuple(tuple(getattr(m, name) for m in modules if hasattr(m, name)) for name in ("ClickException", "Exit", "Abort"))


def _finite_numbers(fn):
    """Every number option must be finite: click's float type takes 'nan' and 'inf'."""
    import functools

    @functools.wraps(fn)
    def checked(**kwargs):
        for name, value in kwargs.items():
            if isinstance(value, float) and not np.isfinite(value):
                raise InputError(f"--{name.replace('_', '-')} must be a finite number, got {value}")
        return fn(**kwargs)

    return checked


for _info in app.registered_commands:
    # the command list: the docstring's first sentence, wrapped to the terminal (not its source lines)
    _info.short_help = re.split(r"(?<=\.)\s+(?=[A-Z])", " ".join((_info.callback.__doc__ or "").split()))[0]
    _info.callback = _finite_numbers(_info.callback)


def main(argv: list[str] | None = None) -> None:
    """The one boundary: bad input ends as `error: ...` and exit 2; bad usage as click's usage
    message and exit 2; anything else is a bug and shows its traceback. Run as the program (argv
    None), it ends without tearing the interpreter down: freeing torch's modules took a third of a
    second of every command, and nothing in it matters once the outputs are committed."""
    try:
        _command(sys.argv[1:] if argv is None else argv)
    except SystemExit as exc:
        if argv is not None:
            raise
        _end(exc.code)


def _end(code) -> None:
    """Exit with `code` as sys.exit would, after the exit handlers and flushing the terminal,
    skipping the interpreter's teardown. Every command's pools, servers and Ray session are
    closed by then (with-blocks), so there are no threads left to wait for."""
    import atexit

    if code is not None and not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (| head) or stream
            pass
    os._exit(code or 0)


def _refuse_empty(args: list[str], command) -> None:
    """InputError for an empty argument (an unset shell variable: `--before "$INIT"`): click
    hands '' to a path option as Path(''), the current folder, so its error would name '.'.
    An option the command does not have is left to click to name; after a flag ('' is not its
    value) the argument is named by its place."""
    commands = getattr(command, "commands", {})
    sub = next((commands[a] for a in args if a in commands), None)
    takes_value = {o: not (p.is_flag or p.count) for p in (*command.params, *getattr(sub, "params", ()))
                   if p.param_type_name == "option" for o in (*p.opts, *p.secondary_opts)}
    for i, a in enumerate(args):
        if a.startswith("--") and a.endswith("="):
            where = a[:-1]
        elif a:
            continue
        elif i and args[i - 1].startswith("-") and takes_value.get(args[i - 1], True):
            where = args[i - 1]
        else:
            where = f"the argument after {args[i - 1]!r}" if i else "the first argument"
        if where.startswith("-") and where not in takes_value:
            return  # click says "No such option"
        raise InputError(f"{where}: empty (an unset shell variable?)")


def _command(args: list[str]) -> None:
    """The command line args run as `main` says, ending in SystemExit."""
    import warnings

    debug = "--debug" in args
    click_error, click_exit, click_abort = _click_exceptions()
    command = typer.main.get_command(app)
    # warnings (numpy's floating-point ones too) are kept, not dropped: shown as they come with
    # --debug, else held off the terminal, where a library's remarks are noise; what they may
    # lead to, a NaN or inf in an output, is an error of the step that made it (`steps.finite`)
    with warnings.catch_warnings(record=not debug) as held:
        warnings.simplefilter("default")
        try:
            _refuse_empty(args, command)
            code = command.main(args=args, prog_name="rgbd-gt", standalone_mode=False)
            sys.exit(code if isinstance(code, int) else 0)
        except InputError as exc:
            if debug:
                raise
            more = f" ({len(held)} warning(s) before it: --debug shows them)" if held and "NaN or inf" in str(exc) else ""
            err.print(f"error: {exc}{more}", markup=False, highlight=False)
            sys.exit(2)
        except click_error as exc:
            exc.show()
            sys.exit(exc.exit_code)
        except click_exit as exc:
            sys.exit(exc.exit_code)
        except (*click_abort, KeyboardInterrupt):
            err.print("aborted", markup=False)
            sys.exit(130)
        except MemoryError:
            err.print("error: out of memory (try --voxel or --crop to reduce the scan)", markup=False)
            sys.exit(1)
