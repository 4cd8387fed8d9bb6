"""Relay spots on constructed highways with known answers."""

from __future__ import annotations

import numpy as np

from gcs.tasking.relay_planner import relay_spots
from gcs.tasking.trajectory_graph import build_trajectory_graph


def _road(xs: np.ndarray, y: float = 0.0):  # type: ignore[no-untyped-def]
    xy = np.stack([xs, np.full_like(xs, y)], 1)
    return build_trajectory_graph(np.zeros(len(xs), dtype=np.int64), np.arange(len(xs)), xy)


def test_the_spot_is_the_covered_waypoint_nearest_the_silent_robot() -> None:
    hw = _road(np.arange(0.0, 40.1, 1.0))
    contact = np.asarray([[2.0, 0.0], [10.0, 0.5], [18.0, 0.0]])
    spots = relay_spots(hw, [[35.0, 3.0]], contact, contact_radius_m=2.0)
    assert len(spots) == 1
    assert abs(hw.nodes_in_map[spots[0], 0] - 20.0) <= 2.0  # within 2 m of the contact at 18
    # two silent robots: one each, in their order; the same spot once
    spots = relay_spots(hw, [[35.0, 0.0], [-5.0, 0.0], [36.0, 0.0]], contact, contact_radius_m=2.0)
    assert len(spots) == 2
    assert hw.nodes_in_map[spots[1], 0] <= 1.0
    # blocked or outside the region: the next covered one
    blocked = np.zeros(hw.size, dtype=bool)
    blocked[spots[0]] = True
    again = relay_spots(hw, [[35.0, 0.0]], contact, contact_radius_m=2.0, blocked=blocked)
    assert again[0] != spots[0] and hw.nodes_in_map[again[0], 0] >= 12.0


def test_no_contact_or_no_silent_robot_gives_no_spot() -> None:
    hw = _road(np.arange(0.0, 10.1, 1.0))
    assert relay_spots(hw, [[5.0, 0.0]], np.zeros((0, 2)), contact_radius_m=2.0).size == 0
    assert relay_spots(hw, np.zeros((0, 2)), [[1.0, 0.0]], contact_radius_m=2.0).size == 0
    far = relay_spots(hw, [[5.0, 0.0]], [[50.0, 50.0]], contact_radius_m=2.0)
    assert far.size == 0
