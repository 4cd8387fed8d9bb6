"""Deadlock detection and breaking between teammates (decoupled planning, paper 4.1 and 5.4).

Each robot plans alone over its own short-memory map, in which a teammate is just an obstacle.
Two robots meeting head-on in a corridor each find the way blocked by the other: both stop
and wait for the map to change (5.4: "no path: stop and wait"), which it never does, or both
take the same long detour and come back together. Nothing in the single-robot pipeline
breaks that symmetry; this module does, the way shared media do (random back-off):

* **detection**: a goal is being pursued but the robot's straight-line distance to it has not
  improved by ``min_progress_m`` for ``stall_s`` plus a random ``[0, stall_jitter_s)`` while
  the robot itself stayed within ``stall_motion_m`` (stalled: blocked, or waiting for a
  path), or for ``livelock_s`` however much it drove (going back and forth). The jitter makes
  one of two robots stuck face to face give way first; the other sees what blocks it recede
  (:meth:`DeadlockBreaker.note_block_distance`: that counts as progress), waits, and goes
  when the way is clear, without backing off itself;
* **yielding** (:func:`path_block_distance`): when the path being followed becomes blocked
  within ``yield_lookahead_m`` and the only way around is a much longer detour
  (``yield_detour_ratio`` times the remaining path plus ``yield_detour_m``) or none, the
  robot stops and waits instead of setting off on the detour: with a 15 s memory and unknown
  cells taken as free, that detour is often a guess through unseen ground that two robots
  meeting head-on would both take and both abandon. The robots' sparse scans cannot tell a
  teammate from a newly seen wall, so waiting is bounded: at most ``yield_budget_s`` per
  goal, after which detours are taken at once; and the robot waits only for what moves
  (``yield_movers_only``, :func:`mover_near_block`): a teammate seen by its tags or a person
  track (people, and teammates the LIDAR takes for people) within ``yield_mover_radius_m`` of
  where the path is blocked (:func:`path_point_at`), or for a block that the newest sweep
  no longer sees where the memory still holds it (``yield_cleared``: a mover's trail, a
  flickering mark; the memory is refreshed and the robot plans again). A static obstacle the
  newest sweep still sees is detoured at once (issue 14, small world seed 1: a robot waited
  60-137 s in the gap between two keep-out disks for the east face of a 10 cm curb its map
  held 0.4 m beside the path, backed off, and drove in again when the memory forgot the
  face). Measured (quick mission, 300 s, at 1d6eb73 against its own runs; load 10-20):
  explored on seeds 0/7/3/11 and 1/2 0.948/0.966/0.901/0.883 and 0.933/0.892 (median of four
  0.925, of six 0.917, mean 0.921) against 0.955/0.945/0.920/0.876 and 0.897/0.868 before
  (0.933, 0.909, mean 0.910): seed 1 0.897 -> 0.933, three seeds below 0.9 became two; 0
  lost, 0 civilians. Movers only, without ``yield_cleared``: 0.931/0.944/0.845/0.902 and
  0.932/0.914 (median of four 0.917, mean 0.911; seed 3: at 200 s a robot turned back east
  into the radio shadow where before it went on to its goal);
* **breaking**: the robot backs off along its own recent trail (ground it has just driven, so
  known to be passable) to the first point at least ``backoff_min_m`` back where the map has
  ``passing_clearance_m`` of room (another robot can get past it there), at most
  ``backoff_max_m`` back; then it holds still for a random time, ``hold_s`` plus a uniform
  draw of up to ``hold_spread_s`` doubled at each further deadlock on the same goal (capped
  by ``hold_spread_max_s``). The robot whose hold ends first goes; the other is out of its
  way and waits, and goes when the way is clear (its planner sees the first robot pass).

The draws come from ``numpy.random.default_rng(seed)``, the node seeds it with its robot id,
so a seeded mission is repeatable and two robots never draw alike. After ``max_attempts``
deadlocks on one goal the breaker stops interfering (:attr:`DeadlockBreaker.gave_up`): the
task's own no-path timeout reports the failure, or the breaker does
(:attr:`DeadlockBreaker.exhausted`) when the robot stalls once more.

**Escapes that fail** (issue 14, small world seed 0: a robot sat 170 s in a room backing off to
the same trail point without moving): a back-off whose plan finds no way to its target follows
the trail itself, reversed (:meth:`DeadlockBreaker.trail_back_path`: ground just driven). A
back-off that ends (arrived, timed out or aborted) less than ``escape_min_motion_m`` from where
the deadlock struck is a failed escape, and the next back-off tries another trail point (the
roomiest one not yet tried, nearest first); ``max_failed_escapes`` in a row make the breaker
:attr:`DeadlockBreaker.exhausted`, and the node reports the task failed with that reason, so
the GCS gives another goal instead of the robot retrying the same one for minutes.

Pure logic over the robot's pose in ``odom``, metres and seconds; the node calls
:meth:`DeadlockBreaker.update` every control period and, when it returns
:attr:`Phase.DEADLOCKED`, :meth:`DeadlockBreaker.start_backoff` with its current obstacle map.
"""

from __future__ import annotations

import enum
import math
from collections import deque

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from robot.planning.path_relaxation import clearance_field
from robot.terrain.grid import GridGeometry

__all__ = [
    "DeadlockBreaker",
    "DeadlockConfig",
    "Phase",
    "mover_near_block",
    "path_block_distance",
    "path_point_at",
]


class DeadlockConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Tunables of :class:`DeadlockBreaker` (see the module docstring)."""

    enabled: bool = True
    stall_s: float = 6.0
    stall_jitter_s: float = 8.0
    stall_motion_m: float = 1.0
    livelock_s: float = 40.0
    min_progress_m: float = 0.75
    recede_m: float = 0.3
    trail_spacing_m: float = 0.2
    trail_length_m: float = 40.0
    backoff_min_m: float = 1.5
    backoff_max_m: float = 25.0
    passing_clearance_m: float = 1.4
    arrive_m: float = 0.4
    backoff_timeout_s: float = 20.0
    hold_s: float = 2.0
    hold_spread_s: float = 8.0
    hold_spread_max_s: float = 40.0
    max_attempts: int = 6
    yield_detour_ratio: float = 1.5
    yield_detour_m: float = 4.0
    yield_lookahead_m: float = 10.0
    yield_budget_s: float = 30.0
    # wait only when a mover (a teammate, a person track) is this near the block, or the
    # newest sweep sees the way clear (yield_cleared; see the module docstring for both and
    # their measurement); False: wait for whatever blocks the path (before issue 14)
    yield_movers_only: bool = True
    yield_mover_radius_m: float = 2.0
    yield_mover_memory_s: float = 10.0
    yield_cleared: bool = True
    escape_min_motion_m: float = 0.5
    max_failed_escapes: int = 2

    def __post_init__(self) -> None:
        for name in (
            "stall_s",
            "stall_motion_m",
            "livelock_s",
            "min_progress_m",
            "recede_m",
            "trail_spacing_m",
            "trail_length_m",
            "backoff_max_m",
            "passing_clearance_m",
            "arrive_m",
            "backoff_timeout_s",
            "yield_detour_ratio",
            "yield_lookahead_m",
            "yield_mover_radius_m",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"deadlock.{name} must be finite and > 0, got {v}")
        for name in (
            "stall_jitter_s",
            "backoff_min_m",
            "hold_s",
            "hold_spread_s",
            "hold_spread_max_s",
            "yield_detour_m",
            "yield_budget_s",
            "yield_mover_memory_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"deadlock.{name} must be finite and >= 0, got {v}")
        if self.backoff_min_m > self.backoff_max_m:
            raise ValueError(
                f"deadlock.backoff_min_m ({self.backoff_min_m}) exceeds backoff_max_m "
                f"({self.backoff_max_m})"
            )
        if not (math.isfinite(self.escape_min_motion_m) and self.escape_min_motion_m >= 0):
            raise ValueError(
                f"deadlock.escape_min_motion_m must be finite and >= 0, got "
                f"{self.escape_min_motion_m}"
            )
        if self.max_failed_escapes < 1:
            raise ValueError(
                f"deadlock.max_failed_escapes must be >= 1, got {self.max_failed_escapes}"
            )
        if self.max_attempts < 1:
            raise ValueError(f"deadlock.max_attempts must be >= 1, got {self.max_attempts}")


class Phase(enum.Enum):
    DRIVE = "drive"  # pursuing the goal; progress is watched
    DEADLOCKED = "deadlocked"  # detected; the node must call start_backoff
    BACKOFF = "backoff"  # driving back along the trail to backoff_target_in_odom
    HOLD = "hold"  # standing still until the random hold ends


def _xy(name: str, v: ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(v, dtype=np.float64).reshape(-1)[:2]
    if a.shape != (2,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite (x, y) in odom, got {v!r}")
    return a


def path_block_distance(
    path_in_odom: ArrayLike,
    position_in_odom: ArrayLike,
    obstacle: NDArray[np.bool_],
    geometry: GridGeometry,
    *,
    robot_radius_m: float,
    lookahead_m: float,
) -> float:
    """How far along ``path_in_odom`` ``(K, 2)``, from ``position_in_odom`` via the path's
    nearest vertex, the path first passes within ``robot_radius_m`` of an ``obstacle`` cell
    (the configuration space's test; the map laid out by ``geometry`` in ``odom``); ``inf``
    when the first ``lookahead_m`` are clear. Cells off the map do not block."""
    path = np.asarray(path_in_odom, dtype=np.float64).reshape(-1, 2)
    pos = _xy("position_in_odom", position_in_odom)
    obs = np.asarray(obstacle)
    if obs.shape != geometry.shape or obs.dtype != np.bool_:
        raise ValueError(
            f"obstacle: expected a bool grid of shape {geometry.shape}, got {obs.dtype} {obs.shape}"
        )
    if len(path) == 0 or not obs.any():
        return math.inf
    res = geometry.resolution_m
    start = int(np.argmin(np.hypot(*(path - pos).T)))
    pts = np.vstack([pos, path[start:]])
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    s = np.arange(0.0, min(lookahead_m, float(along[-1])) + 1e-9, 0.5 * res)
    pts = np.stack([np.interp(s, along, pts[:, 0]), np.interp(s, along, pts[:, 1])], axis=1)
    rc = geometry.cell_of(pts)
    inside = (
        (rc[:, 0] >= 0) & (rc[:, 0] < geometry.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < geometry.cols)
    )
    rc, s = rc[inside], s[inside]
    if len(rc) == 0:
        return math.inf
    k = int(math.ceil(robot_radius_m / res))
    r0, c0 = max(0, int(rc[:, 0].min()) - k), max(0, int(rc[:, 1].min()) - k)
    r1, c1 = int(rc[:, 0].max()) + k + 1, int(rc[:, 1].max()) + k + 1
    mr, mc = np.nonzero(obs[r0:r1, c0:c1])
    if len(mr) == 0:
        return math.inf
    mr, mc = mr + r0, mc + c0
    reach2 = (robot_radius_m / res) ** 2 + 1e-9  # the configuration-space disc
    for i in range(0, len(rc), 128):
        chunk = rc[i : i + 128]
        d2 = (chunk[:, None, 0] - mr[None, :]) ** 2 + (chunk[:, None, 1] - mc[None, :]) ** 2
        hit = np.flatnonzero((d2 <= reach2).any(axis=1))
        if len(hit):
            return float(s[i + int(hit[0])])
    return math.inf


def path_point_at(
    path_in_odom: ArrayLike, position_in_odom: ArrayLike, distance_m: float
) -> NDArray[np.float64]:
    """The point ``distance_m`` along ``path_in_odom`` ``(K, 2)`` from ``position_in_odom``
    via the path's nearest vertex (as :func:`path_block_distance` measures); the path's end
    beyond its length, ``position_in_odom`` for an empty path."""
    path = np.asarray(path_in_odom, dtype=np.float64).reshape(-1, 2)
    pos = _xy("position_in_odom", position_in_odom)
    if len(path) == 0:
        return pos
    start = int(np.argmin(np.hypot(*(path - pos).T)))
    pts = np.vstack([pos, path[start:]])
    along = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(pts, axis=0).T))])
    s = min(max(0.0, float(distance_m)), float(along[-1]))
    return np.array([np.interp(s, along, pts[:, 0]), np.interp(s, along, pts[:, 1])])


def mover_near_block(
    block_in_odom: ArrayLike, movers_in_odom: ArrayLike, *, radius_m: float
) -> bool:
    """Whether any of ``movers_in_odom`` ``(N, 2)`` (teammates, people) is within
    ``radius_m`` of ``block_in_odom``: what blocks the path there may move away."""
    b = _xy("block_in_odom", block_in_odom)
    m = np.asarray(movers_in_odom, dtype=np.float64).reshape(-1, 2)
    if len(m) == 0:
        return False
    return bool(np.any(np.hypot(m[:, 0] - b[0], m[:, 1] - b[1]) <= radius_m))


class DeadlockBreaker:
    """Watches progress towards the goal and runs the back-off (see the module docstring)."""

    def __init__(self, config: DeadlockConfig | None = None, *, seed: int = 0) -> None:
        self.config = config or DeadlockConfig()
        self._rng = np.random.default_rng(seed)
        self.phase = Phase.DRIVE
        self.deadlocks = 0  # detections over the breaker's life
        self.attempts = 0  # deadlocks on the current goal
        self.backoff_target_in_odom: NDArray[np.float64] | None = None
        self._target_back_m = 0.0
        self._trail: deque[NDArray[np.float64]] = deque()
        self._goal: NDArray[np.float64] | None = None
        self._best_m = math.inf
        self._best_t = -math.inf
        self._motion: deque[tuple[float, NDArray[np.float64]]] = deque()
        self._phase_since_s = -math.inf
        self._hold_until_s = -math.inf
        self._stall_s = self._draw_stall()
        self._block_closest_m = math.inf
        self.failed_escapes = 0  # back-offs in a row on this goal that did not move the robot
        self._stuck_xy: NDArray[np.float64] | None = None  # where the deadlock struck
        self._tried: list[NDArray[np.float64]] = []  # back-off targets tried on this goal
        self._stalled_after_giving_up = False

    @property
    def exhausted(self) -> bool:
        """Nothing more to try on this goal: ``max_failed_escapes`` back-offs in a row did not
        move the robot, or it gave up and then stalled again. The node reports the task
        failed (:attr:`exhaustion_reason`)."""
        return (
            self.failed_escapes >= self.config.max_failed_escapes or self._stalled_after_giving_up
        )

    @property
    def exhaustion_reason(self) -> str:
        """Why :attr:`exhausted` (empty when it is not)."""
        if self.failed_escapes >= self.config.max_failed_escapes:
            return (
                f"deadlocked: {self.failed_escapes} back-offs in a row could not move the "
                f"robot {self.config.escape_min_motion_m:g} m"
            )
        if self._stalled_after_giving_up:
            return f"deadlocked: no progress after {self.attempts} back-offs"
        return ""

    @property
    def gave_up(self) -> bool:
        """``max_attempts`` deadlocks on this goal: the breaker no longer interferes."""
        return self.attempts >= self.config.max_attempts

    @property
    def trail_in_odom(self) -> NDArray[np.float64]:
        """``(K, 2)`` recent positions, oldest first, about ``trail_spacing_m`` apart."""
        return np.array(self._trail).reshape(-1, 2)

    def reset(self) -> None:
        """Forget the goal and any back-off (a new task, pause, tele-operation)."""
        self.phase = Phase.DRIVE
        self.attempts = 0
        self.backoff_target_in_odom = None
        self._goal = None
        self._motion.clear()
        self._forget_escapes()

    def update(self, now_s: float, pose_in_odom: ArrayLike, goal_in_odom: ArrayLike) -> Phase:
        """One control period at ``pose_in_odom`` pursuing ``goal_in_odom``; returns the phase
        (:attr:`Phase.DEADLOCKED` once per detection)."""
        cfg = self.config
        xy = _xy("pose_in_odom", pose_in_odom)
        goal = _xy("goal_in_odom", goal_in_odom)
        self._record(xy)
        if self._goal is None or float(np.hypot(*(goal - self._goal))) > 1e-6:
            self._goal = goal
            self.attempts = 0
            self.phase = Phase.DRIVE
            self.backoff_target_in_odom = None
            self._forget_escapes()
            self._restart(now_s, xy)
        if not cfg.enabled:
            return self.phase
        if self.phase is Phase.BACKOFF:
            target = self.backoff_target_in_odom
            arrived = target is None or float(np.hypot(*(xy - target))) <= cfg.arrive_m
            if arrived or now_s - self._phase_since_s >= cfg.backoff_timeout_s:
                self._end_escape(xy)
                self._hold(now_s)
            return self.phase
        if self.phase is Phase.HOLD:
            if now_s >= self._hold_until_s:
                self.phase = Phase.DRIVE
                self.backoff_target_in_odom = None
                self._restart(now_s, xy)
            return self.phase
        if self.phase is Phase.DEADLOCKED:
            return self.phase
        d = float(np.hypot(*(goal - xy)))
        if d < self._best_m - cfg.min_progress_m:
            self._best_m, self._best_t = d, now_s
        self._motion.append((now_s, xy))
        while self._motion and self._motion[0][0] < now_s - self._stall_s:
            self._motion.popleft()
        waited = now_s - self._best_t
        stalled = waited >= self._stall_s and self._spread() < cfg.stall_motion_m
        if self.gave_up:
            if stalled or waited >= cfg.livelock_s:
                self._stalled_after_giving_up = True
            return self.phase
        if stalled or waited >= cfg.livelock_s:
            self._stuck_xy = xy.copy()
            self.phase = Phase.DEADLOCKED
            self.deadlocks += 1
            self.attempts += 1
            self._phase_since_s = now_s
        return self.phase

    def _spread(self) -> float:
        """How far the robot got from the oldest position of the stall window (only asked
        once the progress has stalled that long: every control period it cost an array of
        the window's positions)."""
        pts = np.array([p for _, p in self._motion])
        return float(np.max(np.hypot(*(pts - pts[0]).T))) if len(pts) else 0.0

    def note_block_distance(self, now_s: float, distance_m: float) -> None:
        """While waiting: the path being followed is blocked ``distance_m`` ahead. Something
        receding (the distance grew by ``recede_m`` since the closest) is progress: the stall
        timer restarts, so a robot does not back off from one that is backing off."""
        if self.phase is not Phase.DRIVE or not math.isfinite(distance_m):
            return
        if distance_m < self._block_closest_m:
            self._block_closest_m = distance_m
        elif distance_m >= self._block_closest_m + self.config.recede_m:
            self._block_closest_m = distance_m
            self._best_t = now_s
            self._motion.clear()

    def start_backoff(
        self, now_s: float, obstacle: NDArray[np.bool_], geometry: GridGeometry
    ) -> NDArray[np.float64] | None:
        """Choose where to back off to on the trail, using the current ``obstacle`` map laid out
        by ``geometry`` in ``odom``; returns it (the phase is then BACKOFF), or None when the
        trail offers nowhere to go (the robot then holds where it is)."""
        cfg = self.config
        if self.phase is not Phase.DEADLOCKED:
            raise ValueError(f"start_backoff: no deadlock to break (phase {self.phase.value})")
        obs = np.asarray(obstacle)
        if obs.shape != geometry.shape or obs.dtype != np.bool_:
            raise ValueError(
                f"obstacle: expected a bool grid of shape {geometry.shape}, got "
                f"{obs.dtype} {obs.shape}"
            )
        chosen = self._choose(obs, geometry, min_back_m=cfg.backoff_min_m)
        if chosen is not None and self.failed_escapes > 0:
            chosen = self._choose_untried(obs, geometry) or chosen
        self._phase_since_s = now_s
        if chosen is None:
            self.failed_escapes += 1  # nowhere to back off to
            self._hold(now_s)
            return None
        self.phase = Phase.BACKOFF
        self.backoff_target_in_odom, self._target_back_m = chosen
        self._tried.append(chosen[0].copy())
        return self.backoff_target_in_odom

    def abort_backoff(self, now_s: float) -> None:
        """The way back turned out to be blocked (no path to the target): hold here."""
        if self.phase is Phase.BACKOFF:
            self.backoff_target_in_odom = None
            self.failed_escapes += 1
            self._hold(now_s)

    def trail_back_path(self, position_in_odom: ArrayLike) -> NDArray[np.float64]:
        """``(K, 2)`` the trail reversed (newest first) from the robot back to the back-off
        target: ground the robot has just driven, so known passable when the planner, over a
        map that has since closed it (a doorway's dilated jambs, a teammate's ghost), finds no
        way; from the trail point nearest ``position_in_odom``. Empty when not backing off or
        no trail is left between the robot and the target."""
        pos = _xy("position_in_odom", position_in_odom)
        target = self.backoff_target_in_odom
        trail = self.trail_in_odom[::-1]
        if self.phase is not Phase.BACKOFF or target is None or len(trail) < 2:
            return np.zeros((0, 2))
        end = int(np.argmin(np.hypot(*(trail - target).T)))
        start = int(np.argmin(np.hypot(*(trail[: end + 1] - pos).T)))
        if end - start < 1:
            return np.zeros((0, 2))
        return np.array(trail[start : end + 1], dtype=np.float64)

    def refine_backoff(
        self, obstacle: NDArray[np.bool_], geometry: GridGeometry
    ) -> NDArray[np.float64] | None:
        """While backing off, look again with a newer map (the robot now faces the way back,
        which its LIDAR could not see when it chose): if the target turns out to have too
        little room, move it further back along the trail to the first point that has it.
        Returns the (possibly unchanged) target."""
        if self.phase is not Phase.BACKOFF or self.backoff_target_in_odom is None:
            return self.backoff_target_in_odom
        obs = np.asarray(obstacle)
        if obs.shape != geometry.shape or obs.dtype != np.bool_:
            raise ValueError(
                f"obstacle: expected a bool grid of shape {geometry.shape}, got "
                f"{obs.dtype} {obs.shape}"
            )
        chosen = self._choose(obs, geometry, min_back_m=self._target_back_m, roomy_only=True)
        if chosen is not None:
            self.backoff_target_in_odom, self._target_back_m = chosen
        return self.backoff_target_in_odom

    # ------------------------------------------------------------------ internals

    def _record(self, xy: NDArray[np.float64]) -> None:
        cfg = self.config
        if self.phase in (Phase.BACKOFF, Phase.HOLD):
            return  # the trail is the way we came; backing off must not extend it
        if not self._trail or float(np.hypot(*(xy - self._trail[-1]))) >= cfg.trail_spacing_m:
            self._trail.append(xy.copy())
            while len(self._trail) > cfg.trail_length_m / cfg.trail_spacing_m:
                self._trail.popleft()

    def _forget_escapes(self) -> None:
        self.failed_escapes = 0
        self._stuck_xy = None
        self._tried = []
        self._stalled_after_giving_up = False

    def _end_escape(self, xy: NDArray[np.float64]) -> None:
        """A back-off ended at ``xy``: count it failed when it left the robot where it was."""
        start = self._stuck_xy
        if start is not None and float(np.hypot(*(xy - start))) < self.config.escape_min_motion_m:
            self.failed_escapes += 1
        else:
            self.failed_escapes = 0

    def _far(self, pick: NDArray[np.bool_], trail: NDArray[np.float64]) -> NDArray[np.bool_]:
        """``pick`` narrowed to trail points ``backoff_min_m`` from the robot in a straight
        line when any is: a trail that coiled in a nook (seed 0 after issue 14's first fix: a
        robot wiggling in a dead end) has points far back along it that are beside the robot,
        and backing off to one moves it nowhere."""
        far = pick & (np.hypot(*(trail - trail[0]).T) >= self.config.backoff_min_m - 1e-9)
        return far if far.any() else pick

    def _choose_untried(
        self, obstacle: NDArray[np.bool_], geometry: GridGeometry
    ) -> tuple[NDArray[np.float64], float] | None:
        """After a failed escape: the nearest trail point at least ``backoff_min_m`` back and
        ``arrive_m`` from every target tried, preferring those with passing room."""
        cfg = self.config
        trail = self.trail_in_odom[::-1]
        if len(trail) < 2:
            return None
        back = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(trail, axis=0).T))])
        pick = self._far((back >= cfg.backoff_min_m - 1e-9) & (back <= cfg.backoff_max_m), trail)
        for t in self._tried:
            pick &= np.hypot(*(trail - t).T) > cfg.arrive_m
        rc = geometry.cell_of(trail)
        pick &= (
            (rc[:, 0] >= 0)
            & (rc[:, 0] < geometry.rows)
            & (rc[:, 1] >= 0)
            & (rc[:, 1] < geometry.cols)
        )
        idx = np.flatnonzero(pick)
        if len(idx) == 0:
            return None
        room = clearance_field(obstacle, resolution_m=geometry.resolution_m)[rc[idx, 0], rc[idx, 1]]
        roomy = idx[room >= cfg.passing_clearance_m]
        best = int(roomy[0]) if len(roomy) else int(idx[int(np.argmax(room))])
        return np.asarray(trail[best], dtype=np.float64), float(back[best])

    def _restart(self, now_s: float, xy: NDArray[np.float64]) -> None:
        assert self._goal is not None
        self._best_m = float(np.hypot(*(self._goal - xy)))
        self._best_t = now_s
        self._motion.clear()
        self._stall_s = self._draw_stall()
        self._block_closest_m = math.inf

    def _draw_stall(self) -> float:
        cfg = self.config
        return cfg.stall_s + float(self._rng.uniform(0.0, cfg.stall_jitter_s))

    def _hold(self, now_s: float) -> None:
        cfg = self.config
        spread = min(cfg.hold_spread_s * 2.0 ** max(0, self.attempts - 1), cfg.hold_spread_max_s)
        self.phase = Phase.HOLD
        self._hold_until_s = now_s + cfg.hold_s + float(self._rng.uniform(0.0, spread))

    def _choose(
        self,
        obstacle: NDArray[np.bool_],
        geometry: GridGeometry,
        *,
        min_back_m: float,
        roomy_only: bool = False,
    ) -> tuple[NDArray[np.float64], float] | None:
        """The first trail point ``min_back_m`` or more back (along the trail from where the
        deadlock struck) with ``passing_clearance_m`` of room, else (unless ``roomy_only``)
        the roomiest; with its distance back."""
        cfg = self.config
        trail = self.trail_in_odom[::-1]  # newest first
        if len(trail) < 2:
            return None
        back = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(trail, axis=0).T))])
        pick = self._far((back >= min_back_m - 1e-9) & (back <= cfg.backoff_max_m), trail)
        if not pick.any():
            if roomy_only:
                return None
            pick = back <= cfg.backoff_max_m
            pick[0] = False
            if not pick.any():
                return None
        candidates, distances = trail[pick], back[pick]
        rc = geometry.cell_of(candidates)
        inside = (
            (rc[:, 0] >= 0)
            & (rc[:, 0] < geometry.rows)
            & (rc[:, 1] >= 0)
            & (rc[:, 1] < geometry.cols)
        )
        if not inside.any():
            return None
        candidates, distances, rc = candidates[inside], distances[inside], rc[inside]
        room = clearance_field(obstacle, resolution_m=geometry.resolution_m)[rc[:, 0], rc[:, 1]]
        roomy = np.flatnonzero(room >= cfg.passing_clearance_m)
        if roomy_only and len(roomy) == 0:
            return None
        best = int(roomy[0]) if len(roomy) else int(np.argmax(room))
        return np.asarray(candidates[best], dtype=np.float64), float(distances[best])
