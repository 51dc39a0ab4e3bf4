"""The scan: a point cloud from one or more laser scans (or LiDAR sweeps) in one world frame,
with what each point carries, and the values photos are matched against."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from rgbd_gt.errors import InputError

LUMA = (0.299, 0.587, 0.114)  # Rec. 601: gray from RGB, wherever the project makes one


@dataclass
class Scan:
    """A colored point cloud from one or more laser scans, in one world frame.

    Attributes:
        xyz: (N, 3) float64, metres, in the file's world frame.
        rgb: (N, 3) uint8 or None.
        intensity: (N,) float32 in [0, 1] (scaled by the file's declared limits) or None.
        row, col: (N,) int32 structured-grid indices (row = elevation, col = azimuth) or None.
        scan_id: (N,) int32 index of the scan each point came from, or None.
        origins: (S, 3) float64 sensor position of each scan in the world frame.
        normals: (N, 3) float32 unit normals facing the scanner (0 where unknown) or None
            (`render.normals.with_normals` fills them in).
        ring: (N,) int16 the laser (ring) of a spinning LiDAR that made each return, or None: a
            sweep's rings are known, in whatever frame its points are (`render.points.is_sweep`).
        edge: (N,) float32 or None: a sweep's depth step at each return along its ring (metres:
            how much nearer it is than its nearer neighbour on the ring, 0 where it is not;
            `render.rings.ring_steps`), made on the whole sweep, whose file keeps the ring order.
        cell_bits: (N,) uint8 or None: a grid scan's mesh, a byte a point
            (`render.mesh.grid_cell_bits`), made on the whole scan when it was prepared and
            taken along by its views (made on a view alone, it differs at depth edges).
    """

    xyz: np.ndarray
    rgb: np.ndarray | None = None
    intensity: np.ndarray | None = None
    row: np.ndarray | None = None
    col: np.ndarray | None = None
    scan_id: np.ndarray | None = None
    origins: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    normals: np.ndarray | None = None
    ring: np.ndarray | None = None
    edge: np.ndarray | None = None
    cell_bits: np.ndarray | None = field(default=None, repr=False)

    PER_POINT = ("xyz", "rgb", "intensity", "row", "col", "scan_id", "normals", "ring", "edge")

    def __len__(self) -> int:
        return int(self.xyz.shape[0])

    @property
    def fields(self) -> list[str]:
        """Names of the per-point fields present, e.g. ['xyz', 'rgb', 'intensity']."""
        return [name for name in self.PER_POINT if getattr(self, name) is not None]

    @property
    def has_grid(self) -> bool:
        return self.row is not None and self.col is not None

    def subset(self, index: np.ndarray) -> "Scan":
        """A new Scan with the points selected by a boolean mask or an index array (and their
        cell_bits)."""
        picked = {name: getattr(self, name)[index] for name in self.fields}
        return dataclasses.replace(self, **picked, cell_bits=None if self.cell_bits is None else self.cell_bits[index])


def scan_colors(scan: Scan, path: object = None, to_align: bool = False) -> np.ndarray:
    """What photos are matched against: RGB (N, 3) uint8, else intensity (N, 1) in [0, 1].
    `to_align`: InputError when every point has the same value (nothing to align a photo by)."""
    if scan.rgb is not None:
        colors = scan.rgb
    elif scan.intensity is not None:
        colors = scan.intensity.reshape(-1, 1)
    else:
        raise InputError("the scan has neither colors nor intensity", path)
    if to_align and len(colors) and (colors == colors[0]).all():
        what = "color" if scan.rgb is not None else "intensity"
        raise InputError(f"every point in view has the same {what}: nothing to align the photo by", path)
    return colors


def colors_to_gray(colors: np.ndarray) -> np.ndarray:
    """`scan_colors` output -> (N,) float32 gray in [0, 255]."""
    if colors.shape[1] == 3:
        return colors.astype(np.float32) @ np.array(LUMA, np.float32)
    return colors[:, 0].astype(np.float32) * 255


def ring_ids(values: np.ndarray) -> np.ndarray:
    """A file's ring field as `Scan.ring` (int16; only its presence is used, so any values do)."""
    return np.clip(np.nan_to_num(np.asarray(values, np.float64).ravel()), -32768, 32767).astype(np.int16)
