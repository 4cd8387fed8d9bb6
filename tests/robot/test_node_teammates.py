"""Issue 4: two robots meeting head-on in a corridor both get through.

Each robot plans alone over its own short-memory map, where the other is only an obstacle
(and a trail of old obstacle marks). The corridor, 2 m wide and 18 m long between solid
blocks, is the only way: the robots meet in it, wait, one backs off out of it
(:mod:`robot.control.deadlock`), the other passes, then the first goes.
"""

from __future__ import annotations

import math

import pytest

from protocol.messages import GoToTask, TaskState, TaskStatus
from robot.node import RobotNode
from sim.simulator import Simulator, SimulatorConfig
from tests.sim.simworlds import box, make_world

pytestmark = pytest.mark.slow


def test_two_robots_meeting_in_a_corridor_both_get_through() -> None:
    width, y = 2.0, 9.0
    solids = [
        box("wall", 6.0, 0.0, 24.0, y - width / 2, 2.0),
        box("wall", 6.0, y + width / 2, 24.0, 20.0, 2.0),
    ]
    world = make_world(
        solids=solids,
        robots=[(2.0, y, 0.0, "sensor"), (28.0, y, math.pi, "sensor")],
        size_m=(30.0, 20.0),
    )
    with Simulator(world, config=SimulatorConfig(seed=0)) as sim:
        sent: dict[int, list] = {rid: [] for rid in sim.robot_ids}
        nodes = {rid: RobotNode(rid, send=sent[rid].append) for rid in sim.robot_ids}
        for rid in sim.robot_ids:  # each to the other's start, 26 m ahead in its own frame
            nodes[rid].handle_downlink(GoToTask(1, 0.0, [(26.0, 0.0)]))
        drivers = {rid: sim.driver(rid) for rid in sim.robot_ids}

        def states(rid: int) -> list[TaskState]:
            return [m.state for m in sent[rid] if isinstance(m, TaskStatus)]

        for _ in range(int(240.0 / sim.config.step_s)):
            sim.step()
            for rid in sim.robot_ids:
                for command in nodes[rid].process(drivers[rid].poll(0.0)):
                    drivers[rid].send(command)
            if all(TaskState.SUCCEEDED in states(rid) for rid in sim.robot_ids):
                break
        for rid in sim.robot_ids:
            assert states(rid) == [TaskState.ACTIVE, TaskState.SUCCEEDED], (rid, states(rid))
        # they did meet: at least one of them detected the deadlock and backed off
        assert sum(n.stats.deadlocks for n in nodes.values()) >= 1
        assert not sim.events
