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

    run = sub.add_parser("run", help="simulate a robot team on this machine, end to end")
    run.add_argument("--config", metavar="YAML", help="run configuration (mission.run.RunConfig)")
    run.add_argument(
        "--world",
        metavar="WORLD",
        help="world: a name in configs/world/ (small, magic_phase) or a YAML path (default: small)",
    )
    run.add_argument("--duration", type=float, metavar="S", help="mission seconds to run")
    run.add_argument("--seed", type=int, help="seed of the scripted goals")
    run.add_argument("--quiet", action="store_true", help="no live table, only the summary")

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


def _cmd_run(args: argparse.Namespace) -> int:
    import msgspec
    from rich.console import Console
    from rich.live import Live

    from mission.config import ConfigError, load_config
    from mission.run import RunConfig, RunReport, format_progress, run_mission

    err = Console(stderr=True)

    def fail(problem: object) -> int:
        err.print(f"magic run: {problem}", style="red", markup=False, highlight=False)
        return 2

    try:
        config = load_config(args.config, RunConfig) if args.config else RunConfig()
        overrides = {
            k: v
            for k, v in (("world", args.world), ("duration_s", args.duration), ("seed", args.seed))
            if v is not None
        }
        if overrides:
            config = msgspec.structs.replace(config, **overrides)
    except (ConfigError, ValueError) as exc:
        return fail(exc)
    total_s = config.duration_s
    try:
        if args.quiet:
            report = run_mission(config)
        elif err.is_terminal:
            with Live(console=err, refresh_per_second=4) as live:
                report = run_mission(
                    config, on_progress=lambda r: live.update(format_progress(r, total_s))
                )
        else:  # a log or a pipe: a line every tenth of the run, not a redrawn table
            next_s = [0.0]

            def line(r: RunReport) -> None:
                if r.mission_s >= next_s[0]:
                    next_s[0] += total_s / 10
                    err.print(
                        f"magic run: {r.mission_s:.0f} / {total_s:g} mission-s, "
                        f"x{r.rtf:.1f} real time, {len(r.events)} events",
                        markup=False,
                        highlight=False,
                    )

            report = run_mission(config, on_progress=line)
    except ConfigError as exc:
        return fail(exc)
    Console().print(format_progress(report, total_s))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ("sim", "robot", "gcs", "replay"):  # commands with their own parsers
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
    if args.command in ("bench", "run"):
        if unknown:
            parser.error(f"unrecognized arguments: {' '.join(unknown)}")
        return _cmd_bench(args) if args.command == "bench" else _cmd_run(args)
    what = _NOT_BUILT[args.command]
    print(f"magic {args.command}: not built yet; it arrives with {what}.", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
