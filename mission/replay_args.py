"""``magic replay --carmen``'s command line, light to import: ``magic replay --help`` and a
bad argument answer before the GCS (gtsam, numba) loads (:mod:`mission.replay` parses with
:func:`replay_parser` and then does the work)."""

from __future__ import annotations

import argparse

from protocol.cli_parser import CommandParser

__all__ = ["replay_parser"]


def replay_parser(epilog: str | None = None) -> argparse.ArgumentParser:
    """``magic replay --carmen``'s parser; ``epilog``: a text after the options (exit
    statuses)."""
    p = CommandParser(
        prog="magic replay",
        epilog=epilog,
        description="Replay a CARMEN laser log through the GCS: pose nodes and scan grids into "
        "loop closing and optimization, evaluated against the log's poses and relations. "
        "Exit 0 with the result saved (an evaluation that could not be done is listed under "
        "'evaluation'), 2 on bad input, 130 on ^C and 143 on SIGTERM (what ran is saved).",
    )
    p.add_argument(
        "--carmen", required=True, metavar="FILE", help="CARMEN log (.log or .log.gz); required"
    )
    p.add_argument(
        "--relations",
        metavar="FILE",
        help="Kuemmerle et al. relations file 't1 t2 x y z roll pitch yaw' (s, m, rad); "
        "default: none",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="write summary.json, poses.txt, closures.txt and the map here; default: nothing "
        "written",
    )
    p.add_argument(
        "--config", metavar="YAML", help="replay configuration (ReplayConfig); default: built in"
    )
    p.add_argument(
        "--odom-noise",
        type=float,
        metavar="SCALE",
        help="add odometry noise: SCALE times the pose-node model's sigmas (unitless); "
        "default: the config's noise.scale, 0 (none)",
    )
    p.add_argument("--seed", type=int, help="seed of the odometry noise; default: the config's, 0")
    p.add_argument(
        "--odom-sigma-scale",
        type=float,
        metavar="S",
        help="the log's odometry is S times less certain than the pose-node model says "
        "(unitless); default: the config's, 1",
    )
    p.add_argument(
        "--no-scan-odometry",
        action="store_true",
        help="use the log's odometry as reported, not refined by matching each scan against "
        "the last few (paper 4.1's laser-aided odometry); default: the config's scan_odometry, "
        "on",
    )
    p.add_argument(
        "--scans", type=int, metavar="N", help="replay only the first N scans; default: all"
    )
    p.add_argument(
        "--progress-every",
        type=int,
        default=50,
        metavar="N",
        help="a progress line every N scans (default: %(default)s)",
    )
    p.add_argument(
        "--quiet", action="store_true", help="no progress lines, only the summary (default: off)"
    )
    return p
