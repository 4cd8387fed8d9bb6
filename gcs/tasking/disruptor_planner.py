"""Disruptor task allocation (paper 5.1.2).

"The disruptor planner fulfills two planning goals: 1) immediately tasking an available
disruptor robot to the neutralization region of each newly found static OOI and 2) positioning
idle disruptor robots evenly throughout the environment to minimize response time ... Unlike
sensor robots, disruptor robots *only* travel on the 'highway'."

* :func:`neutralization_nodes`: highway waypoints from which the OOI can be lasered: farther
  than its trigger radius plus a margin (from it and from every other live static OOI), within
  ``laser_range_m``, with line of sight over the planning grid.
  An occupied blob wholly within ``ooi_blob_m`` of the OOI is the OOI itself
  (:func:`without_own_blob`): it does not hide the OOI.
* :func:`failed_view_mask`: waypoints on a side of the OOI where a disruptor already failed to
  laser it for want of line of sight (near the pose it failed from, or within
  ``failed_view_deg`` of its bearing). :func:`dispatch_disruptor` takes them only when no
  other pose as near (within ``preferred_range_m``, or not) is reachable.
* :func:`dispatch_disruptor`: the free disruptor with the shortest highway route to any such
  waypoint (one within ``preferred_range_m`` of the OOI when the highway reaches one), and
  the route (highway waypoints only, never the grid: a shorter path through unexplored
  ground is not allowed).
* :func:`spread_positions`: ``k`` highway waypoints minimising the mean highway distance from
  the explored highway to the nearest of them (k-medoids, Lloyd iterations on graph distances,
  seeded by farthest-point k-centre). On a straight road two disruptors settle at 1/4 and 3/4.
* ``approval``: the rules want an operator's approval before a neutralization; ``auto``
  approves at once (an unattended run; the allocator counts each approval), ``operator`` waits
  for one.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Literal

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import ndimage

from gcs.mapping.rasterization import FREE, OCCUPIED
from gcs.tasking.planning_grid import PlanningGrid, line_of_sight, simplify_path
from gcs.tasking.trajectory_graph import TrajectoryGraph

__all__ = [
    "DisruptorConfig",
    "Dispatch",
    "dispatch_disruptor",
    "failed_view_mask",
    "neutralization_nodes",
    "spread_positions",
    "without_own_blob",
]


class DisruptorConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Metres, seconds. ``hold_s``: the laser hold the rules require (15 s)."""

    trigger_radius_m: float = 2.5
    standoff_margin_m: float = 1.0
    laser_range_m: float = 10.0
    hold_s: float = 15.0
    approval: Literal["auto", "operator"] = "auto"
    spread_iterations: int = 12
    spread_candidates: int = 24
    spread_tolerance_m: float = 3.0
    spread_period_s: float = 20.0
    path_tolerance_m: float = 0.3
    # line of sight is checked up to this far short of the OOI: the OOI (0.25 m in radius) is
    # an obstacle in the GCS's map itself, and the robot's own check stops 0.5 m short too
    # (robot/node.py). With 0 m, small world seed 0 (sharper map, 2026-11-25): the sighting
    # of one OOI lay on occupied cells from 50 s to the end, 0 waypoints saw it and no
    # disruptor was ever sent (0.5 m: 11 waypoints). With 1 m, seed 7 sent the disruptor to
    # poses 8.8-9.8 m off grazing a wall whose laser the rules did not count
    los_clear_m: float = 0.5
    # ... and an occupied blob of the planning grid (8-connected) lying wholly within
    # ooi_blob_m of the sighting is the OOI itself (a free-standing 0.25 m cylinder, under a
    # sighting up to ~0.5 m off its centre, inflated by the 0.3 m coarse cells): it does not
    # hide the OOI however far it reaches towards the viewer; a blob reaching farther (a wall
    # beside the OOI) still blocks beyond los_clear_m. 0: off. Small world seed 0 at 8183549,
    # 59.7 s: the OOI's blob began 0.52 m short of the sighting on the side of the road
    # 6.2 m off, so the only pose left was one 9.7 m off by 58 m of highway, from which the
    # disruptor's perception never found the OOI (failed at 159 s, retried at 219 s, not
    # neutralized by 300 s); with 1 m the road 6.2 m off is taken. Quick mission at 8183549
    # + this, seeds 0/7/3/11 (load 8-16): static OOIs neutralized 1/1/1/1 (0.5/1/1/1),
    # seed 0's second at 82 s (5 m of highway), seed 3's first at the first try (before:
    # failed, "no OOI of its own", retried); explored 0.961/0.917/0.929/0.889 (median 0.923
    # against 0.920), ATE 0.293/0.188/0.106/0.122 (median 0.155 against 0.144 m), F1
    # 0.666/0.568/0.914/0.905 (median 0.786 against 0.906: seed 0's robot 2 took 0.6 m of
    # map error at 122 s on a path that diverged at 95 s; seeds 7 and 11 bit-identical),
    # false closures 0/0/1/0, 0 lost
    ooi_blob_m: float = 1.0
    # a pose this near the OOI is taken when the highway reaches one, over a farther one
    # nearer the disruptor: from ~10 m the disruptor's own perception may not find the OOI
    # (the laser aims only at its own detection) and a laser aimed from there misses a 0.25 m
    # OOI at 1.4 deg of heading error. Small world seed 0: a pose 9.7 m off, laser never on
    # target in 40 s; the next one, 5.3 m off, neutralized it (seed 7: 8.8-9.8 m, none)
    preferred_range_m: float = 6.0
    # idle disruptors wait on highway waypoints at least this far from obstacles: the
    # highway's centre is where everyone drives, and a disruptor waiting in a passage blocks
    # it (small world seed 0: a sensor robot jammed 'deadlock' beside the spread disruptor
    # from 100 s to 240 s); none so clear: any waypoint
    park_clearance_m: float = 2.0
    # a disruptor that failed to laser an OOI from a pose (its own map saw no line of sight,
    # or no OOI from there) is next sent to another side: not within failed_view_m of that
    # pose nor within failed_view_deg of its bearing from the OOI, for OOIs (sightings of the
    # same object placed apart by the map) within failed_view_ooi_m of the failed one. Small
    # world seed 0: an OOI beside a 10 cm curb; the disruptor, on the far side of the curb,
    # saw the curb's edge as an obstacle across the beam and failed five times in a row from
    # the same two poses (140 s); the grid here cannot tell, a curb is no wall in its map
    failed_view_m: float = 2.0
    failed_view_deg: float = 35.0
    failed_view_ooi_m: float = 6.0

    def __post_init__(self) -> None:
        for name in ("trigger_radius_m", "laser_range_m", "hold_s", "path_tolerance_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"disruptor {name} must be finite and > 0, got {v}")
        if not self.laser_range_m > self.trigger_radius_m + self.standoff_margin_m:
            raise ValueError(
                f"disruptor laser_range_m {self.laser_range_m} must exceed trigger_radius_m + "
                f"standoff_margin_m ({self.trigger_radius_m + self.standoff_margin_m})"
            )
        if not (
            self.trigger_radius_m + self.standoff_margin_m
            < self.preferred_range_m
            <= self.laser_range_m
        ):
            raise ValueError(
                f"disruptor preferred_range_m {self.preferred_range_m} must exceed "
                f"trigger_radius_m + standoff_margin_m "
                f"({self.trigger_radius_m + self.standoff_margin_m}) and be <= laser_range_m "
                f"({self.laser_range_m})"
            )
        if not (math.isfinite(self.park_clearance_m) and self.park_clearance_m >= 0):
            raise ValueError(
                f"disruptor park_clearance_m must be finite and >= 0, got {self.park_clearance_m}"
            )
        for name in ("failed_view_m", "failed_view_deg", "failed_view_ooi_m", "ooi_blob_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"disruptor {name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.los_clear_m) and self.los_clear_m >= 0):
            raise ValueError(
                f"disruptor los_clear_m must be finite and >= 0, got {self.los_clear_m}"
            )
        if self.spread_iterations < 1 or self.spread_candidates < 1:
            raise ValueError("disruptor spread_iterations and spread_candidates must be >= 1")


@dataclass(frozen=True)
class Dispatch:
    """Send ``robot_id`` along ``waypoints_in_map`` (highway waypoints, ending at the
    neutralization pose ``pose_in_map``) for hazard ``hazard_id``."""

    robot_id: int
    hazard_id: int
    pose_in_map: tuple[float, float]
    waypoints_in_map: NDArray[np.float64]
    distance_m: float


def failed_view_mask(
    nodes_in_map: ArrayLike,
    ooi_in_map: ArrayLike,
    failed_views_in_map: ArrayLike,
    config: DisruptorConfig,
) -> NDArray[np.bool_]:
    """Which of ``nodes_in_map`` ``(N, 2)`` are on a side of the OOI at ``ooi_in_map`` a
    disruptor already failed to laser it from: ``failed_views_in_map`` ``(F, 4)`` rows
    ``(ooi_x, ooi_y, pose_x, pose_y)``; a row counts when its OOI lies within
    ``failed_view_ooi_m``, and marks nodes within ``failed_view_m`` of its pose or within
    ``failed_view_deg`` of its pose's bearing from this OOI."""
    nodes = np.asarray(nodes_in_map, dtype=np.float64).reshape(-1, 2)
    ooi = np.asarray(ooi_in_map, dtype=np.float64).reshape(2)
    views = np.asarray(failed_views_in_map, dtype=np.float64).reshape(-1, 4)
    out = np.zeros(len(nodes), dtype=bool)
    views = views[np.hypot(*(views[:, :2] - ooi).T) <= config.failed_view_ooi_m]
    if len(views) == 0 or len(nodes) == 0:
        return out
    bearing = np.arctan2(nodes[:, 1] - ooi[1], nodes[:, 0] - ooi[0])
    half = math.radians(config.failed_view_deg)
    for _, _, px, py in views:
        out |= np.hypot(nodes[:, 0] - px, nodes[:, 1] - py) <= config.failed_view_m
        if half > 0 and math.hypot(px - ooi[0], py - ooi[1]) > 1e-6:
            b = math.atan2(py - ooi[1], px - ooi[0])
            diff = np.abs(np.angle(np.exp(1j * (bearing - b))))
            out |= diff <= half
    return out


def without_own_blob(grid: PlanningGrid, ooi_in_map: ArrayLike, radius_m: float) -> PlanningGrid:
    """``grid`` with the occupied blobs (8-connected) lying wholly within ``radius_m`` of
    ``ooi_in_map`` marked free (the OOI's own cells, see ``DisruptorConfig.ooi_blob_m``); a
    blob reaching farther (a wall) stays. ``grid`` itself when there is none (never
    modified)."""
    if radius_m <= 0:
        return grid
    ooi = np.asarray(ooi_in_map, dtype=np.float64).reshape(2)
    res = grid.resolution_m
    r, c = (int(v) for v in grid.cells_of(ooi)[0])
    k = int(math.ceil(radius_m / res)) + 2  # a blob within radius_m never reaches the edge
    rows, cols = grid.shape
    r0, r1 = max(0, r - k), min(rows, r + k + 1)
    c0, c1 = max(0, c - k), min(cols, c + k + 1)
    if r0 >= r1 or c0 >= c1:
        return grid
    occ = grid.values[r0:r1, c0:c1] == OCCUPIED
    if not occ.any():
        return grid
    labels, n = ndimage.label(occ, structure=np.ones((3, 3), dtype=bool))
    rr, cc = np.nonzero(labels)
    centres = grid.centers_of(np.stack([rr + r0, cc + c0], axis=1))
    dist = np.hypot(centres[:, 0] - ooi[0], centres[:, 1] - ooi[1])
    far = np.zeros(n + 1, dtype=bool)
    np.logical_or.at(far, labels[rr, cc], dist > radius_m)
    own = ~far[labels[rr, cc]]
    # a blob touching the grid's edge may go on beyond it: not known to be the OOI's
    edge = np.zeros(n + 1, dtype=bool)
    edge[labels[rr, cc][(rr + r0 == 0) | (rr + r0 == rows - 1)]] = True
    edge[labels[rr, cc][(cc + c0 == 0) | (cc + c0 == cols - 1)]] = True
    own &= ~edge[labels[rr, cc]]
    if not own.any():
        return grid
    values = grid.values.copy()
    values[rr[own] + r0, cc[own] + c0] = FREE
    return dataclasses.replace(grid, values=values)


def neutralization_nodes(
    grid: PlanningGrid,
    highway: TrajectoryGraph,
    ooi_in_map: ArrayLike,
    static_oois_in_map: ArrayLike,
    config: DisruptorConfig,
) -> NDArray[np.int64]:
    """Highway waypoints to laser the OOI at ``ooi_in_map`` from (see the module docstring);
    ``static_oois_in_map`` ``(K, 2)`` are every live static OOI (including this one)."""
    if highway.size == 0:
        return np.zeros(0, dtype=np.int64)
    ooi = np.asarray(ooi_in_map, dtype=np.float64).reshape(2)
    nodes = highway.nodes_in_map
    d = np.hypot(*(nodes - ooi).T)
    safe = config.trigger_radius_m + config.standoff_margin_m
    ok = (d >= safe) & (d <= config.laser_range_m)
    others = np.asarray(static_oois_in_map, dtype=np.float64).reshape(-1, 2)
    for o in others:
        ok &= np.hypot(*(nodes - o).T) >= safe
    cand = np.flatnonzero(ok)
    if cand.size:
        grid = without_own_blob(grid, ooi, config.ooi_blob_m)
    vis = []
    for i in cand:
        away = nodes[i] - ooi
        short_of = ooi + away * (min(config.los_clear_m, float(d[i])) / max(float(d[i]), 1e-9))
        if line_of_sight(grid, nodes[i], short_of):
            vis.append(i)
    return np.asarray(vis, dtype=np.int64)


def dispatch_disruptor(
    grid: PlanningGrid,
    highway: TrajectoryGraph,
    hazard_id: int,
    ooi_in_map: ArrayLike,
    static_oois_in_map: ArrayLike,
    free_disruptors: dict[int, tuple[float, float]],
    blocked: NDArray[np.bool_] | None,
    config: DisruptorConfig,
    failed_views_in_map: ArrayLike | None = None,
) -> Dispatch | None:
    """The nearest (by highway) free disruptor and its route to a neutralization pose of the
    OOI, or None (no disruptor on the highway, no pose with line of sight yet); poses on a
    side already tried (``failed_views_in_map``, :func:`failed_view_mask`) only when no
    other is reachable."""
    if not free_disruptors or highway.size == 0:
        return None
    ooi_xy = np.asarray(ooi_in_map, dtype=np.float64).reshape(2)
    cand = neutralization_nodes(grid, highway, ooi_in_map, static_oois_in_map, config)
    if blocked is not None:
        cand = cand[~blocked[cand]]
    if failed_views_in_map is not None and cand.size:
        tried = failed_view_mask(highway.nodes_in_map[cand], ooi_xy, failed_views_in_map, config)
        cand = np.concatenate([cand[~tried], cand[tried]])
        n_fresh = int((~tried).sum())
    else:
        n_fresh = int(cand.size)
    if cand.size == 0:
        return None
    ids = sorted(free_disruptors)
    pos = np.asarray([free_disruptors[r] for r in ids], dtype=np.float64).reshape(-1, 2)
    access = highway.nearest(pos, blocked)
    have = access >= 0
    if not have.any():
        return None
    d, pred = highway.distances(access[have], blocked)
    entry = np.hypot(*(highway.nodes_in_map[access[have]] - pos[have]).T)
    cost = entry[:, None] + d[:, cand]
    if not np.isfinite(cost).any():
        return None
    # a reachable pose within preferred_range_m wins over a farther one (see DisruptorConfig),
    # then one on a side not yet tried (DisruptorConfig.failed_view_m): a far pose on a fresh
    # side is no better than a near one tried (small world seed 11: sent 65 m round to a pose
    # 9.5 m off, from which it did not see the OOI, where the near side had worked on retry)
    far = np.hypot(*(highway.nodes_in_map[cand] - ooi_xy).T) > config.preferred_range_m
    if np.isfinite(cost[:, ~far]).any():
        cost[:, far] = np.inf
    fresh = np.arange(cand.size) < n_fresh
    if np.isfinite(cost[:, fresh]).any():
        cost[:, ~fresh] = np.inf
    i, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
    robot = [r for r, h in zip(ids, have, strict=True) if h][i]
    target = int(cand[j])
    path = highway.path(pred[i], target)
    wps = simplify_path(highway.nodes_in_map[path], config.path_tolerance_m)
    p = highway.nodes_in_map[target]
    return Dispatch(robot, hazard_id, (float(p[0]), float(p[1])), wps, float(cost[i, j]))


def spread_positions(
    highway: TrajectoryGraph,
    k: int,
    *,
    region: NDArray[np.bool_] | None = None,
    blocked: NDArray[np.bool_] | None = None,
    config: DisruptorConfig | None = None,
) -> NDArray[np.int64]:
    """``k`` highway waypoints spread over ``region`` (default: all waypoints not
    ``blocked``) to minimise the mean highway distance to the nearest (k-medoids)."""
    cfg = config or DisruptorConfig()
    if k <= 0 or highway.size == 0:
        return np.zeros(0, dtype=np.int64)
    mask = np.ones(highway.size, dtype=bool) if region is None else region.copy()
    if blocked is not None:
        mask &= ~blocked
    members = np.flatnonzero(mask)
    if members.size == 0:
        return np.zeros(0, dtype=np.int64)
    k = min(k, int(members.size))
    nodes = highway.nodes_in_map
    # farthest-point seeding, from the member nearest the members' centroid
    first = members[int(np.argmin(np.hypot(*(nodes[members] - nodes[members].mean(0)).T)))]
    centres = [int(first)]
    d, _ = highway.distances([first], blocked)
    nearest = d[0, members]
    for _ in range(1, k):
        finite = np.where(np.isfinite(nearest), nearest, -1.0)
        nxt = int(members[int(np.argmax(finite))])
        if nxt in centres:
            break
        centres.append(nxt)
        dn, _ = highway.distances([nxt], blocked)
        nearest = np.minimum(nearest, dn[0, members])
    for _ in range(cfg.spread_iterations):
        dc, _ = highway.distances(centres, blocked)
        owner = np.argmin(dc[:, members], axis=0)
        new = []
        for c in range(len(centres)):
            mine = members[owner == c]
            if mine.size == 0:
                new.append(centres[c])
                continue
            step = max(1, int(math.ceil(mine.size / cfg.spread_candidates)))
            # candidates: every step-th member in order of distance from the current centre
            by_d = mine[np.argsort(dc[c, mine], kind="stable")]
            cands = np.unique(np.r_[by_d[::step], centres[c]])
            dd, _ = highway.distances(cands, blocked)
            sub = dd[:, mine]
            total = np.where(np.isfinite(sub), sub, 1e9).sum(axis=1)
            new.append(int(cands[int(np.argmin(total))]))
        if new == centres:
            break
        centres = new
    return np.asarray(centres, dtype=np.int64)
