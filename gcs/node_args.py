"""``magic gcs``'s command line, light to import: ``magic gcs --help`` and a bad argument
answer before the station (gtsam, numba, scipy) loads (:mod:`gcs.node` parses with
:func:`gcs_parser` and then does the work)."""

from __future__ import annotations

import argparse
from pathlib import Path

from gcs.operator.node_hooks import add_operator_arguments
from protocol.cli_parser import CommandParser
from protocol.process_cli import add_link_arguments

__all__ = ["gcs_parser"]

_DESCRIPTION = """\
Run the ground-control station (GCS) as its own process. It takes every robot's uplink (pose
nodes, terrain grids, fiducials, detections) over zenoh, builds the only global map (factor
graph, loop closing, iSAM2) and sends each robot a HazardUpdate (every linked robot's
map_from_odom and the hazards) every frames_period_s of mission time (GroundStationConfig,
default 2 s). Bad messages are refused and counted, never fatal; a solver fault is recovered
(batch re-solve) and counted.

Prints a status line every --progress-s wall seconds and a one-line summary at the end: mission
time (s), robots seen and linked to map, pose nodes, grids, graph edges, rejected messages,
solver recoveries/faults and clock anomalies. Exit status: 0 when --duration has passed, 2 on
bad input (one line on stderr, before anything starts), 130 after SIGINT, 143 after SIGTERM.
"""

#: Help of the shared link options, with their defaults and units.
_LINK_HELP = {
    "mission": "mission name in the zenoh keys (default: %(default)s)",
    "radio": "radio config YAML (RadioConfig; default: configs/radio/magic2010.yaml)",
    "connect": "zenoh endpoint to connect to, e.g. tcp/10.0.0.2:7447; repeatable (default: none)",
    "listen": "zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7448; repeatable "
    "(default: tcp/127.0.0.1 on an ephemeral port)",
}


def gcs_parser(epilog: str | None = None) -> argparse.ArgumentParser:
    """``magic gcs``'s parser; ``epilog``: a text after the options (exit statuses)."""
    p = CommandParser(
        prog="magic gcs",
        epilog=epilog,
        description=_DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_link_arguments(p)
    add_operator_arguments(p)  # operator (issue 15)
    for action in p._actions:
        if action.dest in _LINK_HELP:
            action.help = _LINK_HELP[action.dest]
            action.metavar = {"radio": "YAML", "mission": "NAME"}.get(action.dest, "ENDPOINT")
    p.add_argument(
        "--config",
        type=Path,
        metavar="YAML",
        help="GCS config YAML (GroundStationConfig: roster, loop closing, bounds on "
        "covariances and clocks, ...); default: built in",
    )
    p.add_argument(
        "--clock",
        choices=("sim", "wall"),
        default="sim",
        help="mission time source: the simulator's clock ticks, or this host's clock for real "
        "robots (default: %(default)s)",
    )
    p.add_argument(
        "--duration",
        type=float,
        metavar="S",
        help="mission seconds to run (default: until SIGINT or SIGTERM)",
    )
    p.add_argument(
        "--step-s",
        type=float,
        metavar="S",
        default=0.5,
        help="mission seconds between station steps: loop closing, optimization, frames "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--budget-s",
        type=float,
        metavar="S",
        default=0.2,
        help="wall seconds of loop closing per step (default: %(default)s)",
    )
    p.add_argument(
        "--tasking-config",
        type=Path,
        metavar="YAML",
        help="task allocation config YAML (gcs.mission_control.MissionControlConfig: plan "
        "period, disruptors, area of operations, the planners' settings); --disruptors, "
        "--plan-s and --no-tasking override it (default: built in)",
    )
    p.add_argument(
        "--disruptors",
        metavar="IDS",
        default="",
        help="comma-separated ids of the team's disruptors; every other robot is a sensor "
        "robot (default: none)",
    )
    p.add_argument(
        "--plan-s",
        type=float,
        metavar="S",
        help="mission seconds between task allocations (default: 2)",
    )
    p.add_argument(
        "--no-tasking",
        action="store_true",
        help="estimation only: no task allocation, robots get no tasks from this GCS "
        "(default: the planners task every robot)",
    )
    p.add_argument(
        "--out",
        type=Path,
        metavar="RUN_DIR",
        help="run directory: the GCS journal (journal.sqlite: every uplink message, step, "
        "planner decision and operator command) and gcs.json (the resolved configuration); "
        "must not hold a journal yet (default: runs/<UTC date-time>-gcs-<mission>/)",
    )
    p.add_argument(
        "--resume",
        type=Path,
        metavar="RUN_DIR",
        help="carry on a GCS that was killed: rebuild the station from RUN_DIR/journal.sqlite "
        "(graph, closures, hazards, OOIs), re-plan from it, continue every robot's radio "
        "streams where the journal left them, and keep journaling there (its configuration "
        "is the journal's: no --config)",
    )
    p.add_argument(
        "--progress-s",
        type=float,
        metavar="S",
        default=5.0,
        help="wall seconds between status lines (default: %(default)s)",
    )
    return p
