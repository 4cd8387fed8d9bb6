"""Hostile view positions and the 30 s lock."""

from __future__ import annotations

import math

import numpy as np

from gcs.tasking.hostile_planner import HostileConfig, HostileLock, view_positions
from gcs.tasking.planning_grid import coarsen, line_of_sight
from tests.gcs.tasking.maps import FREE, OCCUPIED, RES, blank, box, occupancy

CFG = HostileConfig()


def test_two_views_outside_the_blast_radius_with_line_of_sight() -> None:
    v = blank(40, 40, FREE)
    box(v, 14, 24, 26, 24.5, OCCUPIED)  # a wall north of the hostile
    g = coarsen(occupancy(v), resolution_m=RES, robot_radius_m=0.3)
    h = (20.0, 20.0)
    robots = {1: (20.0, 35.0), 2: (5.0, 20.0), 3: (38.0, 38.0)}
    views = view_positions(g, h, robots, CFG)
    assert set(views) == {1, 2}  # the two nearest
    for p in views.values():
        assert CFG.blast_radius_m + CFG.margin_m <= math.dist(p, h) <= CFG.view_range_m
        assert line_of_sight(g, p, h)
    b = [math.atan2(p[1] - h[1], p[0] - h[0]) for p in views.values()]
    assert abs((b[0] - b[1] + math.pi) % (2 * math.pi) - math.pi) >= CFG.min_bearing_sep_rad


def test_lock_needs_two_robots_for_30_s_without_a_break() -> None:
    lock = HostileLock(CFG)
    seen: dict[int, float] = {}
    for t in np.arange(0.0, 20.0, 0.5):
        seen = {1: float(t), 2: float(t)}
        st = lock.update(9, seen, float(t))
    assert not st.locked and st.since_s == 0.0
    # robot 2 loses it for 3 s: the lock starts over
    for t in np.arange(20.0, 23.0, 0.5):
        st = lock.update(9, {1: float(t), 2: 19.5}, float(t))
    assert st.since_s is None and st.breaks == 1
    for t in np.arange(23.0, 53.5, 0.5):
        st = lock.update(9, {1: float(t), 2: float(t)}, float(t))
    assert st.locked and st.locked_at_s == 53.0


def test_views_where_the_gcs_hears_robots_win_only_a_short_detour() -> None:
    v = blank(40, 40, FREE)
    g = coarsen(occupancy(v), resolution_m=RES, robot_radius_m=0.3)
    h = (20.0, 20.0)
    robots = {1: (32.0, 20.0)}  # east of the hostile
    east = view_positions(g, h, robots, CFG)[1]
    assert east[0] > 27.0  # nearest at the preferred range: on its own side
    # heard a little way round (30 deg): the view goes there
    near = np.asarray([[27.8, 24.5]])
    v_near = view_positions(g, h, robots, CFG, contact_in_map=near, contact_radius_m=2.0)[1]
    assert math.dist(v_near, near[0]) <= 2.0
    assert CFG.blast_radius_m + CFG.margin_m <= math.dist(v_near, h) <= CFG.view_range_m
    # heard only on the far side (a radio shadow around the robot): not worth the way round
    # (the rules' lock does not need the radio)
    far = np.asarray([[11.0, 20.0]])
    v_far = view_positions(g, h, robots, CFG, contact_in_map=far, contact_radius_m=2.0)[1]
    assert v_far == east
    # without the detour cost the heard view would win
    loud = HostileConfig(unheard_cost_m=100.0)
    assert math.dist(view_positions(g, h, robots, loud, contact_in_map=far)[1], far[0]) <= 2.0


def test_watchers_are_placed_where_the_robot_does_not_back_away_from_a_still_hostile() -> None:
    # issue 14: a watcher placed within the distance at which the robot backs away on its
    # own (robot.control.hostile_evasion: a walker that may reach its blast radius plus
    # margin within react_s) backs away as soon as it sees the walker
    from robot.control.hostile_evasion import EvasionConfig, hostile_threat

    ev = EvasionConfig()
    g = coarsen(occupancy(blank(40, 40, FREE)), resolution_m=RES, robot_radius_m=0.3)
    h = (20.0, 20.0)
    # robots right beside the hostile: the nearest admissible cells are the ring's inner edge
    views = view_positions(g, h, {1: (20.0, 27.0), 2: (13.0, 20.0)}, CFG)
    assert len(views) == 2
    still = np.array([[*h, 0.0, 0.0]])
    for p in views.values():
        assert hostile_threat(np.asarray(p), still, ev) >= ev.blast_radius_m + ev.margin_m


def test_views_keep_the_preferred_range_not_the_rings_outer_edge() -> None:
    # issue 14 (small world at 38fac2c): the nearest admissible cell lies on the ring's outer
    # edge, out of the rules' 12 m lock range a few seconds after the walker walks on
    g = coarsen(occupancy(blank(60, 40, FREE)), resolution_m=RES, robot_radius_m=0.3)
    h = (30.0, 20.0)
    robots = {1: (5.0, 20.0), 2: (30.0, 2.0)}
    views = view_positions(g, h, robots, CFG)
    assert set(views) == {1, 2}
    for p in views.values():
        assert abs(math.dist(p, h) - CFG.view_pref_m) <= 0.5
    # no range preference: the outer edge, as before
    edge = view_positions(g, h, robots, HostileConfig(range_weight=0.0))
    assert all(math.dist(p, h) >= CFG.view_range_m - 0.5 for p in edge.values())


def test_a_watcher_that_sees_the_hostile_stays_and_the_other_is_placed_apart() -> None:
    g = coarsen(occupancy(blank(60, 40, FREE)), resolution_m=RES, robot_radius_m=0.3)
    h = (30.0, 20.0)
    fixed = {7: (21.0, 20.5)}  # west of the hostile, seeing it
    robots = {7: fixed[7], 2: (20.0, 18.0)}  # robot 2 right beside it
    views = view_positions(g, h, robots, CFG, fixed_in_map=fixed)
    assert views[7] == fixed[7]
    b7 = math.atan2(fixed[7][1] - h[1], fixed[7][0] - h[0])
    b2 = math.atan2(views[2][1] - h[1], views[2][0] - h[0])
    assert abs((b7 - b2 + math.pi) % (2 * math.pi) - math.pi) >= CFG.min_bearing_sep_rad
