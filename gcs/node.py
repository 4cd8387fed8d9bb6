"""``magic gcs``: the ground-control station as its own process (DESIGN section 4, paper 4.1).

A thin shell around :class:`~gcs.mission_control.MissionControl` (the
:class:`~gcs.ground_station.GroundStation` and the task allocator): uplink messages arrive on
the link's thread and are queued; the node's loop hands them to the station, runs
:meth:`~gcs.mission_control.MissionControl.step` every ``step_period_s`` (mission time: loop
closing, iSAM2, frames and hazards, and a plan every ``plan_period_s``) and sends what it
returns on each robot's downlink (tasks in each robot's private frame). Mission time follows
the simulator's clock ticks (``--clock sim``, the default) or the host's clock (``--clock
wall``) on real robots.
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec

from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.journal import (
    GcsJournal,
    JournaledStation,
    JournalError,
    ResumedControl,
    resume_control,
    step_control,
)
from gcs.mission_control import MissionControl, MissionControlConfig
from gcs.node_args import gcs_parser
from gcs.operator.node_hooks import (  # operator (issue 15): views and console commands
    check_operator_arguments,
    operator_service,
)
from gcs.operator.service import OperatorService  # operator (issue 15)
from protocol import keys
from protocol.clock import ManualClock, ScaledClock, WallClock
from protocol.config import ConfigError, load_config
from protocol.link import Link
from protocol.messages import STREAMS, Direction, HazardUpdate, Reliability, stream_of
from protocol.process_cli import (
    follow_sim_clock,
    link_config,
    spin_until,
    stop_on_interrupt,
)
from protocol.radio import RadioConfig
from protocol.radio_channel import LinkBackpressure

__all__ = [
    "GcsProcess",
    "LinkLedger",
    "check_endpoint",
    "main",
    "restore_link_state",
    "summary_line",
]

#: Sequence numbers a resumed GCS skips on its latest-only downlink streams (acks, hazard
#: updates, broadcasts) past the last journaled snapshot: more than a second of them can
#: have gone out between two snapshots, and a robot drops anything not newer than what it has.
LATEST_SEQ_MARGIN = 100_000
#: Reliable downlink messages per robot and stream a resumed GCS sends again (with their
#: sequence numbers: a robot that had them drops them as duplicates).
RESEND_TAIL = 32
_LATEST_DOWN = [
    name
    for name, spec in STREAMS[Direction.DOWN].items()
    if spec.reliability is not Reliability.RELIABLE and not spec.broadcast
]


def link_snapshot(radio: Any) -> dict[str, Any]:
    """The next sequence numbers of the GCS endpoint's latest-only downlink streams, per robot
    and for the broadcast (for the journal's ``link`` records). Reads the channels' private
    state: the link has no public accessor yet."""
    robots = {}
    for rid in radio.robots():
        ch = radio.channel(rid)
        robots[str(rid)] = {n: ch._send[n].next_seq for n in _LATEST_DOWN if n in ch._send}
    bc = radio.broadcast_channel
    return {"robots": robots, "broadcast": {n: st.next_seq for n, st in bc._send.items()}}


class LinkLedger:
    """What a resumed GCS endpoint needs of the journal to continue every robot's radio streams
    (:func:`restore_link_state`), kept up to date as records are journaled and saved in the
    journal's ``link`` records, so that a resume reads the newest ``link`` record and decodes
    only the records after it, however long the journal (issue 17: a restart that stays
    flat). Per robot: how many messages each reliable uplink stream delivered (the link
    delivers them in order, exactly once, from 1: the count is the last sequence number), the
    record numbers of the last two pose nodes and the last terrain grid (the stream decoders'
    references), and per reliable downlink stream the record numbers of the last
    ``RESEND_TAIL`` messages; and the latest-only streams' snapshot (:func:`link_snapshot`)."""

    def __init__(self) -> None:
        self.up: dict[tuple[int, str], int] = {}
        self.node_seqs: dict[int, list[int]] = {}
        self.grid_seq: dict[int, int] = {}
        self.down_seqs: dict[tuple[int, str], list[int]] = {}
        #: uplink held behind a gap: (robot, stream) -> stream sequence number -> record
        self.held: dict[tuple[int, str], dict[int, int]] = {}
        self.snapshot: dict[str, Any] | None = None
        #: records decoded by :meth:`from_journal` (the tail after the newest ``link`` record)
        self.records_read = 0

    def uplink(self, robot_id: int, msg: Any, seq: int) -> None:
        """An uplink message journaled as record ``seq``."""
        from protocol.messages import PoseNode, TerrainGrid

        spec = stream_of(Direction.UP, msg)
        if spec.reliability is Reliability.RELIABLE:
            key = (robot_id, spec.name)
            self.up[key] = self.up.get(key, 0) + 1
        if isinstance(msg, PoseNode):
            nodes = self.node_seqs.setdefault(robot_id, [])
            nodes.append(seq)
            del nodes[:-2]
        elif isinstance(msg, TerrainGrid):
            self.grid_seq[robot_id] = seq

    def downlink(self, robot_id: int, stream: str, seq: int) -> None:
        """A reliable downlink message of ``stream`` journaled as record ``seq``."""
        tail = self.down_seqs.setdefault((robot_id, stream), [])
        tail.append(seq)
        del tail[:-RESEND_TAIL]

    def journal_held(self, radio: Any, journal: GcsJournal, now_s: float) -> int:
        """Journal (``held`` records) the uplink messages ``radio`` holds behind a gap that
        are not journaled yet, and forget those delivered since: the link acknowledged them
        selectively, so their robots will not send them again, and a GCS killed now must
        not lose them. Call before each commit. Returns the records appended. Reads the
        channels' private state (no public accessor)."""
        from protocol.messages import encode_frame

        added = 0
        for rid in radio.robots():
            ch = radio.channel(rid)
            for name, rs in ch._recv.items():
                if rs.spec.reliability is not Reliability.RELIABLE:
                    continue
                known = self.held.get((rid, name))
                if not rs.buffer and not known:
                    continue
                known = self.held.setdefault((rid, name), {})
                for seq in [s for s in known if s not in rs.buffer]:
                    del known[seq]  # delivered (journaled as uplink) or dropped
                for seq, msg in sorted(rs.buffer.items()):
                    if seq not in known:
                        known[seq] = journal.append(
                            "held", now_s, encode_frame(seq, msg), robot_id=rid
                        )
                        added += 1
        return added

    def robots(self) -> set[int]:
        out = {r for r, _ in self.up} | {r for r, _ in self.down_seqs}
        if self.snapshot is not None:
            out |= {int(r) for r in self.snapshot["robots"]}
        return out

    def to_json(self) -> dict[str, Any]:
        return {
            "up": [[r, s, n] for (r, s), n in sorted(self.up.items())],
            "nodes": {str(r): v for r, v in sorted(self.node_seqs.items())},
            "grid": {str(r): v for r, v in sorted(self.grid_seq.items())},
            "down": [[r, s, v] for (r, s), v in sorted(self.down_seqs.items())],
            "held": [[r, s, sorted(v.items())] for (r, s), v in sorted(self.held.items()) if v],
        }

    @classmethod
    def from_journal(cls, journal: GcsJournal) -> LinkLedger:
        """The ledger at the journal's end: from its newest ``link`` record that carries one
        (the records after it decoded), else (a journal written before ledgers) from every
        record."""
        from protocol.messages import decode_frame

        ledger = cls()
        after = 0
        last = journal.latest_record("link")
        if last is not None:
            body = last.json()
            saved = body.get("ledger")
            if isinstance(saved, dict):
                ledger.up = {(int(r), str(s)): int(n) for r, s, n in saved["up"]}
                ledger.node_seqs = {int(r): [int(x) for x in v] for r, v in saved["nodes"].items()}
                ledger.grid_seq = {int(r): int(v) for r, v in saved["grid"].items()}
                ledger.down_seqs = {
                    (int(r), str(s)): [int(x) for x in v] for r, s, v in saved["down"]
                }
                ledger.held = {
                    (int(r), str(s)): {int(q): int(x) for q, x in v}
                    for r, s, v in saved.get("held", [])
                }
                ledger.snapshot = {"robots": body["robots"], "broadcast": body["broadcast"]}
                after = last.seq
        for rec in journal.records(after_seq=after):
            if rec.kind == "uplink":
                ledger.uplink(rec.robot_id, decode_frame(rec.body, Direction.UP).msg, rec.seq)
                ledger.records_read += 1
            elif rec.kind == "downlink":
                frame = decode_frame(rec.body, Direction.DOWN)
                ledger.downlink(rec.robot_id, stream_of(Direction.DOWN, frame.msg).name, rec.seq)
                ledger.records_read += 1
            elif rec.kind == "held":
                frame = decode_frame(rec.body, Direction.UP)
                key = (rec.robot_id, stream_of(Direction.UP, frame.msg).name)
                ledger.held.setdefault(key, {})[frame.seq] = rec.seq
                ledger.records_read += 1
            elif rec.kind == "link":
                body = rec.json()
                ledger.snapshot = {"robots": body["robots"], "broadcast": body["broadcast"]}
        for key, held in ledger.held.items():  # delivered since they were held
            for seq in [q for q in held if q <= ledger.up.get(key, 0)]:
                del held[seq]
        return ledger


def restore_link_state(
    radio: Any, journal: GcsJournal, ledger: LinkLedger | None = None
) -> dict[str, int]:
    """Give a fresh GCS endpoint the sequence state of the one that was killed, from the
    journal (through ``ledger``, :meth:`LinkLedger.from_journal` when None), so that robots
    notice nothing but a pause and nothing is delivered twice:

    * each robot's reliable uplink streams continue after the last message journaled (the
      GCS acknowledges only what it committed), and the stream decoders of pose nodes and
      grids get their reference back (the last two nodes, the last grid);
    * each reliable downlink stream continues after its last journaled message, and the last
      ``RESEND_TAIL`` go out again with their numbers (one the robot never got would stall
      its stream; those it had it drops);
    * latest-only downlink streams (acks, hazard updates, broadcasts) jump
      ``LATEST_SEQ_MARGIN`` past the last ``link`` snapshot.

    Writes the channels' private state (the link has no public API for it yet). Returns
    counts: robots, uplink streams restored, downlink messages resent, journal records
    decoded."""
    from protocol.messages import decode_frame

    if ledger is None:
        ledger = LinkLedger.from_journal(journal)

    def body(seq: int) -> bytes:
        rec = journal.record(seq)
        if rec is None:
            raise JournalError(f"{journal.path}: the link ledger names record {seq}: missing")
        return rec.body

    resent = 0
    decoded = ledger.records_read
    snapshot = ledger.snapshot
    for rid in sorted(ledger.robots()):
        ch = radio.channel(rid)
        for (r, stream), count in ledger.up.items():
            if r == rid:
                ch._recv[stream].delivered_through = count
        for (r, stream), held in ledger.held.items():
            if r == rid:  # back behind their gap: delivered when the robot fills it
                for rec_seq in held.values():
                    frame = decode_frame(body(rec_seq), Direction.UP)
                    ch._recv[stream].buffer[frame.seq] = frame.msg
                    decoded += 1
        for seq in ledger.node_seqs.get(rid, []):
            ch._coders_in["pose_node"].decode(decode_frame(body(seq), Direction.UP).msg)
            decoded += 1
        if rid in ledger.grid_seq:
            grid = decode_frame(body(ledger.grid_seq[rid]), Direction.UP).msg
            ch._coders_in["terrain_grid"].decode(grid)
            decoded += 1
        if snapshot is not None:
            for name, nxt in snapshot["robots"].get(str(rid), {}).items():
                ch._send[name].next_seq = int(nxt) + LATEST_SEQ_MARGIN
        for (r, stream), seqs in ledger.down_seqs.items():
            if r != rid or not seqs:
                continue
            tail = [decode_frame(body(seq), Direction.DOWN) for seq in seqs]
            decoded += len(tail)
            ch._send[stream].next_seq = tail[0].seq
            for frame in tail:
                radio.send(rid, frame.msg)
                resent += 1
    if snapshot is not None:
        bc = radio.broadcast_channel
        for name, nxt in snapshot["broadcast"].items():
            bc._send[name].next_seq = int(nxt) + LATEST_SEQ_MARGIN
    return {
        "robots": len(ledger.robots()),
        "uplink_streams": len(ledger.up),
        "downlink_resent": resent,
        "records_decoded": decoded,
    }


class GcsProcess:
    """A :class:`GroundStation` and its planners (:class:`MissionControl`) wired to the robots'
    radios over ``link``. ``mission``: the planners' configuration (default: sensor robots
    only, planning every 2 s; ``MissionControlConfig(enabled=False)``: estimation only).

    ``journal`` (:mod:`gcs.journal`): every uplink message before the station takes it, every
    step and the planners' decisions are appended, and committed once per spin. With a
    journal the radio's arrivals are held and processed on this loop's thread
    (:meth:`GcsEndpoint.hold_arrivals`), and when the link has no pump thread
    (``pump_period_s`` 0, as ``magic gcs`` opens it) this loop pumps it after the commit: the
    link acknowledges only what the journal holds. ``control``: a mission control rebuilt
    from a journal (``--resume``) instead of a new one; ``resumed``: what that rebuild fed,
    whose receive state the radio takes back (:func:`restore_link_state`)."""

    def __init__(
        self,
        link: Link,
        clock: Any,
        config: GroundStationConfig | None = None,
        *,
        step_period_s: float = 0.5,
        budget_s: float = 0.2,
        mission: MissionControlConfig | None = None,
        journal: GcsJournal | None = None,
        resumed: ResumedControl | None = None,
    ) -> None:
        self.link = link
        self.clock = clock
        if resumed is not None:
            self.control = resumed.control
            journal = resumed.journal
        else:
            self.control = MissionControl(GroundStation(config), mission)
        self.journal = journal
        self.station = self.control.station
        self.step_period_s = step_period_s
        self.budget_s = budget_s
        self.refused = 0
        self._inbox: queue.Queue[tuple[int, Any]] = queue.Queue()
        self.radio = link.gcs_endpoint(
            on_message=lambda rid, msg: self._inbox.put((rid, msg)), follow_radio=True
        )
        self._pump_here = journal is not None and link.config.pump_period_s <= 0
        self._processed_arrivals = 0
        self._last_snapshot_wall_s = -math.inf
        self._last_snapshot: dict[str, Any] | None = None
        self.link_state: dict[str, int] = {}
        self.ledger = LinkLedger()
        self.restore_link_s = 0.0  # wall seconds restore_link_state took (--resume)
        if journal is not None:
            self.radio.hold_arrivals()
        if resumed is not None:
            t0 = time.perf_counter()
            self.ledger = LinkLedger.from_journal(resumed.journal)
            self.link_state = restore_link_state(self.radio, resumed.journal, self.ledger)
            self.restore_link_s = time.perf_counter() - t0
        self._clock_sub = None
        if isinstance(clock, ManualClock):
            self._clock_sub = follow_sim_clock(link, clock)
        self._stop = threading.Event()
        self._last_step_s = -float("inf")
        self.operator: OperatorService | None = None  # operator (issue 15): set by main

    def spin_once(self, timeout_s: float = 0.05) -> int:
        """Hand the queued messages to the station; step it when due; with a journal, commit
        it, then let the link acknowledge (see the class docstring). Returns messages taken."""
        n = 0
        item: tuple[int, Any] | None = None
        if self.journal is not None:
            self.radio.wait_packets_in(self._processed_arrivals + 1, timeout_s)
            self._processed_arrivals = self.radio.packets_in
            self.radio.deliver_held()  # on_message, on this thread, into the inbox
            timeout_s = 0.0
        try:
            item = self._inbox.get(timeout=timeout_s) if timeout_s > 0 else self._inbox.get_nowait()
        except queue.Empty:
            item = None
        now = self.clock.now()
        while item is not None:
            if self.journal is not None:
                seq = self.journal.uplink(item[0], item[1], now)
                if seq is not None:
                    self.ledger.uplink(item[0], item[1], seq)
            self.control.handle(item[0], item[1], now_s=now)
            if self.operator is not None:  # operator (issue 15)
                self.operator.observe(item[0], item[1], now_s=now, station=self.station)
            n += 1
            try:
                item = self._inbox.get_nowait()
            except queue.Empty:
                item = None
        if now - self._last_step_s >= self.step_period_s:
            self._last_step_s = now
            out = step_control(self.control, self.journal, now_s=now, budget_s=self.budget_s)
            # the station hands every due robot the same HazardUpdate: one broadcast (paper
            # 4.1) when two or more robots are due, instead of one copy per robot
            copies = collections.Counter(id(m) for _, m in out if isinstance(m, HazardUpdate))
            broadcast: set[int] = set()
            for robot_id, msg in out:
                try:
                    if copies.get(id(msg), 0) > 1:
                        if id(msg) not in broadcast:
                            broadcast.add(id(msg))
                            self.radio.broadcast(msg)
                    else:
                        self.send(robot_id, msg)
                except LinkBackpressure:
                    self.refused += 1  # the next periodic update supersedes it
        if self.operator is not None:  # operator (issue 15): commands, status, views
            station: Any = self.station
            if self.journal is not None:  # the operator primitives (accept, rewind) journaled
                station = JournaledStation(self.station, self.journal)
                station._seen(now)
            self.operator.after_step(now_s=now, station=station, send=self.send)
        if self.journal is not None:
            wall = time.monotonic()
            if wall - self._last_snapshot_wall_s >= 1.0:
                self._last_snapshot_wall_s = wall
                snap = link_snapshot(self.radio)
                snap["ledger"] = self.ledger.to_json()
                if snap != self._last_snapshot:  # an idle GCS journals nothing
                    self._last_snapshot = snap
                    self.journal.event("link", now, snap)
            self.ledger.journal_held(self.radio, self.journal, now)
            self.journal.commit()
            if self._pump_here:
                self.link.pump()  # acknowledgements of what the journal now holds
        return n

    def send(self, robot_id: int, msg: Any) -> int:
        """Queue a downlink message; with a journal, a message on a reliable stream (tasks,
        parameters) is journaled with its sequence number, so a resumed GCS continues the
        robot's stream where it was (:func:`restore_link_state`)."""
        seq = self.radio.send(robot_id, msg)
        if self.journal is not None:
            spec = stream_of(Direction.DOWN, msg)
            if spec.reliability is Reliability.RELIABLE:
                rec = self.journal.downlink(robot_id, msg, seq, self.clock.now())
                if rec is not None:
                    self.ledger.downlink(robot_id, spec.name, rec)
        return seq

    def run(
        self,
        *,
        duration_s: float | None = None,
        progress: Callable[[str], None] | None = None,
        progress_period_s: float = 5.0,
    ) -> None:
        spin_until(
            self.spin_once,
            now=self.clock.now,
            stop=self._stop,
            duration_s=duration_s,
            progress=progress,
            status=self.status_line,
            progress_period_s=progress_period_s,
        )

    def status_line(self) -> str:
        s = self.station.stats
        g = self.station.graph
        return (
            f"gcs t={self.clock.now():7.1f}s robots {len(g.robots)} "
            f"linked {len(self.station.frames())} nodes {s.pose_nodes} grids {s.terrain_grids} "
            f"edges {len(g.edges())} rejected {s.rejected_total} "
            f"solver recoveries {s.solver_recoveries}/{s.solver_faults} "
            f"tasks {sum(self.control.tasks_sent.values())}"
            + (" explored" if self.control.explored else "")
            + self._waiting_hint()
        )

    def _waiting_hint(self) -> str:
        """What to check while nothing arrives: the simulator's clock never ticked (``--clock
        sim``), or no robot has been heard."""
        if self._clock_sub is not None and self.clock.now() == 0.0:
            return (
                " (no simulator clock yet: is --connect pointing at magic sim, with the same "
                "--mission?)"
            )
        if not self.station.graph.robots:
            return " (no robot heard yet: do the robots --connect to this GCS or its simulator?)"
        return ""

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        """Release the clock subscription (the link owns the radio endpoint)."""
        if self.operator is not None:  # operator (issue 15): last picture, flush the views
            self.operator.close(self.station)
        if self._clock_sub is not None:
            self._clock_sub.close()


#: zenoh link protocols whose address is ``host:port``.
_HOST_PORT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws")
_OTHER_PROTOCOLS = ("unixsock-stream", "unixpipe", "serial", "vsock")


def check_endpoint(endpoint: str) -> None:
    """Raise ``ValueError`` (one line) unless ``endpoint`` is ``<protocol>/<address>`` with a
    known zenoh protocol and, for tcp/udp/tls/quic/ws, a ``host:port`` address."""
    proto, sep, rest = endpoint.partition("/")
    address = rest.split("?", 1)[0].split("#", 1)[0]
    if not sep or not address:
        raise ValueError(
            f"endpoint {endpoint!r}: expected <protocol>/<address>, e.g. tcp/0.0.0.0:7448"
        )
    if proto in _OTHER_PROTOCOLS:
        return
    if proto not in _HOST_PORT_PROTOCOLS:
        known = ", ".join(_HOST_PORT_PROTOCOLS + _OTHER_PROTOCOLS)
        raise ValueError(f"endpoint {endpoint!r}: unknown protocol {proto!r} (known: {known})")
    host, colon, port = address.rpartition(":")
    if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"endpoint {endpoint!r}: expected {proto}/<host>:<port 0..65535>")


def summary_line(proc: GcsProcess, stopped_by: str | None) -> str:
    """One line: what ran (mission time, robots, nodes, grids, edges, rejections, faults)."""
    s = proc.station.stats
    g = proc.station.graph
    how = f"stopped by {stopped_by}" if stopped_by else "done"
    clocks = sum(s.clock_anomalies.values())
    return (
        f"magic gcs: {how} at t={proc.clock.now():.1f} s: robots {len(g.robots)} "
        f"(linked {len(proc.station.frames())}), nodes {s.pose_nodes}, grids {s.terrain_grids}, "
        f"edges {len(g.edges())}, rejected {s.rejected_total}, solver recoveries "
        f"{s.solver_recoveries}/{s.solver_faults} faults, clock anomalies {clocks}"
    )


def _robot_ids(text: str, option: str) -> tuple[int, ...]:
    """``"3,4"`` -> ``(3, 4)``; ValueError naming the option and the bad item."""
    ids = []
    for item in (t.strip() for t in text.split(",")):
        if not item:
            continue
        if not item.isdigit():
            raise ValueError(f"{option}: expected robot ids >= 0 separated by commas, got {item!r}")
        ids.append(int(item))
    return tuple(ids)


def _short(err: BaseException) -> str:
    """An exception's message on one line, without zenoh's source locations, <= 150 chars."""
    text = " ".join(str(err).split())
    text = text.split(" at /", 1)[0]
    return text if len(text) <= 150 else text[:147] + "..."


def _check_journal_arguments(args: argparse.Namespace) -> None:
    """``--out``/``--resume`` checked before anything opens (ValueError naming the problem)."""
    if args.resume is not None:
        if args.out is not None:
            raise ValueError("--resume RUN_DIR journals there: no --out with it")
        if args.config is not None:
            raise ValueError("--resume: the station's configuration is the journal's: no --config")
        if not (args.resume / "journal.sqlite").is_file():
            raise ValueError(f"--resume {args.resume}: no journal.sqlite there")
    elif args.out is not None:
        if (args.out / "journal.sqlite").exists():
            raise ValueError(
                f"--out {args.out}: holds a journal already (--resume {args.out} carries it on)"
            )
        if args.out.exists() and not args.out.is_dir():
            raise ValueError(f"--out {args.out}: not a directory")


def _open_journal(
    args: argparse.Namespace,
    config: GroundStationConfig | None,
    mission: MissionControlConfig,
) -> tuple[GcsJournal | None, ResumedControl | None]:
    """``--resume RUN_DIR``: the mission control rebuilt from its journal; else a new journal
    in ``--out`` (or the default run directory). ValueError/JournalError naming the problem."""
    if args.resume is not None:
        return None, resume_control(args.resume / "journal.sqlite", mission)
    out = args.out
    if out is None:
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        out = Path("runs") / f"{stamp}-gcs-{args.mission}"
    if (out / "journal.sqlite").exists():
        raise ValueError(f"--out {out}: holds a journal already (--resume {out} carries it on)")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--out {out}: cannot create it: {err.strerror}") from None
    station_config = config or GroundStationConfig()
    resolved = {
        "station": msgspec.to_builtins(station_config),
        "mission": msgspec.to_builtins(mission),
        "argv": sys.argv[1:],
    }
    (out / "gcs.json").write_text(json.dumps(resolved, indent=1, sort_keys=True) + "\n")
    meta = {"source": "magic gcs", "mission": str(args.mission)}
    return GcsJournal.create(out / "journal.sqlite", station_config, meta=meta), None


class _Stopped(BaseException):
    """SIGTERM before the station runs: unwinds like ^C (``KeyboardInterrupt``) does."""


def main(argv: list[str]) -> int:
    """``magic gcs``: returns the exit status (see the ``--help`` text)."""
    on_main = threading.current_thread() is threading.main_thread()
    previous_term = None
    if on_main:  # until the station runs, SIGTERM unwinds like ^C: no traceback, status 143

        def _raise(*_: object) -> None:
            raise _Stopped

        previous_term = signal.signal(signal.SIGTERM, _raise)
    try:
        return _main(argv)
    except KeyboardInterrupt:
        print("magic gcs: stopped by SIGINT before the station started", file=sys.stderr)
        return 130
    except _Stopped:
        print("magic gcs: stopped by SIGTERM before the station started", file=sys.stderr)
        return 143
    finally:
        if previous_term is not None:
            signal.signal(signal.SIGTERM, previous_term)


def _main(argv: list[str]) -> int:
    try:
        args = gcs_parser().parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    try:
        keys.gcs(args.mission, "state")
        for endpoint in args.connect + args.listen:
            check_endpoint(endpoint)
        for name in ("step_s", "budget_s", "progress_s", "plan_s"):
            v = getattr(args, name)
            if v is None:
                continue
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"--{name.replace('_', '-')}: expected seconds > 0, got {v}")
        if args.duration is not None and not (math.isfinite(args.duration) and args.duration >= 0):
            raise ValueError(f"--duration: expected mission seconds >= 0, got {args.duration}")
        config = load_config(args.config, GroundStationConfig) if args.config else None
        mission = (
            load_config(args.tasking_config, MissionControlConfig)
            if args.tasking_config
            else MissionControlConfig()
        )
        overrides: dict[str, Any] = {"enabled": mission.enabled and not args.no_tasking}
        if args.plan_s is not None:
            overrides["plan_period_s"] = args.plan_s
        if args.disruptors:
            overrides["disruptors"] = _robot_ids(args.disruptors, "--disruptors")
        mission = msgspec.structs.replace(mission, **overrides)
        radio = load_config(args.radio, RadioConfig)
        check_operator_arguments(args)  # operator (issue 15)
        _check_journal_arguments(args)
    except (ConfigError, ValueError) as err:
        print(f"magic gcs: {err}", file=sys.stderr)
        return 2
    clock: Any = ManualClock() if args.clock == "sim" else WallClock()
    if args.resume is not None and args.clock == "wall":
        # mission time goes on from the journal's last record, never backwards
        try:
            reader = GcsJournal.open(args.resume / "journal.sqlite")
        except JournalError as err:
            print(f"magic gcs: {err}", file=sys.stderr)
            return 2
        clock = ScaledClock(1.0, start_s=reader.last_time_s())
        reader.close()
    try:
        # no pump thread: the GCS loop pumps after each journal commit (ack what is kept)
        cfg = msgspec.structs.replace(link_config(radio, args), pump_period_s=0.0)
        link = Link(cfg, mission=args.mission, clock=clock)
    except Exception as err:  # zenoh refuses the endpoints (unresolvable, in use, ...)
        print(f"magic gcs: cannot open the zenoh link: {_short(err)}", file=sys.stderr)
        return 2
    try:
        journal, resumed = _open_journal(args, config, mission)
    except (ValueError, JournalError) as err:
        print(f"magic gcs: {err}", file=sys.stderr)
        link.close()
        return 2
    proc = GcsProcess(
        link,
        clock,
        config,
        step_period_s=args.step_s,
        budget_s=args.budget_s,
        mission=mission,
        journal=journal,
        resumed=resumed,
    )
    proc.operator = operator_service(args, link, getattr(proc, "control", None))  # operator (15)
    if proc.operator is not None and proc.operator.journal is None:
        proc.operator.journal = proc.journal  # operator commands into the GCS journal
    assert proc.journal is not None
    if resumed is not None and proc.operator is not None:
        # paused and operator-controlled robots, approvals and interactions as they were
        proc.operator.restore_operator(proc.journal)
    if resumed is not None:
        st = proc.link_state
        print(
            f"magic gcs: resumed from {proc.journal.path} in "
            f"{resumed.rebuild_s + proc.restore_link_s:.2f} s: "
            f"{resumed.summary.records.get('uplink', 0)} uplink messages after the checkpoint "
            f"at t={max(resumed.summary.checkpoint_time_s, 0.0):.1f} s, "
            f"{st['records_decoded']} records read for the radio, nodes "
            f"{proc.station.stats.pose_nodes}, edges {len(proc.station.graph.edges())}; "
            f"radio streams of {st['robots']} robots continued, {st['downlink_resent']} "
            "downlink messages resent",
            flush=True,
        )
    print(
        f"magic gcs: mission {args.mission!r}, journal {proc.journal.path}, waiting for robots",
        flush=True,
    )
    stopped_by: list[int] = []

    def on_signal(signum: int) -> None:
        stopped_by.append(signum)
        proc.stop()

    try:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, lambda *_: on_signal(signal.SIGTERM))
        with stop_on_interrupt(lambda: on_signal(signal.SIGINT)):
            proc.run(
                duration_s=args.duration,
                progress=lambda s: print(s, flush=True),
                progress_period_s=args.progress_s,
            )
    finally:
        proc.close()
        link.close()
        proc.journal.close()
    signame = signal.Signals(stopped_by[0]).name if stopped_by else None
    print(summary_line(proc, signame), flush=True)
    return 128 + stopped_by[0] if stopped_by else 0
