"""Console macros: command lines bound to function keys, from a YAML file (paper 6.2).

::

    # configs/console/macros.yaml
    f1:
      help: release every robot to the planners and resume
      commands: ["auto all", "resume all"]

Keys ``f1`` .. ``f12``; ``commands`` run in order, each as if typed (a failure stops the rest).
Unknown keys, an empty command list or a command that does not parse fail at load time with
the file and the key (:class:`~protocol.config.ConfigError`).
"""

from __future__ import annotations

from pathlib import Path

import msgspec

from gcs.operator.grammar import LOCAL_VERBS, CommandError, parse_line
from protocol.config import CONFIGS_DIR, ConfigError, load_config

__all__ = ["DEFAULT_MACROS", "FUNCTION_KEYS", "Macro", "load_macros"]

FUNCTION_KEYS = tuple(f"f{i}" for i in range(1, 13))
DEFAULT_MACROS = CONFIGS_DIR / "console" / "macros.yaml"


class Macro(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``commands``: the lines to run; ``help``: what the key does, for `macros` and the bar."""

    commands: tuple[str, ...]
    help: str = ""


def load_macros(path: str | Path | None = None) -> dict[str, Macro]:
    """Macros by function key (``f1`` ...) from ``path`` (default: the shipped file)."""
    p = Path(path) if path is not None else DEFAULT_MACROS
    raw = load_config(p, dict[str, Macro])
    out: dict[str, Macro] = {}
    for key, macro in raw.items():
        k = key.lower()
        if k not in FUNCTION_KEYS:
            raise ConfigError(str(p), key, f"expected a function key f1..f12, got {key!r}")
        if not macro.commands:
            raise ConfigError(str(p), f"{key}.commands", "no commands")
        for i, line in enumerate(macro.commands):
            if line.split()[:1] and line.split()[0] in LOCAL_VERBS:
                continue
            try:
                parse_line(line)
            except CommandError as err:
                raise ConfigError(str(p), f"{key}.commands[{i}]", str(err)) from None
        out[k] = macro
    return out
