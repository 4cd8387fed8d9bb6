"""Traversability learned from measured versus requested speed (AOJRF TDP 2009, Eq. 1).

``T = |v_measured| / |v_requested|`` clamped to [0, 1] (AOJRF scale 0..255 here 0..1): ground
where the robot makes less progress than it asks for (sand, slopes, clutter) gets a lower
``T``. The planner multiplies its step cost by ``1 + penalty * (1 - T)``
(:meth:`TraversabilityMap.cost_multiplier`, fed to :meth:`robot.planning.planner.PathPlanner.plan`),
so slippery ground costs more in Dijkstra and a cheap detour around it wins. Cells never
driven keep ``T = 1``: experience only ever makes ground *more* expensive (AOJRF: the map
"mainly reflects the traveled paths").

The map lives in ``odom`` on a coarse lattice of ``resolution_m`` cells, stored sparsely (only
cells with experience), so it is unbounded like the private frame itself. An observation is
blended by an exponential average into every cell within ``spread_m`` of where it was made:
ground is spatially coherent, and the robot's own footprint and the 1.25 s over which a
speed is measured cover more than one cell.

``v_measured`` must come from a source that sees the robot's real motion over ground; wheel
encoders alone do not when wheels spin in sand. The node measures it by matching consecutive
LIDAR sweeps (:mod:`robot.odometry.scan_displacement`) and requests what the wheels did (the
encoder odometry), so ``T`` is the share of the wheels' motion that the body made good.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np
from numpy.typing import NDArray

from robot.terrain.grid import GridGeometry

__all__ = ["TraversabilityConfig", "TraversabilityMap", "traversability"]


def traversability(measured_m_s: float, requested_m_s: float) -> float:
    """AOJRF Eq. 1 on [0, 1]: 0 when nothing was requested, capped at 1."""
    if abs(requested_m_s) < 1e-9:
        return 0.0
    return min(1.0, abs(measured_m_s) / abs(requested_m_s))


class TraversabilityConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``min_requested_m_s``: slower samples say nothing about the ground; ``learning_rate``
    of the exponential average; ``penalty``: cost multiplier at ``T = 0`` is
    ``1 + penalty``; ``resolution_m`` of the lattice; ``spread_m``: radius an observation
    is blended over."""

    min_requested_m_s: float = 0.15
    learning_rate: float = 0.3
    penalty: float = 4.0
    resolution_m: float = 0.5
    spread_m: float = 1.5

    def __post_init__(self) -> None:
        for name in ("min_requested_m_s", "penalty", "spread_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"traversability.{name} must be finite and >= 0, got {v}")
        if not 0 < self.learning_rate <= 1:
            raise ValueError(
                f"traversability.learning_rate must be in (0, 1], got {self.learning_rate}"
            )
        if not (math.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise ValueError(f"traversability.resolution_m must be > 0, got {self.resolution_m}")


class TraversabilityMap:
    """Per-cell traversability ``T`` in ``odom``, sparse and unbounded (see the module doc)."""

    def __init__(self, config: TraversabilityConfig | None = None) -> None:
        self.config = config or TraversabilityConfig()
        self._t: dict[tuple[int, int], float] = {}

    def __len__(self) -> int:
        """Cells with experience."""
        return len(self._t)

    def observe(self, x_m: float, y_m: float, *, measured_m_s: float, requested_m_s: float) -> None:
        """Blend one speed observation made at ``(x_m, y_m)`` into the cells within
        ``spread_m``. Requests slower than ``min_requested_m_s`` are ignored."""
        if not all(math.isfinite(v) for v in (x_m, y_m, measured_m_s, requested_m_s)):
            raise ValueError("traversability observation: non-finite position or speed")
        cfg = self.config
        if abs(requested_m_s) < cfg.min_requested_m_s:
            return
        value = traversability(measured_m_s, requested_m_s)
        res = cfg.resolution_m
        k = int(math.ceil(cfg.spread_m / res))
        ci, cj = math.floor(y_m / res), math.floor(x_m / res)
        for i in range(ci - k, ci + k + 1):
            for j in range(cj - k, cj + k + 1):
                cx, cy = (j + 0.5) * res, (i + 0.5) * res
                if math.hypot(cx - x_m, cy - y_m) > cfg.spread_m + 0.5 * res:
                    continue
                old = self._t.get((i, j), 1.0)
                self._t[(i, j)] = old + cfg.learning_rate * (value - old)

    def t_at(self, x_m: float, y_m: float) -> float:
        """``T`` of the cell containing ``(x_m, y_m)`` (1 without experience)."""
        res = self.config.resolution_m
        return self._t.get((math.floor(y_m / res), math.floor(x_m / res)), 1.0)

    def cost_multiplier(self, geometry: GridGeometry) -> NDArray[np.float64]:
        """Step-cost factors ``1 + penalty * (1 - T)`` (``>= 1``) on the planner's grid
        ``geometry`` (in ``odom``); each fine cell takes the coarse cell its centre is in."""
        out = np.ones(geometry.shape)
        if not self._t:
            return out
        cfg = self.config
        res = cfg.resolution_m
        ox, oy = geometry.origin_m
        g = geometry.resolution_m
        x1, y1 = ox + geometry.cols * g, oy + geometry.rows * g
        for (i, j), t in self._t.items():
            if t >= 1.0:
                continue
            x_lo, y_lo = j * res, i * res
            if x_lo >= x1 or y_lo >= y1 or x_lo + res <= ox or y_lo + res <= oy:
                continue
            # fine cells whose centres lie in [x_lo, x_lo + res) x [y_lo, y_lo + res)
            c0 = max(0, math.ceil((x_lo - ox) / g - 0.5))
            c1 = min(geometry.cols, math.ceil((x_lo + res - ox) / g - 0.5))
            r0 = max(0, math.ceil((y_lo - oy) / g - 0.5))
            r1 = min(geometry.rows, math.ceil((y_lo + res - oy) / g - 0.5))
            if r0 < r1 and c0 < c1:
                out[r0:r1, c0:c1] = 1.0 + cfg.penalty * (1.0 - t)
        return out
