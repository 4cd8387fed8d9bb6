"""A robot without its GCS: link health from what the robot hears, and what it does meanwhile.

MAGIC's robots lost their radio often (paper 4.1, 8: reliable communication remained the
challenge); the decoupled architecture lets a robot go on alone. The link's health is read
from the mission time of the last downlink message the robot *heard* (any: the GCS's hazard
and frame broadcast every ``frames_period_s``, a task, a parameter, a thumbnail request), so
it needs nothing from the radio itself and repeats exactly in lockstep.

States (:class:`LinkState`), with ``quiet = now - last heard``:

* ``CONNECTED``: ``quiet < silence_s``, or not armed yet. Silence means something only
  against a sender that keeps in touch: the watchdog arms once it heard the GCS's periodic
  broadcast (:class:`~protocol.messages.HazardUpdate`, every ``frames_period_s``) at
  ``arm_after_broadcasts`` different times. A ground side that never repeats itself (a script
  that hands a robot one task) never arms it, and a robot that never heard a GCS has no task.
* ``SILENT``: ``quiet >= silence_s``: the link is lost, reported, and the robot keeps executing
  its task: at least ``task_grace_s`` more, and while the task still has waypoints to drive
  (a goal, a stand-off still to reach) up to ``task_limit_s``. What it explores meanwhile
  reaches the GCS when the link is back (below), so the task's driving is not wasted.
* ``HOLDING``: then the robot stops where it is (its task suspended, not canceled; an
  approved neutralization keeps its laser on target).
* ``RETURNING`` (``policy: return``, the default): ``return_after_s`` after the link was lost
  (and not before the task stopped: it holds in between), or ``idle_return_after_s`` after
  it when the robot has no task (it finished it in the silence, or never had one), it
  drives back, with its own
  planner, to where it last heard the GCS (the last point of contact, in its private frame
  ``odom``). Radio coverage has sharp edges (a wall's shadow) and odometry drifts, so if that
  point is silent too it goes on back along its earlier points of contact (a trail of up to
  ``return_trail_points``, ``return_spacing_m`` apart), and holds (``HOLDING``) at the oldest;
  a point not reached within ``return_point_s`` (drift put it in a wall, no way there) is
  passed over for the next one back too.
  Why not hold for good: in a 200 s small-world mission with the real GCS a robot that held
  in a radio shadow stayed there, unheard, to the end; returning along the trail brought two
  robots out of shadows (41 s and 34 s long) into contact again. Why wait first: a silence
  is as often an outage in time (interference, a relay moving, the GCS restarting) as a
  shadow in space, and backing out costs the way back and then forth again; the chaos bench
  (``magic bench chaos``: two 60 s blackouts per robot in 600 mission-s) lost 0.076 of the
  explored fraction with robots suspending their tasks 20 s into a silence and backing out;
  with the task driven on and the return after a minute the faulted run explored 0.884
  against 0.839 without faults, one seed (``robot_suspended_s`` there says what the policy
  costs: 459 robot-s faulted, 607 without faults: the small world's radio shadows).
  A robot without a task has nothing to lose by going back at once: waiting keeps it idle
  until the minute is up, and only the GCS, out of reach, can give it work. Small world
  300 s, seeds 0 and 7: sensor robots finished their exploration goals inside radio shadows
  (behind the east building) and stood idle 28-76 s each time, 195-205 robot-s a run of the
  900 the three sensor robots have.

The first message heard again returns it to ``CONNECTED`` and the suspended task resumes (or
the GCS's next task replaces it), after a *drain hold* when the node reports its uplink
backlog: a robot back from a silence first stands where it heard the GCS (``PAUSED``,
:attr:`CommsWatchdog.draining`) while what it produced in the silence goes up, until its
radio's queue is empty, at most ``drain_hold_frac`` of the silence's length and
``drain_hold_max_s`` (off by default, ``drain_hold_frac`` 0: see the config's comment).
Measured why (``magic bench chaos`` full, seed 7, 30 % loss, 60 s blackouts): the link drains a
60 s backlog (4-12 kB) 1-25 s after its grant returns, but a robot at a radio shadow's edge
heard the GCS for 1-2 s at a time and drove straight back in (a resumed task, or the GCS's
next goal, chosen on a map that lacked everything the robot had seen since it went silent:
the same frontier, inside the shadow, three times). From 136 s to the end its pose nodes and
grids never got through (539 messages in flight at the end, 749 pose nodes at the GCS against
1044 without faults, explored 0.833 against 0.945). Standing at the point of contact until
the backlog is through breaks that loop: the GCS sees where the robot has been before it
picks the robot's next goal. Every transition of a robot with a task is reported as a
``TaskStatus`` (``ACTIVE``, the detail names the state), so operators see afterwards what the
robot did; while holding, its telemetry mode is ``PAUSED``. Everything the robot produced
meanwhile waits in its uplink queue (``protocol.radio_channel``: nothing accepted is dropped)
and goes out once the radio grants a rate again, in order within each stream (streams drain
by priority: a detection may overtake the pose node it refers to).

:class:`CommsWatchdog` is the pure state machine; :class:`LinkAwareTasks` puts it in front of a
:class:`~robot.tasks.task_executor.TaskExecutor` with the executor's own interface, so the robot
node only has to tell it when it heard the GCS (:meth:`LinkAwareTasks.heard`).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from typing import Any, Literal

import msgspec
import numpy as np

from protocol.messages import AutonomyMode, HazardUpdate, TaskState, TaskStatus
from robot.tasks.task_executor import Intent, TaskExecutor, TaskExecutorConfig

__all__ = ["CommsWatchdog", "CommsWatchdogConfig", "LinkAwareTasks", "LinkState"]


class CommsWatchdogConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``silence_s``: no downlink this long and the link counts as lost (the GCS broadcasts
    every 2 s: 10 s is five broadcasts in a row lost, ~0.2% at 30% loss); ``task_grace_s``:
    then keep on the task at least this much longer, and ``task_limit_s`` at most while it
    still has waypoints to drive; ``policy``: then ``hold`` where it is or, from
    ``return_after_s`` after the link was lost, ``return`` to the last point of contact
    (``return_tolerance_m``: close enough there) and further back along the trail of earlier
    ones if that is silent too (module docstring); ``idle_return_after_s``: the same for a
    robot with no task, from the link lost (or its task ended, if later)."""

    enabled: bool = True
    arm_after_broadcasts: int = 2
    silence_s: float = 10.0
    task_grace_s: float = 20.0
    task_limit_s: float = 120.0
    policy: Literal["hold", "return"] = "return"
    return_after_s: float = 60.0
    idle_return_after_s: float = 0.0
    return_tolerance_m: float = 0.75
    return_spacing_m: float = 2.0
    return_trail_points: int = 16
    # a point of contact not reached in this long is given up for the next one back: odometry
    # drift can put it in a wall or a room (small world seed 7: a robot drove to and fro
    # between a building and a tree for 175 s, 2 m short of a point it never reached)
    return_point_s: float = 40.0
    # back in contact after a silence of ``q`` seconds: stand still while the node reports an
    # uplink backlog (LinkAwareTasks.update's uplink_backlog_bytes > 0), at most
    # min(frac * q, max_s) (0: resume at once). A node that does not report its backlog never
    # holds: a hold by time alone would stand idle when the backlog is long gone (a 60 s
    # blackout's 4-12 kB left the robot's queue 1-4 s after the grant returned at 11-86 kbps).
    # Off by default: on (0.2), the quick mission's seed 7 without faults explored 0.830
    # against 0.962 (every return from a radio shadow stood; one run, same code otherwise)
    drain_hold_frac: float = 0.0
    drain_hold_max_s: float = 12.0

    def __post_init__(self) -> None:
        if self.return_trail_points < 1:
            raise ValueError(f"return_trail_points must be >= 1, got {self.return_trail_points}")
        for name in ("silence_s", "return_tolerance_m", "return_spacing_m", "return_point_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        if self.arm_after_broadcasts < 1:
            raise ValueError(f"arm_after_broadcasts must be >= 1, got {self.arm_after_broadcasts}")
        if not (math.isfinite(self.drain_hold_frac) and 0 <= self.drain_hold_frac <= 1):
            raise ValueError(f"drain_hold_frac must be in [0, 1], got {self.drain_hold_frac}")
        for name in ("task_grace_s", "return_after_s", "idle_return_after_s", "drain_hold_max_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.task_limit_s) and self.task_limit_s >= self.task_grace_s):
            raise ValueError(
                f"task_limit_s must be finite and >= task_grace_s ({self.task_grace_s}), "
                f"got {self.task_limit_s}"
            )


class LinkState(enum.Enum):
    CONNECTED = "connected"
    SILENT = "silent"
    HOLDING = "holding"
    RETURNING = "returning"


class CommsWatchdog:
    """The link state from the last time the GCS was heard (see the module docstring).

    Times are mission seconds; poses ``(x, y, theta)`` in the robot's ``odom`` frame.
    """

    def __init__(self, config: CommsWatchdogConfig | None = None) -> None:
        self.config = config or CommsWatchdogConfig()
        self.state = LinkState.CONNECTED
        self.last_heard_s: float | None = None
        #: where the robot was when it last heard the GCS (odom, metres)
        self.contact_in_odom: np.ndarray | None = None
        #: points of contact at least ``return_spacing_m`` apart, oldest first
        self._trail: deque[np.ndarray] = deque(maxlen=self.config.return_trail_points)
        self._route: list[np.ndarray] = []  # returning: the points still to try, last first
        self.silent_since_s: float | None = None  # when the link was declared lost
        self._broadcast_times: set[float] = set()  # until armed
        self.armed = False
        self._returned = False  # this silence's return was made (then it holds for good)
        self._idle_since_s: float | None = None  # without a task since (update's task_idle)
        self._target_since_s = -math.inf  # returning: driving to the current point since
        #: back in contact after a silence: holding for the uplink backlog until then
        self.drain_until_s = -math.inf
        #: holding at the point of contact for the uplink backlog now (set by update)
        self.draining = False

    def heard(self, now_s: float, pose_in_odom: np.ndarray, *, periodic: bool = False) -> LinkState:
        """The GCS was heard at ``now_s`` with the robot at ``pose_in_odom`` (``periodic``:
        its periodic broadcast); returns the state before (the link is ``CONNECTED`` after)."""
        before = self.state
        if before is not LinkState.CONNECTED and self.last_heard_s is not None:
            cfg = self.config
            hold_s = min(cfg.drain_hold_frac * self.quiet_s(now_s), cfg.drain_hold_max_s)
            if hold_s > 0:
                self.drain_until_s = now_s + hold_s  # update() holds while a backlog is reported
        if periodic and not self.armed:
            self._broadcast_times.add(now_s)
            self.armed = len(self._broadcast_times) >= self.config.arm_after_broadcasts
        self.last_heard_s = now_s if self.last_heard_s is None else max(self.last_heard_s, now_s)
        here = np.array(pose_in_odom[:2], dtype=np.float64)
        self.contact_in_odom = here
        trail = self._trail
        if not trail or math.hypot(*(here - trail[-1])) >= self.config.return_spacing_m:
            trail.append(here)
        self._route = []
        self._returned = False
        self.state = LinkState.CONNECTED
        self.silent_since_s = None
        return before

    def quiet_s(self, now_s: float) -> float:
        """Seconds since the GCS was last heard (0 before it ever was)."""
        return 0.0 if self.last_heard_s is None else max(0.0, now_s - self.last_heard_s)

    def update(
        self,
        now_s: float,
        pose_in_odom: np.ndarray,
        *,
        task_driving: bool = False,
        task_idle: bool = False,
        uplink_backlog_bytes: int | None = None,
    ) -> LinkState:
        """Advance to ``now_s``; returns the new state. ``task_driving``: the robot's task
        still has waypoints to drive (it then goes on up to ``task_limit_s``); ``task_idle``:
        the robot has no task (it returns ``idle_return_after_s`` after the link was lost or
        the task ended, whichever came later); ``uplink_backlog_bytes``: what the robot's
        radio still has queued, if the node knows: a robot back in contact stands while it
        is > 0, for at most the drain hold's time (:attr:`draining`; 0 ends the hold, None:
        no hold)."""
        cfg = self.config
        if uplink_backlog_bytes is not None and uplink_backlog_bytes <= 0:
            self.drain_until_s = -math.inf
        self.draining = (
            self.state is LinkState.CONNECTED
            and now_s < self.drain_until_s
            and uplink_backlog_bytes is not None
        )
        if not cfg.enabled or not self.armed or self.last_heard_s is None:
            return self.state
        quiet = self.quiet_s(now_s)
        if self.state is LinkState.CONNECTED and quiet >= cfg.silence_s:
            self.state = LinkState.SILENT
            self.silent_since_s = self.last_heard_s + cfg.silence_s
            self.draining = False
            self.drain_until_s = -math.inf
        lost_s = quiet - cfg.silence_s
        if not task_idle:
            self._idle_since_s = None
        elif self._idle_since_s is None:
            self._idle_since_s = now_s
        idle_back = (
            self._idle_since_s is not None
            and lost_s >= 0
            and min(lost_s, now_s - self._idle_since_s) >= cfg.idle_return_after_s
        )
        if self.state is LinkState.SILENT and (
            idle_back
            or (lost_s >= cfg.task_grace_s and (not task_driving or lost_s >= cfg.task_limit_s))
        ):
            self.state = LinkState.HOLDING
        if (
            self.state is LinkState.HOLDING
            and cfg.policy == "return"
            and not self._returned
            and (lost_s >= cfg.return_after_s or idle_back)
            and self.contact_in_odom is not None
        ):
            self.state = LinkState.RETURNING
            self._returned = True
            self._route = list(self._trail)
            if not self._route or not np.array_equal(self._route[-1], self.contact_in_odom):
                self._route.append(self.contact_in_odom)
            self._target_since_s = now_s
        while self.state is LinkState.RETURNING and (
            self._at(self.return_target_in_odom, pose_in_odom)
            or now_s - self._target_since_s >= cfg.return_point_s
        ):
            self._target_since_s = now_s
            if len(self._route) > 1:
                self._route.pop()  # silent here too, or no way there: further back
            else:
                self.state = LinkState.HOLDING
        return self.state

    @property
    def return_target_in_odom(self) -> np.ndarray | None:
        """Where a returning robot drives: the newest point of contact not yet found silent."""
        return self._route[-1].copy() if self._route else None

    def _at(self, target: np.ndarray | None, pose_in_odom: np.ndarray) -> bool:
        if target is None:
            return True
        d = math.hypot(float(pose_in_odom[0] - target[0]), float(pose_in_odom[1] - target[1]))
        return d <= self.config.return_tolerance_m

    @property
    def suspended(self) -> bool:
        """The task is set aside (holding, returning, or holding for the uplink backlog)."""
        return self.draining or self.state in (LinkState.HOLDING, LinkState.RETURNING)


class LinkAwareTasks:
    """A :class:`TaskExecutor` behind a :class:`CommsWatchdog`, with the executor's interface
    (``submit``, ``update``, ``intent``, ``current_task_id``, ``config``) plus :meth:`heard`.

    While the task is suspended the executor still sees the robot's pose (a waypoint passed on
    the way back counts; no no-path timeout runs: there is no plan for it to miss) but the
    intent is the watchdog's: stay (``PAUSED``), or go to the last point of contact.
    """

    def __init__(
        self,
        executor: TaskExecutor | None = None,
        config: CommsWatchdogConfig | None = None,
    ) -> None:
        self.executor = executor or TaskExecutor()
        self.watchdog = CommsWatchdog(config)
        self._pending: list[TaskStatus] = []  # reports made by heard(), given by update()
        self._holding_laser: tuple[float, float] | None = None

    @property
    def config(self) -> TaskExecutorConfig:
        return self.executor.config

    @property
    def current_task_id(self) -> int:
        return self.executor.current_task_id

    @property
    def state(self) -> LinkState:
        return self.watchdog.state

    def heard(self, now_s: float, pose_in_odom: np.ndarray, message: Any = None) -> None:
        """The GCS was heard (any downlink ``message``): the link is back if it was lost."""
        wd = self.watchdog
        quiet = wd.quiet_s(now_s)
        before = wd.heard(now_s, pose_in_odom, periodic=isinstance(message, HazardUpdate))
        if before is not LinkState.CONNECTED:
            what = "resuming the task" if before is not LinkState.SILENT else "task went on"
            if wd.drain_until_s > now_s:
                hold_s = wd.drain_until_s - now_s
                what += f" once the uplink backlog is through (at most {hold_s:.1f} s)"
            self._note(now_s, f"link back after {quiet:.1f} s silent ({what})")

    def submit(self, task: Any, now_s: float, pose_in_odom: np.ndarray) -> list[TaskStatus]:
        return self.executor.submit(task, now_s, pose_in_odom)

    def update(
        self,
        now_s: float,
        pose_in_odom: np.ndarray,
        *,
        path_found: bool = True,
        laser_on_target: bool = False,
        laser_detail: str = "",
        uplink_backlog_bytes: int | None = None,
    ) -> list[TaskStatus]:
        """The watchdog's transitions, then the executor's progress (see the class);
        ``uplink_backlog_bytes``: the robot radio's queued bytes, if known (ends a drain hold
        once 0, :meth:`CommsWatchdog.update`)."""
        wd = self.watchdog
        before = wd.state
        driving = len(self.executor.intent.waypoints_in_odom) > 0
        idle = self.executor.current_task_id == 0
        state = wd.update(
            now_s,
            pose_in_odom,
            task_driving=driving,
            task_idle=idle,
            uplink_backlog_bytes=uplink_backlog_bytes,
        )
        if state is not before:
            self._note(now_s, self._describe(state, now_s))
        out, self._pending = self._pending, []
        suspended = wd.suspended
        out += self.executor.update(
            now_s,
            pose_in_odom,
            path_found=path_found or suspended,
            laser_on_target=laser_on_target,
            laser_detail=laser_detail,
        )
        return out

    def fail(self, now_s: float, detail: str) -> list[TaskStatus]:
        """The robot cannot carry out the task (:meth:`TaskExecutor.fail`). While it is
        suspended the robot is pursuing the watchdog's goal, not the task's: nothing fails."""
        if self.watchdog.suspended:
            return []
        return self.executor.fail(now_s, detail)

    def _describe(self, state: LinkState, now_s: float) -> str:
        wd = self.watchdog
        cfg = wd.config
        if state is LinkState.SILENT:
            return f"link silent for {cfg.silence_s:.1f} s: continuing the task"
        quiet = wd.quiet_s(now_s)
        if state is LinkState.RETURNING:
            c = wd.contact_in_odom
            where = "" if c is None else f" ({c[0]:.1f}, {c[1]:.1f}) in odom"
            return f"link silent for {quiet:.1f} s: returning to the last point of contact{where}"
        if state is LinkState.HOLDING and wd._returned:
            return "link silent: holding at the oldest point of contact it kept"
        return f"link silent for {quiet:.1f} s: holding"

    def _note(self, now_s: float, detail: str) -> None:
        tid = self.executor.current_task_id
        if tid:  # an idle robot has no task to report on; its telemetry shows the mode
            self._pending.append(TaskStatus(tid, TaskState.ACTIVE, now_s, detail))

    @property
    def intent(self) -> Intent:
        """The executor's intent, or the watchdog's while the task is suspended."""
        inner = self.executor.intent
        wd = self.watchdog
        if wd.state is LinkState.HOLDING or wd.draining:
            # stand still (holding, or where the GCS is heard again while the backlog goes
            # up); an approved neutralization at its stand-off keeps lasering
            return Intent(
                mode=AutonomyMode.PAUSED,
                task_id=inner.task_id,
                laser_target_in_odom=inner.laser_target_in_odom,
            )
        target = wd.return_target_in_odom
        if wd.state is LinkState.RETURNING and target is not None:
            return Intent(
                mode=AutonomyMode.AUTONOMOUS,
                task_id=inner.task_id,
                waypoints_in_odom=target.reshape(1, 2),
            )
        return inner
