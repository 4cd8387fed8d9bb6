"""The autonomous mission end to end (issue 14): simulator, robot nodes and the real GCS over
real zenoh sessions in lockstep; the GCS's allocation, not a script, drives the robots."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from gcs.mapping.rasterization import UNKNOWN
from gcs.mission_control import MissionControlConfig
from gcs.tasking.allocator import TaskingConfig
from mission.assembly import Assembly
from mission.run import RunConfig, RunReport, run_mission
from protocol.messages import GoToTask
from protocol.se2 import transform_points

pytestmark = pytest.mark.slow

CUT_ROBOT = 1  # its radio goes dark at CUT_S: the GCS must write it off and plan without it
CUT_S = 16.0


class _Watch:
    """Follows the run from outside: every task the GCS sent (with the map it was planned on),
    the known area over time; cuts robot CUT_ROBOT's uplink at CUT_S (a radio dead zone)."""

    def __init__(self) -> None:
        self.tasks: list[tuple[float, int, Any, np.ndarray | None]] = []  # t, robot, task, goal
        self.known_m2: list[tuple[float, float]] = []
        self.starts: np.ndarray | None = None
        self.wrapped = False
        self.unknown_at_goal: list[float] = []
        self.control: Any = None

    def __call__(self, asm: Assembly) -> None:
        assert asm.gcs is not None
        sim, control = asm.sim, asm.gcs.control
        if not self.wrapped:
            self.wrapped = True
            self.control = control
            self.starts = sim.robot_poses().copy()
            deliver = asm.gcs.on_message

            def cut(robot_id: int, msg: Any) -> None:
                if robot_id == CUT_ROBOT and sim.time_s >= CUT_S:
                    return  # lost in the air: the GCS never hears it
                deliver(robot_id, msg)

            asm.gcs.on_message = cut  # type: ignore[method-assign]
            control_plan = control.plan

            def plan(now_s: float) -> list[tuple[int, Any]]:
                out = control_plan(now_s)
                occupancy = control.station.rasterize()
                for rid, task in out:
                    goal = None
                    if isinstance(task, GoToTask):
                        mfo = control.station.graph.map_from_odom(rid)
                        goal = transform_points(mfo, np.asarray(task.waypoints_in_odom[-1]))
                        a = control.allocator.assignments[rid]
                        if a.purpose == "explore" and a.goal_in_map is not None:
                            # the frontier goal (the task then comes back towards contact)
                            goal = np.asarray(a.goal_in_map)
                            self.unknown_at_goal.append(_unknown_near(occupancy, goal, 2.0))
                    self.tasks.append((now_s, rid, task, goal))
                return out

            control.plan = plan  # type: ignore[method-assign]
        if round(sim.time_s / sim.config.step_s) % 40 == 0:
            occ = control.station.rasterize()
            known = np.count_nonzero(occ.values != UNKNOWN) * occ.resolution_m**2
            self.known_m2.append((sim.time_s, float(known)))


def _unknown_near(occupancy: Any, xy: np.ndarray, radius_m: float) -> float:
    """Fraction of the cells within ``radius_m`` of ``xy`` that the map does not know (cells
    outside the map count as unknown)."""
    res = occupancy.resolution_m
    n = int(math.ceil(radius_m / res))
    offsets = np.arange(-n, n + 1) * res
    gx, gy = np.meshgrid(offsets, offsets)
    inside = np.hypot(gx, gy) <= radius_m
    pts = np.stack([gx[inside] + xy[0], gy[inside] + xy[1]], axis=1)
    cells = occupancy.cells_of(pts)
    rows, cols = occupancy.shape
    ok = (cells[:, 0] >= 0) & (cells[:, 0] < rows) & (cells[:, 1] >= 0) & (cells[:, 1] < cols)
    unknown = np.ones(len(pts), dtype=bool)
    unknown[ok] = occupancy.values[cells[ok, 0], cells[ok, 1]] == UNKNOWN
    return float(unknown.mean())


@pytest.fixture(scope="module")
def mission() -> tuple[RunReport, _Watch]:
    watch = _Watch()
    tasking = TaskingConfig(silent_after_s=3.0, lost_after_s=6.0)
    config = RunConfig(
        duration_s=36.0,
        seed=5,
        mission=MissionControlConfig(plan_period_s=1.0, tasking=tasking),
    )
    report = run_mission(config, on_step=watch)
    return report, watch


def test_the_gcs_allocation_drives_the_robots_into_unexplored_space(mission) -> None:
    report, watch = mission
    assert report.mission_s == pytest.approx(36.0)
    assert not report.scripted and report.gcs["gcs_linked"] == 4  # staging plan links them
    # every task came from the allocator (its ids), explore goals on the edge of the unknown
    assert watch.tasks and all(t.task_id >= 1_000_000 for _, _, t, _ in watch.tasks)
    explore = [(t, rid) for t, rid, task, goal in watch.tasks if goal is not None]
    assert {rid for _, rid in explore} >= {0, 1, 2}  # every sensor robot got a goal
    assert len(watch.unknown_at_goal) >= 3
    assert np.median(watch.unknown_at_goal) > 0.2  # a frontier: much unknown around the goal
    # and they went there: the map grew, the robots drove away from the staging area
    assert watch.starts is not None
    first_known = next(m2 for t, m2 in watch.known_m2 if m2 > 0)
    assert watch.known_m2[-1][1] > 1.5 * first_known
    moved = [
        report.robots[rid].distance_m for rid in (0, 2)
    ]  # the sensor robots the GCS kept hearing
    assert min(moved) > 5.0, moved


def test_a_robot_lost_to_the_radio_is_written_off_and_the_others_plan_on(mission) -> None:
    report, watch = mission
    lost_at = [
        float(e.split(" s ", 1)[0])
        for e in report.tasking_events
        if f"robot_lost: robot {CUT_ROBOT}" in e
    ]
    assert lost_at, report.tasking_events
    # declared lost about lost_after_s after its last message
    assert CUT_S + 5.0 <= lost_at[0] <= CUT_S + 9.0
    assert any(f"robot_silent: robot {CUT_ROBOT}" in e for e in report.tasking_events)
    # nothing is sent to it once it is lost; the others keep getting tasks afterwards
    assert not [t for t, rid, _, _ in watch.tasks if rid == CUT_ROBOT and t > lost_at[0]]
    later = {rid for t, rid, _, _ in watch.tasks if t > CUT_S}
    assert later & {0, 2}, watch.tasks
    # its task is released: the planners no longer count on it
    a = watch.control.allocator.assignments.get(CUT_ROBOT)
    assert a is None or a.purpose.endswith(":released"), a
