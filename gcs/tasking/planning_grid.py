"""The coarse planning grid the GCS's planners search (paper 5.1).

The rasterized global map (paper 4.8, :class:`~gcs.mapping.rasterization.OccupancyMap`) is
fine (0.1-0.2 m) and large (220 x 160 m in MAGIC); the task planners only need to know where a
robot can drive and where the unknown begins, so they work on a coarser grid:

* a coarse cell is ``OCCUPIED`` if any fine cell in it is occupied (pessimistic: a planner
  never sends a robot through an obstacle it has seen), else ``FREE`` if at least
  ``free_fraction`` of its fine cells are free, else ``UNKNOWN``;
* ``traversable`` cells are free cells at least ``robot_radius_m`` from every occupied cell
  (the circular configuration-space kernel of paper 5.4) and outside every keep-out disc
  (the OOIs' trigger and blast radii, paper section 2).

Also here: :func:`line_of_sight` over the coarse grid (occupied cells block, unknown does not)
and :func:`simplify_path` (Ramer-Douglas-Peucker) for the waypoints sent to robots.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap

__all__ = ["PlanningGrid", "coarsen", "line_of_sight", "simplify_path"]


@dataclass(frozen=True)
class PlanningGrid:
    """``values`` ``(rows, cols)`` int8 (``UNKNOWN``/``FREE``/``OCCUPIED``) and ``traversable``
    bool of the coarse grid; cell ``(row, col)`` covers ``origin_in_map + (col, row) *
    resolution_m`` (rows along +y, as :class:`OccupancyMap`)."""

    values: NDArray[np.int8]
    traversable: NDArray[np.bool_]
    origin_in_map: tuple[float, float]
    resolution_m: float

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.values.shape[0]), int(self.values.shape[1]))

    def cells_of(self, points_in_map: ArrayLike) -> NDArray[np.int64]:
        """``(N, 2)`` ``(row, col)`` holding ``points_in_map`` ``(N, 2)`` (maybe outside)."""
        pts = np.asarray(points_in_map, dtype=np.float64).reshape(-1, 2)
        col = np.floor((pts[:, 0] - self.origin_in_map[0]) / self.resolution_m)
        row = np.floor((pts[:, 1] - self.origin_in_map[1]) / self.resolution_m)
        return np.stack([row, col], axis=1).astype(np.int64)

    def centers_of(self, cells: ArrayLike) -> NDArray[np.float64]:
        """``(N, 2)`` map points at the centres of ``(row, col)`` cells ``(N, 2)``."""
        rc = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
        x = self.origin_in_map[0] + (rc[:, 1] + 0.5) * self.resolution_m
        y = self.origin_in_map[1] + (rc[:, 0] + 0.5) * self.resolution_m
        return np.stack([x, y], axis=1)

    def inside(self, cells: ArrayLike) -> NDArray[np.bool_]:
        rc = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        rows, cols = self.shape
        return (rc[:, 0] >= 0) & (rc[:, 0] < rows) & (rc[:, 1] >= 0) & (rc[:, 1] < cols)  # type: ignore[no-any-return]

    def traversable_near(
        self, point_in_map: ArrayLike, radius_m: float
    ) -> tuple[tuple[int, int], NDArray[np.int64], NDArray[np.int64]] | None:
        """The cell of ``point_in_map`` and the (row, col) indices of the traversable cells in
        the square of half-side ``radius_m`` around it; None if there are none."""
        (r, c) = self.cells_of(point_in_map)[0]
        k = max(0, int(math.ceil(radius_m / self.resolution_m)))
        rows, cols = self.shape
        r0, r1 = max(0, r - k), min(rows, r + k + 1)
        c0, c1 = max(0, c - k), min(cols, c + k + 1)
        if r0 >= r1 or c0 >= c1:
            return None
        rr, cc = np.nonzero(self.traversable[r0:r1, c0:c1])
        if rr.size == 0:
            return None
        return (int(r), int(c)), rr.astype(np.int64) + r0, cc.astype(np.int64) + c0

    def snap(self, point_in_map: ArrayLike, max_m: float) -> tuple[int, int] | None:
        """The traversable cell nearest ``point_in_map`` within ``max_m`` (a robot whose own
        cell lies in the clearance band of a wall still plans from beside it); None if none."""
        near = self.traversable_near(point_in_map, max_m)
        if near is None:
            return None
        (r, c), rr, cc = near
        d2 = (rr - r) ** 2 + (cc - c) ** 2
        i = int(np.argmin(d2))
        if d2[i] * self.resolution_m**2 > max_m**2 + 1e-9:
            return None
        return int(rr[i]), int(cc[i])


def coarsen(
    occupancy: OccupancyMap,
    *,
    resolution_m: float,
    robot_radius_m: float,
    free_fraction: float = 0.5,
    keepout_in_map: ArrayLike | None = None,
) -> PlanningGrid:
    """The planning grid of ``occupancy`` at about ``resolution_m`` (an integer multiple of the
    map's cells, at least 1). ``keepout_in_map`` ``(K, 3)`` ``(x_m, y_m, radius_m)`` discs are
    not traversable."""
    if not (math.isfinite(resolution_m) and resolution_m > 0):
        raise ValueError(f"resolution_m must be finite and > 0, got {resolution_m}")
    fine = np.asarray(occupancy.values)
    if fine.ndim != 2:
        raise ValueError(f"occupancy.values must be 2-D, got shape {fine.shape}")
    # round half up (0.3 / 0.2 is 1.4999...: 2, not 1)
    f = max(1, int(math.floor(resolution_m / occupancy.resolution_m + 0.5 + 1e-9)))
    res = occupancy.resolution_m * f
    rows = -(-fine.shape[0] // f)
    cols = -(-fine.shape[1] // f)
    if f == 1:
        occ = fine == OCCUPIED
        values = np.where(occ, OCCUPIED, np.where(fine == FREE, FREE, UNKNOWN)).astype(np.int8)
    else:
        pad = np.full((rows * f, cols * f), UNKNOWN, dtype=np.int8)
        pad[: fine.shape[0], : fine.shape[1]] = fine
        blocks = pad.reshape(rows, f, cols, f)
        occ = (blocks == OCCUPIED).any(axis=(1, 3))
        nfree = (blocks == FREE).sum(axis=(1, 3))
        values = np.full((rows, cols), UNKNOWN, dtype=np.int8)
        values[nfree >= free_fraction * f * f] = FREE
        values[occ] = OCCUPIED
    free = values == FREE
    if rows and cols and robot_radius_m > 0 and (values == OCCUPIED).any():
        clearance_m = ndimage.distance_transform_edt(values != OCCUPIED) * res
        traversable = free & (clearance_m > robot_radius_m)
    else:
        traversable = free.copy()
    grid = PlanningGrid(values, traversable, tuple(map(float, occupancy.origin_in_map)), res)  # type: ignore[arg-type]
    if keepout_in_map is not None:
        discs = np.asarray(keepout_in_map, dtype=np.float64).reshape(-1, 3)
        for x, y, radius in discs:
            _clear_disc(grid, x, y, radius)
    return grid


def _clear_disc(grid: PlanningGrid, x: float, y: float, radius_m: float) -> None:
    (r, c) = grid.cells_of([x, y])[0]
    k = int(math.ceil(radius_m / grid.resolution_m)) + 1
    rows, cols = grid.shape
    r0, r1 = max(0, r - k), min(rows, r + k + 1)
    c0, c1 = max(0, c - k), min(cols, c + k + 1)
    if r0 >= r1 or c0 >= c1:
        return
    rr, cc = np.mgrid[r0:r1, c0:c1]
    centers = grid.centers_of(np.stack([rr.ravel(), cc.ravel()], axis=1))
    inside = np.hypot(centers[:, 0] - x, centers[:, 1] - y) <= radius_m
    grid.traversable[rr.ravel()[inside], cc.ravel()[inside]] = False


@nb.njit(cache=True, nogil=True)
def _los(values, r0, c0, r1, c1, occupied):  # type: ignore[no-untyped-def]
    # Walk the segment at quarter-cell steps; any occupied cell on it blocks the view.
    rows, cols = values.shape
    n = int(max(abs(r1 - r0), abs(c1 - c0)) * 4.0) + 1
    for i in range(n + 1):
        t = i / n
        r = int(math.floor(r0 + (r1 - r0) * t))
        c = int(math.floor(c0 + (c1 - c0) * t))
        if r < 0 or r >= rows or c < 0 or c >= cols:
            continue
        if values[r, c] == occupied:
            return False
    return True


def line_of_sight(grid: PlanningGrid, a_in_map: ArrayLike, b_in_map: ArrayLike) -> bool:
    """True if no occupied cell of ``grid`` lies on the segment ``a``-``b`` (unknown cells do
    not block: the GCS cannot know better)."""
    a = np.asarray(a_in_map, dtype=np.float64)
    b = np.asarray(b_in_map, dtype=np.float64)
    ox, oy = grid.origin_in_map
    res = grid.resolution_m
    return bool(
        _los(
            grid.values,
            (a[1] - oy) / res,
            (a[0] - ox) / res,
            (b[1] - oy) / res,
            (b[0] - ox) / res,
            OCCUPIED,
        )
    )


def simplify_path(points_in_map: ArrayLike, tolerance_m: float) -> NDArray[np.float64]:
    """Ramer-Douglas-Peucker: the subset of ``points_in_map`` ``(N, 2)`` (first and last always
    kept) within ``tolerance_m`` of the original polyline."""
    pts = np.asarray(points_in_map, dtype=np.float64).reshape(-1, 2)
    if len(pts) <= 2:
        return pts.copy()
    keep = np.zeros(len(pts), dtype=bool)
    keep[0] = keep[-1] = True
    stack = [(0, len(pts) - 1)]
    while stack:
        i, j = stack.pop()
        if j <= i + 1:
            continue
        a, b = pts[i], pts[j]
        ab = b - a
        seg = pts[i + 1 : j] - a
        norm = math.hypot(ab[0], ab[1])
        if norm < 1e-12:
            d = np.hypot(seg[:, 0], seg[:, 1])
        else:
            d = np.abs(ab[0] * seg[:, 1] - ab[1] * seg[:, 0]) / norm
        k = int(np.argmax(d))
        if d[k] > tolerance_m:
            m = i + 1 + k
            keep[m] = True
            stack.append((i, m))
            stack.append((m, j))
    return pts[keep]
