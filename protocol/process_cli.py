"""What every ``magic`` process (``sim``, ``robot``, ``gcs``) shares on its command line.

Each process joins the mission over zenoh with the same options (``--mission``, ``--radio``,
``--connect``, ``--listen``; DESIGN section 4) and stops cleanly on ^C.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from protocol.config import CONFIGS_DIR
from protocol.radio import RadioConfig

if TYPE_CHECKING:
    from protocol.link import LinkConfig

__all__ = ["add_link_arguments", "link_config", "stop_on_interrupt"]


def add_link_arguments(parser: argparse.ArgumentParser) -> None:
    """``--mission``, ``--radio``, ``--connect`` and ``--listen``."""
    parser.add_argument("--mission", default="default", help="mission name in the zenoh keys")
    parser.add_argument(
        "--radio",
        type=Path,
        default=CONFIGS_DIR / "radio" / "magic2010.yaml",
        help="radio config (configs/radio/*.yaml)",
    )
    parser.add_argument("--connect", action="append", default=[], help="zenoh endpoint to connect")
    parser.add_argument("--listen", action="append", default=[], help="zenoh endpoint to listen on")


def link_config(radio: RadioConfig, args: argparse.Namespace) -> LinkConfig:
    """The link configuration the parsed options ask for (defaults where none were given)."""
    from protocol.link import LinkConfig  # zenoh loads only for processes that serve it

    fields: dict[str, object] = {"radio": radio}
    if args.connect:
        fields["connect"] = tuple(args.connect)
    if args.listen:
        fields["listen"] = tuple(args.listen)
    return LinkConfig(**fields)  # type: ignore[arg-type]


@contextlib.contextmanager
def stop_on_interrupt(stop: Callable[[], None]) -> Iterator[None]:
    """Within the block, ^C calls ``stop`` (the process winds down and closes its link)
    instead of raising; the previous handler is restored after. Off the main thread, where
    signals cannot be handled, nothing changes."""
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGINT, lambda *_: stop())
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)
