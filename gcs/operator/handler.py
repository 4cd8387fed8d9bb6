"""The GCS's operator command handler: a command in, effects out (paper 6.2, 5.1.3).

:meth:`CommandHandler.handle` takes an authenticated :class:`~protocol.operator.Command` and
the GCS's collaborators (:class:`OperatorContext`: the
:class:`~gcs.ground_station.GroundStation`, optionally the
:class:`~gcs.tasking.allocator.TaskAllocator`, what the robots last reported) and returns an
:class:`Outcome`: the downlink messages to send (``(robot_id, message)``, tasks already in the
receiving robot's private frame through the GCS's ``map_from_odom``, paper 4.1), a reply text
for the operator and whether it counts as an interaction. Graph operations (suggest a closure,
rewind, restart the loop closer, simplify) are applied to the station at once, through its
operator primitives.

The handler keeps what the operators decided, which the planners must respect
(:attr:`CommandHandler.operator_controlled`, :attr:`CommandHandler.approved_hazard_ids`):

* ``goto`` / ``relay`` / ``neutralize`` make a robot *operator-controlled*
  (semi-autonomous: it plans its own path to the operator's goal); the task allocator must leave
  it alone (``RobotInfo.operator_controlled``) until ``auto`` gives it back;
* ``pause`` holds a robot (operator-controlled while paused); ``resume`` continues its task
  and restores who controlled it before;
* ``approve`` adds an OOI to the approved neutralizations (``TaskingState.approved_hazard_ids``).

The handler never raises for a bad command: :class:`Outcome` ``status`` is ``invalid`` with a
suggestion, or ``failed`` when it cannot be done now (no frame for a robot yet).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from gcs.operator.grammar import (
    KINDS,
    PARAMETERS,
    VERBS,
    CommandError,
    RobotFacts,
    parse_subset,
    suggest,
)
from protocol.messages import (
    AutonomyMode,
    GoToTask,
    Hazard,
    IdleTask,
    NeutralizeTask,
    ObjectKind,
    ParameterUpdate,
    PauseTask,
    RelayTask,
    ResumeTask,
    TaskState,
    TaskStatus,
    Telemetry,
)
from protocol.operator import OPERATOR_TASK_IDS_FROM, Command, is_operator_task
from protocol.se2 import inverse, transform_points

if TYPE_CHECKING:
    from gcs.ground_station import GroundStation

__all__ = ["CommandHandler", "OperatorContext", "Outcome", "RobotReport"]

#: Trigger radius of a static OOI plus a margin: where an operator's disruptor stands (paper 2).
STANDOFF_M = 3.5

#: Several robots sent to one point stand on a ring of this radius around it (m).
GOTO_RING_M = 1.5

#: Keep-out radius by kind after a reclassification (GroundStation.HAZARD_KINDS' values).
_HAZARD_RADIUS_M = {ObjectKind.STATIC_OOI: 2.5, ObjectKind.HOSTILE: 5.0}


@dataclass
class RobotReport:
    """What one robot last told the GCS (kept by the operator service from the uplink)."""

    telemetry: Telemetry | None = None
    status: TaskStatus | None = None
    last_heard_s: float = -math.inf

    @property
    def idle(self) -> bool:
        if self.telemetry is not None:
            return self.telemetry.task_id == 0 or self.telemetry.mode == AutonomyMode.IDLE
        if self.status is not None:
            return self.status.state not in (TaskState.ACCEPTED, TaskState.ACTIVE)
        return True


@dataclass
class OperatorContext:
    """The GCS side a command acts on. ``allocator``: the task allocator when one runs (any
    object with ``pending_approvals``, ``assignments``, ``config``), else None. ``roles``:
    robot id -> ``sensor`` / ``disruptor``; ``reports``: robot id -> :class:`RobotReport`.
    ``set_gcs_parameter(name, value)``: applies a GCS-side parameter (returns a text)."""

    station: GroundStation
    now_s: float
    allocator: Any = None
    roles: Mapping[int, str] = field(default_factory=dict)
    reports: Mapping[int, RobotReport] = field(default_factory=dict)
    set_gcs_parameter: Callable[[str, float], str] | None = None


@dataclass
class Outcome:
    """What a command did: ``status`` ``ok`` / ``invalid`` / ``failed``; ``text`` for the
    operator; ``downlink`` to send; ``interaction`` counts in the mission's metrics."""

    status: str
    text: str
    downlink: list[tuple[int, Any]] = field(default_factory=list)
    interaction: bool = False

    @property
    def task_ids(self) -> tuple[int, ...]:
        return tuple(int(m.task_id) for _, m in self.downlink if hasattr(m, "task_id"))


class _Failed(Exception):
    """It cannot be done now (not a bad command)."""


class CommandHandler:
    """Carries out operator commands (module docstring). ``first_task_id``: ids of the
    operator's tasks count up from here (disjoint from the allocator's, which start at
    1,000,000; the default also differs from a previous GCS run's, since a robot refuses a
    task id it has seen)."""

    def __init__(self, *, first_task_id: int | None = None) -> None:
        if first_task_id is None:
            first_task_id = OPERATOR_TASK_IDS_FROM + (time.time_ns() // 1_000_000) % 1_000_000_000
        if not is_operator_task(first_task_id):
            raise ValueError(
                f"first_task_id {first_task_id}: operator task ids start at "
                f"{OPERATOR_TASK_IDS_FROM} (robots report those tasks as semi-autonomous)"
            )
        self._next_id = int(first_task_id)
        self.operator_controlled: set[int] = set()
        self.paused: dict[int, bool] = {}  # robot -> was operator-controlled before the pause
        self.approved_hazard_ids: set[int] = set()
        self.reclassified: dict[int, str] = {}
        self.operator_tasks: dict[int, tuple[int, str]] = {}  # robot -> (task id, what)
        self.interactions: list[tuple[float, str]] = []  # (mission s, command text)
        self.counts: dict[str, int] = {}

    # ---- saved and restored (a resumed GCS) -----------------------------------------------

    def state(self) -> dict[str, Any]:
        """What the operators decided, as JSON fields (journaled with each command: a GCS
        resumed from its journal holds the same robots, approvals and interactions, and
        counts its task ids on past the killed one's; :meth:`restore`)."""
        return {
            "next_task_id": self._next_id,
            "operator_controlled": sorted(self.operator_controlled),
            "paused": {str(r): bool(was) for r, was in sorted(self.paused.items())},
            "approved_hazard_ids": sorted(self.approved_hazard_ids),
            "reclassified": {str(h): k for h, k in sorted(self.reclassified.items())},
            "operator_tasks": {
                str(r): [int(tid), what] for r, (tid, what) in sorted(self.operator_tasks.items())
            },
            "interactions": [[float(t), text] for t, text in self.interactions],
            "counts": dict(sorted(self.counts.items())),
        }

    def restore(self, state: Mapping[str, Any]) -> None:
        """Take the decisions :meth:`state` saved (a GCS resumed from its journal). Task ids
        go on past both the saved next id and this handler's own. ValueError (naming the
        field) on a state that is not one."""
        try:
            next_id = int(state["next_task_id"])
            controlled = {int(r) for r in state["operator_controlled"]}
            paused = {int(r): bool(was) for r, was in state["paused"].items()}
            approved = {int(h) for h in state["approved_hazard_ids"]}
            reclassified = {int(h): str(k) for h, k in state["reclassified"].items()}
            tasks = {int(r): (int(v[0]), str(v[1])) for r, v in state["operator_tasks"].items()}
            interactions = [(float(t), str(text)) for t, text in state["interactions"]]
            counts = {str(k): int(n) for k, n in state["counts"].items()}
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
            raise ValueError(f"operator handler state: {type(err).__name__}: {err}") from None
        if not is_operator_task(next_id):
            raise ValueError(f"operator handler state: next_task_id {next_id} is no operator id")
        self._next_id = max(self._next_id, next_id)
        self.operator_controlled = controlled
        self.paused = paused
        self.approved_hazard_ids = approved
        self.reclassified = reclassified
        self.operator_tasks = tasks
        self.interactions = interactions
        self.counts = counts

    # ---- planners' view ------------------------------------------------------------------

    def held_robots(self) -> frozenset[int]:
        """Robots the planners must not task now: operator-controlled or paused."""
        return frozenset(self.operator_controlled | set(self.paused))

    def control_of(self, robot_id: int) -> str:
        if robot_id in self.paused:
            return "paused"
        return "operator" if robot_id in self.operator_controlled else "planner"

    def task_text(self, robot_id: int, report: RobotReport | None, allocator: Any) -> str:
        """What the robot is doing: the operator's task with how it stands (``goto 4,4:
        succeeded``, from the robot's report on it), the planners' task, or the task id its
        telemetry names."""
        tid, what = self.operator_tasks.get(robot_id, (0, ""))
        if what:
            st = report.status if report is not None else None
            if st is not None and st.task_id == tid:
                state = TaskState(st.state).name.lower()
                return f"{what}: {state}" + (f" ({st.detail})" if st.detail else "")
            return what
        tele = report.telemetry if report is not None else None
        return planner_task(allocator, robot_id) or (
            f"task {tele.task_id}" if tele is not None and tele.task_id else "none"
        )

    def interactions_per_minute(self, now_s: float, window_s: float = 600.0) -> float:
        """Accepted interactions in the last ``window_s`` mission seconds, per minute."""
        n = sum(1 for t, _ in self.interactions if now_s - t <= window_s)
        return 60.0 * n / max(min(window_s, now_s), 1.0)

    # ---- the command ---------------------------------------------------------------------

    def handle(self, command: Command, ctx: OperatorContext) -> Outcome:
        """Carry out ``command`` (module docstring); never raises."""
        verb = VERBS.get(command.verb)
        if verb is None:
            return Outcome("invalid", suggest(command.verb, VERBS, what="command"))
        try:
            out = getattr(self, "_" + verb.name.replace("-", "_"))(command, ctx)
        except CommandError as err:
            return Outcome("invalid", str(err))
        except _Failed as err:
            return Outcome("failed", str(err))
        except (TypeError, ValueError, IndexError) as err:
            return Outcome("invalid", f"{command.verb}: {err}; usage: {verb.usage()}")
        if out.status == "ok" and verb.mutates:
            out.interaction = True
            self.interactions.append((ctx.now_s, command.text()))
            self.counts[verb.name] = self.counts.get(verb.name, 0) + 1
        return out

    # ---- helpers -------------------------------------------------------------------------

    def _facts(self, ctx: OperatorContext) -> dict[int, RobotFacts]:
        ids = set(ctx.station.graph.robots) | set(ctx.reports) | set(ctx.roles)
        return {
            r: RobotFacts(
                r,
                ctx.roles.get(r, "unknown"),
                (ctx.reports[r].idle if r in ctx.reports else True),
            )
            for r in ids
        }

    def _robots(self, spec: str, ctx: OperatorContext) -> list[int]:
        return parse_subset(spec, self._facts(ctx))

    def _new_id(self) -> int:
        tid = self._next_id
        self._next_id += 1
        return tid

    @staticmethod
    def _frames(ctx: OperatorContext) -> dict[int, tuple[float, float, float]]:
        return {f.robot_id: tuple(f.map_from_odom) for f in ctx.station.frames()}  # type: ignore[misc]

    def _to_odom(
        self, ctx: OperatorContext, robots: list[int], xy_in_map: tuple[float, float]
    ) -> dict[int, tuple[float, float]]:
        frames = self._frames(ctx)
        missing = [r for r in robots if r not in frames]
        if missing:
            raise _Failed(
                f"robot(s) {_ids(missing)} not linked to map yet (no map_from_odom): a goal in "
                "map cannot be expressed in their frame"
            )
        out = {}
        for r in robots:
            odom_from_map = inverse(np.asarray(frames[r], dtype=np.float64))
            p = transform_points(odom_from_map, np.asarray([xy_in_map], dtype=np.float64))[0]
            out[r] = (float(p[0]), float(p[1]))
        return out

    def _hazard(self, ctx: OperatorContext, target: str) -> tuple[int, Hazard]:
        hid = int(target)
        for i, h in enumerate(ctx.station.hazards):
            if h.hazard_id == hid:
                return i, h
        known = [str(h.hazard_id) for h in ctx.station.hazards]
        raise CommandError(suggest(target, known, what="OOI id"))

    def _release_allocator(self, ctx: OperatorContext, robots: list[int]) -> None:
        """Forget the allocator's assignments of ``robots`` so it re-plans them."""
        assignments = getattr(ctx.allocator, "assignments", None)
        if isinstance(assignments, dict):
            for r in robots:
                assignments.pop(r, None)

    def _take(self, robots: list[int], task_ids: list[int], what: str) -> None:
        for r, tid in zip(robots, task_ids, strict=True):
            self.operator_controlled.add(r)
            self.paused.pop(r, None)
            self.operator_tasks[r] = (tid, what)

    # ---- verbs ---------------------------------------------------------------------------

    def _goto(self, c: Command, ctx: OperatorContext) -> Outcome:
        robots = self._robots(c.target, ctx)
        x, y = float(c.args[0]), float(c.args[1])
        out = []
        n = len(robots)
        for i, r in enumerate(robots):
            # several robots to one point: each to its own place on a ring around it
            a = 2.0 * math.pi * i / n
            ring = GOTO_RING_M if n > 1 else 0.0
            goal = self._to_odom(ctx, [r], (x + ring * math.cos(a), y + ring * math.sin(a)))[r]
            out.append((r, GoToTask(self._new_id(), ctx.now_s, [goal])))
        self._take(robots, [m.task_id for _, m in out], f"goto {x:g},{y:g}")
        spread = f", spread {GOTO_RING_M:g} m around it" if n > 1 else ""
        return Outcome(
            "ok",
            f"goto ({x:g}, {y:g}) in map sent to robot(s) {_ids(robots)}{spread} (tasks "
            f"{_ids([m.task_id for _, m in out])}); operator-controlled until `auto`",
            out,
        )

    def _auto(self, c: Command, ctx: OperatorContext) -> Outcome:
        robots = self._robots(c.target, ctx)
        out = []
        for r in robots:
            self.operator_controlled.discard(r)
            self.paused.pop(r, None)
            if self.operator_tasks.pop(r, None) is not None and ctx.allocator is not None:
                # the robot drops the operator's goal now and stands, autonomous, until the
                # planners' next task (it drove on semi-autonomous to the operator's goal)
                out.append((r, IdleTask(self._new_id(), ctx.now_s)))
        self._release_allocator(ctx, robots)
        tail = (
            "the planners task them at their next plan"
            if ctx.allocator is not None
            else "no task allocator runs at this GCS: they keep their current task"
        )
        dropped = f"; operator goal dropped by robot(s) {_ids([r for r, _ in out])}" if out else ""
        return Outcome("ok", f"robot(s) {_ids(robots)} back to the planners; {tail}{dropped}", out)

    def _pause(self, c: Command, ctx: OperatorContext) -> Outcome:
        robots = self._robots(c.target, ctx)
        out = []
        for r in robots:
            if r not in self.paused:
                self.paused[r] = r in self.operator_controlled
            out.append((r, PauseTask(self._new_id(), ctx.now_s)))
        idle = [r for r in robots if r in ctx.reports and ctx.reports[r].idle]
        note = f" (robot(s) {_ids(idle)} had no task: they stand already)" if idle else ""
        return Outcome(
            "ok", f"pause sent to robot(s) {_ids(robots)}; held until `resume`{note}", out
        )

    def _resume(self, c: Command, ctx: OperatorContext) -> Outcome:
        robots = self._robots(c.target, ctx)
        out = []
        for r in robots:
            was_operator = self.paused.pop(r, r in self.operator_controlled)
            if not was_operator:
                self.operator_controlled.discard(r)
            out.append((r, ResumeTask(self._new_id(), ctx.now_s)))
        return Outcome("ok", f"resume sent to robot(s) {_ids(robots)}", out)

    def _neutralize(self, c: Command, ctx: OperatorContext) -> Outcome:
        _, h = self._hazard(ctx, c.target)
        rid = int(c.args[0])
        facts = self._facts(ctx)
        if rid not in facts:
            raise CommandError(suggest(str(rid), [str(r) for r in sorted(facts)], what="robot id"))
        if ctx.roles and ctx.roles.get(rid) != "disruptor":
            disruptors = [r for r, role in sorted(ctx.roles.items()) if role == "disruptor"]
            raise CommandError(
                f"robot {rid} is a {ctx.roles.get(rid, 'robot of unknown role')}, not a "
                f"disruptor; disruptors: {_ids(disruptors) or 'none'}"
            )
        if h.kind not in (ObjectKind.STATIC_OOI, ObjectKind.HOSTILE):
            raise CommandError(
                f"OOI {h.hazard_id} is a {ObjectKind(h.kind).name.lower()}: only static OOIs "
                "are neutralized by a laser (reclassify it first if it is one)"
            )
        xy = (float(h.position_in_map[0]), float(h.position_in_map[1]))
        target = self._to_odom(ctx, [rid], xy)[rid]
        standoff = STANDOFF_M
        cfg = getattr(getattr(ctx.allocator, "config", None), "disruptor", None)
        if cfg is not None:
            standoff = float(cfg.trigger_radius_m + cfg.standoff_margin_m)
        task = NeutralizeTask(self._new_id(), ctx.now_s, target, standoff, True)
        self._take([rid], [task.task_id], f"neutralize {h.hazard_id}")
        self.approved_hazard_ids.add(h.hazard_id)
        return Outcome(
            "ok",
            f"robot {rid} neutralizes OOI {h.hazard_id} at ({xy[0]:.1f}, {xy[1]:.1f}) from "
            f"{standoff:.1f} m, approved (task {task.task_id}); operator-controlled until `auto`",
            [(rid, task)],
        )

    def _approve(self, c: Command, ctx: OperatorContext) -> Outcome:
        _, h = self._hazard(ctx, c.target)
        pending = getattr(ctx.allocator, "pending_approvals", None)
        self.approved_hazard_ids.add(h.hazard_id)
        if ctx.allocator is None:
            tail = "no task allocator runs at this GCS: it applies when one does"
        elif pending is not None and h.hazard_id not in pending:
            tail = "it was not awaiting approval yet: approved in advance"
        else:
            tail = "the planners' disruptor fires once it is in place"
        return Outcome("ok", f"neutralization of OOI {h.hazard_id} approved; {tail}")

    def _relay(self, c: Command, ctx: OperatorContext) -> Outcome:
        rid = parse_subset(c.target, self._facts(ctx))
        if len(rid) != 1:
            raise CommandError(f"relay: one robot, got {_ids(rid)}")
        x, y = float(c.args[0]), float(c.args[1])
        p = self._to_odom(ctx, rid, (x, y))[rid[0]]
        task = RelayTask(self._new_id(), ctx.now_s, p)
        self._take(rid, [task.task_id], f"relay {x:g},{y:g}")
        return Outcome(
            "ok",
            f"robot {rid[0]} holds at ({x:g}, {y:g}) in map as a relay (task {task.task_id})",
            [(rid[0], task)],
        )

    def _reclassify(self, c: Command, ctx: OperatorContext) -> Outcome:
        i, h = self._hazard(ctx, c.target)
        name = str(c.args[0]).lower()
        if name not in KINDS:
            raise CommandError(suggest(name, KINDS, what="kind"))
        kind = ObjectKind[name.upper()]
        radius_m = _HAZARD_RADIUS_M.get(kind, 0.0)
        edit = getattr(ctx.station, "edit_hazard", None)
        if edit is not None:  # a journaled station: the edit survives a resume and a replay
            edit(h.hazard_id, int(kind), radius_m)
        else:  # in place, same index: the station's per-hazard sighting counts stay aligned
            ctx.station.hazards[i] = Hazard(h.hazard_id, kind, h.position_in_map, radius_m)
        self.reclassified[h.hazard_id] = name
        old = ObjectKind(h.kind).name.lower()
        return Outcome(
            "ok",
            f"OOI {h.hazard_id} reclassified {old} -> {name}; keep-out radius "
            f"{_HAZARD_RADIUS_M.get(kind, 0.0):g} m from the next hazard update",
        )

    def _pose_key(self, text: str, ctx: OperatorContext) -> int:
        rid_s, sep, node_s = str(text).partition(":")
        if not sep or not rid_s.isdigit():
            raise CommandError(f"closure: pose {text!r}: expected ROBOT:NODE, e.g. 2:40 or 2:last")
        rid = int(rid_s)
        graph = ctx.station.graph
        if rid not in graph.robots:
            known = [str(r) for r in graph.robots]
            raise CommandError(suggest(rid_s, known, what="robot id with poses"))
        if node_s == "last":
            return int(graph.last_key(rid))
        if not node_s.isdigit():
            raise CommandError(f"closure: pose {text!r}: NODE is an index or `last`")
        key = ctx.station.key_of(rid, int(node_s))
        if key is None:
            raise CommandError(f"closure: robot {rid} has no pose node {node_s} at the GCS")
        return int(key)

    def _closure(self, c: Command, ctx: OperatorContext) -> Outcome:
        a = self._pose_key(str(c.args[0]), ctx)
        b = self._pose_key(str(c.args[1]), ctx)
        if a == b:
            raise CommandError("closure: the two poses are the same")
        if a not in ctx.station.grids or b not in ctx.station.grids:
            raise _Failed("closure: both poses need a terrain grid at the GCS to be matched")
        try:
            result = ctx.station.suggest_closure(a, b)
        except ValueError as err:
            raise _Failed(f"closure: {err}") from None
        score = float(result.normalized_score)
        min_score = float(ctx.station.loop_closer.config.min_score)
        if score < min_score:
            return Outcome(
                "failed",
                f"closure {c.args[0]} ~ {c.args[1]}: best match scores {score:.2f}, below the "
                f"loop closer's {min_score:.2f}; nothing added",
            )
        edge = ctx.station.accept_closure(a, b, result, now_s=ctx.now_s)
        return Outcome(
            "ok",
            f"closure {c.args[0]} ~ {c.args[1]} matched (score {score:.3g}) and added as "
            f"operator edge {edge}; re-optimized at the next step",
        )

    def _rewind(self, c: Command, ctx: OperatorContext) -> Outcome:
        since = float(c.args[0])
        if since < 0:
            since = ctx.now_s + since
        removed = ctx.station.rewind_closures(since)
        return Outcome("ok", f"removed {removed} automatic closure(s) added after t={since:.1f} s")

    def _restart_loops(self, c: Command, ctx: OperatorContext) -> Outcome:
        ctx.station.restart_loop_closer()
        return Outcome("ok", "loop closer restarted: every pair may be matched again")

    def _simplify(self, c: Command, ctx: OperatorContext) -> Outcome:
        before = len(ctx.station.graph.edges())
        removed = ctx.station.simplify_graph()
        return Outcome(
            "ok",
            f"graph simplified: {len(removed)} of {before} edge(s) merged away, "
            f"{len(ctx.station.graph.edges())} left",
        )

    def _set(self, c: Command, ctx: OperatorContext) -> Outcome:
        name = str(c.args[0])
        if name not in PARAMETERS:
            raise CommandError(suggest(name, PARAMETERS, what="parameter"))
        raw = str(c.args[1])
        if PARAMETERS[name].startswith("gcs"):
            value = float(raw)
            if not (math.isfinite(value) and value > 0):
                raise CommandError(f"set {name}: expected seconds > 0, got {raw!r}")
            if ctx.set_gcs_parameter is None:
                raise _Failed(f"set {name}: this GCS does not take that parameter")
            return Outcome("ok", ctx.set_gcs_parameter(name, value))
        robots = self._robots(str(c.args[2]) if len(c.args) > 2 else "all", ctx)
        val: float | str
        if name == "codec":
            from compression import codec_names

            if raw not in codec_names():
                raise CommandError(suggest(raw, codec_names(), what="codec"))
            val = raw
        else:
            val = float(raw)
            if not (math.isfinite(val) and val > 0):
                raise CommandError(f"set {name}: expected a number > 0, got {raw!r}")
        # the telemetry rate is the robot's radio link's own parameter (consumed there)
        wire_name = "link.telemetry_period_s" if name == "telemetry_period_s" else name
        out = [(r, ParameterUpdate(wire_name, val)) for r in robots]
        return Outcome("ok", f"{name} = {val} sent to robot(s) {_ids(robots)}", out)

    def _status(self, c: Command, ctx: OperatorContext) -> Outcome:
        robots = self._robots(c.target, ctx) if c.target else sorted(self._facts(ctx))
        frames = self._frames(ctx)
        lines = [
            f"t={ctx.now_s:.1f} s  robots {len(robots)}  planner "
            f"{'on' if ctx.allocator is not None else 'off'}  interactions "
            f"{len(self.interactions)} ({self.interactions_per_minute(ctx.now_s):.2f}/min)"
        ]
        for r in robots:
            rep = ctx.reports.get(r, RobotReport())
            tele = rep.telemetry
            mode = AutonomyMode(tele.mode).name.lower() if tele is not None else "unknown"
            task = self.task_text(r, rep, ctx.allocator)
            pose = "not linked"
            if r in ctx.station.graph.robots and r in frames:
                x, y, t = ctx.station.graph.pose(ctx.station.graph.last_key(r))
                pose = f"({x:.1f}, {y:.1f}, {math.degrees(t):.0f} deg)"
            heard = (
                f"{ctx.now_s - rep.last_heard_s:.0f} s ago"
                if math.isfinite(rep.last_heard_s)
                else "never"
            )
            bat = (
                f"{100 * tele.battery_frac:.0f}%"
                if tele is not None and math.isfinite(tele.battery_frac)
                else "?"
            )
            lines.append(
                f"  robot {r:>2} {ctx.roles.get(r, '?'):9} {mode:15} {self.control_of(r):8} "
                f"{task:22} {pose:26} battery {bat:>4}  heard {heard}"
            )
        pending: set[int] = getattr(ctx.allocator, "pending_approvals", set()) or set()
        for h in ctx.station.hazards:
            state = (
                "approved"
                if h.hazard_id in self.approved_hazard_ids
                else ("pending approval" if h.hazard_id in pending else "live")
            )
            lines.append(
                f"  OOI {h.hazard_id:>3} {ObjectKind(h.kind).name.lower():11} at "
                f"({h.position_in_map[0]:.1f}, {h.position_in_map[1]:.1f})  {state}"
            )
        return Outcome("ok", "\n".join(lines))


def planner_task(allocator: Any, robot_id: int) -> str:
    """``"explore (task 1000007)"``: what the planners gave the robot, or empty."""
    a = getattr(allocator, "assignments", {}).get(robot_id)
    if a is None:
        return ""
    return f"{str(a.purpose).split(':')[0].replace('_', ' ')} (task {a.task_id})"


def _ids(ids: list[int] | tuple[int, ...]) -> str:
    return ",".join(str(i) for i in ids)
