"""What ``magic gcs`` needs to run the operator station: its options, their checks (before the
link opens) and the :class:`~gcs.operator.service.OperatorService` they describe.

Options: ``--rerun spawn`` (start a viewer), ``--rerun connect [HOST:PORT]`` (a running viewer,
default 127.0.0.1:9876), ``--rerun serve`` (rerun's web viewer, served by this process at http://HOST:9090),
``--rerun-save FILE.rrd`` (a recording), ``--operator-key FILE`` (the operators' shared key;
default ``$MAGIC_OPERATOR_KEY`` or ``~/.config/magic/operator.key``, created on first use).
A viewer that is not running never slows or stops the GCS (the views draw on their own thread
and retry). Commands from consoles are always served.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from gcs.operator.service import OperatorService
from protocol.operator import KeyFileError, default_key_path, load_or_create_key

__all__ = [
    "add_operator_arguments",
    "check_operator_arguments",
    "console_command",
    "operator_service",
]


def add_operator_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--rerun",
        nargs="+",
        metavar="MODE",
        help="live operator views: `spawn` (start a rerun viewer), `connect [HOST:PORT]` (a "
        "running viewer, default 127.0.0.1:9876) or `serve` (rerun's web viewer from this "
        "process: open http://<gcs host>:9090; data on gRPC port 9876); a viewer that is not "
        "there never slows the GCS (default: no live views)",
    )
    p.add_argument(
        "--rerun-save",
        type=Path,
        metavar="FILE.rrd",
        help="write the operator views to a rerun recording (default: none)",
    )
    p.add_argument(
        "--operator-key",
        type=Path,
        metavar="FILE",
        help="the operators' shared HMAC key (hex, mode 0600; created on first use); default "
        f"$MAGIC_OPERATOR_KEY or {default_key_path()}",
    )


def _sinks(args: argparse.Namespace) -> list[str]:
    from gcs.views.rerun_views import parse_sink

    sinks = []
    if args.rerun:
        mode, rest = args.rerun[0], args.rerun[1:]
        if mode not in ("spawn", "connect", "serve"):
            raise ValueError(f"--rerun: expected spawn, connect [HOST:PORT] or serve, got {mode!r}")
        if rest and mode != "connect":
            raise ValueError(f"--rerun {mode}: takes no address")
        if len(rest) > 1:
            raise ValueError("--rerun connect: one HOST:PORT")
        spec = "web" if mode == "serve" else " ".join([mode, *rest])
        sinks.append(spec)
    if args.rerun_save is not None:
        path = Path(args.rerun_save)
        if path.suffix != ".rrd":
            raise ValueError(f"--rerun-save {path}: expected a .rrd file name")
        sinks.append(f"save {path}")
    for s in sinks:
        try:
            parse_sink(s)
        except ValueError as err:
            raise ValueError(f"--rerun: {err}") from None
    return sinks


def check_operator_arguments(args: argparse.Namespace) -> None:
    """ValueError (one line naming the option) for bad views options or an unusable key."""
    _sinks(args)
    path = args.operator_key if args.operator_key is not None else default_key_path()
    if Path(path).exists():  # a missing one is made at the first command
        try:
            load_or_create_key(path, create=False)
        except (KeyFileError, OSError) as err:
            raise ValueError(f"--operator-key: {err}") from None


def operator_service(args: argparse.Namespace, link: Any, control: Any = None) -> OperatorService:
    """The service the options describe (call :func:`check_operator_arguments` first)."""
    return OperatorService(
        link,
        key_file=args.operator_key,
        views=_sinks(args) or None,
        control=control,
    )


def console_command(link: Any) -> str:
    """The ``magic console`` command line that reaches the GCS on ``link`` (its listening
    endpoints and mission name; ``0.0.0.0`` as loopback), for a person to paste."""
    parts = ["magic console"]
    for ep in getattr(link.config, "listen", ()) or ():
        parts.append(f"--connect {str(ep).replace('/0.0.0.0:', '/127.0.0.1:')}")
    parts.append(f"--mission {link.mission}")
    return " ".join(parts)
