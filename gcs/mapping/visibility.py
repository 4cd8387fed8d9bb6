"""Occupied / free / unknown around one pose node from its binary vertical-surface grid.

Robots send, per pose node, only the cells that hold a vertical surface (paper 4.3.3), cropped
to their bounding box. The global map (paper 4.8) also needs free space: here a cell is
*free* when a ray from the sensor origin (the node's base origin) reaches it, within
``free_range_m`` and within the sensor's field of view ``free_fov_rad`` (centred on the base's
+x axis; ``2 pi`` for an all-round sensor), before any occupied cell; *occupied* cells are the
grid's; everything else is *unknown*. This is a polar visibility sweep done ONCE per node, in
the node's own ``base`` frame, on the grid's own lattice; the global rasterizer then only
warps the result.

The sweep casts ``ceil(4 pi R / res)`` rays (spacing at range ``R`` is half a cell, below
the angle any cell within ``R`` subtends, so every cell in range is crossed by some ray) and
walks each with the 4-connected grid traversal of Amanatides and Woo, so a ray never slips
between two diagonal wall cells. A cell is marked free when some ray enters it at a distance
``<= R`` before hitting an occupied cell. ``O(R^2 / res^2)`` per node.

*Wall gaps.* A wall seen at range or at a grazing angle comes as runs of cells with holes
between them (beams 1.5 degrees apart are 18 cm apart at 7 m, more at a slant); a ray through
such a hole would mark a thin streak of free space behind the wall. With ``wall_gap_m``, the
grid is closed morphologically (dilation then erosion by a square of side ``2 m + 1`` cells,
``m = floor(wall_gap_m / (2 res))``): the cells the closing adds (holes up to ``2 m`` cells
between occupied cells) stop rays but stay unknown, so walls are not thickened and free space
still reaches a wall's face. Within ``m + 1`` cells of the origin they do not stop rays (a
robot beside a corner would otherwise see nothing).

The lattice convention follows ``protocol.messages.TerrainGrid``: cell ``(row, col)`` covers
``origin_in_base + (col, row) * resolution_m`` (``origin_in_base`` is the corner of cell
``(0, 0)``; its centre is at ``+ resolution_m / 2``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["FREE", "OCCUPIED", "UNKNOWN", "LocalRaster", "local_raster"]

#: Cell codes of a :class:`LocalRaster`.
UNKNOWN = 0
FREE = 1
OCCUPIED = 2

#: Largest grid side accepted (cells); a 40 m window at 1 cm would be 4000.
MAX_GRID_SIDE = 8192


@dataclass(frozen=True)
class LocalRaster:
    """One node's occupied / free / unknown cells in its ``base`` frame.

    ``cells`` ``(rows, cols)`` int8 of :data:`UNKNOWN`, :data:`FREE`, :data:`OCCUPIED`, cropped
    to the bounding box of the observed (non-unknown) cells; cell ``(r, c)`` covers
    ``origin_in_base + (c, r) * resolution_m``. Empty (``0 x 0``) when nothing is observed.
    """

    cells: NDArray[np.int8]
    origin_in_base: tuple[float, float]
    resolution_m: float

    @property
    def observed_cells(self) -> int:
        return int(np.count_nonzero(self.cells))


@numba.njit(cache=True, nogil=True)
def _sweep(occ, block, near_cells, u0, v0, length_cells, n_rays, half_fov):  # type: ignore[no-untyped-def]
    """Mark cells reached by rays from ``(u0, v0)`` (cell units) before an occupied cell,
    for rays within ``half_fov`` of +x; farther than ``near_cells`` from the origin, a ray
    also stops at a cell of ``block`` (a gap of a wall that the closing filled)."""
    rows, cols = occ.shape
    out = np.zeros((rows, cols), dtype=np.int8)
    for r in range(rows):
        for c in range(cols):
            if occ[r, c]:
                out[r, c] = 2
    for k in range(n_rays):
        a = 2.0 * math.pi * k / n_rays
        if abs(a if a <= math.pi else a - 2.0 * math.pi) > half_fov:
            continue
        dx = math.cos(a)
        dy = math.sin(a)
        ix = int(math.floor(u0))
        iy = int(math.floor(v0))
        if dx > 0:
            step_x = 1
            t_max_x = (ix + 1 - u0) / dx
            t_dx = 1.0 / dx
        elif dx < 0:
            step_x = -1
            t_max_x = (u0 - ix) / -dx
            t_dx = -1.0 / dx
        else:
            step_x = 0
            t_max_x = math.inf
            t_dx = math.inf
        if dy > 0:
            step_y = 1
            t_max_y = (iy + 1 - v0) / dy
            t_dy = 1.0 / dy
        elif dy < 0:
            step_y = -1
            t_max_y = (v0 - iy) / -dy
            t_dy = -1.0 / dy
        else:
            step_y = 0
            t_max_y = math.inf
            t_dy = math.inf
        t = 0.0
        while t <= length_cells:
            if ix < 0 or iy < 0 or ix >= cols or iy >= rows:
                break
            if occ[iy, ix]:
                break
            if block[iy, ix] and t > near_cells:
                break
            out[iy, ix] = 1
            if t_max_x < t_max_y:
                t = t_max_x
                t_max_x += t_dx
                ix += step_x
            else:
                t = t_max_y
                t_max_y += t_dy
                iy += step_y
    return out


def local_raster(
    grid: NDArray[np.bool_],
    origin_in_base: tuple[float, float],
    resolution_m: float,
    *,
    free_range_m: float,
    free_fov_rad: float = 2.0 * math.pi,
    wall_gap_m: float = 0.0,
    where: str = "grid",
) -> LocalRaster:
    """Occupied / free / unknown cells of one node from its binary grid (see module docstring).

    ``grid`` ``(rows, cols)`` bool (or 0/1 integers) of vertical surfaces; it may be ``0 x 0``
    (nothing seen: the node still observes free space). ``wall_gap_m`` (``[0, 10]``; 0: rays
    pass any hole) closes holes in walls up to that width for the rays. ``where`` names the
    grid in errors. Raises ValueError on a bad grid, origin, resolution, range or gap.
    """
    g = np.asarray(grid)
    if g.ndim != 2:
        raise ValueError(f"{where}: grid must be 2-D, got shape {g.shape}")
    if g.dtype != np.bool_:
        if not np.issubdtype(g.dtype, np.integer):
            raise ValueError(f"{where}: grid must be bool or 0/1 integers, got dtype {g.dtype}")
        if g.size and (g.min() < 0 or g.max() > 1):
            raise ValueError(f"{where}: integer grid must hold only 0 and 1")
        g = g.astype(bool)
    if max(g.shape) > MAX_GRID_SIDE:
        raise ValueError(f"{where}: grid shape {g.shape} exceeds {MAX_GRID_SIDE} cells a side")
    if len(origin_in_base) != 2:
        raise ValueError(f"{where}: origin_in_base must be (x, y), got {origin_in_base!r}")
    ox, oy = float(origin_in_base[0]), float(origin_in_base[1])
    res = float(resolution_m)
    if not (math.isfinite(ox) and math.isfinite(oy)):
        raise ValueError(f"{where}: origin_in_base must be finite, got {origin_in_base!r}")
    if not (math.isfinite(res) and 0.001 <= res <= 10.0):
        raise ValueError(f"{where}: resolution_m must be in [0.001, 10], got {resolution_m!r}")
    if not (math.isfinite(free_range_m) and 0 <= free_range_m <= 1000):
        raise ValueError(f"{where}: free_range_m must be in [0, 1000], got {free_range_m!r}")
    if not (math.isfinite(free_fov_rad) and 0 <= free_fov_rad <= 2 * math.pi):
        raise ValueError(f"{where}: free_fov_rad must be in [0, 2 pi], got {free_fov_rad!r}")
    if not (math.isfinite(wall_gap_m) and 0 <= wall_gap_m <= 10):
        raise ValueError(f"{where}: wall_gap_m must be in [0, 10], got {wall_gap_m!r}")
    rows, cols = g.shape
    reach = free_range_m / res
    # Extended lattice: the grid plus every cell a ray can reach (the disc around the origin).
    u = -ox / res
    v = -oy / res
    if abs(u) > 1e6 or abs(v) > 1e6:
        raise ValueError(f"{where}: origin_in_base {origin_in_base!r} is too far from the node")
    c_lo = min(0, math.floor(u - reach) - 1) if reach > 0 else 0
    c_hi = max(cols, math.ceil(u + reach) + 1) if reach > 0 else cols
    r_lo = min(0, math.floor(v - reach) - 1) if reach > 0 else 0
    r_hi = max(rows, math.ceil(v + reach) + 1) if reach > 0 else rows
    if (c_hi - c_lo) * (r_hi - r_lo) > 4 * MAX_GRID_SIDE * MAX_GRID_SIDE:
        raise ValueError(f"{where}: grid and free range span too many cells")
    occ = np.zeros((r_hi - r_lo, c_hi - c_lo), dtype=np.bool_)
    occ[-r_lo : -r_lo + rows, -c_lo : -c_lo + cols] = g
    n_rays = math.ceil(4.0 * math.pi * reach) if reach > 0 else 0
    margin = math.floor(wall_gap_m / (2.0 * res) + 1e-6)
    if margin > 0 and g.any():
        size = 2 * margin + 1
        kernel = np.ones((size, size), np.uint8)
        block = cv2.morphologyEx(occ.view(np.uint8), cv2.MORPH_CLOSE, kernel).view(np.bool_)
    else:
        block = occ
    cells = _sweep(
        occ, block, margin + 1.0, u - c_lo, v - r_lo, reach, n_rays, free_fov_rad / 2 + 1e-12
    )
    seen_rows = np.flatnonzero(cells.any(axis=1))
    if len(seen_rows) == 0:
        return LocalRaster(np.zeros((0, 0), dtype=np.int8), (ox, oy), res)
    seen_cols = np.flatnonzero(cells.any(axis=0))
    r0, r1 = int(seen_rows[0]), int(seen_rows[-1]) + 1
    c0, c1 = int(seen_cols[0]), int(seen_cols[-1]) + 1
    crop = np.ascontiguousarray(cells[r0:r1, c0:c1])
    origin = (ox + (c_lo + c0) * res, oy + (r_lo + r0) * res)
    return LocalRaster(crop, origin, res)
