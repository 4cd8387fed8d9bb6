"""The MAGIC rules (paper section 2), as a pure state machine over numpy arrays.

- **Trigger**: a live robot or civilian within ``trigger_radius_m`` (2.5 m, horizontal
  distance) of an active static OOI or hostile detonates it. A static OOI's blast destroys
  every robot and civilian within ``static_blast_radius_m`` (10 m), a hostile's within
  ``hostile_blast_radius_m`` (5 m). A detonated hostile is gone.
- **Static OOI neutralization**: a live *disruptor* keeps its laser pointer on it, with line
  of sight, for ``laser_hold_s`` (15 s). The caller decides what each laser hits (ray cast);
  any break (no disruptor on it at a step) resets the timer.
- **Hostile neutralization**: at least ``lock_robots`` (two) live *sensor* robots keep it in
  view (line of sight within ``lock_range_m``) for ``lock_hold_s`` (30 s) without a break.
- Toxic vats are not dangerous; they only count for detection.

Every event is recorded with its mission time, the object and the robots/civilians involved.
Within a step, triggers are evaluated before neutralizations. A timer that started at ``t0``
completes at the first step with ``t - t0 >= hold`` (so with steps of ``dt`` the hold is met
exactly when ``hold`` is a multiple of ``dt``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import msgspec
import numpy as np

__all__ = ["Event", "Rules", "RulesConfig"]

_EPS_S = 1e-9


class RulesConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    trigger_radius_m: float = 2.5
    static_blast_radius_m: float = 10.0
    hostile_blast_radius_m: float = 5.0
    laser_hold_s: float = 15.0
    lock_hold_s: float = 30.0
    lock_range_m: float = 12.0
    lock_robots: int = 2
    laser_range_m: float = 30.0

    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")


EventKind = Literal["detonation", "neutralized", "robot_lost", "civilian_harmed"]


@dataclass(frozen=True)
class Event:
    """Something the rules decided. ``subject``: ``static_ooi:<id>``, ``hostile:<id>``,
    ``robot:<id>`` or ``civilian:<id>``; ``cause``: the OOI behind it (for losses) or what
    triggered a detonation; ``robots``/``civilians``: who was involved."""

    time_s: float
    kind: EventKind
    subject: str
    cause: str = ""
    robots: tuple[int, ...] = field(default=())
    civilians: tuple[int, ...] = field(default=())

    def __str__(self) -> str:
        """One line for people: ``t=82.0 s neutralized static_ooi:0 (laser)``."""
        cause = f" ({self.cause})" if self.cause else ""
        return f"t={self.time_s:.1f} s {self.kind} {self.subject}{cause}"


class Rules:
    """Rule state for one phase.

    ``static_xy_m``: ``(K, 2)`` static OOI positions (bombs only; vats do not count), with
    their ids ``static_ids``; ``robot_roles``: ``"sensor"``/``"disruptor"`` per robot;
    ``hostile_ids`` / ``civilian_ids``: the people's ids.
    """

    def __init__(
        self,
        *,
        static_ids: list[int],
        static_xy_m: np.ndarray,
        hostile_ids: list[int],
        civilian_ids: list[int],
        robot_roles: Sequence[str],
        config: RulesConfig | None = None,
    ) -> None:
        self.config = config or RulesConfig()
        self.static_ids = list(static_ids)
        self.static_xy = np.asarray(static_xy_m, dtype=np.float64).reshape(-1, 2)
        self.static_status = ["active"] * len(static_ids)
        self.hostile_ids = list(hostile_ids)
        self.hostile_status = ["active"] * len(hostile_ids)
        self.civilian_ids = list(civilian_ids)
        self.civilian_alive = np.ones(len(civilian_ids), dtype=bool)
        self.is_disruptor = np.array([r == "disruptor" for r in robot_roles], dtype=bool)
        self.robot_alive = np.ones(len(robot_roles), dtype=bool)
        self.laser_start = np.full(len(static_ids), np.nan)
        self.lock_start = np.full(len(hostile_ids), np.nan)
        self.events: list[Event] = []

    def step(
        self,
        time_s: float,
        *,
        robot_xy_m: np.ndarray,
        civilian_xy_m: np.ndarray,
        hostile_xy_m: np.ndarray,
        lasered: np.ndarray,
        hostile_in_view: np.ndarray,
    ) -> list[Event]:
        """Apply the rules at ``time_s``; returns (and records) the new events.

        ``lasered``: ``(N,)`` int, per robot the index into ``static_ids`` its laser is on
        with line of sight, or -1. ``hostile_in_view``: ``(N, M)`` bool, robot ``n`` sees
        hostile ``m`` (line of sight within range). Robots not alive are ignored.
        """
        cfg = self.config
        robot_xy = np.asarray(robot_xy_m, dtype=np.float64).reshape(-1, 2)
        civ_xy = np.asarray(civilian_xy_m, dtype=np.float64).reshape(-1, 2)
        host_xy = np.asarray(hostile_xy_m, dtype=np.float64).reshape(-1, 2)
        new: list[Event] = []

        def detonate(kind: str, ooi: str, xy: np.ndarray, blast: float, cause: str) -> None:
            robots = tuple(
                int(i)
                for i in np.nonzero(
                    self.robot_alive & (np.linalg.norm(robot_xy - xy, axis=1) <= blast)
                )[0]
            )
            civs = (
                tuple(
                    int(i)
                    for i in np.nonzero(
                        self.civilian_alive & (np.linalg.norm(civ_xy - xy, axis=1) <= blast)
                    )[0]
                )
                if len(civ_xy)
                else ()
            )
            new.append(
                Event(
                    time_s,
                    "detonation",
                    ooi,
                    cause,
                    robots,
                    tuple(self.civilian_ids[c] for c in civs),
                )
            )
            for r in robots:
                self.robot_alive[r] = False
                new.append(Event(time_s, "robot_lost", f"robot:{r}", ooi, (r,)))
            for c in civs:
                self.civilian_alive[c] = False
                cid = self.civilian_ids[c]
                new.append(Event(time_s, "civilian_harmed", f"civilian:{cid}", ooi, (), (cid,)))

        def nearest_trigger(xy: np.ndarray) -> str | None:
            d_r = np.where(self.robot_alive, np.linalg.norm(robot_xy - xy, axis=1), np.inf)
            d_c = (
                np.where(self.civilian_alive, np.linalg.norm(civ_xy - xy, axis=1), np.inf)
                if len(civ_xy)
                else np.array([np.inf])
            )
            best_r, best_c = float(d_r.min(initial=np.inf)), float(d_c.min(initial=np.inf))
            if min(best_r, best_c) > cfg.trigger_radius_m:
                return None
            if best_r <= best_c:
                return f"robot:{int(np.argmin(d_r))}"
            return f"civilian:{self.civilian_ids[int(np.argmin(d_c))]}"

        for k, oid in enumerate(self.static_ids):
            if self.static_status[k] != "active":
                continue
            who = nearest_trigger(self.static_xy[k])
            if who is not None:
                self.static_status[k] = "detonated"
                self.laser_start[k] = np.nan
                detonate(
                    "static", f"static_ooi:{oid}", self.static_xy[k], cfg.static_blast_radius_m, who
                )
        for m, hid in enumerate(self.hostile_ids):
            if self.hostile_status[m] != "active":
                continue
            who = nearest_trigger(host_xy[m])
            if who is not None:
                self.hostile_status[m] = "detonated"
                self.lock_start[m] = np.nan
                detonate("hostile", f"hostile:{hid}", host_xy[m], cfg.hostile_blast_radius_m, who)

        las = np.asarray(lasered, dtype=np.int64).reshape(-1)
        for k, oid in enumerate(self.static_ids):
            if self.static_status[k] != "active":
                continue
            on = np.nonzero((las == k) & self.robot_alive & self.is_disruptor)[0]
            if len(on) == 0:
                self.laser_start[k] = np.nan
                continue
            if math.isnan(self.laser_start[k]):
                self.laser_start[k] = time_s
            if time_s - self.laser_start[k] >= cfg.laser_hold_s - _EPS_S:
                self.static_status[k] = "neutralized"
                new.append(
                    Event(
                        time_s,
                        "neutralized",
                        f"static_ooi:{oid}",
                        "laser",
                        tuple(int(r) for r in on),
                    )
                )

        view = np.asarray(hostile_in_view, dtype=bool).reshape(len(robot_xy), len(self.hostile_ids))
        sensors = self.robot_alive & ~self.is_disruptor
        for m, hid in enumerate(self.hostile_ids):
            if self.hostile_status[m] != "active":
                continue
            lookers = np.nonzero(view[:, m] & sensors)[0]
            if len(lookers) < cfg.lock_robots:
                self.lock_start[m] = np.nan
                continue
            if math.isnan(self.lock_start[m]):
                self.lock_start[m] = time_s
            if time_s - self.lock_start[m] >= cfg.lock_hold_s - _EPS_S:
                self.hostile_status[m] = "neutralized"
                new.append(
                    Event(
                        time_s,
                        "neutralized",
                        f"hostile:{hid}",
                        "visual_lock",
                        tuple(int(r) for r in lookers),
                    )
                )
        self.events.extend(new)
        return new
