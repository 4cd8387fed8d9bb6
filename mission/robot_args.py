"""``magic robot``'s command line, light to import: ``magic robot --help`` and a bad argument
answer before the robot node (numba, scipy, cv2) loads (:mod:`mission.robot_process` parses
with :func:`robot_parser` and then does the work)."""

from __future__ import annotations

import argparse
from pathlib import Path

from protocol.cli_parser import CommandParser
from protocol.process_cli import add_link_arguments

__all__ = ["robot_parser"]


def robot_parser(epilog: str | None = None) -> argparse.ArgumentParser:
    """``magic robot``'s parser; ``epilog``: a text after the options (exit statuses)."""
    p = CommandParser(prog="magic robot", description="Run robot nodes.", epilog=epilog)
    p.add_argument(
        "--id",
        required=True,
        metavar="IDS",
        help="robot id (as the simulator numbers them), or several hosted by this one process "
        "(a worker): 0,1,2 or 0-31",
    )
    add_link_arguments(p)
    p.add_argument("--config", type=Path, help="robot node config YAML (RobotNodeConfig)")
    p.add_argument("--duration", type=float, help="mission seconds to run (default: until ^C)")
    p.add_argument("--progress-s", type=float, default=5.0, help="wall seconds between reports")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="be stepped by the ground side of `magic run --robot-processes` (it starts these "
        "processes, or waits for them when they run on other hosts): every step answered, "
        "radio pumped per step, the same mission as in one process (default: process frames "
        "as they come, wall-clock radio)",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="the run's seed (the node's draws derive from it and the id; default: 0)",
    )
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="wall seconds to wait for a --connect endpoint to answer before giving up with "
        "one line naming it (default: 10)",
    )
    return p
