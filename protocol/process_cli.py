"""What every ``magic`` process (``sim``, ``robot``, ``gcs``) shares on its command line.

Each process joins the mission over zenoh with the same options (``--mission``, ``--radio``,
``--connect``, ``--listen``; DESIGN section 4) and stops cleanly on ^C.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING

from protocol.config import CONFIGS_DIR
from protocol.radio import RadioConfig

if TYPE_CHECKING:
    from protocol.clock import ManualClock
    from protocol.link import Link, LinkConfig, Subscription

__all__ = [
    "add_link_arguments",
    "follow_sim_clock",
    "link_config",
    "spin_until",
    "stop_on_interrupt",
]


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


def follow_sim_clock(link: Link, clock: ManualClock) -> Subscription:
    """Advance ``clock`` with the simulator's clock ticks (mission time; never backwards).
    Close the returned subscription to stop following."""
    from protocol import keys
    from protocol.sensors import ClockTick, decode_sensor_frame
    from protocol.wire import ProtocolError

    def on_tick(_key: str, payload: bytes) -> None:
        try:
            tick = decode_sensor_frame(payload)
        except ProtocolError:
            return
        if isinstance(tick, ClockTick) and tick.time_s > clock.now():
            clock.set(tick.time_s)

    return link.subscribe(keys.sim_clock(link.mission), on_tick)


def spin_until(
    spin_once: Callable[[], object],
    *,
    now: Callable[[], float],
    stop: threading.Event,
    duration_s: float | None = None,
    progress: Callable[[str], None] | None = None,
    status: Callable[[], str] = lambda: "",
    progress_period_s: float = 5.0,
) -> None:
    """Call ``spin_once`` until ``stop`` is set or ``duration_s`` mission seconds (by ``now``)
    have passed, reporting ``status()`` to ``progress`` every ``progress_period_s`` wall s."""
    last = time.monotonic()
    start = now()
    while not stop.is_set():
        spin_once()
        if duration_s is not None and now() - start >= duration_s:
            return
        if progress is not None and time.monotonic() - last >= progress_period_s:
            progress(status())
            last = time.monotonic()
