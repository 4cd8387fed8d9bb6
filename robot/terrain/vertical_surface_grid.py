"""Binary grid of approximately vertical surfaces around a pose node (paper 4.3.3).

For loop closing the 3D sweep is collapsed into a 2D binary occupancy grid whose occupied
cells hold an approximately vertical surface (walls, fences, trunks, cars): these are highly
repeatable between visits, unlike the drivability map of 5.3, and compress well for the radio
(4.3.4). A cell is occupied when the (levelled) points inside it, within the height band
``[z_min_m, z_max_m]`` above the base's ground contact, span at least
``min_vertical_extent_m`` vertically: inside a ``resolution_m`` square that means a surface
steeper than ``atan(extent / (resolution * sqrt 2))`` (about 65 deg with the defaults).
The band drops the ground and overhanging canopy.

*Scan-line segments.* The nodding LIDAR's beams are 1.5 deg apart: 13 cm at 5 m, more than a
cell, so a wall's returns alone leave gaps between cells that move from sweep to sweep as the
robot moves, and the same wall rasterizes into different cells at consecutive nodes. The
surface between two consecutive returns of one scan line (same ``point_time_s``) that lie
within ``connect_max_gap_m`` of each other is sampled every half cell and counted like the
returns: walls become continuous lines, the grids repeatable from node to node (what loop
closing and inter-frame compression, 4.3.4 and issue 5, both rely on) and cheaper to code.

The grid is in the node's ``base`` frame (axes aligned with it), centered on the robot: cell
``(row, col)`` covers ``origin_in_base + (col, row) * resolution_m``, as
``protocol.messages.TerrainGrid`` expects. ``O(N + rows * cols)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from robot.terrain.classifier import points_in_odom

__all__ = ["VerticalSurfaceConfig", "VerticalSurfaceGrid", "vertical_surface_grid"]


class VerticalSurfaceConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``resolution_m`` 10 cm; ``size_cells`` square grid side (400: 40 m, the sensor's useful
    range both ways); the height band and the vertical extent that makes a cell occupied;
    ``connect_max_gap_m``: consecutive returns of a scan line this close are joined by a
    segment (0: returns only)."""

    resolution_m: float = 0.10
    size_cells: int = 400
    z_min_m: float = 0.15
    z_max_m: float = 2.0
    min_vertical_extent_m: float = 0.25
    connect_max_gap_m: float = 0.5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution_m) and 0 < self.resolution_m <= 10):
            raise ValueError(f"resolution_m must be in (0, 10], got {self.resolution_m}")
        if not 2 <= self.size_cells <= 10000:
            raise ValueError(f"size_cells must be in [2, 10000], got {self.size_cells}")
        if not (math.isfinite(self.z_min_m) and math.isfinite(self.z_max_m)):
            raise ValueError("z_min_m and z_max_m must be finite")
        if not self.z_min_m < self.z_max_m:
            raise ValueError(f"need z_min_m < z_max_m, got {self.z_min_m}, {self.z_max_m}")
        if not (math.isfinite(self.min_vertical_extent_m) and self.min_vertical_extent_m > 0):
            raise ValueError(f"min_vertical_extent_m must be > 0, got {self.min_vertical_extent_m}")
        if not (math.isfinite(self.connect_max_gap_m) and 0 <= self.connect_max_gap_m <= 5):
            raise ValueError(f"connect_max_gap_m must be in [0, 5], got {self.connect_max_gap_m}")


@dataclass(frozen=True)
class VerticalSurfaceGrid:
    """``occupied`` ``(rows, cols)`` bool; cell ``(r, c)`` covers
    ``origin_in_base + (c, r) * resolution_m`` in the pose node's ``base`` frame."""

    occupied: NDArray[np.bool_]
    origin_in_base: tuple[float, float]
    resolution_m: float


@nb.njit(cache=True, nogil=True, inline="always")
def _extend(zmin, zmax, x, y, z, ox, oy, inv, z_lo, z_hi):  # type: ignore[no-untyped-def]
    if z < z_lo or z > z_hi:
        return
    c = int(math.floor((x - ox) * inv))
    r = int(math.floor((y - oy) * inv))
    if r < 0 or r >= zmin.shape[0] or c < 0 or c >= zmin.shape[1]:
        return
    if z < zmin[r, c]:
        zmin[r, c] = z
    if z > zmax[r, c]:
        zmax[r, c] = z


@nb.njit(cache=True, nogil=True)
def _vertical_cells(x, y, z, line, ox, oy, res, rows, cols, z_lo, z_hi, extent, gap):  # type: ignore[no-untyped-def]
    zmin = np.full((rows, cols), np.inf)
    zmax = np.full((rows, cols), -np.inf)
    inv = 1.0 / res
    n = x.shape[0]
    for i in range(n):
        _extend(zmin, zmax, x[i], y[i], z[i], ox, oy, inv, z_lo, z_hi)
        if i + 1 == n or line[i + 1] != line[i]:
            continue
        dx = x[i + 1] - x[i]
        dy = y[i + 1] - y[i]
        dz = z[i + 1] - z[i]
        if dx * dx + dy * dy + dz * dz > gap * gap:
            continue
        steps = int(math.ceil(math.sqrt(dx * dx + dy * dy) * inv * 2.0))
        for k in range(1, steps):  # the inside of the segment, every half cell
            f = k / steps
            _extend(
                zmin, zmax, x[i] + f * dx, y[i] + f * dy, z[i] + f * dz, ox, oy, inv, z_lo, z_hi
            )
    out = np.zeros((rows, cols), dtype=np.bool_)
    for r in range(rows):
        for c in range(cols):
            out[r, c] = zmax[r, c] - zmin[r, c] >= extent
    return out


def vertical_surface_grid(
    points_in_base: ArrayLike,
    *,
    config: VerticalSurfaceConfig,
    roll_rad: float = 0.0,
    pitch_rad: float = 0.0,
    base_from_point_base: ArrayLike | None = None,
    point_time_s: ArrayLike | None = None,
) -> VerticalSurfaceGrid:
    """The vertical-surface grid of one sweep, centered on the pose node's base.

    ``points_in_base`` ``(N, 3)``: the sweep in ``base``. To de-skew a sweep taken while
    driving, pass ``base_from_point_base``: ``(N, 3)`` SE(2) poses of the base at each point's
    time relative to the node's base (or one ``(3,)`` pose). ``roll_rad``/``pitch_rad`` level
    the body frame. ``point_time_s`` ``(N,)`` (the sweep's, see
    :class:`~protocol.sensors.LidarSweep`): points of one scan line share a time and come in
    scan order; with it, close consecutive returns of a line are joined (module doc). Raises
    ValueError naming bad input (NaN points, wrong shapes).
    """
    pose = np.zeros(3) if base_from_point_base is None else base_from_point_base
    pts = points_in_odom(
        points_in_base,
        pose,
        roll_rad=roll_rad,
        pitch_rad=pitch_rad,
        pose_name="base_from_point_base",
    )
    half = config.size_cells * config.resolution_m / 2
    gap = config.connect_max_gap_m
    if point_time_s is None:
        line = np.arange(len(pts), dtype=np.float64)  # every point its own line: no segments
    else:
        line = np.asarray(point_time_s, dtype=np.float64)
        if line.shape != (len(pts),):
            raise ValueError(f"point_time_s: expected shape ({len(pts)},), got {line.shape}")
    occupied = _vertical_cells(
        np.ascontiguousarray(pts[:, 0]),
        np.ascontiguousarray(pts[:, 1]),
        np.ascontiguousarray(pts[:, 2]),
        np.ascontiguousarray(line),
        -half,
        -half,
        float(config.resolution_m),
        config.size_cells,
        config.size_cells,
        float(config.z_min_m),
        float(config.z_max_m),
        float(config.min_vertical_extent_m),
        float(gap),
    )
    return VerticalSurfaceGrid(occupied, (-half, -half), config.resolution_m)
