"""One robot's radio link as seen from one side: a sans-IO state machine.

The robot side sends on the uplink and receives the downlink; the GCS keeps one channel per
robot that sends on the downlink and receives the uplink. The channel does no I/O and reads no
clock: callers pass mission time ``now`` (seconds), hand it received bytes with
:meth:`RadioChannel.receive`, and take the bytes to put on the air from
:meth:`RadioChannel.poll`. :mod:`protocol.link` wires it to zenoh.

What it implements (DESIGN section 4, paper 4.1):

* **Priority queue** per direction: lower stream priority drains first (acks, task status,
  detections, pose nodes, fiducials, terrain grids, telemetry, images).
* **Rate** granted at run time in bits per second of *mission* time (a token bucket charged
  with frame bytes plus the radio's framing overhead; 0 bps = disconnected, messages wait).
  While the queue is backlogged, credit accumulates without a cap, so the achieved rate equals
  the grant however coarsely ``poll`` is called; when idle, credit is capped at ``burst_s``.
* **Reliable streams**: per-stream sequence numbers from 1; the receiver buffers out-of-order
  messages and delivers in order, exactly once, dropping duplicates. It acknowledges with a
  cumulative sequence number plus a selective bitmap of what arrived beyond the first gap.
  Acks are delayed so that their bytes stay a bounded fraction of the traffic they acknowledge
  (``ack_budget_frac``), and sent sooner after a duplicate (the sender missed an ack) or a
  gap, or when an arrival fills a gap (the sender is recovering: RFC 5681 4.2). The sender
  resends a message at once when ``fast_retransmit_after`` later ones were acknowledged,
  otherwise after a timeout estimated from measured round trips (RFC 6298, Karn's rule),
  doubling per attempt up to ``rto_max_s``; the backoff restarts when the link comes back up.
  A message known to be a hole (fast-retransmitted: the receiver holds later ones, so it acks
  the resend at once) is resent again after ``prompt_rto_s``, doubling, not after the delayed
  acks' timeout: at 30 % loss a lost resend (9 % of messages) held every later message of its
  stream at the GCS for the 9-12 s timeout; after a 60 s blackout the queue was empty in 1-4 s
  and the last grids arrived 10-25 s later (``magic bench chaos``, seed 7, per-second probe).
* **Latest-only streams** (telemetry): a newer message replaces a queued older one; never
  retransmitted; the receiver drops anything older than what it delivered.
* **Latest-reliable streams** (hazard updates): only the newest matters, but it is
  retransmitted until acknowledged or superseded.
* **Loss injection**: each message on the air is lost with the granted ``loss`` probability
  (seeded), for tests and for a radio model that reports loss.
* **Metering** of every byte on the air (:class:`protocol.meter.Meter`).

Nothing accepted is lost: :meth:`RadioChannel.send` refuses (raises :class:`LinkBackpressure`)
rather than dropping, once ``max_queue_bytes`` of reliable data is waiting.
"""

from __future__ import annotations

import heapq
import itertools
import logging
import math
import random
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from protocol.messages import (
    BROADCAST_ROBOT_ID,
    STREAMS,
    Ack,
    AckEntry,
    BroadcastAck,
    Direction,
    HazardUpdateCoded,
    ParameterUpdate,
    PoseNodeCoded,
    Reliability,
    RobotAck,
    StreamSpec,
    TerrainGridCoded,
    broadcast_stream_of,
    decode_frame,
    encode_frame,
    stream_of,
)
from protocol.meter import Meter
from protocol.radio import RadioGrant
from protocol.stream_coding import (
    PoseNodeCoder,
    TerrainGridCoder,
    decode_hazard_update,
    encode_hazard_update,
)
from protocol.wire import ProtocolError

__all__ = [
    "BroadcastChannel",
    "coalesced_ack",
    "ChannelStats",
    "LinkBackpressure",
    "Packet",
    "RadioChannel",
    "ReliabilityConfig",
]

#: Link parameters a :class:`ParameterUpdate` may set (consumed by the channel).
LINK_PARAMETERS = ("link.telemetry_period_s",)
_CODED_TYPES = (PoseNodeCoded, TerrainGridCoded, HazardUpdateCoded, BroadcastAck)
#: A robot reports its backlog again when it moved by this fraction (or this many bytes).
_BACKLOG_REPORT_FRAC = 0.25
_BACKLOG_REPORT_MIN_BYTES = 256

log = logging.getLogger(__name__)
_ACK_ENCODER = msgspec.msgpack.Encoder()


def _with_ack(payload: bytes, ack: Ack) -> bytes:
    """A frame's bytes with ``ack`` appended as its fourth element (see :class:`Frame`)."""
    if payload[0] != 0x93:  # msgpack fixarray of 3: [version, seq, message]
        raise ProtocolError("frame bytes do not start with a 3-element array")
    return b"\x94" + payload[1:] + _ACK_ENCODER.encode(ack)


#: Most sequence numbers beyond a gap that one ack reports (bytes of bitmap = this / 8).
SACK_MAX_BITS = 2048
#: A message is presumed lost once this many later ones were selectively acknowledged (the
#: radio does not reorder a stream, so one suffices; see ``ReliabilityConfig``).
FAST_RETRANSMIT_AFTER = 1
#: Reliable streams acknowledged promptly (``ack_prompt_delay_s``) and resent after
#: ``prompt_rto_s``, not after the delayed acks' ``ack_max_delay_s``: the tasks and their
#: reports, rare and small, on which a robot's work waits. A task lost on the air (30 % of
#: them at the chaos bench's loss) waited 9-12 s for its resend while the robot stood idle;
#: a lost SUCCEEDED report kept the planners from giving the robot its next goal as long.
#: Their acks cost a few bytes per task: no stream carrying bulk data is one of them.
PROMPT_STREAMS = frozenset({"task", "task_status"})
_OPPOSITE = {Direction.UP: Direction.DOWN, Direction.DOWN: Direction.UP}


class ReliabilityConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Tunables of the reliable streams and the queue (all times in mission seconds)."""

    #: Acks may use at most this fraction of the bytes they acknowledge ...
    ack_budget_frac: float = 0.03
    #: ... but wait no longer than this after the first unacknowledged arrival.
    #: (8 s: with coded pose nodes a robot's uplink is ~700 bps, and acks of every 5 s would
    #: cost more than 5% of it; acks also ride in data frames, so most never wait this long)
    ack_max_delay_s: float = 8.0
    #: How soon to ack after a duplicate or an out-of-order arrival.
    ack_prompt_delay_s: float = 0.1
    #: Retransmission timeout before any round trip was measured (> ack_max_delay_s).
    rto_initial_s: float = 10.0
    rto_min_s: float = 1.0
    rto_max_s: float = 12.0
    #: Retransmission timeout of the :data:`PROMPT_STREAMS` (acknowledged at once: a round
    #: trip is the air's delay plus ``ack_prompt_delay_s``), doubling per attempt up to
    #: ``rto_max_s``.
    prompt_rto_s: float = 1.0
    #: Treat the first message of every reliable stream as a :data:`PROMPT_STREAMS` one:
    #: acknowledged at once on arrival, resent after ``prompt_rto_s`` (doubling). Nothing
    #: follows it to reveal its loss and no round trip is measured yet (``rto_initial_s``):
    #: a robot's first pose node, which the GCS needs to place and task the robot, lost twice
    #: at 30 % loss left robot 2 standing untasked until 23 s (``magic bench chaos`` full,
    #: seed 9: node 0 made at 1.2 s, delivered at 23.3 s; its first task at 24 s, 2 s in the
    #: run without faults). On by default since measured on the clean quick missions with
    #: ``fast_retransmit_after`` 1 (small world, 300 mission-s, seeds 0 / 7 / 3 / 11, both at
    #: 239d5d7): ATE 0.177 / 0.185 / 0.214 / 0.095 m against 0.213 / 0.185 / 0.223 / 0.095
    #: with the old defaults (3, off), explored 0.933 / 0.958 / 0.958 / 0.912 against
    #: 0.939 / 0.958 / 0.958 / 0.912, occupancy F1 0.889 / 0.734 / 0.778 / 0.907 against
    #: 0.884 / 0.734 / 0.765 / 0.907.
    prompt_first_message: bool = True
    #: A message is presumed lost (and resent at once) once this many later messages of its
    #: stream, sent after it, were acknowledged (TCP's duplicate-ack threshold is 3; the
    #: radio does not reorder a stream's messages, so 1 suffices there). With 3, a lost
    #: pose node of a robot that moves slowly waits for three more nodes or for the 9-12 s
    #: timeout: at 30 % loss the median pose node reached the GCS 3.9 s after it was made in
    #: the first 120 s (0.1 s without loss; ``magic bench chaos`` full, seed 9). Loss only,
    #: seed 9, 120 mission-s: explored 0.491 with 3, 0.679 with 1 and
    #: ``prompt_first_message`` (0.73 without loss); the clean missions: see
    #: ``prompt_first_message``.
    fast_retransmit_after: int = FAST_RETRANSMIT_AFTER
    #: Messages a receiver buffers ahead of a gap, per stream; later ones are dropped unacked.
    receive_window: int = 4096
    #: Reliable bytes a sender holds (queued or unacknowledged) before refusing new messages.
    max_queue_bytes: int = 16 * 1024 * 1024
    #: Credit an idle queue may save up, in seconds of the granted rate.
    burst_s: float = 0.1

    def __post_init__(self) -> None:
        if not 0 < self.ack_budget_frac < 1:
            raise ValueError(f"ack_budget_frac must be in (0, 1), got {self.ack_budget_frac}")
        if not 0 < self.rto_min_s <= self.rto_max_s:
            raise ValueError("need 0 < rto_min_s <= rto_max_s")
        if not self.ack_prompt_delay_s < self.prompt_rto_s <= self.rto_max_s:
            raise ValueError(
                "need ack_prompt_delay_s < prompt_rto_s <= rto_max_s, or every prompt "
                "stream's message is sent twice"
            )
        if self.rto_initial_s <= self.ack_max_delay_s:
            raise ValueError(
                "rto_initial_s must exceed ack_max_delay_s, or every message is sent twice"
            )
        if self.fast_retransmit_after < 1:
            raise ValueError(
                f"fast_retransmit_after must be >= 1, got {self.fast_retransmit_after}"
            )
        if self.receive_window < 64:
            raise ValueError("receive_window must be >= 64")


class LinkBackpressure(RuntimeError):
    """The sender holds ``max_queue_bytes`` of reliable data already; try again later."""


@dataclass(frozen=True, slots=True)
class Packet:
    """Bytes to put on the air for ``stream`` (the key expression carries robot and stream)."""

    stream: str
    payload: bytes


@dataclass
class ChannelStats:
    sent: int = 0  # messages accepted by send()
    transmitted: int = 0  # messages put on the air, retransmissions included
    retransmitted: int = 0
    lost_in_air: int = 0
    delivered: int = 0
    duplicates_dropped: int = 0
    stale_dropped: int = 0  # latest-only messages older than one already delivered
    out_of_window_dropped: int = 0
    superseded: int = 0  # latest-only messages replaced in the queue before going out
    rejected: int = 0  # bytes that did not decode, or a message on the wrong stream
    acks_sent: int = 0
    acks_piggybacked: int = 0  # acks that rode inside a data frame instead of their own
    bytes_received: int = 0  # on-air bytes that arrived (payload + framing), broadcasts too
    broadcast_unheard: int = 0  # broadcasts this robot did not hear (out of range, lost)


@dataclass(slots=True)
class _Outgoing:
    spec: StreamSpec
    seq: int
    payload: bytes
    queued: bool = True
    alive: bool = True  # False once acked or superseded
    tx_count: int = 0
    last_sent_s: float = -math.inf
    deadline_s: float = math.inf  # retransmission deadline of the latest transmission
    fast_retx_of: int = 0  # the transmission (tx_count) already fast-retransmitted
    # a hole: the receiver acknowledged later messages (so it acks this one promptly); from
    # which transmission on (0: not known to be one)
    hole_from_tx: int = 0


@dataclass
class _SendStream:
    spec: StreamSpec
    next_seq: int = 1
    unacked: dict[int, _Outgoing] = field(default_factory=dict)  # reliable kinds only
    latest: _Outgoing | None = None
    period_s: float = 0.0  # latest-only streams: least time between two on the air
    next_allowed_s: float = -math.inf


@dataclass
class _RecvStream:
    spec: StreamSpec
    delivered_through: int = 0  # reliable: all <= this delivered; latest: newest delivered
    buffer: dict[int, Any] = field(default_factory=dict)


def _bitmap_seqs(bitmap: bytes, base: int) -> list[int]:
    """Sequence numbers set in a selective-ack bitmap (bit i = ``base + i``), ascending."""
    out = []
    for i, byte in enumerate(bitmap[: SACK_MAX_BITS // 8]):
        while byte:
            low = byte & -byte
            out.append(base + i * 8 + low.bit_length() - 1)
            byte ^= low
    return out


class RadioChannel:
    """The link between one robot and the GCS, from one side (see the module docstring).

    ``direction`` is the direction this side *sends*. ``seed`` drives loss injection.
    """

    def __init__(
        self,
        robot_id: int,
        direction: Direction,
        *,
        config: ReliabilityConfig | None = None,
        framing_overhead_bytes: int = 8,
        meter: Meter | None = None,
        grant_bps: float = math.inf,
        loss: float = 0.0,
        seed: int = 0,
    ) -> None:
        self.robot_id = robot_id
        self.direction = direction
        self.config = config or ReliabilityConfig()
        self.framing_bytes = framing_overhead_bytes
        self.meter = meter if meter is not None else Meter()
        self.stats = ChannelStats()
        self._rng = random.Random(seed)
        self._rate_bps = 0.0
        self._loss = 0.0
        self._credit_bytes = 0.0
        self._last_poll_s: float | None = None
        self._backlogged = False
        self._heap: list[tuple[int, int, int, _Outgoing]] = []
        self._heap_bytes = 0
        self._order = itertools.count()
        self._timers: list[tuple[float, int, _Outgoing]] = []
        self._held_bytes = 0
        self._send = {
            name: _SendStream(spec)
            for name, spec in STREAMS[direction].items()
            if not spec.broadcast
        }
        incoming = _OPPOSITE[direction]
        self._recv = {name: _RecvStream(spec) for name, spec in STREAMS[incoming].items()}
        # stream codings (protocol.stream_coding): the uplink's busiest streams
        coders: dict[str, Any] = {"pose_node": PoseNodeCoder, "terrain_grid": TerrainGridCoder}
        self._coders_out: dict[str, Any] = {n: c() for n, c in coders.items() if n in self._send}
        self._coders_in: dict[str, Any] = {n: c() for n, c in coders.items() if n in self._recv}
        #: Acks ride inside outgoing data frames when there are any (coalesced).
        self.piggyback_acks = True
        #: GCS side, coalesced acks: the endpoint collects due acks (take_ack) for one
        #: broadcast instead of this channel sending its own.
        self.external_acks = False
        #: GCS side: called with (robot_id, stream_id, through) for a robot's ack of a
        #: broadcast stream.
        self.on_broadcast_ack: Callable[[int, int, int], None] | None = None
        #: The peer's last reported backlog (bytes it still has queued): its demand.
        self.peer_backlog_bytes = 0
        self._reported_backlog = 0
        # robot side: whether broadcasts reach this robot, and their loss (own draws, so
        # the uplink's loss sequence does not depend on how many broadcasts went out)
        self._hears_broadcast = True
        self._broadcast_loss = 0.0
        self._broadcast_rng = random.Random(seed ^ 0x5BD1E995)
        self._recv_by_id = {s.spec.stream_id: s for s in self._recv.values()}
        self._send_by_id = {s.spec.stream_id: s for s in self._send.values()}
        self._broadcast_ids = {
            spec.stream_id: spec for spec in STREAMS[direction].values() if spec.broadcast
        }
        self._incoming = incoming
        # ack bookkeeping for the incoming reliable streams
        self._ack_dirty: set[int] = set()
        self._ack_bytes_since = 0
        self._ack_first_pending_s: float | None = None
        self._ack_prompt_s: float | None = None
        # round-trip estimate for the outgoing reliable streams
        self._srtt_s: float | None = None
        self._rttvar_s = 0.0
        self.set_grant(grant_bps, loss)

    # ------------------------------------------------------------------ configuration

    def set_grant(self, rate_bps: float, loss: float = 0.0) -> None:
        """Apply the radio's current grant for this side's sending direction."""
        if not (rate_bps >= 0 and not math.isnan(rate_bps)):
            raise ValueError(f"rate_bps must be >= 0, got {rate_bps}")
        if not 0.0 <= loss < 1.0:
            raise ValueError(f"loss must be in [0, 1), got {loss}")
        if self._rate_bps == 0 and rate_bps > 0:
            self._restart_backoff()
        self._rate_bps = float(rate_bps)
        self._loss = float(loss)
        if rate_bps == 0:
            self._credit_bytes = 0.0

    def apply_grant(self, grant: RadioGrant) -> None:
        """Apply a :class:`RadioGrant`, taking the rate of this side's sending direction.

        On the robot side the downlink rate also says whether broadcasts reach the robot (0:
        out of range, it hears none) and the loss applies to each broadcast it hears.
        """
        rate = grant.uplink_bps if self.direction is Direction.UP else grant.downlink_bps
        self.set_grant(rate, grant.loss)
        if self.direction is Direction.UP:
            self._hears_broadcast = grant.downlink_bps > 0
            self._broadcast_loss = grant.loss

    @property
    def rate_bps(self) -> float:
        return self._rate_bps

    @property
    def rto_s(self) -> float:
        """Current retransmission timeout before backoff."""
        cfg = self.config
        if self._srtt_s is None:
            return cfg.rto_initial_s
        # never below what the peer may hold an ack for (ack_max_delay_s): round trips are
        # mostly that wait, and a timeout inside it resends what merely waits for its ack
        floor = max(cfg.rto_min_s, cfg.ack_max_delay_s + cfg.rto_min_s)
        return min(max(self._srtt_s + 4.0 * self._rttvar_s, floor), cfg.rto_max_s)

    @property
    def held_bytes(self) -> int:
        """Reliable bytes queued or awaiting acknowledgement."""
        return self._held_bytes

    # ------------------------------------------------------------------ sending

    def send(self, message: Any) -> int:
        """Queue ``message`` on its stream; returns its sequence number.

        Raises :class:`ProtocolError` if the message does not belong to this direction and
        :class:`LinkBackpressure` if the reliable backlog is full.
        """
        spec = stream_of(self.direction, message)
        if spec.name == "ack":
            raise ProtocolError("acks are generated by the channel, not sent by callers")
        if isinstance(message, _CODED_TYPES):
            raise ProtocolError(f"{type(message).__name__} is made by the channel, not sent")
        st = self._send[spec.name]
        seq = st.next_seq
        rel = spec.reliability
        coder = self._coders_out.get(spec.name)
        if coder is not None:
            # refused before coding: the coder's reference must only see what is sent
            if rel is Reliability.RELIABLE and self._held_bytes >= self.config.max_queue_bytes:
                raise LinkBackpressure(
                    f"robot {self.robot_id} {self.direction.value}link holds "
                    f"{self._held_bytes} reliable bytes (max {self.config.max_queue_bytes})"
                )
            message = coder.encode(message)
        payload = encode_frame(seq, message)
        if rel is Reliability.RELIABLE:
            if coder is None and self._held_bytes + len(payload) > self.config.max_queue_bytes:
                raise LinkBackpressure(
                    f"robot {self.robot_id} {self.direction.value}link holds "
                    f"{self._held_bytes} reliable bytes (max {self.config.max_queue_bytes})"
                )
            self._held_bytes += len(payload)
        st.next_seq = seq + 1
        out = _Outgoing(spec, seq, payload)
        if rel is Reliability.RELIABLE:
            st.unacked[seq] = out
        else:
            if st.latest is not None and st.latest.alive:
                st.latest.alive = False
                if st.latest.queued or st.latest.tx_count == 0:
                    self.stats.superseded += 1
            st.latest = out
            if rel is Reliability.LATEST_RELIABLE:
                st.unacked = {seq: out}
        if st.period_s > 0 and rel is Reliability.LATEST:
            out.queued = False  # released by poll once the stream's period has passed
        else:
            self._enqueue(out)
        self.stats.sent += 1
        return seq

    def set_stream_period(self, stream: str, period_s: float) -> None:
        """Least mission time between two messages of latest-only ``stream`` on the air (0:
        no limit); the newest message waits, older ones are superseded (issue 16: telemetry
        at the rate the GCS sets, ``link.telemetry_period_s``)."""
        st = self._send.get(stream)
        if st is None or st.spec.reliability is not Reliability.LATEST or stream == "ack":
            raise ValueError(f"{stream!r} is not a latest-only {self.direction.value}link stream")
        if not (math.isfinite(period_s) and period_s >= 0):
            raise ValueError(f"period_s must be finite and >= 0, got {period_s}")
        st.period_s = float(period_s)
        item = st.latest
        if period_s == 0 and item is not None and item.alive and not item.queued:
            if item.tx_count == 0:
                self._enqueue(item)

    def _release_periodic(self, now: float) -> None:
        for st in self._send.values():
            item = st.latest
            if (
                st.period_s > 0
                and item is not None
                and item.alive
                and not item.queued
                and item.tx_count == 0
                and now >= st.next_allowed_s
            ):
                self._enqueue(item)

    def backlog_bytes(self) -> int:
        """Bytes queued for the air now (counted from queueing to leaving the queue; a
        message superseded or acknowledged while queued counts until its turn comes)."""
        return self._heap_bytes

    def _enqueue(self, out: _Outgoing) -> None:
        out.queued = True
        self._heap_bytes += len(out.payload)
        heapq.heappush(self._heap, (out.spec.priority, out.seq, next(self._order), out))

    def poll(self, now: float) -> list[Packet]:
        """Advance to mission time ``now``; return what goes on the air, highest priority first."""
        cfg = self.config
        if self._last_poll_s is not None and now > self._last_poll_s and self._rate_bps > 0:
            self._credit_bytes += (now - self._last_poll_s) * self._rate_bps / 8.0
            if not self._backlogged:
                self._credit_bytes = min(self._credit_bytes, self._rate_bps / 8.0 * cfg.burst_s)
        if self._last_poll_s is None or now > self._last_poll_s:
            self._last_poll_s = now
        self._expire_timers(now)
        self._release_periodic(now)
        out: list[Packet] = []
        self._drain(now, out)
        if not self.external_acks and self._maybe_queue_ack(now):
            self._drain(now, out)  # the ack had no data frame to ride in
        self._backlogged = any(entry[3].alive for entry in self._heap)
        return out

    def _drain(self, now: float, out: list[Packet]) -> None:
        heap = self._heap
        unlimited = math.isinf(self._rate_bps)
        while heap and self._rate_bps > 0 and (unlimited or self._credit_bytes > 0):
            item = heapq.heappop(heap)[3]
            self._heap_bytes -= len(item.payload)
            if not item.alive:
                continue
            item.queued = False
            payload = item.payload
            if item.spec.name != "ack" and self.piggyback_acks:
                ack = self._ride_along(now)
                if ack is not None:
                    payload = _with_ack(payload, ack)
            if not unlimited:
                self._credit_bytes -= len(payload) + self.framing_bytes
            self._transmit(item, now, out, payload)

    def _ride_along(self, now: float) -> Ack | None:
        """The ack to put inside the next data frame: every pending acknowledgement, and on
        the robot side the backlog when it changed enough to tell the GCS (its demand)."""
        backlog = 0
        report = False
        if self.direction is Direction.UP:
            backlog = self.backlog_bytes()
            last = self._reported_backlog
            report = abs(backlog - last) >= max(
                _BACKLOG_REPORT_MIN_BYTES, _BACKLOG_REPORT_FRAC * last
            ) or (backlog == 0 < last)
        if not self._ack_dirty and not report:
            return None
        ack = self._take_ack_now(backlog)
        self.stats.acks_piggybacked += 1
        return ack

    def _take_ack_now(self, backlog: int) -> Ack:
        entries = [self._ack_entry(self._recv_by_id[sid]) for sid in sorted(self._ack_dirty)]
        self._ack_dirty.clear()
        self._ack_bytes_since = 0
        self._ack_first_pending_s = None
        self._ack_prompt_s = None
        st = self._send["ack"]
        if st.latest is not None and st.latest.alive:
            st.latest.alive = False  # a standalone ack still queued is now redundant
        self._reported_backlog = backlog
        return Ack(entries, backlog)

    def _transmit(
        self, item: _Outgoing, now: float, out: list[Packet], payload: bytes | None = None
    ) -> None:
        spec = item.spec
        payload = item.payload if payload is None else payload
        lost = self._loss > 0 and self._rng.random() < self._loss
        retrans = item.tx_count > 0
        self.meter.record(
            self.robot_id,
            self.direction,
            spec.name,
            payload_bytes=len(payload),
            framing_bytes=self.framing_bytes,
            retransmission=retrans,
            lost=lost,
        )
        self.stats.transmitted += 1
        self.stats.retransmitted += retrans
        self.stats.lost_in_air += lost
        item.tx_count += 1
        item.last_sent_s = now
        if spec.reliability is not Reliability.LATEST:
            if item.hole_from_tx:
                # the receiver holds later messages: it acks this one at once (a gap filled),
                # so a lost resend shows after a round trip, not after a delayed ack's hold
                backoff = 2.0 ** max(0, item.tx_count - item.hole_from_tx)
                rto = self.config.prompt_rto_s
            else:
                backoff = 2.0 ** (item.tx_count - 1)
                prompt = spec.name in PROMPT_STREAMS or (
                    item.seq == 1 and self.config.prompt_first_message
                )
                rto = self.config.prompt_rto_s if prompt else self.rto_s
            item.deadline_s = now + min(rto * backoff, self.config.rto_max_s)
            heapq.heappush(self._timers, (item.deadline_s, next(self._order), item))
        else:
            st = self._send[spec.name]
            if st.period_s > 0:
                st.next_allowed_s = now + st.period_s
        if spec.name == "ack":
            self.stats.acks_sent += 1
        if not lost:
            out.append(Packet(spec.name, payload))

    def _expire_timers(self, now: float) -> None:
        timers = self._timers
        while timers and timers[0][0] <= now:
            deadline, _, item = heapq.heappop(timers)
            # entries of earlier transmissions are stale: only the latest deadline counts
            if item.alive and not item.queued and deadline == item.deadline_s:
                self._enqueue(item)

    def _restart_backoff(self) -> None:
        """The link came back up: retry unacknowledged messages now rather than after backoff."""
        for st in self._send.values():
            for item in st.unacked.values():
                if item.alive and not item.queued and item.tx_count > 0:
                    item.tx_count = 1
                    item.fast_retx_of = 0
                    item.hole_from_tx = 2 if item.hole_from_tx else 0
                    self._enqueue(item)

    # ------------------------------------------------------------------ receiving

    def receive(self, stream: str, data: bytes, now: float) -> list[Any]:
        """Take bytes that arrived on ``stream``; return the messages now deliverable, in order.

        Acks are consumed here. Raises :class:`ProtocolError` for bytes that do not decode or
        a message on the wrong stream (also counted in ``stats.rejected``).
        """
        rs = self._recv.get(stream)
        if rs is not None and rs.spec.broadcast and not self._hear_broadcast():
            self.stats.broadcast_unheard += 1
            return []
        self.stats.bytes_received += len(data) + self.framing_bytes
        try:
            if rs is None:
                raise ProtocolError(f"no {self._incoming.value}link stream named {stream!r}")
            frame = decode_frame(data, self._incoming)
            msg = frame.msg
            if type(msg) not in rs.spec.types:
                raise ProtocolError(
                    f"{type(msg).__name__} arrived on the {self._incoming.value}link "
                    f"stream {stream!r}"
                )
        except ProtocolError:
            self.stats.rejected += 1
            raise
        if frame.ack is not None:
            self._on_ack(frame.ack, now)
        spec = rs.spec
        if spec.name == "ack":
            self._on_ack(msg, now)
            return []
        seq = frame.seq
        rel = spec.reliability
        if rel is Reliability.RELIABLE:
            return self._consume(rs, self._receive_reliable(rs, seq, msg, len(data), now))
        # broadcasts: their acks wait for a data frame to ride in (or ack_max_delay_s)
        nbytes = 0 if spec.broadcast else len(data)
        if seq <= rs.delivered_through:
            self.stats.stale_dropped += 1
            if rel is Reliability.LATEST_RELIABLE:
                self._note_ack(spec.stream_id, nbytes, now, prompt=True)
            return []
        rs.delivered_through = seq
        if rel is Reliability.LATEST_RELIABLE:
            self._note_ack(spec.stream_id, nbytes, now, prompt=False)
        if isinstance(msg, BroadcastAck):
            for robot_ack in msg.acks:
                if robot_ack.robot_id == self.robot_id:
                    self._on_ack(Ack(robot_ack.entries), now)
            return []
        self.stats.delivered += 1
        return self._consume(rs, [msg])

    def _hear_broadcast(self) -> bool:
        if not self._hears_broadcast:
            return False
        loss = self._broadcast_loss
        return not (loss > 0 and self._broadcast_rng.random() < loss)

    def _consume(self, rs: _RecvStream, messages: list[Any]) -> list[Any]:
        """Delivered messages, in order: codings undone, link parameters applied here."""
        coder = self._coders_in.get(rs.spec.name)
        out = []
        for msg in messages:
            try:
                if coder is not None:
                    msg = coder.decode(msg)
                elif isinstance(msg, HazardUpdateCoded):
                    msg = decode_hazard_update(msg)
                elif isinstance(msg, ParameterUpdate) and msg.name.startswith("link."):
                    self._apply_link_parameter(msg)
                    continue
            except (ProtocolError, ValueError, TypeError) as err:
                # counted and skipped; the rest of the batch is still delivered
                self.stats.rejected += 1
                log.warning("robot %d %s: rejected message: %s", self.robot_id, rs.spec.name, err)
                continue
            out.append(msg)
        return out

    def _apply_link_parameter(self, msg: ParameterUpdate) -> None:
        if msg.name == "link.telemetry_period_s":
            value = msg.value
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"link.telemetry_period_s must be a number, got {value!r}")
            self.set_stream_period("telemetry", float(value))
            return
        raise ValueError(f"unknown link parameter {msg.name!r} (known: {LINK_PARAMETERS})")

    def _receive_reliable(
        self, rs: _RecvStream, seq: int, msg: Any, nbytes: int, now: float
    ) -> list[Any]:
        sid = rs.spec.stream_id
        if seq <= rs.delivered_through or seq in rs.buffer:
            self.stats.duplicates_dropped += 1
            self._note_ack(sid, nbytes, now, prompt=True)
            return []
        if seq > rs.delivered_through + self.config.receive_window:
            self.stats.out_of_window_dropped += 1
            return []
        if seq != rs.delivered_through + 1:
            rs.buffer[seq] = msg
            self._note_ack(sid, nbytes, now, prompt=True)
            return []
        delivered = [msg]
        nxt = seq + 1
        buf = rs.buffer
        filled = bool(buf)  # a gap filled: the sender is recovering, tell it at once
        while nxt in buf:
            delivered.append(buf.pop(nxt))
            nxt += 1
        rs.delivered_through = nxt - 1
        self.stats.delivered += len(delivered)
        prompt = rs.spec.name in PROMPT_STREAMS or (seq == 1 and self.config.prompt_first_message)
        self._note_ack(sid, nbytes, now, prompt=filled or prompt)
        return delivered

    def _note_ack(self, stream_id: int, nbytes: int, now: float, *, prompt: bool) -> None:
        self._ack_dirty.add(stream_id)
        self._ack_bytes_since += nbytes + self.framing_bytes
        if self._ack_first_pending_s is None:
            self._ack_first_pending_s = now
        if prompt and self._ack_prompt_s is None:
            self._ack_prompt_s = now + self.config.ack_prompt_delay_s

    def _ack_entry(self, rs: _RecvStream) -> AckEntry:
        if not rs.buffer:
            return AckEntry(rs.spec.stream_id, rs.delivered_through)
        base = rs.delivered_through + 2
        bits = [s - base for s in rs.buffer if 0 <= s - base < SACK_MAX_BITS]
        bitmap = bytearray(max(bits) // 8 + 1)
        for b in bits:
            bitmap[b >> 3] |= 1 << (b & 7)
        return AckEntry(rs.spec.stream_id, rs.delivered_through, bytes(bitmap))

    def ack_due(self, now: float, *, coalesced: bool = False, shared_bytes: float = 0.0) -> bool:
        """Whether pending acknowledgements should go now: their bytes are within
        ``ack_budget_frac`` of what they acknowledge, or they waited ``ack_max_delay_s``, or
        a duplicate or a gap asks for a prompt one. ``coalesced``: their size is what they
        add to a :class:`BroadcastAck` plus ``shared_bytes``, their share of its frame and
        framing."""
        if not self._ack_dirty:
            return False
        cfg = self.config
        entries = [self._ack_entry(self._recv_by_id[sid]) for sid in sorted(self._ack_dirty)]
        if coalesced:
            ack_size = len(_ACK_ENCODER.encode(RobotAck(self.robot_id, entries))) + shared_bytes
        else:
            ack_size = len(encode_frame(0, Ack(entries))) + self.framing_bytes
        assert self._ack_first_pending_s is not None
        return (
            self._ack_bytes_since * cfg.ack_budget_frac >= ack_size
            or now - self._ack_first_pending_s >= cfg.ack_max_delay_s
            or (self._ack_prompt_s is not None and now >= self._ack_prompt_s)
        )

    def take_ack(self) -> list[AckEntry] | None:
        """Coalesced acks (GCS side, ``external_acks``): the pending entries, now counted as
        sent by the caller's broadcast; None when nothing is pending."""
        if not self._ack_dirty:
            return None
        return self._take_ack_now(0).entries

    def _maybe_queue_ack(self, now: float) -> bool:
        if not self.ack_due(now):
            return False
        backlog = self.backlog_bytes() if self.direction is Direction.UP else 0
        ack = self._take_ack_now(backlog)
        st = self._send["ack"]
        item = _Outgoing(st.spec, 0, encode_frame(0, ack))
        st.latest = item
        self._enqueue(item)
        return True

    def _on_ack(self, ack: Ack, now: float) -> None:
        self.peer_backlog_bytes = ack.backlog_bytes
        for entry in ack.entries:
            st = self._send_by_id.get(entry.stream_id)
            if st is None:
                spec = self._broadcast_ids.get(entry.stream_id)
                if spec is not None and self.on_broadcast_ack is not None:
                    self.on_broadcast_ack(self.robot_id, entry.stream_id, entry.through)
                continue
            if st.spec.reliability is Reliability.LATEST:
                continue
            acked = [s for s in st.unacked if s <= entry.through]
            sacked = _bitmap_seqs(entry.received, entry.through + 2)
            acked += [s for s in sacked if s in st.unacked]
            newest_sent_s = -math.inf
            for s in acked:
                item = st.unacked.pop(s)
                if item.tx_count == 1:  # Karn: only unambiguous samples
                    self._rtt_sample(now - item.last_sent_s)
                newest_sent_s = max(newest_sent_s, item.last_sent_s)
                item.alive = False
                if st.spec.reliability is Reliability.RELIABLE:
                    self._held_bytes -= len(item.payload)
            if len(sacked) >= self.config.fast_retransmit_after:
                self._fast_retransmit(st, sacked, newest_sent_s)

    def _fast_retransmit(self, st: _SendStream, sacked: list[int], newest_sent_s: float) -> None:
        """Resend at once what later acknowledged messages show was lost (SACK recovery).

        A message counts as lost when ``fast_retransmit_after`` messages with higher sequence
        numbers were received and it was sent before them; each transmission is fast-resent at
        most once, after that the timeout and its backoff rule.
        """
        threshold = sacked[-self.config.fast_retransmit_after]
        for seq, item in st.unacked.items():
            if seq >= threshold:
                break
            if (
                not item.queued
                and item.tx_count > 0
                and item.fast_retx_of != item.tx_count
                and item.last_sent_s <= newest_sent_s
            ):
                item.fast_retx_of = item.tx_count
                if not item.hole_from_tx:
                    item.hole_from_tx = item.tx_count + 1
                self._enqueue(item)

    def _rtt_sample(self, rtt_s: float) -> None:
        if rtt_s < 0:
            return
        if self._srtt_s is None:
            self._srtt_s = rtt_s
            self._rttvar_s = rtt_s / 2.0
        else:
            self._rttvar_s = 0.75 * self._rttvar_s + 0.25 * abs(self._srtt_s - rtt_s)
            self._srtt_s = 0.875 * self._srtt_s + 0.125 * rtt_s

    # ------------------------------------------------------------------ inspection

    def pending(self) -> int:
        """Messages queued for the air plus reliable messages awaiting acknowledgement."""
        queued = sum(1 for e in self._heap if e[3].alive)
        waiting = sum(
            1 for st in self._send.values() for it in st.unacked.values() if not it.queued
        )
        return queued + waiting

    def unacked_seqs(self, stream: str) -> list[int]:
        """Sequence numbers sent on ``stream`` not yet acknowledged (still on their way),
        ascending; [] for a stream this side does not send on."""
        st = self._send.get(stream)
        return [] if st is None else sorted(st.unacked)

    def next_seq(self, stream: str) -> int:
        """The sequence number the next message sent on ``stream`` gets."""
        return self._send[stream].next_seq

    def receive_state(self, stream: str) -> tuple[int, list[int]]:
        """``(delivered in order through, sequence numbers held behind a gap)`` of the
        received ``stream`` (the held ones selectively acknowledged, not yet delivered)."""
        rs = self._recv[stream]
        return rs.delivered_through, sorted(rs.buffer)

    # ------------------------------------------------------------------ restoring
    # A GCS resumed from its journal (:func:`gcs.node.restore_link_state`) continues each
    # robot's streams where the one that was killed left them: nothing twice, nothing lost.

    def restore_received(
        self, stream: str, delivered_through: int, held: dict[int, Any] | None = None
    ) -> None:
        """The received ``stream`` delivered in order through ``delivered_through`` (later
        ones are new, earlier ones duplicates), with ``held`` (sequence number -> message)
        back behind the gap, delivered when it is filled."""
        if delivered_through < 0:
            raise ValueError(f"{stream}: delivered_through must be >= 0, got {delivered_through}")
        rs = self._recv[stream]
        rs.delivered_through = int(delivered_through)
        for seq, msg in (held or {}).items():
            if seq > rs.delivered_through:
                rs.buffer[int(seq)] = msg

    def restore_next_seq(self, stream: str, next_seq: int) -> None:
        """Number the next message sent on ``stream`` ``next_seq`` (>= 1)."""
        if next_seq < 1:
            raise ValueError(f"{stream}: next_seq must be >= 1, got {next_seq}")
        self._send[stream].next_seq = int(next_seq)

    def prime_decoder(self, stream: str, message: Any) -> None:
        """Give the received ``stream``'s decoder (coded pose nodes, grids) ``message`` as
        decoded before, its reference for what follows; a stream without one ignores it."""
        coder = self._coders_in.get(stream)
        if coder is not None:
            coder.decode(message)


class BroadcastChannel:
    """The GCS's broadcast to every robot in range (paper 4.1: hazards and every robot's
    ``map_from_odom`` go out once, not once per robot), as a sans-IO state machine.

    One queue drained at its own granted rate (a token bucket like :class:`RadioChannel`'s),
    metered once under :data:`~protocol.messages.BROADCAST_ROBOT_ID`. Reliability follows the
    stream: ``ack_broadcast`` (coalesced acknowledgements) is latest-only, never resent;
    ``hazard_broadcast`` is latest-reliable: each robot acknowledges the broadcast's sequence
    number in its ordinary uplink ack (:meth:`on_robot_ack`), and the broadcast is resent
    after a timeout while a robot in range (the ``in_range`` set given to :meth:`poll`) has
    not acknowledged it, unless a newer one superseded it. Robots decide themselves whether
    they heard it (range, loss: :meth:`RadioChannel.receive`).
    """

    def __init__(
        self,
        *,
        config: ReliabilityConfig | None = None,
        framing_overhead_bytes: int = 8,
        meter: Meter | None = None,
        grant_bps: float = math.inf,
    ) -> None:
        self.config = config or ReliabilityConfig()
        self.framing_bytes = framing_overhead_bytes
        self.meter = meter if meter is not None else Meter()
        self.stats = ChannelStats()
        self._rate_bps = 0.0
        self._credit_bytes = 0.0
        self._last_poll_s: float | None = None
        self._backlogged = False
        self._heap: list[tuple[int, int, int, _Outgoing]] = []
        self._order = itertools.count()
        self._timers: list[tuple[float, int, _Outgoing]] = []
        specs = [spec for spec in STREAMS[Direction.DOWN].values() if spec.broadcast]
        self._send = {spec.name: _SendStream(spec) for spec in specs}
        self._by_id = {spec.stream_id: self._send[spec.name] for spec in specs}
        #: per stream id: robot -> highest sequence number it acknowledged
        self._acked: dict[int, dict[int, int]] = {spec.stream_id: {} for spec in specs}
        self.set_grant(grant_bps)

    def set_grant(self, rate_bps: float) -> None:
        """The broadcast's share of the shared channel, bits per mission second."""
        if not (rate_bps >= 0 and not math.isnan(rate_bps)):
            raise ValueError(f"rate_bps must be >= 0, got {rate_bps}")
        self._rate_bps = float(rate_bps)
        if rate_bps == 0:
            self._credit_bytes = 0.0

    @property
    def rate_bps(self) -> float:
        return self._rate_bps

    def send(self, message: Any) -> int:
        """Queue ``message`` for every robot; returns its broadcast sequence number."""
        spec = broadcast_stream_of(message)
        if isinstance(message, HazardUpdateCoded):
            raise ProtocolError("HazardUpdateCoded is made by the channel, not sent")
        st = self._send[spec.name]
        seq = st.next_seq
        coded = encode_hazard_update(message) if spec.name == "hazard_broadcast" else message
        out = _Outgoing(spec, seq, encode_frame(seq, coded))
        st.next_seq = seq + 1
        if st.latest is not None and st.latest.alive:
            st.latest.alive = False
            if st.latest.tx_count == 0:
                self.stats.superseded += 1
        st.latest = out
        heapq.heappush(self._heap, (spec.priority, seq, next(self._order), out))
        self.stats.sent += 1
        return seq

    def queued(self, stream: str) -> bool:
        """Whether the newest message of ``stream`` still waits for the air."""
        item = self._send[stream].latest
        return item is not None and item.alive and item.queued

    def next_seq(self, stream: str) -> int:
        """The sequence number the next broadcast on ``stream`` gets."""
        return self._send[stream].next_seq

    def restore_next_seq(self, stream: str, next_seq: int) -> None:
        """Number the next broadcast on ``stream`` ``next_seq`` (a resumed GCS, >= 1)."""
        if next_seq < 1:
            raise ValueError(f"{stream}: next_seq must be >= 1, got {next_seq}")
        self._send[stream].next_seq = int(next_seq)

    def on_robot_ack(self, robot_id: int, stream_id: int, through: int) -> None:
        """Robot ``robot_id`` acknowledged broadcast stream ``stream_id`` up to ``through``."""
        acked = self._acked.get(stream_id)
        if acked is not None and through > acked.get(robot_id, 0):
            acked[robot_id] = through

    def acknowledged_by(self, stream: str, seq: int) -> list[int]:
        """Robots that acknowledged ``stream``'s message ``seq`` (or a newer one), sorted."""
        sid = self._send[stream].spec.stream_id
        return sorted(r for r, s in self._acked[sid].items() if s >= seq)

    def poll(self, now: float, in_range: set[int] | frozenset[int]) -> list[Packet]:
        """Advance to mission time ``now``; return what goes on the air. A reliable broadcast
        whose timeout passed is resent if a robot of ``in_range`` did not acknowledge it."""
        if self._last_poll_s is not None and now > self._last_poll_s and self._rate_bps > 0:
            self._credit_bytes += (now - self._last_poll_s) * self._rate_bps / 8.0
            if not self._backlogged:
                burst = self._rate_bps / 8.0 * self.config.burst_s
                self._credit_bytes = min(self._credit_bytes, burst)
        if self._last_poll_s is None or now > self._last_poll_s:
            self._last_poll_s = now
        timers = self._timers
        while timers and timers[0][0] <= now:
            deadline, _, item = heapq.heappop(timers)
            if not (item.alive and not item.queued and deadline == item.deadline_s):
                continue
            acked = self._acked[item.spec.stream_id]
            if all(acked.get(r, 0) >= item.seq for r in in_range):
                item.alive = False  # everyone in range has it
                continue
            heapq.heappush(self._heap, (item.spec.priority, item.seq, next(self._order), item))
            item.queued = True
        out: list[Packet] = []
        heap = self._heap
        unlimited = math.isinf(self._rate_bps)
        while heap and self._rate_bps > 0 and (unlimited or self._credit_bytes > 0):
            item = heapq.heappop(heap)[3]
            if not item.alive:
                continue
            item.queued = False
            if not unlimited:
                self._credit_bytes -= len(item.payload) + self.framing_bytes
            retrans = item.tx_count > 0
            self.meter.record(
                BROADCAST_ROBOT_ID,
                Direction.DOWN,
                item.spec.name,
                payload_bytes=len(item.payload),
                framing_bytes=self.framing_bytes,
                retransmission=retrans,
                lost=False,
            )
            self.stats.transmitted += 1
            self.stats.retransmitted += retrans
            item.tx_count += 1
            item.last_sent_s = now
            if item.spec.reliability is Reliability.LATEST_RELIABLE:
                cfg = self.config
                # robots may hold their ack for ack_max_delay_s waiting for a frame to ride in
                rto = max(cfg.rto_initial_s, cfg.ack_max_delay_s + cfg.rto_min_s)
                item.deadline_s = now + min(rto * 2.0 ** (item.tx_count - 1), 4 * rto)
                heapq.heappush(timers, (item.deadline_s, next(self._order), item))
            else:
                item.alive = False
            out.append(Packet(item.spec.name, item.payload))
        self._backlogged = any(entry[3].alive for entry in heap)
        return out


def coalesced_ack(channels: dict[int, RadioChannel], now: float) -> BroadcastAck | None:
    """One :class:`BroadcastAck` for the channels whose pending acks are due by their size
    inside it (:meth:`RadioChannel.ack_due` ``coalesced``: the budget rule then costs each
    robot's entry and its share of the broadcast's frame and framing); None when none is
    due. Their pending acks are taken (they count as sent)."""
    pending = [ch for ch in channels.values() if ch._ack_dirty]
    if not pending:
        return None
    # the broadcast's own frame and framing, shared by the robots with acks pending: a lone
    # robot's acks keep within the ack budget as they did on a stream of their own
    frame_bytes = len(encode_frame(0, BroadcastAck([]))) + pending[0].framing_bytes
    shared = frame_bytes / len(pending)
    acks = []
    for rid in sorted(channels):
        ch = channels[rid]
        if ch.ack_due(now, coalesced=True, shared_bytes=shared):
            entries = ch.take_ack()
            if entries:
                acks.append(RobotAck(rid, entries))
    return BroadcastAck(acks) if acks else None
