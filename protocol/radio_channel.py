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
  gap. The sender resends a message at once when ``FAST_RETRANSMIT_AFTER`` later ones were
  acknowledged, otherwise after a timeout estimated from measured round trips (RFC 6298,
  Karn's rule), doubling per attempt up to ``rto_max_s``; the backoff restarts when the link
  comes back up.
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
import math
import random
from dataclasses import dataclass, field
from typing import Any

import msgspec

from protocol.messages import (
    STREAMS,
    Ack,
    AckEntry,
    Direction,
    Reliability,
    StreamSpec,
    decode_frame,
    encode_frame,
    stream_of,
)
from protocol.meter import Meter
from protocol.radio import RadioGrant
from protocol.wire import ProtocolError

__all__ = ["ChannelStats", "LinkBackpressure", "Packet", "RadioChannel", "ReliabilityConfig"]

#: Most sequence numbers beyond a gap that one ack reports (bytes of bitmap = this / 8).
SACK_MAX_BITS = 2048
#: A message is presumed lost once this many later ones were selectively acknowledged.
FAST_RETRANSMIT_AFTER = 3
_OPPOSITE = {Direction.UP: Direction.DOWN, Direction.DOWN: Direction.UP}


class ReliabilityConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Tunables of the reliable streams and the queue (all times in mission seconds)."""

    #: Acks may use at most this fraction of the bytes they acknowledge ...
    ack_budget_frac: float = 0.03
    #: ... but wait no longer than this after the first unacknowledged arrival.
    ack_max_delay_s: float = 5.0
    #: How soon to ack after a duplicate or an out-of-order arrival.
    ack_prompt_delay_s: float = 0.1
    #: Retransmission timeout before any round trip was measured (> ack_max_delay_s).
    rto_initial_s: float = 6.0
    rto_min_s: float = 1.0
    rto_max_s: float = 8.0
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
        if self.rto_initial_s <= self.ack_max_delay_s:
            raise ValueError(
                "rto_initial_s must exceed ack_max_delay_s, or every message is sent twice"
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


@dataclass
class _SendStream:
    spec: StreamSpec
    next_seq: int = 1
    unacked: dict[int, _Outgoing] = field(default_factory=dict)  # reliable kinds only
    latest: _Outgoing | None = None


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
        self._order = itertools.count()
        self._timers: list[tuple[float, int, _Outgoing]] = []
        self._held_bytes = 0
        self._send = {name: _SendStream(spec) for name, spec in STREAMS[direction].items()}
        incoming = _OPPOSITE[direction]
        self._recv = {name: _RecvStream(spec) for name, spec in STREAMS[incoming].items()}
        self._recv_by_id = {s.spec.stream_id: s for s in self._recv.values()}
        self._send_by_id = {s.spec.stream_id: s for s in self._send.values()}
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
        """Apply a :class:`RadioGrant`, taking the rate of this side's sending direction."""
        rate = grant.uplink_bps if self.direction is Direction.UP else grant.downlink_bps
        self.set_grant(rate, grant.loss)

    @property
    def rate_bps(self) -> float:
        return self._rate_bps

    @property
    def rto_s(self) -> float:
        """Current retransmission timeout before backoff."""
        cfg = self.config
        if self._srtt_s is None:
            return cfg.rto_initial_s
        return min(max(self._srtt_s + 4.0 * self._rttvar_s, cfg.rto_min_s), cfg.rto_max_s)

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
        st = self._send[spec.name]
        seq = st.next_seq
        payload = encode_frame(seq, message)
        rel = spec.reliability
        if rel is Reliability.RELIABLE:
            if self._held_bytes + len(payload) > self.config.max_queue_bytes:
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
                if st.latest.queued:
                    self.stats.superseded += 1
            st.latest = out
            if rel is Reliability.LATEST_RELIABLE:
                st.unacked = {seq: out}
        self._enqueue(out)
        self.stats.sent += 1
        return seq

    def _enqueue(self, out: _Outgoing) -> None:
        out.queued = True
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
        self._maybe_queue_ack(now)
        out: list[Packet] = []
        heap = self._heap
        unlimited = math.isinf(self._rate_bps)
        while heap and self._rate_bps > 0 and (unlimited or self._credit_bytes > 0):
            item = heapq.heappop(heap)[3]
            if not item.alive:
                continue
            item.queued = False
            size = len(item.payload)
            if not unlimited:
                self._credit_bytes -= size + self.framing_bytes
            self._transmit(item, now, out)
        self._backlogged = any(entry[3].alive for entry in heap)
        return out

    def _transmit(self, item: _Outgoing, now: float, out: list[Packet]) -> None:
        spec = item.spec
        lost = self._loss > 0 and self._rng.random() < self._loss
        retrans = item.tx_count > 0
        self.meter.record(
            self.robot_id,
            self.direction,
            spec.name,
            payload_bytes=len(item.payload),
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
            backoff = 2.0 ** (item.tx_count - 1)
            item.deadline_s = now + min(self.rto_s * backoff, self.config.rto_max_s)
            heapq.heappush(self._timers, (item.deadline_s, next(self._order), item))
        if spec.name == "ack":
            self.stats.acks_sent += 1
        if not lost:
            out.append(Packet(spec.name, item.payload))

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
                    self._enqueue(item)

    # ------------------------------------------------------------------ receiving

    def receive(self, stream: str, data: bytes, now: float) -> list[Any]:
        """Take bytes that arrived on ``stream``; return the messages now deliverable, in order.

        Acks are consumed here. Raises :class:`ProtocolError` for bytes that do not decode or
        a message on the wrong stream (also counted in ``stats.rejected``).
        """
        rs = self._recv.get(stream)
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
        spec = rs.spec
        if spec.name == "ack":
            self._on_ack(msg, now)
            return []
        seq = frame.seq
        rel = spec.reliability
        if rel is Reliability.RELIABLE:
            return self._receive_reliable(rs, seq, msg, len(data), now)
        if seq <= rs.delivered_through:
            self.stats.stale_dropped += 1
            if rel is Reliability.LATEST_RELIABLE:
                self._note_ack(spec.stream_id, len(data), now, prompt=True)
            return []
        rs.delivered_through = seq
        if rel is Reliability.LATEST_RELIABLE:
            self._note_ack(spec.stream_id, len(data), now, prompt=False)
        self.stats.delivered += 1
        return [msg]

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
        while nxt in buf:
            delivered.append(buf.pop(nxt))
            nxt += 1
        rs.delivered_through = nxt - 1
        self.stats.delivered += len(delivered)
        self._note_ack(sid, nbytes, now, prompt=False)
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

    def _maybe_queue_ack(self, now: float) -> None:
        if not self._ack_dirty:
            return
        cfg = self.config
        entries = [self._ack_entry(self._recv_by_id[sid]) for sid in sorted(self._ack_dirty)]
        ack = Ack(entries)
        ack_size = len(encode_frame(0, ack)) + self.framing_bytes
        assert self._ack_first_pending_s is not None
        due = (
            self._ack_bytes_since * cfg.ack_budget_frac >= ack_size
            or now - self._ack_first_pending_s >= cfg.ack_max_delay_s
            or (self._ack_prompt_s is not None and now >= self._ack_prompt_s)
        )
        if not due:
            return
        st = self._send["ack"]
        if st.latest is not None and st.latest.alive:
            st.latest.alive = False
        item = _Outgoing(st.spec, 0, encode_frame(0, ack))
        st.latest = item
        self._enqueue(item)
        self._ack_dirty.clear()
        self._ack_bytes_since = 0
        self._ack_first_pending_s = None
        self._ack_prompt_s = None

    def _on_ack(self, ack: Ack, now: float) -> None:
        for entry in ack.entries:
            st = self._send_by_id.get(entry.stream_id)
            if st is None or st.spec.reliability is Reliability.LATEST:
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
            if len(sacked) >= FAST_RETRANSMIT_AFTER:
                self._fast_retransmit(st, sacked, newest_sent_s)

    def _fast_retransmit(self, st: _SendStream, sacked: list[int], newest_sent_s: float) -> None:
        """Resend at once what later acknowledged messages show was lost (SACK recovery).

        A message counts as lost when ``FAST_RETRANSMIT_AFTER`` messages with higher sequence
        numbers were received and it was sent before them; each transmission is fast-resent at
        most once, after that the timeout and its backoff rule.
        """
        threshold = sacked[-FAST_RETRANSMIT_AFTER]
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
