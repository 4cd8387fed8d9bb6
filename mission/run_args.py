"""``magic run``'s command line, light to import: ``magic run --help`` and a bad argument
answer before the simulator, the GCS (gtsam) and the robots (numba, scipy) load
(:mod:`mission.run` parses with :func:`run_parser` and then does the work)."""

from __future__ import annotations

import argparse
from typing import cast

from protocol.cli_parser import CommandParser

__all__ = ["DEFAULT_DURATION_S", "DEFAULT_SEED", "run_parser"]

#: ``RunConfig``'s defaults the help states (one definition: :class:`mission.run.RunConfig`
#: uses them).
DEFAULT_DURATION_S = 180.0
DEFAULT_SEED = 0

_HELP_EPILOG = """\
what a run produces: a run directory (--out; default runs/<UTC date-time>-<world>-<seed>/):
the record, the final global map, report.json and report.md with plots, scored against the
ground truth (magic report RUN_DIR rebuilds it), and run.log: the GCS's and robots' log
(warnings counted in the summary; never printed through the progress). Progress goes to
stderr (a live table on a terminal, else one line per tenth of the run), the final summary
table and the report's headline to stdout; status 0 when the run completes, 2 on bad input
(one line on stderr), 130 after ^C and 143 after SIGTERM (the run stops at once, its links
are closed, the report is written from what ran and the summary so far is printed).

operators (paper 6): the run's GCS serves consoles over zenoh; the start prints the command
that reaches it ("magic run: operators: magic console --connect ... --mission ..."). Their
commands are interactions in the report (per minute, paper Fig. 24), and a robot on an
operator's goal reports itself semi-autonomous (time and distance per autonomy mode). A run
no console talks to is the same run as without. --rerun / --rerun-save: the operator views.

deterministic by default: a run is fixed by its world, seed, duration and configuration;
running it twice (on a loaded machine too) gives the same poses, events and figures, bit for
bit. --realtime delivers radio traffic on wall-clock threads instead: not repeatable.

terms: mission-s: simulated seconds; "xN real time": mission-s per wall second; events
(rule events): the simulator's rule events, from ground truth (a robot disabled by a trigger
or a hostile, a hostile neutralized, a civilian lasered); tasks ok/sent: tasks the GCS's
planners sent the robot / reports of one succeeded (--scripted: goals ok/sent, scripted goals
reached / given); task: the latest task status the robot reported; driven m: distance driven
(truth); nodes: pose nodes received by the ground side over the radio; uplink B/s: radio
bytes the robot sent per mission-second; closest to a static OOI / hostile: the team's
nearest approach (truth; keep-out 2.5 m / 5 m); teammate deadlocks broken: times a robot
backed off a teammate; gcs: the station's pose nodes, robots linked to its map, automatic
loop closures, hazards known (from robot detections only) and tasks sent; planner: its
latest decision.
"""


def run_parser(epilog: str | None = None) -> argparse.ArgumentParser:
    """``magic run``'s parser; ``epilog``: a text after the run's own (exit statuses)."""
    p = CommandParser(
        prog="magic run",
        description="Run the MAGIC mission on this machine, end to end: the simulator, one\n"
        "robot node per robot and the ground-control station (global map, loop closing, task\n"
        "allocation: it explores and neutralizes what the robots detect), talking over the\n"
        "simulated radio on real zenoh sessions. The team comes from the world's config.",
        epilog=_HELP_EPILOG if epilog is None else f"{_HELP_EPILOG}\n{epilog}",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--config",
        metavar="YAML",
        help="run configuration, a mission.run.RunConfig YAML: any subset of the keys "
        "--print-config lists (default: built-in defaults)",
    )
    p.add_argument(
        "--world",
        metavar="WORLD",
        help="world: a name in configs/world/ (small, magic_phase, magic_team100) or a YAML path "
        "(default: small)",
    )
    p.add_argument(
        "--duration",
        type=float,
        metavar="S",
        help=f"mission-seconds to run (default: {DEFAULT_DURATION_S:g})",
    )
    p.add_argument(
        "--seed",
        type=int,
        metavar="N",
        help=f"the run's seed, >= 0: goals, sensor noise, radio loss, robots' draws "
        f"(default: {DEFAULT_SEED})",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="wall-clock radio delivery (hardware in the loop); the run is NOT repeatable "
        "(default: deterministic lockstep)",
    )
    p.add_argument(
        "--robot-processes",
        action="store_true",
        help="each robot node in its own process (magic robot --lockstep), the simulator and "
        "the ground side in this one: the same run as in one process (default: one process)",
    )
    p.add_argument(
        "--gcs-process",
        action="store_true",
        help="the GCS in a process of its own (and the robot nodes in workers, as "
        "--robot-processes), over the zenoh link, journaling to RUN_DIR/journal.sqlite; if "
        "it dies (kill -9) the run restarts it from the journal (a warm standby takes over) "
        "and goes on, nothing acknowledged lost. The same run as in one process until a "
        "restart; consoles reach it, and its standby after a kill, through the printed "
        "`magic console` line (default: the GCS in this process)",
    )
    spread = p.add_argument_group(
        "across processes and hosts",
        "Each of these but --radio puts the robot nodes in worker processes (as\n"
        "--robot-processes); the simulator and the GCS stay in this one.",
    )
    spread.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="robot worker processes this process starts, robots split among them in "
        "consecutive id groups (default: one per core)",
    )
    spread.add_argument(
        "--remote-robots",
        metavar="IDS",
        help="robots (e.g. 4-7 or 0,2) whose workers another host starts with `magic robot "
        "--lockstep --id IDS --mission NAME --seed SEED` and endpoints reaching this one; the "
        "run waits for them (needs --mission; default: none)",
    )
    from protocol.process_cli import add_link_arguments

    # --mission, --radio, --connect, --listen, --mode, --link-config, --security: magic sim's,
    # robot's and gcs's own (an argument group takes arguments as a parser does)
    add_link_arguments(cast(argparse.ArgumentParser, spread))
    p.set_defaults(mission=None, radio=None)  # unset: the run's config (and a fresh name)
    for action in p._actions:
        if action.dest == "mission":
            action.help = (
                "zenoh mission name the robot workers join (default: a fresh one; name it "
                "when workers run on other hosts)"
            )
        elif action.dest == "radio":
            action.help = "radio model config (default: the run config's, radio/magic2010.yaml)"
    p.add_argument(
        "--out",
        metavar="RUN_DIR",
        help="run directory for the record and the report (report.json, report.md, plots, "
        "map); must not hold a run yet (default: runs/<UTC date-time>-<world>-<seed>/ under "
        "the current directory; --scripted writes none)",
    )
    p.add_argument(
        "--scripted",
        action="store_true",
        help="no GCS: a script sends goals and hazards drawn from the ground truth "
        "(comparisons only; default: the GCS and its planners drive the robots)",
    )
    p.add_argument(
        "--quiet", action="store_true", help="no progress, only the summary (default: progress)"
    )
    p.add_argument(
        "--print-config",
        action="store_true",
        help="print the run's whole configuration (every key --config takes, with the "
        "defaults, --config's values and the flags above applied) as YAML and exit",
    )
    from gcs.operator.node_hooks import add_operator_arguments

    add_operator_arguments(p)  # consoles and views on the run's GCS (issue 15)
    return p
