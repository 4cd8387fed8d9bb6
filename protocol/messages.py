"""Radio messages between robots and the ground-control station (GCS).

Everything here crosses the scarce shared radio (paper 4.1: 115.2 kbps for 14 robots), so
messages are msgspec structs encoded as msgpack *arrays* (no field names on the wire), with
float32 wherever the precision allows (:class:`~protocol.wire.f32` fields). Each direction
has one tagged union (:data:`UplinkMessage`, :data:`DownlinkMessage`); every message travels
inside a :class:`Frame` carrying the protocol version and the stream sequence number.

Frames (paper 4.1, DESIGN section 1):

* ``odom`` is the robot's private frame (``odom/<robot>``): smooth, never loop-closed.
* ``base`` is the robot body: x forward, y left, z up (REP-103).
* ``map`` is the GCS's global frame. Robots never receive the map, only hazards in ``map`` and
  every robot's ``map_from_odom`` (:class:`HazardUpdate`).

A pose is ``(x_m, y_m, yaw_rad)``. A 3x3 pose covariance travels as its upper triangle
``(xx, xy, xθ, yy, yθ, θθ)`` in m², m·rad and rad², the order g2o uses for information.

Streams (:data:`STREAMS`) give each message its priority on the uplink queue and its delivery
semantics: ``RELIABLE`` (every message, exactly once, in order), ``LATEST`` (superseded
messages are dropped, never retransmitted) and ``LATEST_RELIABLE`` (only the newest matters,
but it is retransmitted until acknowledged or superseded).
"""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Any, ClassVar

import msgspec
import numpy as np
from msgspec.structs import force_setattr

from protocol.wire import (
    PROTOCOL_VERSION,
    ProtocolError,
    dec_hook,
    describe_path,
    enc_hook,
    ext_hook,
    f32,
    f32s,
)

__all__ = [
    "Ack",
    "AckEntry",
    "BROADCAST_ROBOT_ID",
    "BroadcastAck",
    "AutonomyMode",
    "Detection",
    "DetectionImage",
    "DownlinkFrame",
    "DownlinkMessage",
    "Direction",
    "FiducialObservation",
    "Frame",
    "GoToTask",
    "Hazard",
    "HazardUpdate",
    "HazardUpdateCoded",
    "IdleTask",
    "NeutralizeTask",
    "ObjectKind",
    "ParameterUpdate",
    "PauseTask",
    "PoseNode",
    "PoseNodeCoded",
    "RelayTask",
    "Reliability",
    "ResumeTask",
    "RobotAck",
    "RobotFrame",
    "STREAMS",
    "StreamSpec",
    "TaskMessage",
    "TaskState",
    "TaskStatus",
    "TeleopTask",
    "Telemetry",
    "covariance_from_upper",
    "covariance_to_upper",
    "TerrainGrid",
    "TerrainGridCoded",
    "ThumbnailRequest",
    "UplinkFrame",
    "UplinkMessage",
    "decode_frame",
    "encode_frame",
    "broadcast_stream_of",
    "stream_of",
]

#: The robot id under which broadcast traffic is metered (once, on the shared channel).
BROADCAST_ROBOT_ID = -1

F2 = tuple[float, float]
F3 = tuple[float, float, float]
F6 = tuple[float, float, float, float, float, float]


_UPPER_ROWS = (0, 0, 0, 1, 1, 2)
_UPPER_COLS = (0, 1, 2, 1, 2, 2)


def covariance_to_upper(covariance: Any) -> F6:
    """A 3x3 pose covariance as its upper triangle ``(xx, xy, xθ, yy, yθ, θθ)`` (g2o order)."""
    c = np.asarray(covariance, dtype=float)
    if c.shape != (3, 3):
        raise ValueError(f"covariance: expected a 3x3 matrix, got shape {c.shape}")
    return tuple(float(c[i, j]) for i, j in zip(_UPPER_ROWS, _UPPER_COLS, strict=True))  # type: ignore[return-value]


def covariance_from_upper(upper: Any) -> Any:
    """The symmetric 3x3 matrix (numpy) of an upper triangle ``(xx, xy, xθ, yy, yθ, θθ)``."""
    u = np.asarray(upper, dtype=float)
    if u.shape != (6,):
        raise ValueError(f"covariance: expected 6 upper-triangle values, got shape {u.shape}")
    c = np.empty((3, 3))
    c[_UPPER_ROWS, _UPPER_COLS] = u
    c[_UPPER_COLS, _UPPER_ROWS] = u
    return c


class _Message(msgspec.Struct, array_like=True, frozen=True, gc=False, omit_defaults=True):
    """Base of all radio messages: fields listed in ``_F32`` are rounded to float32.

    Trailing fields equal to their defaults are left off the wire (``omit_defaults``).
    """

    _F32: ClassVar[tuple[str, ...]] = ()
    _F32_TUPLES: ClassVar[tuple[str, ...]] = ()

    def __post_init__(self) -> None:
        for name in self._F32:
            force_setattr(self, name, f32(getattr(self, name)))
        for name in self._F32_TUPLES:
            force_setattr(self, name, f32s(getattr(self, name)))


# ----------------------------------------------------------------------------- enumerations


class ObjectKind(enum.IntEnum):
    """Objects of interest and other detected objects (paper section 2)."""

    UNKNOWN = 0
    STATIC_OOI = 1  # bomb: triggers within 2.5 m, 10 m blast
    TOXIC_VAT = 2
    CIVILIAN = 3  # blue
    HOSTILE = 4  # red mobile OOI: triggers within 2.5 m, 5 m blast
    MOBILE_OOI = 5


class AutonomyMode(enum.IntEnum):
    """What drives the robot now, for the autonomy metrics (paper section 7)."""

    IDLE = 0
    AUTONOMOUS = 1
    SEMI_AUTONOMOUS = 2
    TELEOPERATED = 3
    PAUSED = 4
    DISABLED = 5


class TaskState(enum.IntEnum):
    ACCEPTED = 0
    ACTIVE = 1
    SUCCEEDED = 2
    FAILED = 3
    REJECTED = 4
    CANCELED = 5


# ----------------------------------------------------------------------------- both directions


class AckEntry(msgspec.Struct, array_like=True, frozen=True, gc=False, omit_defaults=True):
    """Acknowledgement state of one reliable stream.

    ``through``: every sequence number up to and including it was received (0: none yet).
    ``received``: selective acknowledgement bitmap, little-endian bit order: bit ``i`` set
    means ``through + 2 + i`` was also received (``through + 1`` is the gap, by definition).
    """

    stream_id: int
    through: int
    received: bytes = b""


class Ack(_Message, tag=0, frozen=True):
    """Acknowledges reliable streams of the opposite direction (both directions use it).

    ``backlog_bytes``: reliable bytes the sender of this ack still has queued for the air
    (its demand; a robot's tells the GCS how much air time it needs, issue 16). An ack also
    rides inside a data frame (:class:`Frame` ``ack``) instead of going on its own.
    """

    entries: list[AckEntry]
    backlog_bytes: int = 0


# ----------------------------------------------------------------------------- robot -> GCS


class PoseNode(_Message, tag=1, frozen=True):
    """A new sample of the robot's trajectory with its odometry constraint (paper 4.2, 4.3.1).

    ``node_index`` counts this robot's nodes from 0 without gaps. ``pose_in_odom`` is the robot
    base in its private frame. ``odom_delta`` is this node's base pose in the previous node's
    base frame (``previous_from_current``), zeros for node 0, and ``odom_covariance`` its
    covariance (upper triangle, see module docstring). ``time_s``: mission clock.
    """

    _F32_TUPLES = ("pose_in_odom", "odom_delta", "odom_covariance")

    node_index: int
    time_s: float
    pose_in_odom: F3
    odom_delta: F3
    odom_covariance: F6


class PoseNodeCoded(_Message, tag=8, frozen=True):
    """A :class:`PoseNode` as the radio carries it: coded against the stream's previous node
    (:class:`protocol.stream_coding.PoseNodeCoder`). Made and undone by the radio channel;
    nodes and the GCS only ever see :class:`PoseNode`."""

    data: bytes


class TerrainGridCoded(_Message, tag=9, frozen=True):
    """A :class:`TerrainGrid` as the radio carries it (node index against the previous grid,
    resolution only when it changes: :class:`protocol.stream_coding.TerrainGridCoder`)."""

    data: bytes


class TerrainGrid(_Message, tag=2, frozen=True):
    """Binary grid of vertical surfaces around pose node ``node_index`` (paper 4.3.3, 4.3.4).

    ``data`` is the grid compressed by ``compression/`` (``encode_grid``); its header names the
    codec and model version and holds the grid's size and origin, so they are not repeated
    here: cell ``(row, col)`` covers ``(origin_cells + (col, row)) * resolution_m`` in the
    node's ``base`` frame (axes aligned with it). ``resolution_m``: the cell side.
    """

    _F32 = ("resolution_m",)

    node_index: int
    resolution_m: float
    data: bytes


class FiducialObservation(_Message, tag=3, frozen=True):
    """Another robot's AprilTag seen from pose node ``node_index`` (paper 4.3.2).

    ``observed_in_base``: pose of the observed robot's base in the observer's base frame, with
    ``covariance`` (upper triangle). ``tag_id`` is the decoded tag (36h11).
    """

    _F32_TUPLES = ("observed_in_base", "covariance")

    node_index: int
    time_s: float
    observed_robot_id: int
    tag_id: int
    observed_in_base: F3
    covariance: F6


class Detection(_Message, tag=4, frozen=True):
    """An object detected from pose node ``node_index`` (paper 5.2).

    ``position_in_base`` (m) with ``position_covariance`` ``(xx, xy, yy)`` in m²;
    ``radius_m`` and ``height_m`` from the cylinder fit; ``confidence`` in [0, 1].
    ``velocity_in_base`` (m/s) is a tracked object's velocity over the ground, expressed in
    the axes of node ``node_index``'s ``base`` (zero for static objects and untracked ones):
    a hostile walking towards the robot has a velocity pointing at the origin.
    """

    _F32 = ("radius_m", "height_m", "confidence")
    _F32_TUPLES = ("position_in_base", "position_covariance", "velocity_in_base")

    detection_id: int
    node_index: int
    time_s: float
    kind: ObjectKind
    position_in_base: F2
    position_covariance: F3
    radius_m: float
    height_m: float
    confidence: float
    velocity_in_base: F2 = (0.0, 0.0)


class DetectionImage(_Message, tag=5, frozen=True):
    """A camera image sent on demand, e.g. for an operator to confirm a detection (paper 6.1):
    a robot sends one only to answer a :class:`ThumbnailRequest`, never unasked.

    ``detection_id`` is 0 for an image not tied to a detection. ``camera_pan_rad``: camera
    heading in ``base``. ``encoding``: ``"jpeg"`` or ``"png"``.
    """

    _F32 = ("camera_pan_rad",)

    image_id: int
    detection_id: int
    time_s: float
    camera_pan_rad: float
    encoding: str
    width: int
    height: int
    data: bytes


class Telemetry(_Message, tag=6, frozen=True):
    """Latest robot state for operators (latest only: never retransmitted).

    ``velocity``: (linear m/s, angular rad/s) in ``base``; ``roll_pitch_rad`` from gravity;
    ``battery_frac`` in [0, 1]; ``task_id`` 0 when there is no task.
    """

    _F32 = ("battery_frac",)
    _F32_TUPLES = ("pose_in_odom", "velocity", "roll_pitch_rad")

    time_s: float
    pose_in_odom: F3
    velocity: F2
    roll_pitch_rad: F2
    battery_frac: float
    mode: AutonomyMode
    task_id: int


class TaskStatus(_Message, tag=7, frozen=True):
    """Progress of task ``task_id``; ``detail`` says why for failures and rejections."""

    task_id: int
    state: TaskState
    time_s: float
    detail: str = ""


# ----------------------------------------------------------------------------- GCS -> robot
# Task positions are in the receiving robot's private frame ``odom``: the GCS converts with
# its current estimate of ``map_from_odom`` (paper 4.1: robots receive goals in their own frame).


class GoToTask(_Message, tag=16, frozen=True):
    """Drive through ``waypoints_in_odom`` in order; ``speed_limit_m_s`` 0 means default."""

    _F32 = ("speed_limit_m_s",)

    task_id: int
    issued_time_s: float
    waypoints_in_odom: list[F2]
    speed_limit_m_s: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        force_setattr(self, "waypoints_in_odom", [f32s(p) for p in self.waypoints_in_odom])


class NeutralizeTask(_Message, tag=17, frozen=True):
    """Hold the laser pointer on the static OOI at ``target_in_odom`` for 15 s (paper 2).

    The robot drives to a stand-off pose ``standoff_m`` away with line of sight; it fires only
    when ``approved`` (an operator's confirmation).
    """

    _F32 = ("standoff_m",)
    _F32_TUPLES = ("target_in_odom",)

    task_id: int
    issued_time_s: float
    target_in_odom: F2
    standoff_m: float
    approved: bool


class PauseTask(_Message, tag=18, frozen=True):
    """Stop and hold the current task."""

    task_id: int
    issued_time_s: float


class ResumeTask(_Message, tag=19, frozen=True):
    """Resume the paused task."""

    task_id: int
    issued_time_s: float


class RelayTask(_Message, tag=20, frozen=True):
    """Drive to ``position_in_odom`` and hold there as a radio relay."""

    _F32_TUPLES = ("position_in_odom",)

    task_id: int
    issued_time_s: float
    position_in_odom: F2


class IdleTask(_Message, tag=21, frozen=True):
    """Drop any task and stay still."""

    task_id: int
    issued_time_s: float


class TeleopTask(_Message, tag=22, frozen=True):
    """Drive at (``linear_m_s``, ``angular_rad_s``) for ``duration_s``.

    ``conservative``: the robot stops before obstacles (paper 6.1's safe tele-operation).
    """

    _F32 = ("linear_m_s", "angular_rad_s", "duration_s")

    task_id: int
    issued_time_s: float
    linear_m_s: float
    angular_rad_s: float
    duration_s: float
    conservative: bool = True


class Hazard(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """A dangerous object in ``map``: keep out of ``radius_m`` around ``position_in_map``."""

    hazard_id: int
    kind: ObjectKind
    position_in_map: F2
    radius_m: float

    def __post_init__(self) -> None:
        force_setattr(self, "position_in_map", f32s(self.position_in_map))
        force_setattr(self, "radius_m", f32(self.radius_m))


class RobotFrame(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """The GCS's current ``map_from_odom`` for robot ``robot_id`` (``(x_m, y_m, yaw_rad)``)."""

    robot_id: int
    map_from_odom: F3

    def __post_init__(self) -> None:
        force_setattr(self, "map_from_odom", f32s(self.map_from_odom))


class HazardUpdate(_Message, tag=32, frozen=True):
    """All known hazards in ``map`` plus every robot's ``map_from_odom`` (paper 4.1).

    Sent once for all robots rather than once per robot in each private frame; each robot
    converts with its own entry of ``frames``.
    """

    time_s: float
    hazards: list[Hazard]
    frames: list[RobotFrame]


class HazardUpdateCoded(_Message, tag=36, frozen=True):
    """A :class:`HazardUpdate` as the broadcast carries it: ``frames`` packed as robot-id
    differences and quantised ``map_from_odom`` (:mod:`protocol.stream_coding`). Made and
    undone by the radio; robots only ever see :class:`HazardUpdate`."""

    time_s: float
    hazards: list[Hazard]
    frames: bytes


class RobotAck(msgspec.Struct, array_like=True, frozen=True, gc=False, omit_defaults=True):
    """One robot's share of a :class:`BroadcastAck`: what the GCS acknowledges of its uplink."""

    robot_id: int
    entries: list[AckEntry]


class BroadcastAck(_Message, tag=35, frozen=True):
    """The GCS's acknowledgements of many robots' uplinks, coalesced into one broadcast
    (one radio message and one framing for the whole team instead of one per robot)."""

    acks: list[RobotAck]


class ParameterUpdate(_Message, tag=33, frozen=True):
    """Set a robot parameter at run time by dotted name (e.g. ``planner.clearance_m``).

    Names under ``link.`` are the radio link's own and are consumed by the robot's channel,
    never delivered to the node: ``link.telemetry_period_s`` (float, mission seconds: the
    least time between two telemetry messages on the air; 0 lifts the limit).
    """

    name: str
    value: bool | int | float | str


class ThumbnailRequest(_Message, tag=34, frozen=True):
    """Ask the robot for a :class:`DetectionImage` of its detection ``detection_id`` (paper
    6.1: the operator confirms a detection from a small image). The robot crops the image its
    colour test used around the object and answers within ``max_bytes`` (0: its default) on
    the lowest-priority reliable uplink stream (``detection_image``)."""

    request_id: int
    detection_id: int
    max_bytes: int = 0


TaskMessage = GoToTask | NeutralizeTask | PauseTask | ResumeTask | RelayTask | IdleTask | TeleopTask
UplinkMessage = (
    Ack
    | PoseNode
    | PoseNodeCoded
    | TerrainGrid
    | TerrainGridCoded
    | FiducialObservation
    | Detection
    | DetectionImage
    | Telemetry
    | TaskStatus
)
DownlinkMessage = (
    Ack
    | TaskMessage
    | HazardUpdate
    | HazardUpdateCoded
    | ParameterUpdate
    | ThumbnailRequest
    | BroadcastAck
)


# ----------------------------------------------------------------------------- streams


class Direction(enum.Enum):
    UP = "up"  # robot -> GCS
    DOWN = "down"  # GCS -> robot


class Reliability(enum.Enum):
    RELIABLE = "reliable"  # every message, exactly once, in order
    LATEST = "latest"  # newest only, never retransmitted
    LATEST_RELIABLE = "latest_reliable"  # newest only, retransmitted until acked or superseded


@dataclass(frozen=True)
class StreamSpec:
    """One logical stream of one direction: its key name, id, queue priority and semantics.

    Lower ``priority`` drains first (DESIGN section 4: acks and task status first, then
    detections, pose nodes, fiducials, terrain grids, telemetry, images). ``broadcast``
    streams go from the GCS to every robot in range at once (paper 4.1), metered once; their
    reliable kinds are acknowledged by each robot in its ordinary uplink ack.
    """

    name: str
    stream_id: int
    direction: Direction
    priority: int
    reliability: Reliability
    types: tuple[type, ...]
    broadcast: bool = False


def _spec(
    name: str, sid: int, d: Direction, prio: int, rel: Reliability, *types: type
) -> StreamSpec:
    return StreamSpec(name, sid, d, prio, rel, types)


def _bspec(name: str, sid: int, prio: int, rel: Reliability, *types: type) -> StreamSpec:
    return StreamSpec(name, sid, Direction.DOWN, prio, rel, types, broadcast=True)


_UP, _DOWN = Direction.UP, Direction.DOWN
_R, _L, _LR = Reliability.RELIABLE, Reliability.LATEST, Reliability.LATEST_RELIABLE

#: Every stream, by direction then name.
STREAMS: dict[Direction, dict[str, StreamSpec]] = {
    _UP: {
        s.name: s
        for s in (
            _spec("ack", 0, _UP, 0, _L, Ack),
            _spec("task_status", 1, _UP, 1, _R, TaskStatus),
            _spec("detection", 2, _UP, 2, _R, Detection),
            _spec("pose_node", 3, _UP, 3, _R, PoseNode, PoseNodeCoded),
            _spec("fiducial", 4, _UP, 4, _R, FiducialObservation),
            _spec("terrain_grid", 5, _UP, 5, _R, TerrainGrid, TerrainGridCoded),
            _spec("telemetry", 6, _UP, 6, _L, Telemetry),
            _spec("detection_image", 7, _UP, 7, _R, DetectionImage),
        )
    },
    _DOWN: {
        s.name: s
        for s in (
            _spec("ack", 0, _DOWN, 0, _L, Ack),
            _spec("task", 1, _DOWN, 1, _R, *TaskMessage.__args__),
            _spec("hazard_update", 2, _DOWN, 2, _LR, HazardUpdate),
            _spec("parameter_update", 3, _DOWN, 3, _R, ParameterUpdate),
            _spec("thumbnail_request", 4, _DOWN, 4, _R, ThumbnailRequest),
            _bspec("ack_broadcast", 5, 0, _L, BroadcastAck),
            _bspec("hazard_broadcast", 6, 2, _LR, HazardUpdate, HazardUpdateCoded),
        )
    },
}

_STREAM_OF: dict[tuple[Direction, type], StreamSpec] = {
    (d, t): spec
    for d, specs in STREAMS.items()
    for spec in specs.values()
    if not spec.broadcast
    for t in spec.types
}
_BROADCAST_OF: dict[type, StreamSpec] = {
    t: spec for spec in STREAMS[Direction.DOWN].values() if spec.broadcast for t in spec.types
}


def stream_of(direction: Direction, message: Any) -> StreamSpec:
    """The stream that carries ``message`` in ``direction``; ``ProtocolError`` if none does."""
    try:
        return _STREAM_OF[(direction, type(message))]
    except KeyError:
        raise ProtocolError(
            f"{type(message).__name__} is not a {direction.value}link message"
        ) from None


def broadcast_stream_of(message: Any) -> StreamSpec:
    """The broadcast stream that carries ``message``; ``ProtocolError`` if none does."""
    try:
        return _BROADCAST_OF[type(message)]
    except KeyError:
        raise ProtocolError(f"{type(message).__name__} is not a broadcast message") from None


# ----------------------------------------------------------------------------- frames


class Frame(msgspec.Struct, array_like=True, frozen=True, gc=False):
    """What one radio message carries: protocol version, stream sequence number, message.

    ``seq`` counts from 1 per (robot, direction, stream) on reliable streams and orders latest
    streams; 0 for acks. The stream and robot are addressed by the key expression. ``ack``:
    acknowledgements of the opposite direction riding along (coalesced: no radio message and
    framing of their own), absent when there are none.
    """

    version: int
    seq: int
    msg: Any
    ack: Ack | None = None


class UplinkFrame(Frame, frozen=True, gc=False):
    """A :class:`Frame` as decoded from the uplink (robot to GCS)."""

    msg: UplinkMessage


class DownlinkFrame(Frame, frozen=True, gc=False):
    """A :class:`Frame` as decoded from the downlink (GCS to robot)."""

    msg: DownlinkMessage


_ENCODER = msgspec.msgpack.Encoder(enc_hook=enc_hook)
_DECODERS: dict[Direction, msgspec.msgpack.Decoder[Any]] = {
    Direction.UP: msgspec.msgpack.Decoder(UplinkFrame, dec_hook=dec_hook, ext_hook=ext_hook),
    Direction.DOWN: msgspec.msgpack.Decoder(DownlinkFrame, dec_hook=dec_hook, ext_hook=ext_hook),
}
_TAGS = {
    Direction.UP: {t.__struct_config__.tag for t in UplinkMessage.__args__},
    Direction.DOWN: {t.__struct_config__.tag for t in DownlinkMessage.__args__},
}
_FRAME_TYPES = {Direction.UP: UplinkFrame, Direction.DOWN: DownlinkFrame}


def encode_frame(seq: int, message: Any, ack: Ack | None = None) -> bytes:
    """Encode ``message`` with sequence number ``seq`` (and an ``ack`` riding along) into the
    bytes that cross the radio."""
    try:
        if ack is not None:
            return _ENCODER.encode((PROTOCOL_VERSION, seq, message, ack))
        return _ENCODER.encode((PROTOCOL_VERSION, seq, message))
    except (TypeError, ValueError, OverflowError, NotImplementedError) as err:
        raise ProtocolError(f"cannot encode {type(message).__name__}: {err}") from None


def _diagnose(data: bytes, direction: Direction, err: Exception) -> ProtocolError:
    """Turn a decoding failure into a ProtocolError that names the field when it can."""
    if isinstance(err, ProtocolError):
        return err
    text = str(err)
    try:
        raw = msgspec.msgpack.decode(data, ext_hook=lambda code, buf: None)
    except Exception:  # not even msgpack: report msgspec's own message
        return ProtocolError(f"{direction.value}link frame: malformed msgpack: {text}")
    if not (isinstance(raw, list) and len(raw) in (3, 4)):
        return ProtocolError(
            f"{direction.value}link frame: expected [version, seq, message(, ack)]"
        )
    if raw[0] != PROTOCOL_VERSION:
        return ProtocolError(
            f"{direction.value}link frame: protocol version {raw[0]!r}, expected {PROTOCOL_VERSION}"
        )
    msg = raw[2]
    if not (isinstance(msg, list) and msg and isinstance(msg[0], int)):
        return ProtocolError(f"{direction.value}link frame: message is not a tagged array")
    if msg[0] not in _TAGS[direction]:
        return ProtocolError(f"{direction.value}link frame: unknown message type tag {msg[0]}")
    if " - at `$" in text:
        problem, _, path = text.rpartition(" - at `$")
        where = describe_path(_FRAME_TYPES[direction], raw, path.rstrip("`"))
        problem = problem[:1].lower() + problem[1:]
        return ProtocolError(f"{where}: {problem.replace('`', '')}")
    return ProtocolError(f"{direction.value}link frame: {text}")


def decode_frame(data: bytes, direction: Direction) -> Frame:
    """Decode radio bytes of ``direction``; any problem raises :class:`ProtocolError`."""
    try:
        frame: Frame = _DECODERS[direction].decode(data)
        if frame.version != PROTOCOL_VERSION:
            raise ProtocolError(
                f"{direction.value}link frame: protocol version {frame.version}, "
                f"expected {PROTOCOL_VERSION}"
            )
        if frame.seq < 0:
            raise ProtocolError(f"{direction.value}link frame: negative sequence number")
        return frame
    except Exception as err:  # noqa: BLE001 - every failure must surface as ProtocolError
        raise _diagnose(data, direction, err) from None
