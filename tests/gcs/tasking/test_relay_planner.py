"""Relay spots on constructed highways with known answers."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_a_second_relay_stands_a_hop_out_towards_the_silent_robot() -> None:
    """Relays chained outwards (paper 4.1: robots as relays; 8: the radio bounded what was
    explored). Known answer: a road from x 0 to 60, contact up to x 18 (covered to x 20), a
    robot silent at x 55: the edge spot is x ~20 and, with hop_m 30, the outward spot x ~50
    (30 m of highway on towards it); hop_m 0 gives the edge spot alone."""
    hw = _road(np.arange(0.0, 60.1, 1.0))
    contact = np.asarray([[2.0, 0.0], [10.0, 0.0], [18.0, 0.0]])
    alone = relay_spots(hw, [[55.0, 1.0]], contact, contact_radius_m=2.0)
    assert hw.nodes_in_map[alone, 0] == pytest.approx([20.0], abs=2.0)
    chain = relay_spots(hw, [[55.0, 1.0]], contact, contact_radius_m=2.0, hop_m=30.0)
    assert hw.nodes_in_map[chain, 0] == pytest.approx([20.0, 50.0], abs=2.0)
    # 13 m out (within a hop of highway of the edge) the first relay reaches it: no second
    one = relay_spots(hw, [[33.0, 0.0]], contact, contact_radius_m=2.0, hop_m=30.0)
    assert hw.nodes_in_map[one, 0] == pytest.approx([20.0], abs=2.0)
    # three silent robots: edge, outward, edge, edge (the last two within a hop of theirs)
    two = relay_spots(
        hw, [[55.0, 0.0], [-4.0, 0.0], [21.0, 0.0]], contact, contact_radius_m=2.0, hop_m=30.0
    )
    assert hw.nodes_in_map[two, 0] == pytest.approx([20.0, 50.0, 0.0], abs=2.0)


def test_the_outward_spot_counts_highway_not_straight_line() -> None:
    """Known answer: a U-shaped highway (out east along y 0 to x 20, north to y 20, back
    west to x 0): contact at its start, a robot silent at its end (0, 20), 20 m from the
    edge in a straight line but 60 m of highway: the outward spot, 30 m of highway from the
    edge, is (20, 8) (the drive, not across the U's inside, where the robots never went)."""
    east = np.stack([np.arange(0.0, 20.1, 1.0), np.zeros(21)], 1)
    north = np.stack([np.full(20, 20.0), np.arange(1.0, 20.1, 1.0)], 1)
    west = np.stack([np.arange(19.0, -0.1, -1.0), np.full(20, 20.0)], 1)
    xy = np.vstack([east, north, west])
    hw = build_trajectory_graph(np.zeros(len(xy), dtype=np.int64), np.arange(len(xy)), xy)
    spots = relay_spots(hw, [[0.0, 21.0]], [[0.0, 0.0]], contact_radius_m=2.0, hop_m=30.0)
    assert len(spots) == 2
    assert hw.nodes_in_map[spots[0]] == pytest.approx([0.0, 0.0], abs=2.1)
    out = hw.nodes_in_map[spots[1]]
    assert out[0] == pytest.approx(20.0, abs=1.0) and 6.0 <= out[1] <= 10.5
