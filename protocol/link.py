"""The link: every process talks through here, over eclipse-zenoh (DESIGN section 4).

This is the only module that imports zenoh. It is a thin shell: queueing, rates, reliability
and metering live in the sans-IO :class:`~protocol.radio_channel.RadioChannel`; this module
opens the session, moves bytes between channels and zenoh, and runs a pump thread that drains
the queues in mission time.

Embedded default: peer mode listening on loopback only, multicast scouting off, no router, no
external service; shared memory off so what is metered is what would cross a real radio. For
several hosts or large teams, give ``connect``/``listen`` zenoh endpoints (or a router's).

Typical use::

    link = Link(LinkConfig(listen=("tcp/127.0.0.1:7447",)), mission="demo")
    gcs = link.gcs_endpoint()                       # receives every robot's uplink
    robot = Link(LinkConfig(connect=("tcp/127.0.0.1:7447",)), mission="demo").robot_endpoint(3)
    robot.send(PoseNode(...))                       # queued, rate-limited, reliable
    robot_id, msg = gcs.recv(timeout_s=1.0)
    gcs.broadcast(HazardUpdate(...))                # once, to every robot in range
    robot.recv(timeout_s=1.0)                       # -> the HazardUpdate, like any downlink

Broadcasts (paper 4.1) go on ``magic/<mission>/broadcast/down/<stream>`` and are metered once
(robot id :data:`~protocol.messages.BROADCAST_ROBOT_ID`); each robot's channel decides whether
it heard one (its grant's downlink rate and loss) and acknowledges it in its uplink. The GCS's
acknowledgements of every robot's uplink go out coalesced in one broadcast.

Received messages go to the endpoint's ``on_message`` callback (called in order, on a zenoh
thread; keep it short) or, without one, to a queue read by ``recv``. Bad bytes never raise out
of the link: they are counted (``stats.rejected``) and logged.
"""

from __future__ import annotations

import atexit
import json
import logging
import math
import queue
import threading
import time
import weakref
from collections.abc import Callable
from typing import Any, Literal

import msgspec
import zenoh

from protocol import keys
from protocol.clock import Clock, WallClock
from protocol.messages import STREAMS, Direction
from protocol.meter import Meter
from protocol.radio import RadioConfig, RadioGrant
from protocol.radio_channel import (
    BroadcastChannel,
    RadioChannel,
    ReliabilityConfig,
    coalesced_ack,
)
from protocol.sensors import (
    RobotCommand,
    SensorFrame,
    decode_command,
    decode_sensor_frame,
    encode_command,
    encode_sensor_frame,
)
from protocol.wire import ProtocolError

__all__ = [
    "DriverPort",
    "GcsEndpoint",
    "Link",
    "LinkConfig",
    "RemoteDriver",
    "RobotEndpoint",
    "Subscription",
]

log = logging.getLogger(__name__)

#: Links not closed yet. zenoh runs subscriber callbacks in non-daemon threads that live as
#: long as the session, and the interpreter joins such threads before ``atexit`` handlers
#: run: a script that ends without ``close()`` would hang. So the links still open are closed
#: at interpreter shutdown *before* that join (the hook ``concurrent.futures`` uses; plain
#: ``atexit`` where it does not exist).
_OPEN_LINKS: weakref.WeakSet[Link] = weakref.WeakSet()


def _close_open_links() -> None:
    for link in list(_OPEN_LINKS):
        link.close()


getattr(threading, "_register_atexit", atexit.register)(_close_open_links)


_GRANT_DECODER = msgspec.msgpack.Decoder(RadioGrant)
_GRANT_ENCODER = msgspec.msgpack.Encoder()


class LinkConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """How a process joins the zenoh network, and the radio link's tunables.

    ``listen``/``connect``: zenoh endpoints such as ``tcp/127.0.0.1:7447``. ``mode``: ``peer``
    (the default: listens, connects, and meets the peers it learns of directly), ``client``
    (talks only through the router or peer it connects to: processes on hosts that reach each
    other only through a router) or ``router`` (routes for the clients and peers that connect
    to it: one process per site can be the team's router). ``pump_period_s``:
    wall seconds between queue drains by the pump thread; 0 means no thread (call
    :meth:`Link.pump` yourself, e.g. in lockstep simulation). ``initial_grant_bps``: the rate
    each radio channel uses until a radio model grants one (``.inf`` in YAML: unlimited).
    ``security_file``: a :class:`~protocol.transport_security.SecurityConfig` YAML: zenoh over
    mutual TLS (use ``tls/`` endpoints) with access control where it names a roster; empty
    (the default): plain zenoh, as on loopback.
    """

    mode: Literal["peer", "client", "router"] = "peer"
    listen: tuple[str, ...] = ("tcp/127.0.0.1:0",)
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = False
    pump_period_s: float = 0.002
    initial_grant_bps: float = math.inf
    radio: RadioConfig = RadioConfig()
    reliability: ReliabilityConfig = ReliabilityConfig()
    security_file: str = ""

    def __post_init__(self) -> None:
        if not (self.pump_period_s >= 0 and math.isfinite(self.pump_period_s)):
            raise ValueError(f"pump_period_s must be finite and >= 0, got {self.pump_period_s}")
        if not self.initial_grant_bps >= 0:
            raise ValueError(f"initial_grant_bps must be >= 0, got {self.initial_grant_bps}")


def _zenoh_config(cfg: LinkConfig, mission: str) -> zenoh.Config:
    zc = zenoh.Config()
    zc.insert_json5("mode", json.dumps(cfg.mode))
    zc.insert_json5("scouting/multicast/enabled", json.dumps(cfg.multicast_scouting))
    zc.insert_json5("transport/shared_memory/enabled", "false")
    # a client talks only through what it connects to: it listens on nothing
    listen = [] if cfg.mode == "client" else list(cfg.listen)
    zc.insert_json5("listen/endpoints", json.dumps(listen))
    zc.insert_json5("connect/endpoints", json.dumps(list(cfg.connect)))
    if cfg.security_file:
        from protocol.transport_security import apply_to, load_security, zenoh_entries

        security, base_dir = load_security(cfg.security_file)
        apply_to(zc, zenoh_entries(security, base_dir=base_dir, mission=mission))
    return zc


class Subscription:
    """A live subscription; :meth:`close` ends it."""

    def __init__(self, subscriber: Any) -> None:
        self._subscriber = subscriber

    def close(self) -> None:
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None


class _Endpoint:
    """Radio channels of one side, their zenoh publishers, and delivery of what arrives."""

    sends: Direction

    def __init__(
        self,
        link: Link,
        on_message: Callable[..., None] | None,
    ) -> None:
        self._link = link
        self._lock = threading.Lock()  # channel state: send, poll, receive
        self._rx_lock = threading.Lock()  # one delivery at a time keeps streams in order
        self._channels: dict[int, RadioChannel] = {}
        self._publishers: dict[tuple[int, str], Any] = {}
        self._key_cache: dict[str, tuple[int, str]] = {}
        self._on_message = on_message
        self._inbox: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._subs: list[Subscription] = []
        self.callback_errors = 0
        self.rejected_keys = 0
        self.packets_out = 0  # radio packets this endpoint put on zenoh (lost ones excluded)
        self.packets_out_by_robot: dict[int, int] = {}  # the same, per robot channel
        self._arrivals = 0  # radio packets that arrived and were processed (or held)
        self._arrived = threading.Condition()
        # lockstep: arrivals kept, not processed, until deliver_held() (see hold_arrivals)
        self._held: list[tuple[int, str, bytes]] | None = None

    # -- construction helpers

    def _channel(self, robot_id: int) -> RadioChannel:
        ch = self._channels.get(robot_id)
        if ch is None:
            cfg = self._link.config
            ch = RadioChannel(
                robot_id,
                self.sends,
                config=cfg.reliability,
                framing_overhead_bytes=cfg.radio.framing_overhead_bytes,
                meter=self._link.meter,
                grant_bps=cfg.initial_grant_bps,
                seed=self._link.seed * 1_000_003 + robot_id,
            )
            self._setup_channel(ch)
            self._channels[robot_id] = ch
        return ch

    def _setup_channel(self, ch: RadioChannel) -> None:
        """Hook for a side's own wiring of a new channel."""

    def _publisher(self, robot_id: int, stream: str) -> Any:
        pub = self._publishers.get((robot_id, stream))
        if pub is None:
            key = keys.radio(self._link.mission, robot_id, self.sends, stream)
            pub = self._link._session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
            self._publishers[(robot_id, stream)] = pub
        return pub

    def _follow_radio(self, robot_id: int | None) -> None:
        key = keys.sim_radio(self._link.mission, robot_id)
        self._subs.append(self._link.subscribe(key, self._on_grant))

    def _on_grant(self, key: str, payload: bytes) -> None:
        try:
            robot_id = int(key.rsplit("/", 1)[1])
            grant = _GRANT_DECODER.decode(payload)
        except (ValueError, msgspec.DecodeError, msgspec.ValidationError) as err:
            self.rejected_keys += 1
            log.warning("bad radio grant on %s: %s", key, err)
            return
        with self._lock:
            ch = self._accept_channel(robot_id)
            if ch is not None:
                ch.apply_grant(grant)

    # -- data path

    def hold_arrivals(self) -> None:
        """Lockstep mode: from now on radio packets that arrive are counted in
        :attr:`packets_in` but kept, untouched, until :meth:`deliver_held` processes them on
        the caller's thread in a canonical order. Without it, packets are processed and
        messages delivered on zenoh's thread, in arrival order (wall-clock dependent)."""
        with self._arrived:
            if self._held is None:
                self._held = []

    def deliver_held(self) -> int:
        """Process the packets held since the last call, in canonical order: by robot, then
        stream (by its id: acks first), then the order the stream's sender put them on the
        air (zenoh keeps one publisher's order); the channels see the current mission time.
        Messages go to ``on_message`` (on this thread) or the inbox. Returns the packets
        processed."""
        with self._arrived:
            held, self._held = self._held, ([] if self._held is not None else None)
        if not held:
            return 0
        incoming = Direction.UP if self.sends is Direction.DOWN else Direction.DOWN
        rank = {name: spec.stream_id for name, spec in STREAMS[incoming].items()}
        held.sort(key=lambda h: (h[0], rank.get(h[1], len(rank))))  # stable: stream order kept
        for robot_id, stream, data in held:
            self._receive(robot_id, stream, data)
        return len(held)

    def _on_sample(self, sample: Any) -> None:
        if self._held is not None:
            addr = self._address(str(sample.key_expr))
            with self._arrived:
                if addr is not None and self._held is not None:
                    self._held.append((addr[0], addr[1], sample.payload.to_bytes()))
                self._arrivals += 1
                self._arrived.notify_all()
            return
        try:
            self._handle_sample(sample)
        finally:
            with self._arrived:
                self._arrivals += 1
                self._arrived.notify_all()

    @property
    def packets_in(self) -> int:
        """Radio packets that arrived at this endpoint and were processed (or rejected)."""
        return self._arrivals

    def wait_packets_in(self, count: int, timeout_s: float) -> bool:
        """Block until ``packets_in >= count`` (True) or ``timeout_s`` passes (False).

        With :meth:`Link.pump` called by hand this lets a lockstep driver wait until what one
        side put on the air has been processed by the other before time moves on.
        """
        with self._arrived:
            return self._arrived.wait_for(lambda: self._arrivals >= count, timeout_s)

    def _address(self, key: str) -> tuple[int, str] | None:
        """``(robot_id, stream)`` of a radio key; None (counted, logged) if it is not one."""
        addr = self._key_cache.get(key)
        if addr is None:
            try:
                stream = keys.parse_broadcast_key(key)
                if stream is not None:
                    rid = self._broadcast_robot_id()
                    if rid is None:
                        raise ValueError(f"broadcast key {key!r} on a GCS endpoint")
                    addr = (rid, stream)
                else:
                    parsed = keys.parse_radio_key(key)
                    addr = (parsed.robot_id, parsed.stream)
            except ValueError as err:
                self.rejected_keys += 1
                log.warning("ignoring %s", err)
                return None
            self._key_cache[key] = addr
        return addr

    def _broadcast_robot_id(self) -> int | None:
        """The robot whose channel takes broadcasts heard here (None: none does)."""
        return None

    def _handle_sample(self, sample: Any) -> None:
        addr = self._address(str(sample.key_expr))
        if addr is not None:
            self._receive(addr[0], addr[1], sample.payload.to_bytes())

    def _receive(self, robot_id: int, stream: str, data: bytes) -> None:
        now = self._link.clock.now()
        with self._rx_lock:
            with self._lock:
                ch = self._accept_channel(robot_id)
                if ch is None:
                    return
                try:
                    messages = ch.receive(stream, data, now)
                except ProtocolError as err:
                    n = ch.stats.rejected
                    if n <= 5 or n % 1000 == 0:
                        log.warning(
                            "robot %d %s: rejected message #%d: %s", robot_id, stream, n, err
                        )
                    return
            for msg in messages:
                self._deliver(robot_id, msg)

    def _accept_channel(self, robot_id: int) -> RadioChannel | None:
        raise NotImplementedError

    def _deliver(self, robot_id: int, msg: Any) -> None:
        raise NotImplementedError

    def _call(self, *args: Any) -> None:
        assert self._on_message is not None
        try:
            self._on_message(*args)
        except Exception:  # a consumer bug must not kill the link
            self.callback_errors += 1
            log.exception("on_message callback raised")

    def _pump(self, now: float) -> int:
        with self._lock:
            batches = [(rid, ch.poll(now)) for rid, ch in self._channels.items()]
        n = 0
        for robot_id, packets in batches:
            for pkt in packets:
                self._publisher(robot_id, pkt.stream).put(pkt.payload)
            n += len(packets)
            if packets:
                by_robot = self.packets_out_by_robot
                by_robot[robot_id] = by_robot.get(robot_id, 0) + len(packets)
        self.packets_out += n
        return n

    def _close(self) -> None:
        for sub in self._subs:
            sub.close()
        self._subs.clear()
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()

    def _wait_matching(self, robot_id: int, stream: str, timeout_s: float) -> bool:
        pub = self._publisher(robot_id, stream)
        event = threading.Event()
        listener = pub.declare_matching_listener(
            lambda status: event.set() if status.matching else None
        )
        try:
            return bool(pub.matching_status.matching) or event.wait(timeout_s)
        finally:
            listener.undeclare()


class RobotEndpoint(_Endpoint):
    """A robot's side of the radio: sends the uplink, receives the downlink."""

    sends = Direction.UP

    def __init__(
        self,
        link: Link,
        robot_id: int,
        *,
        on_message: Callable[[Any], None] | None = None,
        follow_radio: bool = False,
    ) -> None:
        super().__init__(link, on_message)
        self.robot_id = robot_id
        self.channel = self._channel(robot_id)
        sub = link._session.declare_subscriber(
            keys.radio_wildcard(link.mission, Direction.DOWN, robot_id), self._on_sample
        )
        self._subs.append(Subscription(sub))
        # broadcasts (paper 4.1): heard by every robot; its channel decides whether it was
        # in range and whether the message survived the air
        sub = link._session.declare_subscriber(
            keys.broadcast_wildcard(link.mission), self._on_sample
        )
        self._subs.append(Subscription(sub))
        if follow_radio:
            self._follow_radio(robot_id)

    def _broadcast_robot_id(self) -> int | None:
        return self.robot_id

    def send(self, message: Any) -> int:
        """Queue an uplink message; returns its stream sequence number."""
        with self._lock:
            return self.channel.send(message)

    def set_grant(self, grant: RadioGrant) -> None:
        """Apply a radio grant (its ``uplink_bps`` and ``loss``)."""
        with self._lock:
            self.channel.apply_grant(grant)

    def backlog_bytes(self) -> int:
        """Uplink bytes queued for the air now (:meth:`RadioChannel.backlog_bytes`): what a
        robot back in contact waits for before it drives on (:mod:`robot.comms_watchdog`)."""
        with self._lock:
            return self.channel.backlog_bytes()

    def recv(self, timeout_s: float | None = None) -> Any | None:
        """Next downlink message, or None after ``timeout_s`` (only without ``on_message``)."""
        try:
            return self._inbox.get(timeout=timeout_s)
        except queue.Empty:
            return None

    def wait_for_gcs(self, timeout_s: float) -> bool:
        """Block until a GCS subscribes to this robot's uplink (True) or the timeout passes."""
        return self._wait_matching(self.robot_id, "pose_node", timeout_s)

    def _accept_channel(self, robot_id: int) -> RadioChannel | None:
        return self.channel if robot_id == self.robot_id else None

    def _deliver(self, robot_id: int, msg: Any) -> None:
        if self._on_message is None:
            self._inbox.put(msg)
        else:
            self._call(msg)


class GcsEndpoint(_Endpoint):
    """The GCS side: one radio channel per robot, created when the robot is first heard from,
    and one broadcast to every robot (paper 4.1).

    ``on_message(robot_id, message)`` receives every robot's uplink. :meth:`broadcast` sends
    a message once to every robot in range (hazards and every robot's ``map_from_odom``:
    :class:`~protocol.messages.HazardUpdate`), metered once; robots receive it like any
    downlink message. ``coalesce_acks`` (default): the acknowledgements of every robot's
    uplink go out together as one broadcast :class:`~protocol.messages.BroadcastAck` when one
    of them is due, instead of one radio message per robot.

    Lockstep drivers count arrivals per robot: ``packets_out_by_robot[rid]`` includes every
    broadcast packet put on the air while robot ``rid``'s channel existed (every robot whose
    grant was set), since each robot's endpoint receives each broadcast.
    """

    sends = Direction.DOWN

    def __init__(
        self,
        link: Link,
        *,
        on_message: Callable[[int, Any], None] | None = None,
        follow_radio: bool = False,
        coalesce_acks: bool = True,
    ) -> None:
        cfg = link.config
        self.coalesce_acks = coalesce_acks
        self._broadcast = BroadcastChannel(
            config=cfg.reliability,
            framing_overhead_bytes=cfg.radio.framing_overhead_bytes,
            meter=link.meter,
            grant_bps=cfg.initial_grant_bps,
        )
        self._broadcast_publishers: dict[str, Any] = {}
        self.broadcast_packets_out = 0
        super().__init__(link, on_message)
        sub = link._session.declare_subscriber(
            keys.radio_wildcard(link.mission, Direction.UP), self._on_sample
        )
        self._subs.append(Subscription(sub))
        if follow_radio:
            self._follow_radio(None)

    def send(self, robot_id: int, message: Any) -> int:
        """Queue a downlink message for ``robot_id``; returns its stream sequence number."""
        with self._lock:
            return self._channel(robot_id).send(message)

    def broadcast(self, message: Any) -> int:
        """Queue ``message`` (a :class:`~protocol.messages.HazardUpdate`) once for every robot
        in range; returns its broadcast sequence number. Latest-reliable: a newer one
        supersedes it; it is resent until every robot in range acknowledged it."""
        with self._lock:
            return self._broadcast.send(message)

    def set_broadcast_grant(self, rate_bps: float) -> None:
        """The broadcast's share of the shared channel (bits per mission second)."""
        with self._lock:
            self._broadcast.set_grant(rate_bps)

    @property
    def broadcast_channel(self) -> BroadcastChannel:
        """The broadcast's state machine; read its ``stats`` freely."""
        return self._broadcast

    def demand(self, robot_id: int) -> int:
        """Bytes robot ``robot_id`` last reported still queued for the air (its backlog,
        carried in its acks): what the GCS grants air time by (issue 16)."""
        with self._lock:
            ch = self._channels.get(robot_id)
            return 0 if ch is None else ch.peer_backlog_bytes

    def _setup_channel(self, ch: RadioChannel) -> None:
        ch.external_acks = self.coalesce_acks
        ch.on_broadcast_ack = self._broadcast.on_robot_ack

    def _pump(self, now: float) -> int:
        n = super()._pump(now)
        with self._lock:
            if self.coalesce_acks and not self._broadcast.queued("ack_broadcast"):
                ack = coalesced_ack(self._channels, now)
                if ack is not None:
                    self._broadcast.send(ack)
            in_range = frozenset(r for r, ch in self._channels.items() if ch.rate_bps > 0)
            packets = self._broadcast.poll(now, in_range)
            robots = list(self._channels)
        for pkt in packets:
            pub = self._broadcast_publishers.get(pkt.stream)
            if pub is None:
                pub = self._link._session.declare_publisher(
                    keys.broadcast(self._link.mission, pkt.stream),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )
                self._broadcast_publishers[pkt.stream] = pub
            pub.put(pkt.payload)
        if packets:
            k = len(packets)
            self.broadcast_packets_out += k
            self.packets_out += k
            by_robot = self.packets_out_by_robot
            for rid in robots:
                by_robot[rid] = by_robot.get(rid, 0) + k
        return n + len(packets)

    def _close(self) -> None:
        super()._close()
        for pub in self._broadcast_publishers.values():
            pub.undeclare()
        self._broadcast_publishers.clear()

    def set_grant(self, robot_id: int, grant: RadioGrant) -> None:
        """Apply a radio grant for ``robot_id`` (its ``downlink_bps`` and ``loss``)."""
        with self._lock:
            self._channel(robot_id).apply_grant(grant)

    def channel(self, robot_id: int) -> RadioChannel:
        """The radio channel to ``robot_id`` (created if new); read its ``stats`` freely."""
        with self._lock:
            return self._channel(robot_id)

    def robots(self) -> list[int]:
        with self._lock:
            return sorted(self._channels)

    def recv(self, timeout_s: float | None = None) -> tuple[int, Any] | None:
        """Next ``(robot_id, message)``; None after ``timeout_s`` (only without ``on_message``)."""
        try:
            return self._inbox.get(timeout=timeout_s)  # type: ignore[no-any-return]
        except queue.Empty:
            return None

    def wait_for_robot(self, robot_id: int, timeout_s: float) -> bool:
        """Block until ``robot_id`` subscribes to its downlink (True) or the timeout passes."""
        return self._wait_matching(robot_id, "task", timeout_s)

    def _accept_channel(self, robot_id: int) -> RadioChannel | None:
        return self._channel(robot_id)

    def _deliver(self, robot_id: int, msg: Any) -> None:
        if self._on_message is None:
            self._inbox.put((robot_id, msg))
        else:
            self._call(robot_id, msg)


class RemoteDriver:
    """A :class:`~protocol.sensors.RobotDriver` for a robot node whose simulator (or hardware
    process) runs elsewhere: sensor frames arrive over zenoh, commands go back over zenoh.

    Frames that do not decode are counted in ``rejected`` and logged, never raised.
    """

    def __init__(self, link: Link, robot_id: int) -> None:
        self.robot_id = robot_id
        self.rejected = 0
        self._link = link
        self._frames: queue.SimpleQueue[SensorFrame] = queue.SimpleQueue()
        self._commands_key = keys.sim_commands(link.mission, robot_id)
        self._sub = link.subscribe(keys.sim_sensors(link.mission, robot_id), self._on_frame)

    def _on_frame(self, key: str, payload: bytes) -> None:
        try:
            self._frames.put(decode_sensor_frame(payload))
        except ProtocolError as err:
            self.rejected += 1
            log.warning("robot %d: bad sensor frame on %s: %s", self.robot_id, key, err)

    def poll(self, timeout_s: float) -> list[SensorFrame]:
        """Frames received since the last call, oldest first; waits ``timeout_s`` for one."""
        try:
            frames = [self._frames.get(timeout=timeout_s)]
        except queue.Empty:
            return []
        while True:
            try:
                frames.append(self._frames.get_nowait())
            except queue.Empty:
                return frames

    def send(self, command: RobotCommand) -> None:
        self._link.publish(self._commands_key, encode_command(command))

    def close(self) -> None:
        self._sub.close()


class DriverPort:
    """The simulator's (or hardware process's) end of a :class:`RemoteDriver`.

    ``publish(frame)`` sends a sensor frame to the robot node; each command the node sends is
    decoded and handed to ``on_command``. Bad commands are counted in ``rejected`` and logged.
    """

    def __init__(
        self, link: Link, robot_id: int, on_command: Callable[[RobotCommand], None]
    ) -> None:
        self.robot_id = robot_id
        self.rejected = 0
        self._link = link
        self._on_command = on_command
        self._sensors_key = keys.sim_sensors(link.mission, robot_id)
        self._sub = link.subscribe(keys.sim_commands(link.mission, robot_id), self._on_payload)

    def _on_payload(self, key: str, payload: bytes) -> None:
        try:
            command = decode_command(payload)
        except ProtocolError as err:
            self.rejected += 1
            log.warning("robot %d: bad command on %s: %s", self.robot_id, key, err)
            return
        self._on_command(command)

    def publish(self, frame: SensorFrame) -> None:
        self._link.publish(self._sensors_key, encode_sensor_frame(frame))

    def close(self) -> None:
        self._sub.close()


class Link:
    """One process's zenoh session, its radio endpoints and its radio meter.

    ``clock`` gives mission time for rates and timeouts (default: wall time since start);
    ``meter`` counts the radio bytes this process sends; ``seed`` drives loss injection.
    """

    def __init__(
        self,
        config: LinkConfig | None = None,
        *,
        mission: str = "default",
        clock: Clock | None = None,
        meter: Meter | None = None,
        seed: int = 0,
    ) -> None:
        self.config = config or LinkConfig()
        keys.sim_clock(mission)  # validates the mission name before opening anything
        self.mission = mission
        self.clock: Clock = clock or WallClock()
        self.meter = meter if meter is not None else Meter()
        self.seed = seed
        self._session = zenoh.open(_zenoh_config(self.config, mission))
        _OPEN_LINKS.add(self)
        self._endpoints: list[_Endpoint] = []
        self._publishers: dict[str, Any] = {}
        self._subs: list[Subscription] = []
        self._tokens: list[Any] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if self.config.pump_period_s > 0:
            self._thread = threading.Thread(target=self._pump_loop, name="link-pump", daemon=True)
            self._thread.start()

    # -- radio endpoints

    def robot_endpoint(
        self,
        robot_id: int,
        *,
        on_message: Callable[[Any], None] | None = None,
        follow_radio: bool = False,
    ) -> RobotEndpoint:
        """The radio of robot ``robot_id``. ``follow_radio``: apply grants from the simulator."""
        ep = RobotEndpoint(self, robot_id, on_message=on_message, follow_radio=follow_radio)
        with self._lock:
            self._endpoints.append(ep)
        return ep

    def gcs_endpoint(
        self,
        *,
        on_message: Callable[[int, Any], None] | None = None,
        follow_radio: bool = False,
    ) -> GcsEndpoint:
        """The GCS's radio to every robot. ``follow_radio``: apply grants from the simulator."""
        ep = GcsEndpoint(self, on_message=on_message, follow_radio=follow_radio)
        with self._lock:
            self._endpoints.append(ep)
        return ep

    # -- the driver contract over zenoh (not radio traffic)

    def remote_driver(self, robot_id: int) -> RemoteDriver:
        """A robot node's driver whose sensors are served by another process."""
        return RemoteDriver(self, robot_id)

    def driver_port(self, robot_id: int, on_command: Callable[[RobotCommand], None]) -> DriverPort:
        """The serving end for robot ``robot_id``'s :class:`RemoteDriver`."""
        return DriverPort(self, robot_id, on_command)

    def publish_grant(self, robot_id: int, grant: RadioGrant) -> None:
        """Publish a radio model's grant for ``robot_id`` (endpoints with ``follow_radio``)."""
        self.publish(keys.sim_radio(self.mission, robot_id), _GRANT_ENCODER.encode(grant))

    def pump(self) -> int:
        """Drain every channel's queue at the current mission time; returns packets sent."""
        now = self.clock.now()
        with self._lock:
            endpoints = list(self._endpoints)
        return sum(ep._pump(now) for ep in endpoints)

    def _pump_loop(self) -> None:
        period = self.config.pump_period_s
        while not self._stop.wait(period):
            try:
                self.pump()
            except Exception:  # keep pumping: one bad moment must not silence the radio
                log.exception("link pump failed")

    # -- unmetered traffic (sensor frames, clock, state for consoles and views)

    def publish(self, key: str, payload: bytes) -> None:
        """Publish bytes on ``key``, outside the radio (not metered, not rate-limited)."""
        pub = self._publishers.get(key)
        if pub is None:
            with self._lock:
                pub = self._publishers.get(key)
                if pub is None:
                    # blocking, never dropped: a sensor frame or clock tick lost under load
                    # would make the node's mission depend on the machine's speed
                    pub = self._session.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.BLOCK
                    )
                    self._publishers[key] = pub
        pub.put(payload)

    def subscribe(self, key: str, callback: Callable[[str, bytes], None]) -> Subscription:
        """Call ``callback(key, payload)`` for every publication matching ``key``.

        Exceptions from the callback are logged, never propagated into zenoh.
        """

        def handler(sample: Any) -> None:
            try:
                callback(str(sample.key_expr), sample.payload.to_bytes())
            except Exception:
                log.exception("subscriber callback for %s raised", key)

        sub = Subscription(self._session.declare_subscriber(key, handler))
        self._subs.append(sub)
        return sub

    # -- presence (zenoh liveliness): who serves what, while its process lives

    def declare_presence(self, key: str) -> None:
        """Say that this process serves ``key`` until it closes (a zenoh liveliness token;
        it vanishes with the process, cleanly closed or not)."""
        token = self._session.liveliness().declare_token(key)
        with self._lock:
            self._tokens.append(token)

    def present(self, key_expr: str, timeout_s: float = 1.0) -> list[str]:
        """The keys matching ``key_expr`` that some live process declared (sorted; waits at
        most ``timeout_s`` for the answers)."""
        found = set()
        for reply in self._session.liveliness().get(key_expr, timeout=timeout_s):
            if reply.ok is not None:
                found.add(str(reply.ok.key_expr))
        return sorted(found)

    def neighbours(self) -> int:
        """How many zenoh routers and peers this session is connected to now (0: whatever it
        was told to connect to has not answered)."""
        info = self._session.info
        return len(list(info.routers_zid())) + len(list(info.peers_zid()))

    def wait_reachable(self, timeout_s: float) -> bool:
        """Block until this session has a router or peer (True) or ``timeout_s`` passes: a
        peer told to connect to a host that cannot be reached opens anyway and keeps trying,
        so a process checks here before it waits for anyone."""
        deadline = time.monotonic() + timeout_s
        while self.neighbours() == 0:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)
        return True

    # -- lifetime

    def close(self) -> None:
        """Stop the pump, undeclare everything and close the session (idempotent; links still
        open when the program exits are closed then)."""
        _OPEN_LINKS.discard(self)
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with self._lock:
            endpoints, self._endpoints = self._endpoints, []
        for ep in endpoints:
            ep._close()
        with self._lock:
            tokens, self._tokens = self._tokens, []
        for token in tokens:
            token.undeclare()
        for sub in self._subs:
            sub.close()
        self._subs.clear()
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()
        if not self._session.is_closed():
            self._session.close()

    def __enter__(self) -> Link:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
