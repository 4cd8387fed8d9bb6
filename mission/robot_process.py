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
    StepDone,
    StepGo,
    parse_robot_ids,
    robot_host_key,
    seed_streams,
    step_done_key,
    step_go_key,
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
from protocol.sensors import ClockTick
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
        self.node = RobotNode(robot_id, send=self._send, config=config)
        self.radio = link.robot_endpoint(
            robot_id, on_message=self.node.handle_downlink, follow_radio=True
        )
        self.driver = link.remote_driver(robot_id)
        self._clock_sub = follow_sim_clock(link, clock)
        self._stop = threading.Event()
        self.frames_seen = 0

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
    """A robot node in its own process, stepped by the ground side's :class:`StepGo` so that
    the mission is the one the same team gives in one process (:mod:`mission.lockstep`,
    :mod:`mission.lockstep_protocol`).

    At each step (mission time ``t``): wait for the step's frames (up to the simulator's
    end-of-step ``ClockTick`` on this robot's sensor key) and for the downlink packets the
    ground side counted; process that downlink at the previous step's time (as the in-process
    exchange does); apply the grant; move the clock to ``t``; hand the frames to the node;
    send its commands; pump the radio by hand; answer with :class:`StepDone` (totals of
    uplink packets and commands). ``link`` must have no pump thread and a ManualClock.
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
        self.node = RobotNode(robot_id, send=self._send, config=config, seed=seed)
        self.radio = link.robot_endpoint(robot_id, on_message=self.node.handle_downlink)
        self.radio.hold_arrivals()
        self.driver = link.remote_driver(robot_id)
        self._go: queue.SimpleQueue[StepGo] = queue.SimpleQueue()
        self._go_decoder = msgspec.msgpack.Decoder(StepGo)
        self._encoder = msgspec.msgpack.Encoder()
        self._sub = link.subscribe(step_go_key(link.mission, robot_id), self._on_go)
        self._done_key = step_done_key(link.mission, robot_id)
        self._frames: list[Any] = []
        self._last_t = 0.0
        self.commands_sent = 0
        self.steps = 0
        self.frames_seen = 0
        self._next_hello = 0.0
        self._report_link = False

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

    def _send(self, msg: Any) -> object:
        try:
            return self.radio.send(msg)
        except LinkBackpressure:
            self.refused += 1
            return None

    def _on_go(self, _key: str, payload: bytes) -> None:
        try:
            self._go.put(self._go_decoder.decode(payload))
        except (msgspec.DecodeError, msgspec.ValidationError) as err:
            log.warning("robot %d: bad lockstep message: %s", self.robot_id, err)

    def _done(self, time_s: float) -> None:
        stats = self.node.stats
        done = StepDone(
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
        self.link.publish(self._done_key, self._encoder.encode(done))

    def hello(self) -> None:
        """Tell the ground side this robot is up (repeated until the first step comes)."""
        self._done(0.0)
        self._next_hello = time.monotonic() + 0.5

    def _frames_until(self, t: float) -> list[Any]:
        deadline = time.monotonic() + self.timeout_s
        while True:
            for i, f in enumerate(self._frames):
                if isinstance(f, ClockTick) and f.time_s >= t:
                    out, self._frames = self._frames[:i], self._frames[i + 1 :]
                    return [f for f in out if not isinstance(f, ClockTick)]
            if time.monotonic() > deadline:
                raise TimeoutError(f"robot {self.robot_id}: frames of {t:.2f} s never ended")
            self._frames += self.driver.poll(0.5)

    def take_go(self, timeout_s: float) -> StepGo | None:
        """The next step's :class:`StepGo`, None if none came within ``timeout_s`` (before
        the first step, the hello is repeated meanwhile) or it repeats a step answered."""
        try:
            go = self._go.get(timeout=timeout_s)
        except queue.Empty:
            if self.steps == 0 and time.monotonic() >= self._next_hello:
                self.hello()
            return None
        if go.time_s <= self._last_t and self.steps > 0:
            return None  # a repeated step: answered already
        return go

    def receive(self, go: StepGo) -> list[Any]:
        """The step's first half, before the clock moves to ``go.time_s``: wait for its frames
        and the downlink counted, process that downlink (at the previous step's time) and
        apply the grant; returns the frames."""
        frames = self._frames_until(go.time_s)
        if not self.radio.wait_packets_in(go.downlink_packets, self.timeout_s):
            raise TimeoutError(
                f"robot {self.robot_id}: downlink of {go.time_s:.2f} s not delivered"
            )
        self.radio.deliver_held()  # at the previous step's time
        self.radio.set_grant(go.grant)
        self._report_link = go.report_link
        return frames

    def act(self, frames: list[Any]) -> None:
        """The step's second half, at its time: the node processes the frames and its
        commands go to the simulator (the radio is pumped by the caller, then :meth:`answer`)."""
        self.frames_seen += len(frames)
        for command in self.node.process(frames):
            self.driver.send(command)
            self.commands_sent += 1

    def answer(self, t: float) -> None:
        """Say step ``t`` is done (after the link was pumped)."""
        self._done(t)
        self._last_t = t
        self.steps += 1

    def step_once(self, timeout_s: float = 0.1) -> bool:
        """Answer the next step (False if none came within ``timeout_s``)."""
        go = self.take_go(timeout_s)
        if go is None:
            return False
        frames = self.receive(go)
        if go.time_s > self.clock.now():
            self.clock.set(go.time_s)
        self.act(frames)
        self.link.pump()
        self.answer(go.time_s)
        return True

    def status_line(self) -> str:
        s = self.node.stats
        up = self.link.meter.total_bytes(robot_id=self.robot_id, direction=Direction.UP)
        return (
            f"robot {self.robot_id} t={self.clock.now():7.1f}s lockstep steps {self.steps} "
            f"sweeps {s.sweeps} nodes {s.pose_nodes} uplink bytes {up} "
            f"deadlocks {s.deadlocks} stuck recoveries {s.stuck_recoveries}"
        )

    def close(self) -> None:
        self._sub.close()
        self.driver.close()


class LockstepGroup:
    """Several robot nodes of a lockstep team in one process (a worker of ``magic run``; the
    robot ids of ``magic robot --lockstep --id 0-7``), on one link and one clock: each step
    is what their own processes would do, in three phases so that the shared clock holds the
    previous step's time while every robot's downlink is processed: every robot receives
    (frames, downlink, grant), the clock moves, every robot acts in id order, the link is
    pumped once, every robot answers. Each robot's channels, draws and messages are its own,
    so the run is the one in one process, bit for bit."""

    def __init__(
        self,
        link: Link,
        robot_ids: list[int],
        clock: ManualClock,
        config: RobotNodeConfig,
        seeds: Callable[[int], int],
        *,
        timeout_s: float = 30.0,
    ) -> None:
        if not robot_ids:
            raise ValueError("a lockstep group needs at least one robot id")
        self.link = link
        self.clock = clock
        self.timeout_s = timeout_s
        self.robots = [
            LockstepRobot(link, rid, clock, config, seeds(rid), timeout_s=timeout_s)
            for rid in sorted(robot_ids)
        ]
        self.steps = 0

    @property
    def frames_seen(self) -> int:
        return sum(r.frames_seen for r in self.robots)

    def hello(self) -> None:
        for r in self.robots:
            r.hello()

    def step_once(self, timeout_s: float = 0.1) -> bool:
        """Answer the next step for every robot of the group (False if none came within
        ``timeout_s``). The ground side sends every robot's go at once: after the first,
        the others are waited for up to the group's timeout."""
        first = self.robots[0].take_go(timeout_s)
        if first is None:
            for r in self.robots[1:]:
                if r.steps == 0:
                    r.take_go(0.0)  # keeps the hellos going
            return False
        gos = [first]
        for r in self.robots[1:]:
            go = r.take_go(self.timeout_s)
            if go is None or go.time_s != first.time_s:
                got = "none" if go is None else f"{go.time_s:.2f} s"
                raise TimeoutError(
                    f"robot {r.robot_id}: no step {first.time_s:.2f} s with its group ({got})"
                )
            gos.append(go)
        frames = [r.receive(go) for r, go in zip(self.robots, gos, strict=True)]
        t = first.time_s
        if t > self.clock.now():
            self.clock.set(t)
        for r, f in zip(self.robots, frames, strict=True):
            r.act(f)
        self.link.pump()
        for r in self.robots:
            r.answer(t)
        self.steps += 1
        return True

    def status_line(self) -> str:
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
        for r in self.robots:
            r.close()


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
    proc: RobotProcess | LockstepRobot | LockstepGroup | _FreeGroup
    if args.lockstep and len(robot_ids) == 1:
        proc = LockstepRobot(link, robot_ids[0], clock, config, seeds.robot(robot_ids[0]))
    elif args.lockstep:
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
        if isinstance(proc, LockstepRobot | LockstepGroup):
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
            if isinstance(proc, LockstepRobot | LockstepGroup):
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
