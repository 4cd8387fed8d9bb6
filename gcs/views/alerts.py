"""Operator alerts: rules over the status dashboard's rows, de-duplicated (paper 6.3).

The MAGIC GCS "monitored message rates, battery voltages, memory usage, CPU temperature, etc.,
and would audibly alert the operators to any anomalies" (paper 6.3). Here the rules run over
the plain rows of :class:`~gcs.views.operator_picture.RobotStatus` and the objects the GCS
knows; they are pure: state in, alerts out, no I/O.

Rules (each keyed by ``(rule, subject)``; thresholds in :class:`AlertRulesConfig`):

* ``silence``: no uplink message for ``silence_s`` (warning), ``lost_s`` (error);
* ``message_rate``: uplink rate below ``min_uplink_bps`` once the robot has spoken for a while;
* ``battery``: below ``battery_warn_frac`` (warning) / ``battery_error_frac`` (error);
* ``stuck``: the dashboard's stuck or deadlock flag;
* ``civilian``: a robot within ``civilian_m`` of a civilian.

De-duplication: an alert is raised when its condition starts (or its severity rises) and once
more when it clears (``info``); a condition that stays true raises nothing new, and one that
flickers is not raised again within ``repeat_s``. :class:`AlertLog` keeps the text log.
"""

from __future__ import annotations

import collections
import enum
import math
import shutil
import subprocess
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import msgspec

if TYPE_CHECKING:
    from gcs.views.operator_picture import ObjectSighting, RobotStatus

__all__ = ["Alert", "AlertLog", "AlertRules", "AlertRulesConfig", "Severity", "Speaker"]


class Severity(enum.IntEnum):
    INFO = 0
    WARNING = 1
    ERROR = 2


class AlertRulesConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Thresholds of the alert rules (module docstring). Times in mission seconds."""

    silence_s: float = 10.0
    lost_s: float = 60.0
    min_uplink_bps: float = 20.0
    rate_grace_s: float = 30.0
    battery_warn_frac: float = 0.25
    battery_error_frac: float = 0.10
    civilian_m: float = 3.0
    repeat_s: float = 30.0
    log_size: int = 500

    def __post_init__(self) -> None:
        for name in ("silence_s", "lost_s", "rate_grace_s", "civilian_m", "repeat_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"alerts.{name}: expected a positive finite number, got {v}")
        if not self.lost_s >= self.silence_s:
            raise ValueError(f"alerts.lost_s ({self.lost_s}) must be >= silence_s")
        if not 0 <= self.battery_error_frac <= self.battery_warn_frac <= 1:
            raise ValueError("alerts: need 0 <= battery_error_frac <= battery_warn_frac <= 1")
        if self.min_uplink_bps < 0:
            raise ValueError(f"alerts.min_uplink_bps: expected >= 0, got {self.min_uplink_bps}")
        if self.log_size < 1:
            raise ValueError(f"alerts.log_size: expected >= 1, got {self.log_size}")


@dataclass(frozen=True)
class Alert:
    """One alert line: ``rule`` fired on ``subject`` (``"robot 3"``) at mission ``time_s``."""

    time_s: float
    severity: Severity
    rule: str
    subject: str
    text: str
    robot_id: int | None = None
    cleared: bool = False

    def line(self) -> str:
        return f"[{self.time_s:9.1f} s] {self.severity.name:<7} {self.subject}: {self.text}"


@dataclass
class _Active:
    severity: Severity
    since_s: float
    raised: bool  # False: suppressed as flickering, so its clearing is not reported either


class AlertRules:
    """Evaluates the rules each time it is called; keeps which conditions are active."""

    def __init__(self, config: AlertRulesConfig | None = None) -> None:
        self.config = config or AlertRulesConfig()
        self._active: dict[tuple[str, str], _Active] = {}
        self._cleared_s: dict[tuple[str, str], float] = {}

    def conditions(
        self,
        robots: Sequence[RobotStatus],
        objects: Sequence[ObjectSighting],
        now_s: float,
    ) -> list[tuple[str, str, Severity, str, int | None]]:
        """Every condition true now: ``(rule, subject, severity, text, robot_id)``."""
        cfg = self.config
        out: list[tuple[str, str, Severity, str, int | None]] = []
        civilians = [o for o in objects if o.kind_name == "civilian"]
        for r in robots:
            subject = f"robot {r.robot_id}"
            age = r.last_message_age_s
            if age >= cfg.lost_s:
                out.append(
                    ("silence", subject, Severity.ERROR, f"lost: silent {age:.0f} s", r.robot_id)
                )
            elif age >= cfg.silence_s:
                out.append(
                    ("silence", subject, Severity.WARNING, f"silent {age:.0f} s", r.robot_id)
                )
            elif (
                r.active_s >= cfg.rate_grace_s
                and cfg.min_uplink_bps > 0
                and r.uplink_bps < cfg.min_uplink_bps
            ):
                out.append(
                    (
                        "message_rate",
                        subject,
                        Severity.WARNING,
                        f"uplink {r.uplink_bps:.0f} bit/s below {cfg.min_uplink_bps:.0f}",
                        r.robot_id,
                    )
                )
            b = r.battery_frac
            if math.isfinite(b) and b < cfg.battery_warn_frac:
                sev = Severity.ERROR if b < cfg.battery_error_frac else Severity.WARNING
                out.append(("battery", subject, sev, f"battery {100 * b:.0f} %", r.robot_id))
            if r.stuck or r.deadlock:
                what = "deadlocked" if r.deadlock else "stuck"
                out.append(
                    ("stuck", subject, Severity.WARNING, f"{what} with task {r.task}", r.robot_id)
                )
            if r.pose_in_map is not None and civilians:
                x, y = float(r.pose_in_map[0]), float(r.pose_in_map[1])
                near = min(
                    civilians,
                    key=lambda o: math.hypot(o.position_in_map[0] - x, o.position_in_map[1] - y),
                )
                d = math.hypot(near.position_in_map[0] - x, near.position_in_map[1] - y)
                if d < cfg.civilian_m:
                    out.append(
                        (
                            "civilian",
                            subject,
                            Severity.WARNING,
                            f"{d:.1f} m from civilian {near.object_id}",
                            r.robot_id,
                        )
                    )
        return out

    def evaluate(
        self,
        robots: Sequence[RobotStatus],
        objects: Sequence[ObjectSighting],
        now_s: float,
    ) -> list[Alert]:
        """New alerts since the last call (raised, escalated or cleared), de-duplicated."""
        cfg = self.config
        new: list[Alert] = []
        seen: set[tuple[str, str]] = set()
        for rule, subject, sev, text, rid in self.conditions(robots, objects, now_s):
            key = (rule, subject)
            if key in seen:  # one alert per rule and subject: the worst condition wins
                continue
            seen.add(key)
            active = self._active.get(key)
            if active is None:
                cleared = self._cleared_s.get(key, -math.inf)
                # flickering (raised and cleared a moment ago): keep quiet this time
                raised = now_s - cleared >= cfg.repeat_s
                self._active[key] = _Active(sev, now_s, raised)
                if raised:
                    new.append(Alert(now_s, sev, rule, subject, text, rid))
            elif sev > active.severity:
                active.severity = sev
                active.raised = True
                new.append(Alert(now_s, sev, rule, subject, text, rid))
        for key in [k for k in self._active if k not in seen]:
            active = self._active.pop(key)
            self._cleared_s[key] = now_s
            rid = _robot_of(key[1])
            if active.raised:
                new.append(
                    Alert(now_s, Severity.INFO, key[0], key[1], f"{key[0]} cleared", rid, True)
                )
        return new

    @property
    def active(self) -> dict[tuple[str, str], Severity]:
        """Conditions true at the last evaluation and their severity."""
        return {k: a.severity for k, a in self._active.items()}


def _robot_of(subject: str) -> int | None:
    head, _, tail = subject.partition(" ")
    return int(tail) if head == "robot" and tail.isdigit() else None


class AlertLog:
    """The text log of alerts (bounded), with an optional :class:`Speaker` for errors."""

    def __init__(self, size: int = 500, speaker: Speaker | None = None) -> None:
        self.lines: collections.deque[Alert] = collections.deque(maxlen=size)
        self.speaker = speaker

    def extend(self, alerts: Iterable[Alert]) -> None:
        for a in alerts:
            self.lines.append(a)
            if self.speaker is not None and a.severity >= Severity.ERROR and not a.cleared:
                self.speaker.say(f"{a.subject}: {a.text}")

    def text(self) -> str:
        return "\n".join(a.line() for a in self.lines)


class Speaker:
    """Text-to-speech through a command found on the machine (``spd-say``, ``espeak-ng``,
    ``espeak``, ``say``), started detached so it never waits; ``available`` is False when none
    exists (then :meth:`say` does nothing). At most one utterance runs at a time: a new one
    while another plays is dropped and counted in ``dropped``."""

    COMMANDS = ("spd-say", "espeak-ng", "espeak", "say")

    def __init__(self, command: str | None = None) -> None:
        found = command or next((c for c in self.COMMANDS if shutil.which(c)), None)
        self.command = found if found and shutil.which(found) else None
        self._proc: subprocess.Popen[bytes] | None = None
        self.dropped = 0
        self.failed = 0

    @property
    def available(self) -> bool:
        return self.command is not None

    def say(self, text: str) -> None:
        if self.command is None:
            return
        if self._proc is not None and self._proc.poll() is None:
            self.dropped += 1
            return
        try:
            self._proc = subprocess.Popen(
                [self.command, text],
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
        except OSError:
            self.failed += 1
