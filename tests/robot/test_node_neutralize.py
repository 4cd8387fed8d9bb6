"""A disruptor's node neutralizes a static OOI the GCS placed off by its map's error (issue 14):
the laser aims at the robot's own detection of the OOI near the GCS's target, not at the
target itself (a 0.25 m-radius object is missed by a ray aimed 0.7 m beside it)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from protocol.messages import NeutralizeTask, ObjectKind, TaskState, TaskStatus
from protocol.se2 import relative
from protocol.sensors import LaserPointerCommand
from robot.node import RobotNode, RobotNodeConfig
from sim.simulator import Simulator
from sim.world_generator import Ooi
from tests.sim.simworlds import make_world

pytestmark = pytest.mark.slow

OOI_RGBA = (1.0, 0.3, 0.0, 1.0)
START = np.array([3.0, 10.0, 0.0])
OOI_XY = (10.0, 8.0)


def _neutralize(config: RobotNodeConfig, seconds: float = 70.0) -> tuple[list[Any], list[str]]:
    world = make_world(
        robots=((*START, "disruptor"),),
        oois=(Ooi(1, "static_ooi", OOI_XY, 0.25, 0.8, OOI_RGBA),),
    )
    sent: list[Any] = []
    with Simulator(world) as sim:
        node = RobotNode(0, send=sent.append, config=config)
        truth = relative(START, np.array([*OOI_XY, 0.0]))[:2]
        # the GCS's estimate: 0.7 m off the OOI, across the line of approach
        target = (float(truth[0]), float(truth[1]) + 0.7)
        node.handle_downlink(NeutralizeTask(1, 0.0, target, 3.5, True))
        driver = sim.driver(0)
        end_s = seconds
        while sim.time_s < end_s:
            sim.step()
            for command in node.process(driver.poll(0.0)):
                driver.send(command)
            done = any(isinstance(m, TaskStatus) and m.state is TaskState.SUCCEEDED for m in sent)
            if done and end_s == seconds:
                end_s = sim.time_s + 1.0  # the simulator's rules see the laser's last step
        events = [str(e) for e in sim.events]
    return sent, events


def test_the_laser_finds_the_ooi_the_gcs_placed_off_by_its_map_error() -> None:
    sent, events = _neutralize(RobotNodeConfig())
    states = [m.state for m in sent if isinstance(m, TaskStatus) and m.task_id == 1]
    assert TaskState.SUCCEEDED in states, states
    assert any("neutralized" in e and "static_ooi:1" in e for e in events), events
    assert not any("detonat" in e or "disabled" in e for e in events), events


def test_with_no_ooi_of_its_own_near_the_target_it_does_not_fire_and_fails() -> None:
    """The same task with no own detection close enough (laser_snap_m tiny): the laser stays
    off (a hold on the GCS's target, empty ground, was reported a success) and the task fails
    after ``laser_search_s``."""
    sent, events = _neutralize(RobotNodeConfig(laser_snap_m=1e-6))
    assert not any("neutralized" in e for e in events), events
    reports = [m for m in sent if isinstance(m, TaskStatus) and m.task_id == 1]
    assert reports[-1].state is TaskState.FAILED, reports
    assert "laser not on the target" in reports[-1].detail


# A stand-off 5.5 m from the OOI, the robot facing away (the OOI in the LIDAR's blind sector
# behind it), with its own detection of the OOI made long before: odometry drift since turned
# it 6 deg about the robot (0.58 m), as in the small world's missed neutralizations.
STANDOFF_START = np.array([4.0, 10.0, np.pi])
FAR_OOI_XY = (9.5, 10.0)
STALE_BEARING_RAD = np.deg2rad(6.0)


def _stale_detection_scene(
    *, ooi_present: bool, seconds: float = 40.0
) -> tuple[list[Any], list[str], list[Any]]:
    world = make_world(
        robots=((*STANDOFF_START, "disruptor"),),
        oois=(Ooi(1, "static_ooi", FAR_OOI_XY, 0.25, 0.8, OOI_RGBA),) if ooi_present else (),
    )
    sent: list[Any] = []
    lasers: list[Any] = []
    with Simulator(world) as sim:
        node = RobotNode(0, send=sent.append, config=RobotNodeConfig())
        truth = relative(STANDOFF_START, np.array([*FAR_OOI_XY, 0.0]))[:2]
        c, s = np.cos(STALE_BEARING_RAD), np.sin(STALE_BEARING_RAD)
        stale = np.array([[c, -s], [s, c]]) @ truth  # the same range, 6 deg off
        assert node.perception is not None
        for k in range(12):  # a detection fused from many sightings: it hardly moves now
            node.perception.registry.observe(
                int(ObjectKind.STATIC_OOI),
                stale,
                np.eye(2) * 0.1**2,
                radius_m=0.25,
                height_m=0.8,
                time_s=-20.0 + k,
            )
        node.handle_downlink(NeutralizeTask(1, 0.0, (float(stale[0]), float(stale[1])), 5.5, True))
        driver = sim.driver(0)
        end_s = seconds
        while sim.time_s < end_s:
            sim.step()
            for command in node.process(driver.poll(0.0)):
                if isinstance(command, LaserPointerCommand):
                    lasers.append(command)
                driver.send(command)
            done = any(
                isinstance(m, TaskStatus)
                and m.task_id == 1
                and m.state in (TaskState.SUCCEEDED, TaskState.FAILED)
                for m in sent
            )
            if done and end_s == seconds:
                end_s = sim.time_s + 1.0  # the simulator's rules see the laser's last step
        events = [str(e) for e in sim.events]
    return sent, events, lasers


def test_a_stale_detection_6_deg_off_is_re_detected_at_the_stand_off_and_hit() -> None:
    """The robot turns to face its detection, sees the OOI again with its LIDAR and aims at
    that fresh sighting: the simulator counts the neutralization (aimed at the old detection,
    the beam passes 0.58 m beside a 0.25 m-radius OOI)."""
    sent, events, lasers = _stale_detection_scene(ooi_present=True)
    reports = [m for m in sent if isinstance(m, TaskStatus) and m.task_id == 1]
    assert reports[-1].state is TaskState.SUCCEEDED, reports
    assert any("neutralized" in e and "static_ooi:1" in e for e in events), events
    # the robot turned round to face the OOI before the laser held on it
    on = [cmd for cmd in lasers if cmd.on]
    assert on and abs(on[-1].pan_rad) < 0.5, on[-1:]


def test_at_a_stand_off_where_it_sees_no_ooi_the_task_fails_saying_so() -> None:
    """The same stale detection with no OOI there: the laser never comes on, and the task
    fails (the GCS may send it again) rather than reporting a neutralization."""
    sent, events, lasers = _stale_detection_scene(ooi_present=False)
    reports = [m for m in sent if isinstance(m, TaskStatus) and m.task_id == 1]
    assert reports[-1].state is TaskState.FAILED, reports
    assert "not seen from the stand-off" in reports[-1].detail, reports[-1]
    assert not any(cmd.on for cmd in lasers), lasers
    assert not any("neutralized" in e for e in events), events
