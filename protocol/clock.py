"""Injectable mission clocks (DESIGN section 3: time is the mission clock, in seconds).

The link meters and rate-limits in mission time, so a simulation running faster than real
time still holds its radio rates. Every clock is safe to read from any thread.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol, runtime_checkable

__all__ = ["Clock", "ManualClock", "ScaledClock", "WallClock"]


@runtime_checkable
class Clock(Protocol):
    def now(self) -> float:
        """Mission time in seconds."""
        ...


class WallClock:
    """Seconds since this clock was created, from the monotonic clock."""

    def __init__(self) -> None:
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0


class ScaledClock:
    """Mission time running ``rate`` times faster than the wall clock (a real-time factor)."""

    def __init__(self, rate: float, *, start_s: float = 0.0) -> None:
        if not rate > 0:
            raise ValueError(f"ScaledClock rate must be > 0, got {rate}")
        self._rate = rate
        self._start = start_s
        self._t0 = time.monotonic()

    def now(self) -> float:
        return self._start + (time.monotonic() - self._t0) * self._rate


class ManualClock:
    """A clock that moves only when told to (tests, lockstep simulation, clock subscribers)."""

    def __init__(self, start_s: float = 0.0) -> None:
        self._t = float(start_s)
        self._lock = threading.Lock()

    def now(self) -> float:
        return self._t

    def set(self, t_s: float) -> None:
        """Move to ``t_s``; the clock never goes backwards."""
        with self._lock:
            if t_s < self._t:
                raise ValueError(f"clock cannot go back from {self._t} to {t_s}")
            self._t = float(t_s)

    def advance(self, dt_s: float) -> float:
        with self._lock:
            if dt_s < 0:
                raise ValueError(f"clock cannot advance by a negative {dt_s}")
            self._t += dt_s
            return self._t
