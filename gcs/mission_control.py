"""The GCS's estimate and its planners, composed: the one place they meet (paper 4.1, 5.1).

:class:`MissionControl` owns a :class:`~gcs.ground_station.GroundStation` (the global estimate)
and a :class:`~gcs.tasking.allocator.TaskAllocator` (the planners' memory). The GCS node
(:mod:`gcs.node`, ``magic gcs``) and the mission (``magic run``, :mod:`mission.assembly`) both
drive it the same way:

* :meth:`MissionControl.handle` takes each uplink message (the station's ``handle``);
* :meth:`MissionControl.step` runs the station's step (loop closing, iSAM2, frames and hazards
  for every robot) and, every ``plan_period_s`` mission seconds, builds a
  :class:`~gcs.tasking.allocator.TaskingState` from the station alone (rasterized global map,
  poses and ``map_from_odom`` of every robot linked to ``map``, last task report and last time
  heard, hazards, hostile sightings, the trajectories of the pose graph), plans, and returns the
  tasks with the station's downlink: ``(robot_id, message)`` pairs, each task already in that
  robot's private frame.

Nothing here reads ground truth or the wall clock: given the same messages at the same mission
times it returns the same tasks (the loop closer's wall budget is the caller's: ``math.inf`` in
lockstep, where its match rate in mission time binds). The planners only ever see what the
robots sent; a robot never heard from is not planned for.

Roles come from the team's roster (``disruptors``: ids of the disruptors; every other robot is a
sensor robot, paper 2). Operator hooks: :attr:`MissionControl.operator_controlled` (robots an
operator drives: the planners leave them alone, paper 5.1.3), :attr:`MissionControl.approved`
(neutralizations the operator approved when approval is ``operator``), :attr:`MissionControl.
lost` (robots the operator wrote off). Every planner event is kept in :attr:`journal` and
passed to ``on_event``.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable, Sequence
from typing import Any

import cv2
import msgspec
import numpy as np

from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.mapping.rasterization import OCCUPIED, OccupancyMap
from gcs.tasking.allocator import (
    RobotInfo,
    Role,
    TaskAllocator,
    TaskingConfig,
    TaskingEvent,
    TaskingState,
)
from protocol.messages import AutonomyMode

__all__ = ["MissionControl", "MissionControlConfig", "bounded", "tasking_state"]


class MissionControlConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``plan_period_s``: mission seconds between plans; ``disruptors``: ids of the team's
    disruptors (the others are sensor robots); ``tasking``: the planners' configuration;
    ``journal_size``: planner events kept; ``enabled``: plan at all (off: estimation only);
    ``area_in_map``: the area of operations, a polygon ``[(x_m, y_m), ...]`` in ``map``
    (MAGIC's phase boundaries were known to the teams): the planners treat everything outside
    it as blocked, so no frontier lies beyond it (empty: no bound). The GCS's map marks free
    space by range from each pose, without occlusion, so without a bound the far side of the
    site's outer walls looks like open frontier."""

    plan_period_s: float = 2.0
    # mission time when the mission ends (None: not known), for the planners' end-of-mission
    # rule (TaskingConfig.end_contact_s: in the last minutes, goals only where the robot can
    # be back in radio contact before the end)
    mission_end_s: float | None = None
    disruptors: tuple[int, ...] = ()
    area_in_map: tuple[tuple[float, float], ...] = ()
    tasking: TaskingConfig = msgspec.field(default_factory=TaskingConfig)
    journal_size: int = 10_000
    enabled: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.plan_period_s) and self.plan_period_s > 0):
            raise ValueError(f"plan_period_s: expected seconds > 0, got {self.plan_period_s}")
        if any(r < 0 for r in self.disruptors):
            raise ValueError(f"disruptors: ids must be >= 0, got {self.disruptors}")
        if self.mission_end_s is not None and not math.isfinite(self.mission_end_s):
            raise ValueError(
                f"mission_end_s: expected finite mission seconds, got {self.mission_end_s}"
            )
        if self.journal_size < 1:
            raise ValueError(f"journal_size: expected >= 1, got {self.journal_size}")
        if self.area_in_map and (
            len(self.area_in_map) < 3
            or not all(math.isfinite(v) for xy in self.area_in_map for v in xy)
        ):
            raise ValueError(
                f"area_in_map: expected 3 or more finite (x_m, y_m) vertices, got "
                f"{list(self.area_in_map)}"
            )


def bounded(occupancy: OccupancyMap, area_in_map: Sequence[tuple[float, float]]) -> OccupancyMap:
    """``occupancy`` with every cell outside the polygon ``area_in_map`` marked occupied, to
    within a cell on the polygon's edges (a copy; the input is unchanged). No polygon:
    ``occupancy`` itself."""
    if len(area_in_map) < 3 or occupancy.values.size == 0:
        return occupancy
    res = occupancy.resolution_m
    poly = (np.asarray(area_in_map, dtype=np.float64) - occupancy.origin_in_map) / res - 0.5
    inside = np.zeros(occupancy.values.shape, dtype=np.uint8)
    # cv2 fills integer vertices: 8 fractional bits keep the polygon to 1/256 of a cell
    cv2.fillPoly(inside, [np.round(poly * 256).astype(np.int32)], 1, lineType=cv2.LINE_8, shift=8)
    values = occupancy.values.copy()
    values[inside == 0] = OCCUPIED
    return OccupancyMap(values, occupancy.origin_in_map, res)


def tasking_state(
    station: GroundStation,
    roles: dict[int, Role],
    *,
    operator_controlled: frozenset[int] = frozenset(),
    lost: frozenset[int] = frozenset(),
    approved: frozenset[int] = frozenset(),
    area_in_map: Sequence[tuple[float, float]] = (),
    occupancy: OccupancyMap | None = None,
    mission_end_s: float = math.inf,
) -> TaskingState:
    """What the allocator needs, from the station only: every robot heard from (its role from
    ``roles``, sensor if absent), its pose and ``map_from_odom`` when linked to ``map``, its
    last report and last time heard; the rasterized map (blocked outside ``area_in_map``, see
    :func:`bounded`), hazards, hostile sightings and the pose graph's trajectories. A robot
    whose telemetry says ``DISABLED`` counts as lost. ``occupancy``: the station's map if
    already rasterized now (else rasterized here)."""
    robots = []
    for rid in station.robot_ids:
        heard = station.last_heard_s(rid)
        if heard is None:
            continue
        linked = station.linked(rid)
        mfo = station.graph.map_from_odom(rid) if linked else None
        telemetry = station.telemetry(rid)
        disabled = telemetry is not None and telemetry.mode == AutonomyMode.DISABLED
        robots.append(
            RobotInfo(
                rid,
                roles.get(rid, Role.SENSOR),
                station.pose_in_map(rid) if linked else None,
                None if mfo is None else (float(mfo[0]), float(mfo[1]), float(mfo[2])),
                heard,
                status=station.last_status(rid),
                operator_controlled=rid in operator_controlled,
                lost=rid in lost or disabled,
            )
        )
    ids, keys, xy = station.trajectories()
    return TaskingState(
        bounded(station.rasterize() if occupancy is None else occupancy, area_in_map),
        robots,
        hazards=list(station.hazards),
        trajectory_robot_ids=ids,
        trajectory_keys=keys,
        trajectory_xy_in_map=xy,
        hostile_seen_s=station.hostile_sightings(),
        approved_hazard_ids=approved,
        mission_end_s=mission_end_s,
    )


class MissionControl:
    """The station and the allocator (see the module docstring). Not thread-safe: one thread
    calls :meth:`handle` and :meth:`step` (the GCS node's loop, or the lockstep ground turn)."""

    def __init__(
        self,
        station: GroundStation | GroundStationConfig | None = None,
        config: MissionControlConfig | None = None,
        *,
        on_event: Callable[[TaskingEvent], None] | None = None,
    ) -> None:
        self.station = station if isinstance(station, GroundStation) else GroundStation(station)
        self.config = config or MissionControlConfig()
        self.allocator = TaskAllocator(self.config.tasking)
        self.roles: dict[int, Role] = {r: Role.DISRUPTOR for r in self.config.disruptors}
        self.operator_controlled: set[int] = set()
        self.approved: set[int] = set()
        self.lost: set[int] = set()
        self.journal: collections.deque[TaskingEvent] = collections.deque(
            maxlen=self.config.journal_size
        )
        self.on_event = on_event
        self.tasks_sent: collections.Counter[int] = collections.Counter()
        self.last_tasks: dict[int, Any] = {}
        self.occupancy: OccupancyMap | None = None  # the map of the last plan (views reuse it)
        self._last_plan_s = -math.inf

    def role(self, robot_id: int) -> Role:
        return self.roles.get(robot_id, Role.SENSOR)

    def handle(self, robot_id: int, msg: object, *, now_s: float) -> bool:
        """One uplink message (the station's :meth:`~GroundStation.handle`)."""
        return self.station.handle(robot_id, msg, now_s=now_s)

    def step(self, *, now_s: float, budget_s: float | None = None) -> list[tuple[int, Any]]:
        """The station's step, then a plan when one is due; the downlink to send (frames and
        hazards first, then tasks). ``budget_s``: the loop closer's wall budget (see the
        module docstring)."""
        out = self.station.step(now_s=now_s, budget_s=budget_s)
        if self.config.enabled and now_s - self._last_plan_s >= self.config.plan_period_s:
            self._last_plan_s = now_s
            out.extend(self.plan(now_s))
        return out

    def plan(self, now_s: float) -> list[tuple[int, Any]]:
        """Build the state from the station and plan now (the allocator never raises)."""
        self.occupancy = self.station.rasterize()
        state = tasking_state(
            self.station,
            self.roles,
            operator_controlled=frozenset(self.operator_controlled),
            lost=frozenset(self.lost),
            approved=frozenset(self.approved),
            area_in_map=self.config.area_in_map,
            occupancy=self.occupancy,
            mission_end_s=(
                math.inf if self.config.mission_end_s is None else self.config.mission_end_s
            ),
        )
        tasks = self.allocator.plan(state, now_s)
        for event in self.allocator.events:
            self.journal.append(event)
            if self.on_event is not None:
                self.on_event(event)
        for rid, task in tasks:
            self.tasks_sent[rid] += 1
            self.last_tasks[rid] = task
        return list(tasks)

    @property
    def explored(self) -> bool:
        """The exploration planner found no reachable frontier left (the area is explored)."""
        return self.allocator.stats.explored
