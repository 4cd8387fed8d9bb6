"""The console's connection to a GCS: signed commands out, replies and status in.

:class:`ConsoleClient` signs each :class:`~protocol.operator.Command` with the operator's key
and a fresh sequence number (:class:`~protocol.operator.SequenceCounter`), publishes it on
``magic/<mission>/gcs/command`` and waits for the :class:`~protocol.operator.CommandReply` with
that sequence number on ``.../gcs/reply/<operator>``. The GCS's
:class:`~protocol.operator.GcsStatus` (robots, OOIs: what completion offers) arrives every
status period; a GCS is *connected* while its status keeps arriving (``silence_s``).
zenoh reconnects on its own once the GCS's endpoint is back; :meth:`ConsoleClient.wait_for_gcs`
waits for that. Nothing here raises for a GCS that is not there: replies are None.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from protocol import operator as op

__all__ = ["ConsoleClient"]


class ConsoleClient:
    """One operator's console session over ``link`` (a :class:`~protocol.link.Link`).

    ``on_notice(text)``: called (on a zenoh or timer thread) when the GCS goes silent or
    comes back, and for replies that arrive after their command timed out.
    """

    def __init__(
        self,
        link: Any,
        operator_id: str,
        key: bytes,
        *,
        silence_s: float = 3.0,
        on_notice: Callable[[str], None] | None = None,
    ) -> None:
        self.link = link
        self.mission = link.mission
        op.reply_key(self.mission, operator_id)  # a clear ValueError for a bad id
        self.operator_id = operator_id
        self._key = key
        self.silence_s = silence_s
        self.on_notice = on_notice
        self.seq = op.SequenceCounter()
        self.status: op.GcsStatus | None = None
        self.status_wall = -float("inf")
        self._cv = threading.Condition()
        self._replies: dict[int, op.CommandReply] = {}
        self._waiting: set[int] = set()
        self._was_connected = False
        self.bad_messages = 0
        self.commands_sent = 0  # published by send / send_raw
        self._subs = [
            link.subscribe(op.reply_key(self.mission, operator_id), self._on_reply),
            link.subscribe(op.status_key(self.mission), self._on_status),
        ]
        self._stop = threading.Event()
        self._watch = threading.Thread(target=self._watchdog, name="console-watch", daemon=True)
        self._watch.start()

    # ---- incoming ------------------------------------------------------------------------

    def _on_reply(self, _key: str, payload: bytes) -> None:
        try:
            reply = op.decode_reply(payload)
        except ValueError:
            self.bad_messages += 1
            return
        with self._cv:
            if reply.seq in self._waiting:
                self._replies[reply.seq] = reply
                self._cv.notify_all()
                return
        if self.on_notice is not None and reply.operator_id == self.operator_id:
            self.on_notice(f"late reply to command {reply.seq}: {reply.status}: {reply.text}")

    def _on_status(self, _key: str, payload: bytes) -> None:
        try:
            status = op.decode_status(payload)
        except ValueError:
            self.bad_messages += 1
            return
        with self._cv:
            self.status = status
            self.status_wall = time.monotonic()
            back = not self._was_connected
            self._was_connected = True
            self._cv.notify_all()
        if back and self.on_notice is not None:
            self.on_notice(
                f"connected to the GCS of mission {status.mission!r} (t={status.time_s:.1f} s, "
                f"{len(status.robots)} robots)"
            )

    def _watchdog(self) -> None:
        while not self._stop.wait(0.5):
            with self._cv:
                lost = self._was_connected and not self.connected
                if lost:
                    self._was_connected = False
            if lost and self.on_notice is not None:
                self.on_notice(
                    f"lost the GCS: no status for {self.silence_s:g} s; reconnecting (commands "
                    "wait for it)"
                )

    # ---- state ---------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return time.monotonic() - self.status_wall <= self.silence_s

    def silent_for_s(self) -> float:
        return time.monotonic() - self.status_wall

    def wait_for_gcs(self, timeout_s: float) -> bool:
        """Block until a GCS status arrives within ``silence_s`` (True) or ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while not self.connected:
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(min(left, 0.2))
        return True

    def wait_for_status(self, predicate: Callable[[op.GcsStatus], bool], timeout_s: float) -> bool:
        """Block until a status satisfying ``predicate`` arrives (True) or ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._cv:
            while self.status is None or not predicate(self.status):
                left = deadline - time.monotonic()
                if left <= 0:
                    return False
                self._cv.wait(min(left, 0.2))
        return True

    # ---- outgoing ------------------------------------------------------------------------

    def signed(self, command: op.Command) -> op.SignedCommand:
        return op.sign(self._key, self.mission, self.operator_id, self.seq.next(), command)

    def send(self, command: op.Command, *, timeout_s: float = 5.0) -> op.CommandReply | None:
        """Sign, send and wait for the GCS's reply; None if none came within ``timeout_s``."""
        return self.send_raw(self.signed(command), timeout_s=timeout_s)

    def send_raw(
        self, signed: op.SignedCommand, *, timeout_s: float = 5.0
    ) -> op.CommandReply | None:
        """Send an already signed (or deliberately unsigned, forged) command; wait for it."""
        with self._cv:
            self._waiting.add(signed.seq)
            self.commands_sent += 1
        try:
            self.link.publish(op.command_key(self.mission), op.encode(signed))
            deadline = time.monotonic() + timeout_s
            with self._cv:
                while signed.seq not in self._replies:
                    left = deadline - time.monotonic()
                    if left <= 0:
                        return None
                    self._cv.wait(left)
                return self._replies.pop(signed.seq)
        finally:
            with self._cv:
                self._waiting.discard(signed.seq)

    def close(self) -> None:
        self._stop.set()
        for s in self._subs:
            s.close()
        self._watch.join(2.0)
