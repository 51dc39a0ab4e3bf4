"""Scene geometry for synthetic data: a textured room with objects and a checkerboard.

World frame: z up, metres, the room spans [0, W] x [0, D] x [0, H]. Every surface is a box or
a cylinder with its own pose; its albedo comes from a tileable texture mapped by planar (box)
or cylindrical projection, or from the checkerboard pattern.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from rgbd_gt.pose import rigid, transform_points

BOARD_TEXTURE = -1  # Surface.texture value of the checkerboard
BOARD_WHITE, BOARD_BLACK, BOARD_EDGE = 0.85, 0.04, 0.5


@dataclass
class Surface:
    """One solid. Local frame: `pose` (4x4 world_from_local). A box spans [lo, hi] in local
    coordinates; a cylinder has its axis on local z from lo[2] to hi[2] with radius hi[0]."""

    name: str
    shape: str  # 'box' | 'cylinder'
    pose: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    texture: int
    tex_offset: np.ndarray = field(default_factory=lambda: np.zeros(2))


@dataclass
class Board:
    """A printed checkerboard. Board frame (`pose` = world_from_board): origin at the first inner
    corner, x along the `cols` inner corners, y along the `rows`, z into the board (the printed
    side faces -z)."""

    cols: int
    rows: int
    square: float
    pose: np.ndarray

    def corners_local(self) -> np.ndarray:
        """(cols*rows, 3) inner corners in the board frame, x fastest (OpenCV's object order)."""
        j, i = np.mgrid[0 : self.rows, 0 : self.cols]
        return np.stack([i.ravel() * self.square, j.ravel() * self.square, np.zeros(i.size)], 1)

    def corners(self) -> np.ndarray:
        """(cols*rows, 3) inner corners in the world frame."""
        return transform_points(self.pose, self.corners_local())

    def outline_local(self) -> tuple[np.ndarray, np.ndarray]:
        """Board extent (lo, hi) in the board frame: the pattern plus one square of white border."""
        s = self.square
        return np.array([-2 * s, -2 * s, 0.0]), np.array([(self.cols + 1) * s, (self.rows + 1) * s, 0.005])


@dataclass
class Scene:
    room: np.ndarray  # (3,) W, D, H
    surfaces: list[Surface]
    textures: list[np.ndarray]  # (S, S, 3) float32 linear albedo
    textures_blurred: list[np.ndarray]  # what the scanner's coarser color camera sees
    texel_m: float
    light: np.ndarray  # (3,) point light position
    board: Board
    camera_pose: np.ndarray  # (4, 4) world_from_camera (OpenCV axes)
    scanner_pose: np.ndarray  # (4, 4) world_from_scanner


def rot_z(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def rot_x(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def rot_y(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def look_at(eye: np.ndarray, target: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """world_from_camera (4x4) for an OpenCV camera at `eye` looking at `target`, z up."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], 1) @ rot_z(roll)
    return rigid(R, eye)


def _seg_dist(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """2-D distance from point p to segment ab."""
    ab = b - a
    t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0, 1)
    return float(np.linalg.norm(p - (a + t * ab)))


def _floor_box(name, xy, yaw, size, z0, tex, rng) -> Surface:
    w, d, h = size
    return Surface(name, "box", rigid(rot_z(yaw), [xy[0], xy[1], z0]), np.array([-w / 2, -d / 2, 0]),
                   np.array([w / 2, d / 2, h]), tex, rng.uniform(0, 1000, 2))


def make_layout(rng: np.random.Generator, board_shape: tuple[int, int], square: float,
                board_distance: tuple[float, float], scanner_distance: tuple[float, float],
                hfov_deg: float) -> tuple[list[Surface], Board, np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Random room, objects, board, camera and scanner poses (no textures yet).

    Returns (surfaces, board, room size, camera pose, scanner pose, light position), or None when
    the drawn scanner distances found no spot inside the room (far ones, in a narrow room).
    Texture indices in the surfaces count up from 0 in order.
    """
    W, D, H = rng.uniform(5.0, 7.0), rng.uniform(6.0, 7.5), rng.uniform(2.6, 3.2)
    room = np.array([W, D, H])
    surfaces: list[Surface] = []
    tex = iter(range(10_000))
    t = 0.1
    for name, lo, hi in (
        ("floor", [0, 0, -t], [W, D, 0]), ("ceiling", [0, 0, H], [W, D, H + t]),
        ("wall_south", [-t, -t, 0], [W + t, 0, H]), ("wall_north", [-t, D, 0], [W + t, D + t, H]),
        ("wall_west", [-t, 0, 0], [0, D, H]), ("wall_east", [W, 0, 0], [W + t, D, H]),
    ):
        surfaces.append(Surface(name, "box", np.eye(4), np.array(lo, float), np.array(hi, float), next(tex), rng.uniform(0, 1000, 2)))

    cam = np.array([rng.uniform(1.5, W - 1.5), rng.uniform(0.8, 1.4), rng.uniform(1.2, 1.7)])
    heading = np.deg2rad(90 + rng.uniform(-25, 25))  # mostly looking along +y

    def unit(a):
        return np.array([np.cos(a), np.sin(a)])

    # the board on a stand, facing the camera
    db = rng.uniform(*board_distance)
    b_xy = cam[:2] + db * unit(heading + np.deg2rad(rng.uniform(-8, 8)))
    b_xy = np.clip(b_xy, 0.6, [W - 0.6, D - 0.6])
    b_center = np.array([b_xy[0], b_xy[1], rng.uniform(1.0, 1.45)])
    to_cam = cam - b_center
    face_yaw = np.arctan2(to_cam[1], to_cam[0]) + np.deg2rad(rng.uniform(-15, 15))
    normal = np.array([np.cos(face_yaw), np.sin(face_yaw), 0.0])  # printed side faces the camera
    zb = -normal
    xb = np.cross(zb, [0.0, 0.0, 1.0])
    xb /= np.linalg.norm(xb)
    yb = np.cross(zb, xb)
    Rb = np.stack([xb, yb, zb], 1) @ rot_x(np.deg2rad(rng.uniform(-10, 10))) @ rot_z(np.deg2rad(rng.uniform(-4, 4)))
    cols, rows = board_shape
    origin = b_center - Rb @ np.array([(cols - 1) * square / 2, (rows - 1) * square / 2, 0])
    board = Board(cols, rows, square, rigid(Rb, origin))
    blo, bhi = board.outline_local()
    surfaces.append(Surface("board", "box", board.pose, blo, bhi, BOARD_TEXTURE))
    bottom = (board.pose[:3, :3] @ np.array([(cols - 1) * square / 2, bhi[1], 0]) + origin)[2]
    pole_xy = b_center[:2] + 0.04 * zb[:2] / max(np.linalg.norm(zb[:2]), 1e-9)
    surfaces.append(_floor_box("stand_pole", pole_xy, face_yaw, (0.04, 0.04, max(bottom, 0.05)), 0.0, next(tex), rng))
    surfaces.append(_floor_box("stand_base", pole_xy, face_yaw, (0.45, 0.45, 0.02), 0.0, next(tex), rng))

    # the scanner on a tripod beside the camera
    for _ in range(200):
        ds = rng.uniform(*scanner_distance)
        side = rng.choice([-1, 1])
        s_xy = cam[:2] + ds * unit(heading + side * np.deg2rad(rng.uniform(60, 150)))
        if np.all(s_xy > 0.4) and np.all(s_xy < [W - 0.4, D - 0.4]):
            break
    else:
        return None  # outside the room the scanner would see only the walls' backs
    scanner = np.array([s_xy[0], s_xy[1], rng.uniform(1.3, 1.8)])
    Rs = rot_z(rng.uniform(-np.pi, np.pi)) @ rot_x(np.deg2rad(rng.uniform(-3, 3))) @ rot_y(np.deg2rad(rng.uniform(-3, 3)))
    scanner_pose = rigid(Rs, scanner)

    # objects in front of the camera, off the lines of sight to the board
    placed: list[tuple[np.ndarray, float]] = [(b_xy, 0.45), (cam[:2], 0.5), (scanner[:2], 0.5)]
    half_fov = np.deg2rad(hfov_deg) / 2 * 0.9

    def free_spot(radius):
        for _ in range(300):
            dist = rng.uniform(1.0, 4.2)
            xy = cam[:2] + dist * unit(heading + rng.uniform(-half_fov, half_fov))
            if np.any(xy < radius + 0.05) or np.any(xy > room[:2] - radius - 0.05):
                continue
            if any(np.linalg.norm(xy - c) < radius + r + 0.05 for c, r in placed):
                continue
            if min(_seg_dist(xy, cam[:2], b_xy), _seg_dist(xy, scanner[:2], b_xy)) < radius + 0.2:
                continue
            placed.append((xy, radius))
            return xy
        return None

    tw, td = rng.uniform(1.0, 1.4), rng.uniform(0.6, 0.8)
    xy = free_spot(np.hypot(tw, td) / 2)
    if xy is not None:
        yaw, top_z = rng.uniform(0, np.pi), rng.uniform(0.72, 0.76)
        table_tex = next(tex)
        surfaces.append(_floor_box("table_top", xy, yaw, (tw, td, 0.04), top_z - 0.04, table_tex, rng))
        for k, (sx, sy) in enumerate(((-1, -1), (-1, 1), (1, -1), (1, 1))):
            leg = xy + rot_z(yaw)[:2, :2] @ np.array([sx * (tw / 2 - 0.06), sy * (td / 2 - 0.06)])
            surfaces.append(_floor_box(f"table_leg{k}", leg, yaw, (0.05, 0.05, top_z - 0.04), 0.0, table_tex, rng))
        surfaces.append(_floor_box("table_item", xy + rng.uniform(-0.2, 0.2, 2), rng.uniform(0, np.pi),
                                   rng.uniform([0.15, 0.1, 0.08], [0.35, 0.25, 0.3]), top_z, next(tex), rng))
    for k in range(int(rng.integers(3, 6))):
        size = rng.uniform([0.25, 0.25, 0.2], [0.8, 0.7, 1.3])
        xy = free_spot(np.hypot(size[0], size[1]) / 2)
        if xy is not None:
            surfaces.append(_floor_box(f"box{k}", xy, rng.uniform(0, np.pi), size, 0.0, next(tex), rng))
    for k in range(int(rng.integers(2, 4))):
        r, h = rng.uniform(0.1, 0.3), rng.uniform(0.3, 1.6)
        xy = free_spot(r)
        if xy is not None:
            surfaces.append(Surface(f"cylinder{k}", "cylinder", rigid(np.eye(3), [xy[0], xy[1], 0.0]),
                                    np.array([-r, -r, 0.0]), np.array([r, r, h]), next(tex), rng.uniform(0, 1000, 2)))

    # the camera looks at the board, pulled a little towards the objects
    centroid = np.mean([c for c, _ in placed[3:]], axis=0) if len(placed) > 3 else b_xy
    target = b_center.copy()
    target[:2] += (centroid - b_xy) * rng.uniform(0.0, 0.4)
    target[2] = b_center[2] + rng.uniform(-0.3, 0.1)
    camera_pose = look_at(cam, target, np.deg2rad(rng.uniform(-5, 5)))
    light = np.array([W / 2 + rng.uniform(-1, 1), D / 2 + rng.uniform(-1, 1), H - 0.3])
    return surfaces, board, room, camera_pose, scanner_pose, light


def surface_mesh(s: Surface):
    """The open3d legacy TriangleMesh of a surface, in the world frame."""
    import open3d as o3d

    if s.shape == "box":
        size = s.hi - s.lo
        m = o3d.geometry.TriangleMesh.create_box(*size)
        m.translate(s.lo)
    else:
        r, h = s.hi[0], s.hi[2] - s.lo[2]
        m = o3d.geometry.TriangleMesh.create_cylinder(r, h, resolution=128, split=1)
        m.translate([0, 0, s.lo[2] + h / 2])
    m.transform(s.pose)
    return m


def _lookup(tex: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear, wrapping texture lookup at texel coordinates u, v (N,) -> (N, 3)."""
    n = u.size
    if n == 0:
        return np.zeros((0, 3), np.float32)
    size = tex.shape[0]
    cols = 4096  # cv2.remap maps must stay under 32767 per side: fold the list into rows
    rows = -(-n // cols)
    pad = rows * cols - n
    mx = np.pad(np.mod(u, size), (0, pad)).astype(np.float32).reshape(rows, cols)
    my = np.pad(np.mod(v, size), (0, pad)).astype(np.float32).reshape(rows, cols)
    out = cv2.remap(tex, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
    return out.reshape(-1, 3)[:n]


def surface_albedo(scene: Scene, gid: np.ndarray, points: np.ndarray, normals: np.ndarray, blurred: bool) -> np.ndarray:
    """Albedo (N, 3) at world `points` (N, 3) with unit `normals` on surfaces `gid` (N,)."""
    out = np.zeros((points.shape[0], 3), np.float32)
    textures = scene.textures_blurred if blurred else scene.textures
    for k, s in enumerate(scene.surfaces):
        sel = np.nonzero(gid == k)[0]
        if sel.size == 0:
            continue
        R, t = s.pose[:3, :3], s.pose[:3, 3]
        q = (points[sel] - t) @ R
        n = normals[sel] @ R
        if s.texture == BOARD_TEXTURE:
            sq = scene.board.square
            i, j = np.floor(q[:, 0] / sq), np.floor(q[:, 1] / sq)
            inside = (i >= -1) & (i <= scene.board.cols - 1) & (j >= -1) & (j <= scene.board.rows - 1)
            front = n[:, 2] < -0.5
            value = np.where(inside & ((i + j) % 2 == 0), BOARD_BLACK, BOARD_WHITE)
            out[sel] = np.where(front, value, BOARD_EDGE)[:, None]
            continue
        if s.shape == "cylinder":
            cap = np.abs(n[:, 2]) > 0.9
            u = np.where(cap, q[:, 0], np.arctan2(q[:, 1], q[:, 0]) * s.hi[0])
            v = np.where(cap, q[:, 1], q[:, 2])
        else:
            axis = np.argmax(np.abs(n), axis=1)
            u = np.where(axis == 0, q[:, 1], q[:, 0])
            v = np.where(axis == 2, q[:, 1], q[:, 2])
        out[sel] = _lookup(textures[s.texture], u / scene.texel_m + s.tex_offset[0], v / scene.texel_m + s.tex_offset[1])
    return out
