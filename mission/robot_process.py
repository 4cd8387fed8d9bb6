"""``magic robot --id N``: one robot node as its own process, on any host (DESIGN section 4).

The node's sensors come from a simulator server (``magic sim``) or a hardware process over
zenoh (:class:`~protocol.link.RemoteDriver`); its radio is a robot endpoint of the link, whose
rate follows the radio model's grants; mission time follows the simulator's clock ticks, so
rates and timeouts hold in mission time however fast the simulation runs.

``magic robot --id 0-7`` hosts several nodes in one process (a worker: :class:`LockstepGroup`
with ``--lockstep``, as ``magic run --robot-processes`` starts one per core). Endpoints come
from ``--connect``/``--listen``/``--mode`` or ``--link-config`` (a router across hosts:
``--mode client --connect tcp/<router>:7447``). A process refuses, in one line and status 2,
an id another live process hosts (:func:`~mission.lockstep_protocol.robot_host_key`), an
endpoint in use, and a ``--connect`` endpoint that does not answer within
``--connect-timeout``.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import queue
import signal
import socket
import sys
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import msgspec

from mission.config import ConfigError, load_config
from mission.lockstep_protocol import (
    GroupDone,
    GroupGo,
    RobotGo,
    StepDone,
    group_done_key,
    group_go_key,
    parse_robot_ids,
    robot_host_key,
    seed_streams,
)
from mission.robot_args import robot_parser
from protocol import keys
from protocol.clock import ManualClock
from protocol.link import Link
from protocol.messages import Direction
from protocol.process_cli import (
    follow_sim_clock,
    link_config,
    open_link,
    spin_until,
)
from protocol.radio import RadioConfig
from protocol.radio_channel import LinkBackpressure
from protocol.sensors import decode_sensor_frame, encode_command
from protocol.wire import ProtocolError
from robot.node import RobotNode, RobotNodeConfig

__all__ = [
    "WORKER_NAME",
    "LockstepGroup",
    "LockstepRobot",
    "NotServed",
    "RobotProcess",
    "main",
    "simulator_robots",
]

log = logging.getLogger(__name__)

#: Which process this is, for the ground side's reports: ``<host>:<pid>``.
WORKER_NAME = f"{socket.gethostname()}:{os.getpid()}"


class NotServed(RuntimeError):
    """The mission's simulator does not simulate this robot id."""


def simulator_robots(link: Link, timeout_s: float = 1.0) -> list[int]:
    """The robot ids a simulator of ``link``'s mission serves (its presence tokens); empty
    when no simulator is up (or the sensors come from hardware)."""
    ids = set()
    for key in link.present(keys.sim_radio(link.mission, None), timeout_s):
        try:
            ids.add(int(key.rsplit("/", 1)[1]))
        except ValueError:
            continue
    return sorted(ids)


def _check_served(link: Link, robot_id: int) -> None:
    """Raise :class:`NotServed` if a simulator is up and does not have this robot."""
    robots = simulator_robots(link)
    if robots and robot_id not in robots:
        raise NotServed(
            f"the simulator of mission {link.mission!r} has no robot {robot_id}; "
            f"its robots are {', '.join(map(str, robots))}"
        )


class RobotProcess:
    """A robot node wired to a remote driver and its radio over ``link``."""

    def __init__(
        self, link: Link, robot_id: int, clock: ManualClock, config: RobotNodeConfig
    ) -> None:
        self.link = link
        self.robot_id = robot_id
        self.clock = clock
        self.refused = 0
        self.node = RobotNode(
            robot_id, send=self._send, config=config, uplink_backlog=self._backlog
        )
        self.radio = link.robot_endpoint(
            robot_id, on_message=self.node.handle_downlink, follow_radio=True
        )
        self.driver = link.remote_driver(robot_id)
        self._clock_sub = follow_sim_clock(link, clock)
        self._stop = threading.Event()
        self.frames_seen = 0

    def _backlog(self) -> int:
        # the radio is made after the node (it delivers to the node): asked only once running
        return self.radio.backlog_bytes()

    def _send(self, msg: Any) -> object:
        try:
            return self.radio.send(msg)
        except LinkBackpressure:
            self.refused += 1  # not accepted; the node's next report supersedes it
            return None

    def spin_once(self, timeout_s: float = 0.1) -> int:
        """Process the frames that arrived; returns how many."""
        frames = self.driver.poll(timeout_s)
        self.frames_seen += len(frames)
        for command in self.node.process(frames):
            self.driver.send(command)
        return len(frames)

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
        s = self.node.stats
        pose = self.node.odometry.pose_in_odom
        up = self.link.meter.total_bytes(robot_id=self.robot_id, direction=Direction.UP)
        t = max(self.clock.now(), 1e-9)
        return (
            f"robot {self.robot_id} t={self.clock.now():7.1f}s {self.node.mode.name.lower():>13} "
            f"odom ({pose[0]:6.1f}, {pose[1]:6.1f}) sweeps {s.sweeps} nodes {s.pose_nodes} "
            f"uplink {up * 8 / t:6.0f} bps"
        )

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._clock_sub.close()
        self.driver.close()


class LockstepRobot:
    """A robot node of a lockstep team in a process of its own or with others
    (:class:`LockstepGroup` carries its steps), stepped so that the mission is the one the
    same team gives in one process (:mod:`mission.lockstep`, :mod:`mission.lockstep_protocol`).

    At each step (mission time ``t``, its :class:`RobotGo`): wait for the downlink packets the
    ground side counted; process that downlink at the previous step's time (as the in-process
    exchange does); apply the grant; (the clock moves to ``t``) hand the step's frames to the
    node and keep its commands for the group's answer; (the radio is pumped) answer with its
    :class:`StepDone` (totals of uplink packets and commands). ``link`` must have no pump
    thread and a ManualClock.
    """

    def __init__(
        self,
        link: Link,
        robot_id: int,
        clock: ManualClock,
        config: RobotNodeConfig,
        seed: int,
        *,
        timeout_s: float = 30.0,
    ) -> None:
        if link.config.pump_period_s != 0:
            raise ValueError("a lockstep robot needs a link without a pump thread")
        self.link = link
        self.robot_id = robot_id
        self.clock = clock
        self.timeout_s = timeout_s
        self.refused = 0
        self.rejected_frames = 0
        self.node = RobotNode(
            robot_id, send=self._send, config=config, seed=seed, uplink_backlog=self._backlog
        )
        self.radio = link.robot_endpoint(robot_id, on_message=self.node.handle_downlink)
        self.radio.hold_arrivals()
        self.commands_sent = 0
        self.steps = 0
        self.frames_seen = 0
        self._report_link = False
        self._encoder = msgspec.msgpack.Encoder()

    def _link_state(self) -> bytes:
        """The reliable uplink streams' state (:class:`StepDone`): what the link accepted and
        what is not acknowledged yet (the channels' private state: no public accessor)."""
        from protocol.messages import STREAMS, Reliability

        out = {}
        for name, st in self.radio.channel._send.items():
            spec = STREAMS[Direction.UP].get(name)
            if spec is not None and spec.reliability is Reliability.RELIABLE:
                out[name] = [st.next_seq - 1, sorted(st.unacked)]
        return self._encoder.encode(out)

    def _backlog(self) -> int:
        # the radio is made after the node (it delivers to the node): asked only once running
        return self.radio.backlog_bytes()

    def _send(self, msg: Any) -> object:
        try:
            return self.radio.send(msg)
        except LinkBackpressure:
            self.refused += 1
            return None

    def done(self, time_s: float) -> StepDone:
        """This robot's :class:`StepDone` of step ``time_s`` (0: its hello)."""
        stats = self.node.stats
        return StepDone(
            time_s,
            self.radio.packets_out,
            self.commands_sent,
            self.link.meter.total_bytes(robot_id=self.robot_id, direction=Direction.UP),
            stats.deadlocks,
            stats.stuck_recoveries,
            stats.plan_failures,
            WORKER_NAME,
            self.radio.packets_in,
            self._link_state() if self._report_link else b"",
            self.node.radio_relay,
        )

    def receive(self, go: RobotGo, report_link: bool = False) -> list[Any]:
        """The step's first half, before the clock moves to its time: wait for the downlink
        counted, process that downlink (at the previous step's time) and apply the grant;
        returns the step's frames (one that does not decode is counted and skipped)."""
        if not self.radio.wait_packets_in(go.downlink_packets, self.timeout_s):
            raise TimeoutError(f"robot {self.robot_id}: downlink not delivered")
        self.radio.deliver_held()  # at the previous step's time
        self.radio.set_grant(go.grant)
        self._report_link = report_link
        frames = []
        for data in go.frames:
            try:
                frames.append(decode_sensor_frame(data))
            except ProtocolError as err:
                self.rejected_frames += 1
                log.warning("robot %d: bad sensor frame: %s", self.robot_id, err)
        return frames

    def act(self, frames: list[Any]) -> list[bytes]:
        """The step's second half, at its time: the node processes the frames; returns its
        commands for the simulator, encoded (the radio is pumped by the caller, then
        :meth:`answer`)."""
        self.frames_seen += len(frames)
        commands = [encode_command(c) for c in self.node.process(frames)]
        self.commands_sent += len(commands)
        return commands

    def answer(self, t: float) -> StepDone:
        """Step ``t`` is done (after the link was pumped): its :class:`StepDone`."""
        self.steps += 1
        return self.done(t)

    def status_line(self) -> str:
        s = self.node.stats
        up = self.link.meter.total_bytes(robot_id=self.robot_id, direction=Direction.UP)
        return (
            f"robot {self.robot_id} t={self.clock.now():7.1f}s lockstep steps {self.steps} "
            f"sweeps {s.sweeps} nodes {s.pose_nodes} uplink bytes {up} "
            f"deadlocks {s.deadlocks} stuck recoveries {s.stuck_recoveries}"
        )

    def close(self) -> None:
        pass


class LockstepGroup:
    """The robot nodes of a lockstep team one process hosts (a worker of ``magic run``; the
    robot ids of ``magic robot --lockstep --id 0-7``, one or several), on one link and one
    clock, stepped by one :class:`GroupGo` a step and answering with one :class:`GroupDone`
    (:mod:`mission.lockstep_protocol`). Each step is what the robots' own processes would do,
    in three phases so that the shared clock holds the previous step's time while every
    robot's downlink is processed: every robot receives (downlink, grant, frames), the clock
    moves, every robot acts in id order, the link is pumped once, the group answers. Each
    robot's channels, draws and messages are its own, so the run is the one in one process,
    bit for bit. Until its first step it says hello (a :class:`GroupDone` of time 0) every
    ``hello_period_s`` wall seconds."""

    def __init__(
        self,
        link: Link,
        robot_ids: list[int],
        clock: ManualClock,
        config: RobotNodeConfig,
        seeds: Callable[[int], int],
        *,
        timeout_s: float = 30.0,
        hello_period_s: float = 0.5,
    ) -> None:
        if not robot_ids:
            raise ValueError("a lockstep group needs at least one robot id")
        self.link = link
        self.clock = clock
        self.timeout_s = timeout_s
        self.hello_period_s = hello_period_s
        self.robots = [
            LockstepRobot(link, rid, clock, config, seeds(rid), timeout_s=timeout_s)
            for rid in sorted(robot_ids)
        ]
        self.group = self.robots[0].robot_id
        self.steps = 0
        self._last_t = 0.0
        self._next_hello = 0.0
        self._go: queue.SimpleQueue[GroupGo] = queue.SimpleQueue()
        self._decoder = msgspec.msgpack.Decoder(GroupGo)
        self._encoder = msgspec.msgpack.Encoder()
        self._done_key = group_done_key(link.mission)
        self._sub = link.subscribe(group_go_key(link.mission, self.group), self._on_go)

    @property
    def frames_seen(self) -> int:
        return sum(r.frames_seen for r in self.robots)

    def _on_go(self, _key: str, payload: bytes) -> None:
        try:
            self._go.put(self._decoder.decode(payload))
        except (msgspec.DecodeError, msgspec.ValidationError) as err:
            log.warning("robots %s: bad lockstep message: %s", self.group, err)

    def _publish(self, time_s: float, done: list[StepDone], commands: list[list[bytes]]) -> None:
        msg = GroupDone(time_s, self.group, [r.robot_id for r in self.robots], done, commands)
        self.link.publish(self._done_key, self._encoder.encode(msg))

    def hello(self) -> None:
        """Tell the ground side these robots are up (repeated until the first step comes)."""
        self._publish(0.0, [r.done(0.0) for r in self.robots], [[] for _ in self.robots])
        self._next_hello = time.monotonic() + self.hello_period_s

    def take_go(self, timeout_s: float) -> GroupGo | None:
        """The next step's :class:`GroupGo`, None if none came within ``timeout_s`` (before
        the first step, the hello is repeated meanwhile) or it repeats a step answered."""
        try:
            go = self._go.get(timeout=timeout_s)
        except queue.Empty:
            if self.steps == 0 and time.monotonic() >= self._next_hello:
                self.hello()
            return None
        if go.time_s <= self._last_t and self.steps > 0:
            return None  # a repeated step: answered already
        ids = [g.robot_id for g in go.robots]
        if ids != [r.robot_id for r in self.robots]:  # not this group's: the ground names it
            log.warning(
                "robots %s: a step %.2f s for robots %s, not answered",
                _ids_text([r.robot_id for r in self.robots]),
                go.time_s,
                _ids_text(ids),
            )
            return None
        return go

    def step_once(self, timeout_s: float = 0.1) -> bool:
        """Answer the next step for every robot of the group (False if none came within
        ``timeout_s``)."""
        go = self.take_go(timeout_s)
        if go is None:
            return False
        frames = [r.receive(g, go.report_link) for r, g in zip(self.robots, go.robots, strict=True)]
        t = go.time_s
        if t > self.clock.now():
            self.clock.set(t)
        commands = [r.act(f) for r, f in zip(self.robots, frames, strict=True)]
        self.link.pump()
        self._publish(t, [r.answer(t) for r in self.robots], commands)
        self._last_t = t
        self.steps += 1
        return True

    def status_line(self) -> str:
        if len(self.robots) == 1:
            return self.robots[0].status_line()
        nodes = sum(r.node.stats.pose_nodes for r in self.robots)
        up = sum(
            self.link.meter.total_bytes(robot_id=r.robot_id, direction=Direction.UP)
            for r in self.robots
        )
        ids = ",".join(str(r.robot_id) for r in self.robots)
        return (
            f"robots {ids} t={self.clock.now():7.1f}s lockstep steps {self.steps} "
            f"nodes {nodes} uplink bytes {up}"
        )

    def close(self) -> None:
        self._sub.close()
        for r in self.robots:
            r.close()


def _ids_text(ids: list[int]) -> str:
    return ",".join(map(str, ids))


@contextlib.contextmanager
def _stop_on_signals(stop: Callable[[], None]) -> Iterator[list[int]]:
    """SIGINT and SIGTERM call ``stop`` within the block; yields the signals received (the
    same as ``sim.server.stop_on_signals``, kept here so that a robot host needs no
    simulator)."""
    got: list[int] = []
    previous: dict[int, Any] = {}

    def handler(signum: int, _frame: object) -> None:
        got.append(signum)
        stop()

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
    try:
        yield got
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


def _robot_ids(text: str) -> list[int]:
    text = text.strip()
    if text.startswith("-") and text[1:].isdigit():
        raise ValueError(f"--id must be >= 0, got {text}")
    return parse_robot_ids(text)


def _check_not_hosted(link: Link, robot_ids: list[int]) -> None:
    """ValueError naming a robot id that another live process already hosts."""
    for rid in robot_ids:
        if link.present(robot_host_key(link.mission, rid), 0.5):
            raise ValueError(
                f"robot {rid} of mission {link.mission!r} already runs in another process "
                "(a robot id given twice)"
            )


class _FreeGroup:
    """Several free-running robot nodes in one process (``magic robot --id 0,1`` without
    ``--lockstep``): each spun in turn."""

    def __init__(self, procs: list[RobotProcess]) -> None:
        self.procs = procs
        self.clock = procs[0].clock

    @property
    def frames_seen(self) -> int:
        return sum(p.frames_seen for p in self.procs)

    def spin_once(self) -> None:
        for i, p in enumerate(self.procs):
            p.spin_once(0.05 if i == 0 else 0.0)

    def status_line(self) -> str:
        return "\n".join(p.status_line() for p in self.procs)

    def close(self) -> None:
        for p in self.procs:
            p.close()


#: Set to a directory: the process runs under cProfile and writes ``robot_<pid>.prof`` there
#: when it ends (a worker of ``magic run`` or ``magic bench scale``: where its CPU goes).
PROFILE_DIR_ENV = "MAGIC_ROBOT_PROFILE_DIR"


def main(argv: list[str]) -> int:
    """``magic robot``: 0 at the end, 2 on bad arguments or configuration, an id the
    simulator does not have or that another process hosts, an endpoint in use or that does
    not answer (one line on stderr), 130 / 143 on SIGINT / SIGTERM. With
    ``$MAGIC_ROBOT_PROFILE_DIR`` set, profiled (:data:`PROFILE_DIR_ENV`)."""
    out_dir = os.environ.get(PROFILE_DIR_ENV)
    if not out_dir:
        return _main(argv)
    import cProfile

    profiler = cProfile.Profile()
    profiler.enable()
    try:
        return _main(argv)
    finally:
        profiler.disable()
        os.makedirs(out_dir, exist_ok=True)
        profiler.dump_stats(os.path.join(out_dir, f"robot_{os.getpid()}.prof"))


def _main(argv: list[str]) -> int:
    try:
        args = robot_parser().parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    try:
        robot_ids = _robot_ids(args.id)
        if args.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {args.seed}")
        if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
            raise ValueError(f"--duration must be > 0 mission-seconds, got {args.duration}")
        keys.sim_clock(args.mission)
        config = load_config(args.config, RobotNodeConfig) if args.config else RobotNodeConfig()
        radio = load_config(args.radio, RadioConfig)
        link_cfg = link_config(radio, args)
    except (ConfigError, ValueError) as err:
        print(f"magic robot: {err}", file=sys.stderr)
        return 2
    clock = ManualClock()
    seeds = seed_streams(args.seed)
    if args.lockstep:
        link_cfg = msgspec.structs.replace(link_cfg, pump_period_s=0.0)
    try:
        link = open_link(
            link_cfg,
            mission=args.mission,
            clock=clock,
            seed=seeds.robot_link if args.lockstep else 0,
            reach_timeout_s=args.connect_timeout,
        )
    except ValueError as err:
        print(f"magic robot: {err}", file=sys.stderr)
        return 2
    try:
        _check_not_hosted(link, robot_ids)
    except ValueError as err:
        link.close()
        print(f"magic robot: {err}", file=sys.stderr)
        return 2
    for rid in robot_ids:
        link.declare_presence(robot_host_key(link.mission, rid))
    proc: RobotProcess | LockstepGroup | _FreeGroup
    if args.lockstep:  # one robot or several: a group (one message each way a step)
        proc = LockstepGroup(link, robot_ids, clock, config, seeds.robot)
    elif len(robot_ids) == 1:
        proc = RobotProcess(link, robot_ids[0], clock, config)
    else:
        proc = _FreeGroup([RobotProcess(link, rid, clock, config) for rid in robot_ids])
    stop = threading.Event()
    next_check = [0.0]
    who = (
        f"robot {robot_ids[0]}"
        if len(robot_ids) == 1
        else f"robots {','.join(map(str, robot_ids))}"
    )

    def check_served() -> None:
        for rid in robot_ids:
            _check_served(link, rid)

    last_step = [time.monotonic()]
    ended = [False]

    def spin_once() -> None:
        # until frames flow, check now and then that a simulator that is up has these robots
        if proc.frames_seen == 0 and time.monotonic() >= next_check[0]:
            check_served()
            next_check[0] = time.monotonic() + 1.0
        if isinstance(proc, LockstepGroup):
            now = time.monotonic()
            if proc.step_once():
                last_step[0] = now
            elif proc.frames_seen and now - last_step[0] >= 2.0 and now >= next_check[0]:
                # no step for a while: a run whose simulator is gone has ended (a worker
                # started on another host is not closed by it)
                next_check[0] = now + 2.0
                if not simulator_robots(link, 0.5):
                    ended[0] = True
                    stop.set()
        else:
            proc.spin_once()

    try:
        with _stop_on_signals(stop.set) as stopped_by:
            check_served()
            if isinstance(proc, LockstepGroup):
                proc.hello()
            print(
                f"magic robot: {who} of mission {args.mission!r} waiting for sensor "
                "frames" + (" (lockstep)" if args.lockstep else ""),
                flush=True,
            )
            spin_until(
                spin_once,
                now=proc.clock.now,
                stop=stop,
                duration_s=args.duration,
                progress=lambda s: print(s, flush=True),
                status=proc.status_line,
                progress_period_s=args.progress_s,
            )
    except NotServed as err:
        print(f"magic robot: {err}", file=sys.stderr)
        return 2
    finally:
        proc.close()
        link.close()
    print(proc.status_line(), flush=True)
    if ended[0]:
        print(f"magic robot: the simulator of mission {args.mission!r} is gone: done", flush=True)
    if stopped_by:
        print(f"magic robot: stopped by {signal.Signals(stopped_by[0]).name}", flush=True)
        return 128 + stopped_by[0]
    return 0
