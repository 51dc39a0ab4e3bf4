"""A synthetic drive: the frames of one rig, a camera and a spinning LiDAR behind and above it
(KITTI's layout), in the synthetic room, with the exact LiDAR-to-camera pose. For measuring what
the sweeps' objective and verdict do where no reference of a data set stands between them and
the truth (docs/lidar-method.md, "With exact truth")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rgbd_gt.camera import Camera
from rgbd_gt.scan import Scan
from rgbd_gt.synth import color
from rgbd_gt.synth.generate import SynthConfig, extra_cameras, laid_out, textured
from rgbd_gt.synth.sensors import cast, radiance, render_photo_radiance

# LiDAR (x forward, y left, z up) to camera (x right, y down, z forward): the LiDAR 27 cm behind
# the camera and 8 cm above it, as on KITTI's car
T_CAM_FROM_LIDAR = np.array([[0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, -0.08], [1.0, 0.0, 0.0, -0.27], [0.0, 0.0, 0.0, 1.0]])


@dataclass
class DriveFrame:
    sweep: Scan  # in the LiDAR's frame, in ring order (ring after ring, each by azimuth), with `ring` and intensity
    photo: np.ndarray  # (H, W, 3) uint8
    world_from_camera: np.ndarray  # (4, 4) where the frame was taken, in the room


@dataclass
class Drive:
    frames: list[DriveFrame]
    camera: Camera  # pinhole, no distortion (a rectified photo, as KITTI's)
    T_cam_from_lidar: np.ndarray  # (4, 4) the truth


def synthetic_drive(seed: int, frames: int = 4, ring_deg: float = 0.4, azimuth_deg: float = 0.17,
                    elevation_deg: tuple[float, float] = (2.0, -24.9), range_noise_m: float = 0.01,
                    size: str = "small") -> Drive:
    """`frames` frames of one rig from the places `synth`'s extra photos are taken from: a
    photo each, and a sweep of rings `ring_deg` apart from elevation_deg[0] down to
    elevation_deg[1], returns `azimuth_deg` apart over +-70 deg about the LiDAR's forward (an
    HDL-64E's spacing by default), with Gaussian range noise; intensity the returns'
    reflectance times the cosine of their incidence, as a laser sees it, against the photo's
    shaded colors. Deterministic in its arguments."""
    cfg = SynthConfig()
    preset = cfg.sizes[size]
    rng = np.random.default_rng(seed)
    scene, rc, camera, _ = laid_out(rng, preset, cfg, seed, pinhole=True)
    textured(scene, rng, preset)
    response = color.random_camera_response(rng)
    elevations = np.deg2rad(np.arange(elevation_deg[0], elevation_deg[1], -ring_deg))
    azimuths = np.deg2rad(np.arange(70.0, -70.0, -azimuth_deg))
    E, A = np.meshgrid(elevations, azimuths, indexing="ij")
    rays = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], -1).reshape(-1, 3)
    rings = np.repeat(np.arange(len(elevations), dtype=np.int16), len(azimuths))
    out = []
    for world_from_cam in [scene.camera_pose] + extra_cameras(scene, rc, camera, frames - 1, rng):
        photo = color.camera_forward(response, render_photo_radiance(scene, rc, camera, world_from_cam,
                                                                     preset.supersample, rng), rng)
        world_from_lidar = world_from_cam @ T_CAM_FROM_LIDAR
        d = rays @ world_from_lidar[:3, :3].T
        t, gid, n = cast(rc, world_from_lidar[:3, 3], d)
        hit = gid >= 0
        shade = radiance(scene, world_from_lidar[:3, 3] + t[hit, None] * d[hit], n[hit], gid[hit], blurred=True)
        reflect = np.clip(shade @ np.array([0.5, 0.3, 0.2]), 0, 1)
        incidence = np.abs(np.sum(n[hit] * d[hit], axis=1))
        intensity = np.clip(0.08 + 0.85 * reflect**0.8 * (0.5 + 0.5 * incidence) + rng.normal(0, 0.01, reflect.size), 0, 1)
        xyz = (t[hit] + rng.normal(0, range_noise_m, hit.sum()))[:, None] * rays[hit]
        out.append(DriveFrame(Scan(xyz=xyz, intensity=intensity.astype(np.float32), ring=rings[hit]), photo,
                              world_from_cam))
    return Drive(out, camera, T_CAM_FROM_LIDAR.copy())
