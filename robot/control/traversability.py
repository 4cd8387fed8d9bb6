"""Traversability learned from measured versus requested speed (AOJRF TDP 2009, Eq. 1).

``T = |v_measured| / |v_requested|`` clamped to [0, 1] (AOJRF scale 0..255 here 0..1): ground
where the robot makes less progress than it asks for (sand, slopes, clutter) gets a lower
``T``. The map lives in ``odom`` with the terrain grid's cell convention and is updated at the
cell under the robot by an exponential average; the planner multiplies its step cost by
``1 + penalty * (1 - T)`` (:meth:`TraversabilityMap.cost_multiplier`). Cells never driven
keep ``T = 1``: experience only ever makes ground *more* expensive.

``v_measured`` must come from a source that sees the robot's real motion over ground; wheel
encoders alone do not when wheels spin in sand, so the node uses the pose-node displacement
(odometry corrected by the inertial yaw and, where available, scan alignment).
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

__all__ = ["TraversabilityConfig", "TraversabilityMap", "traversability"]


def traversability(measured_m_s: float, requested_m_s: float) -> float:
    """AOJRF Eq. 1 on [0, 1]: 0 when nothing was requested, capped at 1."""
    if abs(requested_m_s) < 1e-9:
        return 0.0
    return min(1.0, abs(measured_m_s) / abs(requested_m_s))


class TraversabilityConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    min_requested_m_s: float = 0.15  # below this a sample says nothing about the ground
    learning_rate: float = 0.2
    penalty: float = 4.0  # cost multiplier at T = 0 is 1 + penalty


class TraversabilityMap:
    """Per-cell traversability in ``odom`` on a fixed grid."""

    def __init__(
        self,
        shape: tuple[int, int],
        *,
        origin_in_odom: tuple[float, float],
        resolution_m: float,
        config: TraversabilityConfig | None = None,
    ) -> None:
        self.config = config or TraversabilityConfig()
        self.origin_in_odom = origin_in_odom
        self.resolution_m = resolution_m
        self.t = np.ones(shape, dtype=np.float32)

    def observe(self, x_m: float, y_m: float, *, measured_m_s: float, requested_m_s: float) -> None:
        """Blend one speed observation into the cell containing ``(x_m, y_m)``."""
        if abs(requested_m_s) < self.config.min_requested_m_s:
            return
        if not (math.isfinite(measured_m_s) and math.isfinite(requested_m_s)):
            raise ValueError("traversability observation: non-finite speed")
        col = int((x_m - self.origin_in_odom[0]) // self.resolution_m)
        row = int((y_m - self.origin_in_odom[1]) // self.resolution_m)
        if 0 <= row < self.t.shape[0] and 0 <= col < self.t.shape[1]:
            k = self.config.learning_rate
            self.t[row, col] += k * (traversability(measured_m_s, requested_m_s) - self.t[row, col])

    def cost_multiplier(self) -> np.ndarray:
        """Step-cost factor per cell for the planner: 1 on good ground, up to 1 + penalty."""
        return 1.0 + self.config.penalty * (1.0 - self.t)
