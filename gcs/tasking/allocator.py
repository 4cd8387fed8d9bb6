"""Task allocation: the GCS's planners composed (paper 5.1).

:meth:`TaskAllocator.plan` takes a :class:`TaskingState` (what the GCS knows: the rasterized
global map, robot poses in ``map`` and ``map_from_odom``, when each robot was last heard, roles,
task reports, hazards, the pose-graph trajectories) and returns ``(robot_id, task message)``
pairs for the GCS node to send. The allocator holds only planning memory (tasks issued, failed
goals, lock bookkeeping); it does no IO. Each call, in order of urgency:

1. bookkeeping: robots silent longer than ``silent_after_s`` or lost (``lost_after_s``, or
   flagged) are not counted on: nothing is sent to them (a robot out of radio contact keeps
   its last task) and their OOIs and hostile views go to others; a silent robot's exploration
   goal stays claimed while within its timeout (it drives on in the shadow; handed over, the
   next robot went into the same shadow) and goes to others once it is lost; task reports close
   tasks (succeeded, failed, rejected, canceled; a goal not reached within its timeout fails);
2. safety: a robot inside a keep-out disc (a static OOI's trigger radius, a hostile's blast
   radius, plus margins) drives to the nearest safe cell;
3. hostiles (:mod:`~gcs.tasking.hostile_planner`): two sensor robots keep each in view until
   the 30 s lock holds;
4. disruptors (:mod:`~gcs.tasking.disruptor_planner`, 5.1.2): each live static OOI gets the
   nearest free disruptor by highway, then a :class:`~protocol.messages.NeutralizeTask` once
   it is there and approved (``auto`` approval is counted in :attr:`TaskingStats`); idle
   disruptors spread over the highway;
5. exploration (:mod:`~gcs.tasking.exploration_planner`, 5.1.1) for the other sensor robots:
   a new goal when the last was reached, failed or its frontier is gone; a robot never gets
   back a goal it failed; no frontier left: ``explored`` and the sensor robots park. Goals
   go on as tours along the frontier (a robot out of radio contact sweeps it, then comes
   back to contact); in the last ``end_contact_s`` of the mission (``TaskingState.
   mission_end_s``) only goals a robot can be back in contact from before the end.

Goals leave in each robot's private frame (``waypoints_in_odom = odom_from_map * waypoints_in_map``,
paper 4.1).
"""

from __future__ import annotations

import copy
import dataclasses
import enum
import logging
import math
import time
from dataclasses import dataclass, field

import msgspec
import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components

from gcs.mapping.rasterization import OCCUPIED, OccupancyMap
from gcs.tasking.disruptor_planner import DisruptorConfig, dispatch_disruptor, spread_positions
from gcs.tasking.exploration_planner import (
    ExplorationConfig,
    Explorer,
    failed_route_discs,
    plan_exploration,
    return_leg,
    shortcut,
)
from gcs.tasking.frontiers import Frontiers, find_frontiers
from gcs.tasking.hostile_planner import (
    HostileConfig,
    HostileLock,
    evasion_goal,
    view_positions,
    watch_slots,
)
from gcs.tasking.information_gain import information_gain
from gcs.tasking.planning_grid import PlanningGrid, coarsen
from gcs.tasking.relay_planner import relay_spots
from gcs.tasking.trajectory_graph import (
    TrajectoryGraph,
    TrajectoryGraphConfig,
    build_trajectory_graph,
)
from protocol.messages import (
    GoToTask,
    Hazard,
    IdleTask,
    NeutralizeTask,
    ObjectKind,
    RelayTask,
    TaskState,
    TaskStatus,
)
from protocol.operator import OPERATOR_TASK_IDS_FROM
from protocol.se2 import inverse, transform_points

__all__ = [
    "Assignment",
    "Role",
    "RobotInfo",
    "TaskAllocator",
    "TaskingConfig",
    "TaskingEvent",
    "TaskingState",
    "TaskingStats",
]

TaskMessage = GoToTask | NeutralizeTask | IdleTask | RelayTask
log = logging.getLogger(__name__)
_TERMINAL = (TaskState.SUCCEEDED, TaskState.FAILED, TaskState.REJECTED, TaskState.CANCELED)


def _duplicates_of(hazards: list[Hazard], done: set[int], radius_m: float) -> list[Hazard]:
    """Static hazards (static OOIs, vats) not in ``done`` within ``radius_m`` of a ``done``
    hazard of their kind: the same object placed apart by two robots' maps. Transitive: a
    chain of sightings each within ``radius_m`` of the next is one object."""
    kinds = (ObjectKind.STATIC_OOI, ObjectKind.TOXIC_VAT)
    static = [h for h in hazards if h.kind in kinds]
    covered = [h for h in static if h.hazard_id in done]
    out: list[Hazard] = []
    rest = [h for h in static if h.hazard_id not in done]
    while covered:
        c = covered.pop()
        near = [
            h
            for h in rest
            if h.kind == c.kind and math.dist(h.position_in_map, c.position_in_map) < radius_m
        ]
        rest = [h for h in rest if h not in near]
        out.extend(near)
        covered.extend(near)
    return out


class Role(enum.Enum):
    SENSOR = "sensor"
    DISRUPTOR = "disruptor"


class TaskingConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Everything task allocation runs with (metres, seconds).

    ``planning_resolution_m``: cell of the coarse planning grid; ``robot_radius_m``: clearance
    from obstacles; ``snap_m``: how far from its own cell a robot's start cell may be;
    ``silent_after_s`` / ``lost_after_s``: radio silence before a robot is not counted on /
    written off; ``goal_timeout_base_s`` + path length / ``assumed_speed_m_s``: time to reach a
    goal before it counts as failed; ``frontier_gone_m``: a goal whose frontier has no cell
    this close is abandoned; ``goal_failures_global``: robots that must fail a goal before no
    robot gets it; ``keepout_margin_m``: added to trigger and blast radii for every robot;
    ``first_task_id``: ids of the allocator's tasks count up from here."""

    planning_resolution_m: float = 0.3
    robot_radius_m: float = 0.35
    snap_m: float = 1.5
    silent_after_s: float = 10.0
    lost_after_s: float = 60.0
    goal_timeout_base_s: float = 30.0
    assumed_speed_m_s: float = 0.3
    frontier_gone_m: float = 1.5
    goal_failures_global: int = 3
    keepout_margin_m: float = 1.0
    # a disruptor that failed an OOI's neutralization (it saw no OOI near the GCS's target,
    # say) is not sent to that OOI again for this long; then it may be (a lone disruptor
    # would otherwise leave the OOI for good)
    neutralize_retry_s: float = 60.0
    # a sensor robot that fell silent on its way to watch a hostile (radio shadow: MAGIC's
    # robots lost the radio behind buildings) is not sent to watch it for this long: back in
    # contact it was re-sent into the same shadow, over and over (small world seed 0: robots
    # 0 and 1 took turns, robot_back -> hostile_view -> robot_silent, from 95 s to the end)
    shadow_retry_s: float = 90.0
    # ... and one that fell silent on its way to watch a hostile is not sent to watch it for
    # view_shadow_retry_s (0: off; one silent at its view position never is). Watchers sent
    # into the walker's radio shadow fall silent on their way, are heard again seconds later
    # and, barred, are sent to explore just as both come within 12 m of the walker (small
    # world seed 7 at ec6bf10: 122.6 s silent, 126.8 s back and off exploring); 0 goes with
    # the robots' keep_view (robot.control.hostile_evasion, off: its measurement there)
    view_shadow_retry_s: float = 90.0
    # a watcher (hostile_view) heard again after a silence keeps its watch while its hostile
    # is live, rather than being re-planned (sent exploring): a watcher keeping the walker
    # in view in its radio shadow came back in contact 8-11 m from it and was sent off
    # (small world seed 7 at ec6bf10, 126.8 s). Off by default: it goes with the robots'
    # keep_view (robot.control.hostile_evasion, off; without it a watcher back from its
    # silence stands at its point of contact, idle, counted as watching). Measured with it,
    # keep_view and view_shadow_retry_s 0 in keep_view's docstring (session 15)
    watch_on_return: bool = False
    # ... nor given an exploration goal within shadow_goal_radius_m of the one it fell
    # silent on, for shadow_retry_s (issue 17); 0: off. Small world, 300 s, seeds 0/7/3/11,
    # with the hostile rules: 2 m explored 0.878/0.843/0.960/0.948 (ATE 0.23/0.55/0.19/0.13),
    # 5 m 0.926/0.887/0.944/0.956 (ATE 0.83/0.45/0.17/0.26: robots kept off their shadows
    # explore new ground and close fewer loops), off 0.907/0.876/0.934/0.948 (ATE
    # 0.21/0.43/0.22/0.13)
    shadow_goal_radius_m: float = 2.0
    # a robot whose evasion of a hazard failed this often (it could not get out: jammed
    # with others in a corridor, the way out behind a wall) is not sent to evade it again;
    # the full mission re-sent three robots out of one keep-out every 37 s for 600 s
    evade_attempts: int = 2
    # static hazards of one kind closer than this are one object seen from robots whose map
    # positions disagree (small world seed 0: one OOI as hazards 0.9, 1.1 and 3.3 m from it,
    # the station merges at 1.5 m): once one is neutralized the others are too, and only one
    # of them has a disruptor at a time (the robot's laser snaps to its own detection)
    duplicate_m: float = 4.0
    # radio contact (exploration.return_to_contact): where a robot is while the GCS has heard
    # it at most contact_fresh_s apart for contact_steady_s is a point of contact, kept on a
    # contact_bin_m lattice. Steady: a robot just back from a shadow is heard at the shadow's
    # fringe, and the pose the GCS has of it is still one from the shadow (its backlog
    # drains first): small world seed 0, a robot sent back to such a point sat there 40 s
    contact_fresh_s: float = 3.0
    contact_steady_s: float = 10.0
    contact_bin_m: float = 1.0
    # an exploring robot this close to its goal is there (its task goes on: the way back to
    # contact), and re-planned; a goal reached whose frontier is still there is not given to
    # that robot again (what is left there cannot be seen from it)
    goal_reached_m: float = 1.0
    # an exploring robot the GCS hears that has not moved stall_m in stall_s is stuck (two
    # robots jammed in a passage, say: small world seed 0, a robot 45 s within 5 m beside an
    # idle disruptor): its goal counts as failed for it and it gets another
    stall_s: float = 20.0
    stall_m: float = 1.0
    # ... or has not come stall_m nearer its goal in stall_progress_s (a robot backing off
    # and retrying, to and fro: seed 0, 50 s within 3 m)
    stall_progress_s: float = 40.0
    # an exploration route that failed (the task failed or timed out, or the robot stalled
    # on it) is avoided by that robot for avoid_s: discs of avoid_radius_m over the route from
    # avoid_from_m to avoid_to_m past where the robot was (exploration_planner
    # .failed_route_discs); the goal alone was blacklisted, and the next goal a few metres
    # beside it went through the same doorway (small world seed 0: one robot, six goals, 140 s)
    avoid_s: float = 120.0
    avoid_from_m: float = 0.5
    avoid_to_m: float = 3.0
    avoid_radius_m: float = 0.75
    # idle disruptors hold where they are sent as radio relays (RelayTask), and one goes to
    # the relay spot of each sensor robot out of contact (relay_planner.relay_spots) before
    # spreading (paper 4.1: robots used as relays when a robot leaves radio range)
    relays: bool = True
    # relays chained outwards (relay_planner.relay_spots hop_m): each silent robot's edge
    # spot is followed by a second spot up to relay_hop_m of highway further towards it (the
    # radio routes over up to three hops: GCS, relay, relay, robot); 0: off. Relay spots are
    # kept for relay_keep_s after a silent robot last called for them, a relay holding at a
    # kept spot stays there and one on its way to one goes on (the idle spread does not pull
    # it back, newer spots do not turn it round); 0: off. Why: a spot called for by robots
    # out of contact went when they were heard again and the relay left for the spread, near
    # the GCS (full mission seed 0 at 8183549: the four disruptors' mean x 13-36 m, contact
    # ending at x 70-80 m). Both off by default: full mission seed 0, 600 s, at 1d6eb73 + dc4f09f
    # (the highway entry), with 30 m / 120 s: explored 0.397 (0.410 at 1d6eb73; 0.412 with the
    # chain and the keep but relays on their way re-targeted), sensor robots out of contact
    # (simulator's radio, scoring only) 41.8 % against 46.9 % out of direct contact (1d6eb73:
    # 48.6 / 55.4), the disruptors' mean x 17-41 m (5-26), no sensor robot ever routed over
    # 3 hops: relays spent 170-390 s of 600 driving to spots (0.3 m/s over 40-80 m of
    # highway) and 6-266 s holding at them, and the disruptors were on OOIs 45-80 % of the
    # time. The outward spot never fired there: every silent robot's nearest waypoint was
    # within 30 m of highway of its edge spot (the highway beyond contact is only where
    # robots came back from; a robot falls silent at the edge of what is known), and with
    # the chain and keep but no staying on the way the run is the one at dc4f09f to 445 s
    # (explored 0.412 both). Quick mission seeds 0/7/3/11 (30 m / 120 s): explored
    # 0.944/0.887/0.940/0.871 against 0.955/0.945/0.942/0.871 at dc4f09f (seed 7: the
    # relay kept on its spot reached an OOI from another side, its laser missed: 0.5)
    relay_hop_m: float = 0.0
    relay_keep_s: float = 0.0
    # the end of the mission (TaskingState.mission_end_s): what a robot out of radio contact
    # saw when the mission ends never reaches the GCS's map. In the last end_contact_s an
    # exploration goal is given only if the robot can drive to it and on to the nearest
    # point of radio contact (straight lines, at end_speed_m_s) before the end, and goals
    # are not extended into tours; 0: off
    # The rule acts only when the mission's end is known (MissionControlConfig.mission_end_s,
    # unset by default). Quick mission at bbbb9f5 with mission_end_s 300, seeds 0 / 7 / 3 / 11:
    # explored 0.925 / 0.925 / 0.944 / 0.938 (median 0.932), ATE median 0.276 m, F1 0.819,
    # against 0.941, 0.223 m and 0.840 without it (0 lost both): in the small world nearly
    # every goal is in contact, so it only takes goals away; it stays unset by default.
    end_contact_s: float = 90.0
    end_speed_m_s: float = 0.5
    first_task_id: int = 1_000_000
    exploration: ExplorationConfig = msgspec.field(default_factory=ExplorationConfig)
    highway: TrajectoryGraphConfig = msgspec.field(default_factory=TrajectoryGraphConfig)
    disruptor: DisruptorConfig = msgspec.field(default_factory=DisruptorConfig)
    hostile: HostileConfig = msgspec.field(default_factory=HostileConfig)

    def __post_init__(self) -> None:
        for name in (
            "planning_resolution_m",
            "snap_m",
            "silent_after_s",
            "lost_after_s",
            "goal_timeout_base_s",
            "assumed_speed_m_s",
            "frontier_gone_m",
            "neutralize_retry_s",
            "shadow_retry_s",
            "duplicate_m",
            "contact_fresh_s",
            "contact_steady_s",
            "contact_bin_m",
            "goal_reached_m",
            "stall_s",
            "stall_m",
            "stall_progress_s",
            "avoid_s",
            "avoid_radius_m",
            "end_speed_m_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"tasking {name} must be finite and > 0, got {v}")
        if not (math.isfinite(self.view_shadow_retry_s) and self.view_shadow_retry_s >= 0):
            raise ValueError(
                f"tasking view_shadow_retry_s must be >= 0, got {self.view_shadow_retry_s}"
            )
        if not (math.isfinite(self.robot_radius_m) and self.robot_radius_m >= 0):
            raise ValueError(f"tasking robot_radius_m must be >= 0, got {self.robot_radius_m}")
        if self.lost_after_s < self.silent_after_s:
            raise ValueError("tasking lost_after_s must be >= silent_after_s")
        if not (0 <= self.avoid_from_m <= self.avoid_to_m and math.isfinite(self.avoid_to_m)):
            raise ValueError(
                f"tasking needs 0 <= avoid_from_m <= avoid_to_m (finite), got "
                f"{self.avoid_from_m}, {self.avoid_to_m}"
            )
        if not (math.isfinite(self.shadow_goal_radius_m) and self.shadow_goal_radius_m >= 0):
            raise ValueError(
                f"tasking shadow_goal_radius_m must be finite and >= 0, got "
                f"{self.shadow_goal_radius_m}"
            )
        for name in ("relay_hop_m", "relay_keep_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"tasking {name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.end_contact_s) and self.end_contact_s >= 0):
            raise ValueError(
                f"tasking end_contact_s must be finite and >= 0, got {self.end_contact_s}"
            )
        if self.evade_attempts < 1:
            raise ValueError(f"tasking evade_attempts must be >= 1, got {self.evade_attempts}")
        if self.goal_failures_global < 1:
            raise ValueError("tasking goal_failures_global must be >= 1")
        # the robots tell the planners' tasks from the operators' by id (an operator's task is
        # semi-autonomous time, paper 7): the planners' ids must stay below the operators'
        if not (0 < self.first_task_id < OPERATOR_TASK_IDS_FROM):
            raise ValueError(
                f"tasking first_task_id must be > 0 and below the operators' task ids "
                f"({OPERATOR_TASK_IDS_FROM}), got {self.first_task_id}"
            )


@dataclass
class RobotInfo:
    """One robot as the GCS sees it. ``pose_in_map`` / ``map_from_odom`` ``(x_m, y_m, yaw_rad)``
    (None until its trajectory is anchored in ``map``); ``status``: its latest task report;
    ``operator_controlled``: an operator's task overrides the planners (paper 5.1.3);
    ``lost``: written off by the GCS (e.g. the rules disabled it)."""

    robot_id: int
    role: Role
    pose_in_map: tuple[float, float, float] | None
    map_from_odom: tuple[float, float, float] | None
    last_heard_s: float
    status: TaskStatus | None = None
    operator_controlled: bool = False
    lost: bool = False


def _empty_ids() -> NDArray[np.int64]:
    return np.zeros(0, dtype=np.int64)


@dataclass
class TaskingState:
    """What the GCS node fills for :meth:`TaskAllocator.plan`.

    ``occupancy``: the rasterized global map (its origin and resolution inside);
    ``hazards``: every known hazard in ``map`` (ids stable); ``trajectory_*``: the pose graph's
    nodes at their current posterior (robot id, key increasing along each trajectory, x/y in
    map: ``GroundStation.poses_in_map`` with each key's robot); ``hostile_seen_s``:
    ``hazard_id -> robot_id -> last time that robot detected that hostile``;
    ``approved_hazard_ids``: neutralizations an operator approved; ``neutralized_hazard_ids``:
    hazards known neutralized (the allocator also tracks the ones it completed);
    ``mission_end_s``: when the mission ends (``inf``: not known)."""

    occupancy: OccupancyMap
    robots: list[RobotInfo]
    hazards: list[Hazard] = field(default_factory=list)
    trajectory_robot_ids: NDArray[np.int64] = field(default_factory=_empty_ids)
    trajectory_keys: NDArray[np.int64] = field(default_factory=_empty_ids)
    trajectory_xy_in_map: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))
    hostile_seen_s: dict[int, dict[int, float]] = field(default_factory=dict)
    approved_hazard_ids: frozenset[int] = frozenset()
    neutralized_hazard_ids: frozenset[int] = frozenset()
    # when the mission ends (mission seconds; inf: not known): see TaskingConfig.end_contact_s
    mission_end_s: float = math.inf


@dataclass
class Assignment:
    """A task the allocator issued. ``purpose``: ``explore``, ``park``, ``evade``,
    ``hostile_view``, ``neutralize_go``, ``neutralize``, ``spread``."""

    task_id: int
    purpose: str
    issued_s: float
    goal_in_map: tuple[float, float] | None = None
    hazard_id: int | None = None
    timeout_s: float = math.inf
    # ``(K, 2)`` the way sent, from where the robot was (``_goto`` tasks)
    route_in_map: NDArray[np.float64] | None = None
    # ``(T, 2)`` an exploration tour's goals after ``goal_in_map`` (claimed while the robot
    # is out of contact: it drives them)
    tour_in_map: NDArray[np.float64] | None = None


@dataclass(frozen=True)
class TaskingEvent:
    """Something the allocator decided or noticed, for the journal and the operator."""

    time_s: float
    kind: str
    robot_id: int | None
    text: str
    hazard_id: int | None = None


@dataclass
class TaskingStats:
    plans: int = 0
    tasks_issued: int = 0
    goals_reached: int = 0
    goals_failed: int = 0
    reassigned: int = 0
    approvals_auto: int = 0
    approvals_operator: int = 0
    neutralized: int = 0
    hostiles_locked: int = 0
    explored: bool = False
    internal_errors: int = 0
    last_plan_wall_s: float = 0.0


@dataclass
class _WatchArea:
    """A hostile being watched or paused, by where its latest sighting watched is (sightings
    of a walker get new hazard ids as it walks: the record follows them)."""

    xy: tuple[float, float]
    began_s: float | None = None
    paused_until_s: float = -math.inf
    pauses: int = 0


@dataclass
class _Ctx:
    now_s: float
    state: TaskingState
    grid: PlanningGrid
    highway: TrajectoryGraph
    blocked: NDArray[np.bool_]
    robots: dict[int, RobotInfo]
    available: dict[int, RobotInfo]
    cells: dict[int, tuple[int, int]]
    static_live: list[Hazard]
    hostiles_live: list[Hazard]
    # every static OOI, done ones too: the station sends the robots every hazard and a robot
    # keeps out of each (robot/control/keepout.py), neutralized or not
    static_all: list[Hazard]
    out: list[tuple[int, TaskMessage]] = field(default_factory=list)


class TaskAllocator:
    """The planners' memory and composition (see the module docstring). Not thread-safe: the
    GCS node calls :meth:`plan` from its step."""

    def __init__(self, config: TaskingConfig | None = None) -> None:
        self.config = config or TaskingConfig()
        self.assignments: dict[int, Assignment] = {}
        self.stats = TaskingStats()
        self.events: list[TaskingEvent] = []
        self.pending_approvals: set[int] = set()
        self.neutralized: set[int] = set()
        self.frontiers: Frontiers | None = None
        self.grid: PlanningGrid | None = None
        self.highway: TrajectoryGraph | None = None
        self._next_id = self.config.first_task_id
        self._failed_goals: dict[int, list[tuple[float, float]]] = {}
        # robot -> discs (x, y, radius, until_s) its exploration routes avoid
        self._avoid: dict[int, list[tuple[float, float, float, float]]] = {}
        self._goal_failures: list[tuple[tuple[float, float], int]] = []
        # hazard -> robot -> when it failed that hazard's neutralization
        self._dispatch_excluded: dict[int, dict[int, float]] = {}
        # (ooi_x, ooi_y, pose_x, pose_y) in map: where disruptors failed to laser an OOI from
        # (disruptor_planner.failed_view_mask: the next dispatch goes to another side)
        self._failed_views: list[tuple[float, float, float, float]] = []
        self._silent: set[int] = set()
        # hostile -> robot -> when it fell silent on its way to watch that hostile
        self._view_shadowed: dict[int, dict[int, float]] = {}
        self._no_start: set[int] = set()
        self._lost: set[int] = set()
        # robot -> (exploration goal, when) it fell silent on its way to
        self._explore_shadowed: dict[int, list[tuple[tuple[float, float], float]]] = {}
        # (robot, hazard) -> how often the robot's evasion of the hazard failed
        self._evade_failures: dict[tuple[int, int], int] = {}
        self._lock = HostileLock(self.config.hostile)
        self._hostile_at: dict[int, tuple[float, float]] = {}
        # one record a hostile watched (by where its latest sighting is): when its watch
        # began, how often and until when it is paused
        self._watch_areas: list[_WatchArea] = []
        self._spread_at_s = -math.inf
        self._spread_key: tuple[tuple[int, ...], tuple[int, ...]] = ((), ())
        # relay spots kept (relay_keep_s): [x, y, until_s] in map
        self._relay_kept: list[list[float]] = []
        # points of radio contact (lattice cells of contact_bin_m) and their centres
        self._contact_bins: set[tuple[int, int]] = set()
        self._contact_xy: list[tuple[float, float]] = []
        self._heard_since: dict[int, float] = {}  # robot -> heard without a gap since
        # robot -> (task id, when, where) it last moved stall_m on its exploration task
        self._progress: dict[int, tuple[int, float, tuple[float, float]]] = {}
        # robot -> (task id, when, distance) it last came stall_m nearer its goal
        self._nearer: dict[int, tuple[int, float, float]] = {}

    # ---- the step ---------------------------------------------------------------------------

    def plan(self, state: TaskingState, now_s: float) -> list[tuple[int, TaskMessage]]:
        """Tasks to send now (see the module docstring); :attr:`events` says why.

        Never raises: an internal failure is logged, counted (``stats.internal_errors``) and
        reported as an ``internal_error`` event, the planning memory is rolled back to before
        the call (no task is recorded that was not returned) and nothing is sent."""
        t0 = time.perf_counter()
        self.events = []
        self.stats.plans += 1
        saved = copy.deepcopy(
            (self.assignments, self.pending_approvals, self.neutralized, self._lock.states)
        )
        try:
            ctx = self._context(state, now_s)
            self._bookkeeping(ctx)
            self._evade(ctx)
            self._hostiles(ctx)
            self._disruptors(ctx)
            self._explore(ctx)
            out = ctx.out
        except Exception as err:
            self.assignments, self.pending_approvals, self.neutralized, self._lock.states = saved
            self.stats.internal_errors += 1
            text = f"planning failed: {type(err).__name__}: {err}"
            self.events.append(TaskingEvent(float(now_s), "internal_error", None, text))
            log.exception("internal error in TaskAllocator.plan at t=%s (nothing sent)", now_s)
            out = []
        self.stats.last_plan_wall_s = time.perf_counter() - t0
        return out

    # ---- helpers ----------------------------------------------------------------------------

    def _event(
        self, ctx: _Ctx, kind: str, robot: int | None, text: str, hazard: int | None = None
    ) -> None:
        self.events.append(TaskingEvent(ctx.now_s, kind, robot, text, hazard))

    def _new_id(self) -> int:
        tid = self._next_id
        if tid >= OPERATOR_TASK_IDS_FROM:  # about 2e9 tasks: never in a mission, but say so
            raise RuntimeError(f"task id {tid} reached the operators' range")
        self._next_id += 1
        self.stats.tasks_issued += 1
        return tid

    def _position(self, r: RobotInfo) -> tuple[float, float]:
        assert r.pose_in_map is not None
        return (float(r.pose_in_map[0]), float(r.pose_in_map[1]))

    def _goto(
        self,
        ctx: _Ctx,
        r: RobotInfo,
        waypoints_in_map: NDArray[np.float64],
        purpose: str,
        hazard_id: int | None = None,
        goal_in_map: tuple[float, float] | None = None,
    ) -> None:
        """Send ``r`` through ``waypoints_in_map``; its goal is the last unless ``goal_in_map``
        says otherwise (an exploration goal with the way back after it)."""
        assert r.map_from_odom is not None
        wps = np.asarray(waypoints_in_map, dtype=np.float64).reshape(-1, 2)
        odom_from_map = inverse(np.asarray(r.map_from_odom, dtype=np.float64))
        in_odom = transform_points(odom_from_map, wps)
        tid = self._new_id()
        legs = np.vstack([np.asarray(self._position(r)), wps])
        length = float(np.hypot(*np.diff(legs, axis=0).T).sum())
        timeout = self.config.goal_timeout_base_s + length / self.config.assumed_speed_m_s
        goal = goal_in_map if goal_in_map is not None else (float(wps[-1, 0]), float(wps[-1, 1]))
        self.assignments[r.robot_id] = Assignment(
            tid, purpose, ctx.now_s, goal, hazard_id, timeout, route_in_map=legs
        )
        ctx.out.append(
            (r.robot_id, GoToTask(tid, ctx.now_s, [(float(x), float(y)) for x, y in in_odom]))
        )

    def _hold_as_relay(self, ctx: _Ctx, r: RobotInfo, a: Assignment) -> None:
        """``r`` arrived at its spread or relay spot ``a``: hold there with its radio in
        relay mode (a :class:`RelayTask`; the record stays ``a``'s, done)."""
        assert r.map_from_odom is not None and a.goal_in_map is not None
        odom_from_map = inverse(np.asarray(r.map_from_odom, dtype=np.float64))
        x, y = transform_points(odom_from_map, np.asarray(a.goal_in_map, dtype=np.float64))
        tid = self._new_id()
        a.task_id = tid
        ctx.out.append((r.robot_id, RelayTask(tid, ctx.now_s, (float(x), float(y)))))

    def _idle(self, ctx: _Ctx, r: RobotInfo, purpose: str) -> None:
        tid = self._new_id()
        self.assignments[r.robot_id] = Assignment(tid, purpose, ctx.now_s)
        ctx.out.append((r.robot_id, IdleTask(tid, ctx.now_s)))

    def _neutralize(self, ctx: _Ctx, r: RobotInfo, hazard: Hazard) -> None:
        assert r.map_from_odom is not None
        cfg = self.config.disruptor
        target = np.asarray(hazard.position_in_map, dtype=np.float64)
        odom_from_map = inverse(np.asarray(r.map_from_odom, dtype=np.float64))
        t_odom = transform_points(odom_from_map, target)
        standoff = math.dist(self._position(r), hazard.position_in_map)
        standoff = max(standoff, cfg.trigger_radius_m + cfg.standoff_margin_m)
        tid = self._new_id()
        timeout = self.config.goal_timeout_base_s + cfg.hold_s
        self.assignments[r.robot_id] = Assignment(
            tid, "neutralize", ctx.now_s, hazard.position_in_map, hazard.hazard_id, timeout
        )
        ctx.out.append(
            (
                r.robot_id,
                NeutralizeTask(
                    tid, ctx.now_s, (float(t_odom[0]), float(t_odom[1])), standoff, True
                ),
            )
        )

    def _mark_duplicates(self, state: TaskingState, now_s: float) -> set[int]:
        """Hazards done: neutralized, and the static ones within ``duplicate_m`` of a
        neutralized one (the same object; added to :attr:`neutralized`, with an event)."""
        cfg = self.config
        done = self.neutralized | set(state.neutralized_hazard_ids)
        for h in _duplicates_of(state.hazards, done, cfg.duplicate_m):
            self.neutralized.add(h.hazard_id)
            done.add(h.hazard_id)
            self.events.append(
                TaskingEvent(
                    now_s,
                    "duplicate",
                    None,
                    f"hazard {h.hazard_id}: within {cfg.duplicate_m:g} m of a neutralized one, "
                    "the same object: neutralized",
                    h.hazard_id,
                )
            )
        return done

    # ---- 0: the picture ---------------------------------------------------------------------

    def _context(self, state: TaskingState, now_s: float) -> _Ctx:
        cfg = self.config
        done = self._mark_duplicates(state, now_s)
        bad = [h for h in state.hazards if not np.isfinite(h.position_in_map).all()]
        for h in bad:
            self.events.append(
                TaskingEvent(
                    now_s,
                    "bad_input",
                    None,
                    f"hazard {h.hazard_id}: non-finite position, ignored",
                    h.hazard_id,
                )
            )
        if bad:
            state = dataclasses.replace(state, hazards=[h for h in state.hazards if h not in bad])
        locked = {h for h, s in self._lock.states.items() if s.locked}
        static_live = [
            h for h in state.hazards if h.kind == ObjectKind.STATIC_OOI and h.hazard_id not in done
        ]
        hostiles_live = [
            h
            for h in state.hazards
            if h.kind in (ObjectKind.HOSTILE, ObjectKind.MOBILE_OOI)
            and h.hazard_id not in done
            and h.hazard_id not in locked
        ]
        # the keep-outs of done OOIs stay: the robots keep out of them (small world seed 0: a
        # disruptor sent to a pose 2.7 m from a sighting taken as neutralized, a duplicate, sat
        # at its keep-out's edge 3.7 m off until the task timed out, 72 s)
        static_all = [h for h in state.hazards if h.kind == ObjectKind.STATIC_OOI]
        discs = [
            (
                *h.position_in_map,
                max(h.radius_m, cfg.disruptor.trigger_radius_m) + cfg.keepout_margin_m,
            )
            for h in static_all
        ] + [
            (*h.position_in_map, max(h.radius_m, cfg.hostile.blast_radius_m) + cfg.keepout_margin_m)
            for h in hostiles_live
        ]
        grid = coarsen(
            state.occupancy,
            resolution_m=cfg.planning_resolution_m,
            robot_radius_m=cfg.robot_radius_m,
            keepout_in_map=np.asarray(discs, dtype=np.float64).reshape(-1, 3),
        )
        highway = build_trajectory_graph(
            state.trajectory_robot_ids,
            state.trajectory_keys,
            state.trajectory_xy_in_map,
            cfg.highway,
        )
        blocked = np.zeros(highway.size, dtype=bool)
        for x, y, radius in discs:
            blocked |= (
                np.hypot(highway.nodes_in_map[:, 0] - x, highway.nodes_in_map[:, 1] - y) < radius
            )
        self.grid, self.highway = grid, highway
        robots = {r.robot_id: r for r in state.robots}
        return _Ctx(
            now_s,
            state,
            grid,
            highway,
            blocked,
            robots,
            {},
            {},
            static_live,
            hostiles_live,
            static_all,
        )

    # ---- 1: bookkeeping ---------------------------------------------------------------------

    def _bookkeeping(self, ctx: _Ctx) -> None:
        cfg = self.config
        for rid, r in ctx.robots.items():
            quiet_s = ctx.now_s - r.last_heard_s
            if quiet_s > cfg.contact_fresh_s:
                self._heard_since.pop(rid, None)
            else:
                self._heard_since.setdefault(rid, ctx.now_s)
            lost = r.lost or quiet_s > cfg.lost_after_s
            silent = quiet_s > cfg.silent_after_s
            if lost and rid not in self._lost:
                self._lost.add(rid)
                self._event(ctx, "robot_lost", rid, f"robot {rid} lost: its tasks go to others")
            elif silent and not lost and rid not in self._silent:
                self._event(
                    ctx, "robot_silent", rid, f"robot {rid} silent {quiet_s:.0f} s: not counted on"
                )
            if silent and rid not in self._silent and not r.lost:
                self._shadowed(ctx, rid)  # it fell silent just now (not disabled)
            if (silent or lost) and rid in self.assignments:
                # once: a disruptor's OOI handed over turns ":released" into ":dropped"
                # (appending again re-announced the hand-over every plan, 2 s, for the
                # rest of the full mission: 336 'reassigned' events for two OOIs)
                p = self.assignments[rid].purpose
                if ":released" not in p and ":dropped" not in p:
                    self.assignments[rid].purpose = p + ":released"
            if not silent and not lost and (rid in self._silent or rid in self._lost):
                a = self.assignments.get(rid)
                if (
                    cfg.watch_on_return
                    and a is not None
                    and a.purpose == "hostile_view:released"
                    and a.hazard_id is not None
                    and any(h.hazard_id == a.hazard_id for h in ctx.hostiles_live)
                ):
                    # a watcher heard again watches on (the hostile planner re-places or
                    # releases it): it may have kept the walker in view all the while
                    a.purpose = "hostile_view"
                    self._event(ctx, "robot_back", rid, f"robot {rid} heard again: watches on")
                else:
                    self._event(ctx, "robot_back", rid, f"robot {rid} heard again: re-planned")
                    self.assignments.pop(rid, None)
                self._lost.discard(rid)
            if silent:
                self._silent.add(rid)
            else:
                self._silent.discard(rid)
            if r.operator_controlled:
                self.assignments.pop(rid, None)
                continue
            if silent or lost or r.pose_in_map is None or r.map_from_odom is None:
                continue
            pos = r.pose_in_map
            if not all(math.isfinite(v) for v in (*pos, *r.map_from_odom)):
                self._event(
                    ctx, "bad_input", rid, f"robot {rid}: non-finite pose or frame, skipped"
                )
                continue
            ctx.available[rid] = r
            if ctx.now_s - self._heard_since.get(rid, math.inf) >= cfg.contact_steady_s:
                self._contact(pos[0], pos[1])
            cell = ctx.grid.snap(pos[:2], cfg.snap_m)
            if cell is None and any(
                math.dist(pos[:2], h.position_in_map) < cfg.hostile.blast_radius_m + 2
                for h in ctx.hostiles_live
            ):
                # inside a hostile's keep-out it is not evading (a stale sighting, or one it
                # could not get out of): planned from the nearest cell outside (its own
                # planner finds the way; standing there it helps no one)
                cell = ctx.grid.snap(pos[:2], cfg.hostile.blast_radius_m + 2 * cfg.snap_m)
            if cell is not None:
                ctx.cells[rid] = cell
            self._close_task(ctx, r)

    def _contact(self, x: float, y: float) -> None:
        b = self.config.contact_bin_m
        key = (int(math.floor(x / b)), int(math.floor(y / b)))
        if key not in self._contact_bins:
            # the robot's own position, not the bin's centre: a centre may be in a wall
            self._contact_bins.add(key)
            self._contact_xy.append((float(x), float(y)))

    @property
    def failed_views(self) -> list[tuple[float, float, float, float]]:
        """Where disruptors failed to laser an OOI for want of line of sight: ``(ooi x, ooi y,
        disruptor x, disruptor y)`` in ``map`` (a copy; the journal saves it)."""
        return list(self._failed_views)

    def restore_failed_views(self, views: list[tuple[float, float, float, float]]) -> None:
        """Give back :attr:`failed_views` (a resumed GCS, from its journal). ``ValueError``
        naming the row if one is not four finite numbers; nothing is changed then."""
        rows = []
        for i, row in enumerate(views):
            view = tuple(float(v) for v in row)
            if len(view) != 4 or not all(math.isfinite(v) for v in view):
                raise ValueError(f"failed view {i}: expected 4 finite numbers, got {row!r}")
            rows.append((view[0], view[1], view[2], view[3]))
        self._failed_views = rows

    @property
    def contact_in_map(self) -> NDArray[np.float64]:
        """``(C, 2)`` points of radio contact: where the GCS heard robots at once."""
        return np.asarray(self._contact_xy, dtype=np.float64).reshape(-1, 2)

    def _shadowed(self, ctx: _Ctx, rid: int) -> None:
        """Robot ``rid`` just fell silent: the hostile it was on its way to watch is not given
        it for ``shadow_retry_s`` (the lock needs the watchers heard, paper 2: a watcher in a
        radio shadow cannot hold it), nor is the exploration goal it was on its way to (nor
        one within ``shadow_goal_radius_m`` of it): back in contact at the shadow's
        edge for a second or two, its backlog not through yet, it was re-sent into the same
        shadow on a map that lacked what it had seen there (issue 17; chaos bench seed 9:
        robots 1 and 2 never heard again). Another robot may take that goal, and what the
        robot saw in the shadow arrives when its backlog is through (store and forward),
        closing the frontier if it was explored."""
        a = self.assignments.get(rid)
        if a is None or a.goal_in_map is None:
            return
        if a.purpose.split(":")[0] == "explore":
            if self.config.shadow_goal_radius_m <= 0:
                return  # off: its exploration goal may be given again at once
            self._explore_shadowed.setdefault(rid, []).append((a.goal_in_map, ctx.now_s))
            x, y = a.goal_in_map
            self._event(
                ctx,
                "goal_in_shadow",
                rid,
                f"robot {rid} fell silent on its way to explore ({x:.1f}, {y:.1f}): not sent "
                f"there for {self.config.shadow_retry_s:g} s",
            )
            return
        if a.hazard_id is None or a.purpose.split(":")[0] != "hostile_view":
            return
        retry_s = self.config.view_shadow_retry_s
        if retry_s <= 0 or not math.isfinite(a.timeout_s):
            # off, or silent at its view position: it watches on, out of contact (the rules'
            # lock does not need the radio; robot.control.hostile_evasion.keep_in_view_goal)
            return
        self._view_shadowed.setdefault(a.hazard_id, {})[rid] = ctx.now_s + retry_s
        x, y = a.goal_in_map
        self._event(
            ctx,
            "goal_in_shadow",
            rid,
            f"robot {rid} fell silent on its way to watch hostile {a.hazard_id} from "
            f"({x:.1f}, {y:.1f}): not sent to watch it for {retry_s:g} s",
            a.hazard_id,
        )

    def _close_task(self, ctx: _Ctx, r: RobotInfo) -> None:
        a = self.assignments.get(r.robot_id)
        if a is None or a.purpose == "neutralize_wait" or a.purpose.endswith(":done"):
            return  # no task in flight: its report was already folded in
        st = r.status
        finished = st is not None and st.task_id == a.task_id and st.state in _TERMINAL
        timed_out = not finished and ctx.now_s - a.issued_s > a.timeout_s
        if not (finished or timed_out):
            return
        ok = finished and st is not None and st.state == TaskState.SUCCEEDED
        why = (
            "timed out"
            if timed_out
            else (
                st.detail if st is not None and st.detail else (st.state.name.lower() if st else "")
            )
        )
        purpose = a.purpose.split(":")[0]
        if ok:
            self.stats.goals_reached += 1
            if purpose == "neutralize_go":
                self.assignments[r.robot_id] = Assignment(
                    a.task_id, "neutralize_wait", ctx.now_s, a.goal_in_map, a.hazard_id
                )
                return
            if purpose == "neutralize" and a.hazard_id is not None:
                self.neutralized.add(a.hazard_id)
                self.stats.neutralized += 1
                self._event(
                    ctx, "neutralized", r.robot_id, f"hazard {a.hazard_id} neutralized", a.hazard_id
                )
        else:
            self.stats.goals_failed += 1
            self._event(
                ctx,
                "task_failed",
                r.robot_id,
                f"task {a.task_id} ({purpose}) failed: {why}",
                a.hazard_id,
            )
            if purpose == "explore" and a.goal_in_map is not None:
                self._failed_goals.setdefault(r.robot_id, []).append(a.goal_in_map)
                self._goal_failures.append((a.goal_in_map, r.robot_id))
                self._avoid_route(ctx, r, a)
            if purpose == "evade" and a.hazard_id is not None:
                k = (r.robot_id, a.hazard_id)
                self._evade_failures[k] = self._evade_failures.get(k, 0) + 1
                if self._evade_failures[k] == self.config.evade_attempts:
                    self._event(
                        ctx,
                        "evade_given_up",
                        r.robot_id,
                        f"robot {r.robot_id} failed {self.config.evade_attempts} times to leave "
                        f"hazard {a.hazard_id}'s keep-out: not sent out of it again",
                        a.hazard_id,
                    )
            if purpose in ("neutralize_go", "neutralize") and a.hazard_id is not None:
                self._dispatch_excluded.setdefault(a.hazard_id, {})[r.robot_id] = ctx.now_s
                if purpose == "neutralize" and "line of sight" in why:
                    # geometry, not a perception miss (the OOI not seen from there, no own
                    # sighting near the target: those came right on retries, small world
                    # seed 11): another side next time
                    self._failed_view(ctx, r, a)
        if purpose == "hostile_view" and ok:
            a.timeout_s = math.inf  # at its view position: it holds there
            return
        if purpose in ("park", "spread") and ok:
            # a parked or spread robot stays where it is; keep the record (not re-sent)
            a.timeout_s = math.inf
            a.purpose = purpose + ":done"
            if purpose == "spread" and self.config.relays and a.goal_in_map is not None:
                self._hold_as_relay(ctx, r, a)
            return
        self.assignments.pop(r.robot_id, None)

    def _failed_view(self, ctx: _Ctx, r: RobotInfo, a: Assignment) -> None:
        """``r`` failed ``a``, a neutralization of an OOI, for want of line of sight from
        where it is: remembered, so the next dispatch to that OOI goes to another side
        (:func:`~gcs.tasking.disruptor_planner.failed_view_mask`)."""
        h = next((h for h in ctx.state.hazards if h.hazard_id == a.hazard_id), None)
        if h is None:
            return
        pose = self._position(r)
        ox, oy = h.position_in_map
        self._failed_views.append((float(ox), float(oy), float(pose[0]), float(pose[1])))

    def _purpose(self, rid: int) -> str | None:
        a = self.assignments.get(rid)
        return None if a is None else a.purpose

    # ---- 2: safety ----------------------------------------------------------------------------

    def _evade(self, ctx: _Ctx) -> None:
        """Robots out of keep-outs; goals in keep-outs dropped. A robot is sent out of a
        hostile's blast radius only while that sighting is fresh (seen within
        ``hostile.evade_fresh_s``): a walker's old sighting marks where it was (the robot
        keeps out of the disc on its own, and backs away from a hostile it sees coming);
        three robots inside a sighting 100 s old, the walker long gone, were sent out of it
        for the last 600 s of the full mission."""
        cfg = self.config
        seen = ctx.state.hostile_seen_s
        discs = [(h, max(h.radius_m, cfg.disruptor.trigger_radius_m)) for h in ctx.static_live]
        discs += [(h, max(h.radius_m, cfg.hostile.blast_radius_m)) for h in ctx.hostiles_live]
        stale = {
            h.hazard_id
            for h in ctx.hostiles_live
            if ctx.now_s - max(seen.get(h.hazard_id, {}).values(), default=ctx.now_s)
            > cfg.hostile.evade_fresh_s
        }
        for rid, r in ctx.available.items():
            pos = self._position(r)
            a = self.assignments.get(rid)
            # a neutralization's target is the hazard itself, by design: not a goal to move
            if (
                a is not None
                and a.goal_in_map is not None
                and a.purpose not in ("evade", "neutralize")
            ):
                for h, radius in discs:
                    if math.dist(a.goal_in_map, h.position_in_map) < radius:
                        # a hostile moved onto the goal (or an OOI was found there): re-plan
                        self._event(
                            ctx,
                            "goal_in_keepout",
                            rid,
                            f"robot {rid}: its goal is inside hazard {h.hazard_id}'s keep-out",
                            h.hazard_id,
                        )
                        del self.assignments[rid]
                        break
            for h, radius in discs:
                if math.dist(pos, h.position_in_map) < radius:
                    if self._purpose(rid) == "evade":
                        break
                    failed = self._evade_failures.get((rid, h.hazard_id), 0)
                    if failed >= cfg.evade_attempts or h.hazard_id in stale:
                        continue
                    taken = [
                        a.goal_in_map
                        for o, a in self.assignments.items()
                        if o != rid and a.purpose == "evade" and a.goal_in_map is not None
                    ]
                    goal = evasion_goal(
                        ctx.grid,
                        pos,
                        radius + 2 * cfg.keepout_margin_m + cfg.snap_m,
                        taken_in_map=np.asarray(taken, dtype=np.float64).reshape(-1, 2),
                        separation_m=2 * cfg.robot_radius_m + 0.5,
                    )
                    if goal is None:
                        self._event(
                            ctx,
                            "no_evasion",
                            rid,
                            f"robot {rid} inside hazard {h.hazard_id} with no way out",
                            h.hazard_id,
                        )
                        break
                    self._event(
                        ctx,
                        "evade",
                        rid,
                        f"robot {rid} leaves the keep-out of hazard {h.hazard_id}",
                        h.hazard_id,
                    )
                    self._goto(ctx, r, np.asarray([goal]), "evade", h.hazard_id)
                    break

    # ---- 3: hostiles ----------------------------------------------------------------------------

    def _release_viewers(self, hid: int) -> None:
        for rid, a in list(self.assignments.items()):
            if a.purpose == "hostile_view" and a.hazard_id == hid:
                del self.assignments[rid]

    def _hostiles(self, ctx: _Ctx) -> None:
        """Hostile watch (see the module docstring): sightings clustered into hostiles (the
        freshest of sightings within ``same_hostile_m`` of each other stands for them), stale
        ones not watched, at most :func:`~gcs.tasking.hostile_planner.watch_slots` hostiles
        watched at once (those already watched first, then the freshest), each by robots
        within ``watch_reach_m`` only, and a hostile whose watch never starts the lock paused
        for longer each time."""
        cfg = self.config.hostile
        seen = ctx.state.hostile_seen_s

        def last_seen(h: Hazard) -> float:
            # a hostile the GCS has no sighting time for counts as seen now
            return max(seen.get(h.hazard_id, {}).values(), default=ctx.now_s)

        def viewers_of(hid: int) -> list[int]:
            return [
                rid
                for rid, a in self.assignments.items()
                if a.purpose == "hostile_view" and a.hazard_id == hid and rid in ctx.available
            ]

        # watchers of a sighting no longer among the hazards (merged away) are free
        current = {h.hazard_id for h in ctx.state.hazards}
        for rid, a in list(self.assignments.items()):
            if a.purpose == "hostile_view" and a.hazard_id not in current:
                del self.assignments[rid]
        watched: list[tuple[float, float]] = []
        watched_ids: list[int | None] = []  # the hazard each of watched stands for
        live_ids: set[int] = set()  # of those, the ones that may be watched now
        candidates: list[Hazard] = []
        # the latest seen first: of sightings of one walking hostile, the freshest is watched
        for h in sorted(
            (h for h in ctx.state.hazards if h.kind in (ObjectKind.HOSTILE, ObjectKind.MOBILE_OOI)),
            key=lambda h: (-last_seen(h), h.hazard_id),
        ):
            hid = h.hazard_id
            if hid in self.neutralized or hid in ctx.state.neutralized_hazard_ids:
                watched.append(h.position_in_map)  # its other sightings are done with it
                watched_ids.append(None)
                continue
            st = self._lock.update(hid, seen.get(hid, {}), ctx.now_s)
            if st.locked:
                self.neutralized.add(hid)
                self.stats.hostiles_locked += 1
                text = f"hostile {hid} held in view {cfg.lock_s:.0f} s"
                self._event(ctx, "hostile_locked", None, text, hid)
                self._release_viewers(hid)
                self._watch_done(h.position_in_map)
                watched.append(h.position_in_map)
                watched_ids.append(None)
                continue
            if any(math.dist(h.position_in_map, w) < cfg.same_hostile_m for w in watched):
                # another sighting of one handled (or paused): its watchers watch that one
                # (HostileConfig.self_watch_m), else they are free
                kept = next(
                    (
                        k
                        for w, k in zip(watched, watched_ids, strict=True)
                        if math.dist(h.position_in_map, w) < cfg.same_hostile_m
                    ),
                    None,
                )
                if cfg.self_watch_m > 0 and kept is not None and kept in live_ids:
                    for a in self.assignments.values():
                        if a.purpose == "hostile_view" and a.hazard_id == hid:
                            a.hazard_id = kept
                else:
                    self._release_viewers(hid)
                continue
            watched.append(h.position_in_map)
            watched_ids.append(hid)
            if ctx.now_s - last_seen(h) > cfg.watch_fresh_s and st.since_s is None:
                self._unwatch(h)  # stale: the walker is elsewhere
                continue
            area = self._watch_area(h.position_in_map)
            if area is not None and ctx.now_s < area.paused_until_s:
                self._release_viewers(hid)
                continue
            candidates.append(h)
            live_ids.add(hid)
        sensors = sum(1 for r in ctx.available.values() if r.role == Role.SENSOR)
        slots = watch_slots(sensors, cfg)
        # hostiles already watched keep their watchers (no churn), then the freshest
        candidates.sort(key=lambda h: (not viewers_of(h.hazard_id), -last_seen(h), h.hazard_id))
        for h in candidates:
            hid = h.hazard_id
            st = self._lock.states[hid]
            if slots <= 0:
                self._unwatch(h)
                continue
            area = self._watch_area(h.position_in_map, create=True)
            assert area is not None
            area.xy = h.position_in_map  # it follows the walker
            if st.since_s is None and area.began_s is not None:
                if ctx.now_s - area.began_s > cfg.watch_budget_s:
                    pause_s = cfg.watch_pause_s * cfg.pause_growth**area.pauses
                    area.pauses += 1
                    area.began_s = None
                    area.paused_until_s = ctx.now_s + pause_s
                    self._release_viewers(hid)
                    self._event(
                        ctx,
                        "hostile_paused",
                        None,
                        f"hostile {hid}: no lock begun in {cfg.watch_budget_s:g} s, not "
                        f"watched for {pause_s:g} s",
                        hid,
                    )
                    continue
            if self._staff_watch(ctx, h):
                slots -= 1
                if area.began_s is None:
                    area.began_s = ctx.now_s
            else:
                self._unwatch(h)

    def _unwatch(self, h: Hazard) -> None:
        """``h`` is not watched now: its watchers are free, its watch budget starts afresh
        when it is watched again."""
        self._release_viewers(h.hazard_id)
        area = self._watch_area(h.position_in_map)
        if area is not None:
            area.began_s = None

    def _watch_area(self, xy: tuple[float, float], create: bool = False) -> _WatchArea | None:
        """The watch record of the hostile whose sightings are near ``xy``."""
        reach = self.config.hostile.same_hostile_m
        near = [a for a in self._watch_areas if math.dist(a.xy, xy) < reach]
        if near:
            return min(near, key=lambda a: math.dist(a.xy, xy))
        if not create:
            return None
        area = _WatchArea(xy)
        self._watch_areas.append(area)
        return area

    def _watch_done(self, xy: tuple[float, float]) -> None:
        reach = self.config.hostile.same_hostile_m
        self._watch_areas = [a for a in self._watch_areas if math.dist(a.xy, xy) >= reach]

    def _staff_watch(self, ctx: _Ctx, h: Hazard) -> bool:
        """Send robots to watch ``h`` (or keep those on it); False: it cannot be staffed now
        (fewer than ``viewers`` robots within reach, or no views)."""
        cfg = self.config.hostile
        hid = h.hazard_id
        for rid, a in list(self.assignments.items()):
            if a.purpose != "hostile_view" or a.hazard_id != hid or rid not in ctx.available:
                continue
            r = ctx.available[rid]
            # a watcher at its view position holds (timeout_s inf from its arrival), or
            # follows the walker to keep it in view (robot.control.hostile_evasion
            # .keep_in_view_goal): not on its way, not stalled
            on_way = (
                a.goal_in_map is not None
                and math.isfinite(a.timeout_s)
                and math.dist(self._position(r), a.goal_in_map) > self.config.goal_reached_m
            )
            if on_way and self._stalled(ctx, r, a):
                # stuck on its way (a doorway's jamb: full mission, a robot 1300 s in one
                # doorway was sent to watch from there): another watches, it is not sent to
                # this hostile for shadow_retry_s
                self._avoid_route(ctx, r, a)
                until_s = ctx.now_s + self.config.shadow_retry_s
                self._view_shadowed.setdefault(hid, {})[rid] = until_s
                del self.assignments[rid]
                self._event(
                    ctx, "stalled", rid, f"robot {rid} stuck on its way to watch hostile {hid}", hid
                )
        viewers = [
            rid
            for rid, a in self.assignments.items()
            if a.purpose == "hostile_view" and a.hazard_id == hid and rid in ctx.available
        ]
        moved = math.dist(self._hostile_at.get(hid, h.position_in_map), h.position_in_map)
        if len(viewers) >= cfg.viewers and moved < cfg.replan_move_m:
            return True
        # watchers that see it now stay where they are (they keep it in view themselves);
        # the others are placed around them
        seen = ctx.state.hostile_seen_s.get(hid, {})
        # ... and so do watchers (at their views or on their way) within self_watch_m of the
        # sighting: the GCS seldom hears them see it (the walker's radio shadow), and a new
        # view from a sighting seconds old sent them off it (small world seed 7: a watcher
        # 9 m from the walker sent to a view 16 m from it)
        at = {rid: self._position(ctx.available[rid]) for rid in viewers}
        fixed = {
            rid: xy
            for rid, xy in at.items()
            if (
                not math.isfinite(self.assignments[rid].timeout_s)
                and ctx.now_s - seen.get(rid, -math.inf) <= cfg.view_gap_s
            )
            or math.dist(xy, h.position_in_map) <= cfg.self_watch_m
        }
        if len(fixed) >= cfg.viewers:
            self._hostile_at[hid] = h.position_in_map
            return True
        shadowed = self._view_shadowed.get(hid, {})
        pool = {
            rid: self._position(r)
            for rid, r in ctx.available.items()
            if r.role == Role.SENSOR
            and (
                rid in viewers
                or (
                    self._purpose(rid) not in ("hostile_view", "evade")
                    and math.dist(self._position(r), h.position_in_map) <= cfg.watch_reach_m
                )
            )
            and ctx.now_s >= shadowed.get(rid, -math.inf)
        }
        if len(pool) < cfg.viewers:
            return False
        views = view_positions(
            ctx.grid,
            h.position_in_map,
            pool,
            cfg,
            contact_in_map=self.contact_in_map,
            contact_radius_m=self.config.exploration.contact_radius_m,
            fixed_in_map=fixed,
        )
        if len(views) < min(cfg.viewers, 2):
            return False
        self._hostile_at[hid] = h.position_in_map
        for rid, p in views.items():
            if rid in fixed:
                continue
            cur = self.assignments.get(rid)
            if (
                cur is not None
                and cur.purpose == "hostile_view"
                and cur.goal_in_map is not None
                and math.dist(cur.goal_in_map, p) < 0.5
            ):
                continue
            self._event(ctx, "hostile_view", rid, f"robot {rid} to watch hostile {hid}", hid)
            self._goto(ctx, ctx.available[rid], np.asarray([p]), "hostile_view", hid)
        return True

    # ---- 4: disruptors -------------------------------------------------------------------------

    def _disruptors(self, ctx: _Ctx) -> None:
        cfg = self.config.disruptor
        mine = {rid: r for rid, r in ctx.available.items() if r.role == Role.DISRUPTOR}
        # not one neutralized in this plan's bookkeeping (static_live was taken before it),
        # nor another sighting of it
        self._mark_duplicates(ctx.state, ctx.now_s)
        live = {h.hazard_id: h for h in ctx.static_live if h.hazard_id not in self.neutralized}
        # approvals for disruptors at their pose
        for rid, r in mine.items():
            a = self.assignments.get(rid)
            if a is None or a.purpose != "neutralize_wait" or a.hazard_id is None:
                continue
            h = live.get(a.hazard_id)
            if h is None:
                self.assignments.pop(rid, None)
                continue
            if cfg.approval == "auto":
                self.stats.approvals_auto += 1
                self._event(
                    ctx,
                    "approved",
                    rid,
                    f"neutralization of {h.hazard_id} auto-approved",
                    h.hazard_id,
                )
            elif h.hazard_id in ctx.state.approved_hazard_ids:
                self.stats.approvals_operator += 1
                self._event(
                    ctx,
                    "approved",
                    rid,
                    f"operator approved neutralization of {h.hazard_id}",
                    h.hazard_id,
                )
            else:
                if h.hazard_id not in self.pending_approvals:
                    self._event(
                        ctx,
                        "awaiting_approval",
                        rid,
                        f"neutralization of {h.hazard_id} awaits the operator",
                        h.hazard_id,
                    )
                self.pending_approvals.add(h.hazard_id)
                continue
            self.pending_approvals.discard(h.hazard_id)
            self._neutralize(ctx, r, h)
        # who handles which OOI (assignments of silent/lost disruptors are released)
        handled = {
            a.hazard_id
            for rid, a in self.assignments.items()
            if rid in mine and a.purpose in ("neutralize_go", "neutralize_wait", "neutralize")
        }
        for rid, a in list(self.assignments.items()):
            if (
                a.purpose.startswith("neutralize")
                and a.purpose.endswith(":released")
                and a.hazard_id in live
                and a.hazard_id not in handled
            ):
                self.stats.reassigned += 1
                self._event(
                    ctx,
                    "reassigned",
                    rid,
                    f"hazard {a.hazard_id}: its disruptor {rid} is out of contact",
                    a.hazard_id,
                )
                a.purpose = a.purpose.replace(":released", ":dropped")
        static_xy = np.asarray(
            [h.position_in_map for h in ctx.static_all], dtype=np.float64
        ).reshape(-1, 2)
        free_xy = [self._position(r) for rid, r in mine.items()]

        def nearest_m(hid: int) -> float:
            xy = live[hid].position_in_map
            return min((math.dist(xy, p) for p in free_xy), default=0.0)

        # nearest first (a lone disruptor takes them in the order it can reach them)
        for hid in sorted(live, key=lambda k: (nearest_m(k), k)):
            if hid in handled:
                continue
            if any(
                live[o].kind == live[hid].kind
                and math.dist(live[o].position_in_map, live[hid].position_in_map)
                < self.config.duplicate_m
                for o in handled
                if o in live
            ):
                continue  # the same object as one a disruptor is already on
            free = {
                rid: self._position(r)
                for rid, r in mine.items()
                if self._purpose(rid)
                not in ("neutralize_go", "neutralize_wait", "neutralize", "evade")
                and ctx.now_s - self._dispatch_excluded.get(hid, {}).get(rid, -math.inf)
                >= self.config.neutralize_retry_s
            }
            d = dispatch_disruptor(
                ctx.grid,
                ctx.highway,
                hid,
                live[hid].position_in_map,
                static_xy,
                free,
                ctx.blocked,
                cfg,
                failed_views_in_map=np.asarray(self._failed_views, dtype=np.float64).reshape(-1, 4),
            )
            if d is None:
                continue
            self._event(
                ctx,
                "dispatch",
                d.robot_id,
                f"disruptor {d.robot_id} to hazard {hid} ({d.distance_m:.0f} m of highway)",
                hid,
            )
            self._goto(ctx, mine[d.robot_id], d.waypoints_in_map, "neutralize_go", hid)
            handled.add(hid)
        self._spread(ctx, mine)

    def _spread(self, ctx: _Ctx, mine: dict[int, RobotInfo]) -> None:
        cfg = self.config.disruptor
        idle = sorted(
            rid
            for rid in mine
            if (self._purpose(rid) or "spread").split(":")[0] in ("spread", "park")
        )
        if not idle or ctx.highway.size == 0:
            return
        pos = np.asarray([self._position(mine[r]) for r in idle])
        access = self._main_access(ctx.highway, pos, ctx.blocked)
        if (access < 0).all():
            return
        # the explored highway reachable by these disruptors
        dist, _ = ctx.highway.distances(access[access >= 0], ctx.blocked)
        region: NDArray[np.bool_] = np.asarray(np.isfinite(dist).any(axis=0), dtype=bool)
        relay = np.zeros(0, dtype=np.int64)
        if self.config.relays:
            # sensor robots out of contact (not disabled), the longest silent first
            silent = sorted(
                (
                    (r.last_heard_s, rid)
                    for rid, r in ctx.robots.items()
                    if rid in self._silent
                    and not r.lost
                    and r.role == Role.SENSOR
                    and r.pose_in_map is not None
                    and all(math.isfinite(v) for v in r.pose_in_map)
                ),
            )
            relay = relay_spots(
                ctx.highway,
                [self._position(ctx.robots[rid]) for _, rid in silent],
                self.contact_in_map,
                contact_radius_m=self.config.exploration.contact_radius_m,
                region=region,
                blocked=ctx.blocked,
                hop_m=self.config.relay_hop_m,
            )
            relay = self._kept_relay_spots(ctx, relay, region)
            if self.config.relay_keep_s > 0 and relay.size:
                # spots an idle disruptor is on its way to or holding at first: it goes on
                # (the assignment below keeps it there) while robots call for the spot
                goals = [self.assignments[r].goal_in_map for r in idle if r in self.assignments]
                heading = np.asarray([g for g in goals if g is not None], dtype=np.float64)
                mine_first = np.zeros(relay.size, dtype=bool)
                for g in heading.reshape(-1, 2):
                    d_spot = np.hypot(*(ctx.highway.nodes_in_map[relay] - g).T)
                    if float(d_spot.min()) < cfg.spread_tolerance_m:
                        mine_first[int(np.argmin(d_spot))] = True
                relay = np.concatenate([relay[mine_first], relay[~mine_first]])
            relay = relay[: len(idle)]
        key = (tuple(idle), tuple(relay.tolist()))
        # the relay spots alone changing (robots falling silent and heard again, contact
        # growing) re-targets the same idle disruptors at most every spread_period_s: re-
        # planned at each change they never arrived (full mission seed 0, 335-445 s: 40
        # re-targets, one disruptor sent to 6 spots in 34 s, none held as a relay)
        if key[0] == self._spread_key[0] and ctx.now_s - self._spread_at_s < cfg.spread_period_s:
            return
        self._spread_key, self._spread_at_s = key, ctx.now_s
        wide = region & self._clear_of_obstacles(ctx, cfg.park_clearance_m)
        if wide.any():
            region = wide
        centres = spread_positions(
            ctx.highway, len(idle) - len(relay), region=region, blocked=ctx.blocked, config=cfg
        )
        centres = np.concatenate([relay, centres[~np.isin(centres, relay)]]).astype(np.int64)
        if centres.size == 0:
            return
        d_all, pred_all = ctx.highway.distances(np.where(access >= 0, access, 0), ctx.blocked)
        cost = np.where(access[:, None] >= 0, d_all[:, centres], np.inf)
        cost = np.where(np.isfinite(cost), cost, 1e12)
        for i, rid in enumerate(idle):
            # a relay holding at a relay spot stays there, and one on its way to one goes on
            # (relay_keep_s): re-targeted each spread_period_s as robots fell silent and were
            # heard again, relays went to and fro between spots 40-50 m apart, 100 s away
            # (full mission seed 0: spots at 127, 147 and 169 s, none reached)
            a = self.assignments.get(rid)
            if (
                a is None
                or a.purpose not in ("spread", "spread:done")
                or a.goal_in_map is None
                or self.config.relay_keep_s <= 0
            ):
                continue
            at = self._position(mine[rid]) if a.purpose == "spread:done" else a.goal_in_map
            d_spot = np.hypot(*(ctx.highway.nodes_in_map[relay] - np.asarray(at)).T)
            if d_spot.size and float(d_spot.min()) < cfg.spread_tolerance_m:
                cost[i, int(np.argmin(d_spot))] = -1e9
        rows, cols = linear_sum_assignment(cost)
        for i, j in zip(rows, cols, strict=True):
            rid = idle[i]
            if cost[i, j] >= 1e12:
                continue
            target = ctx.highway.nodes_in_map[centres[j]]
            a = self.assignments.get(rid)
            if (
                a is not None
                and a.goal_in_map is not None
                and math.dist(a.goal_in_map, target) < cfg.spread_tolerance_m
            ):
                continue
            if math.dist(self._position(mine[rid]), target) < cfg.spread_tolerance_m:
                if self.config.relays and (a is None or not a.purpose.startswith("spread")):
                    # there already (never sent): hold here as a relay
                    here = Assignment(0, "spread:done", ctx.now_s, self._position(mine[rid]))
                    self.assignments[rid] = here
                    self._hold_as_relay(ctx, mine[rid], here)
                continue
            path = ctx.highway.path(pred_all[i], int(centres[j]))
            why = "relay spot for robots out of contact at" if j < len(relay) else "spread to"
            self._event(
                ctx,
                "spread",
                rid,
                f"idle disruptor {rid}: {why} highway waypoint {int(centres[j])}",
            )
            self._goto(ctx, mine[rid], ctx.highway.nodes_in_map[path], "spread")

    @staticmethod
    def _main_access(
        highway: TrajectoryGraph, pos: NDArray[np.float64], blocked: NDArray[np.bool_]
    ) -> NDArray[np.int64]:
        """Each position's highway entry (``TrajectoryGraph.nearest``), on the largest piece of
        the highway when one of its waypoints is within ``access_m``: a disruptor that has not
        driven yet stands on a waypoint of its own, its start, not joined to its teammates'
        (1.5 m apart in the start zone, bins of 2 m: more than ``merge_m`` between their
        means), and spread over that piece alone it stayed there, never sent as a relay nor
        dispatched (full mission seed 0 at 1d6eb73: disruptor 11 at its start for 600 s while
        the others were sent up to 149 m to OOIs)."""
        access = highway.nearest(pos, blocked)
        if highway.size == 0 or (access < 0).all():
            return access
        _, label = connected_components(highway.graph(blocked), directed=False)
        ok = ~blocked if blocked is not None else np.ones(highway.size, dtype=bool)
        sizes = np.bincount(label[ok], minlength=int(label.max()) + 1)
        main = int(np.argmax(sizes))
        members = np.flatnonzero(ok & (label == main))
        for i in np.flatnonzero((access >= 0) & (label[np.maximum(access, 0)] != main)):
            d = np.hypot(*(highway.nodes_in_map[members] - pos[i]).T)
            if d.size and float(d.min()) <= highway.access_m:
                access[i] = members[int(np.argmin(d))]
        return access

    def _kept_relay_spots(
        self, ctx: _Ctx, relay: NDArray[np.int64], region: NDArray[np.bool_]
    ) -> NDArray[np.int64]:
        """This plan's relay spots, then those kept from the last ``relay_keep_s`` (the most
        recently called for first), as highway waypoints in ``region``, not blocked."""
        keep_s = self.config.relay_keep_s
        if keep_s <= 0:
            return relay
        tol = self.config.disruptor.spread_tolerance_m
        nodes = ctx.highway.nodes_in_map
        for k in relay.tolist():
            x, y = float(nodes[k, 0]), float(nodes[k, 1])
            same = [e for e in self._relay_kept if math.hypot(e[0] - x, e[1] - y) < tol]
            if same:
                same[0][2] = ctx.now_s + keep_s
            else:
                self._relay_kept.append([x, y, ctx.now_s + keep_s])
        self._relay_kept = [e for e in self._relay_kept if e[2] > ctx.now_s]
        out = relay.tolist()
        kept = sorted(self._relay_kept, key=lambda e: -e[2])
        if kept:
            at = ctx.highway.nearest(np.asarray([e[:2] for e in kept]), ~region | ctx.blocked)
            for k, e in zip(at.tolist(), kept, strict=True):
                if k >= 0 and k not in out and math.dist(nodes[k], e[:2]) < tol:
                    out.append(k)
        return np.asarray(out, dtype=np.int64)

    @staticmethod
    def _clear_of_obstacles(ctx: _Ctx, clearance_m: float) -> NDArray[np.bool_]:
        """Highway waypoints at least ``clearance_m`` from every occupied planning cell."""
        grid = ctx.grid
        out = np.zeros(ctx.highway.size, dtype=bool)
        if ctx.highway.size == 0 or grid.values.size == 0:
            return out
        clear_m = ndimage.distance_transform_edt(grid.values != OCCUPIED) * grid.resolution_m
        cells = grid.cells_of(ctx.highway.nodes_in_map)
        inside = grid.inside(cells)
        out[inside] = clear_m[cells[inside, 0], cells[inside, 1]] >= clearance_m
        return out

    # ---- 5: exploration -----------------------------------------------------------------------

    def _explore(self, ctx: _Ctx) -> None:
        cfg = self.config
        sensors = {rid: r for rid, r in ctx.available.items() if r.role == Role.SENSOR}
        # reachable from any sensor robot or from anywhere a robot has driven (the highway):
        # a robot whose cell lies in a pocket of the map (a room whose doorway the dilation
        # closed, say) does not make the rest of the frontier unreachable (small world seed
        # 0: the only sensor heard sat in such a room and the planner said 'explored' at 199 s
        # with 22% of the site unseen); far goals go through the highway
        seeds = [ctx.cells[r] for r in sensors if r in ctx.cells]
        if sensors and ctx.highway.size:
            seeds += [tuple(c) for c in ctx.grid.cells_of(ctx.highway.nodes_in_map).tolist()]
        frontiers = find_frontiers(
            ctx.grid, seeds, goal_spacing_m=cfg.exploration.goal_separation_m / 3.0
        )
        self.frontiers = frontiers
        waiting: list[Explorer] = []
        claimed: list[tuple[float, float]] = []
        # a robot silent on its way to an exploration goal drives on to it (a radio shadow:
        # robot/comms_watchdog.py) and brings back what it saw: its goal stays claimed while
        # it may still be at it (its timeout). Released, it went to the next robot planned,
        # into the same shadow (small world seed 7: two robots took turns at goals 1 m apart
        # in the south-east shadow from 140 s to the end, while the middle stayed unseen)
        # (and the further goals of its tour)
        for rid, held in self.assignments.items():
            if (
                held.purpose == "explore:released"
                and rid in self._silent
                and rid not in self._lost
                and held.goal_in_map is not None
                and ctx.now_s - held.issued_s <= held.timeout_s
            ):
                claimed.append(held.goal_in_map)
                if held.tour_in_map is not None:
                    claimed.extend((float(x), float(y)) for x, y in held.tour_in_map)
        global_bad = self._globally_failed()
        for rid, r in sensors.items():
            a = self.assignments.get(rid)
            purpose = None if a is None else a.purpose
            if purpose in ("evade", "hostile_view"):
                continue
            if purpose == "explore" and a is not None and a.goal_in_map is not None:
                gone = not frontiers.near(a.goal_in_map, ctx.grid, cfg.frontier_gone_m)
                there = math.dist(self._position(r), a.goal_in_map) <= cfg.goal_reached_m
                stalled = self._stalled(ctx, r, a)
                if not (gone or there or stalled):
                    claimed.append(a.goal_in_map)
                    continue
                if stalled and not gone:
                    self.stats.goals_failed += 1
                    self._failed_goals.setdefault(rid, []).append(a.goal_in_map)
                    self._avoid_route(ctx, r, a)
                    self._event(
                        ctx,
                        "stalled",
                        rid,
                        f"robot {rid} stuck on its way ({cfg.stall_m:g} m moved in "
                        f"{cfg.stall_s:g} s or nearer in {cfg.stall_progress_s:g} s): another goal",
                    )
                elif gone:
                    self._event(
                        ctx,
                        "frontier_gone",
                        rid,
                        f"robot {rid}: the frontier at its goal is explored",
                    )
                else:
                    # at its goal and the frontier is still there: what is left cannot be
                    # seen from here; not this goal again for this robot
                    self.stats.goals_reached += 1
                    self._failed_goals.setdefault(rid, []).append(a.goal_in_map)
                    self._event(
                        ctx,
                        "goal_reached",
                        rid,
                        f"robot {rid} at its goal, frontier still there: re-planned",
                    )
            if rid not in ctx.cells:
                if rid not in self._no_start:
                    self._no_start.add(rid)
                    self._event(
                        ctx,
                        "no_start",
                        rid,
                        f"robot {rid}: no traversable map cell within {cfg.snap_m} m (no map "
                        "around it yet?): not planned for",
                    )
                continue
            self._no_start.discard(rid)
            shadow = [
                (g, t)
                for g, t in self._explore_shadowed.get(rid, [])
                if ctx.now_s - t < cfg.shadow_retry_s
            ]
            self._explore_shadowed[rid] = shadow
            bl = self._failed_goals.get(rid, []) + global_bad
            avoid = [d for d in self._avoid.get(rid, []) if d[3] > ctx.now_s]
            self._avoid[rid] = avoid
            waiting.append(
                Explorer(
                    rid,
                    ctx.cells[rid],
                    self._position(r),
                    np.asarray(bl, dtype=np.float64).reshape(-1, 2),
                    np.asarray([d[:3] for d in avoid], dtype=np.float64).reshape(-1, 3),
                    np.asarray(
                        [(g[0], g[1], cfg.shadow_goal_radius_m) for g, _ in shadow],
                        dtype=np.float64,
                    ).reshape(-1, 3),
                )
            )
        if not waiting:
            return
        gains = information_gain(
            ctx.grid, frontiers.goal_cells, sensor_range_m=cfg.exploration.sensor_range_m
        )
        explore_cfg = cfg.exploration
        left_s = ctx.state.mission_end_s - ctx.now_s
        contact = self.contact_in_map
        if left_s <= cfg.end_contact_s and len(contact) and len(frontiers.goals_in_map):
            # the end is near: only goals the robot can reach and come back to contact from
            # before it (the rest are blacklisted for it in this plan), no tours
            explore_cfg = msgspec.structs.replace(explore_cfg, tour_goals=0)
            goals = frontiers.goals_in_map
            back_m = np.full(len(goals), np.inf)
            for chunk in range(0, len(contact), 4096):
                c = contact[chunk : chunk + 4096]
                d = np.hypot(goals[:, None, 0] - c[None, :, 0], goals[:, None, 1] - c[None, :, 1])
                back_m = np.minimum(back_m, d.min(axis=1))
            reach_m = cfg.end_speed_m_s * max(left_s, 0.0)
            for k, e in enumerate(waiting):
                out_m = np.hypot(*(goals - np.asarray(e.position_in_map)).T)
                late = goals[out_m + back_m > reach_m]
                if len(late):
                    waiting[k] = dataclasses.replace(
                        e, blacklist_in_map=np.vstack([e.blacklist_in_map, late])
                    )
        plan = plan_exploration(
            ctx.grid,
            frontiers,
            gains,
            waiting,
            claimed_in_map=np.asarray(claimed, dtype=np.float64).reshape(-1, 2),
            highway=ctx.highway,
            highway_blocked=ctx.blocked,
            config=explore_cfg,
        )
        if plan.explored and not claimed:
            if not self.stats.explored:
                self._event(
                    ctx, "explored", None, "no reachable frontier left: the area is explored"
                )
            self.stats.explored = True
        elif not plan.explored:
            self.stats.explored = False
        for rid, g in plan.goals.items():
            wps = g.waypoints_in_map
            if cfg.exploration.return_to_contact:
                back = return_leg(
                    wps,
                    self._position(sensors[rid]),
                    contact,
                    radius_m=cfg.exploration.contact_radius_m,
                )
                if len(back):
                    # where the way back ends is driven to: a traversable cell (the GCS's
                    # map moved under a point of contact, say), else the robot's start
                    cell = ctx.grid.snap(back[-1], cfg.snap_m)
                    back[-1] = (
                        ctx.grid.centers_of([cell])[0]
                        if cell is not None
                        else np.asarray(self._position(sensors[rid]))
                    )
                if len(g.tour_in_map) and len(back):
                    home = shortcut(
                        ctx.grid,
                        wps[-1],
                        back[-1],
                        limit_m=float(
                            np.hypot(*np.diff(np.vstack([wps[-1:], back]), axis=0).T).sum()
                        ),
                        tolerance_m=cfg.exploration.path_tolerance_m,
                    )
                    if home is not None:
                        back = home
                wps = np.vstack([wps, back])
            self._goto(ctx, sensors[rid], wps, "explore", goal_in_map=g.goal_in_map)
            if len(g.tour_in_map):
                self.assignments[rid].tour_in_map = g.tour_in_map
        for rid in plan.unassigned:
            if (self._purpose(rid) or "").split(":")[0] != "park":
                self._event(ctx, "park", rid, f"robot {rid}: no frontier goal, parked")
                self._idle(ctx, sensors[rid], "park")

    def _avoid_route(self, ctx: _Ctx, r: RobotInfo, a: Assignment) -> None:
        """``r``'s route of ``a`` failed: the stretch just ahead of where it is now is avoided
        by its routes for ``avoid_s`` (see :class:`TaskingConfig`)."""
        cfg = self.config
        if a.route_in_map is None or r.pose_in_map is None:
            return
        route = a.route_in_map
        if a.goal_in_map is not None:
            # the way out only: an exploration route goes on back to radio contact over
            # the same ground, and what held the robot lies towards the goal
            at = np.flatnonzero(np.hypot(*(route - np.asarray(a.goal_in_map)).T) < 1e-6)
            if at.size:
                route = route[: int(at[0]) + 1]
        discs = failed_route_discs(
            route,
            self._position(r),
            from_m=cfg.avoid_from_m,
            to_m=cfg.avoid_to_m,
            radius_m=cfg.avoid_radius_m,
        )
        until = ctx.now_s + cfg.avoid_s
        self._avoid.setdefault(r.robot_id, []).extend(
            (float(x), float(y), float(rad), until) for x, y, rad in discs
        )
        if len(discs):
            x, y = discs[0, :2]
            self._event(
                ctx,
                "route_avoided",
                r.robot_id,
                f"robot {r.robot_id}: its route failed near ({x:.1f}, {y:.1f}): avoided by it "
                f"for {cfg.avoid_s:g} s",
            )

    def _stalled(self, ctx: _Ctx, r: RobotInfo, a: Assignment) -> bool:
        """Whether ``r`` has not moved ``stall_m`` for ``stall_s`` on its task ``a``."""
        cfg = self.config
        pos = self._position(r)
        to_goal = math.inf if a.goal_in_map is None else math.dist(pos, a.goal_in_map)
        ntid, nearer_s, best = self._nearer.get(r.robot_id, (-1, ctx.now_s, to_goal))
        if ntid != a.task_id or to_goal <= best - cfg.stall_m:
            self._nearer[r.robot_id] = (a.task_id, ctx.now_s, to_goal)
        elif ctx.now_s - nearer_s >= cfg.stall_progress_s:
            return True
        tid, since_s, at = self._progress.get(r.robot_id, (-1, ctx.now_s, pos))
        if tid != a.task_id or math.dist(pos, at) >= cfg.stall_m:
            self._progress[r.robot_id] = (a.task_id, ctx.now_s, pos)
            return False
        return ctx.now_s - since_s >= cfg.stall_s

    def _globally_failed(self) -> list[tuple[float, float]]:
        cfg = self.config
        out = []
        r = cfg.exploration.blacklist_radius_m
        for goal, _ in self._goal_failures:
            robots = {rid for g, rid in self._goal_failures if math.dist(g, goal) <= r}
            if len(robots) >= cfg.goal_failures_global:
                out.append(goal)
        return out
