"""The ``magic`` command: one entry point for every process of the system.

Exit statuses, the same for every subcommand (:mod:`protocol.process_cli`): 0 done, 1 the
work failed, 2 bad input (one line on stderr naming what and where, before any long work),
130 stopped by SIGINT, 143 stopped by SIGTERM. :func:`main` makes SIGTERM raise like ^C for
every subcommand and is the last line of defence: a stop that escapes a subcommand ends
with one line (``magic X: stopped by SIGINT``), never a traceback.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

from protocol.cli_parser import CommandParser

__all__ = ["main"]

#: Subcommands with their own parser (``magic X --help`` is theirs): what each produces.
_OWN_PARSERS = {
    "sim": "the simulator server (world, robots, sensors, rules, radio) over zenoh: progress "
    "and a summary line",
    "robot": "one robot node, fed by a simulator (or hardware) over zenoh: a summary line",
    "gcs": "the ground-control station (pose graph, loop closing, maps) over zenoh: status "
    "lines and a summary line",
    "replay": "replay a CARMEN laser log through the GCS and evaluate it (--carmen FILE: the "
    "evaluation, map and summary in --out), or a run's GCS journal (RUN_DIR: the same graph?)",
    "console": "the operators' console: signed commands to a running GCS over zenoh, with "
    "completion, robot subsets, macros (-c CMD, --script FILE without a terminal)",
    "perception": "learn the robots' perception thresholds in simulated worlds: LIDAR shape "
    "(record | train | evaluate: .npz worlds, versioned JSON) and camera colour (colour)",
}

_PERCEPTION_HELP = """\
usage: magic perception {record,train,evaluate} ...  LIDAR shape thresholds (5.2.1)
       magic perception colour [options]             YCrCb colour thresholds (5.2.1)

  record    record labelled LIDAR sweeps of seeded simulated worlds (--seeds, --out DIR)
  train     learn the shape thresholds from recorded worlds (versioned JSON, --out)
  evaluate  score a shape thresholds file on held-out recorded worlds
  colour    render objects, people and distractors under random light in training worlds,
            learn the colour thresholds (--out FILE) and score them on held-out worlds

`magic perception ACTION --help` says what each takes and writes.
"""

#: Every command's help ends with it (lines kept short: raw-text helps print it as it is).
_EXIT_STATUSES = (
    "exit status: 0 done, 1 the work failed, 2 bad input (one line on stderr naming it,\n"
    "before any long work), 130 stopped by SIGINT (^C), 143 stopped by SIGTERM; a stopped\n"
    "command summarises what ran and keeps what it already wrote."
)


class _HelpFormatter(argparse.HelpFormatter):
    """Help as wide as the terminal (100 columns when piped): option texts keep their
    defaults and units on one line where they fit."""

    def __init__(self, prog: str) -> None:
        width = os.get_terminal_size().columns if sys.stdout.isatty() else 100
        super().__init__(prog, width=max(width, 60), max_help_position=28)


def _build_parser() -> argparse.ArgumentParser:
    from mission.bench import BENCH_DIR_ENV, SUITES, bench_root

    parser = CommandParser(
        prog="magic",
        description="magic-recon: supervise a team of autonomous ground robots (MAGIC 2010).\n"
        "`magic COMMAND --help` says what each command takes, produces and where.",
        epilog=_EXIT_STATUSES,
        formatter_class=_HelpFormatter,
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    bench = sub.add_parser(
        "bench",
        help="run a benchmark suite: its metrics as a table on stdout (and --json FILE)",
        description="Run benchmark suite SUITE and print its metrics as a table on stdout "
        "(progress on stderr). Maps and plots a suite draws go to "
        f"${BENCH_DIR_ENV}/SUITE (now: {bench_root()}/SUITE; default: the system temp "
        "dir's magic-bench/SUITE).",
        epilog=_EXIT_STATUSES,
        formatter_class=_HelpFormatter,
    )
    bench.add_argument("suite", metavar="SUITE", help=f"one of: {', '.join(sorted(SUITES))}")
    bench.add_argument(
        "--quick",
        action="store_true",
        help="short run, under 60 s wall time, every metric still measured "
        "(default: the full run, minutes)",
    )
    bench.add_argument(
        "--json",
        metavar="FILE",
        help="also write {suite, quick, metrics} as JSON to FILE; its directory must exist "
        "and is checked before the suite runs (default: no file)",
    )

    run = sub.add_parser(  # its own parser: mission/run.py
        "run", help="simulate a robot team on this machine, end to end", add_help=False
    )
    run.add_argument("args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)

    for name, what in _OWN_PARSERS.items():
        p = sub.add_parser(name, help=what, add_help=False)
        p.add_argument("args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)

    codec = sub.add_parser(
        "codec",
        help="terrain-grid codecs: record a corpus, train the models (.npz files)",
        description="Terrain-grid codecs (paper 4.3.4): record a corpus of grids from "
        "simulator runs, train the context models from it.",
        epilog=_EXIT_STATUSES,
        formatter_class=_HelpFormatter,
    )
    codec_sub = codec.add_subparsers(dest="codec_command", metavar="ACTION", required=True)
    record = codec_sub.add_parser(
        "record",
        help="record grids from simulator runs: a corpus .npz",
        description="Run the simulator worlds of the split with their whole teams (minutes) "
        "and write every pose node's terrain grid to a corpus .npz; progress on stderr.",
        formatter_class=_HelpFormatter,
    )
    record.add_argument(
        "--split",
        choices=("train", "test"),
        default="train",
        help="which worlds to run (default: %(default)s)",
    )
    record.add_argument(
        "--out",
        metavar="NPZ",
        help="corpus file to write, checked first (default: the shipped "
        "compression/corpus/terrain_SPLIT.npz)",
    )
    train = codec_sub.add_parser(
        "train",
        help="train the models from a corpus: the model file .npz",
        description="Train the codec context models from a corpus and write the model file; "
        "progress on stderr.",
        formatter_class=_HelpFormatter,
    )
    train.add_argument(
        "--corpus",
        metavar="NPZ",
        help="training corpus, checked first (default: the shipped "
        "compression/corpus/terrain_train.npz)",
    )
    train.add_argument(
        "--out",
        metavar="NPZ",
        help="model file to write, checked first (default: the shipped model file)",
    )
    train.add_argument(
        "--version",
        type=int,
        metavar="N",
        help="model version 1..255 in every stream header (default: the shipped one + 1)",
    )

    report = sub.add_parser(
        "report",
        help="rebuild a mission's report from its run directory: report.json, report.md, plots",
        description="Score the run recorded in RUN_DIR against its ground truth and write "
        "RUN_DIR/report.json (metrics, time series, configuration), RUN_DIR/report.md (with "
        "the plots) and RUN_DIR/plots/*.png, from the run directory alone (RUN_DIR/record/, "
        "written by the mission's recorder). The headline metrics go to stdout.",
        epilog=_EXIT_STATUSES,
        formatter_class=_HelpFormatter,
    )
    report.add_argument("run_dir", metavar="RUN_DIR", help="a run directory (has record/)")
    return parser


def _console(*, stderr: bool = False):  # type: ignore[no-untyped-def]
    """A rich console that does not wrap mid-phrase when piped (a terminal keeps its width)."""
    from rich.console import Console

    stream = sys.stderr if stderr else sys.stdout
    if stream.isatty():
        return Console(stderr=stderr, highlight=False, log_path=False)
    return Console(stderr=stderr, highlight=False, width=160, soft_wrap=True)


def _cmd_bench(args: argparse.Namespace) -> int:
    from rich.table import Table

    from mission.bench import BENCH_DIR_ENV, SUITES, BenchError, bench_root, run_suite, write_json
    from protocol.process_cli import (
        check_output_dir,
        check_output_file,
        exit_code_for,
        one_line,
        signals_received,
        stop_cause,
        stop_exception,
        stopped_line,
    )

    err = _console(stderr=True)
    out = _console()

    def fail(problem: object) -> int:
        err.print(one_line(f"magic bench: {problem}"), style="red", markup=False)
        return 2

    # everything the suite's end needs, checked before it starts (a suite runs for minutes)
    if args.suite not in SUITES:
        known = ", ".join(sorted(SUITES))
        return fail(f"unknown benchmark suite {args.suite!r}; known suites: {known}")
    try:
        if args.json:
            check_output_file(args.json, "--json")
        check_output_dir(bench_root(), f"${BENCH_DIR_ENV}")
    except ValueError as exc:
        return fail(exc)

    start = time.monotonic()
    stops_before = len(signals_received())
    last = [""]
    try:
        with err.status(f"bench {args.suite}...") as status:

            def progress(msg: str) -> None:
                last[0] = msg
                status.update(f"bench {args.suite}: {msg}")
                if err.is_terminal:
                    err.log(msg, markup=False)
                else:  # piped: plain timestamped lines, never padded or wrapped
                    err.print(f"{time.strftime('%H:%M:%S')} {msg}", markup=False)

            metrics = run_suite(args.suite, quick=args.quick, progress=progress)
        if len(signals_received()) > stops_before:  # the stop was swallowed by C code
            raise stop_exception(signals_received()[stops_before])
    except BenchError as exc:
        return fail(exc)
    except (KeyboardInterrupt, Exception) as exc:
        stop = stop_cause(exc)  # a stop, or an error C code made of one
        if stop is None:
            raise
        took = f"suite {args.suite} stopped after {time.monotonic() - start:.0f} s"
        detail = f"{took}; last: {last[0]}" if last[0] else took
        err.print(one_line(stopped_line("bench", stop, detail)), markup=False)
        return exit_code_for(stop)
    table = Table(title=f"bench {args.suite}" + (" (quick)" if args.quick else ""))
    table.add_column("metric", no_wrap=True)
    table.add_column("value", justify="right", no_wrap=True)
    for key, value in metrics.items():
        table.add_row(key, f"{value:.6g}")
    out.print(table)
    if args.json:
        try:
            write_json(args.json, suite=args.suite, quick=args.quick, metrics=metrics)
        except OSError as exc:  # the directory went away while the suite ran
            err.print(one_line(f"magic bench: cannot write {args.json}: {exc.strerror}"))
            return 1
        err.print(f"wrote {args.json}", markup=False)
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    """``magic report RUN_DIR``: rebuild the report; a bad RUN_DIR is one line, status 2."""
    from protocol.process_cli import one_line

    err = _console(stderr=True)
    from mission.report.report_builder import RunDirError, build_report

    try:
        metrics = build_report(args.run_dir)
    except RunDirError as exc:
        err.print(one_line(f"magic report: {exc}"), style="red", markup=False)
        return 2
    except OSError as exc:  # e.g. the run directory is read-only
        err.print(one_line(f"magic report: cannot write into {args.run_dir}: {exc}"), markup=False)
        return 1
    out = _console()
    from mission.report.markdown import headline_lines

    for line in headline_lines(metrics):
        out.print(line, markup=False)
    err.print(f"wrote {args.run_dir}/report.json, report.md and plots/", markup=False)
    return 0


def _cmd_perception(argv: list[str]) -> int:
    """``magic perception ...``: the shape (mission/perception_training.py) and colour
    (mission/perception_camera_training.py) recorders and trainers."""
    if argv and argv[0] == "colour":
        from mission.perception_camera_training import main as colour_main

        return colour_main(argv[1:])
    if not argv or argv[0] in ("-h", "--help"):
        print(_PERCEPTION_HELP, end="", file=sys.stdout if argv else sys.stderr)
        return 0 if argv else 2
    from mission.perception_training import main as shape_main

    return shape_main(argv)


def _light_parser(command: str) -> argparse.ArgumentParser:
    """``magic COMMAND``'s own parser with the exit statuses as its epilog, from a module
    that imports none of the command's work (gtsam, PyBullet, numba, scipy load after)."""
    if command == "run":
        from mission.run_args import run_parser

        return run_parser(_EXIT_STATUSES)
    if command == "robot":
        from mission.robot_args import robot_parser

        return robot_parser(_EXIT_STATUSES)
    if command == "replay":
        from mission.replay_args import replay_parser

        return replay_parser(_EXIT_STATUSES)
    if command == "gcs":
        from gcs.node_args import gcs_parser

        return gcs_parser(_EXIT_STATUSES)
    from sim.server_args import sim_parser

    return sim_parser(_EXIT_STATUSES)


def _dispatch(argv: list[str]) -> int:
    if argv and argv[0] == "perception":  # its own parsers: mission/perception_*training.py
        return _cmd_perception(argv[1:])
    if argv and argv[0] == "console":  # its own parser: gcs/console/repl.py
        from gcs.console.repl import main as console_main

        return console_main(argv[1:])
    if argv and argv[0] in ("sim", "robot", "gcs", "replay", "run"):  # their own parsers
        # parsed first without the work's modules: --help and a bad argument answer at once
        journal_replay = argv[0] == "replay" and len(argv) > 1 and not argv[1].startswith("-")
        if not journal_replay:
            try:
                _light_parser(argv[0]).parse_args(argv[1:])
            except SystemExit as exit_:
                if argv[0] in ("run", "replay"):  # their main lets argparse exit too
                    raise
                return int(exit_.code or 0)  # sim, robot, gcs return the status
        if argv[0] == "run":
            from mission.run import main as run_main

            return run_main(argv[1:])
        if argv[0] == "sim":
            from sim.server import main as sim_main

            return sim_main(argv[1:])
        if argv[0] == "replay":
            from mission.replay import main as replay_main

            return replay_main(argv[1:])
        if argv[0] == "gcs":
            from gcs.node import main as gcs_main

            return gcs_main(argv[1:])
        from mission.robot_process import main as robot_main

        return robot_main(argv[1:])
    parser = _build_parser()
    args, unknown = parser.parse_known_args(argv)
    if args.command == "codec":
        if unknown:
            parser.error(f"unrecognized arguments: {' '.join(unknown)}")
        from mission.codec_training import codec_command

        return codec_command(args)
    if args.command == "bench":
        if unknown:
            parser.error(f"unrecognized arguments: {' '.join(unknown)}")
        return _cmd_bench(args)
    assert args.command == "report", args.command  # the others have parsers of their own
    if unknown:
        parser.error(f"unrecognized arguments: {' '.join(unknown)}")
    return _cmd_report(args)


def _stop_children() -> None:
    """Terminate the multiprocessing children a stopped command leaves (they would outlive
    it on SIGTERM, which reaches the parent only)."""
    mp = sys.modules.get("multiprocessing")
    if mp is None:
        return
    for child in mp.active_children():
        child.terminate()
    for child in mp.active_children():
        child.join(5.0)


def _quiet_stops(hook: Callable[[Any], object]) -> Callable[[Any], object]:
    """``sys.unraisablehook`` that drops a stop raised where C code swallows it (a ctypes
    callback: numba compiling); the stop is on record (``signals_received``) and the
    command acts on it. Everything else goes to ``hook``."""

    def quiet(unraisable: Any) -> object:
        if isinstance(unraisable.exc_value, KeyboardInterrupt):
            return None
        return hook(unraisable)

    return quiet


def main(argv: Sequence[str] | None = None) -> int:
    """``magic COMMAND ...``: returns the exit status (module doc)."""
    from protocol.process_cli import (
        exit_code_for,
        install_stop_handlers,
        stop_cause,
        stopped_line,
    )

    argv = list(sys.argv[1:] if argv is None else argv)
    command = argv[0] if argv and not argv[0].startswith("-") else "?"
    previous = install_stop_handlers()
    previous_hook = sys.unraisablehook
    sys.unraisablehook = _quiet_stops(previous_hook)
    try:
        return _dispatch(argv)
    except BrokenPipeError:  # ``magic ... | head``: the reader left; no traceback
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 141
    except (KeyboardInterrupt, Exception) as exc:  # ^C or SIGTERM (Terminated) escaping
        stop = stop_cause(exc)  # (or an error C code made of one: numba's SystemError)
        if stop is None:
            raise
        for sig in previous:  # a second signal does not cut the last line short
            signal.signal(sig, signal.SIG_IGN)
        _stop_children()
        print(stopped_line(command, stop), file=sys.stderr, flush=True)
        return exit_code_for(stop)
    finally:
        sys.unraisablehook = previous_hook
        for sig, handler in previous.items():
            if handler is not None:
                signal.signal(sig, handler)


if __name__ == "__main__":
    sys.exit(main())
