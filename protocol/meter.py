"""Radio metering: every byte that crosses the radio, by robot, direction and stream.

Counted by the sender at the moment a message goes on the air: its encoded frame plus the
radio's per-message framing overhead (:attr:`protocol.radio.RadioConfig.framing_overhead_bytes`).
Messages lost in the air still used the radio, so they count too (and are also counted as
lost). Sensor frames between the simulator and a robot node are not radio traffic.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

from protocol.messages import Direction

__all__ = ["Meter", "StreamCount"]


@dataclass
class StreamCount:
    """Totals for one (robot, direction, stream)."""

    messages: int = 0
    bytes: int = 0
    payload_bytes: int = 0  # bytes of encoded frames, without the radio's framing
    retransmissions: int = 0
    lost: int = 0


@dataclass
class Meter:
    """Thread-safe radio byte counters; one per process, shared by all of its channels."""

    _counts: dict[tuple[int, Direction, str], StreamCount] = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def record(
        self,
        robot_id: int,
        direction: Direction,
        stream: str,
        *,
        payload_bytes: int,
        framing_bytes: int,
        retransmission: bool,
        lost: bool,
    ) -> None:
        key = (robot_id, direction, stream)
        with self._lock:
            c = self._counts.get(key)
            if c is None:
                c = self._counts[key] = StreamCount()
            c.messages += 1
            c.payload_bytes += payload_bytes
            c.bytes += payload_bytes + framing_bytes
            c.retransmissions += retransmission
            c.lost += lost

    def snapshot(self) -> dict[tuple[int, Direction, str], StreamCount]:
        """A copy of every counter, keyed by ``(robot_id, direction, stream)``."""
        with self._lock:
            return {k: StreamCount(**vars(v)) for k, v in self._counts.items()}

    def total_bytes(
        self,
        *,
        robot_id: int | None = None,
        direction: Direction | None = None,
        stream: str | None = None,
    ) -> int:
        """Sum of on-air bytes over the counters matching every given filter."""
        with self._lock:
            return sum(
                c.bytes
                for (r, d, s), c in self._counts.items()
                if (robot_id is None or r == robot_id)
                and (direction is None or d == direction)
                and (stream is None or s == stream)
            )
