"""ICL-NUIM livingroom1 cases, as in the paper's Sec. 4.1.

A case: the point cloud of frame i (noisy depth, frame i's colors) in the world frame; the
photo of frame j with random multimodal effects; the initial pose is camera i's, the truth
camera j's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from rgbd_gt.camera import Camera, backproject
from rgbd_gt.errors import InputError
from rgbd_gt.pose import invert, transform_points

ICL_CAMERA = Camera(640, 480, 525.0, 525.0, 319.5, 239.5)
LUMA = np.array([0.299, 0.587, 0.114], np.float32)


def read_trajectory(path: Path) -> list[np.ndarray]:
    """trajectory.log -> list of 4x4 camera-to-world matrices (OpenCV axes), by frame."""
    rows = [line.split() for line in path.read_text().splitlines() if line.strip()]
    poses = []
    for k in range(0, len(rows), 5):
        poses.append(np.array(rows[k + 1 : k + 5], float))
    return poses


def frame_count(folder: Path) -> int:
    return len(sorted(folder.glob("color_*.jpg")))


def read_color(folder: Path, i: int) -> np.ndarray:
    img = cv2.imread(str(folder / f"color_{i:05d}.jpg"))
    if img is None:
        raise InputError(f"missing frame {i}", folder)
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def read_depth(folder: Path, i: int, kind: str = "noisy") -> np.ndarray:
    """(H, W) float64 z-depth in metres (0 = none)."""
    d = cv2.imread(str(folder / f"depth_{kind}_{i:05d}.png"), cv2.IMREAD_UNCHANGED)
    if d is None:
        raise InputError(f"missing depth {kind} {i}", folder)
    return d.astype(np.float64) / 1000.0


def depth_points(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels with depth of a depth image (H, W) metres, back-projected through ICL_CAMERA:
    (camera-frame points (N, 3), their rows v (N,), their columns u (N,))."""
    v, u = np.nonzero(depth > 0)
    return backproject(ICL_CAMERA, np.stack([u, v], 1), depth[v, u]), v, u


def frame_cloud(folder: Path, i: int, kind: str = "noisy") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frame i's depth back-projected into the world: (xyz (N, 3), rgb (N, 3) uint8, pixel (N, 2))."""
    cam, v, u = depth_points(read_depth(folder, i, kind))
    T_wc = read_trajectory(folder / "trajectory.log")[i]
    return transform_points(T_wc, cam), read_color(folder, i)[v, u], np.stack([u, v], 1)


def multimodal_effects(rgb: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, dict]:
    """The paper's random photo effects: brightness, contrast and saturation factors from
    [1 - 0.4, 1 + 0.4], hue shift from [-0.06, 0.06] turns, gamma from [0.5, 1] or [1, 2],
    Gaussian blur sigma from [0, 0.75] px. Returns (uint8 RGB, the parameters)."""
    img = rgb.astype(np.float32) / 255.0
    p = {
        "brightness": rng.uniform(0.6, 1.4), "contrast": rng.uniform(0.6, 1.4),
        "saturation": rng.uniform(0.6, 1.4), "hue": rng.uniform(-0.06, 0.06),
        "gamma": rng.uniform(0.5, 1.0) if rng.random() < 0.5 else rng.uniform(1.0, 2.0),
        "blur": rng.uniform(0.0, 0.75),
    }
    gray = img @ LUMA
    for op in rng.permutation(["brightness", "contrast", "saturation", "hue"]):
        if op == "brightness":
            img = img * p["brightness"]
        elif op == "contrast":
            img = (img - gray.mean()) * p["contrast"] + gray.mean()
        elif op == "saturation":
            g = (np.clip(img, 0, 1) @ LUMA)[..., None]
            img = (img - g) * p["saturation"] + g
        else:
            hsv = cv2.cvtColor(np.clip(img, 0, 1), cv2.COLOR_RGB2HSV)
            hsv[..., 0] = (hsv[..., 0] + p["hue"] * 360.0) % 360.0
            img = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
        img = np.clip(img, 0, 1)
        gray = img @ LUMA
    img = img ** p["gamma"]
    if p["blur"] > 0.05:
        img = cv2.GaussianBlur(img, (0, 0), p["blur"])
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8), {k: float(v) for k, v in p.items()}


@dataclass
class Case:
    name: str
    i: int
    j: int
    effects: dict
    points: np.ndarray  # (N, 3) world
    colors: np.ndarray  # (N, 3) uint8
    photo: np.ndarray  # (H, W, 3) uint8
    T_init: np.ndarray  # T_cam_from_scan of camera i
    T_true: np.ndarray  # ... of camera j


def make_cases(folder: Path, offsets=(1,), effects_per_pair: int = 4, seed: int = 0, effects: bool = True,
               depth: str = "noisy") -> list[Case]:
    """Every ordered pair (i, j = i +- offset) of frames, each with `effects_per_pair` random effects
    (with effects=False, the photo as it is, once per pair). depth: 'noisy' (the paper's) or 'clean'."""
    n = frame_count(folder)
    if n == 0:
        raise InputError("no ICL frames (color_00000.jpg ...)", folder)
    poses = read_trajectory(folder / "trajectory.log")
    rng = np.random.default_rng(seed)
    clouds = {}
    cases = []
    for off in offsets:
        for i in range(n):
            for j in (i - off, i + off):
                if not 0 <= j < n:
                    continue
                if i not in clouds:
                    clouds[i] = frame_cloud(folder, i, depth)[:2]
                photo = read_color(folder, j)
                for k in range(effects_per_pair if effects else 1):
                    img, eff = multimodal_effects(photo, rng) if effects else (photo, {})
                    cases.append(Case(f"{i}->{j}#{k}", i, j, eff, clouds[i][0], clouds[i][1], img,
                                      invert(poses[i]), invert(poses[j])))
    return cases
