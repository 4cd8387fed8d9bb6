"""A team in one process, stepped in deterministic mission time (DESIGN section 4).

:class:`TeamInLockstep` composes the simulator, one :class:`~robot.node.RobotNode` per robot
and the radio between them and a ground side (the GCS, or a script: :mod:`mission.assembly`),
over two real zenoh sessions on loopback. Each :meth:`TeamInLockstep.step`:

1. steps the simulator by ``step_s`` and sets the mission clock to its time;
2. applies the radio model's grants to both ends of every robot's radio;
3. hands each robot node, in robot-id order, the frames its driver holds and sends its
   commands back to the simulator (applied at the next step), and puts its radio in or out
   of relay mode as the node says (:attr:`~robot.node.RobotNode.radio_relay`: a relay task;
   :meth:`~sim.simulator.Simulator.set_relay`, from the next radio update);
4. calls the ground side's ``on_step`` (it may send downlink messages);
5. exchanges the radio in lockstep (:class:`~protocol.loopback.LockstepRadio`): every link is
   pumped by hand at this mission time, the exchange waits until the other side has received
   every packet put on the air, and arrivals are processed in a canonical order (robot,
   stream, sender's order), on this thread: the ground side's ``on_message`` then the robots'
   downlink queues (applied by each node at its next frame).

Nothing then depends on wall-clock timing, thread scheduling or machine load; every random
draw comes from streams derived from the run's seed (:func:`seed_streams`): the simulator's
noise and slip, the radio channels' loss draws, each robot node's back-off draws, and the
ground side's own (``seeds.ground``). The same world, team, seed, duration and configuration
give the same poses, events and messages, bit for bit.

:class:`TeamOverProcesses` is the same team with the robot nodes in worker processes, a group
of nodes per process (``magic robot --lockstep --id 0-7``; ``magic run --robot-processes``:
one worker per core), on this host or others (zenoh endpoints, a router), and gives the same
run, bit for bit: the per-step counts of :mod:`mission.lockstep_protocol` stand in for the
ordering zenoh keeps only within one key, and a group's frames and commands travel in its one
message each way a step. Not covered yet: the simulator
and the ground side in separate processes (``magic sim`` + ``magic gcs``), which needs the
ground side to send the step's downlink counts and the simulator to wait for them.

``realtime=True`` (hardware in the loop; ``magic run --realtime``) keeps wall-clock delivery:
links pumped by their own threads every ``pump_period_s`` wall seconds, messages delivered on
zenoh's threads as they arrive. It runs no faster (the exchange costs little) and promises no
repeatability.
"""

from __future__ import annotations

import functools
import logging
import time as _time
from collections.abc import Callable
from typing import Any

import msgspec

from mission.lockstep_protocol import (
    GroupDone,
    GroupGo,
    RobotGo,
    RunSeeds,
    StepDone,
    group_done_key,
    group_go_key,
    seed_streams,
)
from protocol.clock import ManualClock
from protocol.link import GcsEndpoint, Link, LinkConfig, RobotEndpoint
from protocol.loopback import LockstepRadio, free_loopback_port, unique_mission
from protocol.radio import RadioConfig
from protocol.radio_channel import LinkBackpressure
from protocol.sensors import decode_command, encode_sensor_frame
from protocol.wire import ProtocolError
from robot.node import RobotNode, RobotNodeConfig
from sim.simulator import CommandError, SimDriver, Simulator

__all__ = [
    "RunSeeds",
    "TeamInLockstep",
    "TeamOverProcesses",
    "WorkerDied",
    "seed_streams",
    "step_wait_s",
    "worker_groups",
]


log = logging.getLogger(__name__)


class TeamInLockstep:
    """The simulator, the robot nodes and the radio to a ground side (module docstring).

    ``on_ground_message(robot_id, message)`` receives the uplink (in lockstep: inside
    :meth:`step`, on this thread, in canonical order); ``ground`` (a
    :class:`~protocol.link.GcsEndpoint`) sends the downlink. Close with :meth:`close` (or use
    as a context manager): links first, then the simulator.
    """

    def __init__(
        self,
        sim: Simulator,
        *,
        radio: RadioConfig,
        seeds: RunSeeds,
        on_ground_message: Callable[[int, Any], None],
        robot_config: RobotNodeConfig | None = None,
        realtime: bool = False,
        link_config: LinkConfig | None = None,
        connect_timeout_s: float = 10.0,
        exchange_timeout_s: float = 10.0,
    ) -> None:
        self.sim = sim
        self.realtime = realtime
        self.seeds = seeds
        self.exchange_timeout_s = exchange_timeout_s
        self._relaying: dict[int, bool] = {}
        self.clock = ManualClock(sim.time_s)
        base = link_config or LinkConfig()
        pump = base.pump_period_s if realtime else 0.0
        if realtime and pump <= 0:
            raise ValueError("realtime mode needs a link pump thread (pump_period_s > 0)")
        endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        mission = unique_mission("run")
        ground_cfg = msgspec.structs.replace(
            base, listen=(endpoint,), connect=(), radio=radio, pump_period_s=pump
        )
        robot_cfg = msgspec.structs.replace(
            base, listen=(), connect=(endpoint,), radio=radio, pump_period_s=pump
        )
        self.ground_link = Link(
            ground_cfg, mission=mission, clock=self.clock, seed=seeds.ground_link
        )
        self.robot_link: Link | None = None
        self.radio: LockstepRadio | None = None
        try:
            self.robot_link = Link(
                robot_cfg, mission=mission, clock=self.clock, seed=seeds.robot_link
            )
            self.ground: GcsEndpoint = self.ground_link.gcs_endpoint(on_message=on_ground_message)
            self.nodes: dict[int, RobotNode] = {}
            self.radios: dict[int, RobotEndpoint] = {}
            self.drivers: dict[int, SimDriver] = {}
            for rid in sim.robot_ids:
                node = RobotNode(
                    rid,
                    send=self._uplink(rid),
                    config=robot_config,
                    seed=seeds.robot(rid),
                    uplink_backlog=functools.partial(self._radio_backlog, rid),
                )
                self.nodes[rid] = node
                self.radios[rid] = self.robot_link.robot_endpoint(
                    rid, on_message=node.handle_downlink
                )
                self.drivers[rid] = sim.driver(rid)
            if not realtime:
                self.radio = LockstepRadio(
                    self.ground_link, self.ground, [self.robot_link], self.radios
                )
            for rid, ep in self.radios.items():
                if not (
                    ep.wait_for_gcs(connect_timeout_s)
                    and self.ground.wait_for_robot(rid, connect_timeout_s)
                ):
                    raise TimeoutError(f"robot {rid}'s radio did not come up on {endpoint}")
        except BaseException:
            self.close()
            raise

    def _radio_backlog(self, robot_id: int) -> int:
        """Robot ``robot_id``'s queued uplink bytes (its node's drain hold asks)."""
        return self.radios[robot_id].backlog_bytes()

    def _uplink(self, robot_id: int) -> Callable[[Any], object]:
        """The node's ``send``: its radio endpoint's, tolerating a full queue (the message was
        refused, not accepted; the node's next report supersedes it)."""

        def send(msg: Any) -> object:
            try:
                return self.radios[robot_id].send(msg)
            except LinkBackpressure:
                return None

        return send

    def step(self, on_step: Callable[[], None] | None = None) -> None:
        """One simulator step, the robots' answers, ``on_step`` (the ground side's turn), and
        the radio exchange (module docstring)."""
        sim = self.sim
        sim.step()
        self.clock.set(sim.time_s)
        for rid, grant in sim.radio_grants().items():
            self.radios[rid].set_grant(grant)
            self.ground.set_grant(rid, grant)
        for rid in sim.robot_ids:
            driver = self.drivers[rid]
            node = self.nodes[rid]
            for command in node.process(driver.poll(0.0)):
                driver.send(command)
            relay = node.radio_relay  # the robot's radio setting (a relay task holds it)
            if relay != self._relaying.get(rid, False):
                sim.set_relay(rid, relay)
                self._relaying[rid] = relay
        if on_step is not None:
            on_step()
        if self.radio is not None:
            self.radio.exchange(self.exchange_timeout_s)

    def node_counters(self, robot_id: int) -> tuple[int, int, int]:
        """Robot ``robot_id``'s node's deadlocks, stuck recoveries and plan failures."""
        s = self.nodes[robot_id].stats
        return (s.deadlocks, s.stuck_recoveries, s.plan_failures)

    def uplink_bytes(self, robot_id: int) -> int:
        from protocol.messages import Direction

        assert self.robot_link is not None
        return self.robot_link.meter.total_bytes(robot_id=robot_id, direction=Direction.UP)

    def link_bytes(self) -> dict[tuple[int, str, str], int]:
        """Radio bytes so far by ``(robot_id, "up" | "down", stream)``: what each end put on
        the air (the robots' meter for the uplink, the ground's for the downlink)."""
        from protocol.messages import Direction

        out: dict[tuple[int, str, str], int] = {}
        links = [self.ground_link] + ([self.robot_link] if self.robot_link is not None else [])
        for link in links:
            for (rid, direction, stream), c in link.meter.snapshot().items():
                d = "up" if direction == Direction.UP else "down"
                out[(rid, d, stream)] = out.get((rid, d, stream), 0) + c.bytes
        return out

    def close(self) -> None:
        """Close both links (idempotent); the simulator is the caller's."""
        if self.robot_link is not None:
            self.robot_link.close()
        self.ground_link.close()

    def __enter__(self) -> TeamInLockstep:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class WorkerDied(RuntimeError):
    """A robot worker process ended during a run: which one, its robots, its exit status and
    the last line it wrote on stderr."""


def worker_groups(robot_ids: list[int], workers: int) -> list[list[int]]:
    """``robot_ids`` split into ``workers`` groups of consecutive ids, sizes differing by at
    most one (fewer groups when there are fewer robots)."""
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    ids = sorted(robot_ids)
    n = min(workers, len(ids))
    if n == 0:
        return []
    size, extra = divmod(len(ids), n)
    out, i = [], 0
    for g in range(n):
        k = size + (1 if g < extra else 0)
        out.append(ids[i : i + k])
        i += k
    return out


def _ids_text(ids: list[int]) -> str:
    """``[0, 1, 2, 5]`` -> ``"0-2,5"`` (``magic robot --id``)."""
    parts: list[str] = []
    i = 0
    while i < len(ids):
        j = i
        while j + 1 < len(ids) and ids[j + 1] == ids[j] + 1:
            j += 1
        parts.append(str(ids[i]) if i == j else f"{ids[i]}-{ids[j]}")
        i = j + 1
    return ",".join(parts)


def step_wait_s(
    time_s: float, step_timeout_s: float, startup_timeout_s: float, startup_mission_s: float
) -> float:
    """How long a lockstep step at mission time ``time_s`` waits for its robots: the longer
    ``startup_timeout_s`` before ``startup_mission_s`` (kernels compiling at the first sweep,
    plan and image), ``step_timeout_s`` after."""
    return max(step_timeout_s, startup_timeout_s) if time_s < startup_mission_s else step_timeout_s


class TeamOverProcesses:
    """The same team with its robot nodes in worker processes (``magic robot --lockstep
    --id 0-7``: a group of nodes per process, :class:`~mission.robot_process.LockstepGroup`),
    the simulator and the ground side in this one; same interface as
    :class:`TeamInLockstep` except ``nodes`` (empty: the nodes live elsewhere) and
    ``uplink_bytes`` (metered there).

    ``workers``: how many worker processes to start, robots split among them in consecutive
    id groups (default: one per core; ``len(robots)``: one per robot). ``remote_robots``:
    robots this process does not start: their workers run elsewhere (other hosts:
    ``magic robot --lockstep --id ... --mission M --seed S`` with endpoints reaching this
    process's) and are waited for. ``link``: this process's zenoh endpoints and mode (default:
    listen on a free loopback port); ``worker_link_args``: the endpoint options the started
    workers get (default: ``--connect`` to what ``link`` connects to, in its mode, when it
    connects anywhere, e.g. a router; else to ``link``'s listen endpoints). ``mission``: the
    zenoh mission name (default: a fresh one; name it when workers start elsewhere).

    Each :meth:`step` mirrors the in-process one (see :mod:`mission.lockstep_protocol`): the
    simulator steps and the ground end gets the grants; one :class:`GroupGo` per group of
    robot nodes (the groups as their hellos said) goes out with its robots' frames, grants and
    downlink counts; the ground side has its turn; then this process waits for every robot's
    :class:`StepDone` (one :class:`GroupDone` a group, whose commands go to the simulator as
    it arrives) and for the uplink packets they count, processes the uplink in canonical order
    and pumps the downlink. A robot processes that downlink at its next step, at this step's
    time, as in one process.
    A worker that ends raises :class:`WorkerDied` (which, its robots, exit status, last
    stderr line); a robot that does not answer within ``step_timeout_s`` a TimeoutError naming
    it; two processes answering for one robot a ValueError naming the robot and both. Until
    ``startup_mission_s`` mission seconds the wait is ``startup_timeout_s`` instead: the robots'
    numba kernels compile at their first sweep, plan and image (minutes on a cold cache, the
    first run after an install, where 30 s had ended the run); a worker that dies is noticed at
    once either way.
    """

    def __init__(
        self,
        sim: Simulator,
        *,
        radio: RadioConfig,
        radio_path: str,
        seeds: RunSeeds,
        on_ground_message: Callable[[int, Any], None],
        robot_config: RobotNodeConfig | None = None,
        connect_timeout_s: float = 60.0,
        step_timeout_s: float = 120.0,
        startup_timeout_s: float = 900.0,
        startup_mission_s: float = 5.0,
        workers: int | None = None,
        remote_robots: tuple[int, ...] = (),
        link: LinkConfig | None = None,
        worker_link_args: list[str] | None = None,
        mission: str | None = None,
        remote_gcs: Callable[..., Any] | None = None,
    ) -> None:
        import os
        import subprocess
        import sys
        import tempfile
        import threading

        from sim.server import SimServer

        self.sim = sim
        self.realtime = False
        self.seeds = seeds
        self.step_timeout_s = step_timeout_s
        self.startup_timeout_s = startup_timeout_s
        self.startup_mission_s = startup_mission_s
        self.clock = sim.clock  # the simulator's mission clock
        self.nodes: dict[int, RobotNode] = {}
        unknown = sorted(set(remote_robots) - set(sim.robot_ids))
        if unknown:
            raise ValueError(f"remote robots {unknown} are not in the simulator's team")
        self.mission = mission = mission or unique_mission("run")
        if link is None:
            endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
            link = LinkConfig(listen=(endpoint,))
        cfg = msgspec.structs.replace(link, radio=radio, pump_period_s=0.0)
        where = ", ".join(cfg.connect or cfg.listen)
        if worker_link_args is None:
            if cfg.connect:
                worker_link_args = [a for e in cfg.connect for a in ("--connect", e)]
                worker_link_args += ["--mode", "client" if cfg.mode == "client" else "peer"]
            else:
                worker_link_args = [a for e in cfg.listen for a in ("--connect", e)]
            if "client" not in worker_link_args:
                worker_link_args += ["--listen", "tcp/127.0.0.1:0"]
        try:
            self.ground_link = Link(cfg, mission=mission, clock=self.clock, seed=seeds.ground_link)
        except Exception as err:  # noqa: BLE001 - zenoh's ZError: an endpoint in use, ...
            from protocol.process_cli import zenoh_error_text

            raise ValueError(
                f"cannot open the ground side's zenoh link on {where}: {zenoh_error_text(err)}"
            ) from None
        self._procs: list[subprocess.Popen[bytes]] = []
        self._groups: list[list[int]] = []
        self._stderr: list[str] = []
        self._tmp = tempfile.TemporaryDirectory(prefix="magic-run-")
        self.server: SimServer | None = None
        self._done: dict[int, StepDone] = {}
        self._relaying: dict[int, bool] = {}  # as the robots last said (StepDone.relay)
        self._hosts: dict[int, str] = {}
        self._twice: str | None = None
        self._done_cond = threading.Condition()
        #: each group of robot nodes (its first robot id -> its ids), as its hello said
        self._robot_groups: dict[int, list[int]] = {}
        self._decode_done = msgspec.msgpack.Decoder(GroupDone)
        self._encode = msgspec.msgpack.Encoder()
        self.rejected_commands = 0  # commands that did not decode (the simulator counts its own)
        #: the GCS in its own process (:class:`mission.lockstep_gcs.RemoteGcs`), or None: the
        #: ground end of the radio is in this process (``ground``)
        self.remote: Any = None
        #: ask the robots for their reliable uplink state with the next steps
        #: (:attr:`StepDone.link_state`: the chaos bench's accounting)
        self.report_link = False
        try:
            if cfg.connect and not self.ground_link.wait_reachable(min(connect_timeout_s, 10.0)):
                raise ValueError(
                    f"cannot reach {where} (no zenoh router or peer answered within "
                    f"{min(connect_timeout_s, 10.0):g} s)"
                )
            self.ground: GcsEndpoint | None = None
            if remote_gcs is None:
                self.ground = self.ground_link.gcs_endpoint(on_message=on_ground_message)
                self.ground.hold_arrivals()
            # the robots' frames go in each group's GroupGo, their commands come in its
            # GroupDone: the server publishes the clock, grants and the truth only
            self.server = SimServer(
                sim, link=self.ground_link, mission=mission, rtf=0.0, serve_drivers=False
            )
            self.ground_link.subscribe(group_done_key(mission), self._on_done)
            self._go_keys: dict[int, str] = {}  # each group's go key, built once
            argv = ["--mission", mission, *worker_link_args, "--radio", radio_path]
            argv += ["--lockstep", "--seed", str(seeds.seed), "--progress-s", "1e9"]
            if robot_config is not None and robot_config != RobotNodeConfig():
                path = f"{self._tmp.name}/robot.json"  # JSON is YAML
                with open(path, "wb") as f:
                    f.write(msgspec.json.encode(robot_config))
                argv += ["--config", path]
            local = [r for r in sim.robot_ids if r not in set(remote_robots)]
            n = workers if workers is not None else len(os.sched_getaffinity(0))
            self._groups = worker_groups(local, n)
            for i, group in enumerate(self._groups):
                err_path = f"{self._tmp.name}/worker{i}.err"
                self._stderr.append(err_path)
                with open(err_path, "wb") as err_file:
                    self._procs.append(
                        subprocess.Popen(
                            [sys.executable, "-m", "mission.cli", "robot"]
                            + ["--id", _ids_text(group), *argv],
                            stdout=subprocess.DEVNULL,
                            stderr=err_file,
                        )
                    )
            deadline = _time.monotonic() + connect_timeout_s
            ground = self.ground
            for rid in sim.robot_ids if ground is not None else []:
                while ground is not None and not ground.wait_for_robot(rid, 0.5):
                    self._check_workers()
                    if _time.monotonic() > deadline:
                        who = "started elsewhere" if rid in remote_robots else "a worker here"
                        raise TimeoutError(
                            f"robot {rid} ({who}) did not come up on {where} within "
                            f"{connect_timeout_s:g} s"
                        )
            self._wait_done(0.0, max(1.0, deadline - _time.monotonic()))  # every robot hello
            if remote_gcs is not None:
                gcs_args = list(worker_link_args)
                self.remote = remote_gcs(
                    self.ground_link, mission, gcs_args, lambda: dict(self._done)
                )
        except BaseException:
            self.close()
            raise

    @property
    def worker_pids(self) -> list[int]:
        """The started workers' process ids, in group order (:attr:`groups`)."""
        return [p.pid for p in self._procs]

    @property
    def groups(self) -> list[list[int]]:
        """The robot ids of each started worker."""
        return [list(g) for g in self._groups]

    def _check_workers(self) -> None:
        """Raise :class:`WorkerDied` for the first worker that has ended."""
        for i, p in enumerate(self._procs):
            status = p.poll()
            if status is None:
                continue
            last = ""
            try:
                with open(self._stderr[i], "rb") as f:
                    lines = [x for x in f.read().decode(errors="replace").splitlines() if x]
                last = lines[-1].strip() if lines else ""
            except OSError:
                pass
            what = f"signal {-status}" if status < 0 else f"status {status}"
            raise WorkerDied(
                f"robot worker {i} (robots {_ids_text(self._groups[i])}, pid {p.pid}) exited "
                f"with {what}" + (f": {last}" if last else "")
            )

    def _on_done(self, _key: str, payload: bytes) -> None:
        """A group's :class:`GroupDone` (zenoh's thread): for each robot whose step is new,
        its commands go to the simulator (in the group's order, before its done is recorded:
        the step waits for the dones, so they are in before the next simulator step), then
        its done; a robot another process answers for too is named (:meth:`_wait_done`)."""
        try:
            msg = self._decode_done.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError) as err:
            log.warning("bad lockstep answer from a robot group: %s", err)
            return
        known = set(self.sim.robot_ids)
        with self._done_cond:
            for rid, done, commands in zip(msg.robot_ids, msg.done, msg.commands, strict=False):
                if rid not in known:
                    continue
                host = self._hosts.setdefault(rid, done.worker)
                if done.worker != host and self._twice is None:
                    self._twice = f"robot {rid} is hosted twice: by {host} and by {done.worker}"
                last = self._done.get(rid)
                if last is not None and done.time_s < last.time_s:
                    continue
                if last is None or done.time_s > last.time_s:
                    for data in commands:
                        self._command(rid, data)
                self._done[rid] = done
            if msg.time_s == 0.0 and msg.group not in self._robot_groups:
                self._robot_groups[msg.group] = [r for r in msg.robot_ids if r in known]
            self._done_cond.notify_all()

    def _command(self, robot_id: int, data: bytes) -> None:
        """One of robot ``robot_id``'s commands to the simulator (bad ones counted, logged)."""
        try:
            self.sim.command(robot_id, decode_command(data))
        except (ProtocolError, CommandError) as err:
            self.rejected_commands += 1
            log.warning("robot %d: refused command: %s", robot_id, err)

    def _wait_done(self, time_s: float, timeout_s: float) -> dict[int, StepDone]:
        def all_done() -> bool:
            return all(
                rid in self._done and self._done[rid].time_s >= time_s for rid in self.sim.robot_ids
            )

        deadline = _time.monotonic() + timeout_s
        with self._done_cond:
            while not self._done_cond.wait_for(all_done, 0.5):
                if self._twice is not None:
                    raise ValueError(self._twice)
                self._check_workers()
                if _time.monotonic() > deadline:
                    late = [
                        r
                        for r in self.sim.robot_ids
                        if r not in self._done or self._done[r].time_s < time_s
                    ]
                    raise TimeoutError(
                        f"robots {_ids_text(late)} did not answer mission time {time_s:.2f} s "
                        f"within {timeout_s:g} s"
                    )
            if self._twice is not None:
                raise ValueError(self._twice)
            return dict(self._done)

    def _downlink_packets(self, robot_id: int) -> int:
        if self.remote is not None:
            return int(self.remote.downlink_packets(robot_id))
        assert self.ground is not None
        return self.ground.packets_out_by_robot.get(robot_id, 0)

    def _send_go(self, grants: dict[int, Any]) -> None:
        """Each group's :class:`GroupGo`: its robots' downlink counts, grants and frames."""
        sim = self.sim
        with self._done_cond:
            groups = sorted(self._robot_groups.items())
        for first, ids in groups:
            robots = [
                RobotGo(
                    rid,
                    self._downlink_packets(rid),
                    grants[rid],
                    [encode_sensor_frame(f) for f in sim.driver(rid).take_frames()],
                )
                for rid in ids
            ]
            key = self._go_keys.get(first)
            if key is None:
                key = self._go_keys[first] = group_go_key(self.mission, first)
            go = GroupGo(sim.time_s, robots, self.report_link)
            self.ground_link.publish(key, self._encode.encode(go))

    def step(self, on_step: Callable[[], None] | None = None) -> None:
        """One step (class docstring); with the GCS in its own process
        (:mod:`mission.lockstep_gcs`) its turn and the end of its exchange are messages."""
        sim = self.sim
        assert self.server is not None
        sim.step()
        grants = sim.radio_grants()
        if self.ground is not None:
            for rid, grant in grants.items():
                self.ground.set_grant(rid, grant)
        self.server.publish()
        self._send_go(grants)
        if self.remote is not None:
            self.remote.go(sim.time_s, grants)
        if on_step is not None:
            on_step()
        wait_s = step_wait_s(
            sim.time_s, self.step_timeout_s, self.startup_timeout_s, self.startup_mission_s
        )
        done = self._wait_done(sim.time_s, wait_s)
        if self.remote is not None:
            self.remote.end(sim.time_s, done, sim.time_s + sim.config.step_s)
        else:
            assert self.ground is not None
            uplink = sum(d.uplink_packets for d in done.values())
            if not self.ground.wait_packets_in(uplink, self.step_timeout_s):
                raise TimeoutError(f"uplink packets not delivered at {sim.time_s:.2f} s")
        for rid, d in done.items():
            if d.relay != self._relaying.get(rid, False):  # from the next radio update
                sim.set_relay(rid, d.relay)
                self._relaying[rid] = d.relay
        if self.ground is not None:
            self.ground.deliver_held()
            self.ground_link.pump()

    def robot_done(self) -> dict[int, StepDone]:
        """Each robot's latest :class:`StepDone`."""
        with self._done_cond:
            return dict(self._done)

    def uplink_bytes(self, robot_id: int) -> int:
        """Radio bytes robot ``robot_id`` sent (metered in its process, told each step)."""
        done = self._done.get(robot_id)
        return 0 if done is None else done.uplink_bytes

    def link_bytes(self) -> dict[tuple[int, str, str], int]:
        """Radio bytes so far by ``(robot_id, "up" | "down", stream)``: the downlink by stream
        (metered here), each robot's uplink in one ``"all"`` stream (metered in its process,
        told each step)."""
        from protocol.messages import Direction

        out: dict[tuple[int, str, str], int] = {}
        for (rid, direction, stream), c in self.ground_link.meter.snapshot().items():
            d = "up" if direction == Direction.UP else "down"
            out[(rid, d, stream)] = out.get((rid, d, stream), 0) + c.bytes
        for rid in self.sim.robot_ids:
            out[(rid, "up", "all")] = self.uplink_bytes(rid)
        return out

    def node_counters(self, robot_id: int) -> tuple[int, int, int]:
        """Robot ``robot_id``'s node's deadlocks, stuck recoveries and plan failures."""
        done = self._done.get(robot_id)
        if done is None:
            return (0, 0, 0)
        return (done.deadlocks, done.stuck_recoveries, done.plan_failures)

    def close(self) -> None:
        if self.remote is not None:
            self.remote.close()
            self.remote = None
        for p in self._procs:
            if p.poll() is None:
                p.terminate()
        for p in self._procs:
            try:
                p.wait(timeout=10.0)
            except Exception:  # noqa: BLE001 - a robot that will not end is killed
                p.kill()
                p.wait()
        self._procs.clear()
        if self.server is not None:
            self.server.close()
            self.server = None
        self.ground_link.close()
        self._tmp.cleanup()

    def __enter__(self) -> TeamOverProcesses:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
