"""SAGE event narration: events from simple rules, merged, prioritised, the top four kept
(paper 6.4.2).

"SAGE recognizes when new objects are detected, when robots change to a neutralization task,
and when civilians are close to dangerous OOIs ... the system prioritizes events and shows only
the top four events at any time. It also merges similar events and removes events over time
based on the type and severity of the event" (paper 6.4.2). Pure: pictures in, events out.

Rules (one per :class:`EventKind`, each episode raised once):

* ``new_object``: an object id seen for the first time (dangerous kinds rank highest);
* ``neutralization_started`` / ``neutralization_finished``: a robot's task kind becomes / stops
  being ``neutralize``;
* ``civilian_near_danger``: a civilian inside a dangerous object's blast ring;
* ``link_outage``: a robot silent for ``outage_s``; ``robot_lost``: silent for ``lost_s``.

Merging: an event of the same kind and subject, or of the same kind within ``merge_m`` of a live
one raised less than ``merge_window_s`` ago, refreshes that one (``count`` grows, its zoom box
covers both). Priority: ``severity * exp(-age / ttl)`` with a per-kind ``ttl``; an event older
than ``3 ttl`` is dropped. Each event carries a zoom box in ``map`` (centre, half-size m): the
local view the display shows beside the global one.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import msgspec

if TYPE_CHECKING:
    from gcs.views.operator_picture import ObjectSighting, RobotStatus

__all__ = ["Event", "EventKind", "Narrator", "NarrationConfig", "blast_radius_m", "TRIGGER_M"]

#: MAGIC rules (paper 2): a static OOI or hostile triggers within 2.5 m; static OOIs blast
#: 10 m, hostiles (mobile) 5 m.
TRIGGER_M = 2.5
BLAST_M = {"static_ooi": 10.0, "hostile": 5.0}


def blast_radius_m(kind_name: str) -> float | None:
    """Blast radius (m) of a dangerous kind, None for a harmless one."""
    return BLAST_M.get(kind_name)


class EventKind(enum.Enum):
    NEW_OBJECT = "new_object"
    NEUTRALIZATION_STARTED = "neutralization_started"
    NEUTRALIZATION_FINISHED = "neutralization_finished"
    CIVILIAN_NEAR_DANGER = "civilian_near_danger"
    LINK_OUTAGE = "link_outage"
    ROBOT_LOST = "robot_lost"


class NarrationConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Narration tunables: ``top`` events shown, merging distance/window, silence thresholds,
    zoom half-size, and the per-kind time to live (s) that ages an event's priority."""

    top: int = 4
    merge_m: float = 10.0
    merge_window_s: float = 30.0
    outage_s: float = 10.0
    lost_s: float = 60.0
    zoom_half_m: float = 8.0
    ttl_s: dict[str, float] = msgspec.field(
        default_factory=lambda: {
            "new_object": 60.0,
            "neutralization_started": 120.0,
            "neutralization_finished": 60.0,
            "civilian_near_danger": 120.0,
            "link_outage": 60.0,
            "robot_lost": 300.0,
        }
    )

    def __post_init__(self) -> None:
        if self.top < 1:
            raise ValueError(f"narration.top: expected >= 1, got {self.top}")
        for name in ("merge_m", "merge_window_s", "outage_s", "lost_s", "zoom_half_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"narration.{name}: expected a positive finite number, got {v}")
        kinds = {k.value for k in EventKind}
        for k, v in self.ttl_s.items():
            if k not in kinds:
                raise ValueError(f"narration.ttl_s: unknown event kind {k!r} (known: {kinds})")
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"narration.ttl_s.{k}: expected > 0, got {v}")


#: Base severity (1 low .. 3 high) by kind; a new dangerous object is raised to 3.
_SEVERITY = {
    EventKind.NEW_OBJECT: 1,
    EventKind.NEUTRALIZATION_STARTED: 2,
    EventKind.NEUTRALIZATION_FINISHED: 2,
    EventKind.CIVILIAN_NEAR_DANGER: 3,
    EventKind.LINK_OUTAGE: 2,
    EventKind.ROBOT_LOST: 3,
}


@dataclass
class Event:
    """A narrated event: what, about whom, and where to look (``zoom_center_in_map``,
    ``zoom_half_m``)."""

    event_id: int
    kind: EventKind
    subject: str
    text: str
    severity: int
    first_s: float
    last_s: float
    zoom_center_in_map: tuple[float, float]
    zoom_half_m: float
    robot_id: int | None = None
    count: int = 1
    points_in_map: list[tuple[float, float]] = field(default_factory=list)

    def priority(self, now_s: float, ttl_s: float) -> float:
        return self.severity * math.exp(-max(0.0, now_s - self.last_s) / ttl_s)

    def title(self) -> str:
        more = f" (x{self.count})" if self.count > 1 else ""
        return f"{self.kind.value.replace('_', ' ')}{more}: {self.text}"


class Narrator:
    """Detects events between successive calls of :meth:`update` and keeps the live ones."""

    def __init__(self, config: NarrationConfig | None = None) -> None:
        self.config = config or NarrationConfig()
        self.events: list[Event] = []
        self._next_id = 1
        self._known_objects: set[int] = set()
        self._neutralizing: dict[int, bool] = {}
        self._episodes: set[tuple[str, str]] = set()  # conditions raised and still true

    def _ttl(self, kind: EventKind) -> float:
        return self.config.ttl_s.get(kind.value, 60.0)

    def update(
        self,
        robots: Sequence[RobotStatus],
        objects: Sequence[ObjectSighting],
        now_s: float,
    ) -> list[Event]:
        """Run the rules on the current state; returns the events raised or refreshed now."""
        cfg = self.config
        raised: list[Event] = []
        cond_now: set[tuple[str, str]] = set()

        def emit(
            kind: EventKind,
            subject: str,
            text: str,
            points: list[tuple[float, float]],
            *,
            severity: int | None = None,
            robot_id: int | None = None,
        ) -> None:
            ev = self._merge_or_add(
                kind, subject, text, points, severity or _SEVERITY[kind], now_s, robot_id
            )
            raised.append(ev)

        for o in objects:
            if o.object_id in self._known_objects:
                continue
            self._known_objects.add(o.object_id)
            danger = blast_radius_m(o.kind_name) is not None
            emit(
                EventKind.NEW_OBJECT,
                f"object {o.object_id}",
                f"{o.kind_name} {o.object_id} seen by robot {o.robot_id}",
                [o.position_in_map],
                severity=3 if danger else (2 if o.kind_name == "civilian" else 1),
                robot_id=o.robot_id,
            )
        for r in robots:
            where = (
                []
                if r.pose_in_map is None
                else [(float(r.pose_in_map[0]), float(r.pose_in_map[1]))]
            )
            if r.goal_in_map is not None:
                where = where + [(float(r.goal_in_map[0]), float(r.goal_in_map[1]))]
            neutralizing = r.task_kind == "neutralize"
            was = self._neutralizing.get(r.robot_id, False)
            if neutralizing and not was:
                emit(
                    EventKind.NEUTRALIZATION_STARTED,
                    f"robot {r.robot_id}",
                    f"robot {r.robot_id} {r.task}",
                    where,
                    robot_id=r.robot_id,
                )
            elif was and not neutralizing:
                emit(
                    EventKind.NEUTRALIZATION_FINISHED,
                    f"robot {r.robot_id}",
                    f"robot {r.robot_id} now {r.task}",
                    where,
                    robot_id=r.robot_id,
                )
            self._neutralizing[r.robot_id] = neutralizing
            age = r.last_message_age_s
            for kind, limit in (
                (EventKind.ROBOT_LOST, cfg.lost_s),
                (EventKind.LINK_OUTAGE, cfg.outage_s),
            ):
                if age >= limit:
                    key = (kind.value, f"robot {r.robot_id}")
                    cond_now.add(key)
                    if key not in self._episodes:
                        self._episodes.add(key)
                        emit(
                            kind,
                            key[1],
                            f"robot {r.robot_id} silent {age:.0f} s",
                            where,
                            robot_id=r.robot_id,
                        )
                    break  # lost implies an outage: one event
        dangers = [o for o in objects if blast_radius_m(o.kind_name) is not None]
        for c in (o for o in objects if o.kind_name == "civilian"):
            for d in dangers:
                dist = math.dist(c.position_in_map, d.position_in_map)
                blast = blast_radius_m(d.kind_name) or 0.0
                if dist <= blast:
                    key = (
                        EventKind.CIVILIAN_NEAR_DANGER.value,
                        f"object {d.object_id}/{c.object_id}",
                    )
                    cond_now.add(key)
                    if key not in self._episodes:
                        self._episodes.add(key)
                        emit(
                            EventKind.CIVILIAN_NEAR_DANGER,
                            key[1],
                            f"civilian {c.object_id} {dist:.1f} m from {d.kind_name} {d.object_id} "
                            f"(blast {blast:.0f} m)",
                            [c.position_in_map, d.position_in_map],
                        )
        self._episodes &= cond_now  # a condition that ended may be raised again later
        self.events = [e for e in self.events if now_s - e.last_s <= 3.0 * self._ttl(e.kind)]
        return raised

    def _merge_or_add(
        self,
        kind: EventKind,
        subject: str,
        text: str,
        points: list[tuple[float, float]],
        severity: int,
        now_s: float,
        robot_id: int | None,
    ) -> Event:
        cfg = self.config
        for e in self.events:
            if e.kind is not kind or now_s - e.last_s > cfg.merge_window_s:
                continue
            near = (
                bool(points)
                and bool(e.points_in_map)
                and min(math.dist(p, q) for p in points for q in e.points_in_map) <= cfg.merge_m
            )
            if e.subject == subject or near:
                e.count += 1
                e.last_s = now_s
                e.severity = max(e.severity, severity)
                e.text = text
                e.points_in_map = (e.points_in_map + points)[-16:]
                e.zoom_center_in_map, e.zoom_half_m = _zoom(e.points_in_map, cfg.zoom_half_m)
                return e
        center, half = _zoom(points, cfg.zoom_half_m)
        ev = Event(
            self._next_id,
            kind,
            subject,
            text,
            severity,
            now_s,
            now_s,
            center,
            half,
            robot_id,
            points_in_map=list(points),
        )
        self._next_id += 1
        self.events.append(ev)
        return ev

    def top(self, now_s: float) -> list[Event]:
        """The ``top`` live events by priority (severity aged by the kind's ttl), best first."""
        ranked = sorted(
            self.events,
            key=lambda e: (-e.priority(now_s, self._ttl(e.kind)), -e.last_s, e.event_id),
        )
        return ranked[: self.config.top]


def _zoom(
    points: Sequence[tuple[float, float]], min_half_m: float
) -> tuple[tuple[float, float], float]:
    """Centre and half-size (m) of a square view holding ``points`` with a margin."""
    if not points:
        return (0.0, 0.0), min_half_m
    xs = [p[0] for p in points]
    ys = [p[1] for p in points]
    cx, cy = (min(xs) + max(xs)) / 2.0, (min(ys) + max(ys)) / 2.0
    half = max(min_half_m, (max(xs) - min(xs)) / 2.0 + 3.0, (max(ys) - min(ys)) / 2.0 + 3.0)
    return (float(cx), float(cy)), float(half)
