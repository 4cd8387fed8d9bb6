"""Checking and repairing the clock of a recorded log (issue 19 item 3).

Public logs carry clocks that are frozen (every stamp 0), coarse (a Unix time printed with
``%g``: ``1.13486e+09``, changing every 1e4 s), jumping (a 32-bit wrap adds 4.29e9 s from some
scan on) or running backwards for a scan or two (a corrected log's reordering). Anything that
runs on message times -- a node's gyro covariance term ``gyro²·dt`` (paper 4.3.3), the node
maker's interval rule -- then sees nonsense: one jump becomes a yaw variance of 1e4 rad².

:func:`check_clock` looks at the steps ``dt = t[k+1] - t[k]`` of a log's stamps and returns a
usable clock:

* **none**: no finite stamp at all (the Duke DP-SLAM format): ``default_period_s`` per scan.
* **frozen**: one distinct value: every step gets ``default_period_s``.
* **coarse**: most steps (more than ``max_zero_step_frac``) are exactly 0, i.e. the stamps are
  quantized far coarser than the scan period: every step gets ``default_period_s``, unless the
  stamps hold at least 10 distinct values (the span is then known to 10%) and the log's span
  over its scan count gives a plausible period (``min_period_s..max_period_s``).
* **jump**: a step more than ``jump_factor`` times the median step of the good ones, or more
  than ``max_step_s``: that step gets the median period.
* **backwards**: a negative step: that step gets the median period.
* **too fast**: a step so short that the odometry moved faster than ``max_speed_m_per_s`` or
  turned faster than ``max_turn_rad_per_s`` (only with ``odometry``): reported and kept (a
  short ``dt`` only makes the gyro term smaller; replacing it would shift the rest of the
  clock away from the log's, which relations files refer to).

Good stretches keep their own steps, so the repaired clock is the cumulative sum of the good
steps and the replacements from the first finite stamp (0 when there is none); a stretch after a
jump stays on the clock before it. Each kind found is reported once, as one
:class:`ClockAnomaly` line saying which scans and what was done.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ClockAnomaly", "ClockCheck", "check_clock"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class ClockAnomaly:
    """One kind of clock defect: ``kind``, how many steps it hit, the first scan, what was done."""

    kind: str  # none | frozen | coarse | jump | backwards | too_fast
    steps: int
    first_scan: int
    action: str

    def line(self) -> str:
        """One line (under 200 characters) for logs and summaries."""
        where = f"from scan {self.first_scan}" if self.steps > 1 else f"at scan {self.first_scan}"
        return f"clock {self.kind}: {self.steps} step(s) {where}; {self.action}"


@dataclass(frozen=True)
class ClockCheck:
    """The verdict on a clock: ``time_s`` ``(N,)`` the usable clock, ``period_s`` the median
    scan period it assumes for replaced steps, ``repaired`` ``(N-1,)`` which steps were
    replaced, ``anomalies`` one per kind found (empty: the log's clock is used as is)."""

    time_s: FloatArray
    period_s: float
    repaired: NDArray[np.bool_]
    anomalies: tuple[ClockAnomaly, ...]

    @property
    def ok(self) -> bool:
        return not self.anomalies

    @property
    def dt_s(self) -> FloatArray:
        """The repaired steps ``(N-1,)`` (all >= 0)."""
        return np.diff(self.time_s)  # type: ignore[no-any-return]

    @property
    def rewritten(self) -> bool:
        """Whether the clock as a whole was replaced or shifted (none, frozen, coarse, jump):
        times then no longer match the log's own stamps."""
        return any(a.kind in ("none", "frozen", "coarse", "jump") for a in self.anomalies)

    def lines(self) -> list[str]:
        return [a.line() for a in self.anomalies]


def _first(mask: NDArray[np.bool_]) -> int:
    return int(np.flatnonzero(mask)[0]) + 1  # step k leads to scan k + 1


def check_clock(
    time_s: ArrayLike,
    *,
    odometry: ArrayLike | None = None,
    default_period_s: float = 0.5,
    max_zero_step_frac: float = 0.5,
    jump_factor: float = 1000.0,
    max_step_s: float = 86400.0,
    min_period_s: float = 1e-3,
    max_period_s: float = 60.0,
    max_speed_m_per_s: float = 5.0,
    max_turn_rad_per_s: float = 2.0 * math.pi,
) -> ClockCheck:
    """Check the stamps ``time_s`` ``(N,)`` of a log's scans and repair them (module docstring).

    ``odometry`` ``(N, 3)`` (x, y, yaw per scan), when given, flags steps shorter than the
    motion allows. Pure; never raises on odd stamps (that is its point), only on bad arguments.
    """
    t = np.asarray(time_s, dtype=np.float64).reshape(-1)
    n = len(t)
    if not (math.isfinite(default_period_s) and default_period_s > 0):
        raise ValueError(f"default_period_s: expected > 0, got {default_period_s}")
    if n < 2:
        out = np.where(np.isfinite(t), t, 0.0)
        return ClockCheck(out, default_period_s, np.zeros(0, dtype=bool), ())
    finite = np.isfinite(t)
    anomalies: list[ClockAnomaly] = []
    if not finite.any():
        steps = np.full(n - 1, default_period_s)
        anomalies.append(
            ClockAnomaly(
                "none", n - 1, 1, f"no timestamps: {default_period_s:g} s per scan assumed"
            )
        )
        return ClockCheck(
            np.r_[0.0, np.cumsum(steps)],
            default_period_s,
            np.ones(n - 1, dtype=bool),
            tuple(anomalies),
        )
    origin = float(t[finite][0])
    # A missing stamp inside a clocked log: its two steps are unknown.
    dt = np.diff(t)
    unknown = ~np.isfinite(dt)
    bad = unknown.copy()
    dt_f = np.where(unknown, 0.0, dt)
    zero = (dt_f == 0.0) & ~unknown
    distinct = len(np.unique(t[finite]))
    if distinct == 1 or zero.sum() > max_zero_step_frac * (n - 1):
        span = float(np.nanmax(t) - np.nanmin(t))
        period = span / (n - 1)
        # A span known to one quantum only says something when it holds many quanta.
        if distinct < 10 or not (min_period_s <= period <= max_period_s):
            period = default_period_s
            how = f"{period:g} s per scan assumed"
        else:
            how = f"{period:.4g} s per scan from the log's span over its scan count"
        kind = "frozen" if distinct == 1 else "coarse"
        what = (
            f"every stamp {origin:.6g}"
            if distinct == 1
            else f"{distinct} distinct stamps over {n} scans"
        )
        anomalies.append(ClockAnomaly(kind, n - 1, 1, f"{what}; {how}"))
        steps = np.full(n - 1, period)
        return ClockCheck(
            origin + np.r_[0.0, np.cumsum(steps)],
            period,
            np.ones(n - 1, dtype=bool),
            tuple(anomalies),
        )
    positive = dt_f > 0.0
    period = float(np.median(dt_f[positive])) if positive.any() else default_period_s
    # The median of all positive steps is robust to a few jumps; recompute without them.
    jump = positive & ((dt_f > jump_factor * period) | (dt_f > max_step_s))
    if (positive & ~jump).any():
        period = float(np.median(dt_f[positive & ~jump]))
    backwards = (dt_f < 0.0) & ~unknown
    too_fast = np.zeros(n - 1, dtype=bool)
    if odometry is not None:
        odom = np.asarray(odometry, dtype=np.float64).reshape(n, 3)
        ds = np.hypot(np.diff(odom[:, 0]), np.diff(odom[:, 1]))
        dyaw = np.abs((np.diff(odom[:, 2]) + np.pi) % (2 * np.pi) - np.pi)
        # Only steps shorter than the period are suspects: a long step is jump's business.
        need = np.maximum(ds / max_speed_m_per_s, dyaw / max_turn_rad_per_s)
        too_fast = positive & ~jump & (dt_f < need) & (dt_f < 0.5 * period)
    for kind, mask in (
        ("jump", jump),
        ("backwards", backwards),
        ("too_fast", too_fast),
        ("missing", unknown),
    ):
        if mask.any():
            worst = float(np.max(np.abs(dt_f[mask]))) if kind != "missing" else math.nan
            detail = "" if kind == "missing" else f" (largest {worst:.6g} s)"
            action = (
                f"step{detail} kept: motion too fast for it"
                if kind == "too_fast"
                else f"step{detail} replaced by the median period {period:.4g} s"
            )
            anomalies.append(
                ClockAnomaly(
                    kind,
                    int(mask.sum()),
                    _first(mask),
                    action,
                )
            )
            if kind != "too_fast":
                bad |= mask
    steps = np.where(bad, period, dt_f)
    return ClockCheck(origin + np.r_[0.0, np.cumsum(steps)], period, bad, tuple(anomalies))
