"""``magic console``: the operators' REPL, a client of a running GCS (paper 6.2).

Connects over zenoh to the GCS's endpoints (``--connect``, default ``tcp/127.0.0.1:7448``,
the port the README's ``magic gcs --listen tcp/0.0.0.0:7448`` opens), signs every command
with the operator's key (``--operator-key``; see :mod:`protocol.operator`) and prints the GCS's
reply. Interactive (a terminal): a prompt_toolkit prompt with completion of commands,
arguments, robot ids and OOI ids, history (``--history``), function-key macros
(``--macros``, :mod:`gcs.console.macros`) and a status bar (GCS time, robots, interactions,
connection). ``-c "CMD; CMD"``, ``--script FILE`` and lines piped on stdin run commands without a
terminal.

Lines: one or more commands separated by ``;``. Local words: ``help [COMMAND]``, ``macros``,
``history``, ``quit``. Commands and robot subsets: :mod:`gcs.operator.grammar`.

Exit status (``-c`` / ``--script``): 0 every command ``ok``, 1 one was refused, invalid,
failed or unanswered, 2 bad input (options, key file, macros file, script file: one line on
stderr), 130 / 143 stopped by SIGINT / SIGTERM.
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gcs.console.client import ConsoleClient
from gcs.console.macros import FUNCTION_KEYS, Macro, load_macros
from gcs.operator.grammar import (
    GROUPS,
    LOCAL_VERBS,
    VERBS,
    CommandError,
    RobotFacts,
    parse_line,
    parse_subset,
    suggest,
)
from protocol import operator as op
from protocol.cli_parser import CommandParser
from protocol.config import ConfigError

__all__ = ["Console", "main"]

DEFAULT_CONNECT = "tcp/127.0.0.1:7448"


class Console:
    """Runs command lines against a GCS through ``client``; ``out(text)`` prints."""

    def __init__(
        self,
        client: ConsoleClient,
        *,
        macros: dict[str, Macro] | None = None,
        out: Callable[[str], None] = print,
        reply_timeout_s: float = 5.0,
        wait_s: float = 10.0,
    ) -> None:
        self.client = client
        self.macros = macros or {}
        self.out = out
        self.reply_timeout_s = reply_timeout_s
        self.wait_s = wait_s
        self.history: list[str] = []
        self.done = False

    # ---- lines ---------------------------------------------------------------------------

    def run_line(self, line: str) -> bool:
        """Run every ``;``-separated command of ``line``; False if one did not succeed (the
        rest of the line is skipped then)."""
        line = line.strip()
        if not line or line.startswith("#"):
            return True
        self.history.append(line)
        for part in (p.strip() for p in line.split(";")):
            if part and not self.run_command(part):
                return False
        return True

    def run_command(self, text: str) -> bool:
        head = text.split()[0].lower()
        if head in LOCAL_VERBS:
            return self._local(head, text.split()[1:])
        try:
            command = parse_line(text)
        except CommandError as err:
            self.out(f"error: {err}")
            return False
        if not self.client.connected:
            self.out(
                f"waiting up to {self.wait_s:g} s for the GCS (mission {self.client.mission!r})..."
            )
            if not self.client.wait_for_gcs(self.wait_s):
                self.out(
                    f"error: no GCS answers on mission {self.client.mission!r}; not sent "
                    "(is `magic run` or `magic gcs` running? `magic run` prints the console "
                    "command that reaches it; else --connect must point at the GCS's --listen)"
                )
                return False
        try:
            self._check_robots(command)
        except CommandError as err:
            self.out(f"error: {err}")
            return False
        signed = self.client.signed(command)
        self.out(f"> {command.text()}  [seq {signed.seq}]")
        reply = self.client.send_raw(signed, timeout_s=self.reply_timeout_s)
        if reply is None:
            self.out(
                f"error: no reply within {self.reply_timeout_s:g} s: the GCS may be gone; the "
                "command may or may not have been carried out (see `status`)"
            )
            return False
        head = reply.status if not reply.reason else f"{reply.status} ({reply.reason})"
        self.out(f"{head}: {reply.text}")
        return reply.status == "ok"

    def _check_robots(self, command: op.Command) -> None:
        """Catch an unknown robot id here, with a suggestion (the GCS checks again)."""
        verb = VERBS[command.verb]
        status = self.client.status
        if status is None or not command.target:
            return
        if verb.target in ("robots", "robot", "optional_robots"):
            facts = {
                r.robot_id: RobotFacts(r.robot_id, r.role, r.task in ("none", ""))
                for r in status.robots
            }
            if facts:
                parse_subset(command.target, facts)
        elif verb.target == "ooi":
            ids = [str(h.hazard_id) for h in status.hazards]
            if command.target not in ids:
                raise CommandError(suggest(command.target, ids, what="OOI id"))

    # ---- local words ---------------------------------------------------------------------

    def _local(self, head: str, rest: list[str]) -> bool:
        if head in ("quit", "exit"):
            self.done = True
            return True
        if head == "history":
            for i, line in enumerate(self.history[-50:], 1):
                self.out(f"{i:4}  {line}")
            return True
        if head == "macros":
            self.out(self.macros_text())
            return True
        self.out(self.help_text(rest[0] if rest else None))
        return True

    def macros_text(self) -> str:
        if not self.macros:
            return "no macros loaded (--macros FILE)"
        return "\n".join(
            f"  {k.upper():4} {'; '.join(m.commands):32} {m.help}"
            for k, m in sorted(self.macros.items(), key=lambda kv: int(kv[0][1:]))
        )

    def help_text(self, topic: str | None = None) -> str:
        if topic is not None:
            verb = VERBS.get(topic.lower())
            if verb is None:
                return suggest(topic, [*VERBS, *LOCAL_VERBS], what="command")
            return f"{verb.usage()}\n  {verb.help}"
        lines = ["commands (TAB completes; `help COMMAND` for details; `;` separates):"]
        for v in VERBS.values():
            lines.append(f"  {v.usage():38} {_first_sentence(v.help)}")
        lines.append(
            "ROBOTS: an id (3), a range (2-5), " + ", ".join(GROUPS) + ", or a comma list "
            "(1,4-6,disruptors). Positions are metres in the map frame."
        )
        lines.append("local: help [COMMAND], macros, history, quit")
        if self.macros:
            lines.append("function keys:\n" + self.macros_text())
        return "\n".join(lines)

    def toolbar(self, typing: str = "") -> str:
        """The status bar; ``typing`` (the line being typed): its command's usage and what it
        does on a second line, so arguments completion cannot offer (numbers) are named."""
        c = self.client
        s = c.status
        if s is None or not c.connected:
            silent = "never heard" if s is None else f"silent {c.silent_for_s():.0f} s"
            bar = (
                f" GCS {c.mission}: NOT CONNECTED ({silent}); reconnecting | operator "
                f"{c.operator_id}"
            )
        else:
            by_operator = sum(1 for r in s.robots if r.control != "planner")
            bar = (
                f" GCS {s.mission} t={s.time_s:.0f} s | robots {len(s.robots)} "
                f"({by_operator} operator-controlled) | "
                f"OOIs {len(s.hazards)} | interactions {s.interactions} | planner "
                f"{'on' if s.planner else 'off'} | operator {c.operator_id}"
            )
        last = typing.split(";")[-1].split()
        verb = VERBS.get(last[0].lower()) if last else None
        if verb is not None:
            bar += f"\n {verb.usage()}: {_first_sentence(verb.help)}"
        return bar


def _first_sentence(text: str) -> str:
    """The first sentence (an abbreviation's "e.g." is no sentence end)."""
    return re.split(r"(?<!e\.g)(?<!i\.e)\. ", text)[0].rstrip(".")


# ---- the command ----------------------------------------------------------------------------


def _isatty(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, OSError, ValueError):
        return False


def _read_lines(stream: Any) -> list[str]:
    try:
        return str(stream.read()).splitlines()
    except (OSError, ValueError):  # no readable stdin (closed, or a test harness's)
        return []


def _runnable(line: str) -> bool:
    text = line.strip()
    return bool(text) and not text.startswith("#")


def _check_endpoint(endpoint: str) -> None:
    """ValueError unless ``endpoint`` looks like ``<protocol>/<address>`` (zenoh says more
    when it opens; importing the GCS node's full check would cost seconds of start-up)."""
    proto, sep, address = endpoint.partition("/")
    if not sep or not proto.isidentifier() and "-" not in proto or not address:
        raise ValueError(
            f"endpoint {endpoint!r}: expected <protocol>/<address>, e.g. tcp/127.0.0.1:7448"
        )
    if proto in ("tcp", "udp", "tls", "quic", "ws"):
        host, colon, port = address.split("?", 1)[0].rpartition(":")
        if not colon or not host or not port.isdigit() or not 0 <= int(port) <= 65535:
            raise ValueError(f"endpoint {endpoint!r}: expected {proto}/<host>:<port 0..65535>")


def _plain(rst: str) -> str:
    """The module docstring as help text: reStructuredText roles and literals unwrapped."""
    text = re.sub(r":(?:mod|class|func|meth|attr):`~?([^`]+)`", r"\1", rst)
    return text.replace("``", "")


def _parser() -> argparse.ArgumentParser:
    from protocol.process_cli import add_link_arguments

    p = CommandParser(
        prog="magic console",
        description=_plain(__doc__.split("\n\n", 1)[1]) if __doc__ else None,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_link_arguments(p)
    for action in p._actions:
        if action.dest == "connect":
            action.help = (
                f"the GCS's zenoh endpoint, e.g. tcp/10.0.0.2:7448; repeatable (default: "
                f"{DEFAULT_CONNECT})"
            )
    p.add_argument(
        "--operator",
        default=os.environ.get("USER") or "operator",
        metavar="ID",
        help="your operator id, in every command and the GCS's log (default: $USER: %(default)s)",
    )
    p.add_argument(
        "--operator-key",
        type=Path,
        metavar="FILE",
        help=f"the operators' shared key (created on first use, mode 0600); default "
        f"$MAGIC_OPERATOR_KEY or {op.default_key_path()}",
    )
    p.add_argument(
        "-c",
        dest="commands",
        metavar="CMD",
        action="append",
        help="run CMD (`;` separates several) and exit; repeatable",
    )
    p.add_argument(
        "--script",
        type=Path,
        metavar="FILE",
        help="run FILE's lines (# comments) and exit; stops at the first failure",
    )
    p.add_argument(
        "--macros",
        type=Path,
        metavar="YAML",
        help="function-key macros (default: configs/console/macros.yaml)",
    )
    p.add_argument(
        "--history",
        type=Path,
        metavar="FILE",
        default=Path.home() / ".magic_console_history",
        help="where typed commands are kept across sessions (default: %(default)s)",
    )
    p.add_argument(
        "--wait-s",
        type=float,
        default=10.0,
        metavar="S",
        help="wall seconds to wait for the GCS before a command (default: %(default)s)",
    )
    p.add_argument(
        "--timeout-s",
        type=float,
        default=5.0,
        metavar="S",
        help="wall seconds to wait for a reply (default: %(default)s)",
    )
    return p


def main(argv: list[str]) -> int:
    """``magic console``: returns the exit status (module docstring)."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)

    def fail(text: object) -> int:
        print(f"magic console: {' '.join(str(text).split())}", file=sys.stderr)
        return 2

    try:
        op.reply_key(args.mission, args.operator)
        for name in ("wait_s", "timeout_s"):
            v = getattr(args, name)
            if not v > 0:
                raise ValueError(f"--{name.replace('_', '-')}: expected seconds > 0, got {v}")
        for endpoint in args.connect + args.listen:
            _check_endpoint(endpoint)
        macros = load_macros(args.macros)
        script: list[str] = []
        if args.script is not None:
            if not args.script.is_file():
                raise ValueError(f"--script {args.script}: no such file")
            script = args.script.read_text(encoding="utf-8").splitlines()
        interactive = args.commands is None and args.script is None
        if interactive and not _isatty(sys.stdin):
            # piped: the lines of stdin are the script (`echo "pause all" | magic console`)
            script = _read_lines(sys.stdin)
            interactive = False
        lines = [*(args.commands or []), *script]
        if not interactive and not any(_runnable(line) for line in lines):
            return 0  # nothing to send: no key, no link
        key = op.load_or_create_key(args.operator_key)
    except (ValueError, ConfigError, OSError) as err:
        return fail(err)
    from protocol.link import Link, LinkConfig

    extra: dict[str, Any] = {}
    if getattr(args, "security", ""):  # mutual TLS across hosts, as every magic process
        extra["security_file"] = str(args.security)
    config = LinkConfig(
        connect=tuple(args.connect or [DEFAULT_CONNECT]),
        listen=tuple(args.listen) if args.listen else ("tcp/127.0.0.1:0",),
        pump_period_s=0.0,
        **extra,
    )
    try:
        link = Link(config, mission=args.mission)
    except Exception as err:
        return fail(f"cannot open the zenoh link: {str(err).split(' at /')[0]}")
    # interactive: notices wait until the introduction is printed (a GCS heard at once
    # was announced above it)
    held: list[str] = []
    printer: list[Callable[[str], None]] = [held.append if interactive else print]
    client = ConsoleClient(
        link, args.operator, key, on_notice=lambda t: printer[0](f"[console] {t}")
    )
    console = Console(
        client,
        macros=macros,
        reply_timeout_s=args.timeout_s,
        wait_s=args.wait_s,
        out=lambda t: printer[0](t),
    )
    try:
        if not interactive:
            ok = True
            for line in lines:
                if not console.run_line(line):
                    ok = False
                    break
                if console.done:
                    break
            return 0 if ok else 1
        return _interactive(console, args.history, printer, held)
    except KeyboardInterrupt:
        print("magic console: stopped by SIGINT", file=sys.stderr)
        return 130
    finally:
        client.close()
        link.close()


def _interactive(
    console: Console,
    history: Path,
    printer: list[Callable[[str], None]],
    held: list[str] | None = None,
) -> int:
    from prompt_toolkit import PromptSession
    from prompt_toolkit.application.current import get_app
    from prompt_toolkit.history import FileHistory, InMemoryHistory
    from prompt_toolkit.key_binding import KeyBindings
    from prompt_toolkit.patch_stdout import patch_stdout

    from gcs.console.completion import ConsoleCompleter

    kb = KeyBindings()
    for key in FUNCTION_KEYS:
        macro = console.macros.get(key)
        if macro is None:
            continue

        def run_macro(event: Any, m: Macro = macro) -> None:
            buf = event.app.current_buffer
            buf.text = "; ".join(m.commands)
            buf.validate_and_handle()

        kb.add(key)(run_macro)
    try:
        hist: Any = FileHistory(str(history))
    except OSError:
        hist = InMemoryHistory()
    session: PromptSession[str] = PromptSession(
        completer=ConsoleCompleter(lambda: console.client.status),
        complete_while_typing=True,
        history=hist,
        key_bindings=kb,
        bottom_toolbar=lambda: console.toolbar(get_app().current_buffer.text),
        refresh_interval=1.0,
    )
    print(
        f"magic console: operator {console.client.operator_id}, mission "
        f"{console.client.mission!r}: `help` lists the commands, TAB completes, ^D leaves;\n"
        "the bar below shows the GCS and what the command being typed takes."
    )
    print("function keys:\n" + console.macros_text() if console.macros else "no macros")
    printer[0] = print
    for notice in held or []:
        print(notice)
    if not console.client.wait_for_gcs(2.0):
        print("[console] no GCS yet; commands wait for it (see the bar below)")
    with patch_stdout(raw=True):
        printer[0] = print
        while not console.done:
            try:
                line = session.prompt("magic> ")
            except KeyboardInterrupt:
                continue  # ^C clears the line, as in a shell
            except EOFError:
                break
            try:
                console.run_line(line)
            except KeyboardInterrupt:
                print("(interrupted)")
    return 0
