"""A robot holding still backs away from a hostile walking at it, and comes back after
(issue 14: small world seed 0 lost two robots to a hostile that walked onto the robot
watching it). Real PyBullet: the robot sees the hostile with its own LIDAR and camera."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from protocol.messages import (
    GoToTask,
    Hazard,
    HazardUpdate,
    ObjectKind,
    RelayTask,
    RobotFrame,
    TaskStatus,
)
from robot.control.hostile_evasion import EvasionConfig
from robot.node import RobotNode, RobotNodeConfig
from sim.simulator import Simulator
from sim.world_generator import Human
from tests.sim.simworlds import make_world

pytestmark = pytest.mark.slow

# keep_view is off by default (robot.control.hostile_evasion: its measurement)
KEEP_VIEW = RobotNodeConfig(evasion=EvasionConfig(keep_view=True))

HOSTILE_RGBA = (0.9, 0.05, 0.05, 1.0)
START = (8.0, 10.0, 0.0)
# the hostile walks straight through where the robot holds, then away round a loop
ROUTE = ((20.0, 10.3), (1.0, 10.3), (1.0, 2.0), (20.0, 2.0))


def test_a_holding_robot_backs_out_of_an_approaching_hostiles_radius_and_returns() -> None:
    world = make_world(
        robots=((*START, "sensor"),),
        humans=(Human(1, "hostile", ROUTE, 0.6, 0.25, 1.7, HOSTILE_RGBA),),
    )
    sent: list[Any] = []
    closest_m = math.inf
    with Simulator(world) as sim:
        node = RobotNode(0, send=sent.append)
        node.handle_downlink(RelayTask(1, 0.0, (0.0, 0.0)))  # hold where it stands
        driver = sim.driver(0)
        while sim.time_s < 42.0:
            sim.step()
            for command in node.process(driver.poll(0.0)):
                driver.send(command)
            robot = sim.robot_poses()[0]
            hostile = sim.routes.positions(sim.time_s)[0]
            closest_m = min(closest_m, math.hypot(*(robot[:2] - hostile)))
        events = [str(e) for e in sim.events]
        end = sim.robot_poses()[0]
    assert not events, events  # no detonation, no robot lost
    # it kept out of the blast radius (5 m; the trigger is 2.5 m); holding still, the
    # hostile walked through where it stood
    assert closest_m > 5.0, closest_m
    assert node.stats.evasions >= 1
    details = [m.detail for m in sent if isinstance(m, TaskStatus) and m.task_id == 1]
    assert any("backing away" in d for d in details), details
    assert any("resuming the task" in d for d in details), details
    # and it came back to hold where its task had it
    assert float(np.hypot(end[0] - START[0], end[1] - START[1])) < 0.75, end


# a walker the camera cannot colour (grey): the robot knows a hostile only from the GCS's
# hazard where it was seen, and its LIDAR's unlabelled person track (issue 14: small world
# seeds 3, 7, 11 at 66f8349, robots drove head-on at an uncoloured walker to 4.8, 3.4 and
# 2.9 m; the trigger is 2.5 m, the blast 5 m)
GREY_RGBA = (0.5, 0.5, 0.5, 1.0)


def _run(
    robot: tuple[float, float, float],
    route: tuple[tuple[float, float], ...],
    task: Any,
    *,
    until_s: float,
    heard_until_s: float = math.inf,
) -> tuple[float, list[str], RobotNode]:
    """A robot at ``robot`` (world = map) with ``task``, the GCS's hazard of a hostile at
    the route's start heard every second until ``heard_until_s``; the grey walker walks
    ``route``. Returns the closest robot-walker distance, the rule events and the node."""
    world = make_world(
        robots=((*robot, "sensor"),),
        humans=(Human(1, "hostile", route, 0.6, 0.25, 1.7, GREY_RGBA),),
        size_m=(40.0, 20.0),
    )
    closest_m = math.inf
    with Simulator(world) as sim:
        node = RobotNode(0, send=lambda _m: None)
        frames = [RobotFrame(0, robot)]
        hazard = Hazard(7, ObjectKind.HOSTILE, route[0], 5.0)
        node.handle_downlink(HazardUpdate(0.0, [hazard], frames))
        node.handle_downlink(task)
        driver = sim.driver(0)
        next_heard = 1.0
        while sim.time_s < until_s:
            sim.step()
            if sim.time_s >= next_heard and sim.time_s <= heard_until_s:
                node.handle_downlink(HazardUpdate(sim.time_s, [hazard], frames))
                next_heard += 1.0
            for command in node.process(driver.poll(0.0)):
                driver.send(command)
            pose = sim.robot_poses()[0]
            walker = sim.routes.positions(sim.time_s)[0]
            closest_m = min(closest_m, math.hypot(*(pose[:2] - walker)))
        return closest_m, [str(e) for e in sim.events], node


@pytest.mark.parametrize("heard_until_s", [math.inf, 4.0], ids=["heard", "silent"])
def test_a_driving_robot_keeps_out_of_an_uncoloured_walkers_blast_coming_head_on(
    heard_until_s: float,
) -> None:
    # the robot's goal is 26 m east along the walker's way; the walker comes west at it
    # (silent: the GCS is not heard after 4 s; the robot drives its task on, alone)
    route = ((30.0, 10.0), (2.0, 10.0))
    goal = GoToTask(1, 0.0, [(26.0, 0.0)])
    closest_m, events, node = _run(
        (4.0, 10.0, 0.0), route, goal, until_s=30.0, heard_until_s=heard_until_s
    )
    assert not events, events
    assert node.stats.evasions >= 1
    assert closest_m > 5.0, closest_m


def test_a_holding_robot_keeps_out_of_an_uncoloured_walker_coming_from_behind() -> None:
    # the robot holds facing east; the walker comes from 11 m behind it (west), the LIDAR's
    # blind quarter, through where it holds
    route = ((0.5, 10.2), (30.0, 10.2))
    closest_m, events, node = _run(
        (11.5, 10.0, 0.0), route, RelayTask(1, 0.0, (0.0, 0.0)), until_s=40.0
    )
    assert not events, events
    assert node.stats.evasions >= 1
    assert closest_m > 5.0, closest_m


def test_a_robot_with_no_task_follows_a_walker_leaving_its_view() -> None:
    # issue 14: the rules' lock needs the walker in view (within 12 m) for 30 s; a watcher
    # that holds where the GCS sent it loses a walker walking on within seconds. Here the
    # red walker starts 8 m east of an idle robot and walks east for 30 s (18 m)
    start = (6.0, 10.0, 0.0)
    route = ((14.0, 10.0), (38.0, 10.0))
    world = make_world(
        robots=((*start, "sensor"),),
        humans=(Human(1, "hostile", route, 0.6, 0.25, 1.7, HOSTILE_RGBA),),
        size_m=(40.0, 20.0),
    )
    closest_m, far_s = math.inf, 0.0
    with Simulator(world) as sim:
        node = RobotNode(0, send=lambda _m: None, config=KEEP_VIEW)
        driver = sim.driver(0)
        while sim.time_s < 30.0:
            sim.step()
            for command in node.process(driver.poll(0.0)):
                driver.send(command)
            pose = sim.robot_poses()[0]
            d = math.hypot(*(pose[:2] - sim.routes.positions(sim.time_s)[0]))
            closest_m = min(closest_m, d)
            far_s += sim.config.step_s if d > 12.0 else 0.0  # out of the rules' lock range
        events = [str(e) for e in sim.events]
    assert not events, events
    assert node.stats.keep_view_starts >= 1
    assert closest_m > 5.0, closest_m
    # holding where it stood it would be 26 m off at the end, out of range from 10 s on
    assert far_s <= 3.0, far_s


def test_a_robot_at_its_view_watches_on_through_a_silence_instead_of_going_back() -> None:
    # issue 14: a watcher sent to a view of a hostile falls silent there (the small world's
    # walker patrols a radio shadow); with no task left it went back to its last point of
    # radio contact at once, away from the walker. The GCS is heard until 3 s; the robot
    # drives 10 m east to its view, 10 m short of the hostile the GCS told it of
    start = (4.0, 10.0, 0.0)
    world = make_world(robots=((*start, "sensor"),), size_m=(40.0, 20.0))
    with Simulator(world) as sim:
        node = RobotNode(0, send=lambda _m: None, config=KEEP_VIEW)
        frames = [RobotFrame(0, start)]
        hazard = Hazard(7, ObjectKind.HOSTILE, (24.0, 10.0), 5.0)
        node.handle_downlink(GoToTask(1, 0.0, [(10.0, 0.0)]))
        driver = sim.driver(0)
        next_heard = 1.0
        while sim.time_s < 45.0:
            sim.step()
            if next_heard <= sim.time_s <= 3.0:
                node.handle_downlink(HazardUpdate(sim.time_s, [hazard], frames))
                next_heard += 1.0
            for command in node.process(driver.poll(0.0)):
                driver.send(command)
        end = sim.robot_poses()[0]
    assert node.tasks.state.name != "CONNECTED"  # the link is silent
    assert node.tasks.current_task_id == 0  # its goal reached
    # it stayed at its view, 10 m off the hostile, not back at the point of contact
    assert float(np.hypot(end[0] - 14.0, end[1] - 10.0)) < 1.5, end
