"""Stuck detection: the robot is asked to move but does not (paper 5.4's "no path" cousin).

Stuck when, for ``window_s``, the commanded speed is substantial while the pose moved less
than ``min_progress_m`` and turned less than ``min_turn_rad``. The node's recovery is to back
up briefly and replan; the planner's short memory forgets a bad map meanwhile.
"""

from __future__ import annotations

import math
from collections import deque

import msgspec
import numpy as np

__all__ = ["StuckConfig", "StuckDetector"]


class StuckConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    window_s: float = 4.0
    min_command_m_s: float = 0.2
    min_progress_m: float = 0.15
    min_turn_rad: float = 0.2


class StuckDetector:
    def __init__(self, config: StuckConfig | None = None) -> None:
        self.config = config or StuckConfig()
        self._hist: deque[tuple[float, float, float, float, float]] = deque()

    def update(
        self, t_s: float, pose_in_odom: np.ndarray, commanded_m_s: float, commanded_rad_s: float
    ) -> bool:
        """Record one control period; True when the robot is stuck."""
        cfg = self.config
        x, y, th = (float(v) for v in pose_in_odom)
        trying = (
            abs(commanded_m_s) >= cfg.min_command_m_s
            or abs(commanded_rad_s) >= 2 * cfg.min_turn_rad
        )
        if not trying:
            self._hist.clear()
            return False
        self._hist.append((t_s, x, y, th, commanded_m_s))
        while self._hist and self._hist[0][0] < t_s - cfg.window_s:
            self._hist.popleft()
        t0, x0, y0, th0, _ = self._hist[0]
        if t_s - t0 < 0.95 * cfg.window_s:
            return False
        moved = math.hypot(x - x0, y - y0)
        turned = abs(math.remainder(th - th0, 2 * math.pi))
        return moved < cfg.min_progress_m and turned < cfg.min_turn_rad

    def reset(self) -> None:
        self._hist.clear()
