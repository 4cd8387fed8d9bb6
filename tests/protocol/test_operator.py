"""Operator commands: signing, the GCS's verification (unsigned, forged, replayed refused), the
key file (created 0600, permissions checked)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from protocol import operator as op

KEY = bytes(range(32))


def _signed(seq: int, *, key: bytes = KEY, mission: str = "m1", text: str = "all") -> bytes:
    return op.encode(op.sign(key, mission, "alice", seq, op.Command("pause", text)))


def test_a_signed_command_is_accepted_once_and_in_order() -> None:
    v = op.CommandVerifier(KEY, "m1", floor_seq=0)
    cmd, reason, _ = v.check(_signed(10))
    assert reason == "ok" and cmd is not None and cmd.command == op.Command("pause", "all")
    assert v.check(_signed(10))[1] == "replayed"  # the same bytes again
    assert v.check(_signed(9))[1] == "replayed"  # older
    assert v.check(_signed(11))[1] == "ok"
    assert v.accepted == 2 and v.refused == {"replayed": 2}


def test_unsigned_forged_other_mission_and_malformed_are_refused() -> None:
    v = op.CommandVerifier(KEY, "m1", floor_seq=0)
    good = op.sign(KEY, "m1", "alice", 5, op.Command("goto", "3", (1.0, 2.0)))
    unsigned = op.SignedCommand(good.version, "alice", 6, good.command)
    assert v.check(op.encode(unsigned))[1] == "unsigned"
    altered = op.SignedCommand(
        good.version, "alice", 7, op.Command("goto", "3", (50.0, 2.0)), 0.0, good.mac
    )
    assert v.check(op.encode(altered))[1] == "forged"
    assert v.check(_signed(8, key=bytes(32)))[1] == "forged"  # wrong key
    assert v.check(_signed(9, mission="m2"))[1] == "forged"  # recorded in another mission
    impostor = op.SignedCommand(good.version, "bob", good.seq, good.command, 0.0, good.mac)
    assert v.check(op.encode(impostor))[1] == "forged"  # another operator's MAC
    assert v.check(b"\x93garbage")[1] == "malformed"
    assert v.accepted == 0


def test_sequence_floor_refuses_commands_from_before_the_gcs_started() -> None:
    v = op.CommandVerifier(KEY, "m1")  # floor: now less the clock allowance
    assert v.check(_signed(1))[1] == "replayed"
    assert v.check(op.encode(op.sign(KEY, "m1", "alice", op.SequenceCounter().next(),
                                     op.Command("status"))))[1] == "ok"  # fmt: skip


def test_sequence_counter_is_strictly_increasing() -> None:
    c = op.SequenceCounter()
    seqs = [c.next() for _ in range(1000)]
    assert all(b > a for a, b in zip(seqs, seqs[1:], strict=False))


def test_key_file_created_0600_and_reused(tmp_path: Path) -> None:
    path = tmp_path / "conf" / "operator.key"
    key = op.load_or_create_key(path)
    assert len(key) == 32
    assert (path.stat().st_mode & 0o777) == 0o600
    assert op.load_or_create_key(path) == key


def test_key_file_readable_by_others_or_not_hex_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "operator.key"
    op.load_or_create_key(path)
    os.chmod(path, 0o644)
    with pytest.raises(op.KeyFileError, match="chmod 600"):
        op.load_or_create_key(path)
    os.chmod(path, 0o600)
    path.write_text("not hex\n")
    with pytest.raises(op.KeyFileError, match="hex"):
        op.load_or_create_key(path)
    with pytest.raises(op.KeyFileError, match="does not exist"):
        op.load_or_create_key(tmp_path / "missing.key", create=False)
