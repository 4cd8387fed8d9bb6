"""The node's yield rule waits only for what may move (issue 14, small world seed 1).

A robot whose path is blocked close ahead with only a long detour left waits rather than
detours (:mod:`robot.control.deadlock`), but only when a teammate seen by its tags or a
person track is near the block: a static obstacle (a curb's face held in the terrain map)
does not move out of the way, and waiting for it cost seed 1's robot 60-137 s.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from robot.control.deadlock import DeadlockConfig
from robot.node import RobotNode, RobotNodeConfig
from robot.perception.person_tracker import PersonTrack
from robot.terrain.grid import DRIVABLE, OBSTACLE, GridGeometry

GOAL = np.array([10.0, 0.0])
NOW = 20.0


def blocked_node(**deadlock: object) -> tuple[RobotNode, np.ndarray, GridGeometry]:
    """A node at the origin following a straight path to ``GOAL``; the map it replans on has
    a wall across that path 3 m ahead, and the new plan found no way round."""
    cfg = RobotNodeConfig(deadlock=DeadlockConfig(**deadlock))  # type: ignore[arg-type]
    node = RobotNode(1, send=lambda _m: None, config=cfg)
    assert node.perception is not None
    node._now = NOW
    path = np.stack([np.linspace(0.0, 10.0, 21), np.zeros(21)], axis=1)
    node._reference = (GOAL.copy(), path)
    geometry = GridGeometry((-5.0, -5.0), 0.1, 100, 200)
    classes = np.full(geometry.shape, DRIVABLE, dtype=np.uint8)
    rows, cols = geometry.cell_of(np.array([[3.0, y] for y in np.arange(-1.0, 1.01, 0.1)])).T
    classes[rows, cols] = OBSTACLE
    return node, classes, geometry


def should_yield(node: RobotNode, classes: np.ndarray, geometry: GridGeometry) -> bool:
    no_path = SimpleNamespace(ok=False, length_m=math.inf)
    return node._should_yield(GOAL.copy(), no_path, classes, geometry)


def test_a_static_obstacle_across_the_path_is_not_waited_for() -> None:
    node, classes, geometry = blocked_node()
    assert not should_yield(node, classes, geometry)


def test_waiting_for_any_block_when_movers_only_is_off() -> None:
    node, classes, geometry = blocked_node(yield_movers_only=False)
    assert should_yield(node, classes, geometry)


def test_a_teammate_seen_at_the_block_is_waited_for() -> None:
    node, classes, geometry = blocked_node()
    assert node.perception is not None
    node.perception._teammates_seen.append((NOW - 1.0, 3.4, 0.2))
    assert should_yield(node, classes, geometry)


def test_a_teammate_seen_long_ago_or_far_from_the_block_is_not() -> None:
    node, classes, geometry = blocked_node()
    assert node.perception is not None
    node.perception._teammates_seen.append((NOW - 30.0, 3.4, 0.2))  # too long ago
    node.perception._teammates_seen.append((NOW - 1.0, 3.0, 4.0))  # 4 m off the block
    assert not should_yield(node, classes, geometry)


@pytest.mark.parametrize("confirmed", [True, False])
def test_a_person_track_at_the_block_is_waited_for_once_confirmed(confirmed: bool) -> None:
    node, classes, geometry = blocked_node()
    assert node.perception is not None
    track = PersonTrack(
        track_id=7,
        x=np.array([3.5, -0.3, -0.5, 0.0]),
        p=np.eye(4),
        time_s=NOW - 0.5,
        hits=3 if confirmed else 1,
        confirmed=confirmed,
    )
    node.perception.lidar.tracker.tracks.append(track)
    assert should_yield(node, classes, geometry) is confirmed


@pytest.mark.parametrize("cleared", [True, False])
def test_a_block_the_newest_sweep_no_longer_sees_is_waited_for_with_yield_cleared(
    cleared: bool,
) -> None:
    """The memory holds the wall, the newest sweep sees the way clear (a mover's trail):
    with ``yield_cleared`` the robot waits and its memory is refreshed."""
    node, classes, geometry = blocked_node(yield_cleared=cleared)
    node._latest = (np.zeros(geometry.shape, dtype=bool), geometry)
    assert should_yield(node, classes, geometry) is cleared
    # the newest sweep still sees the wall: a static obstacle either way
    node, classes, geometry = blocked_node(yield_cleared=cleared)
    node._latest = (classes == OBSTACLE, geometry)
    assert not should_yield(node, classes, geometry)
