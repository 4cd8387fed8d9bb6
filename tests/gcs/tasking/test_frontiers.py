"""Reachable frontier clusters on constructed maps."""

from __future__ import annotations

import numpy as np

from gcs.tasking.frontiers import find_frontiers
from gcs.tasking.planning_grid import coarsen
from tests.gcs.tasking.maps import FREE, RES, UNKNOWN, blank, box, occupancy, room


def _grid(values: np.ndarray):  # type: ignore[no-untyped-def]
    return coarsen(occupancy(values), resolution_m=RES, robot_radius_m=0.3)


def test_a_room_with_one_door_has_one_frontier_at_the_door() -> None:
    v = blank(20, 12)
    room(v, 0, 0, 12, 12)
    box(v, 11.5, 5, 12, 7, FREE)  # a 2 m door in the east wall, unknown beyond
    g = _grid(v)
    f = find_frontiers(g, [g.snap((6, 6), 1.0)])
    assert f.clusters == 1
    assert len(f.goals_in_map) >= 1
    assert np.all(f.goals_in_map[:, 0] > 11.0) and np.all(np.abs(f.goals_in_map[:, 1] - 6) < 1.2)
    assert f.near((11.9, 6.0), g, 0.5) and not f.near((6.0, 6.0), g, 2.0)


def test_a_frontier_no_robot_can_reach_is_not_offered() -> None:
    v = blank(30, 12)
    room(v, 0, 0, 12, 12)  # closed: nothing to explore from inside
    room(v, 15, 0, 27, 12)
    box(v, 26.5, 5, 27, 7, FREE)  # the other room has a door, but no robot is there
    g = _grid(v)
    assert find_frontiers(g, [g.snap((6, 6), 1.0)]).empty
    assert not find_frontiers(g, [g.snap((21, 6), 1.0)]).empty


def test_speckles_of_unknown_are_not_frontier() -> None:
    v = blank(20, 12)
    room(v, 0, 0, 12, 12)
    box(v, 5, 5, 5.25, 5.25, UNKNOWN)  # one unknown fine cell inside a seen room
    g = _grid(v)
    f = find_frontiers(g, [g.snap((3, 3), 1.0)], min_cluster_cells=5)
    assert f.empty
