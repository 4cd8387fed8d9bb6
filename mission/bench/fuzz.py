"""``magic bench fuzz``: hostile input to every decoder and entry point (issue 17 item 4).

Each entry point gets ``N`` inputs (10^5; ``--quick`` 10^4), drawn from a fixed seed: half are
*mutants* of valid inputs (bit flips, byte and token edits, cuts, splices of two valid inputs,
repeated chunks, numbers swapped for extreme ones: ``nan``, ``1e309``, ``2**64``, ``-0``),
half are *garbage* (random bytes, or random lines of printable text for text formats). An
entry point may refuse an input only with its documented error type; anything else it raises
is a *crash*. Entry points:

- ``uplink_frames`` / ``downlink_frames``: :func:`protocol.messages.decode_frame` (every
  message type of the radio), ``ProtocolError``;
- ``sensor_frames`` / ``robot_commands``: :mod:`protocol.sensors` (the sim <-> robot sensor
  interface), ``ProtocolError``;
- ``grids_<codec>``: :func:`compression.decode_grid_with_header` for streams of every codec,
  inter-frame codecs with their reference grid, ``CodecError``;
- ``station``: whatever ``uplink_frames`` accepts, handed to a live
  :class:`~gcs.ground_station.GroundStation` (``handle`` never raises; a refusal is counted
  inside it) and stepped every 500 inputs;
- ``journal_records``: :func:`gcs.journal.replay_journal` of a one-record journal whose body
  is the input, ``JournalError``;
- ``world_configs`` / ``radio_configs``: YAML text into the typed configs
  (:func:`protocol.config.load_config_text`), ``ConfigError``;
- ``carmen_logs`` / ``g2o_graphs``: the dataset parsers, ``CarmenLogError`` / ``G2oError``.

Metrics: ``crashes`` and ``hangs`` (an input taking over 1 s of CPU time: a busy machine's
waits are not the decoder's) summed over entry points (both
must be 0), ``accepted_garbage`` (garbage inputs an entry point with redundancy in its format
accepted: 0 expected, random bytes are no valid frame, config or log),
``accepted_garbage_grids`` (the same for the grid codecs, reported, not a fault: see below),
``grid_body_garbage_accepted_frac`` and ``_max`` (a valid header with a random body: the
share each codec decodes, averaged over codecs and the largest), ``inputs_per_entry``,
``entry_points``, ``accepted_mutants_frac``
(mutants accepted: a mutant can be valid, so this is how deep the fuzz reaches, not a fault),
``slowest_input_ms`` (CPU) and ``inputs_per_s``. A crashing input is written with its
traceback under :func:`mission.bench.output_dir` ``("fuzz")/crashes`` to reproduce it. The
operator console's command parser joins when it exists (``console_commands``).

Why accepted garbage is no fault of a grid codec: an arithmetic (range) coder maps nearly
every bit string to some grid. It carries no redundancy by design (30-45 bytes a grid; a
CRC-32 in the header would add 10 %), so a random body under a valid header often decodes
(:func:`grid_body_garbage`, 200 bodies each: ctx10a 0.90, ctx16a 0.93, inter16 0.84, ctx4a
0.60; ctx16t, intra16 under 0.07; the magic codecs, run lengths and zlib none: their
streams' ends are checked). Integrity is the link's: the radio's frame CRC (counted in
``framing_overhead_bytes``), TLS's authenticated encryption across hosts
(:mod:`protocol.transport_security`), TCP's checksum on loopback. What a codec must do with
garbage is what is counted as a fault: no crash, no hang, nothing beyond the header's size
limits (:func:`compression.read_header`). Random bytes pass that header (a known codec id,
its model version, a size within limits) rarely: 23 of the 700 000 garbage inputs over the
14 codecs of the full run, which is what ``accepted_garbage_grids`` shows.
"""

from __future__ import annotations

import importlib.util
import logging
import math
import time
import traceback
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["EntryPoint", "FuzzResult", "entry_points", "fuzz_entry", "grid_body_garbage", "run"]

#: An input slower than this is a hang.
HANG_S = 1.0

_EXTREMES = ("nan", "-nan", "inf", "-inf", "1e309", "-1e309", "18446744073709551616", "-0", "0")


@dataclass
class EntryPoint:
    """What to fuzz: valid ``seeds``, the ``call`` that consumes one input, the error types
    that are a proper refusal, and whether inputs are text."""

    name: str
    seeds: list[bytes]
    call: Callable[[bytes], object]
    refusals: tuple[type[BaseException], ...]
    text: bool = False
    #: the format has redundancy to refuse garbage with (a grid codec has none: module doc)
    redundant: bool = True


@dataclass
class FuzzResult:
    name: str
    inputs: int = 0
    crashes: int = 0
    hangs: int = 0
    accepted_garbage: int = 0
    mutants: int = 0
    accepted_mutants: int = 0
    slowest_s: float = 0.0
    wall_s: float = 0.0
    crash_examples: list[tuple[bytes, str]] = field(default_factory=list)


# ------------------------------------------------------------------------- input generation


def _mutate(rng: np.random.Generator, seeds: list[bytes], text: bool) -> bytes:
    data = bytearray(seeds[int(rng.integers(len(seeds)))])
    for _ in range(int(rng.integers(1, 4))):
        op = int(rng.integers(7))
        n = len(data)
        if op == 0 and n:  # bit flips
            for _ in range(int(rng.integers(1, 5))):
                i = int(rng.integers(n))
                data[i] ^= 1 << int(rng.integers(8))
        elif op == 1:  # insert random bytes
            i = int(rng.integers(n + 1))
            data[i:i] = rng.bytes(int(rng.integers(1, 9)))
        elif op == 2 and n:  # delete a run
            i = int(rng.integers(n))
            del data[i : i + int(rng.integers(1, 9))]
        elif op == 3 and n:  # cut
            del data[int(rng.integers(n)) :]
        elif op == 4:  # splice with another valid input
            other = seeds[int(rng.integers(len(seeds)))]
            i, j = int(rng.integers(n + 1)), int(rng.integers(len(other) + 1))
            data = data[:i] + bytearray(other[j:])
        elif op == 5 and n:  # repeat a chunk
            i = int(rng.integers(n))
            chunk = data[i : i + int(rng.integers(1, 17))]
            data[i:i] = chunk * int(rng.integers(1, 8))
        elif op == 6:  # a number swapped for an extreme one (text), or an extreme msgpack value
            if text:
                tokens = bytes(data).split(b" ")
                if tokens:
                    k = int(rng.integers(len(tokens)))
                    tokens[k] = _EXTREMES[int(rng.integers(len(_EXTREMES)))].encode()
                    data = bytearray(b" ".join(tokens))
            elif n:
                i = int(rng.integers(n))
                extreme = (b"\xcb\x7f\xf8\x00\x00\x00\x00\x00\x00", b"\xcf" + b"\xff" * 8, b"\xc0")
                data[i : i + 1] = extreme[int(rng.integers(len(extreme)))]
    return bytes(data)


def _garbage(rng: np.random.Generator, text: bool) -> bytes:
    if not text:
        return rng.bytes(int(rng.integers(0, 300)))
    # the first character is no blank or comment: an empty YAML document (all defaults) or
    # an empty g2o file is a document, not garbage
    first = np.frombuffer(b"abcdefxyz0123456789", dtype=np.uint8)
    alphabet = np.frombuffer(b"abcdefxyz0123456789 .-:_\t{}[],'\"#!&*|>%@", dtype=np.uint8)
    lines = [bytes(first[rng.integers(0, len(first), 1)])]
    for _ in range(int(rng.integers(1, 12))):
        k = int(rng.integers(0, 60))
        lines.append(bytes(alphabet[rng.integers(0, len(alphabet), k)]))
    lines[0] += lines.pop(1)
    return b"\n".join(lines)


def _inputs(rng: np.random.Generator, ep: EntryPoint, n: int) -> Iterator[tuple[bytes, bool]]:
    """``(input, is_garbage)``: mutants and garbage alternate."""
    for i in range(n):
        if i % 2 == 0:
            yield _mutate(rng, ep.seeds, ep.text), False
        else:
            yield _garbage(rng, ep.text), True


def fuzz_entry(ep: EntryPoint, n: int, *, seed: int = 17) -> FuzzResult:
    """Feed ``n`` inputs to ``ep`` and count what happened."""
    rng = np.random.default_rng([seed, sum(ep.name.encode())])
    res = FuzzResult(ep.name)
    t_start = time.perf_counter()
    for data, garbage in _inputs(rng, ep, n):
        res.inputs += 1
        res.mutants += not garbage
        t0 = time.thread_time()  # CPU time: a busy machine does not make a hang
        accepted = False
        try:
            ep.call(data)
            accepted = True
        except ep.refusals:
            pass
        except Exception:  # noqa: BLE001 - that is what a crash is here
            res.crashes += 1
            if len(res.crash_examples) < 5:
                res.crash_examples.append((data, traceback.format_exc()))
        dt = time.thread_time() - t0
        res.slowest_s = max(res.slowest_s, dt)
        res.hangs += dt > HANG_S
        if accepted:
            if garbage:
                res.accepted_garbage += 1
            else:
                res.accepted_mutants += 1
    res.wall_s = time.perf_counter() - t_start
    return res


# ------------------------------------------------------------------------- entry points


def _frames() -> tuple[list[bytes], list[bytes]]:
    from protocol.messages import (
        Ack,
        AckEntry,
        AutonomyMode,
        Detection,
        FiducialObservation,
        GoToTask,
        Hazard,
        HazardUpdate,
        IdleTask,
        NeutralizeTask,
        ObjectKind,
        PauseTask,
        PoseNode,
        RobotFrame,
        TaskState,
        TaskStatus,
        Telemetry,
        TerrainGrid,
        encode_frame,
    )

    grid = _grid_streams()["magic4"][0]
    cov = (0.01, 0.0, 0.0, 0.01, 0.0, 0.001)
    up = [
        PoseNode(3, 1.5, (1.0, 2.0, 0.3), (0.5, 0.0, 0.01), cov),
        TerrainGrid(3, 0.1, grid),
        Detection(1, 3, 1.5, ObjectKind.STATIC_OOI, (2.0, 1.0), (0.01, 0.0, 0.01), 0.3, 0.6, 0.9),
        FiducialObservation(3, 1.5, 2, 7, (1.0, 0.5, 0.2), cov),
        Telemetry(1.5, (1.0, 2.0, 0.3), (0.5, 0.1), (0.0, 0.0), 0.8, AutonomyMode.AUTONOMOUS, 4),
        TaskStatus(4, TaskState.ACTIVE, 1.5, ""),
    ]
    down = [
        GoToTask(4, 1.5, [(1.0, 2.0), (3.0, 4.0)], 0.0),
        NeutralizeTask(5, 1.5, (1.0, 2.0), 2.0, True),
        PauseTask(4, 1.5),
        IdleTask(6, 1.5),
        HazardUpdate(
            1.5,
            [Hazard(1, ObjectKind.STATIC_OOI, (1.0, 2.0), 2.5)],
            [RobotFrame(2, (0.0, 1.0, 0.1))],
        ),
        Ack([AckEntry(1, 5, b"\x05")]),
    ]
    return [encode_frame(i + 1, m) for i, m in enumerate(up)], [
        encode_frame(i + 1, m) for i, m in enumerate(down)
    ]


def _reference() -> Any:
    """The reference grid every inter-frame stream of the bench is coded against."""
    from compression.registry import GridReference

    rng = np.random.default_rng(3)
    grid = np.zeros((60, 80), dtype=bool)
    grid[10, 5:70] = True
    grid[10:50, 40] = True
    grid |= rng.random(grid.shape) < 0.02
    return GridReference(
        node_index=2,
        grid=grid,
        origin_cells=(-40, -30),
        reference_from_current=(0.2, 0.0, 0.0),
        resolution_m=0.1,
    )


def _grid_streams() -> dict[str, list[bytes]]:
    from compression import codec_names, encode_grid, is_inter

    ref = _reference()
    moved = np.roll(ref.grid, 2, axis=1)
    out: dict[str, list[bytes]] = {}
    for name in codec_names():
        inter = is_inter(name)
        out[name] = [
            encode_grid(
                moved if inter else ref.grid,
                codec=name,
                origin_cells=(-40, -30),
                reference=ref if inter else None,
            )
        ]
    return out


_G2O = b"""VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1.0 0.1 0.05
VERTEX_SE2 2 2.0 0.2 0.1
EDGE_SE2 0 1 1.0 0.1 0.05 100 0 0 100 0 1000
EDGE_SE2 1 2 1.0 0.1 0.05 100 0 0 100 0 1000
EDGE_SE2 0 2 2.0 0.2 0.1 50 0 0 50 0 500
"""

_CARMEN = b"""ODOM 0.0 0.0 0.0 0 0 0 1.0 nohost 1.0
FLASER 5 1.0 1.1 1.2 1.3 1.4 0.0 0.0 0.0 0.0 0.0 0.0 1.0 nohost 1.0
ODOM 0.5 0.0 0.0 0 0 0 2.0 nohost 2.0
FLASER 5 1.0 1.1 1.2 1.3 1.4 0.5 0.0 0.0 0.5 0.0 0.0 2.0 nohost 2.0
"""


def entry_points() -> list[EntryPoint]:
    """Every entry point fuzzed by the bench (see the module docstring)."""
    from compression import CodecError, decode_grid_with_header
    from compression.registry import read_header
    from gcs.graph.g2o import G2oError, parse_g2o
    from gcs.ground_station import GroundStation, GroundStationConfig
    from gcs.journal import GcsJournal, JournalError, replay_journal
    from gcs.replay.carmen_log import CarmenLogError, parse_carmen_log
    from protocol.config import ConfigError, config_path, load_config_text
    from protocol.messages import Direction, decode_frame
    from protocol.radio import RadioConfig
    from protocol.sensors import (
        ClockTick,
        VelocityCommand,
        decode_command,
        decode_sensor_frame,
        encode_command,
        encode_sensor_frame,
    )
    from protocol.wire import ProtocolError
    from sim.world_generator import WorldConfig

    up, down = _frames()
    eps = [
        EntryPoint("uplink_frames", up, lambda b: decode_frame(b, Direction.UP), (ProtocolError,)),
        EntryPoint(
            "downlink_frames", down, lambda b: decode_frame(b, Direction.DOWN), (ProtocolError,)
        ),
        EntryPoint(
            "sensor_frames",
            [encode_sensor_frame(ClockTick(1.5))],
            decode_sensor_frame,
            (ProtocolError,),
        ),
        EntryPoint(
            "robot_commands",
            [encode_command(VelocityCommand(1.5, 0.5, 0.1))],
            decode_command,
            (ProtocolError,),
        ),
    ]
    reference = _reference()
    for name, seeds in _grid_streams().items():

        def decode(b: bytes) -> object:
            ref = reference if read_header(b).reference_node is not None else None
            return decode_grid_with_header(b, reference=ref)

        eps.append(EntryPoint(f"grids_{name}", seeds, decode, (CodecError,), redundant=False))

    station = GroundStation(GroundStationConfig())
    calls = [0]

    def to_station(b: bytes) -> object:
        msg = decode_frame(b, Direction.UP).msg
        calls[0] += 1
        station.handle(int(calls[0] % 3), msg, now_s=calls[0] * 0.01)
        if calls[0] % 500 == 0:
            station.step(now_s=calls[0] * 0.01, budget_s=0.05)
        return msg

    eps.append(EntryPoint("station", up, to_station, (ProtocolError,)))

    from mission.bench import output_dir

    journal_path = output_dir("fuzz") / "journal.sqlite"
    for stale in journal_path.parent.glob("journal.sqlite*"):
        stale.unlink()
    journal = GcsJournal.create(journal_path, GroundStationConfig())
    replayed = GroundStation(GroundStationConfig())

    def journal_record(b: bytes) -> object:
        seq = journal.append("uplink", 1.0, b, robot_id=0)
        journal.commit()
        return replay_journal(journal, replayed, after_seq=seq - 1)

    eps.append(EntryPoint("journal_records", up, journal_record, (JournalError,)))
    world = config_path("small", "world").read_bytes()
    radio = config_path("magic2010", "radio").read_bytes()
    eps += [
        EntryPoint(
            "world_configs",
            [world],
            lambda b: load_config_text(b.decode("utf-8", "replace"), WorldConfig),
            (ConfigError,),
            text=True,
        ),
        EntryPoint(
            "radio_configs",
            [radio],
            lambda b: load_config_text(b.decode("utf-8", "replace"), RadioConfig),
            (ConfigError,),
            text=True,
        ),
        EntryPoint(
            "carmen_logs",
            [_CARMEN],
            lambda b: parse_carmen_log(b.decode("utf-8", "replace")),
            (CarmenLogError,),
            text=True,
        ),
        EntryPoint(
            "g2o_graphs",
            [_G2O],
            lambda b: parse_g2o(b.decode("utf-8", "replace")),
            (G2oError,),
            text=True,
        ),
    ]
    eps += _console_entry_points()
    return eps


def _console_entry_points() -> list[EntryPoint]:
    """The operator console's command parser (issue 15), where it is built."""
    if importlib.util.find_spec("gcs.operator.grammar") is None:
        return []
    from gcs.operator.grammar import CommandError, parse_line

    seeds = [
        b"pause all",
        b"goto 3 12.5 -4",
        b"resume 2-5,7",
        b"status",
        b"neutralize 7 4",
        b"approve 7",
        b"relay 2 10 -3.5",
        b"reclassify 7 toxic_vat",
        b"rewind 120",
        b"set telemetry_period_s 2 sensors",
    ]
    return [
        EntryPoint(
            "console_commands",
            seeds,
            lambda b: parse_line(b.decode("utf-8", "replace")),
            (CommandError,),
            text=True,
        )
    ]


# ------------------------------------------------------------------------- the suite


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    n = 10_000 if quick else 100_000
    results: list[FuzzResult] = []
    t0 = time.perf_counter()
    logging.disable(logging.WARNING)  # the station logs every refusal: 10^5 lines here
    try:
        return _run(n, progress, results, t0)
    finally:
        logging.disable(logging.NOTSET)


def _run(
    n: int, progress: Callable[[str], None], results: list[FuzzResult], t0: float
) -> dict[str, float]:
    from mission.bench import output_dir

    eps = entry_points()
    for ep in eps:
        res = fuzz_entry(ep, n)
        results.append(res)
        progress(
            f"{ep.name:18s} {res.inputs} inputs in {res.wall_s:5.1f} s: crashes {res.crashes}, "
            f"hangs {res.hangs}, garbage accepted {res.accepted_garbage}, mutants accepted "
            f"{res.accepted_mutants}/{res.mutants}, slowest {res.slowest_s * 1e3:.1f} ms"
        )
        if res.crash_examples:
            out = output_dir("fuzz") / "crashes"
            out.mkdir(parents=True, exist_ok=True)
            for i, (data, tb) in enumerate(res.crash_examples):
                (out / f"{ep.name}-{i}.bin").write_bytes(data)
                (out / f"{ep.name}-{i}.txt").write_text(tb)
            progress(f"  crashing inputs and tracebacks in {out}")
    body_frac = grid_body_garbage(max(100, n // 50))
    progress(
        "grid bodies       random bodies under valid headers decoded: "
        + ", ".join(f"{k} {v:.2f}" for k, v in body_frac.items())
    )
    wall = time.perf_counter() - t0
    total = sum(r.inputs for r in results)
    mutants = sum(r.mutants for r in results)
    redundant = {ep.name for ep in eps if ep.redundant}
    return {
        "entry_points": float(len(results)),
        "inputs_per_entry": float(n),
        "crashes": float(sum(r.crashes for r in results)),
        "hangs": float(sum(r.hangs for r in results)),
        "accepted_garbage": float(sum(r.accepted_garbage for r in results if r.name in redundant)),
        "accepted_garbage_grids": float(
            sum(r.accepted_garbage for r in results if r.name not in redundant)
        ),
        "grid_body_garbage_accepted_frac": float(np.mean(list(body_frac.values()))),
        "grid_body_garbage_accepted_max": float(max(body_frac.values())),
        "accepted_mutants_frac": sum(r.accepted_mutants for r in results) / max(mutants, 1),
        "slowest_input_ms": max((r.slowest_s for r in results), default=math.nan) * 1e3,
        "inputs_per_s": total / wall if wall > 0 else math.nan,
    }


def grid_body_garbage(n: int, *, seed: int = 23) -> dict[str, float]:
    """Per codec: the share of ``n`` streams with a valid header (the bench's grid's) and a
    random body of the valid body's length that decode (module docstring)."""
    from compression import CodecError, decode_grid_with_header, read_header

    rng = np.random.default_rng(seed)
    reference = _reference()
    out: dict[str, float] = {}
    for name, (valid,) in _grid_streams().items():
        hdr = read_header(valid)
        ref = reference if hdr.reference_node is not None else None
        body = len(valid) - hdr.size
        ok = 0
        for _ in range(n):
            try:
                decode_grid_with_header(valid[: hdr.size] + rng.bytes(body), reference=ref)
                ok += 1
            except CodecError:
                pass
        out[name] = ok / n
    return out


def _describe(results: list[FuzzResult]) -> dict[str, Any]:  # pragma: no cover - debugging aid
    return {r.name: r.__dict__ for r in results}
