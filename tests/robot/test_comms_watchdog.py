"""The comms watchdog (issue 17): silent -> task goes on -> hold or return -> resume."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from protocol.config import load_config
from protocol.messages import AutonomyMode, GoToTask, HazardUpdate, TaskState
from robot.comms_watchdog import CommsWatchdog, CommsWatchdogConfig, LinkAwareTasks, LinkState
from robot.node import RobotNodeConfig

POSE = np.zeros(3)


def _beat(tasks: LinkAwareTasks, t: float, pose: np.ndarray = POSE) -> None:
    tasks.heard(t, pose, HazardUpdate(t, [], []))


def test_states_follow_the_quiet_time_and_any_message_brings_it_back() -> None:
    wd = CommsWatchdog(CommsWatchdogConfig(silence_s=10.0, task_grace_s=20.0, policy="hold"))
    for t in (0.0, 2.0):
        wd.heard(t, POSE, periodic=True)
    assert wd.armed
    assert wd.update(11.9, POSE) is LinkState.CONNECTED
    assert wd.update(12.0, POSE) is LinkState.SILENT and wd.silent_since_s == 12.0
    assert wd.update(31.9, POSE) is LinkState.SILENT
    assert wd.update(32.0, POSE) is LinkState.HOLDING
    assert wd.heard(60.0, POSE) is LinkState.HOLDING  # a task, not a broadcast: still contact
    assert wd.update(60.05, POSE) is LinkState.CONNECTED


def test_unarmed_watchdog_never_declares_silence() -> None:
    """A ground side that handed one task and never repeats itself is no basis for silence."""
    wd = CommsWatchdog()
    wd.heard(0.0, POSE, periodic=True)
    wd.heard(0.0, POSE)  # the task with it
    assert wd.update(1000.0, POSE) is LinkState.CONNECTED and not wd.armed
    off = CommsWatchdog(CommsWatchdogConfig(enabled=False))
    for t in (0.0, 2.0):
        off.heard(t, POSE, periodic=True)
    assert off.update(1000.0, POSE) is LinkState.CONNECTED


def test_hold_suspends_the_task_reports_it_and_resumes_it() -> None:
    # a robot stuck without a path is still given waypoints: hold at the grace, not the limit
    cfg = CommsWatchdogConfig(
        silence_s=5.0, task_grace_s=5.0, task_limit_s=5.0, policy="hold", drain_hold_frac=0.2
    )
    tasks = LinkAwareTasks(config=cfg)
    _beat(tasks, 0.0)
    _beat(tasks, 2.0)
    assert [s.state for s in tasks.submit(GoToTask(7, 2.0, [(20.0, 0.0)]), 2.0, POSE)] == [
        TaskState.ACTIVE
    ]
    goal = tasks.intent.waypoints_in_odom.copy()
    reports = []
    for k in range(0, 400):  # 20 s without a word
        t = 2.0 + 0.05 * k
        reports += tasks.update(t, POSE, path_found=False)
        if t < 7.0:
            assert tasks.intent.mode is AutonomyMode.AUTONOMOUS
    assert tasks.state is LinkState.HOLDING
    intent = tasks.intent
    assert intent.mode is AutonomyMode.PAUSED and len(intent.waypoints_in_odom) == 0
    assert intent.task_id == 7
    _beat(tasks, 22.0)
    # back after 20 s silent, with an uplink backlog: it first stands at most 0.2 * 20 = 4 s
    reports += tasks.update(22.0, POSE, uplink_backlog_bytes=3000)
    assert tasks.state is LinkState.CONNECTED and tasks.watchdog.draining
    assert tasks.intent.mode is AutonomyMode.PAUSED and tasks.intent.task_id == 7
    reports += tasks.update(25.95, POSE, uplink_backlog_bytes=3000)
    assert tasks.intent.mode is AutonomyMode.PAUSED
    reports += tasks.update(26.0, POSE, uplink_backlog_bytes=3000)
    assert not tasks.watchdog.draining
    assert np.array_equal(tasks.intent.waypoints_in_odom, goal)  # resumed, not failed
    details = [r.detail for r in reports if r.task_id == 7]
    assert [d.split(":")[0] for d in details] == [
        "link silent for 5.0 s",
        "link silent for 10.0 s",
        "link back after 20.0 s silent (resuming the task once the uplink backlog is through "
        "(at most 4.0 s))",
    ], details
    # suspended time did not count as a missing path: the 30 s no-path timeout never ran
    assert all(r.state is TaskState.ACTIVE for r in reports)


def test_return_drives_back_along_its_points_of_contact_then_holds() -> None:
    cfg = CommsWatchdogConfig(
        silence_s=5.0, task_grace_s=0.0, task_limit_s=0.0, return_after_s=0.0, policy="return"
    )
    tasks = LinkAwareTasks(config=cfg)
    earlier, contact = np.array([0.0, 0.0, 0.0]), np.array([3.0, -1.0, 0.0])
    _beat(tasks, 0.0, earlier)
    tasks.heard(1.0, earlier + [0.5, 0.0, 0.0])  # within return_spacing_m: not kept
    _beat(tasks, 2.0, contact)
    tasks.submit(GoToTask(1, 2.0, [(50.0, 0.0)]), 2.0, contact)
    away = np.array([10.0, 4.0, 0.0])
    tasks.update(7.5, away)
    assert tasks.state is LinkState.RETURNING
    intent = tasks.intent
    assert intent.mode is AutonomyMode.AUTONOMOUS and intent.task_id == 1
    assert np.allclose(intent.waypoints_in_odom, [[3.0, -1.0]])
    # at the last point of contact and still silent (a shadow's sharp edge): further back
    tasks.update(20.0, contact + [0.3, 0.2, 0.0])
    assert tasks.state is LinkState.RETURNING
    assert np.allclose(tasks.intent.waypoints_in_odom, [[0.0, 0.0]])
    tasks.update(30.0, earlier + [0.2, 0.1, 0.0])
    assert tasks.state is LinkState.HOLDING and tasks.intent.mode is AutonomyMode.PAUSED
    _beat(tasks, 31.0, earlier)
    tasks.update(31.0, earlier)
    assert tasks.state is LinkState.CONNECTED
    assert np.allclose(tasks.intent.waypoints_in_odom, [[50.0, 0.0]])  # the task again


def test_a_driving_task_goes_on_through_a_silence_then_holds_then_returns() -> None:
    """An outage in time costs the robot nothing while its task has ground to cover: it
    drives on, holds when the goal is reached, and backs out only after ``return_after_s``."""
    cfg = CommsWatchdogConfig(
        silence_s=5.0, task_grace_s=5.0, task_limit_s=60.0, return_after_s=30.0, policy="return"
    )
    tasks = LinkAwareTasks(config=cfg)
    _beat(tasks, 0.0)
    _beat(tasks, 2.0)
    tasks.submit(GoToTask(3, 2.0, [(20.0, 0.0)]), 2.0, POSE)
    x, reports = 0.0, []
    for k in range(1, 401):  # 0.1 s steps at 1 m/s towards the goal, never heard
        t = 2.0 + 0.1 * k
        reports += tasks.update(t, np.array([x, 0.0, 0.0]))
        if tasks.intent.mode is AutonomyMode.AUTONOMOUS and tasks.state is not LinkState.RETURNING:
            x = min(20.0, x + 0.1)
        if t <= 21.0:  # silent from 7 s, the grace over at 12 s: still driving to the goal
            assert tasks.state in (LinkState.CONNECTED, LinkState.SILENT), t
    assert [r.state for r in reports if r.task_id == 3][-1] is TaskState.SUCCEEDED
    assert x >= 19.0  # it got there (within the waypoint tolerance), 18 s into the silence
    wd = tasks.watchdog
    assert wd.state is LinkState.RETURNING  # lost at 7 s: back from 37 s on
    assert np.allclose(tasks.intent.waypoints_in_odom, [[0.0, 0.0]])
    stuck = CommsWatchdog(cfg)
    for t in (0.0, 2.0):
        stuck.heard(t, POSE, periodic=True)
    assert stuck.update(60.0, POSE, task_driving=True) is LinkState.SILENT  # 53 s lost
    away = np.array([10.0, 0.0, 0.0])
    assert stuck.update(67.0, away, task_driving=True) is LinkState.RETURNING  # the limit


def test_config_rejects_unknown_keys_and_bad_values(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "robot.yaml"
    path.write_text("comms:\n  policy: hold\n  silence_s: 8\n")
    assert load_config(path, RobotNodeConfig).comms.policy == "hold"
    path.write_text("comms:\n  policy: return\n  silense_s: 8\n")
    with pytest.raises(Exception, match="silense_s"):
        load_config(path, RobotNodeConfig)
    with pytest.raises(msgspec.ValidationError, match="policy"):
        msgspec.convert({"policy": "wander"}, CommsWatchdogConfig)
    with pytest.raises(msgspec.ValidationError, match="silence_s"):
        msgspec.convert({"silence_s": 0}, CommsWatchdogConfig)
    with pytest.raises(msgspec.ValidationError, match="task_limit_s"):
        msgspec.convert({"task_grace_s": 30, "task_limit_s": 10}, CommsWatchdogConfig)


def test_a_robot_whose_task_ended_in_a_silence_returns_at_once() -> None:
    """Small world 300 s: sensor robots finished their goals in radio shadows and stood idle
    28-76 s until ``return_after_s``; without a task there is nothing to wait for."""
    cfg = CommsWatchdogConfig(
        silence_s=5.0, task_grace_s=5.0, task_limit_s=60.0, return_after_s=60.0, policy="return"
    )
    tasks = LinkAwareTasks(config=cfg)
    _beat(tasks, 0.0)
    _beat(tasks, 2.0)
    tasks.submit(GoToTask(3, 2.0, [(10.0, 0.0)]), 2.0, POSE)
    goal = np.array([10.0, 0.0, 0.0])
    tasks.update(8.0, np.array([6.0, 0.0, 0.0]))
    assert tasks.state is LinkState.SILENT  # lost at 7 s, driving on
    reports = tasks.update(9.0, goal)  # there: the task ends 2 s into the silence
    assert [r.state for r in reports if r.task_id == 3][-1] is TaskState.SUCCEEDED
    tasks.update(9.05, goal)
    assert tasks.state is LinkState.RETURNING  # not 60 s later
    intent = tasks.intent
    assert intent.mode is AutonomyMode.AUTONOMOUS
    assert np.allclose(intent.waypoints_in_odom, [[0.0, 0.0]])
    # a robot idle before the silence goes back as soon as the link counts as lost
    idle = LinkAwareTasks(config=cfg)
    _beat(idle, 0.0)
    _beat(idle, 2.0)
    idle.update(6.9, goal)
    assert idle.state is LinkState.CONNECTED
    idle.update(7.0, goal)
    assert idle.state is LinkState.RETURNING
    # with a wait configured, it waits that long from the later of the two
    slow = LinkAwareTasks(config=msgspec.structs.replace(cfg, idle_return_after_s=3.0))
    _beat(slow, 0.0)
    _beat(slow, 2.0)
    slow.update(7.0, goal)
    assert slow.state is LinkState.SILENT
    slow.update(9.9, goal)
    assert slow.state is LinkState.SILENT
    slow.update(10.0, goal)
    assert slow.state is LinkState.RETURNING


def test_a_point_of_contact_not_reached_in_time_is_passed_over_for_the_next() -> None:
    """Odometry drift can put a point of contact in a wall: a robot returning to it drove to
    and fro 175 s, 2 m short (small world seed 7). After ``return_point_s`` it tries the next
    point back, and holds at the end of the trail."""
    cfg = CommsWatchdogConfig(
        silence_s=5.0,
        task_grace_s=0.0,
        task_limit_s=0.0,
        return_after_s=0.0,
        return_point_s=10.0,
        policy="return",
    )
    wd = CommsWatchdog(cfg)
    wd.heard(0.0, np.array([0.0, 0.0, 0.0]), periodic=True)
    wd.heard(2.0, np.array([3.0, 0.0, 0.0]), periodic=True)
    stuck = np.array([8.0, 2.0, 0.0])
    assert wd.update(7.0, stuck) is LinkState.RETURNING
    assert np.allclose(np.asarray(wd.return_target_in_odom), [3.0, 0.0])
    assert wd.update(16.9, stuck) is LinkState.RETURNING
    assert np.allclose(np.asarray(wd.return_target_in_odom), [3.0, 0.0])
    assert wd.update(17.0, stuck) is LinkState.RETURNING
    assert np.allclose(np.asarray(wd.return_target_in_odom), [0.0, 0.0])  # the next back
    assert wd.update(26.9, stuck) is LinkState.RETURNING
    assert wd.update(27.0, stuck) is LinkState.HOLDING  # the trail is used up


def test_drain_hold_ends_with_the_backlog_or_a_new_silence_and_is_capped() -> None:
    """Back in contact after a silence, the robot stands where it heard the GCS while what it
    produced meanwhile goes up: ``drain_hold_frac`` of the silence, at most
    ``drain_hold_max_s``; a reported empty backlog ends it at once, a new silence too."""
    cfg = CommsWatchdogConfig(
        silence_s=5.0,
        task_grace_s=5.0,
        task_limit_s=5.0,
        policy="hold",
        drain_hold_frac=0.2,
        drain_hold_max_s=12.0,
    )

    def silent_then_back(back_s: float) -> LinkAwareTasks:
        tasks = LinkAwareTasks(config=cfg)
        _beat(tasks, 0.0)
        _beat(tasks, 2.0)
        tasks.submit(GoToTask(7, 2.0, [(20.0, 0.0)]), 2.0, POSE)
        for k in range(int((back_s - 2.0) / 0.5)):
            tasks.update(2.0 + 0.5 * k, POSE)
        assert tasks.state is LinkState.HOLDING
        _beat(tasks, back_s)
        return tasks

    # 100 s silent: 0.2 * 100 = 20 s, capped at 12 s
    tasks = silent_then_back(102.0)
    for t in (104.0, 106.0, 108.0, 110.0, 112.0):  # the GCS heard on: the hold is not restarted
        _beat(tasks, t)
        tasks.update(t, POSE, uplink_backlog_bytes=4000)
    tasks.update(113.9, POSE, uplink_backlog_bytes=4000)
    assert tasks.watchdog.draining and tasks.intent.mode is AutonomyMode.PAUSED
    assert tasks.watchdog.suspended  # no task failure or no-path timeout while it stands
    tasks.update(114.0, POSE, uplink_backlog_bytes=4000)
    assert not tasks.watchdog.draining
    assert tasks.intent.mode is not AutonomyMode.PAUSED and len(tasks.intent.waypoints_in_odom)
    # the node reports its backlog: empty ends the hold at once
    tasks = silent_then_back(102.0)
    tasks.update(103.0, POSE, uplink_backlog_bytes=1500)
    assert tasks.watchdog.draining
    tasks.update(104.0, POSE, uplink_backlog_bytes=0)
    assert not tasks.watchdog.draining and len(tasks.intent.waypoints_in_odom)
    tasks.update(105.0, POSE, uplink_backlog_bytes=900)  # new data: not a new hold
    assert not tasks.watchdog.draining
    # silent again while it stands: the hold ends, the silence rules take over
    tasks = silent_then_back(32.0)  # 30 s silent: 6 s hold, then nothing heard for 5 s
    tasks.update(36.9, POSE, uplink_backlog_bytes=800)
    assert tasks.watchdog.draining
    tasks.update(37.0, POSE, uplink_backlog_bytes=800)
    assert tasks.state is LinkState.SILENT and not tasks.watchdog.draining
    # a node that does not report its backlog: no hold
    tasks = silent_then_back(102.0)
    tasks.update(102.5, POSE)
    assert not tasks.watchdog.draining and len(tasks.intent.waypoints_in_odom)
    # off: resumes at once
    off = LinkAwareTasks(config=msgspec.structs.replace(cfg, drain_hold_frac=0.0))
    _beat(off, 0.0)
    _beat(off, 2.0)
    off.submit(GoToTask(7, 2.0, [(20.0, 0.0)]), 2.0, POSE)
    for k in range(60):
        off.update(2.0 + 0.5 * k, POSE)
    _beat(off, 40.0)
    off.update(40.0, POSE, uplink_backlog_bytes=5000)
    assert not off.watchdog.draining and len(off.intent.waypoints_in_odom)
    with pytest.raises(ValueError, match="drain_hold_frac"):
        CommsWatchdogConfig(drain_hold_frac=1.5)
    with pytest.raises(ValueError, match="drain_hold_max_s"):
        CommsWatchdogConfig(drain_hold_max_s=-1.0)
