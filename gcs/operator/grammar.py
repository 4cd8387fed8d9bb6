"""The operator command language, shared by the console (parsing, completion, help) and the
GCS (validation): verbs, their arguments, robot subsets, suggestions (paper 6.2).

A command line is ``VERB [TARGET] [ARGS...]``::

    goto 3 12.5 -4        robot 3 to (12.5, -4) in map: semi-autonomous (operator-controlled)
    auto sensors          back to the planners: fully autonomous
    pause all / resume 2-5
    neutralize 4 7        disruptor 7 neutralizes OOI 4 (approved)
    approve 4             approve the pending neutralization of OOI 4
    relay 6 30 12         robot 6 holds at (30, 12) as a radio relay
    reclassify 4 civilian
    closure 1:40 2:17     suggest a closure between pose 40 of robot 1 and pose 17 of robot 2
    rewind 120            remove automatic closures since mission second 120
    restart-loops / simplify
    set telemetry_period_s 0.5 [ROBOTS]
    status [ROBOTS]

Robot subsets (:func:`parse_subset`): an id ``3``, a range ``2-5``, a role ``sensors`` /
``disruptors``, ``idle`` (no task), ``all``, or comma lists of these (``1,4-6,disruptors``).
An unknown verb, robot id or word gets the nearest known ones as a suggestion
(:func:`suggest`), never a traceback.
"""

from __future__ import annotations

import difflib
import math
import shlex
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from protocol.messages import ObjectKind
from protocol.operator import Command

__all__ = [
    "GROUPS",
    "KINDS",
    "PARAMETERS",
    "VERBS",
    "CommandError",
    "RobotFacts",
    "Verb",
    "parse_line",
    "parse_subset",
    "suggest",
]

#: Robot subset words.
GROUPS = ("all", "sensors", "disruptors", "idle")

#: Object kinds an operator may reclassify an OOI as.
KINDS = tuple(k.name.lower() for k in ObjectKind)

#: Parameters ``set`` knows: where they apply and what values they take.
PARAMETERS: dict[str, str] = {
    "telemetry_period_s": "robot: seconds between telemetry messages (> 0)",
    "codec": "robot: terrain-grid codec name (e.g. inter16, magic4, zlib)",
    "status_period_s": "gcs: seconds between status messages to consoles (> 0)",
    "views_period_s": "gcs: seconds between operator pictures (robots, dashboard) (> 0)",
}


class CommandError(ValueError):
    """A command that cannot be carried out as typed; the text says why and suggests."""


@dataclass(frozen=True)
class Verb:
    """``target``: what the first argument is (``robots``, ``robot``, ``ooi``, ``none``,
    ``optional_robots``); ``args``: names of the remaining arguments (``?`` suffix:
    optional); ``mutates``: counted as an interaction when accepted; ``help``: one paragraph."""

    name: str
    target: str
    args: tuple[str, ...]
    help: str
    mutates: bool = True

    def usage(self) -> str:
        parts = [self.name]
        if self.target == "robots":
            parts.append("ROBOTS")
        elif self.target == "optional_robots":
            parts.append("[ROBOTS]")
        elif self.target == "robot":
            parts.append("ROBOT")
        elif self.target == "ooi":
            parts.append("OOI")
        for a in self.args:
            parts.append(f"[{a[:-1].upper()}]" if a.endswith("?") else a.upper())
        return " ".join(parts)


_V = Verb
VERBS: dict[str, Verb] = {
    v.name: v
    for v in (
        _V(
            "goto",
            "robots",
            ("x_m", "y_m"),
            "Send ROBOTS to (X_M, Y_M) in the map frame (metres). The robots plan their own path "
            "(semi-autonomous) and are operator-controlled: the planners leave them alone until "
            "`auto`.",
        ),
        _V(
            "auto",
            "robots",
            (),
            "Give ROBOTS back to the planners (fully autonomous): they get new tasks from the "
            "task allocator at its next plan.",
        ),
        _V(
            "pause",
            "robots",
            (),
            "Stop ROBOTS where they are and hold their current task (PauseTask). The planners "
            "leave paused robots alone until `resume`.",
        ),
        _V(
            "resume",
            "robots",
            (),
            "Continue the paused task of ROBOTS (ResumeTask); they return to whoever controlled "
            "them before the pause.",
        ),
        _V(
            "neutralize",
            "ooi",
            ("robot",),
            "Send disruptor ROBOT to neutralize OOI (a static OOI's id from `status`): it drives "
            "to a stand-off point and holds its laser on it for 15 s. Operator-approved.",
        ),
        _V(
            "approve",
            "ooi",
            (),
            "Approve the pending neutralization of OOI (the planners' disruptor fires once it is "
            "in place).",
        ),
        _V(
            "relay",
            "robot",
            ("x_m", "y_m"),
            "Send ROBOT to (X_M, Y_M) in map to hold as a radio relay (operator-controlled).",
        ),
        _V(
            "reclassify",
            "ooi",
            ("kind",),
            "Change the kind of OOI (e.g. a false static OOI is a civilian); the robots' "
            "keep-out discs follow at the next hazard update.",
        ),
        _V(
            "closure",
            "none",
            ("pose_a", "pose_b"),
            "Suggest a loop closure between two poses written ROBOT:NODE (node index, or "
            "`last`). The GCS matches their grids around the current estimate and adds the "
            "closure when the match is good.",
        ),
        _V(
            "rewind",
            "none",
            ("since_s",),
            "Remove the automatic loop closures added after mission second SINCE_S "
            "(negative: that many seconds ago) and re-optimize.",
        ),
        _V(
            "restart-loops",
            "none",
            (),
            "Restart the loop closer: forget hypotheses and tried pairs so every pair may be "
            "matched again (accepted closures stay).",
        ),
        _V(
            "simplify",
            "none",
            (),
            "Simplify the SLAM graph (paper 4.7, Algorithm 1) at the current estimate: "
            "redundant edges merged, the estimate unchanged.",
        ),
        _V(
            "set",
            "none",
            ("name", "value", "robots?"),
            "Set a parameter: " + "; ".join(f"{k} ({v})" for k, v in PARAMETERS.items()) + ". "
            "Robot parameters go to ROBOTS (default all).",
        ),
        _V(
            "status",
            "optional_robots",
            (),
            "Show every robot (or ROBOTS): role, mode, task, who controls it, position, battery, "
            "last message; and the OOIs with their state.",
            mutates=False,
        ),
    )
}

#: Console-only words (never sent).
LOCAL_VERBS = ("help", "macros", "history", "quit", "exit")


@dataclass(frozen=True)
class RobotFacts:
    """What subset words need to know of one robot."""

    robot_id: int
    role: str = "unknown"
    idle: bool = False


def suggest(word: str, known: Iterable[str], *, what: str) -> str:
    """``unknown {what} 'word'; did you mean 'x'?`` (or the list of known ones)."""
    known = [str(k) for k in known]
    close = difflib.get_close_matches(word, known, n=3, cutoff=0.5)
    if close:
        alts = " or ".join(repr(c) for c in close)
        return f"unknown {what} {word!r}; did you mean {alts}?"
    shown = ", ".join(known[:20]) + (", ..." if len(known) > 20 else "")
    return f"unknown {what} {word!r}; known: {shown or 'none yet'}"


def parse_subset(spec: str, robots: Mapping[int, RobotFacts]) -> list[int]:
    """The sorted robot ids ``spec`` names among ``robots`` (module docstring); raises
    :class:`CommandError` with a suggestion for an unknown id or word, or an empty result."""
    spec = spec.strip()
    if not spec:
        raise CommandError("no robots given (e.g. 3, 2-5, sensors, idle, all)")
    known = sorted(robots)
    out: set[int] = set()
    for part in spec.split(","):
        part = part.strip().lower()
        if not part:
            raise CommandError(f"robots {spec!r}: empty item in the comma list")
        if part.isdigit():
            rid = int(part)
            if rid not in robots:
                raise CommandError(suggest(part, [str(k) for k in known], what="robot id"))
            out.add(rid)
        elif "-" in part and all(p.strip().isdigit() for p in part.split("-", 1)):
            lo, hi = (int(p) for p in part.split("-", 1))
            if lo > hi:
                raise CommandError(f"robots {part!r}: range runs backwards (write {hi}-{lo})")
            hit = [r for r in known if lo <= r <= hi]
            if not hit:
                raise CommandError(f"robots {part!r}: no known robot in that range ({known})")
            out.update(hit)
        elif part in ("all", "*"):
            out.update(known)
        elif part in ("sensors", "sensor"):
            out.update(r for r in known if robots[r].role == "sensor")
            if not any(robots[r].role != "unknown" for r in known):
                raise CommandError("robot roles are unknown at the GCS: name the robots")
        elif part in ("disruptors", "disruptor"):
            out.update(r for r in known if robots[r].role == "disruptor")
            if not any(robots[r].role != "unknown" for r in known):
                raise CommandError("robot roles are unknown at the GCS: name the robots")
        elif part == "idle":
            out.update(r for r in known if robots[r].idle)
        else:
            raise CommandError(
                suggest(part, [*GROUPS, *(str(k) for k in known)], what="robot or group")
            )
    if not out:
        raise CommandError(f"robots {spec!r}: names no robot right now")
    return sorted(out)


def _number(text: str, what: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise CommandError(f"{what}: expected a number, got {text!r}") from None
    if not math.isfinite(v):
        raise CommandError(f"{what}: expected a finite number, got {text!r}")
    return v


def parse_line(line: str) -> Command:
    """A typed line as a :class:`Command` (syntax only: robots, OOIs and values are checked
    where they are known). Raises :class:`CommandError` with a suggestion."""
    try:
        words = shlex.split(line)
    except ValueError as err:
        raise CommandError(f"cannot split {line!r}: {err}") from None
    if not words:
        raise CommandError("empty command; type `help`")
    head = words[0].lower()
    verb = VERBS.get(head)
    if verb is None:
        raise CommandError(suggest(head, [*VERBS, *LOCAL_VERBS], what="command"))
    rest = words[1:]
    target = ""
    if verb.target in ("robots", "robot", "ooi"):
        if not rest:
            raise CommandError(f"{verb.name}: missing {verb.target.upper()}; usage: {verb.usage()}")
        target, rest = rest[0], rest[1:]
    elif verb.target == "optional_robots" and rest:
        target, rest = rest[0], rest[1:]
    required = [a for a in verb.args if not a.endswith("?")]
    if len(rest) < len(required):
        missing = " ".join(a.upper() for a in required[len(rest) :])
        raise CommandError(f"{verb.name}: missing {missing}; usage: {verb.usage()}")
    if len(rest) > len(verb.args):
        extra = " ".join(rest[len(verb.args) :])
        raise CommandError(f"{verb.name}: unexpected {extra!r}; usage: {verb.usage()}")
    args: list[float | int | str] = []
    for name, text in zip(verb.args, rest, strict=False):
        name = name.rstrip("?")
        if name.endswith("_m") or name.endswith("_s"):
            args.append(_number(text, f"{verb.name} {name.upper()}"))
        elif name in ("robot",):
            if not text.isdigit():
                raise CommandError(f"{verb.name}: ROBOT must be a robot id, got {text!r}")
            args.append(int(text))
        elif name == "kind":
            if text.lower() not in KINDS:
                raise CommandError(suggest(text.lower(), KINDS, what="kind"))
            args.append(text.lower())
        elif name == "name":
            if text not in PARAMETERS:
                raise CommandError(suggest(text, PARAMETERS, what="parameter"))
            args.append(text)
        else:
            args.append(text)
    if verb.target == "ooi" and not target.isdigit():
        raise CommandError(f"{verb.name}: OOI must be an id from `status`, got {target!r}")
    if verb.target == "robot" and not target.isdigit():
        raise CommandError(f"{verb.name}: ROBOT must be one robot id, got {target!r}")
    return Command(verb.name, target, tuple(args))
