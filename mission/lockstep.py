"""A team in one process, stepped in deterministic mission time (DESIGN section 4).

:class:`TeamInLockstep` composes the simulator, one :class:`~robot.node.RobotNode` per robot
and the radio between them and a ground side (a script today, the GCS next), over two real
zenoh sessions on loopback. Each :meth:`TeamInLockstep.step`:

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

``realtime=True`` (hardware in the loop; ``magic run --realtime``) keeps wall-clock delivery:
links pumped by their own threads every ``pump_period_s`` wall seconds, messages delivered on
zenoh's threads as they arrive. It runs no faster (the exchange costs little) and promises no
repeatability.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np

from protocol.clock import ManualClock
from protocol.link import GcsEndpoint, Link, LinkConfig, RobotEndpoint
from protocol.loopback import LockstepRadio, free_loopback_port, unique_mission
from protocol.radio import RadioConfig
from protocol.radio_channel import LinkBackpressure
from robot.node import RobotNode, RobotNodeConfig
from sim.simulator import SimDriver, Simulator

__all__ = ["RunSeeds", "TeamInLockstep", "seed_streams"]


def _draw(ss: np.random.SeedSequence) -> int:
    return int(ss.generate_state(1, dtype=np.uint32)[0])


@dataclass(frozen=True)
class RunSeeds:
    """Independent seeds of one run, all derived from its seed (numpy ``SeedSequence``
    children: the same seed always gives the same streams, distinct streams never overlap)."""

    seed: int
    simulator: int  # the simulator's sensor noise and slip (with the world's own seed)
    ground: int  # the ground side's draws (scripted goals)
    ground_link: int  # loss draws of the ground's radio channels
    robot_link: int  # loss draws of the robots' radio channels

    def robot(self, index: int) -> int:
        """Robot number ``index``'s node draws (deadlock back-off)."""
        return _draw(np.random.SeedSequence(self.seed, spawn_key=(4, index)))


def seed_streams(seed: int, *, simulator_seed: int = 0) -> RunSeeds:
    """Seeds for every random stream of a run, from ``seed`` (``simulator_seed``:
    ``SimulatorConfig.seed``, mixed in so that it still matters)."""
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    sim_ss, ground, ground_link, robot_link = np.random.SeedSequence(seed).spawn(4)
    return RunSeeds(
        seed=seed,
        simulator=_draw(np.random.SeedSequence([_draw(sim_ss), simulator_seed])),
        ground=_draw(ground),
        ground_link=_draw(ground_link),
        robot_link=_draw(robot_link),
    )


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
            for k, rid in enumerate(sim.robot_ids):
                node = RobotNode(
                    rid, send=self._uplink(rid), config=robot_config, seed=seeds.robot(k)
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

    def uplink_bytes(self, robot_id: int) -> int:
        from protocol.messages import Direction

        assert self.robot_link is not None
        return self.robot_link.meter.total_bytes(robot_id=robot_id, direction=Direction.UP)

    def close(self) -> None:
        """Close both links (idempotent); the simulator is the caller's."""
        if self.robot_link is not None:
            self.robot_link.close()
        self.ground_link.close()

    def __enter__(self) -> TeamInLockstep:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
