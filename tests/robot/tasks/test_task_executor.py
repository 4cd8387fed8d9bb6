"""The task executor: validation, replacement, pause/resume, neutralize and status reports."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.messages import (
    AutonomyMode,
    GoToTask,
    IdleTask,
    NeutralizeTask,
    PauseTask,
    RelayTask,
    ResumeTask,
    TaskState,
    TeleopTask,
)
from protocol.operator import OPERATOR_TASK_IDS_FROM
from robot.tasks.task_executor import TaskExecutor, TaskExecutorConfig

ORIGIN = np.zeros(3)


def states(reports: list) -> list[tuple[int, TaskState]]:
    return [(r.task_id, r.state) for r in reports]


def test_goto_advances_through_waypoints_and_succeeds() -> None:
    ex = TaskExecutor()
    assert states(ex.submit(GoToTask(1, 0.0, [(2.0, 0.0), (4.0, 0.0)]), 0.0, ORIGIN)) == [
        (1, TaskState.ACTIVE)
    ]
    assert ex.intent.mode is AutonomyMode.AUTONOMOUS
    assert ex.update(1.0, np.array([2.1, 0.0, 0.0])) == []
    assert np.allclose(ex.intent.waypoints_in_odom, [[4.0, 0.0]])
    assert states(ex.update(2.0, np.array([3.9, 0.1, 0.0]))) == [(1, TaskState.SUCCEEDED)]
    assert ex.intent.mode is AutonomyMode.IDLE and ex.current_task_id == 0


@pytest.mark.parametrize(
    ("task", "detail"),
    [
        (GoToTask(5, 0.0, [(1.0, 2.0), (math.nan, 0.0)]), "waypoints_in_odom[1][0] is not finite"),
        (GoToTask(5, 0.0, []), "waypoints_in_odom is empty"),
        (NeutralizeTask(5, 0.0, (math.inf, 0.0), 3.0, True), "target_in_odom[0] is not finite"),
        (NeutralizeTask(5, 0.0, (1.0, 0.0), -1.0, True), "standoff_m must be > 0"),
        (TeleopTask(5, 0.0, 9.0, 0.0, 1.0), "linear_m_s 9.0 exceeds"),
        (TeleopTask(5, 0.0, 0.5, 0.0, math.nan), "is not finite"),
        (RelayTask(5, 0.0, (0.0, math.nan)), "position_in_odom[1] is not finite"),
        ("not a task", "unknown task kind str"),
    ],
)
def test_bad_tasks_are_rejected_with_a_clear_status(task: object, detail: str) -> None:
    ex = TaskExecutor()
    ex.submit(GoToTask(1, 0.0, [(10.0, 0.0)]), 0.0, ORIGIN)
    (report,) = ex.submit(task, 1.0, ORIGIN)
    assert report.state is TaskState.REJECTED
    assert detail in report.detail
    assert ex.current_task_id == 1  # the current task goes on


def test_new_task_cancels_current_and_duplicate_ids_are_refused() -> None:
    ex = TaskExecutor()
    ex.submit(GoToTask(1, 0.0, [(10.0, 0.0)]), 0.0, ORIGIN)
    assert states(ex.submit(RelayTask(2, 1.0, (3.0, 3.0)), 1.0, ORIGIN)) == [
        (1, TaskState.CANCELED),
        (2, TaskState.ACTIVE),
    ]
    assert states(ex.submit(GoToTask(1, 2.0, [(1.0, 0.0)]), 2.0, ORIGIN)) == [
        (1, TaskState.REJECTED)
    ]
    assert states(ex.submit(IdleTask(3, 3.0), 3.0, ORIGIN)) == [
        (2, TaskState.CANCELED),
        (3, TaskState.SUCCEEDED),
    ]
    assert ex.intent.mode is AutonomyMode.IDLE


def test_pause_and_resume() -> None:
    ex = TaskExecutor()
    ex.submit(GoToTask(1, 0.0, [(10.0, 0.0)]), 0.0, ORIGIN)
    ex.submit(PauseTask(2, 1.0), 1.0, ORIGIN)
    assert ex.intent.mode is AutonomyMode.PAUSED
    assert ex.update(2.0, np.array([10.0, 0.0, 0.0])) == []  # paused: no progress
    ex.submit(ResumeTask(3, 3.0), 3.0, ORIGIN)
    assert ex.intent.mode is AutonomyMode.AUTONOMOUS
    assert states(ex.update(4.0, np.array([10.0, 0.0, 0.0]))) == [(1, TaskState.SUCCEEDED)]


def test_no_path_fails_after_timeout() -> None:
    ex = TaskExecutor()
    ex.submit(GoToTask(1, 0.0, [(10.0, 0.0)]), 0.0, ORIGIN)
    assert ex.update(1.0, ORIGIN, path_found=False) == []
    assert ex.update(20.0, ORIGIN, path_found=False) == []
    (report,) = ex.update(31.0, ORIGIN, path_found=False)
    assert report.state is TaskState.FAILED and "no path" in report.detail


def test_neutralize_needs_approval_and_15_s_of_line_of_sight() -> None:
    ex = TaskExecutor()
    target = (10.0, 0.0)
    ex.submit(NeutralizeTask(7, 0.0, target, 4.0, False), 0.0, ORIGIN)
    standoff = ex.intent.waypoints_in_odom[0]
    assert np.allclose(standoff, [6.0, 0.0])  # on the line from the robot, 4 m short
    at = np.array([6.0, 0.0, 0.0])
    (waiting,) = ex.update(5.0, at)
    assert "waiting for approval" in waiting.detail
    assert ex.intent.laser_target_in_odom is None  # never fires unapproved
    assert ex.update(30.0, at, laser_on_target=True) == []
    (approved,) = ex.submit(NeutralizeTask(7, 31.0, target, 4.0, True), 31.0, at)
    assert approved.detail == "approved by operator"
    assert ex.intent.laser_target_in_odom == target
    ex.update(32.0, at, laser_on_target=True)
    ex.update(40.0, at, laser_on_target=False)  # line of sight breaks: count restarts
    ex.update(41.0, at, laser_on_target=True)
    assert ex.update(55.0, at, laser_on_target=True) == []  # 14 s since the restart
    assert states(ex.update(56.0, at, laser_on_target=True)) == [(7, TaskState.SUCCEEDED)]


def test_neutralize_fails_when_the_laser_never_finds_its_target() -> None:
    """At the stand-off and approved, ``laser_search_s`` without the laser on target: FAILED
    (the robot sees no OOI there); a moment on target restarts the wait."""
    ex = TaskExecutor(TaskExecutorConfig(laser_search_s=20.0))
    ex.submit(NeutralizeTask(8, 0.0, (10.0, 0.0), 4.0, True), 0.0, ORIGIN)
    at = np.array([6.0, 0.0, 0.0])
    assert ex.update(5.0, at) == []  # arrived, approved: the search starts
    assert ex.update(15.0, at, laser_on_target=True) == []  # on target: restarts
    assert ex.update(16.0, at) == []
    assert ex.update(34.9, at) == []  # 19.9 s off target since
    (report,) = ex.update(35.0, at)
    assert report.state is TaskState.FAILED and "laser not on the target" in report.detail
    assert ex.intent.laser_target_in_odom is None


def test_teleop_runs_for_its_duration() -> None:
    ex = TaskExecutor()
    ex.submit(TeleopTask(4, 0.0, 0.5, 0.2, 3.0, conservative=True), 0.0, ORIGIN)
    intent = ex.intent
    assert intent.mode is AutonomyMode.TELEOPERATED
    assert intent.teleop == (0.5, pytest.approx(0.2)) and intent.conservative
    assert ex.update(2.9, ORIGIN) == []
    assert states(ex.update(3.0, ORIGIN)) == [(4, TaskState.SUCCEEDED)]


def test_relay_holds_position() -> None:
    ex = TaskExecutor()
    assert not ex.relaying
    ex.submit(RelayTask(9, 0.0, (5.0, 5.0)), 0.0, ORIGIN)
    assert ex.relaying  # the radio relays from the moment the task is taken
    (holding,) = ex.update(10.0, np.array([5.0, 5.2, 0.0]))
    assert holding.state is TaskState.ACTIVE and "relay" in holding.detail
    assert ex.update(100.0, np.array([5.0, 5.2, 0.0])) == []
    assert ex.current_task_id == 9 and ex.relaying
    # another task ends relay mode
    ex.submit(GoToTask(10, 101.0, [(0.0, 0.0)]), 101.0, np.array([5.0, 5.2, 0.0]))
    assert not ex.relaying


def test_operator_tasks_drive_semi_autonomously_until_the_planners_task_again() -> None:
    """An operator's goto (its id in the operators' range) is semi-autonomous (paper 6.2, 7);
    paused is paused; the planners' next task is autonomous again."""
    ex = TaskExecutor()
    op_id = OPERATOR_TASK_IDS_FROM + 7
    ex.submit(GoToTask(op_id, 0.0, [(10.0, 0.0)]), 0.0, ORIGIN)
    assert ex.intent.mode is AutonomyMode.SEMI_AUTONOMOUS and ex.intent.task_id == op_id
    ex.submit(PauseTask(op_id + 1, 1.0), 1.0, ORIGIN)
    assert ex.intent.mode is AutonomyMode.PAUSED
    ex.submit(ResumeTask(op_id + 2, 2.0), 2.0, ORIGIN)
    assert ex.intent.mode is AutonomyMode.SEMI_AUTONOMOUS
    ex.submit(RelayTask(op_id + 3, 3.0, (3.0, 3.0)), 3.0, ORIGIN)
    assert ex.intent.mode is AutonomyMode.SEMI_AUTONOMOUS
    ex.submit(GoToTask(1_000_001, 4.0, [(5.0, 0.0)]), 4.0, ORIGIN)  # the planners' again
    assert ex.intent.mode is AutonomyMode.AUTONOMOUS


def test_fail_ends_the_task_with_the_reason_and_needs_a_task() -> None:
    ex = TaskExecutor()
    assert ex.fail(1.0, "deadlocked") == []
    ex.submit(GoToTask(1, 0.0, [(10.0, 0.0)]), 0.0, ORIGIN)
    (status,) = ex.fail(2.0, "deadlocked: 2 back-offs in a row could not move the robot")
    assert status.task_id == 1 and status.state is TaskState.FAILED
    assert "could not move" in status.detail
    assert ex.current_task_id == 0 and ex.fail(3.0, "again") == []
