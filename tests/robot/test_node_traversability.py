"""Issue 4: slippery ground learned from measured versus requested speed (AOJRF Eq. 1) makes
the planner go around a sand patch when the detour is cheap.

A robot drives 18 m straight across a 4 m x 3 m sand patch (25% extra wheel slip) and back.
Going out it has no experience and crosses the patch; matching consecutive LIDAR sweeps
against pillars along the way measures how much less than its wheels it moved
(:mod:`robot.odometry.scan_displacement`), which the traversability map keeps. Coming back,
the planner's Dijkstra pays for that ground and takes the short detour around it; with the
traversability penalty off it drives straight through again.
"""

from __future__ import annotations

import numpy as np
import pytest

from protocol.messages import GoToTask, TaskState, TaskStatus
from robot.control.traversability import TraversabilityConfig
from robot.node import RobotNode, RobotNodeConfig
from sim.simulator import Simulator, SimulatorConfig
from tests.sim.simworlds import box, make_world

pytestmark = pytest.mark.slow

SAND = (12.0, 8.5, 16.0, 11.5)  # x0, y0, x1, y1 in the world


def out_and_back(penalty: float) -> tuple[RobotNode, np.ndarray]:
    """Drive out and back; returns the node and the world track of the way back."""
    solids = []
    for x in np.arange(2.0, 29.0, 3.0):  # pillars both sides: something to match sweeps on
        solids += [
            box("pillar", x, 4.0, x + 0.4, 4.4, 1.5),
            box("pillar", x, 15.6, x + 0.4, 16.0, 1.5),
        ]
    world = make_world(
        solids=solids,
        robots=[(4.0, 10.0, 0.0, "sensor")],
        size_m=(30.0, 20.0),
        sand=[(*SAND, 0.25)],
    )
    config = RobotNodeConfig(traversability=TraversabilityConfig(penalty=penalty))
    with Simulator(world, config=SimulatorConfig(seed=0)) as sim:
        sent: list = []
        node = RobotNode(0, send=sent.append, config=config)
        node.handle_downlink(GoToTask(1, 0.0, [(18.0, 0.0)]))  # odom starts at (4, 10)
        driver = sim.driver(0)
        back: list[np.ndarray] = []

        def states(task: int) -> list[TaskState]:
            return [m.state for m in sent if isinstance(m, TaskStatus) and m.task_id == task]

        for _ in range(int(120.0 / sim.config.step_s)):
            sim.step()
            for command in node.process(driver.poll(0.0)):
                driver.send(command)
            if TaskState.SUCCEEDED in states(1) and not states(2):
                node.handle_downlink(GoToTask(2, sim.time_s, [(0.0, 0.0)]))
            if states(2):
                back.append(sim.robot_poses()[0][:2].copy())
            if TaskState.SUCCEEDED in states(2):
                break
        assert states(1)[-1] is TaskState.SUCCEEDED and states(2)[-1] is TaskState.SUCCEEDED
        return node, np.array(back)


def in_sand(track: np.ndarray, margin_m: float) -> np.ndarray:
    x0, y0, x1, y1 = SAND
    return (
        (track[:, 0] > x0 + margin_m)
        & (track[:, 0] < x1 - margin_m)
        & (track[:, 1] > y0 + margin_m)
        & (track[:, 1] < y1 - margin_m)
    )


def test_learned_slip_makes_the_way_back_go_around_the_sand() -> None:
    node, back = out_and_back(penalty=TraversabilityConfig().penalty)
    tm = node.traversability
    assert node.stats.slip_measurements >= 10
    # in odom (origin at the start, x along the track): the patch is x in [8, 12]
    assert max(tm.t_at(x, 0.0) for x in (9.0, 10.0, 11.0)) < 0.92  # slippery, learned
    assert min(tm.t_at(x, 0.0) for x in (2.0, 4.0, 16.0)) > 0.95  # hard ground: no slip
    assert not in_sand(back, margin_m=0.3).any()  # around it, not through it

    _, straight = out_and_back(penalty=0.0)  # the same run without the learned cost
    assert in_sand(straight, margin_m=0.3).any()
