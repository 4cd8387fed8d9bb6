"""Compact radio codings of the busiest streams: pose nodes and grids against the previous
node, broadcast hazard updates with quantised frames (issue 16 item 1, paper 4.1, 4.3.4).

The radio is the binding constraint of a large team (paper 4.1, 8): a :class:`PoseNode` in
plain msgpack is 78 bytes, more than the compressed grid it anchors. The channel therefore
codes these streams on the air and decodes them back to the ordinary message types, so nodes
and the GCS never see the codings:

* **Pose nodes** (:class:`PoseNodeCoder`): each node is coded against the previous node *of
  the same stream*, which both ends hold because the stream is reliable and delivered in order
  (the sender codes in sequence order at ``send``, the receiver decodes in delivery order;
  a retransmission resends the same bytes). Quantised, zigzag varints:

  - node index: difference from ``previous + 1`` (0 on a gap-free stream: 1 byte);
  - time: milliseconds, second difference (a node per metre at a steady speed: 1 byte);
  - ``pose_in_odom``: ``QUANTUM_M`` / ``QUANTUM_RAD`` units, second difference (the step
    against the previous step: small when driving straight);
  - ``odom_delta``: its float32 values exactly (12 bytes): the GCS decodes inter-frame grids
    against the previous grid warped by this delta, which must be the robot's to the bit;
  - covariance: each upper-triangle entry on a log scale (``COV_STEPS_PER_OCTAVE`` steps per
    factor of two, relative error at most 0.27%, sign kept, so a non-physical covariance
    stays non-physical for the GCS to refuse), difference from the previous node's codes.

  Quantisation is absolute (each value is rounded on its own grid, the differences are exact
  integers), so no error accumulates along the trajectory: a decoded ``pose_in_odom`` is
  within half a quantum (0.05 mm, 5 µrad) of the robot's, whatever the node count, and
  ``odom_delta`` is the robot's exactly. A node
  with a value that is not finite, or too large for the grid, travels as a plain
  :class:`PoseNode` and both ends restart the reference from zero.
* **Terrain grids** (:class:`TerrainGridCoder`): node index against the previous grid's,
  resolution only when it changes, then the compressed grid bytes unchanged (lossless).
* **Hazard updates** (:func:`encode_hazard_update` / :func:`decode_hazard_update`): the
  broadcast carries every robot's ``map_from_odom``; frames go as robot-id differences and
  millimetre / 0.1 mrad integers (quantisation far below the GCS's own uncertainty), each
  update self-contained (a robot that missed the previous one decodes the next).

Everything here is pure: bytes in, messages out, :class:`~protocol.wire.ProtocolError` for
bytes that do not decode.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

from protocol.messages import (
    HazardUpdate,
    HazardUpdateCoded,
    PoseNode,
    PoseNodeCoded,
    RobotFrame,
    TerrainGrid,
    TerrainGridCoded,
)
from protocol.wire import ProtocolError

__all__ = [
    "COV_STEPS_PER_OCTAVE",
    "FRAME_QUANTUM_M",
    "FRAME_QUANTUM_RAD",
    "QUANTUM_M",
    "QUANTUM_RAD",
    "QUANTUM_S",
    "PoseNodeCoder",
    "TerrainGridCoder",
    "decode_hazard_update",
    "encode_hazard_update",
]

QUANTUM_M = 1e-4
QUANTUM_RAD = 1e-5
QUANTUM_S = 1e-3
COV_STEPS_PER_OCTAVE = 128
FRAME_QUANTUM_M = 1e-3
FRAME_QUANTUM_RAD = 1e-4
#: Quantised values beyond this magnitude (in units) are not coded (the plain message goes).
_MAX_UNITS = 2**50
_COV_OFFSET = 2**20
_F32 = struct.Struct("<f")
_DELTA = struct.Struct("<3f")


# ----------------------------------------------------------------------------- varints


def _put(out: bytearray, value: int) -> None:
    """Append ``value`` as a zigzag LEB128 varint (|v| < 64: one byte)."""
    z = (value << 1) if value >= 0 else ((-value) << 1) - 1
    while z >= 0x80:
        out.append((z & 0x7F) | 0x80)
        z >>= 7
    out.append(z)


class _Reader:
    def __init__(self, data: bytes, what: str) -> None:
        self.data = data
        self.pos = 0
        self.what = what

    def varint(self) -> int:
        z = 0
        shift = 0
        data = self.data
        while True:
            if self.pos >= len(data):
                raise ProtocolError(f"{self.what}: truncated at byte {self.pos}")
            b = data[self.pos]
            self.pos += 1
            z |= (b & 0x7F) << shift
            if b < 0x80:
                break
            shift += 7
            if shift > 140:
                raise ProtocolError(f"{self.what}: varint too long at byte {self.pos}")
        return (z >> 1) if not z & 1 else -((z + 1) >> 1)

    def raw(self, n: int) -> bytes:
        if self.pos + n > len(self.data):
            raise ProtocolError(f"{self.what}: truncated at byte {self.pos}")
        out = self.data[self.pos : self.pos + n]
        self.pos += n
        return bytes(out)

    def rest(self) -> bytes:
        out = bytes(self.data[self.pos :])
        self.pos = len(self.data)
        return out

    def end(self) -> None:
        if self.pos != len(self.data):
            raise ProtocolError(f"{self.what}: {len(self.data) - self.pos} bytes left over")


# ----------------------------------------------------------------------------- quantisers


def _units(value: float, quantum: float) -> int | None:
    """``round(value / quantum)``; None when not finite or beyond the coded range."""
    if not math.isfinite(value):
        return None
    u = value / quantum
    if abs(u) >= _MAX_UNITS:
        return None
    return round(u)


def _cov_code(value: float) -> int | None:
    """Log-scale code of one covariance entry: 0 for 0, else ``2 * (m + offset) + negative``
    with ``m = round(log2|v| * COV_STEPS_PER_OCTAVE)``; None if not finite or extreme."""
    if value == 0.0:
        return 0
    if not math.isfinite(value) or not 2.0**-1000 < abs(value) < 2.0**1000:
        return None
    m = round(math.log2(abs(value)) * COV_STEPS_PER_OCTAVE)
    return 2 * (m + _COV_OFFSET) + (1 if value < 0 else 0)


def _cov_value(code: int) -> float:
    if code == 0:
        return 0.0
    m = (code >> 1) - _COV_OFFSET
    if abs(m) > 1000 * COV_STEPS_PER_OCTAVE:
        raise ProtocolError(f"covariance code {code} out of range")
    v = 2.0 ** (m / COV_STEPS_PER_OCTAVE)
    return -v if code & 1 else v


# ----------------------------------------------------------------------------- pose nodes


@dataclass
class _PoseRef:
    """What both ends remember of the previous node (all integers: units and codes)."""

    index: int = -1
    t_ms: int = 0
    dt_ms: int = 0
    pose: list[int] = field(default_factory=lambda: [0, 0, 0])
    step: list[int] = field(default_factory=lambda: [0, 0, 0])
    cov: list[int] = field(default_factory=lambda: [0] * 6)


_POSE_Q = (QUANTUM_M, QUANTUM_M, QUANTUM_RAD)


def _pose_ints(node: PoseNode) -> tuple[int, list[int], list[int]] | None:
    t = _units(node.time_s, QUANTUM_S)
    pose = [_units(v, q) for v, q in zip(node.pose_in_odom, _POSE_Q, strict=True)]
    cov = [_cov_code(v) for v in node.odom_covariance]
    if t is None or None in pose or None in cov:
        return None
    if not all(math.isfinite(v) for v in node.odom_delta):
        return None
    return t, pose, cov  # type: ignore[return-value]


class PoseNodeCoder:
    """One end of a pose-node stream: codes (sender) or decodes (receiver) in stream order.

    The sender calls :meth:`encode` for every node in sequence order and sends what it returns
    (a :class:`PoseNodeCoded`, or the node itself when it cannot be coded); the receiver calls
    :meth:`decode` on every message in delivery order. Both update the same reference.
    """

    def __init__(self) -> None:
        self._ref = _PoseRef()

    def encode(self, node: PoseNode) -> PoseNodeCoded | PoseNode:
        ints = _pose_ints(node)
        if ints is None:
            self._ref = _PoseRef()
            return node
        t, pose, cov = ints
        ref = self._ref
        out = bytearray()
        _put(out, node.node_index - (ref.index + 1))
        dt = t - ref.t_ms
        _put(out, dt - ref.dt_ms)
        step = [p - r for p, r in zip(pose, ref.pose, strict=True)]
        for s, r in zip(step, ref.step, strict=True):
            _put(out, s - r)
        out += _DELTA.pack(*node.odom_delta)
        for c, r in zip(cov, ref.cov, strict=True):
            _put(out, c - r)
        self._ref = _PoseRef(node.node_index, t, dt, pose, step, cov)
        return PoseNodeCoded(bytes(out))

    def decode(self, msg: PoseNodeCoded | PoseNode) -> PoseNode:
        if isinstance(msg, PoseNode):
            ints = _pose_ints(msg)
            if ints is None:
                self._ref = _PoseRef()
            else:
                t, pose, cov = ints
                ref = self._ref
                step = [p - r for p, r in zip(pose, ref.pose, strict=True)]
                self._ref = _PoseRef(msg.node_index, t, t - ref.t_ms, pose, step, cov)
            return msg
        ref = self._ref
        r = _Reader(msg.data, "PoseNodeCoded.data")
        index = ref.index + 1 + r.varint()
        dt = ref.dt_ms + r.varint()
        t = ref.t_ms + dt
        step = [s + r.varint() for s in ref.step]
        pose = [p + s for p, s in zip(ref.pose, step, strict=True)]
        odom_delta = _DELTA.unpack(r.raw(12))
        cov = [c + r.varint() for c in ref.cov]
        r.end()
        if any(c < 0 for c in cov):
            raise ProtocolError("PoseNodeCoded.data: negative covariance code")
        node = PoseNode(
            index,
            t * QUANTUM_S,
            tuple(u * q for u, q in zip(pose, _POSE_Q, strict=True)),  # type: ignore[arg-type]
            odom_delta,  # type: ignore[arg-type]
            tuple(_cov_value(c) for c in cov),  # type: ignore[arg-type]
        )
        self._ref = _PoseRef(index, t, dt, pose, step, cov)
        return node


# ----------------------------------------------------------------------------- grids


class TerrainGridCoder:
    """Grids against the previous grid of the stream (lossless; see the module docstring)."""

    def __init__(self) -> None:
        self._index = -1
        self._resolution: bytes = b""

    def encode(self, grid: TerrainGrid) -> TerrainGridCoded:
        out = bytearray()
        _put(out, grid.node_index - (self._index + 1))
        res = _F32.pack(grid.resolution_m)
        if res == self._resolution:
            out.append(0)
        else:
            out.append(1)
            out += res
        out += grid.data
        self._index = grid.node_index
        self._resolution = res
        return TerrainGridCoded(bytes(out))

    def decode(self, msg: TerrainGridCoded | TerrainGrid) -> TerrainGrid:
        if isinstance(msg, TerrainGrid):
            self._index = msg.node_index
            self._resolution = _F32.pack(msg.resolution_m)
            return msg
        r = _Reader(msg.data, "TerrainGridCoded.data")
        index = self._index + 1 + r.varint()
        flag = r.raw(1)[0]
        if flag == 0:
            if not self._resolution:
                raise ProtocolError("TerrainGridCoded.data: no previous resolution to reuse")
            res = self._resolution
        elif flag == 1:
            res = r.raw(4)
        else:
            raise ProtocolError(f"TerrainGridCoded.data: bad resolution flag {flag}")
        grid = TerrainGrid(index, _F32.unpack(res)[0], r.rest())
        self._index = index
        self._resolution = res
        return grid


# ----------------------------------------------------------------------------- hazard updates

_FRAME_Q = (FRAME_QUANTUM_M, FRAME_QUANTUM_M, FRAME_QUANTUM_RAD)


def encode_hazard_update(update: HazardUpdate) -> HazardUpdateCoded | HazardUpdate:
    """The broadcast form of ``update`` (frames quantised and sorted by robot id); the update
    itself when a frame is not finite or a robot id repeats."""
    frames = sorted(update.frames, key=lambda f: f.robot_id)
    out = bytearray()
    previous = -1
    for f in frames:
        units = [_units(v, q) for v, q in zip(f.map_from_odom, _FRAME_Q, strict=True)]
        if None in units or f.robot_id <= previous:
            return update
        _put(out, f.robot_id - previous - 1)
        for u in units:
            _put(out, u)  # type: ignore[arg-type]
        previous = f.robot_id
    return HazardUpdateCoded(update.time_s, update.hazards, bytes(out))


def decode_hazard_update(msg: HazardUpdateCoded | HazardUpdate) -> HazardUpdate:
    """Inverse of :func:`encode_hazard_update` (frames at their quantised values)."""
    if isinstance(msg, HazardUpdate):
        return msg
    r = _Reader(msg.frames, "HazardUpdateCoded.frames")
    frames = []
    previous = -1
    while r.pos < len(r.data):
        rid = previous + 1 + r.varint()
        if rid < 0:
            raise ProtocolError("HazardUpdateCoded.frames: negative robot id")
        pose = tuple(r.varint() * q for q in _FRAME_Q)
        frames.append(RobotFrame(rid, pose))  # type: ignore[arg-type]
        previous = rid
    return HazardUpdate(msg.time_s, list(msg.hazards), frames)
