"""Up-detector: the second stage of terrain classification (paper 5.3, Eq. 2).

An obstacle lies between cells ``A`` and ``B``, ``l`` cells apart, when
``|z_A - z_B| > a * l + b`` (constant-slope model; ``a`` the climbable rise per cell, ``b`` the
climbable step). Only the *higher* cell is marked, so obstacles are not dilated into the
drivable terrain in front of them.

``l`` is never computed: heights travel by message passing between 4-connected cells, each
hop adding ``a``. A cell keeps ``z_min`` and ``z_max`` of its ground-filtered points
(:func:`filter_height_range`); messages carry the lowest surface reachable from the sender
raised by ``a`` per hop, and a cell keeps the min of what it receives and its own ``z_min``.
After ``iterations`` rounds each cell knows ``L(A) = min_B (z_min(B) + a * l(A, B))`` over the
cells within ``iterations + 1`` hops (itself included, ``l = 0``), and ``A`` is an obstacle when
``z_max(A) - L(A) > b``.

Deviation from the paper's wording, which compares a cell's ``z_min`` with its neighbours'
``z_max``: we compare the cell's *highest* point with the *lowest* surface nearby. This is the
same Eq. 2 test of the pair (higher cell ``A``, lower cell ``B``), and it also marks cells
that contain a vertical face (a wall cell holds both the ground at its foot and the wall),
which the ``z_min``-based test misses. The lower cell of a pair is never marked: its own
``z_max`` is not above its neighbourhood.

Complexity ``O(N + iterations * rows * cols)``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from robot.terrain.grid import GridGeometry

__all__ = ["filter_height_range", "up_detector"]

FloatGrid = NDArray[np.float64]


@nb.njit(cache=True, nogil=True)
def _height_range(x, y, z, ox, oy, res, ground, clearance):  # type: ignore[no-untyped-def]
    rows, cols = ground.shape
    zmin = np.full((rows, cols), np.inf)
    zmax = np.full((rows, cols), -np.inf)
    inv = 1.0 / res
    for i in range(x.shape[0]):
        c = int(math.floor((x[i] - ox) * inv))
        r = int(math.floor((y[i] - oy) * inv))
        if r < 0 or r >= rows or c < 0 or c >= cols:
            continue
        zi = z[i]
        g = ground[r, c]
        if zi < g or zi > g + clearance:
            continue
        if zi < zmin[r, c]:
            zmin[r, c] = zi
        if zi > zmax[r, c]:
            zmax[r, c] = zi
    return zmin, zmax


@nb.njit(cache=True, nogil=True)
def _detect(zmin, zmax, a, b, iterations):  # type: ignore[no-untyped-def]
    rows, cols = zmin.shape
    cur = zmin.copy()
    nxt = np.empty_like(cur)
    for _ in range(iterations + 1):
        for r in range(rows):
            for c in range(cols):
                v = cur[r, c]
                if r > 0:
                    v = min(v, cur[r - 1, c] + a)
                if r + 1 < rows:
                    v = min(v, cur[r + 1, c] + a)
                if c > 0:
                    v = min(v, cur[r, c - 1] + a)
                if c + 1 < cols:
                    v = min(v, cur[r, c + 1] + a)
                nxt[r, c] = v
        cur, nxt = nxt, cur
    out = np.zeros((rows, cols), dtype=np.bool_)
    for r in range(rows):
        for c in range(cols):
            out[r, c] = zmax[r, c] - cur[r, c] > b
    return out


def filter_height_range(
    points: NDArray[np.float64],
    geometry: GridGeometry,
    ground_m: FloatGrid,
    *,
    overhead_clearance_m: float,
) -> tuple[FloatGrid, FloatGrid]:
    """``(z_min, z_max)`` per cell of the points with ``ground <= z <= ground + clearance``.

    Points below the cell's ground estimate are outliers (the ground model uses the
    second-lowest z); points more than ``overhead_clearance_m`` above it pass over the robot
    (tree canopy, paper 5.3). Empty cells get ``z_min = +inf``, ``z_max = -inf``.
    """
    if ground_m.shape != geometry.shape:
        raise ValueError(f"ground_m: shape {ground_m.shape} does not match grid {geometry.shape}")
    return _height_range(  # type: ignore[no-any-return]
        np.ascontiguousarray(points[:, 0]),
        np.ascontiguousarray(points[:, 1]),
        np.ascontiguousarray(points[:, 2]),
        float(geometry.origin_m[0]),
        float(geometry.origin_m[1]),
        float(geometry.resolution_m),
        np.ascontiguousarray(ground_m, dtype=np.float64),
        float(overhead_clearance_m),
    )


def up_detector(
    z_min: FloatGrid,
    z_max: FloatGrid,
    *,
    slope_per_cell_m: float,
    step_m: float,
    iterations: int,
    ground_m: FloatGrid | None = None,
) -> NDArray[np.bool_]:
    """Obstacle mask of Eq. 2 by ``iterations`` rounds of message passing (see module doc).

    ``slope_per_cell_m`` is ``a`` (climbable rise per cell), ``step_m`` is ``b``. Cells without
    points (``z_max = -inf``) are never obstacles. ``ground_m`` (the ground model), when given,
    is the height that cells *without* points send: the ground model's estimate in unobserved
    regions (paper 5.3) lets a face seen from afar, with no ground returns next to it, be
    compared with the ground beyond the gap. Because the ground model's prior slope bounds how
    fast those estimates rise, this is still Eq. 2 between observed cells, over a longer ``l``.
    """
    if z_min.shape != z_max.shape or z_min.ndim != 2:
        raise ValueError(f"z_min {z_min.shape} and z_max {z_max.shape} must be equal 2D shapes")
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if not (slope_per_cell_m >= 0 and step_m >= 0):
        raise ValueError(
            f"slope_per_cell_m ({slope_per_cell_m}) and step_m ({step_m}) must be >= 0"
        )
    low = np.asarray(z_min, dtype=np.float64)
    if ground_m is not None:
        if ground_m.shape != z_min.shape:
            raise ValueError(f"ground_m: shape {ground_m.shape} does not match z_min {z_min.shape}")
        low = np.where(np.isfinite(low), low, ground_m)
    return _detect(  # type: ignore[no-any-return]
        np.ascontiguousarray(low),
        np.ascontiguousarray(z_max, dtype=np.float64),
        float(slope_per_cell_m),
        float(step_m),
        int(iterations),
    )
