"""The robot node against the real simulator, in lockstep, in process."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from compression import decode_grid_with_header, read_header
from protocol.messages import (
    GoToTask,
    Hazard,
    HazardUpdate,
    ObjectKind,
    ParameterUpdate,
    PoseNode,
    RobotFrame,
    TaskState,
    TaskStatus,
    Telemetry,
    TerrainGrid,
)
from protocol.se2 import compose, relative
from robot.node import RobotNode
from sim.simulator import Simulator, load_world_config

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def sim() -> Iterator[Simulator]:
    with Simulator(load_world_config("configs/world/small.yaml")) as s:
        yield s


def run(sim: Simulator, node: RobotNode, seconds: float, until=None) -> None:
    driver = sim.driver(node.robot_id)
    for _ in range(int(round(seconds / sim.config.step_s))):
        sim.step()
        for command in node.process(driver.poll(0.0)):
            driver.send(command)
        if until is not None and until():
            return


def statuses(sent: list, task_id: int) -> list[TaskState]:
    return [m.state for m in sent if isinstance(m, TaskStatus) and m.task_id == task_id]


def test_goto_reaches_goal_and_reports_nodes_grids_and_telemetry(sim: Simulator) -> None:
    rid = sim.robot_ids[0]
    k = sim.robot_ids.index(rid)
    start = sim.robot_poses()[k].copy()
    sent: list = []
    node = RobotNode(rid, send=sent.append)
    node.handle_downlink(GoToTask(1, sim.time_s, [(4.0, 0.0)]))
    run(sim, node, 40.0, until=lambda: TaskState.SUCCEEDED in statuses(sent, 1))
    assert statuses(sent, 1) == [TaskState.ACTIVE, TaskState.SUCCEEDED]
    moved = relative(start, sim.robot_poses()[k])
    assert np.hypot(moved[0] - 4.0, moved[1]) < 0.75  # the goal's tolerance plus odometry error
    # odometry agrees with truth within 2% of the distance
    est = node.odometry.pose_in_odom
    assert np.hypot(*(est[:2] - moved[:2])) <= 0.02 * np.hypot(*moved[:2]) + 0.02
    # the sweeps aided the heading (laser-aided odometry) and it agrees with the truth
    assert node.stats.heading_matches >= 2
    assert abs(math.degrees(math.remainder(est[2] - moved[2], 2 * math.pi))) < 1.0
    nodes = [m for m in sent if isinstance(m, PoseNode)]
    grids = [m for m in sent if isinstance(m, TerrainGrid)]
    assert len(nodes) >= 2 and [n.node_index for n in nodes] == list(range(len(nodes)))
    assert [g.node_index for g in grids] == [n.node_index for n in nodes]
    spans = []
    for g in grids:
        occ, header = decode_grid_with_header(g.data)  # key frames: send() returned None
        assert occ.shape == (header.height, header.width) and occ.any()
        spans.append(max(header.height, header.width) * g.resolution_m)
    # the first node's grid (the staging area) reaches beyond the others' 15 m square
    assert spans[0] > 20.0 and max(spans[1:]) <= 15.0 + 1e-6
    pose = np.array(nodes[0].pose_in_odom)
    for n in nodes[1:]:  # the constraints chain to the reported poses
        pose = compose(pose, np.array(n.odom_delta))
        assert np.allclose(pose[:2], n.pose_in_odom[:2], atol=2e-3)
    assert any(isinstance(m, Telemetry) for m in sent)


def test_bad_tasks_and_messages_are_rejected_and_the_node_carries_on(sim: Simulator) -> None:
    rid = sim.robot_ids[1]
    sent: list = []
    node = RobotNode(rid, send=sent.append)
    node.handle_downlink(GoToTask(7, sim.time_s, [(1.0, math.nan)]))
    node.handle_downlink(ParameterUpdate("no.such.parameter", 3))
    node.handle_downlink(ParameterUpdate("codec", "nope"))
    run(sim, node, 1.0)
    rejected = [m for m in sent if isinstance(m, TaskStatus) and m.task_id == 7]
    assert [r.state for r in rejected] == [TaskState.REJECTED]
    assert "not finite" in rejected[0].detail
    assert node.stats.bad_messages == 2
    node.handle_downlink(ParameterUpdate("codec", "rle_zlib"))
    node.handle_downlink(GoToTask(8, sim.time_s, [(3.0, 0.0)]))
    run(sim, node, 30.0, until=lambda: TaskState.SUCCEEDED in statuses(sent, 8))
    assert statuses(sent, 8)[-1] is TaskState.SUCCEEDED
    grids = [m for m in sent if isinstance(m, TerrainGrid)]
    assert read_header(grids[-1].data).codec == "rle_zlib"


def test_never_enters_a_hazard_keepout_disk(sim: Simulator) -> None:
    rid = sim.robot_ids[2]
    k = sim.robot_ids.index(rid)
    start = sim.robot_poses()[k].copy()
    sent: list = []
    node = RobotNode(rid, send=sent.append)
    # the GCS's map is the simulator's world here; this robot's odom starts at its start pose
    # robots start in a cluster; the hazard sits on the straight line to the goal
    ooi_world = compose(start, np.array([6.0, 0.0, 0.0]))[:2]
    node.handle_downlink(
        HazardUpdate(
            sim.time_s,
            [Hazard(1, ObjectKind.STATIC_OOI, (float(ooi_world[0]), float(ooi_world[1])), 2.5)],
            [RobotFrame(rid, (float(start[0]), float(start[1]), float(start[2])))],
        )
    )
    node.handle_downlink(GoToTask(3, sim.time_s, [(12.0, 0.0)]))
    closest = math.inf
    driver = sim.driver(rid)
    for _ in range(int(60.0 / sim.config.step_s)):
        sim.step()
        for command in node.process(driver.poll(0.0)):
            driver.send(command)
        closest = min(closest, float(np.hypot(*(sim.robot_poses()[k][:2] - ooi_world))))
        if TaskState.SUCCEEDED in statuses(sent, 3):
            break
    assert closest >= 2.5 + 0.75  # the trigger distance plus the margin
    assert statuses(sent, 3)[-1] is TaskState.SUCCEEDED  # it went around, not home


def test_a_robot_inside_a_keepout_disk_drives_out_never_deeper(sim: Simulator) -> None:
    """A hazard reported 1.5 m from where the robot stands (inside its 3.25 m disk): the
    robot leaves for a goal on the far side of it, never closer than it started (the
    whole disk as an obstacle left it no start cell: it sat there, goal after goal)."""
    rid = sim.robot_ids[3]
    k = sim.robot_ids.index(rid)
    start = sim.robot_poses()[k].copy()
    sent: list = []
    node = RobotNode(rid, send=sent.append)
    run(sim, node, 0.5)
    here = sim.robot_poses()[k].copy()
    ooi_world = compose(here, np.array([0.0, 1.5, 0.0]))[:2]
    node.handle_downlink(
        HazardUpdate(
            sim.time_s,
            [Hazard(1, ObjectKind.STATIC_OOI, (float(ooi_world[0]), float(ooi_world[1])), 2.5)],
            [RobotFrame(rid, (float(start[0]), float(start[1]), float(start[2])))],
        )
    )
    goal_odom = relative(start, compose(here, np.array([4.0, -3.0, 0.0])))[:2]
    node.handle_downlink(GoToTask(4, sim.time_s, [(float(goal_odom[0]), float(goal_odom[1]))]))
    closest = math.inf
    driver = sim.driver(rid)
    for _ in range(int(40.0 / sim.config.step_s)):
        sim.step()
        for command in node.process(driver.poll(0.0)):
            driver.send(command)
        closest = min(closest, float(np.hypot(*(sim.robot_poses()[k][:2] - ooi_world))))
        if TaskState.SUCCEEDED in statuses(sent, 4):
            break
    assert statuses(sent, 4)[-1] is TaskState.SUCCEEDED
    assert closest >= 1.5 - 0.2  # odometry and control error, not a step towards it


def test_cheap_perception_steps_are_timed_every_nth_call_and_counted_n_times(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import time

    from robot.node import RobotNodeConfig

    with pytest.raises(ValueError, match="perception_cpu_sample_every"):
        RobotNodeConfig(perception_cpu_sample_every=0)
    with pytest.raises(ValueError, match="scan_odometry_grid_cells"):
        RobotNodeConfig(scan_odometry_grid_cells=1)
    node = RobotNode(0, send=[].append, config=RobotNodeConfig(perception_cpu_sample_every=4))
    reads: list[float] = []
    real = time.thread_time

    def counted() -> float:
        reads.append(real())
        return reads[-1]

    monkeypatch.setattr("robot.node.time.thread_time", counted)

    def busy() -> None:
        t0 = real()
        while real() - t0 < 0.002:  # 2 ms of CPU
            pass

    for _ in range(8):
        node._perceive(busy, sampled="control")
    assert len(reads) == 4  # calls 0 and 4 of that kind, two reads each
    assert 8 * 0.002 * 0.8 <= node.stats.perception_cpu_s <= 8 * 0.002 * 3
    node._perceive(busy)  # an unsampled step is always timed
    assert len(reads) == 6
