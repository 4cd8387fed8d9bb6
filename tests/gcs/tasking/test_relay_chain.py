"""Idle disruptors as relays (allocator + relay_planner, paper 4.1, 5.1.2, 8) on a
constructed road with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.tasking.allocator import RobotInfo, Role, TaskAllocator, TaskingConfig, TaskingState
from protocol.messages import GoToTask
from tests.gcs.tasking.maps import FREE, blank, occupancy

XS = np.arange(0.5, 61.0, 0.5)
ROAD = np.stack([XS, np.full_like(XS, 3.0)], 1)  # driven: the highway, x 0.5 to 60.5


def robot(rid: int, x: float, role: Role = Role.SENSOR) -> RobotInfo:
    return RobotInfo(rid, role, (x, 3.0, 0.0), (0.0, 0.0, 0.0), 0.0)


def state(robots: list[RobotInfo]) -> TaskingState:
    return TaskingState(
        occupancy(blank(65, 6, FREE)),
        robots,
        trajectory_robot_ids=np.ones(len(XS), dtype=np.int64),
        trajectory_keys=np.arange(len(XS)),
        trajectory_xy_in_map=ROAD,
    )


def test_a_disruptor_on_a_waypoint_of_its_own_enters_the_highway_by_its_largest_piece() -> None:
    """A disruptor that has not driven stands on a waypoint of its own (its start, 2 m from
    the road, more than merge_m: not joined): spread over that piece alone it stayed (full
    mission seed 0: a disruptor at its start for 600 s). Known answer: contact along the
    road to x 20, robot 1 silent at x 40, the disruptor at (1, 5) with its one pose there:
    it is sent to the relay spot (x ~21), by the road."""
    s, d = robot(1, 5.0), RobotInfo(21, Role.DISRUPTOR, (1.0, 5.0, 0.0), (0.0, 0.0, 0.0), 0.0)
    cfg = TaskingConfig()
    alloc = TaskAllocator(cfg)

    def st() -> TaskingState:
        return TaskingState(
            occupancy(blank(65, 8, FREE)),
            [s, d],
            trajectory_robot_ids=np.r_[np.ones(len(XS), dtype=np.int64), 21],
            trajectory_keys=np.r_[np.arange(len(XS)), 0],
            trajectory_xy_in_map=np.vstack([ROAD, [[1.0, 5.0]]]),
        )

    t = 0.0
    for x in np.arange(5.0, 20.01, 0.5):
        s.pose_in_map = (float(x), 3.0, 0.0)
        s.last_heard_s = d.last_heard_s = t
        alloc.plan(st(), now_s=t)
        t += 1.0
    s.pose_in_map, s.last_heard_s = (40.0, 3.0, 0.0), t - cfg.silent_after_s - 1.0
    d.last_heard_s = t
    alloc._spread_at_s = -math.inf
    out = alloc.plan(st(), now_s=t)
    go = [m for rid, m in out if rid == 21 and isinstance(m, GoToTask)]
    assert len(go) == 1
    wps = np.asarray(go[0].waypoints_in_odom)
    assert wps[-1, 0] == pytest.approx(21.0, abs=2.0)
    assert np.abs(wps[:, 1] - 3.0).max() < 0.5  # along the road
