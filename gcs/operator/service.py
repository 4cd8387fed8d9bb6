"""The operator station at the GCS: commands from consoles and the views, in one object the GCS
node calls (paper 6; DESIGN section 8: operators are clients of a running GCS).

:class:`OperatorService` is the node-side shell around the pure parts:

* commands: subscribes to ``magic/<mission>/gcs/command``; every sample is checked by
  :class:`~protocol.operator.CommandVerifier` on arrival (refused ones are logged, counted and
  answered with the reason); accepted ones wait for the node's thread, where
  :meth:`OperatorService.after_step` hands them to the
  :class:`~gcs.operator.handler.CommandHandler` with the station and the allocator, sends the
  tasks on the radio and publishes the reply on ``.../gcs/reply/<operator>``;
* status: a :class:`~protocol.operator.GcsStatus` on ``.../gcs/state/status`` every
  ``status_period_s`` (wall seconds: a console must see a live GCS even when mission time
  stands still) and a liveliness token on ``.../gcs/presence``;
* metrics: operator interactions (accepted commands that change something; ``on_interaction``
  tells the mission recorder) and time and distance per autonomy mode from each robot's
  telemetry (paper 7, Tables 4-5): a robot on an operator's task reports itself
  semi-autonomous (:data:`protocol.operator.OPERATOR_TASK_IDS_FROM`); one the operators hold
  that still reports autonomous is counted semi-autonomous too;
* views (optional): a :class:`~gcs.views.operator_picture.PictureBuilder` fed by
  :meth:`observe` and drawn by :class:`~gcs.views.rerun_views.RerunViews` (its own thread,
  never blocking the GCS) when a picture is due. ``cpu_s`` counts the views' CPU on the node
  thread; ``views.stats.draw_cpu_s`` the drawing thread's. A failure of the views (a picture
  not built, a sink or a drawing that failed in the views' thread) goes into the GCS journal
  as a ``view`` record at the next step, one per kind of failure with its count: when the
  operators did not see what the GCS knew (paper 7).

The node calls :meth:`observe` after each ``station.handle``, :meth:`after_step` once per
loop (after ``station.step``) and :meth:`close` on exit. Nothing here raises into the node.
"""

from __future__ import annotations

import collections
import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from gcs.operator.grammar import VERBS
from gcs.operator.handler import (
    CommandHandler,
    OperatorContext,
    Outcome,
    RobotReport,
)
from protocol import operator as op
from protocol.messages import AutonomyMode, ObjectKind, TaskStatus, Telemetry, encode_frame
from protocol.radio_channel import LinkBackpressure

if TYPE_CHECKING:
    from gcs.ground_station import GroundStation
    from gcs.views.operator_picture import PictureBuilder, PlannerView, ViewsConfig
    from gcs.views.rerun_views import RerunViews
    from protocol.link import Link

__all__ = ["ModeLedger", "OperatorService"]

log = logging.getLogger("magic.gcs.operator")


@dataclass
class ModeLedger:
    """Mission seconds and metres per autonomy mode, per robot, from telemetry (paper 7).

    A robot's interval between two telemetry messages is charged to the mode of the first;
    distance is the straight line between their private-frame positions (smooth, no loop
    closure jumps). Operator-controlled robots driving autonomously count as semi-autonomous.
    """

    time_s: dict[str, float] = field(default_factory=lambda: collections.defaultdict(float))
    distance_m: dict[str, float] = field(default_factory=lambda: collections.defaultdict(float))
    _last: dict[int, tuple[float, float, float, str]] = field(default_factory=dict)

    def add(self, robot_id: int, tele: Telemetry, mode: str) -> None:
        t = float(tele.time_s)
        x, y = float(tele.pose_in_odom[0]), float(tele.pose_in_odom[1])
        last = self._last.get(robot_id)
        if last is not None and t > last[0] and math.isfinite(x) and math.isfinite(y):
            self.time_s[last[3]] += t - last[0]
            self.distance_m[last[3]] += math.hypot(x - last[1], y - last[2])
        if math.isfinite(t):
            self._last[robot_id] = (t, x, y, mode)

    def state(self) -> dict[str, Any]:
        """The ledger as JSON fields (what :meth:`restore` takes back): the totals so far and
        each robot's last telemetry point, so the interval after a restart is charged too."""
        return {
            "time_s": {m: float(v) for m, v in sorted(self.time_s.items())},
            "distance_m": {m: float(v) for m, v in sorted(self.distance_m.items())},
            "last": {str(r): [t, x, y, m] for r, (t, x, y, m) in sorted(self._last.items())},
        }

    def restore(self, state: Mapping[str, Any]) -> None:
        """Take back a :meth:`state` (raises ``KeyError``/``TypeError``/``ValueError`` on a
        damaged one, leaving this ledger unchanged)."""
        time_s = {str(m): float(v) for m, v in state["time_s"].items()}
        distance_m = {str(m): float(v) for m, v in state["distance_m"].items()}
        last = {
            int(r): (float(v[0]), float(v[1]), float(v[2]), str(v[3]))
            for r, v in state["last"].items()
        }
        self.time_s.clear()
        self.time_s.update(time_s)
        self.distance_m.clear()
        self.distance_m.update(distance_m)
        self._last = last


class OperatorService:
    """Commands, status, metrics and views of the GCS (module docstring).

    ``link``: the GCS's :class:`~protocol.link.Link`; ``key``: the operator key (bytes), or
    ``key_file`` (default :func:`protocol.operator.default_key_path`, created on first use);
    ``views``: rerun sinks (``["spawn"]``, ``["save run.rrd"]``, ...) or None for no views;
    ``roles``: robot id -> ``sensor`` / ``disruptor`` (subsets ``sensors``, ``disruptors``);
    ``control``: the GCS's planners when they run (duck-typed
    :class:`~gcs.mission_control.MissionControl`: ``allocator``, ``role(id)``, and the sets
    ``operator_controlled`` and ``approved`` it plans with, which this service keeps equal to
    the operators' decisions), or None (estimation only: commands still reach the robots).
    ``journal``: the GCS journal (:class:`gcs.journal.GcsJournal`): every command, carried out
    or refused, becomes an ``operator`` record, and every ``ledger_period_s`` mission seconds
    one more carries the autonomy-mode ledger, so a resumed GCS's report counts the whole
    mission (:meth:`restore_operator`).
    """

    def __init__(
        self,
        link: Link,
        *,
        key: bytes | None = None,
        key_file: str | Path | None = None,
        views: list[str] | None = None,
        views_config: ViewsConfig | None = None,
        roles: Mapping[int, str] | None = None,
        control: Any = None,
        status_period_s: float = 1.0,
        handler: CommandHandler | None = None,
        meter_views_bytes: bool = True,
        journal: Any = None,
        ledger_period_s: float = 10.0,
    ) -> None:
        self.link = link
        self.mission = link.mission
        self._key_file = key_file
        if key is None:
            try:
                key = op.load_or_create_key(key_file, create=False)
            except op.KeyFileError:
                # no key file yet: made at the first command (the console makes it on its
                # first use too), so a GCS that never hears a console writes nothing
                if (Path(key_file) if key_file else op.default_key_path()).exists():
                    raise
        self.verifier: op.CommandVerifier | None = (
            op.CommandVerifier(key, self.mission) if key is not None else None
        )
        self._verifier_lock = threading.Lock()
        self.handler = handler or CommandHandler()
        self._roles: dict[int, str] = dict(roles or {})
        self.control = control
        self.status_period_s = status_period_s
        self.journal = journal  # a gcs.journal.GcsJournal: every command, kept or refused
        self.ledger_period_s = float(ledger_period_s)
        self._ledger_journaled_s = -math.inf
        self.reports: dict[int, RobotReport] = {}
        self.ledger = ModeLedger()
        self.refused_log: collections.deque[str] = collections.deque(maxlen=200)
        self.replies_sent = 0
        self.commands_done = 0
        self.commands_received = 0  # samples on the command key, kept or refused
        self.command_wall_s: list[float] = []  # wall seconds from arrival to reply
        self._pending: queue.SimpleQueue[tuple[float, op.SignedCommand | None, str, str]] = (
            queue.SimpleQueue()
        )
        self._last_status_wall = -math.inf
        self._now_s = 0.0
        self.cpu_s = 0.0  # views' CPU on the node thread (building pictures)
        self.view_failures = 0  # failures of the views taken from them (and journaled)
        self._key_problem = ""
        self.builder: PictureBuilder | None = None
        self.views: RerunViews | None = None
        self._meter_views_bytes = meter_views_bytes
        self._closed = False
        # told of every interaction (an accepted command that changed something), on the
        # node's thread: ``(mission s, operator id, command text, robots sent a task)``
        self.on_interaction: Callable[[float, str, str, tuple[int, ...]], None] | None = None
        if views:
            from gcs.views.operator_picture import PictureBuilder
            from gcs.views.rerun_views import RerunViews

            self.builder = PictureBuilder(views_config)
            self.views = RerunViews(views, application_id="magic_gcs")
        self._sub = link.subscribe(op.command_key(self.mission), self._on_command)
        link.declare_presence(op.presence_key(self.mission))

    @property
    def roles(self) -> dict[int, str]:
        """Robot id -> role, from the planners' roster when they run."""
        out = dict(self._roles)
        role = getattr(self.control, "role", None)
        if callable(role):
            for rid in set(self.reports) | set(out):
                r = role(rid)
                out[rid] = str(getattr(r, "value", r))
        return out

    def _allocator(self) -> Any:
        c = self.control
        if c is None or not getattr(getattr(c, "config", None), "enabled", True):
            return None
        return getattr(c, "allocator", None)

    def _sync_control(self) -> None:
        """The planners plan with the operators' decisions (held robots, approvals)."""
        c = self.control
        if c is None:
            return
        held = getattr(c, "operator_controlled", None)
        if isinstance(held, set):
            held.clear()
            held.update(self.handler.held_robots())
        approved = getattr(c, "approved", None)
        if isinstance(approved, set):
            approved.update(self.handler.approved_hazard_ids)

    def _get_verifier(self) -> op.CommandVerifier | None:
        """The verifier, made from the key file at the first command if there was none."""
        if self.verifier is not None:
            return self.verifier
        with self._verifier_lock:
            if self.verifier is None:
                try:
                    key = op.load_or_create_key(self._key_file)
                except (op.KeyFileError, OSError) as err:
                    self._key_problem = f"the GCS has no usable operator key: {err}"
                    return None
                self.verifier = op.CommandVerifier(key, self.mission)
            return self.verifier

    # ---- zenoh thread --------------------------------------------------------------------

    def _on_command(self, _key: str, payload: bytes) -> None:
        self.commands_received += 1  # one zenoh callback thread: no lock needed
        verifier = self._get_verifier()
        if verifier is None:
            try:
                cmd: op.SignedCommand | None = op.decode_signed(payload)
            except ValueError:
                cmd = None
            self._pending.put((time.perf_counter(), cmd, "no_key", self._key_problem))
            return
        cmd, reason, text = verifier.check(payload)
        self._pending.put((time.perf_counter(), cmd, reason, text))

    # ---- node thread ---------------------------------------------------------------------

    def observe(
        self,
        robot_id: int,
        msg: Any,
        *,
        now_s: float,
        station: GroundStation,
        nbytes: int | None = None,
    ) -> None:
        """Note an uplink message the station just took. Never raises."""
        try:
            rep = self.reports.get(robot_id)
            if rep is None:
                rep = self.reports[robot_id] = RobotReport()
            rep.last_heard_s = now_s
            if isinstance(msg, Telemetry):
                rep.telemetry = msg
                self.ledger.add(robot_id, msg, self._mode_name(robot_id, msg))
            elif isinstance(msg, TaskStatus):
                rep.status = msg
            if self.builder is not None:
                if nbytes is None and self._meter_views_bytes:
                    nbytes = len(encode_frame(0, msg))  # what the frame put on the radio
                self.builder.observe(
                    robot_id, msg, now_s=now_s, nbytes=nbytes or 0, station=station
                )
        except Exception:
            log.exception("operator observe failed (the GCS goes on)")

    def _mode_name(self, robot_id: int, tele: Telemetry) -> str:
        mode = AutonomyMode(tele.mode)
        if mode == AutonomyMode.AUTONOMOUS and robot_id in self.handler.operator_controlled:
            mode = AutonomyMode.SEMI_AUTONOMOUS
        return mode.name.lower()

    def after_step(
        self,
        *,
        now_s: float,
        station: GroundStation,
        send: Callable[[int, Any], object],
        occupancy: Any = None,
    ) -> None:
        """Carry out the commands that arrived, publish status and views when due. Call once
        per node loop, after ``station.step``. Never raises."""
        self._now_s = now_s
        try:
            self._commands(now_s, station, send)
        except Exception:
            log.exception("operator commands failed (the GCS goes on)")
        try:
            if time.monotonic() - self._last_status_wall >= self.status_period_s:
                self._last_status_wall = time.monotonic()
                self.link.publish(op.status_key(self.mission), op.encode(self.status(station)))
        except Exception:
            log.exception("operator status failed (the GCS goes on)")
        self._journal_ledger(now_s)
        self._views(now_s, station, occupancy)

    def _journal_ledger(self, now_s: float) -> None:
        """An ``operator`` record with the mode ledger (and the handler state, so the newest
        such record is still what :meth:`restore_operator` starts from), when one is due."""
        if self.journal is None or not self.ledger._last:
            return  # nothing heard yet: nothing to keep
        if not now_s - self._ledger_journaled_s >= self.ledger_period_s:
            return
        self._ledger_journaled_s = now_s
        try:
            fields = {"ledger": self.ledger.state(), "handler": self.handler.state()}
            self.journal.event("operator", now_s, fields)
        except Exception:
            log.exception("journaling the mode ledger failed (the GCS goes on)")

    def _context(self, station: GroundStation, now_s: float) -> OperatorContext:
        return OperatorContext(
            station=station,
            now_s=now_s,
            allocator=self._allocator(),
            roles=self.roles,
            reports=self.reports,
            set_gcs_parameter=self._set_gcs_parameter,
        )

    def _commands(
        self, now_s: float, station: GroundStation, send: Callable[[int, Any], object]
    ) -> None:
        while True:
            try:
                t0, cmd, reason, text = self._pending.get_nowait()
            except queue.Empty:
                return
            if reason != "ok" or cmd is None:
                who = cmd.operator_id if cmd is not None else "?"
                line = f"t={now_s:.1f} s refused command from {who!r}: {reason}: {text}"
                self.refused_log.append(line)
                refused = self.verifier.refused if self.verifier is not None else {}
                n = sum(refused.values())
                if n <= 20 or n % 1000 == 0:  # a flood of forgeries must not flood the log
                    log.warning("%s (%d refused so far: %s)", line, n, dict(refused))
                if cmd is not None:
                    self._reply(cmd, "refused", reason, text, now_s)
                continue
            outcome = self.handler.handle(cmd.command, self._context(station, now_s))
            self._sync_control()
            failed_sends = self._send(outcome, send)
            if failed_sends:
                outcome.text += f" (radio queue full for robot(s) {failed_sends}: not sent)"
            log.info(
                "t=%.1f s operator %s: %s -> %s",
                now_s,
                cmd.operator_id,
                cmd.command.text(),
                outcome.status,
            )
            self.commands_done += 1
            self._reply(cmd, outcome.status, "", outcome.text, now_s, outcome)
            if outcome.interaction and self.on_interaction is not None:
                robots = tuple(sorted({int(r) for r, _ in outcome.downlink}))
                try:
                    self.on_interaction(now_s, cmd.operator_id, cmd.command.text(), robots)
                except Exception:
                    log.exception("on_interaction failed (the GCS goes on)")
            self.command_wall_s.append(time.perf_counter() - t0)

    def _send(self, outcome: Outcome, send: Callable[[int, Any], object]) -> list[int]:
        failed = []
        for rid, msg in outcome.downlink:
            try:
                send(rid, msg)
            except LinkBackpressure:
                failed.append(rid)
        return failed

    def _reply(
        self,
        cmd: op.SignedCommand,
        status: str,
        reason: str,
        text: str,
        now_s: float,
        outcome: Outcome | None = None,
    ) -> None:
        try:
            key = op.reply_key(self.mission, cmd.operator_id)
        except ValueError:
            return  # an operator id that cannot be a key: nobody to answer
        self._journal(cmd, status, reason, text, now_s, outcome)
        reply = op.CommandReply(
            op.OPERATOR_PROTOCOL_VERSION,
            cmd.operator_id,
            cmd.seq,
            status,
            reason,
            text,
            now_s,
            bool(outcome and outcome.interaction),
            outcome.task_ids if outcome else (),
        )
        self.link.publish(key, op.encode(reply))
        self.replies_sent += 1

    def _journal(
        self,
        cmd: op.SignedCommand,
        status: str,
        reason: str,
        text: str,
        now_s: float,
        outcome: Outcome | None,
    ) -> None:
        """An ``operator`` record in the GCS journal (paper 7: the logs the evaluation uses)."""
        if self.journal is None:
            return
        try:
            self.journal.event(
                "operator",
                now_s,
                {
                    "operator": cmd.operator_id,
                    "seq": cmd.seq,
                    "command": cmd.command.text(),
                    "status": status,
                    "reason": reason,
                    "text": text[:500],
                    "interaction": bool(outcome and outcome.interaction),
                    "task_ids": list(outcome.task_ids) if outcome else [],
                    # what the operators decided after it: a resumed GCS starts from the
                    # newest (restore_operator)
                    "handler": self.handler.state(),
                },
            )
        except Exception:
            log.exception("journaling an operator command failed (the GCS goes on)")

    def restore_operator(
        self, journal: Any = None, *, record: Any = None, heard: Mapping[int, Any] | None = None
    ) -> bool:
        """Take back what the operators had decided at the GCS that wrote ``journal`` (a
        :class:`gcs.journal.GcsJournal`; default this service's): the handler state of its
        newest ``operator`` record (or of ``record``, one such record), so a resumed GCS
        holds the same paused and operator-controlled robots, approvals, operator tasks and
        interactions as the killed one, and the planners plan with them at once. Returns
        whether there was a state to restore; a damaged one is logged and skipped (the
        resumed GCS starts with no operator decisions, as before). What the robots last
        reported comes back too (``heard``: robot id -> :class:`gcs.journal.Heard`, default
        :func:`gcs.journal.latest_heard` of the journal), so status shows them as before."""
        journal = journal if journal is not None else self.journal
        if heard is None and journal is not None:
            from gcs.journal import latest_heard

            try:
                heard = latest_heard(journal)
            except Exception as err:  # noqa: BLE001 - only what status shows
                log.error("robots' last reports not restored: %s", err)
        for rid, h in (heard or {}).items():
            rep = self.reports.setdefault(int(rid), RobotReport())
            if h.time_s > rep.last_heard_s:
                rep.last_heard_s = float(h.time_s)
                rep.telemetry = h.telemetry if h.telemetry is not None else rep.telemetry
                rep.status = h.status if h.status is not None else rep.status
        if journal is not None:
            self._restore_ledger(journal)
        if record is None:
            if journal is None:
                return False
            record = journal.latest_record("operator")
        if record is None:
            return False
        try:
            state = record.json().get("handler")
            if state is None:  # journaled before operator records carried it
                return False
            self.handler.restore(state)
        except Exception as err:  # noqa: BLE001 - a damaged record must not stop a resume
            log.error("operator state of journal record %s not restored: %s", record.seq, err)
            return False
        self._sync_control()
        log.info(
            "operator state restored from record %d: paused %s, operator-controlled %s, "
            "%d interaction(s)",
            record.seq,
            sorted(self.handler.paused),
            sorted(self.handler.operator_controlled),
            len(self.handler.interactions),
        )
        return True

    def _restore_ledger(self, journal: Any) -> None:
        """The autonomy-mode ledger of the newest ``operator`` record that carries one, and
        the telemetry journaled after it (at most ``ledger_period_s`` of it). A damaged
        record is logged and the ledger starts afresh, as before ledgers were journaled."""
        from gcs.journal import JournalError
        from protocol.messages import Direction, decode_frame

        try:
            newest = None
            for rec in journal.records(kind="operator"):
                if b'"ledger"' in rec.body:
                    newest = rec
            if newest is None:
                return
            self.ledger.restore(newest.json()["ledger"])
            n = 0
            for rec in journal.records(after_seq=newest.seq, kind="uplink"):
                try:
                    msg = decode_frame(rec.body, Direction.UP).msg
                except ValueError:
                    continue  # a damaged record: the replay names it
                if isinstance(msg, Telemetry):
                    self.ledger.add(rec.robot_id, msg, self._mode_name(rec.robot_id, msg))
                    n += 1
        except (JournalError, KeyError, TypeError, ValueError, AttributeError) as err:
            log.error("autonomy-mode ledger not restored (it starts afresh): %s", err)
            self.ledger = ModeLedger()
            return
        log.info(
            "autonomy-mode ledger restored from record %d and %d telemetry message(s) after it",
            newest.seq,
            n,
        )

    def _set_gcs_parameter(self, name: str, value: float) -> str:
        if name == "status_period_s":
            self.status_period_s = value
            return f"status_period_s = {value:g} s"
        if name == "views_period_s":
            if self.builder is None:
                return "views_period_s: no views run at this GCS (start it with --rerun ...)"
            import msgspec

            cfg = msgspec.structs.replace(self.builder.config, robots_period_s=value)
            self.builder.config = cfg
            return f"views_period_s = {value:g} s"
        raise ValueError(f"unknown GCS parameter {name!r}")

    # ---- status --------------------------------------------------------------------------

    def status(self, station: GroundStation) -> op.GcsStatus:
        """What consoles show and complete from."""
        graph = station.graph
        frames = {f.robot_id for f in station.frames()}
        roles = self.roles
        alloc = self._allocator()
        ids = sorted(set(graph.robots) | set(self.reports) | set(roles))
        rows = []
        for r in ids:
            rep = self.reports.get(r, RobotReport())
            tele = rep.telemetry
            pose = None
            if r in graph.robots and r in frames:
                x, y, t = graph.pose(graph.last_key(r))
                pose = (float(x), float(y), float(t))
            task = self.handler.task_text(r, rep, alloc)
            rows.append(
                op.RobotRow(
                    r,
                    roles.get(r, "unknown"),
                    AutonomyMode(tele.mode).name.lower() if tele is not None else "unknown",
                    task,
                    self.handler.control_of(r),
                    pose,
                    rep.last_heard_s if math.isfinite(rep.last_heard_s) else -1.0,
                    float(tele.battery_frac) if tele is not None else math.nan,
                )
            )
        pending: set[int] = getattr(alloc, "pending_approvals", set()) or set()
        neutralized: set[int] = getattr(alloc, "neutralized", set()) or set()
        hazards = []
        for h in station.hazards:
            if h.hazard_id in neutralized:
                state = "neutralized"
            elif h.hazard_id in self.handler.approved_hazard_ids:
                state = "approved"
            elif h.hazard_id in pending:
                state = "pending_approval"
            else:
                state = "live"
            hazards.append(
                op.HazardRow(
                    h.hazard_id,
                    ObjectKind(h.kind).name.lower(),
                    (float(h.position_in_map[0]), float(h.position_in_map[1])),
                    state,
                )
            )
        return op.GcsStatus(
            op.OPERATOR_PROTOCOL_VERSION,
            self.mission,
            self._now_s,
            rows,
            hazards,
            len(self.handler.interactions),
            alloc is not None,
            tuple(VERBS),
        )

    def metrics(self) -> dict[str, float]:
        """Interactions and autonomy-mode figures for the mission report."""
        now = self._now_s
        out: dict[str, float] = {
            "interactions": float(len(self.handler.interactions)),
            "interactions_per_min": self.handler.interactions_per_minute(now, window_s=now or 1),
            "commands_refused": float(
                sum(self.verifier.refused.values()) if self.verifier is not None else 0
            ),
        }
        for mode, t in self.ledger.time_s.items():
            out[f"time_s_{mode}"] = t
        for mode, d in self.ledger.distance_m.items():
            out[f"distance_m_{mode}"] = d
        return out

    # ---- views ---------------------------------------------------------------------------

    def planner_view(self) -> PlannerView | None:
        """The allocator's frontiers, highway and goals for the TOC (None without one)."""
        from gcs.views.operator_picture import PlannerView

        alloc = self._allocator()
        if alloc is None:
            return None
        fr = getattr(alloc, "frontiers", None)
        hw = getattr(alloc, "highway", None)
        edges = None
        if hw is not None and int(getattr(hw, "size", 0)):
            coo = hw.adjacency.tocoo()
            keep = coo.row < coo.col
            edges = np.column_stack([coo.row[keep], coo.col[keep]]).astype(np.int64)
        goals = {}
        tasks = {}
        for rid, a in getattr(alloc, "assignments", {}).items():
            if a.goal_in_map is not None:
                goals[rid] = np.asarray(a.goal_in_map, dtype=float)
            tasks[rid] = a.purpose.split(":")[0].replace("_", " ")
        for rid, (_, what) in self.handler.operator_tasks.items():
            tasks[rid] = "operator " + what
        return PlannerView(
            frontiers_in_map=None if fr is None else fr.goals_in_map,
            trajectory_nodes_in_map=None if hw is None else hw.nodes_in_map,
            trajectory_edges=edges,
            goals_in_map=goals,
            tasks=tasks,
        )

    def _views(self, now_s: float, station: GroundStation, occupancy: Any) -> None:
        if self.builder is None or self.views is None:
            return
        c0 = time.thread_time()
        if occupancy is None:
            # the map the planners rasterized for their last plan, when they keep it: the
            # views then need no rasterization of their own
            occupancy = getattr(self.control, "occupancy", None)
        try:
            if self.builder.due(now_s):
                pic = self.builder.build(
                    station, now_s, occupancy=occupancy, planner=self.planner_view()
                )
                self.views.publish(pic, now_s)
        except Exception as err:
            log.exception("operator views failed (the GCS goes on)")
            self._journal_view("build", f"building the picture failed: {_what(err)}", 1, now_s)
        finally:
            self._journal_view_failures(now_s)
            self.cpu_s += time.thread_time() - c0

    def _journal_view_failures(self, now_s: float) -> None:
        """The views' failures since the last step, into the journal (module docstring)."""
        if self.views is None:
            return
        for f in self.views.take_failures():
            self._journal_view(f.kind, f.text, f.count, now_s)

    def _journal_view(self, kind: str, text: str, count: int, now_s: float) -> None:
        self.view_failures += count
        if self.journal is None:
            return
        try:
            self.journal.event("view", now_s, {"kind": kind, "text": text, "count": count})
        except Exception:
            log.exception("journaling a view failure failed (the GCS goes on)")

    def close(self, station: GroundStation | None = None, timeout_s: float = 5.0) -> None:
        """A last full picture (map and graph), flush the views, stop listening."""
        if self._closed:
            return
        self._closed = True
        try:
            self._sub.close()
        except Exception:
            pass
        if self.views is not None:
            try:
                if station is not None and self.builder is not None and station.graph.robots:
                    pic = self.builder.build(
                        station, self._now_s, planner=self.planner_view(), force_layers=True
                    )
                    self.views.publish(pic, self._now_s)
            except Exception:
                log.exception("final operator picture failed")
                self._journal_view("build", "the last picture failed", 1, self._now_s)
            self.views.close(timeout_s)
            self._journal_view_failures(self._now_s)  # the last flush's too


def _what(err: BaseException) -> str:
    return f"{type(err).__name__}: {err}"


def views_thread_cpu_s(service: OperatorService) -> float:
    """CPU seconds the views cost: node-thread building plus the drawing thread."""
    return service.cpu_s + (service.views.stats.draw_cpu_s if service.views else 0.0)
