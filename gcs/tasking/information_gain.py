"""Expected information gain of a candidate goal (paper 5.1.1).

"The expected information gain is calculated by casting out rays from a candidate goal to
estimate a robot's sensor coverage of new terrain at the goal location." From the goal's cell
centre, ``rays`` rays (evenly spread over 360 degrees) walk at half-cell steps out to
``sensor_range_m``; a ray stops at the first occupied cell (the sensor cannot see through it) or
at the grid's edge, and every distinct unknown cell it crosses counts once. The gain is that
count times the cell area (m^2). Cells beyond the grid's edge are unknown too (the map grows)
and count up to ``sensor_range_m``. ``rays`` 0 picks enough rays that neighbouring rays are at
most one cell apart at full range (an estimate: a cell a ray only grazes may be missed).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from gcs.mapping.rasterization import OCCUPIED, UNKNOWN
from gcs.tasking.planning_grid import PlanningGrid

__all__ = ["information_gain", "rays_for"]


def rays_for(sensor_range_m: float, resolution_m: float) -> int:
    """Rays needed so neighbours are <= one cell apart at ``sensor_range_m``."""
    return max(8, int(math.ceil(2.0 * math.pi * sensor_range_m / resolution_m)))


@nb.njit(cache=True, nogil=True)
def _gain(values, goal_cells, range_cells, rays, unknown, occupied):  # type: ignore[no-untyped-def]
    rows, cols = values.shape
    k = int(math.ceil(range_cells)) + 1
    w = 2 * k + 1
    stamp = np.zeros((w, w), dtype=np.int32)
    out = np.zeros(len(goal_cells), dtype=np.int64)
    steps = int(range_cells * 2.0)
    for g in range(len(goal_cells)):
        gr = goal_cells[g, 0]
        gc = goal_cells[g, 1]
        tag = g + 1
        count = 0
        r0 = gr + 0.5
        c0 = gc + 0.5
        for a in range(rays):
            ang = 2.0 * math.pi * a / rays
            dr = math.sin(ang) * 0.5
            dc = math.cos(ang) * 0.5
            for s in range(1, steps + 1):
                r = int(math.floor(r0 + dr * s))
                c = int(math.floor(c0 + dc * s))
                lr = r - gr + k
                lc = c - gc + k
                inside = r >= 0 and r < rows and c >= 0 and c < cols
                if inside and values[r, c] == occupied:
                    break
                if stamp[lr, lc] == tag:
                    continue
                stamp[lr, lc] = tag
                if (not inside) or values[r, c] == unknown:
                    count += 1
        out[g] = count
    return out


def information_gain(
    grid: PlanningGrid,
    goal_cells: ArrayLike,
    *,
    sensor_range_m: float,
    rays: int = 0,
) -> NDArray[np.float64]:
    """``(K,)`` m^2 of unknown terrain a robot at each of ``goal_cells`` ``(K, 2)`` would see."""
    cells = np.ascontiguousarray(np.asarray(goal_cells, dtype=np.int64).reshape(-1, 2))
    if not (math.isfinite(sensor_range_m) and sensor_range_m > 0):
        raise ValueError(f"sensor_range_m must be finite and > 0, got {sensor_range_m}")
    if len(cells) == 0:
        return np.zeros(0)
    n = rays if rays > 0 else rays_for(sensor_range_m, grid.resolution_m)
    counts = _gain(
        np.ascontiguousarray(grid.values),
        cells,
        sensor_range_m / grid.resolution_m,
        n,
        UNKNOWN,
        OCCUPIED,
    )
    return counts.astype(np.float64) * grid.resolution_m**2  # type: ignore[no-any-return]
