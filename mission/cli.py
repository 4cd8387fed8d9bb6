"""The ``magic`` command: one entry point for every process of the system.

Subcommands that are not built yet say so on stderr and exit with status 2; none prints
made-up output.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

__all__ = ["main"]

#: Subcommands that are specified but not built yet, and the issue that brings each.
_NOT_BUILT = {
    "console": "the operator console (operator interfaces)",
    "report": "mission reports against ground truth (metrics)",
}


def _build_parser() -> argparse.ArgumentParser:
    from mission.bench import SUITES  # names only: the suites import when they run

    parser = argparse.ArgumentParser(
        prog="magic",
        description="magic-recon: supervise a team of autonomous ground robots (MAGIC 2010).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    bench = sub.add_parser("bench", help="run a benchmark suite and print its metrics")
    bench.add_argument("suite", help=f"one of: {', '.join(sorted(SUITES))}")
    bench.add_argument("--quick", action="store_true", help="short run (under 60 s)")
    bench.add_argument("--json", metavar="FILE", help="also write the metrics as JSON to FILE")

    run = sub.add_parser(  # its own parser: mission/run.py
        "run", help="simulate a robot team on this machine, end to end", add_help=False
    )
    run.add_argument("args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)

    codec = sub.add_parser("codec", help="terrain-grid codecs: record a corpus, train the models")
    codec_sub = codec.add_subparsers(dest="codec_command", metavar="ACTION", required=True)
    record = codec_sub.add_parser("record", help="record grids from simulator runs (a corpus)")
    record.add_argument("--split", choices=("train", "test"), default="train")
    record.add_argument("--out", metavar="NPZ", help="corpus file (default: the shipped one)")
    train = codec_sub.add_parser("train", help="train the models and write the model file")
    train.add_argument("--corpus", metavar="NPZ", help="training corpus (default: shipped)")
    train.add_argument("--out", metavar="NPZ", help="model file (default: the shipped one)")
    train.add_argument("--version", type=int, help="model version (default: shipped + 1)")

    for name, what in (
        ("sim", "the simulator server: world, robots, sensors, rules, radio over zenoh"),
        ("robot", "one robot node, fed by a simulator (or hardware) over zenoh"),
        ("gcs", "the ground-control station: pose graph, loop closing, maps, over zenoh"),
        ("replay", "replay a CARMEN laser log through the GCS and evaluate it (--carmen FILE)"),
    ):
        p = sub.add_parser(name, help=what, add_help=False)
        p.add_argument("args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)

    for name, what in _NOT_BUILT.items():
        p = sub.add_parser(name, help=f"{what} [not built yet]", add_help=True)
        p.add_argument("args", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
    return parser


def _cmd_bench(args: argparse.Namespace) -> int:
    from rich.console import Console
    from rich.table import Table

    from mission.bench import BenchError, run_suite, write_json

    err = Console(stderr=True)
    out = Console()
    try:
        with err.status(f"bench {args.suite}...") as status:

            def progress(msg: str) -> None:
                status.update(f"bench {args.suite}: {msg}")
                err.log(msg)

            metrics = run_suite(args.suite, quick=args.quick, progress=progress)
    except BenchError as exc:
        err.print(f"magic bench: {exc}", style="red", markup=False, highlight=False)
        return 2
    table = Table(title=f"bench {args.suite}" + (" (quick)" if args.quick else ""))
    table.add_column("metric")
    table.add_column("value", justify="right")
    for key, value in metrics.items():
        table.add_row(key, f"{value:.6g}")
    out.print(table)
    if args.json:
        write_json(args.json, suite=args.suite, quick=args.quick, metrics=metrics)
        err.print(f"wrote {args.json}", markup=False, highlight=False)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ("sim", "robot", "gcs", "replay", "run"):  # their own parsers
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
    # Unbuilt subcommands take whatever options they will have (``magic robot --id 3``).
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
    what = _NOT_BUILT[args.command]
    print(f"magic {args.command}: not built yet; it arrives with {what}.", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
