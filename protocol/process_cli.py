"""What every ``magic`` process (``sim``, ``robot``, ``gcs``) shares on its command line.

Each process joins the mission over zenoh with the same options (``--mission``, ``--radio``,
``--connect``, ``--listen``; DESIGN section 4) and stops cleanly on ^C and SIGTERM.

The exit-status contract every ``magic`` command keeps: 0 done, 1 the work itself failed,
2 bad input (one line on stderr naming what and where, before any long work starts),
130 stopped by SIGINT, 143 stopped by SIGTERM (``128 + signal``; what ran is summarised and
everything already written is kept). :func:`raise_on_sigterm` makes SIGTERM raise
:class:`Terminated`, a ``KeyboardInterrupt``, so that one ``except KeyboardInterrupt`` covers
both signals and :func:`exit_code_for` tells them apart.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import signal
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from protocol.config import CONFIGS_DIR
from protocol.radio import RadioConfig

if TYPE_CHECKING:
    from protocol.clock import ManualClock
    from protocol.link import Link, LinkConfig, Subscription

__all__ = [
    "Terminated",
    "add_link_arguments",
    "check_input_file",
    "check_output_dir",
    "check_output_file",
    "exit_code_for",
    "follow_sim_clock",
    "one_line",
    "open_link",
    "zenoh_error_text",
    "install_sigterm_handler",
    "install_stop_handlers",
    "link_config",
    "raise_on_sigterm",
    "signal_name_for",
    "signals_received",
    "spin_until",
    "stop_cause",
    "stop_exception",
    "stop_on_interrupt",
    "stopped_line",
]


class Terminated(KeyboardInterrupt):
    """A signal other than ^C (SIGTERM by default) raised where ^C would raise
    ``KeyboardInterrupt``: every existing ``except KeyboardInterrupt`` stops the same way."""

    def __init__(self, signum: int | str = signal.SIGTERM) -> None:
        # raised from signal handlers: never fails; a name ("SIGTERM") or number is taken,
        # anything else is kept as the message of a SIGTERM
        super().__init__(signum)
        self.signum = _signal_number(signum)


def _signal_number(signal_: int | str) -> int:
    if isinstance(signal_, str):
        try:
            return int(signal.Signals[signal_.strip().upper()])
        except KeyError:
            return int(signal.SIGTERM)
    try:
        return int(signal_)
    except (TypeError, ValueError):
        return int(signal.SIGTERM)


#: Every stop signal :func:`install_stop_handlers`' handlers took, oldest first.
_RECEIVED: list[int] = []


def _raise_terminated(signum: int, _frame: object) -> None:
    _RECEIVED.append(signum)
    raise stop_exception(signum)


def stop_exception(signum: int) -> KeyboardInterrupt:
    """What a stop signal raises: ``KeyboardInterrupt`` for SIGINT, else :class:`Terminated`."""
    return KeyboardInterrupt() if signum == signal.SIGINT else Terminated(signum)


def install_stop_handlers() -> dict[int, Callable[..., object] | int | None]:
    """From now on SIGINT raises ``KeyboardInterrupt`` and SIGTERM :class:`Terminated` in the
    main thread, and both are recorded (:func:`signals_received`); returns the previous
    handlers by signal (empty off the main thread, where nothing changes). A signal the
    process was started ignoring (``nohup``, a background job) stays ignored."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {
        sig: signal.signal(sig, _raise_terminated)
        for sig in (signal.SIGINT, signal.SIGTERM)
        if signal.getsignal(sig) is not signal.SIG_IGN  # nohup, background jobs: kept
    }


def stop_cause(exc: BaseException) -> KeyboardInterrupt | None:
    """The stop (``KeyboardInterrupt``, :class:`Terminated`) behind ``exc``, if any: C code a
    stop interrupted may wrap it (numba's dispatcher raises ``SystemError`` from it)."""
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        if isinstance(current, KeyboardInterrupt):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def signals_received() -> tuple[int, ...]:
    """The stop signals the handlers of :func:`install_stop_handlers` (and
    :func:`install_sigterm_handler`) took, oldest first. An exception raised from a signal
    handler while C code calls back into Python (a ctypes callback: numba compiling, for one)
    is swallowed there; a command that ends normally can look here to see it was told to stop.
    """
    return tuple(_RECEIVED)


def install_sigterm_handler() -> Callable[..., object] | int | None:
    """From now on SIGTERM raises :class:`Terminated` in the main thread; returns the previous
    handler (``None`` off the main thread, where nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_terminated)


@contextlib.contextmanager
def raise_on_sigterm() -> Iterator[None]:
    """Within the block SIGTERM raises :class:`Terminated`; the previous handler after."""
    previous = install_sigterm_handler()
    try:
        yield
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def exit_code_for(exc: BaseException) -> int:
    """The exit status for a stop: 143 for SIGTERM (``128 + signal`` for any
    :class:`Terminated`), 130 for ^C (a plain ``KeyboardInterrupt``)."""
    if isinstance(exc, Terminated):
        return 128 + exc.signum
    return 128 + signal.SIGINT


def signal_name_for(exc: BaseException) -> str:
    """``"SIGTERM"``, ``"SIGINT"``, ...: the signal that stopped the process."""
    signum = exc.signum if isinstance(exc, Terminated) else signal.SIGINT
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


def stopped_line(command: str, exc: BaseException, detail: str = "") -> str:
    """``magic bench: stopped by SIGINT (suite loops)``: the one line a stopped command prints."""
    line = f"magic {command}: stopped by {signal_name_for(exc)}"
    return f"{line} ({detail})" if detail else line


#: Longest error line a command prints (the issue's bound: under 200 characters).
MAX_ERROR_CHARS = 199


def one_line(text: object, limit: int = MAX_ERROR_CHARS) -> str:
    """``text`` on one line (whitespace runs collapsed), at most ``limit`` characters: a
    longer one loses its middle (the command's name and the problem, at the end, stay)."""
    flat = " ".join(str(text).split())
    if len(flat) <= limit:
        return flat
    head = (limit - 5) // 2
    return f"{flat[:head]} ... {flat[len(flat) - (limit - 5 - head) :]}"


def _writable_dir(directory: Path) -> bool:
    """Whether a file can be created in ``directory`` (tried: permissions alone say yes to
    root on a read-only mount); the probe file is gone on return."""
    if not os.access(directory, os.W_OK | os.X_OK):
        return False
    try:
        with tempfile.TemporaryFile(dir=directory):
            return True
    except OSError:
        return False


def check_input_file(path: str | Path, what: str) -> Path:
    """``path`` as a readable file, or ValueError naming ``what`` and the path."""
    p = Path(path)
    if not p.is_file():
        problem = "is a directory" if p.is_dir() else "not found"
        raise ValueError(f"{what} {p}: {problem}")
    if not os.access(p, os.R_OK):
        raise ValueError(f"{what} {p}: not readable")
    return p


def check_output_file(path: str | Path, what: str) -> Path:
    """``path`` as a file this process can write: its directory exists and is writable and
    the path is not a directory; else ValueError naming ``what`` and the directory. Nothing
    is created."""
    p = Path(path)
    parent = p.parent
    if p.is_dir():
        raise ValueError(f"{what} {p}: is a directory")
    if not parent.is_dir():
        raise ValueError(f"{what} {p}: directory {parent} does not exist")
    if not _writable_dir(parent) or (p.exists() and not os.access(p, os.W_OK)):
        raise ValueError(f"{what} {p}: directory {parent} is not writable")
    return p


def check_output_dir(path: str | Path, what: str) -> Path:
    """``path`` as a directory this process can fill: it is a writable directory, or the
    nearest existing ancestor is one (the rest is created when written); else ValueError
    naming ``what`` and the directory at fault. Nothing is created."""
    p = Path(path)
    probe = p
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if not probe.is_dir():
        raise ValueError(f"{what} {p}: {probe} is not a directory")
    if not _writable_dir(probe):
        raise ValueError(f"{what} {p}: directory {probe} is not writable")
    return p


def _security_file(text: str) -> str:
    """``--security``'s argparse type: the file is read and checked at once (one line, status
    2, on a missing certificate, an open key or a bad key)."""
    from protocol.config import ConfigError
    from protocol.transport_security import load_security

    try:
        load_security(text)
    except ConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return text


def add_link_arguments(parser: argparse.ArgumentParser) -> None:
    """``--mission``, ``--radio``, ``--connect``, ``--listen``, ``--mode``, ``--link-config``
    and ``--security``."""
    parser.add_argument(
        "--mission",
        default="default",
        help="mission name in the zenoh keys; processes of one mission share it "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--radio",
        type=Path,
        default=CONFIGS_DIR / "radio" / "magic2010.yaml",
        metavar="YAML",
        help="radio model config (default: configs/radio/magic2010.yaml)",
    )
    parser.add_argument(
        "--connect",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447; repeatable (default: none)",
    )
    parser.add_argument(
        "--listen",
        action="append",
        default=[],
        metavar="ENDPOINT",
        help="zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447; repeatable "
        "(default: tcp/127.0.0.1:0, loopback, any free port)",
    )
    parser.add_argument(
        "--mode",
        choices=("peer", "client", "router"),
        default=None,
        help="zenoh mode: peer (meets the peers it learns of directly), client (only through "
        "the router it connects to: hosts that reach each other through a router) or router "
        "(routes for the others); default: peer, or the --link-config file's",
    )
    parser.add_argument(
        "--link-config",
        type=Path,
        default=None,
        metavar="YAML",
        help="a protocol.link.LinkConfig YAML (mode, listen, connect, ...): the endpoints of a "
        "deployment in one file; --mode, --connect and --listen override it",
    )
    parser.add_argument(
        "--security",
        type=_security_file,
        default=None,
        metavar="YAML",
        help="mutual TLS and access control across hosts (configs/security/example.yaml says "
        "how; use tls/ endpoints); default: plain zenoh",
    )


def open_link(
    config: LinkConfig,
    *,
    mission: str,
    clock: Any = None,
    seed: int = 0,
    reach_timeout_s: float = 0.0,
) -> Link:
    """A :class:`~protocol.link.Link`, or ``ValueError("cannot open the zenoh link: ...")``
    on one line (an endpoint in use or unresolvable, a TLS file zenoh refuses), without
    zenoh's source locations: every command reports it as bad input (status 2).
    ``reach_timeout_s`` > 0 and endpoints to connect to: also wait that long for one of them
    to answer (a peer opens without it and keeps trying), else ValueError naming them."""
    from protocol.link import Link as _Link

    try:
        link = _Link(config, mission=mission, clock=clock, seed=seed)
    except Exception as err:  # noqa: BLE001 - zenoh raises its own ZError (and others)
        raise ValueError(f"cannot open the zenoh link: {zenoh_error_text(err)}") from None
    if reach_timeout_s > 0 and config.connect and not link.wait_reachable(reach_timeout_s):
        link.close()
        raise ValueError(
            f"cannot reach {', '.join(config.connect)} (no zenoh router or peer answered "
            f"within {reach_timeout_s:g} s)"
        )
    return link


def zenoh_error_text(err: BaseException) -> str:
    """A zenoh error on one line without its source locations (at most 150 characters):
    ``Can not create a new TCP listener bound to tcp/127.0.0.1:7447: [...Address already in
    use (os error 98)``."""
    text = " ".join(str(err).split()).split(" at /", 1)[0]
    return text if len(text) <= 150 else text[:147] + "..."


def link_config(radio: RadioConfig, args: argparse.Namespace) -> LinkConfig:
    """The link configuration the parsed options ask for: ``--link-config``'s file (or the
    defaults) with ``--mode``, ``--connect``, ``--listen`` and ``--security`` over it; the
    radio is always ``radio``. A bad file raises ConfigError naming it and the key."""
    from protocol.link import LinkConfig  # zenoh loads only for processes that serve it

    fields: dict[str, object] = {"radio": radio}
    base = LinkConfig()
    if getattr(args, "link_config", None) is not None:
        from protocol.config import load_config

        base = load_config(args.link_config, LinkConfig)  # ConfigError naming file and key
    if getattr(args, "mode", None):
        fields["mode"] = args.mode
    if args.connect:
        fields["connect"] = tuple(args.connect)
    if args.listen:
        fields["listen"] = tuple(args.listen)
    if getattr(args, "security", ""):
        fields["security_file"] = str(args.security)
    return msgspec.structs.replace(base, **fields)


@contextlib.contextmanager
def stop_on_interrupt(stop: Callable[[], None]) -> Iterator[list[int]]:
    """Within the block, ^C and SIGTERM call ``stop`` (the process winds down and closes its
    link) instead of raising; yields the list of signals received (exit status ``128 +
    signal``). SIGTERM is taken only when its handler is the default one or
    :func:`install_sigterm_handler`'s: a caller that set its own keeps it. The previous
    handlers are restored after. Off the main thread, where signals cannot be handled,
    nothing changes."""
    received: list[int] = []

    def handler(signum: int, _frame: object) -> None:
        received.append(signum)
        stop()

    previous: dict[int, Callable[..., object] | int | None] = {}
    if threading.current_thread() is threading.main_thread():
        previous[signal.SIGINT] = signal.signal(signal.SIGINT, handler)
        if signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, _raise_terminated):
            previous[signal.SIGTERM] = signal.signal(signal.SIGTERM, handler)
    try:
        yield received
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


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
    have passed, reporting ``status()`` to ``progress`` every ``progress_period_s`` wall s.
    While the mission clock stands still (the simulator ended, paused or not started) the
    status is reported once, saying so, not repeated unchanged until ^C."""
    last = time.monotonic()
    start = now()
    reported_t: float | None = None
    still_said = False
    while not stop.is_set():
        spin_once()
        if duration_s is not None and now() - start >= duration_s:
            return
        if progress is not None and time.monotonic() - last >= progress_period_s:
            t = now()
            if t != reported_t:
                progress(status())
                still_said = False
            elif not still_said:
                progress(
                    f"{status()} (the mission clock stands at t={t:.1f} s: the simulator has "
                    "ended, paused or not started; waiting, quiet until it moves)"
                )
                still_said = True
            reported_t = t
            last = time.monotonic()
