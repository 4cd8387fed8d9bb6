"""Two processes' links on one machine's loopback, stepped in lockstep mission time.

Benchmarks, tests and single-host tools use this to run a GCS link and a robot link over real
zenoh sessions (two sessions, TCP on 127.0.0.1) while mission time advances only when told:
each :meth:`LockstepPair.step` moves the shared :class:`~protocol.clock.ManualClock`, pumps one
side, waits until everything it put on the air has been processed by the other side, then does
the same the other way. Runs are therefore repeatable and as fast as the machine allows.

:class:`LockstepRadio` is the general form (one ground endpoint, any number of robot
endpoints on one or more links): :meth:`LockstepRadio.exchange` pumps every robot link, waits
until the ground side has *received* every packet put on the air, processes them in canonical
order (:meth:`~protocol.link._Endpoint.deliver_held`: robot, stream, sender's order), then does
the same for the downlink, broadcasts included (each robot waits for its unicast packets and
every broadcast packet). Wall-clock timing then decides nothing: what a side sees at a
mission step is exactly what was due, in an order fixed by the run.
"""

from __future__ import annotations

import socket
import uuid
from dataclasses import dataclass
from typing import Any

from protocol.clock import ManualClock
from protocol.link import GcsEndpoint, Link, LinkConfig, RobotEndpoint
from protocol.meter import Meter

__all__ = [
    "LockstepPair",
    "LockstepRadio",
    "free_loopback_port",
    "open_pair",
    "unique_mission",
]


def unique_mission(prefix: str) -> str:
    """A mission name no other process uses: sessions of different processes on one machine
    can find each other (gossip, reused loopback ports), and the mission name is what keeps
    their key spaces apart."""
    return f"{prefix}-{uuid.uuid4().hex[:10]}"


def free_loopback_port() -> int:
    """A TCP port on 127.0.0.1 that is free right now."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def open_pair(
    *,
    mission: str | None = None,
    config: LinkConfig | None = None,
    clock: object | None = None,
    seed: int = 0,
) -> tuple[Link, Link]:
    """Open a listening (GCS) link and a connecting (robot) link on a free loopback port
    (``mission`` defaults to a fresh :func:`unique_mission`)."""
    mission = mission or unique_mission("loopback")
    base = config or LinkConfig()
    port = free_loopback_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    fields = {f: getattr(base, f) for f in base.__struct_fields__}
    gcs_cfg = LinkConfig(**{**fields, "listen": (endpoint,), "connect": ()})
    robot_cfg = LinkConfig(**{**fields, "listen": (), "connect": (endpoint,)})
    gcs = Link(gcs_cfg, mission=mission, clock=clock, meter=Meter(), seed=seed)  # type: ignore[arg-type]
    try:
        robot = Link(robot_cfg, mission=mission, clock=clock, meter=Meter(), seed=seed + 1)  # type: ignore[arg-type]
    except Exception:
        gcs.close()
        raise
    return gcs, robot


def _wait(endpoint: Any, count: int, timeout_s: float, what: str) -> None:
    if endpoint.packets_in < count and not endpoint.wait_packets_in(count, timeout_s):
        raise TimeoutError(
            f"{what}: {count - endpoint.packets_in} radio packets not delivered within "
            f"{timeout_s} s"
        )


class LockstepRadio:
    """One ground endpoint and robot endpoints, exchanging in lockstep (module docstring).

    Every endpoint is switched to held arrivals (:meth:`~protocol.link._Endpoint.hold_arrivals`)
    and every link must have ``pump_period_s == 0`` (nothing sends behind the driver's back).
    Messages reach the endpoints' ``on_message`` callbacks (or inboxes) inside
    :meth:`exchange`, on the caller's thread.
    """

    def __init__(
        self,
        ground_link: Link,
        ground: GcsEndpoint,
        robot_links: list[Link],
        robots: dict[int, RobotEndpoint],
    ) -> None:
        for link in (ground_link, *robot_links):
            if link.config.pump_period_s != 0:
                raise ValueError(
                    f"lockstep needs links without a pump thread (pump_period_s 0), got "
                    f"{link.config.pump_period_s}"
                )
        self.ground_link = ground_link
        self.ground = ground
        self.robot_links = list(robot_links)
        self.robots = dict(sorted(robots.items()))
        ground.hold_arrivals()
        for rid, ep in self.robots.items():
            ep.hold_arrivals()
            # every robot hears every broadcast: the ground counts broadcast packets for the
            # robots it has a channel to, so it gets one for each from the start
            ground.channel(rid)

    def wait_connected(self, timeout_s: float) -> None:
        """Block until every robot and the ground side hear each other (TimeoutError)."""
        for rid, ep in self.robots.items():
            if not (ep.wait_for_gcs(timeout_s) and self.ground.wait_for_robot(rid, timeout_s)):
                raise TimeoutError(f"robot {rid}'s radio did not come up within {timeout_s} s")

    def exchange(self, timeout_s: float = 10.0) -> None:
        """Uplink then downlink at the current mission time: pump, wait for every packet to
        arrive, process them in canonical order."""
        for link in self.robot_links:
            link.pump()
        sent_up = sum(ep.packets_out for ep in self.robots.values())
        _wait(self.ground, sent_up, timeout_s, "uplink")
        self.ground.deliver_held()
        self.ground_link.pump()
        for rid, ep in self.robots.items():
            _wait(ep, self.ground.packets_out_by_robot.get(rid, 0), timeout_s, f"robot {rid}")
            ep.deliver_held()


@dataclass
class LockstepPair:
    """A GCS endpoint and one robot endpoint on separate loopback sessions, in lockstep."""

    clock: ManualClock
    gcs_link: Link
    robot_link: Link
    gcs: GcsEndpoint
    robot: RobotEndpoint
    _radio: LockstepRadio | None = None

    @classmethod
    def open(
        cls,
        robot_id: int = 1,
        *,
        config: LinkConfig | None = None,
        mission: str | None = None,
        seed: int = 0,
        timeout_s: float = 10.0,
    ) -> LockstepPair:
        clock = ManualClock()
        base = config or LinkConfig()
        fields = {f: getattr(base, f) for f in base.__struct_fields__}
        cfg = LinkConfig(**{**fields, "pump_period_s": 0.0})
        mission = mission or unique_mission("lockstep")
        gcs_link, robot_link = open_pair(mission=mission, config=cfg, clock=clock, seed=seed)
        try:
            gcs = gcs_link.gcs_endpoint()
            robot = robot_link.robot_endpoint(robot_id)
            if not (robot.wait_for_gcs(timeout_s) and gcs.wait_for_robot(robot_id, timeout_s)):
                raise TimeoutError(f"loopback sessions did not match within {timeout_s} s")
        except Exception:
            robot_link.close()
            gcs_link.close()
            raise
        return cls(clock, gcs_link, robot_link, gcs, robot)

    def step(self, dt_s: float, *, timeout_s: float = 10.0) -> None:
        """Advance mission time by ``dt_s`` and exchange what both sides send, in lockstep
        (a one-robot :class:`LockstepRadio`: messages are delivered inside this call, on
        this thread)."""
        self.clock.advance(dt_s)
        if self._radio is None:
            self._radio = LockstepRadio(
                self.gcs_link, self.gcs, [self.robot_link], {self.robot.robot_id: self.robot}
            )
        self._radio.exchange(timeout_s)

    def close(self) -> None:
        self.robot_link.close()
        self.gcs_link.close()

    def __enter__(self) -> LockstepPair:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
