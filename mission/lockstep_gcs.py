"""The GCS in its own process in a lockstep team (``magic run --gcs-process``, issue 17).

The ground side of :class:`~mission.lockstep.TeamOverProcesses` can run in a process of its own
(this module's :func:`main`, started by :class:`RemoteGcs`), talking to the robots over the
real zenoh radio link as a ``magic gcs`` does and journaling to the run directory
(``RUN_DIR/journal.sqlite``). Each step the orchestrator (the simulator's process) and the GCS
process exchange three messages (:mod:`mission.lockstep_protocol`):

1. :class:`GcsGo`: the GCS process sets its mission clock and the robots' radio grants and
   takes its turn (:meth:`mission.assembly.GcsGround.turn`: the uplink of the previous step,
   a station step and a plan when due, the downlink queued), answering ``turn``;
2. once every robot answered the step, :class:`GcsEnd`: the GCS process waits for the uplink
   packets the robots counted, takes them (journaled *now*, under the next step's time, when
   its station will handle them), commits its journal and only then pumps its radio: the
   robots' acknowledgements cover only what the journal holds. It answers ``end`` with the
   downlink packets it has put on the air (the robots wait for them at the next step) and
   the figures the run's report shows.

A step is committed once, at its end, with the turn's records (its station step, plans,
downlink, checkpoint) and a mark of the step (the journal's meta ``lockstep_through_s``):
nothing of the step went on the air before, so a GCS killed anywhere in it leaves the journal
as the previous step ended, and a restart is the same run whenever in the turn the kill struck
(``tests/mission/test_lockstep_gcs.py``); one killed after the commit is not given that
step's turn again. With ``GcsSetup.operator`` the process serves ``magic console`` and the
views (:class:`gcs.operator.service.OperatorService`) as the in-process GCS does.

The order of everything the station sees, the radio's exchange and every random draw are
those of the in-process ground side: same seed, same run, bit for bit (``tests/mission``).

If the GCS process dies (``kill -9``), :class:`RemoteGcs` notices it while it waits, promotes a
*standby* process (started beside it, its libraries loaded, its zenoh session open, and
following the journal as it is committed: :class:`gcs.journal.JournalFollower`, so it takes
over with only the last records to apply) or starts a new one, which rebuilds the station from
the journal (``--resume``: the latest checkpoint and the records after it,
:func:`gcs.journal.resume_control`); either restores the radio's sequence state
(:func:`gcs.node.restore_link_state`) and the operators' decisions
(:meth:`gcs.operator.service.OperatorService.restore_operator`), and the step goes on: its turn
again, the robots' uplink of that step retransmitted by their links (what the dead process had
acknowledged is in the journal). The planners' assignments come back from the journal too, so
the robots keep their tasks; the rest of the planners' memory starts afresh, so from the
restart on the run is not quite the one without it, and it goes on (repeatably: same seed, same
kill step, same run).
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import queue
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec

from mission.lockstep_protocol import (
    GcsDone,
    GcsEnd,
    GcsGo,
    StepDone,
    gcs_done_key,
    gcs_end_key,
    gcs_go_key,
)
from protocol.cli_parser import CommandParser

__all__ = ["GcsSetup", "OperatorSetup", "RemoteGcs", "main"]

log = logging.getLogger(__name__)

#: The file in the run directory the orchestrator writes the GCS's setup to.
SETUP_FILE = "gcs_setup.msgpack"


class OperatorSetup(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The operator station the GCS process serves consoles and views with
    (:class:`gcs.operator.service.OperatorService`, as ``magic run`` attaches it in process):
    ``key_file``: the operators' HMAC key file (None: the default); ``views``: rerun sinks
    (``"save run.rrd"``, ``"spawn"``, ...)."""

    key_file: str | None = None
    views: list[str] = msgspec.field(default_factory=list)

    def __post_init__(self) -> None:
        # magic run's --operator-key is a Path: written to the setup file as its text (a
        # Path does not encode: `magic run --gcs-process --operator-key F` failed there)
        if self.key_file is not None and not isinstance(self.key_file, str):
            msgspec.structs.force_setattr(self, "key_file", os.fspath(self.key_file))


class GcsSetup(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """What the GCS process is started with (written by the orchestrator, msgpack: configs
    hold infinities). ``station`` and ``mission`` are msgpack of the
    :class:`~gcs.ground_station.GroundStationConfig` and
    :class:`~gcs.mission_control.MissionControlConfig`; ``hints``: the deployment plan's start
    hints ``(robot, map_from_odom, sigma_xy_m, sigma_yaw_rad)``; ``ground_link_seed``: the
    ground link's loss draws (:class:`~mission.lockstep.RunSeeds`)."""

    station: bytes
    mission: bytes
    hints: list[tuple[int, tuple[float, float, float], float, float]]
    robots: list[int]
    step_period_s: float
    radio_path: str
    ground_link_seed: int
    seed: int
    #: consoles and views (None: none): ``magic console`` then reaches this process's GCS
    operator: OperatorSetup | None = None


class _Figures:
    """What the run's report shows of the GCS, kept in the GCS process: each robot's
    progress row (the uplink the station took: task reports, nodes, grids, telemetry) and the
    tasks sent (planners' and operators'), the GCS's own figures and its planner events."""

    def __init__(self, robots: list[int]) -> None:
        self.rows: dict[int, list[Any]] = {r: ["-", "-", 0, 0] for r in robots}
        self.sent: dict[int, set[int]] = {r: set() for r in robots}
        self.ended: dict[int, dict[int, bool]] = {r: {} for r in robots}
        self.events_sent = 0

    def tap(self, robot_id: int, msg: Any, accepted: bool) -> None:
        from protocol.messages import PoseNode, TaskState, TaskStatus, Telemetry, TerrainGrid

        row = self.rows.get(robot_id)
        if row is None:
            return
        if isinstance(msg, TaskStatus):
            row[0] = msg.state.name.lower() + (f" ({msg.detail})" if msg.detail else "")
            if msg.state in (TaskState.SUCCEEDED, TaskState.FAILED, TaskState.REJECTED):
                ends = self.ended.setdefault(robot_id, {})
                ends.setdefault(int(msg.task_id), msg.state is TaskState.SUCCEEDED)
        elif isinstance(msg, PoseNode):
            row[2] += 1
        elif isinstance(msg, TerrainGrid):
            row[3] += 1
        elif isinstance(msg, Telemetry):
            row[1] = msg.mode.name.lower()

    def encode(self, control: Any, radio: Any) -> bytes:
        from gcs.graph.pose_graph import Provenance
        from protocol.messages import STREAMS, Direction, Reliability

        st = control.station
        progress = {}
        for rid, row in self.rows.items():
            ids = self.sent.get(rid, set())
            ends = [ok for tid, ok in self.ended.get(rid, {}).items() if tid in ids]
            ok = sum(ends)
            progress[rid] = [*row, len(ids), ok, len(ends) - ok]
        events = list(control.journal)
        new = [f"{e.time_s:.1f} s {e.kind}: {e.text}" for e in events[self.events_sent :]]
        self.events_sent = len(events)
        gcs = {
            "gcs_pose_nodes": float(st.stats.pose_nodes),
            "gcs_grids": float(st.stats.terrain_grids),
            "gcs_rejected": float(st.stats.rejected_total),
            "gcs_linked": float(len(st.frames())),
            "gcs_closures": float(len(st.graph.edges(Provenance.LOOP_AUTO))),
            "gcs_hazards": float(len(st.hazards)),
            "tasks_sent": float(sum(control.tasks_sent.values())),
            "tasking_events": float(len(control.journal)),
            "plans": float(control.allocator.stats.plans),
            "explored": float(control.explored),
        }
        # the reliable uplink streams' receive state: in order through, and held in the
        # reorder buffer behind a gap (the chaos bench's accounting)
        reliable = [
            name
            for name, spec in STREAMS[Direction.UP].items()
            if spec.reliability is Reliability.RELIABLE
        ]
        recv: dict[int, dict[str, Any]] = {}
        for rid in self.rows:
            ch = radio.channel(rid)
            recv[rid] = {name: list(ch.receive_state(name)) for name in reliable}
        return msgspec.msgpack.encode(
            {"progress": progress, "gcs": gcs, "events": new, "recv": recv}
        )


#: The journal's meta entry naming the last step whose exchange it holds whole.
THROUGH_META = "lockstep_through_s"


class _StepJournal:
    """The GCS process's journal as its ground side sees it: everything the journal does,
    but the ground side's commit at the end of its turn is held back, so that a step is
    committed once, at its end (:meth:`_Server.end`)."""

    def __init__(self, journal: Any) -> None:
        self._journal = journal

    def commit(self) -> bool:
        return False

    def __getattr__(self, name: str) -> Any:
        return getattr(self._journal, name)


class _Server:
    """The GCS process's side (module docstring)."""

    def __init__(
        self,
        args: argparse.Namespace,
        setup: GcsSetup,
        incarnation: int,
        link: Any,
        clock: Any,
        follower: Any = None,
    ) -> None:
        from gcs.ground_station import GroundStation, GroundStationConfig
        from gcs.journal import GcsJournal, JournaledStation, JournalError, resume_control
        from gcs.mission_control import MissionControl, MissionControlConfig
        from gcs.node import LinkLedger, restore_link_state
        from mission.assembly import GcsGround

        t0 = time.perf_counter()
        # what a resume spent where (its stderr: the chaos bench's restart time)
        phases: list[str] = []

        def phase(name: str, since: float) -> float:
            now = time.perf_counter()
            phases.append(f"{name} {now - since:.2f} s")
            return now

        self.incarnation = incarnation
        self.setup = setup
        self.clock = clock
        self.link = link
        self.figures = _Figures(setup.robots)
        journal_path = Path(args.run_dir) / "journal.sqlite"
        mission_cfg = msgspec.msgpack.decode(setup.mission, type=MissionControlConfig)
        if args.resume:
            resumed = None
            if follower is not None:  # a warm standby: it followed the journal while waiting
                try:
                    resumed = follower.take_over(mission_cfg)
                    how = "followed, last records"
                except (JournalError, sqlite3.Error) as err:
                    print(f"gcs process: {err}; rebuilding instead", file=sys.stderr, flush=True)
            if resumed is None:
                resumed = resume_control(journal_path, mission_cfg)
                how = "rebuilt"
            control, journal = resumed.control, resumed.journal
            t = phase(f"journal ({how} {resumed.summary.records})", t0)
        else:
            station_cfg = msgspec.msgpack.decode(setup.station, type=GroundStationConfig)
            station = GroundStation(station_cfg)
            journal = GcsJournal.create(
                journal_path,
                station.config,
                meta={"source": "magic run --gcs-process", "seed": str(setup.seed)},
            )
            hinted = JournaledStation(station, journal)
            for rid, mfo, sxy, syaw in setup.hints:
                hinted.add_start_hint(rid, map_from_odom=mfo, sigma_xy_m=sxy, sigma_yaw_rad=syaw)
            control = MissionControl(station, mission_cfg)
        self.journal = journal
        #: the last step whose exchange the journal holds whole (a resumed GCS does not take
        #: that step's turn again: :meth:`turn`)
        self.through_s = -math.inf
        if args.resume:
            try:
                self.through_s = float(journal.meta().get(THROUGH_META, "-inf"))
            except ValueError:
                log.warning("gcs process: journal meta %s unreadable: ignored", THROUGH_META)
        self.ground = GcsGround(
            control,
            lockstep=True,
            step_period_s=setup.step_period_s,
            taps=[self.figures.tap],
            # one commit per step, at its end (the ground side's own commit is held back)
            journal=_StepJournal(journal),  # type: ignore[arg-type]
            journal_uplink=False,  # journaled on arrival, before the acknowledgement
        )
        if setup.operator is not None:  # consoles and views, as in process (issue 15)
            from gcs.operator.service import OperatorService

            self.ground.attach_operator(
                OperatorService(
                    link,
                    key_file=setup.operator.key_file,
                    views=list(setup.operator.views) or None,
                    control=control,
                )
            )
            if args.resume:
                # the killed GCS's operator decisions (paused robots, operator tasks,
                # approvals, interactions), before the planners' first plan
                self.ground.operator.restore_operator(
                    journal, heard=follower.heard if how.startswith("followed") else None
                )
        if args.resume:
            t = phase("control and operator", t)
        self._next_t = 0.0
        self.ledger = LinkLedger()
        self.radio = self.link.gcs_endpoint(on_message=self._arrived)
        self.radio.hold_arrivals()
        if args.resume:
            t = phase("radio endpoint", t)
            self.ledger = LinkLedger.from_journal(journal)
            restore_link_state(self.radio, journal, self.ledger)
            phase("link state", t)
        self.rebuild_s = time.perf_counter() - t0
        print(
            f"gcs process {incarnation}: {'resumed' if args.resume else 'started'} in "
            f"{self.rebuild_s:.2f} s" + (f" ({', '.join(phases)})" if phases else ""),
            file=sys.stderr,
            flush=True,
        )
        self._last_link_s = -1.0
        self._inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self._encoder = msgspec.msgpack.Encoder()
        self._go = msgspec.msgpack.Decoder(GcsGo)
        self._end = msgspec.msgpack.Decoder(GcsEnd)
        mission = args.mission
        self.link.subscribe(gcs_go_key(mission), lambda _k, p: self._inbox.put(("go", p)))
        self.link.subscribe(gcs_end_key(mission), lambda _k, p: self._inbox.put(("end", p)))
        self._done_key = gcs_done_key(mission)

    def _arrived(self, robot_id: int, msg: Any) -> None:
        """The radio's delivery at the end of a step (on this thread): journaled under the
        next step's time, when the station takes it (the in-process order), then queued."""
        seq = self.journal.uplink(robot_id, msg, self._next_t)
        if seq is not None:
            self.ledger.uplink(robot_id, msg, seq)
        self.ground.on_message(robot_id, msg)

    def wait_for_robots(self, timeout_s: float) -> None:
        t0 = time.perf_counter()
        deadline = time.monotonic() + timeout_s
        for rid in self.setup.robots:
            if not self.radio.wait_for_robot(rid, max(0.1, deadline - time.monotonic())):
                raise TimeoutError(f"gcs process: robot {rid} never came up")
        print(
            f"gcs process {self.incarnation}: robots' downlink matched in "
            f"{time.perf_counter() - t0:.2f} s",
            file=sys.stderr,
            flush=True,
        )

    def answer(self, time_s: float, phase: str, figures: bytes = b"") -> None:
        done = GcsDone(
            time_s,
            phase,
            self.incarnation,
            dict(self.radio.packets_out_by_robot),
            self.radio.packets_in,
            figures,
            os.getpid(),
            self.rebuild_s,
        )
        self.link.publish(self._done_key, self._encoder.encode(done))

    def turn(self, go: GcsGo) -> None:
        from protocol.messages import Direction, HazardUpdate, Reliability, stream_of

        self.clock.set(go.time_s)
        for rid, grant in go.grants.items():
            self.radio.set_grant(rid, grant)
        if go.time_s <= self.through_s:
            # the GCS that died finished this step's exchange (journaled, committed) before
            # it could answer: its turn is not taken twice (its downlink is resent from the
            # journal, :func:`gcs.node.restore_link_state`)
            self.answer(go.time_s, "turn")
            return
        out = self.ground.turn(go.time_s)
        # as Assembly._ground_turn: the station's shared HazardUpdate as one broadcast
        shared: dict[int, int] = {}
        for _, msg in out:
            if isinstance(msg, HazardUpdate):
                shared[id(msg)] = shared.get(id(msg), 0) + 1
        sent: set[int] = set()
        for rid, msg in out:
            if shared.get(id(msg), 0) > 1:
                if id(msg) not in sent:
                    sent.add(id(msg))
                    self.radio.broadcast(msg)
                continue
            seq = self.radio.send(rid, msg)
            spec = stream_of(Direction.DOWN, msg)
            if spec.reliability is Reliability.RELIABLE:  # a resumed GCS continues the stream
                rec = self.journal.downlink(rid, msg, seq, go.time_s)
                if rec is not None:
                    self.ledger.downlink(rid, spec.name, rec)
            task_id = getattr(msg, "task_id", None)
            if isinstance(task_id, int) and type(msg).__name__ not in ("PauseTask", "ResumeTask"):
                self.figures.sent.setdefault(rid, set()).add(task_id)
        # not committed here: the turn's records (its step, decisions, downlink, a checkpoint)
        # are committed with the step's end, before anything of the step goes on the air. A
        # GCS killed before that leaves the journal as the previous step ended, whenever in
        # the turn the kill struck, so a resume is repeatable (it takes this turn again)
        self.answer(go.time_s, "turn")

    def end(self, end: GcsEnd) -> None:
        from gcs.node import link_snapshot

        self.radio.wait_packets_in(end.uplink_packets, end.wait_s)
        self._next_t = end.next_time_s
        self.radio.deliver_held()  # -> _arrived: journaled
        if end.time_s - self._last_link_s >= 1.0:  # the radio's state, each mission second
            self._last_link_s = end.time_s
            snap = link_snapshot(self.radio)
            snap["ledger"] = self.ledger.to_json()
            self.journal.event("link", end.time_s, snap)
        self.ledger.journal_held(self.radio, self.journal, end.time_s)
        self.through_s = max(self.through_s, end.time_s)
        self.journal.set_meta(THROUGH_META, repr(self.through_s))
        # the step's one commit (its turn's records too), before the acknowledgements and
        # the downlink the pump sends
        self.journal.commit()
        self.link.pump()
        self.answer(end.time_s, "end", self.figures.encode(self.ground.control, self.radio))

    def serve(self, stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                kind, payload = self._inbox.get(timeout=0.2)
            except queue.Empty:
                continue
            try:
                if kind == "go":
                    self.turn(self._go.decode(payload))
                else:
                    self.end(self._end.decode(payload))
            except (msgspec.DecodeError, msgspec.ValidationError) as err:
                log.warning("gcs process: bad lockstep message: %s", err)

    def close(self) -> None:
        if self.ground.operator is not None:
            self.ground.operator.close(self.ground.station)  # last picture, views flushed
        self.link.close()
        self.journal.close()


def _warm_up(setup: GcsSetup) -> float:
    """What a resume runs for the first time in a process, run once by a standby while it
    waits: a small synthetic mission through a station of the run's configuration (nodes,
    grids, steps with loop closing, a rasterization) saved and loaded as a checkpoint is.
    numba compiles the rasterizer's and the loop closer's kernels on first use (3.8 of a
    4.8 s resume, measured); afterwards they are ready. Returns the wall seconds it took."""
    import math as _math

    import numpy as np

    from compression import encode_grid, origin_cells_of
    from gcs.ground_station import GroundStation, GroundStationConfig
    from gcs.journal import load_station, save_station
    from gcs.loops.synthetic_scenes import random_world, scan_grid, scan_points
    from protocol.messages import PoseNode, TerrainGrid
    from protocol.se2 import relative

    t0 = time.perf_counter()
    config = msgspec.msgpack.decode(setup.station, type=GroundStationConfig)
    station = GroundStation(config)
    rid = config.graph.map_robot_id
    rng = np.random.default_rng(0)
    world = random_world(rng, size_m=30.0)
    poses = [(x, 0.5, 0.0) for x in np.arange(-4.0, 4.01, 1.0)]
    poses += [(x, -0.5, _math.pi) for x in np.arange(4.0, -4.01, -1.0)]
    cov = (1e-4, 0.0, 0.0, 1e-4, 0.0, 1e-4)
    for i, pose in enumerate(poses):
        delta = (0.0, 0.0, 0.0) if i == 0 else tuple(relative(poses[i - 1], pose))
        station.handle(rid, PoseNode(i, float(i), pose, delta, cov), now_s=float(i))  # type: ignore[arg-type]
        grid, origin = scan_grid(scan_points(world, np.asarray(pose), rng=rng))
        data = encode_grid(grid, origin_cells=origin_cells_of(origin, 0.1))
        station.handle(rid, TerrainGrid(i, 0.1, data), now_s=float(i))
        station.step(now_s=float(i), budget_s=_math.inf)
    again = load_station(save_station(station))
    again.step(now_s=float(len(poses)), budget_s=_math.inf)
    again.rasterize()
    return time.perf_counter() - t0


#: Wall seconds between a standby's reads of the journal it follows.
FOLLOW_PERIOD_S = 0.25


def _follow_until_told(journal_path: Path) -> tuple[str, Any]:
    """A standby's wait: the line the orchestrator writes on stdin (the incarnation to take
    over as; empty: the run ended), and meanwhile the journal followed
    (:class:`gcs.journal.JournalFollower`: its station kept as the running GCS's, every
    ``FOLLOW_PERIOD_S``), so that taking over applies only the last records instead of
    everything since the latest checkpoint. Returns the line and the follower (None when it
    could not follow: the resume then rebuilds from the journal, slower, not wrong)."""
    from gcs.journal import JournalError, JournalFollower

    lines: queue.SimpleQueue[str] = queue.SimpleQueue()
    threading.Thread(target=lambda: lines.put(sys.stdin.readline()), daemon=True).start()
    follower = None
    try:
        t0 = time.perf_counter()
        follower = JournalFollower(journal_path)
        print(
            f"gcs standby: following {journal_path} from record {follower.seq} (loaded in "
            f"{time.perf_counter() - t0:.2f} s)",
            file=sys.stderr,
            flush=True,
        )
    except (JournalError, sqlite3.Error) as err:
        print(f"gcs standby: not following the journal: {err}", file=sys.stderr, flush=True)
    while True:
        try:
            return lines.get(timeout=FOLLOW_PERIOD_S), follower
        except queue.Empty:
            pass
        if follower is None:
            continue
        try:
            follower.catch_up()
        except (JournalError, sqlite3.Error) as err:
            print(f"gcs standby: stopped following: {err}", file=sys.stderr, flush=True)
            follower.close()
            follower = None


def _open_link(args: argparse.Namespace, setup: GcsSetup) -> tuple[Any, Any]:
    """The GCS's zenoh link (a standby opens it before it is needed: a session and its
    routes take a while) on a mission clock of its own."""
    from protocol.clock import ManualClock
    from protocol.config import load_config
    from protocol.link import Link, LinkConfig
    from protocol.radio import RadioConfig

    radio = load_config(setup.radio_path, RadioConfig)
    cfg = LinkConfig(
        connect=tuple(args.connect),
        listen=tuple(args.listen),
        mode=args.mode,
        radio=radio,
        pump_period_s=0.0,
    )
    clock = ManualClock()
    return Link(cfg, mission=args.mission, clock=clock, seed=setup.ground_link_seed), clock


def _parser() -> argparse.ArgumentParser:
    p = CommandParser(
        prog="python -m mission.lockstep_gcs",
        description="The GCS process of a lockstep run (started by magic run --gcs-process).",
    )
    p.add_argument("--run-dir", required=True, help="the run directory (journal.sqlite, setup)")
    p.add_argument("--mission", required=True, help="the zenoh mission name")
    p.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect to")
    p.add_argument("--listen", action="append", default=[], help="zenoh endpoint to listen on")
    p.add_argument("--mode", choices=("peer", "client"), default="peer", help="zenoh mode")
    p.add_argument("--resume", action="store_true", help="rebuild from the run's journal")
    p.add_argument("--incarnation", type=int, default=1, help="which start of the GCS this is")
    p.add_argument(
        "--standby",
        action="store_true",
        help="load the libraries, then wait for a line on stdin before resuming (a warm spare)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    """The GCS process: 0 when told to stop (SIGTERM), 2 on a setup it cannot use."""
    args = _parser().parse_args(argv)
    setup_path = Path(args.run_dir) / SETUP_FILE
    try:
        setup = msgspec.msgpack.decode(setup_path.read_bytes(), type=GcsSetup)
    except (OSError, msgspec.DecodeError, msgspec.ValidationError) as err:
        print(f"gcs process: {setup_path}: {err}", file=sys.stderr)
        return 2
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    incarnation = args.incarnation
    link, clock = _open_link(args, setup)
    if args.standby:
        # the libraries a resume needs, loaded while the GCS it stands in for still runs
        import gcs.journal  # noqa: F401
        import gcs.mission_control  # noqa: F401
        import gcs.node  # noqa: F401
        import mission.assembly  # noqa: F401
        import protocol.link  # noqa: F401

        try:
            warm_s = _warm_up(setup)
            print(f"gcs standby: warmed up in {warm_s:.2f} s", file=sys.stderr, flush=True)
        except Exception as err:  # noqa: BLE001 - a cold resume is slower, not wrong
            print(f"gcs standby: no warm-up ({type(err).__name__}: {err})", file=sys.stderr)
        line, follower = _follow_until_told(Path(args.run_dir) / "journal.sqlite")
        if not line.strip():
            if follower is not None:
                follower.close()
            link.close()
            return 0  # the run ended: never needed
        followed = (
            f"followed to record {follower.seq}, {follower.catch_up_s:.1f} s catching up, "
            if follower is not None
            else ""
        )
        print(
            f"gcs standby: told at {time.strftime('%H:%M:%S')} ({followed}process CPU "
            f"{time.process_time():.1f} s)",
            file=sys.stderr,
            flush=True,
        )
        incarnation = int(line)
        args.resume = True
    else:
        follower = None
    try:
        server = _Server(args, setup, incarnation, link, clock, follower)
    except BaseException:
        link.close()
        raise
    try:
        server.wait_for_robots(60.0)
        server.answer(0.0, "hello")
        server.serve(stop)
    finally:
        server.close()
    return 0


class RemoteGcs:
    """The orchestrator's side of the GCS process (module docstring): starts it (and a
    standby), exchanges each step's messages with it and restarts it when it dies.

    ``robot_done()``: the robots' latest :class:`StepDone` by id (from the team), whose
    counts a restarted GCS process's are offset by. ``restarts`` and ``restart_s`` (wall
    seconds from noticing the death to a serving GCS, each) say what happened."""

    def __init__(
        self,
        link: Any,
        mission: str,
        run_dir: Path,
        setup: GcsSetup,
        *,
        link_args: list[str],
        robot_done: Callable[[], dict[int, StepDone]],
        timeout_s: float = 60.0,
        standby: bool = True,
    ) -> None:
        self.link = link
        self.mission = mission
        self.run_dir = Path(run_dir)
        self.setup = setup
        self.link_args = link_args
        self.robot_done = robot_done
        self.timeout_s = timeout_s
        self.use_standby = standby
        self.incarnation = 0
        self.proc: subprocess.Popen[bytes] | None = None
        self.standby: subprocess.Popen[bytes] | None = None
        self.restarts = 0
        self.restart_s: list[float] = []
        self.rebuild_s: list[float] = []
        self.figures: dict[str, Any] = {}
        self.events: list[str] = []
        #: how many planner events the GCS keeps (its MissionControl's journal_size)
        self.setup_journal_size = _journal_size(setup)
        self._base_down: dict[int, int] = {}
        self._base_up = 0
        self._grace = False  # after a restart: uplink published before it may be gone
        self._last: dict[str, GcsDone] = {}
        self._cond = threading.Condition()
        self._dec = msgspec.msgpack.Decoder(GcsDone)
        self._enc = msgspec.msgpack.Encoder()
        self._go: GcsGo | None = None
        self._killed_at = math.inf
        (self.run_dir / SETUP_FILE).write_bytes(msgspec.msgpack.encode(setup))
        self._sub = link.subscribe(gcs_done_key(mission), self._on_done)
        self._stderr: list[Any] = []
        self._start(resume=False)

    # ---- processes ------------------------------------------------------------------------

    def _spawn(self, *extra: str) -> subprocess.Popen[bytes]:
        argv = [sys.executable, "-m", "mission.lockstep_gcs", "--run-dir", str(self.run_dir)]
        argv += ["--mission", self.mission, *self.link_args, *extra]
        err = open(self.run_dir / f"gcs{len(self._stderr)}.err", "wb")  # noqa: SIM115
        self._stderr.append(err)
        return subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=err)

    def _start(self, *, resume: bool) -> None:
        self.incarnation += 1
        with self._cond:
            self._last.clear()  # the dead one's counts and answers
        if resume and self.standby is not None and self.standby.poll() is None:
            self.proc, self.standby = self.standby, None
            assert self.proc.stdin is not None
            self.proc.stdin.write(f"{self.incarnation}\n".encode())
            self.proc.stdin.flush()
        else:
            extra = ["--incarnation", str(self.incarnation)] + (["--resume"] if resume else [])
            self.proc = self._spawn(*extra)
        hello = self._wait("hello", 0.0, self.timeout_s, restart=False)
        if resume:
            self.rebuild_s.append(hello.rebuild_s)
        if self.use_standby and (self.standby is None or self.standby.poll() is not None):
            self.standby = self._spawn("--standby")

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def kill(self) -> None:
        """``kill -9`` the GCS process (the chaos bench); the next wait notices it, and the
        restart's time counts from here."""
        assert self.proc is not None
        self._killed_at = time.perf_counter()
        os.kill(self.proc.pid, signal.SIGKILL)

    def _restart(self) -> None:
        t0 = min(time.perf_counter(), self._killed_at)
        self._killed_at = math.inf
        assert self.proc is not None
        self.proc.wait()
        log.warning("the GCS process (pid %d) died: restarting it from its journal", self.pid)
        # its counts are gone with it: the new one counts from where the robots are
        done = self.robot_done()
        self._base_down = {rid: d.downlink_packets_in for rid, d in done.items()}
        self._base_up = sum(d.uplink_packets for d in done.values())
        self._start(resume=True)
        self._grace = True
        self.restarts += 1
        self.restart_s.append(time.perf_counter() - t0)

    # ---- messages -------------------------------------------------------------------------

    def _on_done(self, _key: str, payload: bytes) -> None:
        done = self._dec.decode(payload)
        with self._cond:
            if done.incarnation == self.incarnation:
                self._last[done.phase] = done
                self._cond.notify_all()

    def _wait(self, phase: str, time_s: float, timeout_s: float, *, restart: bool) -> GcsDone:
        """The GCS's answer ``phase`` for ``time_s``; a dead GCS restarted (``restart``,
        then None is returned: the caller repeats its request) or reported."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while True:
                got = self._last.get(phase)
                if got is not None and got.time_s >= time_s and got.incarnation == self.incarnation:
                    return got
                assert self.proc is not None
                status = self.proc.poll()
                if status is not None:
                    if not restart:
                        raise RuntimeError(
                            f"the GCS process exited with status {status} before it served "
                            f"(see {self.run_dir}/gcs*.err)"
                        )
                    raise _Died
                if time.monotonic() > deadline:
                    raise TimeoutError(f"the GCS process did not answer {phase} of {time_s:.2f} s")
                self._cond.wait(0.2)

    def downlink_packets(self, robot_id: int) -> int:
        """Radio packets robot ``robot_id`` is to have received from the GCS so far."""
        last = self._last.get("end") or self._last.get("hello")
        mine = 0 if last is None else last.downlink_packets.get(robot_id, 0)
        return self._base_down.get(robot_id, 0) + mine

    def go(self, time_s: float, grants: dict[int, Any]) -> None:
        """The ground side's turn at ``time_s`` (answered later: :meth:`end`)."""
        self._go = GcsGo(time_s, grants)
        self.link.publish(gcs_go_key(self.mission), self._enc.encode(self._go))

    def end(self, time_s: float, done: dict[int, StepDone], next_time_s: float) -> None:
        """The step's end: the robots' uplink counted in ``done`` taken and acknowledged by
        the GCS process (restarted first if it died; the turn then repeated)."""
        assert self._go is not None
        while True:
            try:
                self._wait("turn", time_s, self.timeout_s, restart=True)
                uplink = sum(d.uplink_packets for d in done.values()) - self._base_up
                wait_s = 2.0 if self._grace else self.timeout_s
                end = GcsEnd(time_s, uplink, next_time_s, wait_s)
                self.link.publish(gcs_end_key(self.mission), self._enc.encode(end))
                got = self._wait("end", time_s, self.timeout_s + wait_s, restart=True)
                break
            except _Died:
                self._restart()
                self.link.publish(gcs_go_key(self.mission), self._enc.encode(self._go))
        if got.packets_in < uplink:
            if not self._grace:
                raise TimeoutError(f"uplink packets not delivered to the GCS at {time_s:.2f} s")
            self._base_up += uplink - got.packets_in  # published before it listened: resent
        self._grace = False
        figures = msgspec.msgpack.decode(got.figures) if got.figures else {}
        if figures:
            self.figures = figures
            self.events.extend(figures.get("events", []))

    def close(self) -> None:
        """End the GCS process (SIGTERM: it closes its journal) and the standby (SIGKILL: it
        holds nothing, and may still be warming up)."""
        if self.standby is not None and self.standby.poll() is None:
            self.standby.kill()
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
        for p in (self.standby, self.proc):
            if p is None:
                continue
            try:
                p.wait(timeout=20.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for f in self._stderr:
            f.close()
        self._sub.close()


def _journal_size(setup: GcsSetup) -> int:
    from gcs.mission_control import MissionControlConfig

    return int(msgspec.msgpack.decode(setup.mission, type=MissionControlConfig).journal_size)


class _Died(Exception):
    """The GCS process ended while the orchestrator waited for it."""


if __name__ == "__main__":
    sys.exit(main())
