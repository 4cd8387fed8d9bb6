"""Reachable frontier of the global map (paper 5.1.1, after Yamauchi 1998).

"The *frontier* consists of the reachable regions of the environment on the boundary between
the known and unknown regions of the world." A frontier cell is a traversable cell of the
planning grid (known free, ``robot_radius_m`` clear of obstacles, outside every keep-out disc)
with an unknown 4-neighbour. It is *reachable* when its 8-connected traversable component holds
a robot: robots reach it through known-free space. Frontier cells are grouped into 8-connected
clusters; clusters smaller than ``min_cluster_cells`` are noise (a speckle of unknown inside
seen ground) and dropped. Each cluster offers candidate goals, one per ``goal_spacing_m``
square it touches, so a long frontier gives several robots somewhere to go.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from gcs.mapping.rasterization import UNKNOWN
from gcs.tasking.planning_grid import PlanningGrid

__all__ = ["Frontiers", "find_frontiers"]

_EIGHT = np.ones((3, 3), dtype=bool)


@dataclass(frozen=True)
class Frontiers:
    """``mask`` ``(rows, cols)``: reachable frontier cells; ``goal_cells`` ``(K, 2)`` and
    ``goals_in_map`` ``(K, 2)``: candidate goals; ``goal_cluster`` ``(K,)``: their cluster id;
    ``clusters``: number of clusters kept."""

    mask: NDArray[np.bool_]
    goal_cells: NDArray[np.int64]
    goals_in_map: NDArray[np.float64]
    goal_cluster: NDArray[np.int64]
    clusters: int

    @property
    def empty(self) -> bool:
        return len(self.goal_cells) == 0

    def near(self, point_in_map: ArrayLike, grid: PlanningGrid, radius_m: float) -> bool:
        """True if a frontier cell lies within ``radius_m`` of ``point_in_map`` (is a goal's
        frontier still there?)."""
        (r, c) = grid.cells_of(point_in_map)[0]
        k = int(math.ceil(radius_m / grid.resolution_m))
        rows, cols = self.mask.shape
        r0, r1 = max(0, r - k), min(rows, r + k + 1)
        c0, c1 = max(0, c - k), min(cols, c + k + 1)
        if r0 >= r1 or c0 >= c1:
            return False
        rr, cc = np.nonzero(self.mask[r0:r1, c0:c1])
        if rr.size == 0:
            return False
        d2 = (rr + r0 - r) ** 2 + (cc + c0 - c) ** 2
        return bool(d2.min() * grid.resolution_m**2 <= radius_m**2)


def find_frontiers(
    grid: PlanningGrid,
    robot_cells: ArrayLike,
    *,
    min_cluster_cells: int = 3,
    goal_spacing_m: float = 2.0,
) -> Frontiers:
    """Reachable frontier of ``grid`` from the robots at ``robot_cells`` ``(R, 2)`` (cells on
    the traversable grid, e.g. from :meth:`PlanningGrid.snap`)."""
    trav = grid.traversable
    rows, cols = trav.shape
    empty = Frontiers(
        np.zeros((rows, cols), dtype=bool),
        np.zeros((0, 2), dtype=np.int64),
        np.zeros((0, 2)),
        np.zeros(0, dtype=np.int64),
        0,
    )
    cells = np.asarray(robot_cells, dtype=np.int64).reshape(-1, 2)
    if rows == 0 or cols == 0 or len(cells) == 0:
        return empty
    unknown = grid.values == UNKNOWN
    touches = np.zeros_like(unknown)
    touches[1:, :] |= unknown[:-1, :]
    touches[:-1, :] |= unknown[1:, :]
    touches[:, 1:] |= unknown[:, :-1]
    touches[:, :-1] |= unknown[:, 1:]
    # the grid's border touches the unknown beyond the map
    touches[0, :] = touches[-1, :] = True
    touches[:, 0] = touches[:, -1] = True
    frontier = trav & touches
    if not frontier.any():
        return empty
    components, _ = ndimage.label(trav, structure=_EIGHT)
    ok = grid.inside(cells)
    seeds = components[cells[ok, 0], cells[ok, 1]]
    seeds = np.unique(seeds[seeds > 0])
    if seeds.size == 0:
        return empty
    frontier &= np.isin(components, seeds)
    labels, n = ndimage.label(frontier, structure=_EIGHT)
    if n == 0:
        return empty
    sizes = np.bincount(labels.ravel(), minlength=n + 1)
    keep = sizes >= max(1, min_cluster_cells)
    keep[0] = False
    frontier = keep[labels]
    rr, cc = np.nonzero(frontier)
    lab = labels[rr, cc].astype(np.int64)
    if rr.size == 0:
        return Frontiers(frontier, empty.goal_cells, empty.goals_in_map, empty.goal_cluster, 0)
    block = max(1, int(round(goal_spacing_m / grid.resolution_m)))
    br, bc = rr // block, cc // block
    key = (lab * ((rows // block) + 1) + br) * ((cols // block) + 1) + bc
    # one goal per (cluster, square): the member cell nearest the members' mean
    order = np.argsort(key, kind="stable")
    key_s = key[order]
    starts = np.flatnonzero(np.r_[True, key_s[1:] != key_s[:-1]])
    counts = np.diff(np.r_[starts, len(key_s)])
    mean_r = np.add.reduceat(rr[order].astype(float), starts) / counts
    mean_c = np.add.reduceat(cc[order].astype(float), starts) / counts
    group = np.repeat(np.arange(len(starts)), counts)
    d2 = (rr[order] - mean_r[group]) ** 2 + (cc[order] - mean_c[group]) ** 2
    # argmin per group: sort by (group, d2) and take each group's first
    pick = np.lexsort((d2, group))
    first = pick[np.r_[True, group[pick][1:] != group[pick][:-1]]]
    sel = order[first]
    goal_cells = np.stack([rr[sel], cc[sel]], axis=1).astype(np.int64)
    return Frontiers(
        frontier,
        goal_cells,
        grid.centers_of(goal_cells),
        lab[sel],
        int(keep.sum()),
    )
