"""The layouts training code reads, written from plain data: one function per format. Poses are
T_cam_from_scan (x right, y down, z forward: OpenCV) unless a format says otherwise."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.errors import InputError
from rgbd_gt.io.camera_file import camera_to_dict
from rgbd_gt.io.depth_file import write_depth_png16, write_exr, write_pfm, write_png16
from rgbd_gt.io.image import write_image
from rgbd_gt.io.json_text import json_text
from rgbd_gt.pose import matrix_to_quat

CONVENTION = ("T_cam_from_scan maps scan coordinates (metres) to the camera frame, x right, y down, z forward "
              "(OpenCV); depth is z along the optical axis in metres, 0 where unknown")


def camera_dict(camera: Camera) -> dict:
    """The camera file's keys (`io.camera_file.camera_to_dict`), the distortion always, and the model."""
    return camera_to_dict(camera) | {"distortion": list(camera.distortion),
                                     "model": "opencv" if camera.has_distortion else "pinhole"}


def write_plain(folder: Path, shot, p, scan_name: str) -> dict:
    """A photo's `plain` files in `folder`: the original photo as it was, image.png (undistorted,
    pinhole), and aligned with it depth.exr (metres), depth.png (uint16 millimetres), normals.exr
    (as `export-depth`'s of those names), valid.png (255 where the depth is to be trusted), depth_sigma.exr (Z: the depth's
    1-sigma in metres; IMAGE: the pixel's image-position 1-sigma) and near_edge.png (255: within
    reach of a depth discontinuity). shot: `export.source.Shot`; p: its
    `export.dataset.DepthProducts`. Returns its entry of cameras.json: both camera models (the
    original's, with its distortion, and the pinhole one the depth belongs to), the poses, the verdict."""
    from rgbd_gt.steps import write_depth

    folder.mkdir(parents=True, exist_ok=True)
    original = f"original{shot.image.suffix.lower()}"
    shutil.copyfile(shot.image, folder / original)
    write_image(folder / "image.png", p.image)
    # the files export-depth writes under these names, as it writes them
    write_depth(p.depth, p.camera, p.T, scan_name, folder / "depth.exr", folder / "depth.png", folder / "normals.exr")
    write_image(folder / "valid.png", p.valid.astype(np.uint8) * 255)
    write_image(folder / "near_edge.png", p.near.astype(np.uint8) * 255)
    write_exr(folder / "depth_sigma.exr", {"Z": p.sigma.depth, "IMAGE": p.sigma.image},
              {"rgbd_gt_units": "Z: 1-sigma of depth (metres); IMAGE: 1-sigma of image position (pixels); 0 = no depth"})
    return {"image": f"{folder.name}/image.png", "camera": camera_dict(p.camera), "T_cam_from_scan": p.T.tolist(),
            "original": f"{folder.name}/{original}", "original_camera": camera_dict(shot.camera),
            "T_cam_from_scan_original": shot.T.tolist(), "verdict": shot.verdict}


def write_colmap(folder: Path, shots: list, seen: list[tuple[np.ndarray, np.ndarray]], xyz: np.ndarray,
                 rgb: np.ndarray | None) -> None:
    """A COLMAP text model: cameras.txt (OPENCV: fx fy cx cy k1 k2 p1 p2; FULL_OPENCV with k3 k4 k5
    k6 when the camera has them; PINHOLE without distortion; cx, cy and
    the observations in COLMAP's pixel convention, the top-left pixel's centre at 0.5), images.txt
    (world-to-camera quaternion and translation: the scan is COLMAP's world) with each photo's
    observations of points3D.txt, and the photos in images/. shots: `export.source.Shot`s; seen:
    per shot (point ids (n,) into xyz, pixels (n, 2) of the original photo); xyz (P, 3), rgb
    (P, 3) uint8 or None: the scan points that some photo sees."""
    (folder / "images").mkdir(parents=True, exist_ok=True)
    cams, cam_id = [], {}
    for s in shots:
        key = (s.camera_name, s.camera)
        if key not in cam_id:
            cam_id[key] = len(cam_id) + 1
            c = s.camera
            d = list(c.distortion) + [0.0] * 8
            if any(c.distortion[8:]):
                raise InputError(f"camera {s.camera_name}: COLMAP has no model for OpenCV's thin-prism or tilt "
                                 f"coefficients (distortion {list(c.distortion)})", s.image)
            # COLMAP's pixel (0, 0) spans [0, 1) (its centre at 0.5); OpenCV's is centred at 0
            cx, cy = c.cx + 0.5, c.cy + 0.5
            if any(c.distortion[4:]):  # k3 (and k4..k6, the rational model)
                model, params = "FULL_OPENCV", [c.fx, c.fy, cx, cy, *d[:8]]
            elif c.has_distortion:
                model, params = "OPENCV", [c.fx, c.fy, cx, cy, *d[:4]]
            else:
                model, params = "PINHOLE", [c.fx, c.fy, cx, cy]
            cams.append(f"{cam_id[key]} {model} {c.width} {c.height} " + " ".join(repr(float(v)) for v in params))
    (folder / "cameras.txt").write_text("# Camera list with one line of data per camera:\n"
                                        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n" + "\n".join(cams) + "\n")
    lines, track_img, track_pt, track_k = [], [], [], []
    for k, (s, (ids, uv)) in enumerate(zip(shots, seen), start=1):
        name = f"{s.name}{s.image.suffix.lower()}"
        shutil.copyfile(s.image, folder / "images" / name)
        q, t = matrix_to_quat(s.T[:3, :3]), s.T[:3, 3]
        lines.append(" ".join(repr(float(v)) for v in (*q, *t)) + f" {cam_id[(s.camera_name, s.camera)]} {name}")
        lines.append(" ".join(f"{a:.4f} {b:.4f} {i}" for (a, b), i in zip((uv + 0.5).tolist(), (ids + 1).tolist())))
        track_img.append(np.full(len(ids), k))
        track_pt.append(ids)
        track_k.append(np.arange(len(ids)))
    (folder / "images.txt").write_text(
        "# Image list with two lines of data per image:\n#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n" + "".join(f"{k} {a}\n{b}\n" for k, (a, b) in
                                                       enumerate(zip(lines[::2], lines[1::2]), start=1)))
    img, pt, idx = (np.concatenate(a) if a else np.zeros(0, np.int64) for a in (track_img, track_pt, track_k))
    order = np.lexsort((img, pt))
    img, pt, idx = img[order], pt[order], idx[order]
    starts = np.flatnonzero(np.r_[True, pt[1:] != pt[:-1]]) if len(pt) else np.zeros(0, np.int64)
    # a point's track, as text: its (IMAGE_ID, POINT2D_IDX) pairs joined in one pass over them
    pairs = np.char.add(np.char.add(np.char.add(" ", img.astype(str)), " "), idx.astype(str)).astype(object)
    tracks = np.add.reduceat(pairs, starts) if len(pairs) else np.zeros(0, object)
    ids = pt[starts]
    color = rgb[ids] if rgb is not None else np.full((len(ids), 3), 128, np.uint8)
    head = [f"{i + 1} {x!r} {y!r} {z!r} {r} {g} {b} 0" for i, (x, y, z), (r, g, b) in
            zip(ids.tolist(), xyz[ids].tolist(), color.tolist())]
    (folder / "points3D.txt").write_text(
        "# 3D point list with one line of data per point:\n#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
        + "".join(f"{h}{t}\n" for h, t in zip(head, tracks)))


def nerfstudio_folder(out: Path, scan: str | None = None) -> Path:
    """An export's nerfstudio scene of a scan's photos: OUT/nerfstudio, or for a site (several
    scans, each its own world frame) OUT/nerfstudio/SCAN."""
    return out / "nerfstudio" / scan if scan else out / "nerfstudio"


def nerfstudio_frame(folder: Path, name: str, p) -> dict:
    """One photo's nerfstudio files, images/NAME.png (the undistorted photo, as plain's) and
    depth/NAME.png (uint16 millimetres, z-depth), and its frame of transforms.json: its camera
    (PINHOLE) and transform_matrix, camera-to-world with OpenGL axes (x right, y up, z back), as
    nerfstudio's data conventions state; cx, cy as nerfstudio casts its rays, through pixel
    centres at index + 0.5 (COLMAP's convention, from which its own data comes), i.e. OpenCV's +
    0.5. p: `export.dataset.DepthProducts`."""
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "depth").mkdir(exist_ok=True)
    write_image(folder / "images" / f"{name}.png", p.image)
    write_depth_png16(folder / "depth" / f"{name}.png", p.z)
    c2w = np.linalg.inv(p.T)
    c2w[:3, 1:3] *= -1  # OpenCV's y down, z forward to OpenGL's y up, z back
    c = p.camera
    return {"file_path": f"images/{name}.png", "depth_file_path": f"depth/{name}.png", "fl_x": c.fx, "fl_y": c.fy,
            "cx": c.cx + 0.5, "cy": c.cy + 0.5, "w": c.width, "h": c.height, "transform_matrix": c2w.tolist()}


def write_transforms(folder: Path, frames: list[dict]) -> None:
    """nerfstudio's transforms.json of the frames (`nerfstudio_frame`): the first frame's camera
    at the top (each frame keeps its own), depth_unit_scale_factor 0.001 (millimetre PNGs)."""
    first = frames[0]
    (folder / "transforms.json").write_text(json_text({
        "camera_model": "PINHOLE", **{k: first[k] for k in ("fl_x", "fl_y", "cx", "cy", "w", "h")},
        "depth_unit_scale_factor": 0.001, "frames": frames}))


def middlebury_calib(camera: Camera, baseline: float, ndisp: int) -> str:
    """calib.txt of the Middlebury 2014 (and ETH3D two-view) sets: baseline in millimetres."""
    K = f"[{camera.fx!r} 0 {camera.cx!r}; 0 {camera.fy!r} {camera.cy!r}; 0 0 1]"
    return (f"cam0={K}\ncam1={K}\ndoffs=0\nbaseline={baseline * 1e3!r}\nwidth={camera.width}\nheight={camera.height}\n"
            f"ndisp={ndisp}\n")


def write_middlebury(folder: Path, s) -> None:
    """A rectified pair in Middlebury's layout: im0.png, im1.png, calib.txt, disp0GT.pfm (+inf
    where unknown), mask0nocc.png (255 non-occluded, 128 occluded, 0 unknown), and
    disp0GT_sigma.pfm, the disparity's 1-sigma in pixels (+inf where unknown). s:
    `export.dataset.StereoProducts`."""
    folder.mkdir(parents=True, exist_ok=True)
    write_image(folder / "im0.png", s.left.image)
    write_image(folder / "im1.png", s.right)
    ndisp = int(np.ceil(max(float(s.disp.max()), 1.0) * 1.1 / 16) * 16)
    (folder / "calib.txt").write_text(middlebury_calib(s.left.camera, s.baseline, ndisp))
    write_pfm(folder / "disp0GT.pfm", np.where(s.left.valid, s.disp, np.inf))
    write_pfm(folder / "disp0GT_sigma.pfm", np.where(s.left.valid, s.disp_sigma, np.inf))
    mask = np.where(s.left.valid, np.where(s.occluded, 128, 255), 0).astype(np.uint8)
    write_image(folder / "mask0nocc.png", mask)


def write_kitti(folder: Path, index: int, s) -> None:
    """A rectified pair in KITTI 2015's stereo layout: image_2/ image_3/ (left, right),
    disp_occ_0/ (every pixel with disparity) and disp_noc_0/ (non-occluded only), uint16 PNG
    disparity x 256 (0: none), calib_cam_to_cam/ with P_rect_02 and P_rect_03; and
    disp_sigma_0/ the disparity's 1-sigma (PFM pixels, +inf where none)."""
    stem = f"{index:06d}_10"
    for sub in ("image_2", "image_3", "disp_occ_0", "disp_noc_0", "disp_sigma_0", "calib_cam_to_cam"):
        (folder / sub).mkdir(parents=True, exist_ok=True)
    write_image(folder / "image_2" / f"{stem}.png", s.left.image)
    write_image(folder / "image_3" / f"{stem}.png", s.right)
    d = np.clip(np.round(s.disp * 256), 1, 65535)  # a disparity under 1/256 px would read as none
    write_png16(folder / "disp_occ_0" / f"{stem}.png", np.where(s.left.valid, d, 0))
    write_png16(folder / "disp_noc_0" / f"{stem}.png", np.where(s.left.valid & ~s.occluded, d, 0))
    # not KITTI's own: a 1-sigma of a few thousandths of a pixel has no room in its x 256 PNGs
    write_pfm(folder / "disp_sigma_0" / f"{stem}.pfm", np.where(s.left.valid, s.disp_sigma, np.inf))
    c = s.left.camera
    P2 = np.array([[c.fx, 0, c.cx, 0], [0, c.fy, c.cy, 0], [0, 0, 1, 0]])
    P3 = P2.copy()
    P3[0, 3] = -c.fx * s.baseline
    (folder / "calib_cam_to_cam" / f"{index:06d}.txt").write_text(
        "".join(f"{k}: " + " ".join(f"{v:.12e}" for v in P.ravel()) + "\n" for k, P in (("P_rect_02", P2), ("P_rect_03", P3)))
        + f"S_rect_02: {c.width} {c.height}\nS_rect_03: {c.width} {c.height}\n")
