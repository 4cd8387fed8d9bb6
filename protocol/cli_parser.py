"""The argument parser every ``magic`` command uses: a usage error is one line.

The exit-status contract (:mod:`protocol.process_cli`) promises bad input one line on stderr,
naming what is wrong, and status 2. :class:`argparse.ArgumentParser` prints the whole usage
block first (nine lines for ``magic run``), which buries the one line that matters;
:class:`CommandParser` prints ``PROG: MESSAGE (PROG --help says what it takes)`` instead.
Sub-command parsers made with ``add_subparsers`` are of the same class. Light to import: a
bad argument is answered before any of a command's work (gtsam, PyBullet, numba) loads.
"""

from __future__ import annotations

import argparse
from typing import NoReturn

__all__ = ["CommandParser"]


class CommandParser(argparse.ArgumentParser):
    """An :class:`argparse.ArgumentParser` whose usage errors are one line and status 2."""

    def error(self, message: str) -> NoReturn:
        text = " ".join(message.split())
        self.exit(2, f"{self.prog}: {text} ({self.prog} --help says what it takes)\n")
