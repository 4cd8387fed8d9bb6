"""Ground model: the first stage of terrain classification (paper 5.3).

The minimum z observed in a cell is an upper bound of the ground height there (we cannot see
through the ground). Simple outlier rejection: a cell with two or more points uses its
*second*-lowest z, so one spurious low return cannot pull the ground down. The bounds are then
propagated between cells with a prior of terrain sloping upward at most ``ground_slope_deg``
(20 deg in the paper): ``ground(c) = min_s bound(s) + tan(slope) * dist(c, s)``. This gives
ground estimates in unobserved cells too, and lets the up-detector reject points far above the
ground such as overhanging tree canopy (:func:`filter_height_range`).

The propagation is a two-pass chamfer transform over the 8-connected grid (steps of 1 and
sqrt(2) cells), exact for that metric, ``O(rows * cols)``. Each pass takes a row's
neighbours in the row before it in one loop the compiler vectorizes, then the row's own
neighbour in a running scan: 1.45 -> 0.56 ms thread CPU at 400 x 400, the same values as the
cell-by-cell sweep (session 13, load ~20; the robot node runs it for terrain classification
and for perception's segmentation every sweep).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from robot.terrain.grid import GridGeometry

__all__ = ["cell_ground_bounds", "ground_model", "propagate_ground"]

FloatGrid = NDArray[np.float64]


@nb.njit(cache=True, nogil=True)
def _lowest_two(x, y, z, ox, oy, res, rows, cols):  # type: ignore[no-untyped-def]
    z1 = np.full((rows, cols), np.inf)
    z2 = np.full((rows, cols), np.inf)
    inv = 1.0 / res
    for i in range(x.shape[0]):
        c = int(math.floor((x[i] - ox) * inv))
        r = int(math.floor((y[i] - oy) * inv))
        if r < 0 or r >= rows or c < 0 or c >= cols:
            continue
        zi = z[i]
        if zi < z1[r, c]:
            z2[r, c] = z1[r, c]
            z1[r, c] = zi
        elif zi < z2[r, c]:
            z2[r, c] = zi
    out = np.empty((rows, cols))
    for r in range(rows):
        for c in range(cols):
            out[r, c] = z2[r, c] if z2[r, c] < np.inf else z1[r, c]
    return out


@nb.njit(cache=True, nogil=True)
def _chamfer_min(g, step, diag):  # type: ignore[no-untyped-def]
    # every cell the minimum of the same candidates as the cell-by-cell sweep, in another
    # order (no NaN: bounds are finite or +inf), so the same values (module docstring)
    rows, cols = g.shape
    for r in range(rows):
        row = g[r]
        if r > 0:
            up = g[r - 1]
            for c in range(cols):
                v = min(row[c], up[c] + step)
                if c > 0:
                    v = min(v, up[c - 1] + diag)
                if c + 1 < cols:
                    v = min(v, up[c + 1] + diag)
                row[c] = v
        for c in range(1, cols):
            row[c] = min(row[c], row[c - 1] + step)
    for r in range(rows - 1, -1, -1):
        row = g[r]
        if r + 1 < rows:
            down = g[r + 1]
            for c in range(cols):
                v = min(row[c], down[c] + step)
                if c + 1 < cols:
                    v = min(v, down[c + 1] + diag)
                if c > 0:
                    v = min(v, down[c - 1] + diag)
                row[c] = v
        for c in range(cols - 2, -1, -1):
            row[c] = min(row[c], row[c + 1] + step)
    return g


def cell_ground_bounds(points: NDArray[np.float64], geometry: GridGeometry) -> FloatGrid:
    """Per-cell upper bound of the ground height: the second-lowest z of the cell's points
    (the lowest when the cell has one point), ``+inf`` in cells without points.

    ``points`` is ``(N, 3)`` in the grid's frame (z up); points outside the grid are ignored.
    ``O(N + rows * cols)``.
    """
    return _lowest_two(  # type: ignore[no-any-return]
        np.ascontiguousarray(points[:, 0]),
        np.ascontiguousarray(points[:, 1]),
        np.ascontiguousarray(points[:, 2]),
        float(geometry.origin_m[0]),
        float(geometry.origin_m[1]),
        float(geometry.resolution_m),
        geometry.rows,
        geometry.cols,
    )


def propagate_ground(
    bounds: FloatGrid, *, resolution_m: float, ground_slope_deg: float = 20.0
) -> FloatGrid:
    """``min_s bounds[s] + tan(ground_slope_deg) * d8(c, s) * resolution_m`` for every cell
    ``c``, with ``d8`` the 8-connected chamfer distance in cells (steps 1 and sqrt(2)).
    Returns a new array; all ``+inf`` if no cell has a bound."""
    if not 0.0 <= ground_slope_deg < 90.0:
        raise ValueError(f"ground_slope_deg must be in [0, 90), got {ground_slope_deg}")
    rise = math.tan(math.radians(ground_slope_deg)) * resolution_m
    g = np.array(bounds, dtype=np.float64, copy=True)
    return _chamfer_min(g, rise, rise * math.sqrt(2.0))  # type: ignore[no-any-return]


def ground_model(
    points: NDArray[np.float64], geometry: GridGeometry, *, ground_slope_deg: float = 20.0
) -> FloatGrid:
    """The ground height estimate of every cell (paper 5.3, first stage): per-cell bounds
    (:func:`cell_ground_bounds`) propagated with the slope prior (:func:`propagate_ground`)."""
    return propagate_ground(
        cell_ground_bounds(points, geometry),
        resolution_m=geometry.resolution_m,
        ground_slope_deg=ground_slope_deg,
    )
