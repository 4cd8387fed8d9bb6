"""``magic sim``'s command line, light to import: ``magic sim --help`` and a bad argument
answer before PyBullet loads (:mod:`sim.server` parses with :func:`sim_parser` and then does
the work)."""

from __future__ import annotations

import argparse
from pathlib import Path

from protocol.cli_parser import CommandParser
from protocol.process_cli import add_link_arguments

__all__ = ["sim_parser"]


def sim_parser(epilog: str | None = None) -> argparse.ArgumentParser:
    """``magic sim``'s parser; ``epilog``: a text after the options (exit statuses)."""
    p = CommandParser(
        prog="magic sim", description="Run the PyBullet simulator server.", epilog=epilog
    )
    p.add_argument(
        "--world",
        default="small",
        help="world: a name in configs/world/ (small, magic_phase) or a YAML path (default: small)",
    )
    p.add_argument("--sim-config", type=Path, help="simulator config YAML (SimulatorConfig)")
    add_link_arguments(p)
    p.add_argument(
        "--rtf", type=float, default=1.0, help="target real-time factor; 0 runs as fast as possible"
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="advance only when every robot node consumed its last sweep",
    )
    p.add_argument("--duration", type=float, help="mission seconds to run (default: until ^C)")
    p.add_argument("--no-zenoh", action="store_true", help="step the world without serving it")
    p.add_argument("--progress-s", type=float, default=2.0, help="wall seconds between reports")
    return p
