"""Relays chained outwards and kept where they serve (allocator + relay_planner, paper 4.1,
5.1.2, 8) on a constructed road with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.tasking.allocator import RobotInfo, Role, TaskAllocator, TaskingConfig, TaskingState
from protocol.messages import GoToTask, RelayTask, TaskState, TaskStatus
from tests.gcs.tasking.maps import FREE, blank, occupancy

XS = np.arange(0.5, 61.0, 0.5)
ROAD = np.stack([XS, np.full_like(XS, 3.0)], 1)  # driven: the highway, x 0.5 to 60.5
#: the chain and the keep on (both off by default: TaskingConfig.relay_hop_m)
ON = TaskingConfig(relay_hop_m=30.0, relay_keep_s=120.0)


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


def heard_along(alloc: TaskAllocator, s: RobotInfo, others: list[RobotInfo], x1: float) -> float:
    """Robot ``s`` heard steadily along the road from x 5 to ``x1`` (points of contact);
    returns the time after."""
    t = 0.0
    for x in np.arange(5.0, x1 + 0.01, 0.5):
        s.pose_in_map = (float(x), 3.0, 0.0)
        for r in [s, *others]:
            r.last_heard_s = t
        alloc.plan(state([s, *others]), now_s=t)
        t += 1.0
    return t


def test_a_silent_robot_beyond_a_hop_gets_two_relays_in_a_chain() -> None:
    """Known answer: contact along the road to x 20, robot 1 silent at x 58, two idle
    disruptors near x 10: one goes to the edge of contact (x ~21), the other a hop (30 m of
    highway) on towards robot 1 (x ~51): GCS, relay, relay, robot. With relay_hop_m 0 (the
    rule off, the default) the second disruptor spreads instead (to the road's middle, x ~30)."""

    def goals(cfg: TaskingConfig) -> list[float]:
        s = robot(1, 5.0)
        d1, d2 = robot(21, 10.0, Role.DISRUPTOR), robot(22, 11.0, Role.DISRUPTOR)
        alloc = TaskAllocator(cfg)
        t = heard_along(alloc, s, [d1, d2], 20.0)
        s.pose_in_map, s.last_heard_s = (58.0, 3.0, 0.0), t - cfg.silent_after_s - 1.0
        d1.last_heard_s = d2.last_heard_s = t
        for rid in (21, 22):
            alloc.assignments.pop(rid, None)
        alloc._spread_at_s = -math.inf
        alloc.plan(state([s, d1, d2]), now_s=t)
        out = []
        for rid in (21, 22):
            g = alloc.assignments[rid].goal_in_map
            assert g is not None
            out.append(g[0])
        return sorted(out)

    on = goals(ON)
    assert on == pytest.approx([21.0, 51.0], abs=2.0)
    off = goals(TaskingConfig(relay_keep_s=120.0))
    assert off[0] == pytest.approx(21.0, abs=2.0) and off[1] < 40.0


def test_a_relay_holding_at_its_spot_stays_there_when_the_robot_is_heard_again() -> None:
    """Known answer: contact to x 45, robot 1 silent at x 58: the idle disruptor goes to the
    edge spot (x ~46) and holds there as a relay (RelayTask). Robot 1 is heard again
    (through it); the disruptor holds there for relay_keep_s (kept), and after it goes back
    to spreading (the road's middle, x ~30); with relay_keep_s 0 (the rule off, the default) it
    is sent to spread a spread period after."""

    def run(cfg: TaskingConfig) -> tuple[list[float], TaskAllocator]:
        s, d = robot(1, 5.0), robot(21, 12.0, Role.DISRUPTOR)
        alloc = TaskAllocator(cfg)
        t = heard_along(alloc, s, [d], 45.0)
        s.pose_in_map, s.last_heard_s = (58.0, 3.0, 0.0), t - cfg.silent_after_s - 1.0
        d.last_heard_s = t
        alloc.assignments.pop(21, None)
        alloc._spread_at_s = -math.inf
        out = alloc.plan(state([s, d]), now_s=t)
        go = [m for rid, m in out if rid == 21 and isinstance(m, GoToTask)]
        assert len(go) == 1
        a = alloc.assignments[21]
        assert a.goal_in_map is not None and a.goal_in_map[0] == pytest.approx(46.0, abs=2.0)
        # it arrives and says so: it holds there as a relay
        d.pose_in_map = (a.goal_in_map[0], a.goal_in_map[1], 0.0)
        d.status = TaskStatus(go[0].task_id, TaskState.SUCCEEDED, t + 5.0)
        t += 5.0
        d.last_heard_s = t
        out = alloc.plan(state([s, d]), now_s=t)
        assert any(rid == 21 and isinstance(m, RelayTask) for rid, m in out)
        # robot 1 heard again near x 58, through the relay; the disruptor's goal, plan by plan
        xs: list[float] = []
        for _ in range(int(200 / 10)):
            t += 10.0
            s.last_heard_s = d.last_heard_s = t
            alloc.plan(state([s, d]), now_s=t)
            b = alloc.assignments.get(21)  # None: its spread task timed out (it never moves)
            xs.append(math.nan if b is None or b.goal_in_map is None else b.goal_in_map[0])
        return xs, alloc

    xs, alloc = run(ON)
    keep_s = alloc.config.relay_keep_s
    n_keep = int((keep_s - 5.0 - 1.0) / 10.0)
    assert xs[:n_keep] == pytest.approx([xs[0]] * n_keep) and xs[0] == pytest.approx(46.0, abs=2)
    assert np.nanmin(xs[n_keep:]) < 40.0  # the spot expired: it spreads
    off, _ = run(TaskingConfig(relay_hop_m=30.0))
    assert off[2] < 40.0 and off[0] == pytest.approx(46.0, abs=2)


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


def test_a_relay_on_its_way_goes_on_while_its_spot_is_called_for() -> None:
    """Relays re-targeted each spread period as robots fell silent and were heard again went
    to and fro and reached no spot (full mission seed 0: spots at 127, 147, 169 s). Known
    answer: contact to x 20; robot 1 silent at x 38 sends the disruptor to x ~21; a spread
    period on robot 1 is heard and robot 2 silent at x 1 (its spot x ~5): the disruptor
    goes on to x ~21 (kept for relay_keep_s); with relay_keep_s 0 (the default) it turns to
    x ~5."""

    def goal_after(cfg: TaskingConfig) -> float:
        s1, s2, d = robot(1, 5.0), robot(2, 5.0), robot(21, 12.0, Role.DISRUPTOR)
        s2.pose_in_map = (5.0, 2.0, 0.0)
        alloc = TaskAllocator(cfg)
        t = heard_along(alloc, s1, [s2, d], 20.0)
        s1.pose_in_map, s1.last_heard_s = (38.0, 3.0, 0.0), t - cfg.silent_after_s - 1.0
        alloc.assignments.pop(21, None)
        alloc._spread_at_s = -math.inf
        alloc.plan(state([s1, s2, d]), now_s=t)
        first = alloc.assignments[21].goal_in_map
        assert first is not None and first[0] == pytest.approx(21.0, abs=2.0)
        t += cfg.disruptor.spread_period_s + 1.0
        s1.last_heard_s = d.last_heard_s = t
        s2.pose_in_map, s2.last_heard_s = (1.0, 3.0, 0.0), t - cfg.silent_after_s - 1.0
        alloc.plan(state([s1, s2, d]), now_s=t)
        goal = alloc.assignments[21].goal_in_map
        assert goal is not None
        return goal[0]

    assert goal_after(ON) == pytest.approx(21.0, abs=2.0)
    assert goal_after(TaskingConfig(relay_hop_m=30.0)) < 8.0
