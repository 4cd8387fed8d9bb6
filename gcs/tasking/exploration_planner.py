"""Exploration task allocation: greedy frontier goals for the sensor robots (paper 5.1.1).

"The planner greedily assigns each robot a goal on the frontier based on both the expected
amount of information to be gained by traveling to a location and the cost to acquire that
information ... at first we only search up to a set distance away, e.g. 20 m, for potential
goals ... when a robot explores all the frontier in its vicinity it must search further",
through the trajectory graph.

The utility of goal ``g`` for robot ``r`` is ``gain_m2(g) - distance_weight_m2_per_m *
distance_m(r, g)``; goals with less than ``min_gain_m2`` to see are not worth a trip. Greedy
assignment: the best (robot, goal) pair over every robot still waiting is taken first, then
goals within ``goal_separation_m`` of it are withdrawn (two robots would see the same ground),
and so on; then two robots swap goals while that shortens their travel (routes that cross
jam where robots stand close, at the start). Phase 1 uses grid travel distances bounded by
``near_radius_m``; robots left without a goal then search the whole map through the highway:
enter it at the waypoint nearest the robot, leave at the one nearest the goal
(:class:`~gcs.tasking.trajectory_graph.TrajectoryGraph`), or, if the highway does not reach, by
an unbounded grid search (``far_grid_fallback``).

Radio shadows: :func:`return_leg` gives each goal the way back to where the GCS heard robots.
Tours: each goal assigned goes on through up to ``tour_goals`` further frontier goals (each the
best by the same utility from the last, within ``tour_leg_m`` of travel, ``goal_separation_m``
from every goal taken; the robots take one stop each a round, the best first). A robot the GCS
hears is re-planned at its first goal; one out of contact drives the tour, sweeping the
frontier, and then :func:`shortcut` home to contact. Without tours a robot in a shadow drove
out to one goal ~10 m off and back to contact, again and again (full mission, seed 0, 240-440
s: 70-80 % of the exploring robot-seconds on ground already seen, explored +0.04 per 120 s).

Failure memory: each robot carries goals it failed to reach (``blacklist_in_map``); candidates
within ``blacklist_radius_m`` of one are never offered to that robot again. It also carries
the places where its routes failed (``avoid_in_map``: discs the GCS put where the robot got
stuck on its way): that robot's searches, on the grid and on the highway, go around them (its
own cell excepted), so it is not sent again through the door or gap it could not pass to a
goal a little beside the failed one (small world seed 0: a robot deadlocked on six goals 2-5 m
apart in a row, each routed through the same doorway, 140 s). Goals claimed by
robots already under way are withdrawn like assigned ones. No reachable frontier worth a trip
at all: the plan says ``explored``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgspec
import numpy as np
from numpy.typing import NDArray

from gcs.tasking.frontiers import Frontiers
from gcs.tasking.grid_dijkstra import GridDistances, grid_distances
from gcs.tasking.planning_grid import PlanningGrid, simplify_path
from gcs.tasking.trajectory_graph import TrajectoryGraph

__all__ = [
    "ExplorationConfig",
    "ExplorationGoal",
    "ExplorationPlan",
    "Explorer",
    "failed_route_discs",
    "plan_exploration",
    "return_leg",
    "shortcut",
]


class ExplorationConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Metres, square metres; see the module docstring."""

    near_radius_m: float = 20.0
    sensor_range_m: float = 8.0
    distance_weight_m2_per_m: float = 2.0
    min_gain_m2: float = 2.0
    goal_separation_m: float = 6.0
    blacklist_radius_m: float = 2.0
    path_tolerance_m: float = 0.5
    far_grid_fallback: bool = True
    # the way back to radio contact after the goal (see return_leg): the GCS re-plans a robot
    # it hears long before it drives it; one it does not hear comes back by itself
    return_to_contact: bool = True
    contact_radius_m: float = 2.0
    # tours (see plan_exploration): after its goal a robot goes on through up to tour_goals
    # more frontier goals, each within tour_leg_m of the last and at least goal_separation_m
    # from every goal taken, while the tour adds at most tour_length_m of travel. A robot the
    # GCS hears is re-planned at its first goal anyway (the rest is never driven); one in a
    # radio shadow drives on along the frontier instead of back to contact after each goal.
    # Full mission (magic_phase, seed 0, 240-345 s): robots in shadows drove out ~10 m to a
    # goal and back to contact, star patterns, 70-80 % of exploring robot-seconds on known
    # ground (explored 0.29 at 300 s and +0.04 per 120 s). Measured at 66f8349 (load 8-10):
    # magic_phase seed 0, explored at 180 / 300 / 420 / 540 / 600 s 0.249 / 0.296 / 0.330 /
    # 0.374 / 0.393 without tours, 0.247 / 0.304 / 0.374 / 0.394 / 0.425 with them (and the
    # relay and end rules, mission_end_s 600); heard exploring robots added 1548 / 1437 m2
    # of new ground in 240-360 / 360-480 s (566 / 607 without). Quick mission seeds 0 / 7 /
    # 3 / 11: 0.962 / 0.860 / 0.960 / 0.944 (median 0.952) -> 0.954 / 0.919 / 0.928 / 0.956
    # (median 0.941); robots lost 0 / 0 / 0 / 0 -> 1 / 0 / 0 / 1 (hostile 0: seed 0 a heard
    # robot blasted as the hostile was first detected, seed 11 one silent on its tour, the
    # hostile not yet known to the GCS). OFF by default since: at dd73057 (every helper's
    # change of session 13 in; load ~4) the quick mission with tours gave explored 0.923 /
    # 0.886 / 0.878 / 0.948 (median 0.905), false closures 3 / 0 / 0 / 1, F1 median 0.815,
    # against 0.926 / 0.935 / 0.947 / 0.948 (median 0.941), 1 / 0 / 0 / 0 and 0.840 with
    # tour_goals 0 (robots lost 0 in both): in the small world most goals are in contact, and
    # a tour's claimed stops keep the others off the nearby frontier. magic_phase's gain is
    # one seed; turn them on there with --config (mission: {tasking: {exploration:
    # {tour_goals: 3}}}).
    tour_goals: int = 0
    tour_leg_m: float = 20.0
    tour_length_m: float = 45.0

    def __post_init__(self) -> None:
        if self.tour_goals < 0:
            raise ValueError(f"exploration tour_goals must be >= 0, got {self.tour_goals}")
        for name in ("near_radius_m", "sensor_range_m", "path_tolerance_m", "tour_leg_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"exploration {name} must be finite and > 0, got {v}")
        for name in (
            "contact_radius_m",
            "distance_weight_m2_per_m",
            "min_gain_m2",
            "goal_separation_m",
            "blacklist_radius_m",
            "tour_length_m",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"exploration {name} must be finite and >= 0, got {v}")


@dataclass(frozen=True)
class Explorer:
    """A sensor robot waiting for a goal: its start ``cell`` on the traversable grid, its
    position, and the goals it failed to reach (``(K, 2)`` in map)."""

    robot_id: int
    cell: tuple[int, int]
    position_in_map: tuple[float, float]
    blacklist_in_map: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    # ``(K, 3)`` discs ``(x_m, y_m, radius_m)`` in map its routes must not enter
    avoid_in_map: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    # ``(K, 3)`` discs in map where it gets no goal (its routes may cross them): the radio
    # shadow it fell silent in, for a while (allocator ``shadow_goal_radius_m``)
    goals_off_in_map: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))


def _avoid(e: Explorer) -> NDArray[np.float64]:
    return np.asarray(e.avoid_in_map, dtype=np.float64).reshape(-1, 3)


def _traversable_for(grid: PlanningGrid, e: Explorer) -> NDArray[np.bool_]:
    """The grid's traversable cells less ``e``'s avoid discs (its own cell kept: it plans
    from there)."""
    discs = _avoid(e)
    if len(discs) == 0:
        return grid.traversable
    rows, cols = grid.shape
    res, (ox, oy) = grid.resolution_m, grid.origin_in_map
    out: NDArray[np.bool_] = grid.traversable.copy()
    for cx, cy, r in discs:  # each disc over its bounding window only
        c0, c1 = max(0, int((cx - r - ox) / res)), min(cols, int((cx + r - ox) / res) + 2)
        r0, r1 = max(0, int((cy - r - oy) / res)), min(rows, int((cy + r - oy) / res) + 2)
        if r0 >= r1 or c0 >= c1:
            continue
        rr, cc = np.mgrid[r0:r1, c0:c1]
        inside = np.hypot(ox + (cc + 0.5) * res - cx, oy + (rr + 0.5) * res - cy) <= r
        out[r0:r1, c0:c1] &= ~inside
    out[e.cell] = grid.traversable[e.cell]
    return out


def _highway_blocked_for(
    highway: TrajectoryGraph, blocked: NDArray[np.bool_] | None, e: Explorer
) -> NDArray[np.bool_] | None:
    """``blocked`` waypoints plus those in ``e``'s avoid discs."""
    discs = _avoid(e)
    if len(discs) == 0 or highway.size == 0:
        return blocked
    out = np.zeros(highway.size, dtype=bool) if blocked is None else blocked.copy()
    xy = highway.nodes_in_map
    for x, y, r in discs:
        out |= np.hypot(xy[:, 0] - x, xy[:, 1] - y) <= r
    return out


@dataclass(frozen=True)
class ExplorationGoal:
    """``waypoints_in_map`` ``(K, 2)`` go to ``goal_in_map`` and end there, or, on a tour,
    at the last of ``tour_in_map`` ``(T, 2)`` (the further goals, in order); ``via_highway``:
    a far goal."""

    robot_id: int
    goal_in_map: tuple[float, float]
    waypoints_in_map: NDArray[np.float64]
    distance_m: float
    gain_m2: float
    via_highway: bool
    tour_in_map: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True)
class ExplorationPlan:
    goals: dict[int, ExplorationGoal]
    explored: bool
    unassigned: list[int]


def _suppress(
    util: NDArray[np.float64], goals: NDArray[np.float64], at: NDArray[np.float64], r: float
) -> None:
    if r <= 0 or len(goals) == 0:
        return
    near = np.hypot(goals[:, 0] - at[0], goals[:, 1] - at[1]) < r
    util[:, near] = -np.inf


def _blacklisted(ex: Explorer, goals: NDArray[np.float64], r: float) -> NDArray[np.bool_]:
    bl = np.asarray(ex.blacklist_in_map, dtype=np.float64).reshape(-1, 2)
    if len(bl) == 0 or len(goals) == 0:
        return np.zeros(len(goals), dtype=bool)
    d = np.hypot(goals[:, None, 0] - bl[None, :, 0], goals[:, None, 1] - bl[None, :, 1])
    out: NDArray[np.bool_] = np.asarray((d <= r).any(axis=1), dtype=bool)
    return out


def _in_avoid(e: Explorer, goals: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Goals inside ``e``'s avoid discs or its goals-off discs."""
    off = np.asarray(e.goals_off_in_map, dtype=np.float64).reshape(-1, 3)
    discs = np.vstack([_avoid(e), off])
    out = np.zeros(len(goals), dtype=bool)
    for x, y, r in discs:
        out |= np.hypot(goals[:, 0] - x, goals[:, 1] - y) <= r
    return out


def _greedy(
    util: NDArray[np.float64], goals: NDArray[np.float64], sep: float
) -> list[tuple[int, int]]:
    out = []
    util = util.copy()
    while util.size and np.isfinite(util).any():
        i, j = np.unravel_index(int(np.argmax(util)), util.shape)
        if not np.isfinite(util[i, j]):
            break
        out.append((int(i), int(j)))
        util[i, :] = -np.inf
        util[:, j] = -np.inf
        _suppress(util, goals, goals[j], sep)
    return out


def _uncross(util: NDArray[np.float64], pairs: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Greedy pairs improved by swapping goals between two robots while that raises the sum
    of their utilities (the goals' gains stay, so the sum of travel falls): greedy choice
    can hand two robots side by side each other's side, and their routes cross (at the
    start, where robots stand close, crossing routes jam: each waits for the other)."""
    out = list(pairs)
    for _ in range(len(out) ** 2 + 1):  # each swap raises the total: this ends sooner
        best = 0.0
        swap: tuple[int, int] | None = None
        for a in range(len(out)):
            for b in range(a + 1, len(out)):
                (i, ga), (j, gb) = out[a], out[b]
                new = util[i, gb] + util[j, ga]
                if not np.isfinite(new):
                    continue
                gain = new - (util[i, ga] + util[j, gb])
                if gain > best + 1e-9:
                    best, swap = gain, (a, b)
        if swap is None:
            break
        a, b = swap
        (i, ga), (j, gb) = out[a], out[b]
        out[a], out[b] = (i, gb), (j, ga)
    return out


def _grid_waypoints(
    grid: PlanningGrid,
    dist: GridDistances,
    goal_cell: tuple[int, int],
    goal: NDArray[np.float64],
    tol: float,
) -> NDArray[np.float64]:
    cells = dist.path_cells(goal_cell)
    pts = simplify_path(grid.centers_of(cells), tol) if len(cells) else np.zeros((0, 2))
    pts = pts[1:] if len(pts) > 1 else pts[:0]  # the robot is at the first
    if len(pts):
        pts[-1] = goal
        return pts
    return goal.reshape(1, 2).copy()


def plan_exploration(
    grid: PlanningGrid,
    frontiers: Frontiers,
    gains_m2: NDArray[np.float64],
    explorers: list[Explorer],
    *,
    claimed_in_map: NDArray[np.float64] | None = None,
    highway: TrajectoryGraph | None = None,
    highway_blocked: NDArray[np.bool_] | None = None,
    config: ExplorationConfig | None = None,
) -> ExplorationPlan:
    """Goals for ``explorers`` over the candidate goals of ``frontiers`` (with ``gains_m2``
    ``(K,)`` from :func:`~gcs.tasking.information_gain.information_gain`); far routes avoid
    ``highway_blocked`` waypoints (inside keep-out discs)."""
    cfg = config or ExplorationConfig()
    goals = frontiers.goals_in_map
    gains = np.asarray(gains_m2, dtype=np.float64).reshape(-1)
    if len(gains) != len(goals):
        raise ValueError(f"gains_m2 has {len(gains)} entries for {len(goals)} candidate goals")
    worth = gains >= cfg.min_gain_m2
    ids = [e.robot_id for e in explorers]
    if not worth.any():
        return ExplorationPlan({}, True, ids)
    cand = np.flatnonzero(worth)
    goals_c = goals[cand]
    cells_c = frontiers.goal_cells[cand]
    gains_c = gains[cand]
    claimed = (
        np.zeros((0, 2)) if claimed_in_map is None else np.asarray(claimed_in_map).reshape(-1, 2)
    )
    base = np.zeros(len(cand))
    for c in claimed:
        _suppress(base[None, :], goals_c, c, cfg.goal_separation_m)  # marks -inf in base
    out: dict[int, ExplorationGoal] = {}
    if not explorers:
        return ExplorationPlan(out, False, [])

    # phase 1: bounded grid search around each robot
    trav = [_traversable_for(grid, e) for e in explorers]
    near = [
        grid_distances(t, e.cell, resolution_m=grid.resolution_m, limit_m=cfg.near_radius_m)
        for e, t in zip(explorers, trav, strict=True)
    ]
    util = np.full((len(explorers), len(cand)), -np.inf)
    for i, (e, d) in enumerate(zip(explorers, near, strict=True)):
        dist = d.at(cells_c)
        u = gains_c - cfg.distance_weight_m2_per_m * dist + base
        u[_blacklisted(e, goals_c, cfg.blacklist_radius_m) | _in_avoid(e, goals_c)] = -np.inf
        util[i] = u
    for i, j in _uncross(util, _greedy(util, goals_c, cfg.goal_separation_m)):
        e = explorers[i]
        goal = goals_c[j]
        cell = (int(cells_c[j, 0]), int(cells_c[j, 1]))
        wps = _grid_waypoints(grid, near[i], cell, goal, cfg.path_tolerance_m)
        out[e.robot_id] = ExplorationGoal(
            e.robot_id,
            (float(goal[0]), float(goal[1])),
            wps,
            float(near[i].at(np.asarray([cell]))[0]),
            float(gains_c[j]),
            False,
        )
    for gid in out.values():
        _suppress(base[None, :], goals_c, np.asarray(gid.goal_in_map), cfg.goal_separation_m)

    # phase 2: far goals through the highway (or an unbounded grid search)
    rest = [i for i, e in enumerate(explorers) if e.robot_id not in out]
    if rest:
        util = np.full((len(rest), len(cand)), -np.inf)
        plans: dict[tuple[int, int], tuple[NDArray[np.float64], float, bool]] = {}
        own_blocked: dict[int, NDArray[np.bool_] | None] = {}
        goal_nodes: dict[int, NDArray[np.int64] | None] = {}
        far_grid: dict[int, GridDistances] = {}
        for row, i in enumerate(rest):
            e = explorers[i]
            pos = np.asarray(e.position_in_map, dtype=np.float64)
            cost = np.full(len(cand), np.inf)
            via = np.zeros(len(cand), dtype=bool)
            goal_node = None
            if highway is not None and highway.size:
                hb = _highway_blocked_for(highway, highway_blocked, e)
                own_blocked[i] = hb
                goal_node = highway.nearest(goals_c, hb)
                rn = int(highway.nearest(pos, hb)[0])
                if rn >= 0:
                    hd, _ = highway.distances([rn], hb)
                    ok = goal_node >= 0
                    gn = goal_node[ok]
                    cost[ok] = (
                        math.hypot(*(highway.nodes_in_map[rn] - pos))
                        + hd[0, gn]
                        + np.hypot(*(highway.nodes_in_map[gn] - goals_c[ok]).T)
                    )
                    via[ok] = np.isfinite(cost[ok])
            goal_nodes[i] = goal_node
            if cfg.far_grid_fallback and not np.isfinite(cost).any():
                fd = grid_distances(trav[i], e.cell, resolution_m=grid.resolution_m)
                far_grid[i] = fd
                cost = fd.at(cells_c)
                via[:] = False
            u = gains_c - cfg.distance_weight_m2_per_m * cost + base
            u[_blacklisted(e, goals_c, cfg.blacklist_radius_m) | _in_avoid(e, goals_c)] = -np.inf
            util[row] = u
            for jj in np.flatnonzero(np.isfinite(u)).tolist():
                plans[(row, jj)] = (pos, float(cost[jj]), bool(via[jj]))
        for row, j in _greedy(util, goals_c, cfg.goal_separation_m):
            i = rest[row]
            e = explorers[i]
            goal = goals_c[j]
            pos, cost_m, via_hw = plans[(row, j)]
            gnodes = goal_nodes[i]
            if via_hw and highway is not None and gnodes is not None:
                hb = own_blocked[i]
                rn = int(highway.nearest(pos, hb)[0])
                _, pred = highway.distances([rn], hb)
                nodes = highway.path(pred[0], int(gnodes[j]))
                pts = simplify_path(
                    np.vstack([highway.nodes_in_map[nodes], goal]), cfg.path_tolerance_m
                )
                wps = pts
            else:
                cell = (int(cells_c[j, 0]), int(cells_c[j, 1]))
                wps = _grid_waypoints(grid, far_grid[i], cell, goal, cfg.path_tolerance_m)
            out[e.robot_id] = ExplorationGoal(
                e.robot_id, (float(goal[0]), float(goal[1])), wps, cost_m, float(gains_c[j]), via_hw
            )
    if cfg.tour_goals > 0:
        out = _tours(grid, explorers, trav, out, goals_c, cells_c, gains_c, base, claimed, cfg)
    return ExplorationPlan(out, False, [e.robot_id for e in explorers if e.robot_id not in out])


def _tours(
    grid: PlanningGrid,
    explorers: list[Explorer],
    trav: list[NDArray[np.bool_]],
    out: dict[int, ExplorationGoal],
    goals_c: NDArray[np.float64],
    cells_c: NDArray[np.int64],
    gains_c: NDArray[np.float64],
    base: NDArray[np.float64],
    claimed: NDArray[np.float64],
    cfg: ExplorationConfig,
) -> dict[int, ExplorationGoal]:
    """Each goal of ``out`` extended into a tour (see :class:`ExplorationConfig`), one stop
    per robot a round, the robots with the best next stop first: from its last stop, the
    candidate of best ``gain - distance_weight * travel`` within ``tour_leg_m`` of travel on
    the robot's own traversable grid, at least ``goal_separation_m`` from every goal
    assigned, claimed (``base`` marks those near them) or on a tour already, not
    blacklisted or in the robot's avoid discs, while the tour stays within
    ``tour_length_m``."""
    sep = cfg.goal_separation_m
    taken = [np.asarray(g.goal_in_map) for g in out.values()] + [np.asarray(c) for c in claimed]
    index = {e.robot_id: i for i, e in enumerate(explorers)}
    ok: dict[int, NDArray[np.bool_]] = {}
    cur: dict[int, tuple[int, int]] = {}
    length = dict.fromkeys(out, 0.0)
    legs: dict[int, list[NDArray[np.float64]]] = {rid: [] for rid in out}
    stops: dict[int, list[NDArray[np.float64]]] = {rid: [] for rid in out}
    for rid, g in out.items():
        e = explorers[index[rid]]
        cell = grid.cells_of(np.asarray(g.goal_in_map))[0]
        if grid.inside(cell[None])[0]:
            cur[rid] = (int(cell[0]), int(cell[1]))
            ok[rid] = np.isfinite(base) & ~(
                _blacklisted(e, goals_c, cfg.blacklist_radius_m) | _in_avoid(e, goals_c)
            )
    for _ in range(cfg.tour_goals):
        bids: list[tuple[float, int, int, GridDistances]] = []
        for rid in sorted(cur):
            limit = min(cfg.tour_leg_m, cfg.tour_length_m - length[rid])
            if limit <= 0:
                continue
            free = ok[rid].copy()
            for t in taken:
                free &= np.hypot(goals_c[:, 0] - t[0], goals_c[:, 1] - t[1]) >= sep
            if not free.any():
                continue
            d = grid_distances(
                trav[index[rid]], cur[rid], resolution_m=grid.resolution_m, limit_m=limit
            )
            dist = d.at(cells_c)
            u = np.where(
                free & np.isfinite(dist), gains_c - cfg.distance_weight_m2_per_m * dist, -np.inf
            )
            j = int(np.argmax(u))
            if np.isfinite(u[j]) and u[j] > 0:
                bids.append((float(u[j]), rid, j, d))
        if not bids:
            break
        bids.sort(key=lambda b: (-b[0], b[1]))
        for _, rid, j, d in bids:
            if any(math.dist(goals_c[j], t) < sep for t in taken):
                continue  # a robot before it in this round took a stop near it
            cell = (int(cells_c[j, 0]), int(cells_c[j, 1]))
            legs[rid].append(_grid_waypoints(grid, d, cell, goals_c[j], cfg.path_tolerance_m))
            stops[rid].append(goals_c[j].copy())
            taken.append(goals_c[j].copy())
            length[rid] += float(d.at(np.asarray([cell]))[0])
            cur[rid] = cell
    result = dict(out)
    for rid, g in out.items():
        if stops[rid]:
            result[rid] = ExplorationGoal(
                g.robot_id,
                g.goal_in_map,
                np.vstack([g.waypoints_in_map, *legs[rid]]),
                g.distance_m,
                g.gain_m2,
                g.via_highway,
                np.asarray(stops[rid], dtype=np.float64).reshape(-1, 2),
            )
    return result


def failed_route_discs(
    route_in_map: NDArray[np.float64],
    position_in_map: tuple[float, float],
    *,
    from_m: float,
    to_m: float,
    radius_m: float,
    step_m: float = 0.5,
) -> NDArray[np.float64]:
    """``(K, 3)`` discs ``(x_m, y_m, radius_m)`` over the stretch of a failed route
    ``route_in_map`` ``(N, 2)`` (its start first) from ``from_m`` to ``to_m`` past the route's
    point nearest ``position_in_map`` (where the robot was when the route failed: what held
    it is just ahead), cut at the route's end; empty for a route of fewer than two points.

    The robot that failed is then routed around that stretch (:class:`Explorer`'s
    ``avoid_in_map``): a doorway narrower than the GCS's map shows, a gap its own map closes,
    a spot where it keeps deadlocking. ``O(N + (to_m - from_m) / step_m)``."""
    route = np.asarray(route_in_map, dtype=np.float64).reshape(-1, 2)
    if len(route) < 2 or to_m < from_m:
        return np.zeros((0, 3))
    a, b = route[:-1], route[1:]
    ab = b - a
    seg_len = np.hypot(ab[:, 0], ab[:, 1])
    p = np.asarray(position_in_map, dtype=np.float64)
    t = np.clip(((p - a) * ab).sum(axis=1) / np.maximum(seg_len**2, 1e-12), 0.0, 1.0)
    foot = a + ab * t[:, None]
    k = int(np.argmin(np.hypot(*(foot - p).T)))
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    s0 = cum[k] + t[k] * seg_len[k]
    s = np.arange(s0 + from_m, min(s0 + to_m, cum[-1]) + 1e-9, step_m)
    if s.size == 0:
        return np.zeros((0, 3))
    j = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(seg_len) - 1)
    frac = (s - cum[j]) / np.maximum(seg_len[j], 1e-12)
    pts = a[j] + ab[j] * frac[:, None]
    return np.column_stack([pts, np.full(len(pts), radius_m)])


def return_leg(
    waypoints_in_map: NDArray[np.float64],
    start_in_map: tuple[float, float],
    contact_in_map: NDArray[np.float64],
    *,
    radius_m: float,
    step_m: float = 0.5,
) -> NDArray[np.float64]:
    """The way back from a goal to radio contact: ``(K, 2)`` waypoints to append to
    ``waypoints_in_map`` (which end at the goal; the robot starts at ``start_in_map``), empty
    when the goal itself is within ``radius_m`` of a point of ``contact_in_map`` ``(C, 2)``
    (places where the GCS heard robots steadily), or when none is known yet; no such point
    on the route: all the way back to the start, then on to the point of contact nearest it.

    Why: MAGIC's radio had shadows (paper 4.1, 8) and a robot that finishes its task out of
    contact waits for the link before it gives up and backs out (``robot/comms_watchdog.py``:
    a minute in a 300 s mission); the GCS cannot re-task a robot it does not hear. So every
    exploration goal is a round trip: out along the route, then back along it to the last
    point of the route near a point of contact (walking back from the goal). A robot the GCS
    hears is re-planned when its goal's frontier is gone or it is at its goal, long before it
    drives the way back; one in a shadow explores it and comes back with what it saw, which
    the link then delivers (store and forward). ``O(route points x contact points)``."""
    wps = np.asarray(waypoints_in_map, dtype=np.float64).reshape(-1, 2)
    contact = np.asarray(contact_in_map, dtype=np.float64).reshape(-1, 2)
    if len(wps) == 0 or len(contact) == 0:
        return np.zeros((0, 2))  # where the radio reaches is not known yet: no guess
    route = np.vstack([np.asarray(start_in_map, dtype=np.float64).reshape(1, 2), wps])
    # the route densified at ``step_m``, walked back from the goal; ``vertex`` marks where
    # each dense point lies (vertex index of the segment it is on)
    pts = [route[-1:]]
    seg = [np.asarray([len(route) - 1])]
    for i in range(len(route) - 1, 0, -1):
        a, b = route[i], route[i - 1]
        n = max(1, int(math.ceil(math.hypot(*(b - a)) / step_m)))
        t = np.arange(1, n + 1)[:, None] / n
        pts.append(a + (b - a) * t)
        seg.append(np.full(n, i - 1))
    dense = np.vstack(pts)
    vertex = np.concatenate(seg)
    near = np.zeros(len(dense), dtype=bool)
    for chunk in range(0, len(contact), 4096):  # bounded memory on long missions
        c = contact[chunk : chunk + 4096]
        d2 = (dense[:, None, 0] - c[None, :, 0]) ** 2 + (dense[:, None, 1] - c[None, :, 1]) ** 2
        near |= (d2 <= radius_m**2).any(axis=1)
    hit = np.flatnonzero(near)
    k = int(hit[0]) if hit.size else len(dense) - 1  # none: all the way back to the start
    if k == 0:
        return np.zeros((0, 2))
    # back through the route's vertices passed on the way, then to the point of contact
    back = [route[j] for j in range(len(route) - 2, int(vertex[k]), -1)]
    back.append(dense[k])
    if not hit.size and len(contact):
        # the start was not a point of contact either (a robot just back from a shadow is
        # on its fringe): on to the point of contact nearest the start
        d = np.hypot(*(contact - route[0]).T)
        if d.min() > radius_m:
            back.append(contact[int(np.argmin(d))])
    return np.asarray(back, dtype=np.float64).reshape(-1, 2)


def shortcut(
    grid: PlanningGrid,
    from_in_map: NDArray[np.float64],
    to_in_map: NDArray[np.float64],
    *,
    limit_m: float,
    tolerance_m: float,
) -> NDArray[np.float64] | None:
    """``(K, 2)`` waypoints of the shortest way over ``grid`` from ``from_in_map`` to
    ``to_in_map`` (ending there), or None when there is none shorter than ``limit_m`` or
    either end has no traversable cell within a cell. The way home from the end of a tour:
    straight back to the point of contact, not back along the tour."""
    start = grid.snap(from_in_map, grid.resolution_m * 1.5)
    goal = grid.snap(to_in_map, grid.resolution_m * 1.5)
    if start is None or goal is None or not math.isfinite(limit_m):
        return None
    d = grid_distances(grid.traversable, start, resolution_m=grid.resolution_m, limit_m=limit_m)
    if not math.isfinite(float(d.at(np.asarray([goal]))[0])):
        return None
    return _grid_waypoints(grid, d, goal, np.asarray(to_in_map, dtype=np.float64), tolerance_m)
