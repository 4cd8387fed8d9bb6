"""A team in one process, stepped in deterministic mission time (DESIGN section 4).

:class:`TeamInLockstep` composes the simulator, one :class:`~robot.node.RobotNode` per robot
and the radio between them and a ground side (the GCS, or a script: :mod:`mission.assembly`),
over two real zenoh sessions on loopback. Each :meth:`TeamInLockstep.step`:

1. steps the simulator by ``step_s`` and sets the mission clock to its time;
2. applies the radio model's grants to both ends of every robot's radio;
3. hands each robot node, in robot-id order, the frames its driver holds and sends its
   commands back to the simulator (applied at the next step);
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

:class:`TeamOverProcesses` is the same team with each robot node in its own process
(``magic robot --lockstep``; ``magic run --robot-processes``) and gives the same run, bit for
bit: the per-step counts of :mod:`mission.lockstep_protocol` stand in for the ordering zenoh
keeps only within one key. Not covered yet: the simulator and the ground side in separate
processes (``magic sim`` + ``magic gcs``), which needs the ground side to send the step's
downlink counts and the simulator to wait for them.

``realtime=True`` (hardware in the loop; ``magic run --realtime``) keeps wall-clock delivery:
links pumped by their own threads every ``pump_period_s`` wall seconds, messages delivered on
zenoh's threads as they arrive. It runs no faster (the exchange costs little) and promises no
repeatability.
"""

from __future__ import annotations

import time as _time
from collections.abc import Callable
from typing import Any

import msgspec

from mission.lockstep_protocol import (
    RunSeeds,
    StepDone,
    StepGo,
    seed_streams,
    step_done_key,
    step_go_key,
)
from protocol.clock import ManualClock
from protocol.link import GcsEndpoint, Link, LinkConfig, RobotEndpoint
from protocol.loopback import LockstepRadio, free_loopback_port, unique_mission
from protocol.radio import RadioConfig
from protocol.radio_channel import LinkBackpressure
from robot.node import RobotNode, RobotNodeConfig
from sim.simulator import SimDriver, Simulator

__all__ = ["RunSeeds", "TeamInLockstep", "TeamOverProcesses", "seed_streams"]


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
                    rid, send=self._uplink(rid), config=robot_config, seed=seeds.robot(rid)
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
            for command in self.nodes[rid].process(driver.poll(0.0)):
                driver.send(command)
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


class TeamOverProcesses:
    """The same team with each robot node in its own process (``magic robot --lockstep``),
    the simulator and the ground side in this one; same interface as :class:`TeamInLockstep`
    except ``nodes`` (empty: the nodes live elsewhere) and ``uplink_bytes`` (metered there).

    Each :meth:`step` mirrors the in-process one (see :mod:`mission.lockstep_protocol`): the
    simulator steps and the ground end gets the grants; the step's frames, each robot's
    end-of-step tick and a :class:`StepGo` per robot go out; the ground side has its turn;
    then this process waits for every robot's :class:`StepDone` and for the uplink packets
    and commands it counts, processes the uplink in canonical order and pumps the downlink.
    A robot processes that downlink at its next step, at this step's time, as in one process.
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
        step_timeout_s: float = 30.0,
    ) -> None:
        import subprocess
        import sys
        import tempfile
        import threading

        from sim.server import SimServer

        self.sim = sim
        self.realtime = False
        self.seeds = seeds
        self.step_timeout_s = step_timeout_s
        self.clock = sim.clock  # the simulator's mission clock
        self.nodes: dict[int, RobotNode] = {}
        endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        self.mission = mission = unique_mission("run")
        cfg = LinkConfig(listen=(endpoint,), radio=radio, pump_period_s=0.0)
        self.ground_link = Link(cfg, mission=mission, clock=self.clock, seed=seeds.ground_link)
        self._procs: list[subprocess.Popen[bytes]] = []
        self._tmp = tempfile.TemporaryDirectory(prefix="magic-run-")
        self.server: SimServer | None = None
        self._done: dict[int, StepDone] = {}
        self._done_cond = threading.Condition()
        self._decode_done = msgspec.msgpack.Decoder(StepDone)
        self._encode = msgspec.msgpack.Encoder()
        try:
            self.ground: GcsEndpoint = self.ground_link.gcs_endpoint(on_message=on_ground_message)
            self.ground.hold_arrivals()
            self.server = SimServer(sim, link=self.ground_link, mission=mission, rtf=0.0)
            self.server.end_of_step_ticks = True
            for rid in sim.robot_ids:
                self.ground_link.subscribe(step_done_key(mission, rid), self._on_done(rid))
            argv = ["--mission", mission, "--connect", endpoint, "--radio", radio_path]
            argv += ["--listen", "tcp/127.0.0.1:0", "--lockstep", "--seed", str(seeds.seed)]
            if robot_config is not None and robot_config != RobotNodeConfig():
                path = f"{self._tmp.name}/robot.json"  # JSON is YAML
                with open(path, "wb") as f:
                    f.write(msgspec.json.encode(robot_config))
                argv += ["--config", path]
            for rid in sim.robot_ids:
                self._procs.append(
                    subprocess.Popen(
                        [sys.executable, "-m", "mission.cli", "robot", "--id", str(rid), *argv],
                        stdout=subprocess.DEVNULL,
                    )
                )
            for rid in sim.robot_ids:
                if not self.ground.wait_for_robot(rid, connect_timeout_s):
                    raise TimeoutError(f"robot {rid}'s process did not come up on {endpoint}")
            self._wait_done(0.0, connect_timeout_s)  # every robot said hello
        except BaseException:
            self.close()
            raise

    def _on_done(self, robot_id: int) -> Callable[[str, bytes], None]:
        def handle(_key: str, payload: bytes) -> None:
            done = self._decode_done.decode(payload)
            with self._done_cond:
                last = self._done.get(robot_id)
                if last is None or done.time_s >= last.time_s:
                    self._done[robot_id] = done
                self._done_cond.notify_all()

        return handle

    def _wait_done(self, time_s: float, timeout_s: float) -> dict[int, StepDone]:
        def all_done() -> bool:
            return all(
                rid in self._done and self._done[rid].time_s >= time_s for rid in self.sim.robot_ids
            )

        deadline = _time.monotonic() + timeout_s
        with self._done_cond:
            while not self._done_cond.wait_for(all_done, 0.5):
                if _time.monotonic() > deadline or any(p.poll() is not None for p in self._procs):
                    late = [r for r in self.sim.robot_ids if r not in self._done]
                    raise TimeoutError(
                        f"robots did not answer mission time {time_s:.2f} s (none yet from {late})"
                    )
            return dict(self._done)

    def _send_go(self) -> None:
        sim = self.sim
        grants = sim.radio_grants()
        for rid in sim.robot_ids:
            go = StepGo(sim.time_s, self.ground.packets_out_by_robot.get(rid, 0), grants[rid])
            self.ground_link.publish(step_go_key(self.mission, rid), self._encode.encode(go))

    def step(self, on_step: Callable[[], None] | None = None) -> None:
        sim = self.sim
        assert self.server is not None
        sim.step()
        for rid, grant in sim.radio_grants().items():
            self.ground.set_grant(rid, grant)
        self.server.publish()
        self._send_go()
        if on_step is not None:
            on_step()
        done = self._wait_done(sim.time_s, self.step_timeout_s)
        uplink = sum(d.uplink_packets for d in done.values())
        if not self.ground.wait_packets_in(uplink, self.step_timeout_s):
            raise TimeoutError(f"uplink packets not delivered at {sim.time_s:.2f} s")
        for rid, d in done.items():
            if not self.server.wait_commands(rid, d.commands, self.step_timeout_s):
                raise TimeoutError(f"robot {rid}'s commands not delivered at {sim.time_s:.2f} s")
        self.ground.deliver_held()
        self.ground_link.pump()

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
