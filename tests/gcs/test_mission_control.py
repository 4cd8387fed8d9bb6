"""The GCS's estimate and planners composed: tasks from what the robots sent, in each robot's
private frame; roles; estimation-only mode; lost robots (issue 14)."""

from __future__ import annotations

import numpy as np
import pytest

from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.mapping.rasterization import UNKNOWN
from gcs.mission_control import MissionControl, MissionControlConfig, tasking_state
from gcs.tasking.allocator import Role, TaskingConfig, TaskingEvent
from protocol.messages import AutonomyMode, GoToTask, HazardUpdate, Telemetry
from protocol.se2 import compose, transform_points
from tests.gcs.test_ground_station import grid_msg, nodes_along, straight

#: Where robot 1's private frame starts in map (robot 0's): the deployment plan's hint.
MAP_FROM_ODOM1 = np.array([0.0, 3.0, 0.0])


def _wall_grid() -> np.ndarray:
    g = np.zeros((60, 60), dtype=bool)
    g[5, :] = True  # a wall 2.5 m to the right of each node
    return g


def _team(config: MissionControlConfig, robots: tuple[int, ...] = (0, 1, 2)) -> MissionControl:
    station = GroundStation(GroundStationConfig(robots=robots))
    for rid in robots[1:]:
        station.add_start_hint(
            rid,
            map_from_odom=MAP_FROM_ODOM1 * rid,
            sigma_xy_m=0.05,
            sigma_yaw_rad=0.01,
        )
    control = MissionControl(station, config)
    for rid in robots:
        feed(control, rid, 0.0, upto=4)
    return control


def feed(control: MissionControl, rid: int, now_s: float, *, upto: int) -> None:
    """Robot ``rid``'s first ``upto`` pose nodes (along +x in its odom), grids, telemetry."""
    path = straight(upto)
    for msg in nodes_along(path):
        control.handle(rid, msg, now_s=now_s)
        control.handle(rid, grid_msg(msg.node_index, _wall_grid()), now_s=now_s)
    t = Telemetry(now_s, tuple(path[-1]), (0.0, 0.0), (0.0, 0.0), 1.0, AutonomyMode.IDLE, 0)  # type: ignore[arg-type]
    control.handle(rid, t, now_s=now_s)


def heard(control: MissionControl, rid: int, now_s: float) -> None:
    path = straight(4)
    t = Telemetry(now_s, tuple(path[-1]), (0.0, 0.0), (0.0, 0.0), 1.0, AutonomyMode.IDLE, 0)  # type: ignore[arg-type]
    control.handle(rid, t, now_s=now_s)


def test_goals_go_to_the_frontier_in_each_robots_private_frame() -> None:
    control = _team(MissionControlConfig(plan_period_s=1.0))
    out = control.step(now_s=1.0, budget_s=float("inf"))
    frames = [m for _, m in out if isinstance(m, HazardUpdate)]
    tasks = {rid: m for rid, m in out if isinstance(m, GoToTask)}
    assert frames and set(tasks) == {0, 1, 2}
    occupancy = control.station.rasterize()
    for rid, task in tasks.items():
        wps_in_map = transform_points(MAP_FROM_ODOM1 * rid, np.asarray(task.waypoints_in_odom))
        goal = control.allocator.assignments[rid].goal_in_map
        assert goal is not None
        # out to the goal (then back towards where the robot was heard)
        assert np.hypot(*(wps_in_map - np.asarray(goal)).T).min() < 1e-3
        end = np.asarray(goal)
        # the goal is on the edge of what the map knows: unknown cells within 1.5 m of it
        res = occupancy.resolution_m
        offsets = np.stack(np.meshgrid(np.arange(-15, 16), np.arange(-15, 16)), -1).reshape(-1, 2)
        cells = occupancy.cells_of(end) + offsets[:, ::-1]
        rows, cols = occupancy.shape
        inside = (
            (cells[:, 0] >= 0) & (cells[:, 0] < rows) & (cells[:, 1] >= 0) & (cells[:, 1] < cols)
        )
        unknown = ~inside.all() or np.any(
            occupancy.values[cells[inside, 0], cells[inside, 1]] == UNKNOWN
        )
        assert unknown, (rid, end, res)
        start = compose(MAP_FROM_ODOM1 * rid, straight(4)[-1])[:2]
        assert np.hypot(*(end - start)) > 2.0  # away from where the robot is
    assert dict(control.tasks_sent) == {0: 1, 1: 1, 2: 1}
    # the next plan is not due before plan_period_s; nothing new is sent for goals in flight
    assert not [m for _, m in control.step(now_s=1.5, budget_s=1.0) if isinstance(m, GoToTask)]


def test_roles_come_from_the_roster_and_estimation_only_sends_no_task() -> None:
    control = _team(MissionControlConfig(disruptors=(2,)))
    state = tasking_state(control.station, control.roles)
    assert {r.robot_id: r.role for r in state.robots} == {
        0: Role.SENSOR,
        1: Role.SENSOR,
        2: Role.DISRUPTOR,
    }
    assert all(r.pose_in_map is not None and r.map_from_odom is not None for r in state.robots)
    assert state.occupancy.values.size and len(state.trajectory_keys) == 12
    out = control.step(now_s=1.0, budget_s=1.0)
    sent = {rid for rid, m in out if isinstance(m, GoToTask)}
    purposes = {rid: control.allocator.assignments[rid].purpose for rid in sent}
    explore = {rid for rid, purpose in purposes.items() if purpose == "explore"}
    assert explore == {0, 1}  # a disruptor does not explore ...
    # ... it may only be spread over the highway (it joins it from its start since dc4f09f)
    assert purposes.get(2, "spread") == "spread"
    quiet = _team(MissionControlConfig(enabled=False))
    assert not [
        m for _, m in quiet.step(now_s=1.0, budget_s=1.0) if not isinstance(m, HazardUpdate)
    ]


def test_a_robot_that_falls_silent_is_written_off_and_gets_nothing_more() -> None:
    events: list[TaskingEvent] = []
    tasking = TaskingConfig(silent_after_s=3.0, lost_after_s=6.0)
    control = _team(MissionControlConfig(plan_period_s=1.0, tasking=tasking))
    control.on_event = events.append
    first = control.step(now_s=1.0, budget_s=1.0)
    assert {rid for rid, m in first if isinstance(m, GoToTask)} == {0, 1, 2}
    sent_after: list[int] = []
    for t in np.arange(2.0, 12.0, 1.0):
        for rid in (0, 2):  # robot 1 is never heard again
            heard(control, rid, float(t))
        sent_after += [
            rid
            for rid, m in control.step(now_s=float(t), budget_s=1.0)
            if not isinstance(m, HazardUpdate)
        ]
    kinds = [(e.kind, e.robot_id) for e in events]
    assert ("robot_silent", 1) in kinds and ("robot_lost", 1) in kinds
    lost_at = next(e.time_s for e in events if e.kind == "robot_lost")
    assert 6.0 < lost_at - 0.0 <= 8.0  # lost_after_s after its last message (at t = 0)
    assert 1 not in sent_after
    a = control.allocator.assignments.get(1)
    assert a is None or a.purpose.endswith(":released")
    assert control.journal[-1] is events[-1]


def test_the_area_of_operations_blocks_everything_outside_it() -> None:
    from gcs.mapping.rasterization import FREE, OCCUPIED, OccupancyMap
    from gcs.mission_control import bounded

    occ = OccupancyMap(np.full((40, 60), FREE, dtype=np.int8), (-1.0, -2.0), 0.1)
    area = ((0.0, 0.0), (4.0, 0.0), (4.0, 1.5), (0.0, 1.5))
    out = bounded(occ, area)
    assert (occ.values == FREE).all()  # the input is unchanged
    centres_x = -1.0 + (np.arange(60) + 0.5) * 0.1
    centres_y = -2.0 + (np.arange(40) + 0.5) * 0.1

    def within(margin: float) -> np.ndarray:
        ok_y = (centres_y[:, None] > margin) & (centres_y[:, None] < 1.5 - margin)
        return ok_y & (centres_x[None, :] > margin) & (centres_x[None, :] < 4.0 - margin)

    # exact to within a cell on the boundary
    assert (out.values[within(0.1)] == FREE).all()
    assert (out.values[~within(-0.1)] == OCCUPIED).all()
    assert bounded(occ, ()) is occ
    with pytest.raises(ValueError, match="area_in_map: expected 3 or more finite"):
        MissionControlConfig(area_in_map=((0.0, 0.0), (1.0, float("nan")), (2.0, 0.0)))


def test_no_frontier_beyond_the_area_of_operations() -> None:
    """A robot by the site's edge: the free disc the map draws beyond the edge is not
    explored towards; inside the bound, goals go where the map is unknown."""
    area = ((-1.0, -3.0), (12.0, -3.0), (12.0, 3.0), (-1.0, 3.0))
    control = _team(MissionControlConfig(area_in_map=area), robots=(0,))
    out = control.step(now_s=1.0, budget_s=1.0)
    goals = [m for _, m in out if isinstance(m, GoToTask)]
    assert len(goals) == 1
    wps = np.asarray(goals[0].waypoints_in_odom)
    assert ((-1.0 < wps[:, 0]) & (wps[:, 0] < 12.0)).all(), wps
    assert ((-3.0 < wps[:, 1]) & (wps[:, 1] < 3.0)).all(), wps
    assert wps[:, 0].max() > 4.0  # along the corridor, where the map does not reach yet
