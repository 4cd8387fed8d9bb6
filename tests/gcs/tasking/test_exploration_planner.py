"""Greedy frontier assignment: near goals, far goals through the highway, failure memory."""

from __future__ import annotations

import numpy as np
import pytest

from gcs.tasking.exploration_planner import (
    ExplorationConfig,
    Explorer,
    _uncross,
    failed_route_discs,
    plan_exploration,
    return_leg,
)
from gcs.tasking.frontiers import find_frontiers
from gcs.tasking.information_gain import information_gain
from gcs.tasking.planning_grid import coarsen
from gcs.tasking.trajectory_graph import build_trajectory_graph
from tests.gcs.tasking.maps import FREE, OCCUPIED, RES, blank, box, occupancy

CFG = ExplorationConfig()
TOURS = ExplorationConfig(tour_goals=3)  # tours are off by default


def corridor(x0: float = 5.0, x1: float = 35.0):  # type: ignore[no-untyped-def]
    """A corridor y in [1, 5] from x0 to x1, open at both ends into the unknown."""
    v = blank(40, 6)
    box(v, x0, 0.5, x1, 1.0, OCCUPIED)
    box(v, x0, 5.0, x1, 5.5, OCCUPIED)
    box(v, x0, 1.0, x1, 5.0, FREE)
    return coarsen(occupancy(v), resolution_m=RES, robot_radius_m=0.3)


def _plan(grid, robots, **kw):  # type: ignore[no-untyped-def]
    explorers = [
        Explorer(i, grid.snap(p, 1.0), p, *kw.pop(f"bl{i}", ())) for i, p in robots.items()
    ]
    f = find_frontiers(grid, [e.cell for e in explorers])
    gains = information_gain(grid, f.goal_cells, sensor_range_m=CFG.sensor_range_m)
    return plan_exploration(grid, f, gains, explorers, config=kw.pop("config", CFG), **kw)


def test_two_robots_two_frontiers_each_gets_the_nearer() -> None:
    g = corridor()
    plan = _plan(g, {1: (15.0, 3.0), 2: (25.0, 3.0)})
    assert not plan.explored and plan.unassigned == []
    assert plan.goals[1].goal_in_map[0] < 6.0  # the west end
    assert plan.goals[2].goal_in_map[0] > 34.0  # the east end
    for goal in plan.goals.values():
        assert not goal.via_highway
        assert np.allclose(goal.waypoints_in_map[-1], goal.goal_in_map)
        # the travel distance is a path length along the corridor
        assert goal.distance_m == pytest.approx(10.0, abs=1.5)


def test_a_single_frontier_goes_to_the_nearer_robot_and_the_other_waits() -> None:
    v = blank(40, 6)  # closed at the west, open at the east
    box(v, 0.0, 0.5, 35.0, 5.5, OCCUPIED)
    box(v, 0.5, 1.0, 35.0, 5.0, FREE)
    g = coarsen(occupancy(v), resolution_m=RES, robot_radius_m=0.3)
    plan = _plan(g, {1: (20.0, 3.0), 2: (30.0, 3.0)})
    assert set(plan.goals) == {2} and plan.unassigned == [1]
    assert plan.goals[2].goal_in_map[0] > 34.0


def test_failed_goals_are_not_offered_again() -> None:
    g = corridor()
    first = _plan(g, {1: (15.0, 3.0)}).goals[1].goal_in_map
    assert first[0] < 6.0
    again = _plan(g, {1: (15.0, 3.0)}, bl1=(np.asarray([first]),)).goals[1].goal_in_map
    assert np.hypot(again[0] - first[0], again[1] - first[1]) > CFG.blacklist_radius_m
    # both ends failed: no goal, but the map is not explored
    east = again
    plan = _plan(g, {1: (15.0, 3.0)}, bl1=(np.asarray([first, east]),))
    for gl in plan.goals.values():
        for bad in (first, east):
            assert np.hypot(gl.goal_in_map[0] - bad[0], gl.goal_in_map[1] - bad[1]) > 2.0


def test_no_goal_in_a_goals_off_disc_but_routes_may_cross_it() -> None:
    """The radio shadow a robot fell silent in (allocator ``shadow_goal_radius_m``): no goal
    within the disc; a goal beyond it is reached through it."""
    g = corridor()
    east = _plan(g, {1: (25.0, 3.0)}).goals[1].goal_in_map
    assert east[0] > 34.0
    off = np.asarray([[east[0], east[1], 5.0]])
    plan = _plan(g, {1: (25.0, 3.0)}, bl1=(np.zeros((0, 2)), np.zeros((0, 3)), off))
    assert plan.goals[1].goal_in_map[0] < 6.0  # the west end, not anywhere near the east
    # with the west end off too, the east end is reached through a disc on the way
    off2 = np.asarray([[30.0, 3.0, 2.0], [5.0, 3.0, 4.0]])
    plan = _plan(g, {1: (15.0, 3.0)}, bl1=(np.zeros((0, 2)), np.zeros((0, 3)), off2))
    goal = plan.goals[1]
    assert goal.goal_in_map[0] > 34.0 and goal.distance_m == pytest.approx(20.0, abs=1.5)


def test_no_frontier_means_explored() -> None:
    v = blank(12, 12)
    box(v, 0, 0, 12, 12, OCCUPIED)
    box(v, 0.5, 0.5, 11.5, 11.5, FREE)
    g = coarsen(occupancy(v), resolution_m=RES, robot_radius_m=0.3)
    plan = _plan(g, {1: (6.0, 6.0)})
    assert plan.explored and plan.goals == {} and plan.unassigned == [1]


def test_far_goals_route_through_the_highway() -> None:
    # a long corridor: the only frontier is 60 m east, beyond the 20 m search
    v = blank(70, 6)
    box(v, 0.0, 0.5, 65.0, 5.5, OCCUPIED)
    box(v, 0.5, 1.0, 65.0, 5.0, FREE)
    g = coarsen(occupancy(v), resolution_m=RES, robot_radius_m=0.3)
    xs = np.arange(1.0, 62.0, 0.5)
    driven = np.stack([xs, np.full_like(xs, 3.0)], axis=1)
    hw = build_trajectory_graph(np.ones(len(xs)), np.arange(len(xs)), driven)
    plan = _plan(g, {1: (2.0, 3.0)}, highway=hw)
    goal = plan.goals[1]
    assert goal.via_highway
    assert goal.goal_in_map[0] > 64.0
    assert goal.distance_m == pytest.approx(63.0, abs=3.0)
    assert np.allclose(goal.waypoints_in_map[-1], goal.goal_in_map)
    # without a highway the planner falls back to a full grid search and finds the same end
    plan = _plan(g, {1: (2.0, 3.0)})
    assert plan.goals[1].goal_in_map[0] > 64.0 and not plan.goals[1].via_highway


def test_the_way_back_ends_at_the_last_point_of_contact_on_the_route() -> None:
    # out east along y = 0, then north to the goal (10, 8); heard along x <= 4 only
    wps = np.asarray([[10.0, 0.0], [10.0, 8.0]])
    contact = np.asarray([[0.0, 0.0], [2.0, 0.0], [4.0, 0.0]])
    back = return_leg(wps, (0.0, 0.0), contact, radius_m=1.0)
    # back through the corner, then along the road to 1 m from the last point of contact
    assert np.allclose(back[0], (10.0, 0.0))
    assert np.allclose(back[-1], (5.0, 0.0), atol=0.26)
    assert len(back) == 2
    # heard near the corner: back only to the corner's neighbourhood, down the last leg
    back = return_leg(wps, (0.0, 0.0), np.asarray([[10.0, 1.0]]), radius_m=1.5)
    assert len(back) == 1 and np.allclose(back[0], (10.0, 2.5), atol=0.26)
    # the goal itself is in contact: no way back
    assert return_leg(wps, (0.0, 0.0), np.asarray([[10.5, 8.0]]), radius_m=1.0).shape == (0, 2)
    # heard nowhere on the route: all the way back to the start
    # then on to the point of contact nearest the start
    back = return_leg(wps, (0.0, 0.0), np.asarray([[50.0, 50.0], [-5.0, 0.0]]), radius_m=1.0)
    assert np.allclose(back, [[10.0, 0.0], [0.0, 0.0], [-5.0, 0.0]])
    # none known yet: no guess
    assert return_leg(wps, (0.0, 0.0), np.zeros((0, 2)), radius_m=1.0).shape == (0, 2)


def test_greedy_pairs_whose_routes_cross_swap_goals() -> None:
    # robot 0 at (0, 0) between goal a (1, 0) and goal b (-1, 0); robot 1 at (3, 0). Greedy
    # takes 0 -> a (the best pair), leaving 1 the far goal b across robot 0: 1 + 4 m of
    # travel; swapped, 1 + 2 m (same gains)
    robots = np.asarray([[0.0, 0.0], [3.0, 0.0]])
    goals = np.asarray([[1.0, 0.0], [-1.0, 0.0]])
    gains = np.asarray([10.0, 9.0])
    util = gains[None, :] - 2.0 * np.hypot(*(robots[:, None, :] - goals[None, :, :]).T).T
    greedy = [(0, 0), (1, 1)]
    assert _uncross(util, greedy) == [(0, 1), (1, 0)]
    # already the best pairing: kept; a swap onto a forbidden goal (-inf) is never made
    assert _uncross(util, [(0, 1), (1, 0)]) == [(0, 1), (1, 0)]
    util[0, 1] = -np.inf
    assert _uncross(util, greedy) == greedy


def test_failed_route_discs_lie_ahead_of_the_robot_on_the_way_out() -> None:
    route = np.asarray([[0.0, 0.0], [4.0, 0.0], [4.0, 4.0]])
    d = failed_route_discs(route, (3.0, 0.3), from_m=0.5, to_m=3.0, radius_m=0.75)
    # from 3.5 m along (x 3.5) to 6 m along (the corner, then 2 m up)
    assert np.allclose(d[0], [3.5, 0.0, 0.75]) and np.allclose(d[-1], [4.0, 2.0, 0.75])
    assert np.allclose(np.diff(d[:, :2], axis=0).__abs__().sum(axis=1), 0.5)
    # cut at the route's end; nothing from a single point
    d = failed_route_discs(route, (4.0, 3.0), from_m=0.5, to_m=3.0, radius_m=0.75)
    assert np.allclose(d[:, :2], [[4.0, 3.5], [4.0, 4.0]])
    assert failed_route_discs(route[:1], (0, 0), from_m=0, to_m=1, radius_m=1).shape == (0, 3)


def test_an_explorers_avoid_discs_route_it_around_or_elsewhere() -> None:
    """Known answer: the corridor's west end is behind a disc for robot 1 only, so robot 1
    gets the east end however much nearer the west is; a robot without it goes west."""
    g = corridor()
    disc = np.asarray([[10.0, 3.0, 2.5]])
    plan = _plan(g, {1: (14.0, 3.0), 2: (17.0, 3.0)})
    assert plan.goals[1].goal_in_map[0] < 6.0  # the nearer, west
    f = find_frontiers(g, [g.snap((14.0, 3.0), 1.0)])
    gains = information_gain(g, f.goal_cells, sensor_range_m=CFG.sensor_range_m)
    ex = [Explorer(1, g.snap((14.0, 3.0), 1.0), (14.0, 3.0), avoid_in_map=disc)]
    plan = plan_exploration(g, f, gains, ex, config=CFG)
    assert plan.goals[1].goal_in_map[0] > 34.0
    # another robot with no discs still goes west
    ex2 = [Explorer(2, g.snap((14.0, 3.0), 1.0), (14.0, 3.0))]
    assert plan_exploration(g, f, gains, ex2, config=CFG).goals[2].goal_in_map[0] < 6.0
    assert np.hypot(*(plan.goals[1].waypoints_in_map - disc[0, :2]).T).min() > 2.5


def strip():  # type: ignore[no-untyped-def]
    """A known strip y in [0.5, 4] from x 0.5 to 39.5, walled south, west and east, with
    the unknown north of it: one long frontier along y ~4."""
    v = blank(40, 12)
    box(v, 0.0, 0.0, 40.0, 4.0, OCCUPIED)
    box(v, 0.5, 0.5, 39.5, 4.0, FREE)
    return coarsen(occupancy(v), resolution_m=RES, robot_radius_m=0.3)


def test_a_goal_goes_on_as_a_tour_along_the_frontier() -> None:
    """Known answer: a robot at the west end of a strip whose north side is one frontier gets
    a goal near it and then a tour east along the frontier, each further goal at least
    goal_separation_m from the last, every one on the way (the waypoints pass through them),
    the tour no longer than tour_length_m: a robot out of contact there sweeps the frontier
    instead of driving back to contact after the first goal (full mission: star patterns)."""
    g = strip()
    plan = _plan(g, {1: (2.0, 2.0)}, config=TOURS)
    goal = plan.goals[1]
    assert goal.goal_in_map[0] < 8.0
    tour = goal.tour_in_map
    assert 1 <= len(tour) <= TOURS.tour_goals
    stops = np.vstack([goal.goal_in_map, tour])
    assert (np.diff(stops[:, 0]) > 0).all()  # on east along the frontier
    assert (np.hypot(*np.diff(stops, axis=0).T) >= CFG.goal_separation_m - 1e-9).all()
    assert (stops[:, 1] > 3.0).all()  # on the frontier
    wps = goal.waypoints_in_map
    assert np.allclose(wps[-1], tour[-1])
    for s in stops:  # each stop is a waypoint
        assert np.hypot(*(wps - s).T).min() < 1e-6
    # the tour's travel after the first goal stays within tour_length_m
    after = wps[int(np.argmin(np.hypot(*(wps - stops[0]).T))) :]
    assert np.hypot(*np.diff(after, axis=0).T).sum() <= TOURS.tour_length_m + 1.0
    # tours off: the goal alone
    off = _plan(g, {1: (2.0, 2.0)}, config=ExplorationConfig(tour_goals=0))
    assert len(off.goals[1].tour_in_map) == 0
    assert np.allclose(off.goals[1].waypoints_in_map[-1], off.goals[1].goal_in_map)


def test_tours_keep_clear_of_other_robots_goals_and_claims() -> None:
    """Two robots at the strip's two ends: neither's tour comes within goal_separation_m of
    the other's goal or tour stops, nor of a claimed goal."""
    g = strip()
    claimed = np.asarray([[20.0, 3.5]])
    plan = _plan(g, {1: (2.0, 2.0), 2: (38.0, 2.0)}, claimed_in_map=claimed, config=TOURS)
    s1 = np.vstack([plan.goals[1].goal_in_map, plan.goals[1].tour_in_map])
    s2 = np.vstack([plan.goals[2].goal_in_map, plan.goals[2].tour_in_map])
    assert len(s1) > 1 and len(s2) > 1
    d = np.hypot(s1[:, None, 0] - s2[None, :, 0], s1[:, None, 1] - s2[None, :, 1])
    assert d.min() >= CFG.goal_separation_m - 1e-9
    for s in (s1, s2):
        assert np.hypot(*(s - claimed[0]).T).min() >= CFG.goal_separation_m - 1e-9
