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


def test_views_where_the_gcs_hears_robots_come_first() -> None:
    v = blank(40, 40, FREE)
    g = coarsen(occupancy(v), resolution_m=RES, robot_radius_m=0.3)
    h = (20.0, 20.0)
    robots = {1: (20.0, 35.0)}  # north of the hostile
    north = view_positions(g, h, robots, CFG)[1]
    assert north[1] > 25.0  # nearest: on its own side
    # heard only south of the hostile (a radio shadow to the north): the view goes south
    contact = np.asarray([[20.0, 11.0], [19.0, 11.0]])
    south = view_positions(g, h, robots, CFG, contact_in_map=contact, contact_radius_m=2.0)[1]
    assert min(math.dist(south, c) for c in contact) <= 2.0
    assert CFG.blast_radius_m + CFG.margin_m <= math.dist(south, h) <= CFG.view_range_m
    # no heard cell in the ring: the nearest view as before
    far = np.asarray([[0.0, 0.0]])
    assert view_positions(g, h, robots, CFG, contact_in_map=far) == {1: north}


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
