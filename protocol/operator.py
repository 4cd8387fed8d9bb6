"""Operator commands between a console and the GCS, over zenoh, authenticated (paper 6.2).

Not radio traffic: consoles and the GCS talk on the zenoh network the processes share
(``magic/<mission>/gcs/...``, DESIGN sections 4 and 8), never over the robots' radio. The GCS
turns an accepted command into tasks on the radio itself; it is the only sender of tasks.

Keys (built here, in the style of :mod:`protocol.keys`)::

    magic/<mission>/gcs/command                 SignedCommand, console -> GCS
    magic/<mission>/gcs/reply/<operator>        CommandReply, GCS -> that operator's consoles
    magic/<mission>/gcs/state/status            GcsStatus, GCS -> consoles, every status period
    magic/<mission>/gcs/presence                liveliness token of a running GCS

Authentication. Every :class:`SignedCommand` carries the operator's id, a sequence number that
only grows (:class:`SequenceCounter`: wall-clock microseconds, bumped past the previous one)
and ``mac`` = HMAC-SHA256 over the canonical msgpack encoding of ``(version, mission,
operator_id, seq, command)`` with a shared secret key read from a file
(:func:`load_or_create_key`: 32 random bytes written hex on first use with mode 0600; a file
that group or others may read or write is refused, as ssh does). Binding the mission name in
the MAC stops a command recorded in one mission from being replayed in another. The GCS
(:class:`CommandVerifier`) refuses, with a reason the console is told: ``malformed`` (bytes
that do not decode), ``unsigned`` (no MAC), ``forged`` (a MAC that does not verify: wrong key,
altered command, another mission), ``replayed`` (a sequence number not above the last one
accepted from that operator, or older than ``floor_seq``: before the GCS started, less a
clock allowance).

Messages are msgspec structs encoded as msgpack arrays, with :data:`OPERATOR_PROTOCOL_VERSION`.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
import threading
import time
from pathlib import Path

import msgspec

from protocol import keys

__all__ = [
    "DEFAULT_KEY_ENV",
    "OPERATOR_PROTOCOL_VERSION",
    "OPERATOR_TASK_IDS_FROM",
    "Command",
    "CommandReply",
    "CommandVerifier",
    "GcsStatus",
    "HazardRow",
    "KeyFileError",
    "RobotRow",
    "SequenceCounter",
    "SignedCommand",
    "command_key",
    "decode_reply",
    "decode_signed",
    "decode_status",
    "default_key_path",
    "encode",
    "is_operator_task",
    "load_or_create_key",
    "presence_key",
    "reply_key",
    "reply_wildcard",
    "sign",
    "status_key",
]

#: Bumped whenever a message below changes layout.
OPERATOR_PROTOCOL_VERSION = 1

#: Environment variable naming the operator key file (default: ~/.config/magic/operator.key).
DEFAULT_KEY_ENV = "MAGIC_OPERATOR_KEY"

#: Task ids from here up are the operators' (gcs.operator.handler); the planners' count up
#: from 1,000,000 (gcs.tasking). A robot driving an operator's task reports
#: ``SEMI_AUTONOMOUS``: an operator chose the goal, the robot plans and drives there (paper 6.2,
#: and the time and distance per autonomy mode of paper 7, Tables 4-5).
OPERATOR_TASK_IDS_FROM = 2_000_000_000

_KEY_BYTES = 32


def is_operator_task(task_id: int) -> bool:
    """Whether ``task_id`` is in the operators' range (:data:`OPERATOR_TASK_IDS_FROM`)."""
    return int(task_id) >= OPERATOR_TASK_IDS_FROM


# ----------------------------------------------------------------------------- keys


def command_key(mission: str) -> str:
    return keys.gcs(mission, "command")


def reply_key(mission: str, operator_id: str) -> str:
    return keys.gcs(mission, f"reply/{operator_id}")


def reply_wildcard(mission: str) -> str:
    return keys.gcs(mission, "reply") + "/*"


def status_key(mission: str) -> str:
    return keys.gcs(mission, "state/status")


def presence_key(mission: str) -> str:
    return keys.gcs(mission, "presence")


# ----------------------------------------------------------------------------- messages


class Command(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """One operator command: ``verb`` (``goto``, ``pause``, ...), ``target`` (a robot subset
    as typed: ``3``, ``2-5``, ``sensors``, ``all``, ``1,4``; or an OOI id, or empty) and
    ``args`` (numbers and words, verb-specific). The GCS checks everything."""

    verb: str
    target: str = ""
    args: tuple[float | int | str, ...] = ()

    def text(self) -> str:
        parts = [self.verb, self.target, *(str(a) for a in self.args)]
        return " ".join(p for p in parts if p != "")


class SignedCommand(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """A :class:`Command` with its operator, sequence number and MAC (module docstring).
    ``sent_wall_s``: the console's wall clock when sent (for latency, not trusted)."""

    version: int
    operator_id: str
    seq: int
    command: Command
    sent_wall_s: float = 0.0
    mac: bytes = b""


class CommandReply(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """The GCS's answer to ``(operator_id, seq)``. ``status``: ``ok`` (done), ``refused``
    (authentication: ``reason`` is ``unsigned``, ``forged``, ``replayed``, ``malformed``),
    ``invalid`` (a bad command: ``text`` says what and suggests), ``failed`` (it could not be
    done now, e.g. no frame for that robot yet). ``text``: what happened, for a person.
    ``time_s``: mission time at the GCS. ``interaction``: counted as an operator interaction."""

    version: int
    operator_id: str
    seq: int
    status: str
    reason: str
    text: str
    time_s: float
    interaction: bool = False
    task_ids: tuple[int, ...] = ()


class RobotRow(msgspec.Struct, array_like=True, frozen=True):
    """One robot as the GCS sees it, for completion and ``status`` on a console."""

    robot_id: int
    role: str  # sensor, disruptor or unknown
    mode: str  # from telemetry (idle, autonomous, paused, ...) or unknown
    task: str  # short text
    control: str  # planner, operator, paused
    pose_in_map: tuple[float, float, float] | None
    last_heard_s: float
    battery_frac: float


class HazardRow(msgspec.Struct, array_like=True, frozen=True):
    """One OOI (a GCS hazard) for consoles: id, kind, position in ``map`` and its state
    (``live``, ``pending_approval``, ``approved``, ``neutralized``)."""

    hazard_id: int
    kind: str
    position_in_map: tuple[float, float]
    state: str


class GcsStatus(msgspec.Struct, array_like=True, frozen=True):
    """What a console shows and completes from, published every status period."""

    version: int
    mission: str
    time_s: float
    robots: list[RobotRow]
    hazards: list[HazardRow]
    interactions: int = 0
    planner: bool = False  # a task allocator runs at the GCS
    verbs: tuple[str, ...] = ()


_ENC = msgspec.msgpack.Encoder()
_DEC_SIGNED = msgspec.msgpack.Decoder(SignedCommand)
_DEC_REPLY = msgspec.msgpack.Decoder(CommandReply)
_DEC_STATUS = msgspec.msgpack.Decoder(GcsStatus)


def encode(msg: SignedCommand | CommandReply | GcsStatus) -> bytes:
    return _ENC.encode(msg)


def decode_signed(data: bytes) -> SignedCommand:
    """Raises ``ValueError`` naming the problem for bytes that are not a SignedCommand."""
    try:
        return _DEC_SIGNED.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError) as err:
        raise ValueError(f"operator command: {err}") from None


def decode_reply(data: bytes) -> CommandReply:
    try:
        return _DEC_REPLY.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError) as err:
        raise ValueError(f"operator reply: {err}") from None


def decode_status(data: bytes) -> GcsStatus:
    try:
        return _DEC_STATUS.decode(data)
    except (msgspec.DecodeError, msgspec.ValidationError) as err:
        raise ValueError(f"gcs status: {err}") from None


# ----------------------------------------------------------------------------- signing


def _mac(key: bytes, mission: str, operator_id: str, seq: int, command: Command) -> bytes:
    body = _ENC.encode((OPERATOR_PROTOCOL_VERSION, mission, operator_id, seq, command))
    return hmac.new(key, body, hashlib.sha256).digest()


def sign(key: bytes, mission: str, operator_id: str, seq: int, command: Command) -> SignedCommand:
    """The signed form of ``command`` (module docstring)."""
    keys.gcs(mission, f"reply/{operator_id}")  # validates both names
    return SignedCommand(
        OPERATOR_PROTOCOL_VERSION,
        operator_id,
        int(seq),
        command,
        time.time(),
        _mac(key, mission, operator_id, int(seq), command),
    )


class SequenceCounter:
    """Monotonic sequence numbers that also grow across console restarts: wall-clock
    microseconds, bumped past the previous number (a clock stepping back cannot repeat one)."""

    def __init__(self) -> None:
        self._last = 0
        self._lock = threading.Lock()

    def next(self) -> int:
        with self._lock:
            self._last = max(self._last + 1, time.time_ns() // 1000)
            return self._last


class CommandVerifier:
    """The GCS's check of signed commands (module docstring). ``floor_seq``: sequence numbers
    at or below are refused as replayed (default: this process's start, wall-clock
    microseconds, less ``clock_allowance_s``). Thread-safe. ``refused`` counts by reason."""

    def __init__(
        self,
        key: bytes,
        mission: str,
        *,
        floor_seq: int | None = None,
        clock_allowance_s: float = 300.0,
    ) -> None:
        if len(key) < 16:
            raise ValueError(f"operator key: expected at least 16 bytes, got {len(key)}")
        self._key = key
        self.mission = mission
        self.floor_seq = (
            floor_seq
            if floor_seq is not None
            else int((time.time() - clock_allowance_s) * 1_000_000)
        )
        self._last: dict[str, int] = {}
        self._lock = threading.RLock()
        self.accepted = 0
        self.refused: dict[str, int] = {}

    def check(self, data: bytes) -> tuple[SignedCommand | None, str, str]:
        """``(command, "ok", "")`` for a command to carry out; else ``(command or None,
        reason, text)`` with reason ``malformed``, ``unsigned``, ``forged`` or ``replayed``."""
        try:
            cmd = decode_signed(data)
        except ValueError as err:
            return self._refuse(None, "malformed", str(err))
        if cmd.version != OPERATOR_PROTOCOL_VERSION:
            return self._refuse(
                cmd,
                "malformed",
                f"operator protocol version {cmd.version}, expected {OPERATOR_PROTOCOL_VERSION}",
            )
        if not cmd.mac:
            return self._refuse(cmd, "unsigned", "command carries no MAC")
        want = _mac(self._key, self.mission, cmd.operator_id, cmd.seq, cmd.command)
        if not hmac.compare_digest(want, cmd.mac):
            return self._refuse(
                cmd, "forged", "MAC does not verify (wrong key, altered command or mission)"
            )
        with self._lock:
            last = max(self._last.get(cmd.operator_id, 0), self.floor_seq)
            if cmd.seq <= last:
                return self._refuse(
                    cmd,
                    "replayed",
                    f"sequence {cmd.seq} not above {last} (a replay, or a console clock far "
                    "behind the GCS's)",
                )
            self._last[cmd.operator_id] = cmd.seq
            self.accepted += 1
        return cmd, "ok", ""

    def _refuse(
        self, cmd: SignedCommand | None, reason: str, text: str
    ) -> tuple[SignedCommand | None, str, str]:
        with self._lock:
            self.refused[reason] = self.refused.get(reason, 0) + 1
        return cmd, reason, text


# ----------------------------------------------------------------------------- key file


class KeyFileError(ValueError):
    """The key file cannot be used; the message names the file and the fix."""


def default_key_path() -> Path:
    env = os.environ.get(DEFAULT_KEY_ENV, "").strip()
    if env:
        return Path(env).expanduser()
    return Path.home() / ".config" / "magic" / "operator.key"


def load_or_create_key(path: str | Path | None = None, *, create: bool = True) -> bytes:
    """The shared operator key from ``path`` (default :func:`default_key_path`), created on
    first use (32 random bytes as hex, mode 0600, its directory 0700 if new). Refused with
    :class:`KeyFileError`: a file group or others may read or write, one not owned by this
    user, not hex, or shorter than 16 bytes."""
    p = Path(path).expanduser() if path is not None else default_key_path()
    if not p.exists():
        if not create:
            raise KeyFileError(f"operator key file {p} does not exist")
        p.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        try:
            fd = os.open(p, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        except FileExistsError:
            pass  # another process created it meanwhile: read theirs
        else:
            with os.fdopen(fd, "w") as f:
                f.write(secrets.token_hex(_KEY_BYTES) + "\n")
    st = p.stat()
    if not stat.S_ISREG(st.st_mode):
        raise KeyFileError(f"operator key file {p} is not a regular file")
    if st.st_mode & 0o077:
        raise KeyFileError(
            f"operator key file {p} has mode {stat.S_IMODE(st.st_mode):04o}: others may read "
            f"it; run chmod 600 {p}"
        )
    if hasattr(os, "getuid") and st.st_uid != os.getuid():
        raise KeyFileError(f"operator key file {p} belongs to another user (uid {st.st_uid})")
    text = p.read_text(encoding="ascii", errors="replace").strip()
    try:
        key = bytes.fromhex(text)
    except ValueError:
        raise KeyFileError(f"operator key file {p}: expected hex digits") from None
    if len(key) < 16:
        raise KeyFileError(f"operator key file {p}: {len(key)} bytes, expected at least 16")
    return key
