"""Completion for the console: commands, their arguments, robot ids and OOI ids (paper 6.2).

:func:`candidates` is pure: the text before the cursor and the GCS's latest
:class:`~protocol.operator.GcsStatus` in, ``(completion, description)`` pairs out, each
completing the word under the cursor. :class:`ConsoleCompleter` wraps it for prompt_toolkit.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

from prompt_toolkit.completion import CompleteEvent, Completer, Completion
from prompt_toolkit.document import Document

from gcs.operator.grammar import GROUPS, KINDS, LOCAL_VERBS, PARAMETERS, VERBS
from protocol.operator import GcsStatus

__all__ = ["ConsoleCompleter", "candidates"]

_LOCAL_HELP = {
    "help": "help [COMMAND]: what each command does",
    "macros": "the function-key macros",
    "history": "the commands typed so far",
    "quit": "leave the console",
    "exit": "leave the console",
}


def _robots(status: GcsStatus | None) -> list[tuple[str, str]]:
    if status is None:
        return []
    return [(str(r.robot_id), f"{r.role} {r.mode} {r.control} {r.task}") for r in status.robots]


def _subset(word: str, status: GcsStatus | None) -> list[tuple[str, str]]:
    """Complete the last item of a comma list of robots and groups."""
    head, _, last = word.rpartition(",")
    prefix = head + "," if head else ""
    items = [(g, "robot group") for g in GROUPS] + _robots(status)
    return [(prefix + w, d) for w, d in items if w.startswith(last)]


def _hazards(
    word: str, status: GcsStatus | None, *, only: Iterable[str] = ()
) -> list[tuple[str, str]]:
    if status is None:
        return []
    wanted = set(only)
    return [
        (
            str(h.hazard_id),
            f"{h.kind} at ({h.position_in_map[0]:.1f}, {h.position_in_map[1]:.1f}) {h.state}",
        )
        for h in status.hazards
        if str(h.hazard_id).startswith(word) and (not wanted or h.state in wanted)
    ]


def _filter(word: str, items: Iterable[tuple[str, str]]) -> list[tuple[str, str]]:
    return [(w, d) for w, d in items if w.startswith(word)]


def candidates(text: str, status: GcsStatus | None) -> list[tuple[str, str]]:
    """What may complete the last word of ``text`` (module docstring)."""
    words = text.split()
    if not text or text[-1].isspace():
        words.append("")
    word = words[-1]
    if len(words) == 1:
        items = [(v.name, v.usage()) for v in VERBS.values()]
        items += [(v, _LOCAL_HELP[v]) for v in LOCAL_VERBS]
        return _filter(word.lower(), items)
    verb_name = words[0].lower()
    if verb_name == "help" and len(words) == 2:
        return _filter(word, [(v.name, v.usage()) for v in VERBS.values()])
    verb = VERBS.get(verb_name)
    if verb is None:
        return []
    position = len(words) - 2  # index among the words after the verb
    slots: list[str] = []
    if verb.target in ("robots", "robot", "ooi", "optional_robots"):
        slots.append(verb.target)
    slots += [a.rstrip("?") for a in verb.args]
    if position >= len(slots):
        return []
    slot = slots[position]
    if slot in ("robots", "optional_robots"):
        return _subset(word, status)
    if slot == "robot":
        if verb.name == "neutralize" and status is not None:
            disruptors = [(i, d) for i, d in _robots(status) if d.startswith("disruptor")]
            return _filter(word, disruptors or _robots(status))
        return _filter(word, _robots(status))
    if slot == "ooi":
        only = ("pending_approval", "live") if verb.name == "approve" else ()
        return _hazards(word, status, only=only)
    if slot == "kind":
        return _filter(word.lower(), [(k, "object kind") for k in KINDS])
    if slot == "name":
        return _filter(word, PARAMETERS.items())
    if slot in ("pose_a", "pose_b"):
        if ":" in word:
            rid = word.split(":", 1)[0]
            return _filter(word, [(f"{rid}:last", "its latest pose"), (f"{rid}:0", "its first")])
        return [(f"{r}:", d) for r, d in _robots(status) if r.startswith(word)]
    if slot in ("x_m", "y_m", "since_s", "value"):
        return []  # numbers: nothing to offer
    return []


class ConsoleCompleter(Completer):
    """prompt_toolkit completer over :func:`candidates` with the latest status."""

    def __init__(self, status: Callable[[], GcsStatus | None]) -> None:
        self._status = status

    def get_completions(self, document: Document, complete_event: CompleteEvent):  # type: ignore[no-untyped-def]
        text = document.text_before_cursor
        words = text.split()
        word = "" if (not text or text[-1].isspace() or not words) else words[-1]
        for cand, meta in candidates(text, self._status()):
            yield Completion(cand, start_position=-len(word), display_meta=meta)
