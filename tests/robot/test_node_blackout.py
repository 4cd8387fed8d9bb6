"""Issue 17: a robot through a 60 s radio blackout, in lockstep over real zenoh.

One robot in an open field, a ground side that acts like the GCS on the radio (its
frame/hazard broadcast every 2 s, one long GoTo task) and counts what arrives. The simulator
turns the robot's radio off for 60 s (``SimulatorConfig.radio_blackouts``). The robot keeps
driving its task while the link is silent, holds after ``silence_s + task_limit_s`` (here
equal to ``task_grace_s``: the task is far from done), resumes
when the radio returns, and every pose node and terrain grid it made arrives afterwards, once
each and in order.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from mission.lockstep import TeamInLockstep, seed_streams
from protocol.messages import (
    GoToTask,
    HazardUpdate,
    PoseNode,
    RobotFrame,
    TaskState,
    TaskStatus,
    TerrainGrid,
)
from protocol.radio import RadioConfig
from robot.comms_watchdog import CommsWatchdogConfig, LinkState
from robot.node import RobotNodeConfig
from sim.simulator import Simulator, SimulatorConfig
from tests.sim.simworlds import make_world

pytestmark = pytest.mark.slow

BLACKOUT_START_S, BLACKOUT_S = 12.0, 60.0
END_S = BLACKOUT_START_S + BLACKOUT_S + 12.0


@pytest.mark.parametrize("policy", ["hold", "return"])
def test_robot_through_a_60_s_blackout_delivers_everything_afterwards(policy: str) -> None:
    world = make_world(robots=[(5.0, 20.0, 0.0, "sensor")], size_m=(140.0, 40.0))
    sim_cfg = SimulatorConfig(seed=0, radio_blackouts=((0, BLACKOUT_START_S, BLACKOUT_S),))
    comms = CommsWatchdogConfig(
        silence_s=10.0,
        task_grace_s=15.0,
        task_limit_s=15.0,
        return_after_s=15.0,
        policy=policy,  # type: ignore[arg-type]
    )
    robot_cfg = RobotNodeConfig(comms=comms)
    arrived: list[tuple[float, Any]] = []
    with Simulator(world, config=sim_cfg, radio=RadioConfig()) as sim:
        team = TeamInLockstep(
            sim,
            radio=RadioConfig(),
            seeds=seed_streams(0),
            on_ground_message=lambda rid, msg: arrived.append((sim.time_s, msg)),
            robot_config=robot_cfg,
        )
        with team:
            node = team.nodes[0]
            channel = team.radios[0].channel
            last_beat = -math.inf
            task_sent = False
            states: list[tuple[float, LinkState]] = []
            truth: list[tuple[float, np.ndarray]] = []
            held_max = 0

            def ground() -> None:  # the GCS's side of the radio, as the GCS does it
                nonlocal last_beat, task_sent
                now = sim.time_s
                if now - last_beat >= 2.0:
                    team.ground.broadcast(HazardUpdate(now, [], [RobotFrame(0, (0.0, 0.0, 0.0))]))
                    last_beat = now
                if not task_sent and now >= 4.0:
                    team.ground.send(0, GoToTask(1, now, [(120.0, 0.0)]))
                    task_sent = True

            while sim.time_s < END_S:
                team.step(ground)
                states.append((sim.time_s, node.tasks.state))
                truth.append((sim.time_s, sim.robot_poses()[0][:2].copy()))
                held_max = max(held_max, channel.held_bytes)

    def at(t: float) -> np.ndarray:
        return next(p for s, p in truth if s >= t)

    def first(state: LinkState) -> float:
        return next(t for t, s in states if s is state)

    # the link goes silent silence_s after the last broadcast heard, the policy applies
    # task_grace_s later, the first broadcast after the blackout brings it back
    silent_s, suspended_s = (
        first(LinkState.SILENT),
        first(LinkState.HOLDING if policy == "hold" else LinkState.RETURNING),
    )
    back_s = next(t for t, s in states if t > suspended_s and s is LinkState.CONNECTED)
    assert BLACKOUT_START_S + 10.0 - 2.5 <= silent_s <= BLACKOUT_START_S + 10.0 + 0.1
    assert suspended_s - silent_s == pytest.approx(15.0, abs=0.1)
    assert BLACKOUT_START_S + BLACKOUT_S <= back_s <= BLACKOUT_START_S + BLACKOUT_S + 2.5
    # the task went on while the link was silent ...
    assert np.linalg.norm(at(suspended_s) - at(BLACKOUT_START_S)) > 10.0
    if policy == "hold":  # ... then it stood still ...
        assert np.linalg.norm(at(back_s - 0.1) - at(suspended_s + 2.0)) < 0.3
    else:  # ... or drove back towards where it last heard the GCS ...
        assert (
            np.linalg.norm(at(back_s - 0.1) - at(BLACKOUT_START_S))
            < np.linalg.norm(at(suspended_s) - at(BLACKOUT_START_S)) - 5.0
        )
    # ... and went on with its task once the link was back
    assert np.linalg.norm(at(END_S - 0.1) - at(back_s + 2.0)) > 3.0

    # everything it made arrived, after the blackout, once each and in order
    nodes = [m.node_index for _, m in arrived if isinstance(m, PoseNode)]
    grids = [m.node_index for _, m in arrived if isinstance(m, TerrainGrid)]
    assert node.stats.pose_nodes > 20
    assert nodes == list(range(node.stats.pose_nodes)), nodes
    assert len(grids) == node.stats.terrain_grids and grids == sorted(grids)
    late = [t for t, m in arrived if isinstance(m, PoseNode) and t > BLACKOUT_START_S + BLACKOUT_S]
    assert len(late) >= 10  # the blackout's nodes came afterwards
    during = [
        (t, type(m).__name__)
        for t, m in arrived
        if BLACKOUT_START_S + 0.1 < t < BLACKOUT_START_S + BLACKOUT_S - 1e-6
    ]
    assert not during, during
    # the operators learn afterwards what the robot did (reliable task status, in order)
    details = [m.detail for _, m in arrived if isinstance(m, TaskStatus) and m.task_id == 1]
    expected = ["continuing the task", "holding" if policy == "hold" else "returning to"]
    if policy == "return" and "holding at" in details[-2]:  # reached the oldest point kept
        expected.append("holding at")
    assert len(details) == len(expected) + 2, details
    for detail, words in zip(details[1:-1], expected, strict=True):
        assert detail.startswith("link silent") and words in detail, details
    assert details[-1].startswith("link back after") and "resuming the task" in details[-1]
    assert all(m.state is TaskState.ACTIVE for _, m in arrived if isinstance(m, TaskStatus)), (
        details
    )
    print(f"policy {policy}: {len(nodes)} nodes, {len(grids)} grids, held max {held_max} B")
