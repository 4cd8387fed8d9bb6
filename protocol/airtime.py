"""Air time that follows need: the GCS's shares of the one shared radio channel (issue 16).

MAGIC's radio was the binding constraint of the team (paper 4.1, 8). An equal split gives an
idle robot the same air time as one with a backlog of grids; here the GCS grants each robot
its demand, weighted by priority, bounded by the shared capacity:

* a robot's **demand** is the rate it has been using (bytes that arrived, smoothed) plus what
  it reports still queued (``Ack.backlog_bytes``, :meth:`protocol.link.GcsEndpoint.demand`)
  spread over ``drain_s``, with ``headroom`` on top so a steady robot is never the bottleneck;
* **weighted water-filling** (max-min fair with weights): every robot gets its demand if the
  capacity allows; otherwise robots are served in order of demand per weight, the rest share
  what is left in proportion to their weights. A robot never gets more than its link allows
  (``link_max_bps``: range, walls, relays from a radio model) nor less than ``floor_bps``
  while connected (acks and telemetry must get through). What demand leaves unused is handed
  out by weight too, so a burst starts draining before the next allocation.

The sum of grants never exceeds the capacity given. Pure: numbers in, numbers out.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import msgspec

__all__ = ["AirtimeConfig", "AirtimeScheduler", "allocate_airtime"]


def allocate_airtime(
    demand_bps: Mapping[int, float],
    *,
    capacity_bps: float,
    weights: Mapping[int, float] | None = None,
    link_max_bps: Mapping[int, float] | None = None,
    floor_bps: float = 0.0,
) -> dict[int, float]:
    """Grants (bps) for every robot of ``demand_bps`` (module docstring).

    ``weights`` (default 1): priority, larger gets more when the capacity is short.
    ``link_max_bps``: the most each robot's link can carry (0: disconnected, gets 0).
    """
    if not (math.isfinite(capacity_bps) and capacity_bps >= 0):
        raise ValueError(f"capacity_bps must be finite and >= 0, got {capacity_bps}")
    robots = sorted(demand_bps)
    w = {r: float((weights or {}).get(r, 1.0)) for r in robots}
    for r, v in w.items():
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"weight of robot {r} must be finite and > 0, got {v}")
    cap = {r: float((link_max_bps or {}).get(r, math.inf)) for r in robots}
    live = [r for r in robots if cap[r] > 0]
    grant = dict.fromkeys(robots, 0.0)
    if not live:
        return grant
    floor = min(floor_bps, capacity_bps / len(live))
    budget = capacity_bps
    for r in live:
        grant[r] = min(floor, cap[r])
        budget -= grant[r]
    need = {r: max(0.0, min(float(demand_bps[r]), cap[r]) - grant[r]) for r in live}
    for r, g in _fill(need, w, budget).items():
        grant[r] += g
    budget = capacity_bps - sum(grant.values())
    spare = {r: cap[r] - grant[r] for r in live}
    for r, g in _fill(spare, w, budget).items():
        grant[r] += g
    return grant


def _fill(caps: dict[int, float], weights: Mapping[int, float], budget: float) -> dict[int, float]:
    """Weighted max-min fair shares of ``budget`` with per-robot ``caps`` (inf allowed)."""
    alloc = dict.fromkeys(caps, 0.0)
    left = {r: c for r, c in caps.items() if c > 0}
    while left and budget > 1e-9:
        level = budget / sum(weights[r] for r in left)
        full = [r for r in sorted(left) if left[r] <= weights[r] * level]
        if not full:
            for r in left:
                alloc[r] += weights[r] * level
            break
        for r in full:
            alloc[r] += left[r]
            budget -= left.pop(r)
    return alloc


class AirtimeConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Tunables of :class:`AirtimeScheduler` (rates in bits per mission second)."""

    #: Smoothing time of the measured rate (an exponential moving average).
    rate_window_s: float = 10.0
    #: A reported backlog is granted the rate that drains it in this time.
    drain_s: float = 10.0
    #: Demand is the measured rate times this (room to grow without waiting a round).
    headroom: float = 1.25
    #: Every connected robot gets at least this (acks, telemetry, a first report).
    floor_bps: float = 150.0

    def __post_init__(self) -> None:
        for name in ("rate_window_s", "drain_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        if not (math.isfinite(self.headroom) and self.headroom >= 1):
            raise ValueError(f"headroom must be >= 1, got {self.headroom}")
        if not (math.isfinite(self.floor_bps) and self.floor_bps >= 0):
            raise ValueError(f"floor_bps must be finite and >= 0, got {self.floor_bps}")


@dataclass
class AirtimeScheduler:
    """The GCS's allocator over time: feed it what arrived and what robots report queued,
    get each robot's uplink grant (:func:`allocate_airtime`)."""

    config: AirtimeConfig = field(default_factory=AirtimeConfig)
    _rate_bps: dict[int, float] = field(default_factory=dict)
    _bytes: dict[int, int] = field(default_factory=dict)
    _last_s: float | None = None

    def update(
        self,
        now_s: float,
        *,
        bytes_received: Mapping[int, int],
        backlog_bytes: Mapping[int, int],
        capacity_bps: float,
        weights: Mapping[int, float] | None = None,
        link_max_bps: Mapping[int, float] | None = None,
    ) -> dict[int, float]:
        """Uplink grants at ``now_s``: ``bytes_received`` are cumulative per robot (e.g. the
        GCS channels' ``stats.bytes_received``), ``backlog_bytes`` the robots' last reports."""
        cfg = self.config
        dt = 0.0 if self._last_s is None else max(0.0, now_s - self._last_s)
        self._last_s = now_s
        alpha = 1.0 - math.exp(-dt / cfg.rate_window_s) if dt > 0 else 0.0
        demand = {}
        for r in sorted(set(bytes_received) | set(backlog_bytes)):
            total = int(bytes_received.get(r, 0))
            if r in self._bytes and dt > 0:
                inst = 8.0 * (total - self._bytes[r]) / dt
                self._rate_bps[r] = self._rate_bps.get(r, inst) + alpha * (
                    inst - self._rate_bps.get(r, inst)
                )
            self._bytes[r] = total
            backlog_bps = 8.0 * int(backlog_bytes.get(r, 0)) / cfg.drain_s
            demand[r] = cfg.headroom * self._rate_bps.get(r, 0.0) + backlog_bps
        return allocate_airtime(
            demand,
            capacity_bps=capacity_bps,
            weights=weights,
            link_max_bps=link_max_bps,
            floor_bps=cfg.floor_bps,
        )
