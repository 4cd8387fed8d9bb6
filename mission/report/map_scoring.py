"""The GCS's global map scored against the simulator's truth raster (issue 14 item 3; paper 7).

Ground truth reaches only ``mission/`` (DESIGN section 2). Two grids meet here:

* the global map, an :class:`~gcs.mapping.rasterization.OccupancyMap` in ``map`` (values
  ``UNKNOWN`` -1, ``FREE`` 0, ``OCCUPIED`` 100; cell ``(row, col)`` covers
  ``origin + (col, row) * res``);
* the truth layers of :class:`~sim.ground_truth.GroundTruth` in ``world`` (cell ``[i, j]``
  covers ``x in [j res, (j + 1) res)``, ``y in [i res, (i + 1) res)``).

``world_from_map`` relates them. The GCS anchors ``map`` to one robot's private frame
(``PoseGraphConfig.map_robot_id`` with ``map_from_odom``), and a robot's ``odom`` starts at its
start pose, so ``world_from_map = start(map robot) * inverse(map_from_odom)`` holds exactly in
the truth: the map is scored in the frame it claims, with no fitted alignment (its drift away
from the anchor is an error of the map).

Scores (pure functions over numpy arrays):

* :func:`explored_frac`: the fraction of the truth's *reachable* cells (where a robot's centre
  can get to) that the map knows (free or occupied): how much of the area a team could reach
  it has mapped.
* :func:`occupancy_scores`: precision, recall and F1 of the map's occupied cells against the
  truth's vertical structures, with a distance tolerance (a LIDAR map is as good as its poses:
  ``tolerance_m`` of 0.2 m is two truth cells). Precision: occupied map cells within tolerance
  of a truth structure. Recall: truth *surface* cells (a structure cell beside a free one: the
  inside of a wall or a car is never seen) within tolerance of an occupied map cell, counted
  only where the map knows some cell within tolerance (what was observed; the rest is
  exploration, scored by :func:`explored_frac`).

Measured ceiling (small world, 300 s, seeds 0 / 7 at 66f8349, journals replayed): the same
nodes' grids rasterized by the GCS at the *true* poses score F1 0.952 / 0.952 (precision
0.942 / 0.945, recall 0.963 / 0.959), at the GCS's poses 0.869 / 0.746 (ATE 0.177 / 0.578 m):
below 0.9 the score measures pose error, not the grids or this scoring. Rigidly aligned to
the truth instead of scored in ``map`` (seed 3: 0.949 against 0.891, the map 0.13 m off its
anchor) shows how much of it is the drift away from the anchor.

Complexity: ``O(truth cells + map cells)`` per call (two distance transforms, vectorized
look-ups).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from gcs.mapping.rasterization import OCCUPIED, UNKNOWN, OccupancyMap
from protocol.se2 import compose, inverse

__all__ = [
    "OccupancyScores",
    "cell_centres",
    "explored_frac",
    "lookup",
    "map_in_world",
    "occupancy_scores",
    "surface_cells",
    "world_from_map",
]


def world_from_map(
    start_of_map_robot: NDArray[np.float64] | tuple[float, float, float],
    map_from_odom: NDArray[np.float64] | tuple[float, float, float] = (0.0, 0.0, 0.0),
) -> NDArray[np.float64]:
    """``world_from_map`` (x, y, yaw) of a GCS whose ``map`` is ``map_from_odom`` of the robot
    that started at ``start_of_map_robot`` (``world_from_base`` at time 0 = ``world_from_odom``)."""
    return compose(np.asarray(start_of_map_robot, float), inverse(np.asarray(map_from_odom, float)))


def cell_centres(mask: NDArray[np.bool_], resolution_m: float) -> NDArray[np.float64]:
    """``(N, 2)`` world ``(x, y)`` of the centres of the ``True`` cells of a truth raster."""
    rows, cols = np.nonzero(mask)
    return np.stack([(cols + 0.5) * resolution_m, (rows + 0.5) * resolution_m], axis=1)


def _to_frame(
    a_from_b: NDArray[np.float64], points_in_b: NDArray[np.float64]
) -> NDArray[np.float64]:
    c, s = np.cos(a_from_b[2]), np.sin(a_from_b[2])
    x, y = points_in_b[:, 0], points_in_b[:, 1]
    return np.stack([a_from_b[0] + c * x - s * y, a_from_b[1] + s * x + c * y], axis=1)


def lookup(
    grid: NDArray[Any],
    origin_m: tuple[float, float],
    resolution_m: float,
    points_m: NDArray[np.float64],
    *,
    outside: int | float | bool,
) -> NDArray[Any]:
    """Values of ``grid`` (cell ``(row, col)`` covers ``origin + (col, row) * res``) at
    ``points_m`` ``(N, 2)`` in the grid's frame; ``outside`` where a point is off the grid."""
    out = np.full(len(points_m), outside, dtype=grid.dtype)
    if grid.size == 0 or len(points_m) == 0:
        return out
    col = np.floor((points_m[:, 0] - origin_m[0]) / resolution_m).astype(np.int64)
    row = np.floor((points_m[:, 1] - origin_m[1]) / resolution_m).astype(np.int64)
    ok = (row >= 0) & (row < grid.shape[0]) & (col >= 0) & (col < grid.shape[1])
    out[ok] = grid[row[ok], col[ok]]
    return out


def explored_frac(
    occupancy: OccupancyMap, reachable_in_map: NDArray[np.float64]
) -> tuple[float, int]:
    """``(fraction, known count)`` of the reachable truth cells, given by their centres in
    ``map`` (``(N, 2)``, see :func:`cell_centres` and ``world_from_map``), that the map knows."""
    if len(reachable_in_map) == 0:
        return float("nan"), 0
    v = lookup(
        occupancy.values, occupancy.origin_in_map, occupancy.resolution_m, reachable_in_map,
        outside=UNKNOWN,
    )  # fmt: skip
    known = int(np.count_nonzero(v != UNKNOWN))
    return known / len(reachable_in_map), known


def surface_cells(occupied: NDArray[np.bool_]) -> NDArray[np.bool_]:
    """Occupied cells with a free 4-neighbour (what a range sensor can see)."""
    occ = occupied.astype(bool)
    free_nb = np.zeros_like(occ)
    free_nb[1:, :] |= ~occ[:-1, :]
    free_nb[:-1, :] |= ~occ[1:, :]
    free_nb[:, 1:] |= ~occ[:, :-1]
    free_nb[:, :-1] |= ~occ[:, 1:]
    return occ & free_nb


def _distance_to(mask: NDArray[np.bool_], resolution_m: float) -> NDArray[np.float32]:
    """Distance (m) from every cell to the nearest ``True`` cell (inf if there is none)."""
    if not mask.any():
        return np.full(mask.shape, np.inf, dtype=np.float32)
    src = np.where(mask, 0, 255).astype(np.uint8)
    return cv2.distanceTransform(src, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * np.float32(resolution_m)


@dataclass(frozen=True)
class OccupancyScores:
    """Counts behind the scores; ``precision``, ``recall`` and ``f1`` are NaN without data."""

    map_occupied: int
    map_occupied_true: int
    truth_surface_observed: int
    truth_surface_recalled: int

    @property
    def precision(self) -> float:
        return self.map_occupied_true / self.map_occupied if self.map_occupied else float("nan")

    @property
    def recall(self) -> float:
        n = self.truth_surface_observed
        return self.truth_surface_recalled / n if n else float("nan")

    @property
    def f1(self) -> float:
        p, r = self.precision, self.recall
        if not (p + r > 0):
            return float("nan") if np.isnan(p + r) else 0.0
        return 2.0 * p * r / (p + r)


def occupancy_scores(
    occupancy: OccupancyMap,
    truth_occupied: NDArray[np.bool_],
    truth_resolution_m: float,
    world_from_map_pose: NDArray[np.float64],
    *,
    tolerance_m: float = 0.2,
) -> OccupancyScores:
    """Occupied cells of the map against the truth's vertical structures (module docstring)."""
    res = occupancy.resolution_m
    values = occupancy.values
    occ_map = values == OCCUPIED
    # precision: occupied map cells, by their centres, near a truth structure
    rows, cols = np.nonzero(occ_map)
    centres_map = np.stack(
        [
            occupancy.origin_in_map[0] + (cols + 0.5) * res,
            occupancy.origin_in_map[1] + (rows + 0.5) * res,
        ],
        axis=1,
    ).astype(np.float64)
    centres_world = _to_frame(np.asarray(world_from_map_pose, float), centres_map)
    # half a cell of either raster: a cell centre is up to that far from the structure it shows
    slack = tolerance_m + 0.5 * max(res, truth_resolution_m)
    # a margin of empty cells around the truth raster: a structure on its edge (a perimeter
    # fence) seen a little outside it is scored by its distance, not as off the grid
    pad = int(math.ceil(slack / truth_resolution_m)) + 1
    truth_dist = _distance_to(np.pad(truth_occupied.astype(bool), pad), truth_resolution_m)
    edge = -pad * truth_resolution_m
    d = lookup(truth_dist, (edge, edge), truth_resolution_m, centres_world, outside=np.inf)
    true_pos = int(np.count_nonzero(d <= slack))
    # recall: truth surface cells where the map observed something nearby
    surface = cell_centres(surface_cells(truth_occupied), truth_resolution_m)
    surface_map = _to_frame(inverse(np.asarray(world_from_map_pose, float)), surface)
    known = values != UNKNOWN
    d_known = lookup(
        _distance_to(known, res), occupancy.origin_in_map, res, surface_map, outside=np.inf
    )
    d_occ = lookup(
        _distance_to(occ_map, res), occupancy.origin_in_map, res, surface_map, outside=np.inf
    )
    observed = d_known <= slack
    recalled = observed & (d_occ <= slack)
    return OccupancyScores(
        map_occupied=len(rows),
        map_occupied_true=true_pos,
        truth_surface_observed=int(np.count_nonzero(observed)),
        truth_surface_recalled=int(np.count_nonzero(recalled)),
    )


def map_in_world(
    occupancy: OccupancyMap,
    world_from_map_pose: NDArray[np.float64],
    shape: tuple[int, int],
    resolution_m: float,
) -> NDArray[np.int8]:
    """The map resampled onto the truth raster's lattice (``shape`` cells of ``resolution_m``
    from the world origin): each truth cell takes the map value at its centre (for plots and
    side-by-side comparison)."""
    rows, cols = np.indices(shape)
    centres = np.stack(
        [(cols.ravel() + 0.5) * resolution_m, (rows.ravel() + 0.5) * resolution_m], axis=1
    )
    in_map = _to_frame(inverse(np.asarray(world_from_map_pose, float)), centres)
    v = lookup(
        occupancy.values.astype(np.int8), occupancy.origin_in_map, occupancy.resolution_m, in_map,
        outside=UNKNOWN,
    )  # fmt: skip
    return v.reshape(shape).astype(np.int8)
