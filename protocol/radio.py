"""The radio: its configuration and the grants a radio model hands each robot's link.

MAGIC's robots shared one 115.2 kbps channel (paper 4.1, ``configs/radio/magic2010.yaml``).
A radio model (the simulator's, or a real radio's known rate) decides at run time how much of
it each robot gets in each direction and how lossy its link is; the link drains its queues at
exactly that rate, in mission time. A grant of 0 bps means disconnected: messages wait.
"""

from __future__ import annotations

import math

import msgspec

__all__ = ["RadioConfig", "RadioGrant"]


class RadioConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The shared radio (``configs/radio/*.yaml``).

    ``shared_capacity_bps``: total capacity divided among all transmitting robots and the GCS.
    ``framing_overhead_bytes``: bytes the radio adds to every message (addressing, length,
    CRC); metering and rate limiting count them on top of each message's payload.

    The simulator's radio model (``sim/radio_model.py``) uses the rest: a link's margin is
    ``10 * path_loss_exponent * log10(range_m / distance) - wall_loss_db * walls`` dB; it is
    connected while the margin is positive, at full quality from ``fade_margin_db`` up, with a
    message loss rising to ``max_loss`` as the margin falls to 0. Robots in relay mode forward
    for others (at most ``relay_max_hops`` hops). Each transmitting robot gets an equal share of
    the air time, ``uplink_fraction`` of it towards the GCS.
    """

    shared_capacity_bps: float = 115_200.0
    framing_overhead_bytes: int = 8
    range_m: float = 150.0
    path_loss_exponent: float = 2.5
    wall_loss_db: float = 6.0
    fade_margin_db: float = 10.0
    max_loss: float = 0.3
    uplink_fraction: float = 0.75
    relay_max_hops: int = 3

    def __post_init__(self) -> None:
        if not (math.isfinite(self.shared_capacity_bps) and self.shared_capacity_bps > 0):
            raise ValueError(f"shared_capacity_bps must be > 0, got {self.shared_capacity_bps}")
        if self.framing_overhead_bytes < 0:
            raise ValueError(
                f"framing_overhead_bytes must be >= 0, got {self.framing_overhead_bytes}"
            )
        for name in ("range_m", "path_loss_exponent", "fade_margin_db"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        if not (math.isfinite(self.wall_loss_db) and self.wall_loss_db >= 0):
            raise ValueError(f"wall_loss_db must be finite and >= 0, got {self.wall_loss_db}")
        if not 0.0 <= self.max_loss < 1.0:
            raise ValueError(f"max_loss must be in [0, 1), got {self.max_loss}")
        if not 0.0 < self.uplink_fraction < 1.0:
            raise ValueError(f"uplink_fraction must be in (0, 1), got {self.uplink_fraction}")
        if self.relay_max_hops < 1:
            raise ValueError(f"relay_max_hops must be >= 1, got {self.relay_max_hops}")


class RadioGrant(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """What the radio grants one robot now (published on ``magic/<mission>/sim/radio/<id>``).

    ``uplink_bps`` / ``downlink_bps``: rates in bits per second of mission time (0 while
    disconnected); ``loss``: probability that a message is lost in the air, in [0, 1).
    """

    uplink_bps: float
    downlink_bps: float
    loss: float = 0.0

    def __post_init__(self) -> None:
        for name in ("uplink_bps", "downlink_bps"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"RadioGrant.{name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.loss) and 0.0 <= self.loss < 1.0):
            raise ValueError(f"RadioGrant.loss must be in [0, 1), got {self.loss}")
