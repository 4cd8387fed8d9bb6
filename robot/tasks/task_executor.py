"""Task execution on the robot: the GCS says *what*, the robot decides *how* (paper 4.1, 5.1).

Tasks arrive from the downlink already expressed in the robot's private frame ``odom``. The
executor validates them, keeps the current one, reports every state change as a
:class:`~protocol.messages.TaskStatus`, and exposes an :class:`Intent` that the robot node turns
into planning and motion:

* ``GoToTask``: drive through the waypoints; succeeds at the last one; fails after
  ``no_path_timeout_s`` without a path (the short sensor memory may clear a bad map first).
* ``NeutralizeTask`` (paper 2): drive to a stand-off point ``standoff_m`` from the static OOI,
  then, only once ``approved``, hold the laser pointer on it; 15 s of continuous line of sight
  succeed, a break resets the count. Re-sending the same task id with ``approved=True`` is how
  the operator approves.
* ``RelayTask``: drive to the position and hold there (active until replaced); the robot's
  radio is in relay mode meanwhile (:attr:`TaskExecutor.relaying`: it forwards teammates'
  traffic to the GCS, paper 4.1's robots used as relays).
* ``TeleopTask``: drive at the given velocities for the duration (conservative: the node stops
  before obstacles); ``PauseTask``/``ResumeTask`` freeze and continue the current task;
  ``IdleTask`` cancels it.

A new task replaces the current one (which is reported ``CANCELED``). Bad tasks (non-finite
numbers, no waypoints, speeds beyond limits, an unknown kind) are ``REJECTED`` with a detail
that names the problem; the current task continues.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from protocol.messages import (
    AutonomyMode,
    GoToTask,
    IdleTask,
    NeutralizeTask,
    PauseTask,
    RelayTask,
    ResumeTask,
    TaskState,
    TaskStatus,
    TeleopTask,
)
from protocol.operator import is_operator_task

__all__ = ["Intent", "TaskExecutor", "TaskExecutorConfig"]


class TaskExecutorConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    waypoint_tolerance_m: float = 0.5
    standoff_tolerance_m: float = 0.75
    laser_hold_s: float = 15.0  # paper 2: the disruptor's laser must stay on for 15 s
    # at the stand-off and approved, the laser never on target this long: the task fails,
    # saying why (the robot has no OOI of its own near the GCS's target, or does not see it
    # from the stand-off); the GCS may send it again. 20 s: the robot turns to face the OOI
    # in a few seconds and its LIDAR sweeps every 1.25 s; a neutralization the GCS sends at
    # the stand-off times out there after 30 s + the 15 s hold
    laser_search_s: float = 20.0
    no_path_timeout_s: float = 30.0
    max_teleop_linear_m_s: float = 1.5
    max_teleop_angular_rad_s: float = 2.0
    max_teleop_duration_s: float = 30.0


@dataclass
class Intent:
    """What the node should do now, in ``odom``.

    ``waypoints_in_odom``: remaining goals ``(K, 2)`` for the planner (empty: stay);
    ``teleop``: ``(linear_m_s, angular_rad_s)`` to apply directly (None: autonomous);
    ``laser_target_in_odom``: where to point the laser (None: laser off).
    """

    mode: AutonomyMode = AutonomyMode.IDLE
    task_id: int = 0
    waypoints_in_odom: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    teleop: tuple[float, float] | None = None
    conservative: bool = True
    laser_target_in_odom: tuple[float, float] | None = None


@dataclass
class _Active:
    task: Any
    waypoints: np.ndarray
    started_s: float
    paused: bool = False
    arrived: bool = False  # at the last waypoint / stand-off / relay point
    approved: bool = False
    los_since_s: float | None = None
    no_path_since_s: float | None = None
    ready_since_s: float | None = None  # at the stand-off and approved (neutralization)


def _finite(name: str, values: Any) -> str | None:
    arr = np.asarray(values, dtype=np.float64)
    if arr.size and not np.all(np.isfinite(arr)):
        bad = np.argwhere(~np.isfinite(arr))[0]
        idx = "".join(f"[{int(i)}]" for i in bad) if arr.ndim else ""
        return f"{name}{idx} is not finite"
    return None


class TaskExecutor:
    """The robot's current task and its status reports (see the module docstring)."""

    def __init__(self, config: TaskExecutorConfig | None = None) -> None:
        self.config = config or TaskExecutorConfig()
        self._active: _Active | None = None
        self._seen: set[int] = set()

    @property
    def current_task_id(self) -> int:
        return 0 if self._active is None else self._active.task.task_id

    @property
    def relaying(self) -> bool:
        """Whether the current task is a :class:`RelayTask` (paused or not: a relay holding
        still forwards): the radio's relay mode."""
        return self._active is not None and isinstance(self._active.task, RelayTask)

    # ------------------------------------------------------------------ input

    def submit(self, task: Any, now_s: float, pose_in_odom: np.ndarray) -> list[TaskStatus]:
        """Take a task from the downlink; returns the status reports it causes."""
        task_id = getattr(task, "task_id", 0)
        if not isinstance(
            task,
            GoToTask | NeutralizeTask | RelayTask | TeleopTask | PauseTask | ResumeTask | IdleTask,
        ):
            return [
                self._status(
                    task_id, TaskState.REJECTED, now_s, f"unknown task kind {type(task).__name__}"
                )
            ]
        act = self._active
        if isinstance(task, NeutralizeTask) and act is not None and act.task.task_id == task_id:
            return self._update_neutralize(act, task, now_s)
        if task_id in self._seen:
            return [self._status(task_id, TaskState.REJECTED, now_s, "duplicate task id")]
        problem = self._validate(task)
        if problem is not None:
            return [self._status(task_id, TaskState.REJECTED, now_s, problem)]
        self._seen.add(task_id)
        out: list[TaskStatus] = []
        if isinstance(task, PauseTask | ResumeTask):
            if act is None:
                return [
                    self._status(task_id, TaskState.REJECTED, now_s, "no task to pause or resume")
                ]
            act.paused = isinstance(task, PauseTask)
            out.append(self._status(task_id, TaskState.SUCCEEDED, now_s))
            detail = "paused" if act.paused else "resumed"
            out.append(self._status(act.task.task_id, TaskState.ACTIVE, now_s, detail))
            return out
        if act is not None:
            out.append(
                self._status(
                    act.task.task_id, TaskState.CANCELED, now_s, f"replaced by task {task_id}"
                )
            )
            self._active = None
        if isinstance(task, IdleTask):
            out.append(self._status(task_id, TaskState.SUCCEEDED, now_s))
            return out
        self._active = _Active(task, self._waypoints_for(task, pose_in_odom), now_s)
        if isinstance(task, NeutralizeTask):
            self._active.approved = task.approved
        out.append(self._status(task_id, TaskState.ACTIVE, now_s))
        return out

    def _validate(self, task: Any) -> str | None:
        cfg = self.config
        if isinstance(task, GoToTask):
            if not task.waypoints_in_odom:
                return "waypoints_in_odom is empty"
            return _finite("waypoints_in_odom", task.waypoints_in_odom) or _finite(
                "speed_limit_m_s", task.speed_limit_m_s
            )
        if isinstance(task, NeutralizeTask):
            if problem := _finite("target_in_odom", task.target_in_odom) or _finite(
                "standoff_m", task.standoff_m
            ):
                return problem
            if task.standoff_m <= 0:
                return f"standoff_m must be > 0, got {task.standoff_m}"
        if isinstance(task, RelayTask):
            return _finite("position_in_odom", task.position_in_odom)
        if isinstance(task, TeleopTask):
            values = (task.linear_m_s, task.angular_rad_s, task.duration_s)
            if problem := _finite("teleop (linear_m_s, angular_rad_s, duration_s)", values):
                return problem
            if abs(task.linear_m_s) > cfg.max_teleop_linear_m_s:
                return f"linear_m_s {task.linear_m_s} exceeds {cfg.max_teleop_linear_m_s}"
            if abs(task.angular_rad_s) > cfg.max_teleop_angular_rad_s:
                return f"angular_rad_s {task.angular_rad_s} exceeds {cfg.max_teleop_angular_rad_s}"
            if not 0 < task.duration_s <= cfg.max_teleop_duration_s:
                return (
                    f"duration_s must be in (0, {cfg.max_teleop_duration_s}], got {task.duration_s}"
                )
        return None

    def _waypoints_for(self, task: Any, pose_in_odom: np.ndarray) -> np.ndarray:
        if isinstance(task, GoToTask):
            return np.asarray(task.waypoints_in_odom, dtype=np.float64).reshape(-1, 2)
        if isinstance(task, RelayTask):
            return np.asarray([task.position_in_odom], dtype=np.float64)
        if isinstance(task, NeutralizeTask):
            target = np.asarray(task.target_in_odom, dtype=np.float64)
            away = np.asarray(pose_in_odom[:2], dtype=np.float64) - target
            n = float(np.linalg.norm(away))
            unit = away / n if n > 1e-6 else np.array([1.0, 0.0])
            return (target + unit * task.standoff_m).reshape(1, 2)
        return np.zeros((0, 2))

    def _update_neutralize(
        self, act: _Active, task: NeutralizeTask, now_s: float
    ) -> list[TaskStatus]:
        if task.approved and not act.approved:
            act.approved = True
            return [self._status(task.task_id, TaskState.ACTIVE, now_s, "approved by operator")]
        return []

    # ------------------------------------------------------------------ progress

    def fail(self, now_s: float, detail: str) -> list[TaskStatus]:
        """The robot cannot carry out its current task (``detail`` says why, e.g. a deadlock
        it could not break): end it FAILED, so the GCS gives another. No report without one."""
        act = self._active
        if act is None or act.paused or isinstance(act.task, TeleopTask):
            return []
        self._active = None
        return [self._status(act.task.task_id, TaskState.FAILED, now_s, detail)]

    def update(
        self,
        now_s: float,
        pose_in_odom: np.ndarray,
        *,
        path_found: bool = True,
        laser_on_target: bool = False,
        laser_detail: str = "",
    ) -> list[TaskStatus]:
        """Advance the current task given where the robot is; returns status reports.

        ``path_found``: the planner has a path to the next waypoint; ``laser_on_target``: the
        laser is on the OOI, seen now with line of sight, this instant; ``laser_detail``: why
        not (the failure's detail says it).
        """
        act = self._active
        if act is None or act.paused:
            return []
        cfg = self.config
        task = act.task
        tid = task.task_id
        if isinstance(task, TeleopTask):
            if now_s - act.started_s >= task.duration_s:
                self._active = None
                return [self._status(tid, TaskState.SUCCEEDED, now_s)]
            return []
        out: list[TaskStatus] = []
        pos = np.asarray(pose_in_odom[:2], dtype=np.float64)
        tol = (
            cfg.standoff_tolerance_m
            if isinstance(task, NeutralizeTask)
            else cfg.waypoint_tolerance_m
        )
        while len(act.waypoints) and np.linalg.norm(act.waypoints[0] - pos) <= tol:
            act.waypoints = act.waypoints[1:]
        if len(act.waypoints) == 0 and not act.arrived:
            act.arrived = True
            if isinstance(task, GoToTask):
                self._active = None
                return [self._status(tid, TaskState.SUCCEEDED, now_s)]
            if isinstance(task, RelayTask):
                out.append(self._status(tid, TaskState.ACTIVE, now_s, "holding as relay"))
            if isinstance(task, NeutralizeTask) and not act.approved:
                out.append(
                    self._status(tid, TaskState.ACTIVE, now_s, "at stand-off, waiting for approval")
                )
        if not act.arrived:
            if path_found:
                act.no_path_since_s = None
            elif act.no_path_since_s is None:
                act.no_path_since_s = now_s
            elif now_s - act.no_path_since_s >= cfg.no_path_timeout_s:
                self._active = None
                return [
                    *out,
                    self._status(tid, TaskState.FAILED, now_s, "no path to the next waypoint"),
                ]
        if isinstance(task, NeutralizeTask) and act.arrived and act.approved:
            if act.ready_since_s is None or laser_on_target:
                act.ready_since_s = now_s
            if not laser_on_target and now_s - act.ready_since_s >= cfg.laser_search_s:
                self._active = None
                detail = f"laser not on the target for {cfg.laser_search_s:g} s"
                if laser_detail:
                    detail += f": {laser_detail}"
                return [*out, self._status(tid, TaskState.FAILED, now_s, detail)]
            if not laser_on_target:
                act.los_since_s = None
            elif act.los_since_s is None:
                act.los_since_s = now_s
            elif now_s - act.los_since_s >= cfg.laser_hold_s:
                self._active = None
                return [*out, self._status(tid, TaskState.SUCCEEDED, now_s)]
        return out

    @property
    def intent(self) -> Intent:
        """What the node should do now."""
        act = self._active
        if act is None:
            return Intent()
        task = act.task
        if act.paused:
            return Intent(mode=AutonomyMode.PAUSED, task_id=task.task_id)
        if isinstance(task, TeleopTask):
            return Intent(
                mode=AutonomyMode.TELEOPERATED,
                task_id=task.task_id,
                teleop=(task.linear_m_s, task.angular_rad_s),
                conservative=task.conservative,
            )
        laser = None
        if isinstance(task, NeutralizeTask) and act.arrived and act.approved:
            laser = (float(task.target_in_odom[0]), float(task.target_in_odom[1]))
        # an operator's task (its id in the operators' range): the operator chose the goal,
        # the robot drives there on its own (semi-autonomous, paper 6.2 and 7)
        return Intent(
            mode=AutonomyMode.SEMI_AUTONOMOUS
            if is_operator_task(task.task_id)
            else AutonomyMode.AUTONOMOUS,
            task_id=task.task_id,
            waypoints_in_odom=act.waypoints.copy(),
            laser_target_in_odom=laser,
        )

    @staticmethod
    def _status(task_id: int, state: TaskState, now_s: float, detail: str = "") -> TaskStatus:
        return TaskStatus(task_id, state, now_s, detail)
