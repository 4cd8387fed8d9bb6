"""``import pybullet`` without its banner: the module prints its build time on the C ``stderr``
when imported, which would land in every command's error stream before the first line that
matters (a config error, progress). The import runs with file descriptor 2 pointed at
``/dev/null``; an import failure still raises as usual (Python errors are exceptions)."""

from __future__ import annotations

import os
import sys
from types import ModuleType

__all__ = ["import_pybullet"]


def import_pybullet() -> ModuleType:
    """The ``pybullet`` module, imported once, silently."""
    if "pybullet" in sys.modules:
        return sys.modules["pybullet"]
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        import pybullet
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)
    return pybullet
