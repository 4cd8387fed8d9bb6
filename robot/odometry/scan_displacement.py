"""How far the robot really moved between two LIDAR sweeps: the slip the wheels cannot see.

Wheel encoders count what the wheels did; on sand the body moves less (paper 4.3.1: the
reason MAGIC's robots needed more than wheel odometry), so odometry over-counts by the
slip. Static obstacles do not move: if the odometry over-counted by ``e`` between two sweeps,
everything the second sweep sees is placed ``e`` too far along, in ``odom``. Shifting the
second sweep's obstacle cells until they fall back onto the first sweep's (a correlation over
a small window of whole-cell translations) measures ``-e``; the true displacement is the
odometry's plus that shift. This is the *measured* speed of AOJRF's traversability (Eq. 1,
:mod:`robot.control.traversability`), against the wheels' speed as the requested one.

Heading is the gyro's, good over 1.25 s, so only translation is searched. A match is
accepted only with enough cells, a clear share of them agreeing, and a peak that is unique
along the direction of motion (a long wall parallel to the motion cannot tell how far the
robot went). Pure numpy/numba over the classifier's obstacle grids on one ``odom`` lattice;
``O(N * (2K + 1)^2)`` for ``N`` cells and a ``K``-cell window.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from robot.terrain.grid import GridGeometry

__all__ = ["ScanShift", "match_translation"]


@dataclass(frozen=True)
class ScanShift:
    """``shift_in_odom``: the ``(dx, dy)`` metres that move the newer sweep's obstacles onto
    the older sweep's (add it to the odometry's displacement for the true one); ``agreeing``:
    how many of ``cells`` cells matched at that shift."""

    shift_in_odom: tuple[float, float]
    agreeing: int
    cells: int


@nb.njit(cache=True, nogil=True)
def _scores(prev, pr0, pc0, rows, cols, k):  # type: ignore[no-untyped-def]
    n = rows.shape[0]
    h, w = prev.shape
    out = np.zeros((2 * k + 1, 2 * k + 1), dtype=np.int64)
    for i in range(n):
        for dr in range(-k, k + 1):
            r = rows[i] + dr - pr0
            if r < 0 or r >= h:
                continue
            for dc in range(-k, k + 1):
                c = cols[i] + dc - pc0
                if 0 <= c < w and prev[r, c]:
                    out[dr + k, dc + k] += 1
    return out


def match_translation(
    prev_obstacle: NDArray[np.bool_],
    prev_geometry: GridGeometry,
    obstacle: NDArray[np.bool_],
    geometry: GridGeometry,
    *,
    center_in_odom: ArrayLike,
    direction_in_odom: ArrayLike,
    radius_m: float,
    max_shift_m: float,
    min_cells: int = 30,
    min_agreeing_frac: float = 0.3,
    max_ambiguity_m: float = 0.15,
) -> ScanShift | None:
    """Match the newer sweep's ``obstacle`` cells within ``radius_m`` of ``center_in_odom``
    onto ``prev_obstacle`` (both grids on the same ``odom`` lattice), over whole-cell shifts
    up to ``max_shift_m``; None when the match is not trustworthy (see the module doc).
    ``direction_in_odom``: the direction of motion, along which the peak must be unique
    (near-best shifts, within 90% of the best count, spread at most ``max_ambiguity_m``)."""
    if not math.isclose(prev_geometry.resolution_m, geometry.resolution_m, rel_tol=1e-9):
        raise ValueError("match_translation: the two sweeps' grids differ in resolution")
    for name, grid, geo in (
        ("prev_obstacle", prev_obstacle, prev_geometry),
        ("obstacle", obstacle, geometry),
    ):
        if np.shape(grid) != geo.shape or np.asarray(grid).dtype != np.bool_:
            raise ValueError(f"{name}: expected a bool grid of shape {geo.shape}")
    center = np.asarray(center_in_odom, dtype=np.float64).reshape(2)
    direction = np.asarray(direction_in_odom, dtype=np.float64).reshape(2)
    norm = float(np.hypot(*direction))
    if not (np.all(np.isfinite(center)) and math.isfinite(norm) and norm > 0):
        raise ValueError("center_in_odom and direction_in_odom must be finite, direction non-zero")
    direction = direction / norm
    res = geometry.resolution_m
    rr, cc = np.nonzero(obstacle)
    if len(rr) < min_cells:
        return None
    xy = geometry.center_of(np.stack([rr, cc], axis=1))
    near = np.hypot(xy[:, 0] - center[0], xy[:, 1] - center[1]) <= radius_m
    rr, cc = rr[near], cc[near]
    n = len(rr)
    if n < min_cells:
        return None
    r0, c0 = geometry.lattice_index()
    p0, q0 = prev_geometry.lattice_index()
    # one cell of tolerance: the two sweeps' scan lines hit surfaces at slightly different spots
    prev = cv2.dilate(np.asarray(prev_obstacle).view(np.uint8), np.ones((3, 3), np.uint8)) > 0
    k = max(1, int(round(max_shift_m / res)))
    scores = _scores(prev, p0, q0, (rr + r0).astype(np.int64), (cc + c0).astype(np.int64), k)
    best = int(scores.max())
    if best < min_cells or best < min_agreeing_frac * n:
        return None
    dr, dc = np.nonzero(scores >= 0.9 * best)
    along = ((dc - k) * direction[0] + (dr - k) * direction[1]) * res
    if float(along.max() - along.min()) > max_ambiguity_m:
        return None
    i, j = np.unravel_index(int(np.argmax(scores)), scores.shape)
    return ScanShift(((j - k) * res, (i - k) * res), best, n)
