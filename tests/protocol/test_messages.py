"""Radio messages: exact round trips, streams, and ProtocolError (naming the field) on bad bytes."""

from __future__ import annotations

import math
import struct
from typing import Any

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from protocol.messages import (
    STREAMS,
    Ack,
    AckEntry,
    AutonomyMode,
    BroadcastAck,
    Detection,
    DetectionImage,
    Direction,
    DownlinkFrame,
    DownlinkMessage,
    FiducialObservation,
    GoToTask,
    Hazard,
    HazardUpdate,
    HazardUpdateCoded,
    IdleTask,
    NeutralizeTask,
    ObjectKind,
    ParameterUpdate,
    PauseTask,
    PoseNode,
    PoseNodeCoded,
    RelayTask,
    Reliability,
    ResumeTask,
    RobotAck,
    RobotFrame,
    TaskState,
    TaskStatus,
    Telemetry,
    TeleopTask,
    TerrainGrid,
    TerrainGridCoded,
    ThumbnailRequest,
    UplinkFrame,
    UplinkMessage,
    broadcast_stream_of,
    decode_frame,
    encode_frame,
    stream_of,
)
from protocol.wire import PROTOCOL_VERSION, ProtocolError, f32

V = PROTOCOL_VERSION

UP, DOWN = Direction.UP, Direction.DOWN
FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ----------------------------------------------------------------------------- strategies

# msgpack carries int64 and uint64.
ints = st.integers(min_value=-(2**63), max_value=2**64 - 1)
seqs = st.integers(min_value=0, max_value=2**64 - 1)
f64 = st.floats(allow_nan=False)
# f32 fields: values float32 represents exactly, and arbitrary doubles (rounded on construction).
f32v = st.floats(width=32, allow_nan=False) | st.floats(allow_nan=False)
texts = st.text(max_size=16)
blobs = st.binary(max_size=48)


def f32_tuple(n: int) -> st.SearchStrategy[tuple[float, ...]]:
    return st.tuples(*[f32v] * n)


ack_entries = st.builds(AckEntry, stream_id=ints, through=ints, received=blobs)
acks = st.builds(
    Ack, entries=st.lists(ack_entries, max_size=4), backlog_bytes=st.integers(0, 2**40)
)
pose_nodes = st.builds(
    PoseNode,
    node_index=ints,
    time_s=f64,
    pose_in_odom=f32_tuple(3),
    odom_delta=f32_tuple(3),
    odom_covariance=f32_tuple(6),
)
terrain_grids = st.builds(
    TerrainGrid,
    node_index=ints,
    resolution_m=f32v,
    data=blobs,
)
fiducials = st.builds(
    FiducialObservation,
    node_index=ints,
    time_s=f64,
    observed_robot_id=ints,
    tag_id=ints,
    observed_in_base=f32_tuple(3),
    covariance=f32_tuple(6),
)
detections = st.builds(
    Detection,
    detection_id=ints,
    node_index=ints,
    time_s=f64,
    kind=st.sampled_from(ObjectKind),
    position_in_base=f32_tuple(2),
    position_covariance=f32_tuple(3),
    radius_m=f32v,
    height_m=f32v,
    confidence=f32v,
)
detection_images = st.builds(
    DetectionImage,
    image_id=ints,
    detection_id=ints,
    time_s=f64,
    camera_pan_rad=f32v,
    encoding=st.sampled_from(["jpeg", "png"]),
    width=ints,
    height=ints,
    data=blobs,
)
telemetries = st.builds(
    Telemetry,
    time_s=f64,
    pose_in_odom=f32_tuple(3),
    velocity=f32_tuple(2),
    roll_pitch_rad=f32_tuple(2),
    battery_frac=f32v,
    mode=st.sampled_from(AutonomyMode),
    task_id=ints,
)
task_statuses = st.builds(
    TaskStatus, task_id=ints, state=st.sampled_from(TaskState), time_s=f64, detail=texts
)
goto_tasks = st.builds(
    GoToTask,
    task_id=ints,
    issued_time_s=f64,
    waypoints_in_odom=st.lists(f32_tuple(2), max_size=6),
    speed_limit_m_s=f32v,
)
neutralize_tasks = st.builds(
    NeutralizeTask,
    task_id=ints,
    issued_time_s=f64,
    target_in_odom=f32_tuple(2),
    standoff_m=f32v,
    approved=st.booleans(),
)
pause_tasks = st.builds(PauseTask, task_id=ints, issued_time_s=f64)
resume_tasks = st.builds(ResumeTask, task_id=ints, issued_time_s=f64)
relay_tasks = st.builds(RelayTask, task_id=ints, issued_time_s=f64, position_in_odom=f32_tuple(2))
idle_tasks = st.builds(IdleTask, task_id=ints, issued_time_s=f64)
teleop_tasks = st.builds(
    TeleopTask,
    task_id=ints,
    issued_time_s=f64,
    linear_m_s=f32v,
    angular_rad_s=f32v,
    duration_s=f32v,
    conservative=st.booleans(),
)
hazards = st.builds(
    Hazard,
    hazard_id=ints,
    kind=st.sampled_from(ObjectKind),
    position_in_map=f32_tuple(2),
    radius_m=f32v,
)
robot_frames = st.builds(RobotFrame, robot_id=ints, map_from_odom=f32_tuple(3))
hazard_updates = st.builds(
    HazardUpdate,
    time_s=f64,
    hazards=st.lists(hazards, max_size=4),
    frames=st.lists(robot_frames, max_size=4),
)
parameter_updates = st.builds(
    ParameterUpdate,
    name=texts,
    value=st.one_of(st.booleans(), ints, f64, texts),
)
coded_blobs = st.binary(max_size=48)
pose_nodes_coded = st.builds(PoseNodeCoded, data=coded_blobs)
terrain_grids_coded = st.builds(TerrainGridCoded, data=coded_blobs)
hazard_updates_coded = st.builds(
    HazardUpdateCoded, time_s=f64, hazards=st.lists(hazards, max_size=4), frames=coded_blobs
)
broadcast_acks = st.builds(
    BroadcastAck,
    acks=st.lists(
        st.builds(RobotAck, robot_id=ints, entries=st.lists(ack_entries, max_size=3)),
        max_size=4,
    ),
)
thumbnail_requests = st.builds(
    ThumbnailRequest, request_id=ints, detection_id=ints, max_bytes=st.integers(0, 65535)
)

UPLINK: dict[type, st.SearchStrategy[Any]] = {
    Ack: acks,
    PoseNode: pose_nodes,
    PoseNodeCoded: pose_nodes_coded,
    TerrainGrid: terrain_grids,
    TerrainGridCoded: terrain_grids_coded,
    FiducialObservation: fiducials,
    Detection: detections,
    DetectionImage: detection_images,
    Telemetry: telemetries,
    TaskStatus: task_statuses,
}
DOWNLINK: dict[type, st.SearchStrategy[Any]] = {
    Ack: acks,
    GoToTask: goto_tasks,
    NeutralizeTask: neutralize_tasks,
    PauseTask: pause_tasks,
    ResumeTask: resume_tasks,
    RelayTask: relay_tasks,
    IdleTask: idle_tasks,
    TeleopTask: teleop_tasks,
    HazardUpdate: hazard_updates,
    ParameterUpdate: parameter_updates,
    ThumbnailRequest: thumbnail_requests,
    HazardUpdateCoded: hazard_updates_coded,
    BroadcastAck: broadcast_acks,
}
CASES = [(UP, t) for t in UPLINK] + [(DOWN, t) for t in DOWNLINK]
STRATEGIES = {UP: UPLINK, DOWN: DOWNLINK}


def test_strategies_cover_every_message_type() -> None:
    assert set(UPLINK) == set(UplinkMessage.__args__)
    assert set(DOWNLINK) == set(DownlinkMessage.__args__)


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize(("direction", "cls"), CASES, ids=lambda v: getattr(v, "__name__", v))
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), seq=seqs)
def test_round_trip(direction: Direction, cls: type, data: st.DataObject, seq: int) -> None:
    msg = data.draw(STRATEGIES[direction][cls])
    wire = encode_frame(seq, msg)
    frame = decode_frame(wire, direction)
    assert type(frame) is (UplinkFrame if direction is UP else DownlinkFrame)
    assert frame.version == PROTOCOL_VERSION
    assert frame.seq == seq
    assert type(frame.msg) is cls
    assert frame.msg == msg
    if cls is ParameterUpdate:  # True == 1 == 1.0: the type must survive too
        assert type(frame.msg.value) is type(msg.value)
    assert encode_frame(seq, frame.msg) == wire


@settings(max_examples=60, deadline=None)
@given(
    x=st.floats(allow_nan=False),
    pose=st.tuples(*[st.floats(allow_nan=False)] * 3),
    waypoints=st.lists(st.tuples(st.floats(allow_nan=False), st.floats(allow_nan=False))),
)
def test_f32_fields_hold_the_float32_rounding(
    x: float, pose: tuple[float, float, float], waypoints: list[tuple[float, float]]
) -> None:
    def r32(v: float) -> float:
        with np.errstate(over="ignore"):
            return float(np.float32(v))

    det = Detection(1, 2, 3.0, ObjectKind.CIVILIAN, (x, x), (x, 0.0, x), x, x, x)
    tele = Telemetry(x, pose, (x, x), (x, x), x, AutonomyMode.IDLE, 0)
    goto = GoToTask(1, x, waypoints, x)
    upd = HazardUpdate(x, [Hazard(1, ObjectKind.HOSTILE, (x, x), x)], [RobotFrame(2, pose)])
    decoded = [decode_frame(encode_frame(1, m), d).msg for m, d in [(det, UP), (tele, UP)]]
    decoded += [decode_frame(encode_frame(1, m), DOWN).msg for m in (goto, upd)]
    d_det, d_tele, d_goto, d_upd = decoded
    assert d_det.radius_m == d_det.height_m == d_det.confidence == r32(x)
    assert d_det.position_in_base == (r32(x), r32(x))
    assert d_tele.pose_in_odom == tuple(r32(v) for v in pose)
    assert d_tele.time_s == x  # float64 field: exact
    assert d_goto.waypoints_in_odom == [(r32(a), r32(b)) for a, b in waypoints]
    assert d_goto.issued_time_s == x
    assert d_upd.hazards[0].radius_m == r32(x)
    assert d_upd.hazards[0].position_in_map == (r32(x), r32(x))
    assert d_upd.frames[0].map_from_odom == tuple(r32(v) for v in pose)
    assert all(type(v) is f32 for v in (*d_tele.pose_in_odom, d_upd.hazards[0].radius_m))


def test_f32_fields_travel_as_msgpack_float32() -> None:
    msg = TerrainGrid(7, 0.1, b"\x01")
    wire = encode_frame(9, msg)
    # [version, seq, [tag, node, resolution, data]]
    expected = (
        bytes([0x93, V, 0x09]) + b"\x94\x02\x07\xca" + struct.pack(">f", 0.1) + b"\xc4\x01\x01"
    )
    assert wire == expected


def test_nan_f32_survives_bit_exact() -> None:
    msg = Telemetry(math.nan, (math.nan, 0.0, -0.0), (1.0, 2.0), (3.0, 4.0), math.nan, 1, 2)
    wire = encode_frame(3, msg)
    back = decode_frame(wire, UP).msg
    assert math.isnan(back.time_s) and math.isnan(back.battery_frac)
    assert math.isnan(back.pose_in_odom[0]) and math.copysign(1.0, back.pose_in_odom[2]) == -1.0
    assert encode_frame(3, back) == wire


def test_encode_failures_are_protocol_errors() -> None:
    with pytest.raises(ProtocolError, match=r"^cannot encode object"):
        encode_frame(1, object())
    with pytest.raises(ProtocolError, match=r"^cannot encode Ack"):
        encode_frame(1, Ack([AckEntry(2**70, 1)]))


# ----------------------------------------------------------------------------- streams


@pytest.mark.parametrize(("direction", "cls"), CASES, ids=lambda v: getattr(v, "__name__", v))
def test_every_message_type_has_exactly_one_stream(direction: Direction, cls: type) -> None:
    """One unicast stream per type (a broadcast stream may carry it too, see below)."""
    carrying = [s for s in STREAMS[direction].values() if cls in s.types and not s.broadcast]
    broadcast = [s for s in STREAMS[direction].values() if cls in s.types and s.broadcast]
    assert len(carrying) + len(broadcast) >= 1 and len(carrying) <= 1 and len(broadcast) <= 1
    msg = _sample(direction, cls)
    if carrying:
        spec = stream_of(direction, msg)
        assert spec is carrying[0]
        assert spec.direction is direction
        assert STREAMS[direction][spec.name] is spec
    else:
        with pytest.raises(ProtocolError, match="not a downlink message"):
            stream_of(direction, msg)
    if broadcast:
        assert broadcast_stream_of(msg) is broadcast[0]
    else:
        with pytest.raises(ProtocolError, match="not a broadcast message"):
            broadcast_stream_of(msg)


def _sample(direction: Direction, cls: type) -> Any:
    samples = {
        Ack: Ack([]),
        PoseNode: PoseNode(0, 0.0, (0, 0, 0), (0, 0, 0), (0, 0, 0, 0, 0, 0)),
        TerrainGrid: TerrainGrid(0, 0.1, b""),
        FiducialObservation: FiducialObservation(0, 0.0, 1, 2, (0, 0, 0), (0, 0, 0, 0, 0, 0)),
        Detection: Detection(0, 0, 0.0, ObjectKind.UNKNOWN, (0, 0), (0, 0, 0), 0, 0, 0),
        DetectionImage: DetectionImage(0, 0, 0.0, 0.0, "png", 1, 1, b""),
        Telemetry: Telemetry(0.0, (0, 0, 0), (0, 0), (0, 0), 1.0, AutonomyMode.IDLE, 0),
        TaskStatus: TaskStatus(1, TaskState.ACTIVE, 0.0),
        GoToTask: GoToTask(1, 0.0, [(1.0, 2.0)]),
        NeutralizeTask: NeutralizeTask(1, 0.0, (1, 2), 3.0, False),
        PauseTask: PauseTask(1, 0.0),
        ThumbnailRequest: ThumbnailRequest(1, 7),
        ResumeTask: ResumeTask(1, 0.0),
        RelayTask: RelayTask(1, 0.0, (1, 2)),
        IdleTask: IdleTask(1, 0.0),
        TeleopTask: TeleopTask(1, 0.0, 0.5, 0.1, 2.0),
        HazardUpdate: HazardUpdate(0.0, [], []),
        ParameterUpdate: ParameterUpdate("planner.clearance_m", 0.3),
        PoseNodeCoded: PoseNodeCoded(b"\x00"),
        TerrainGridCoded: TerrainGridCoded(b"\x00"),
        HazardUpdateCoded: HazardUpdateCoded(0.0, [], b""),
        BroadcastAck: BroadcastAck([]),
    }
    msg = samples[cls]
    assert type(msg) is cls and direction in STREAMS
    return msg


def test_streams_match_the_unions_and_the_design_priorities() -> None:
    for direction, union in ((UP, UplinkMessage), (DOWN, DownlinkMessage)):
        specs = list(STREAMS[direction].values())
        carried = {t for s in specs for t in s.types}
        assert sorted(carried, key=str) == sorted(union.__args__, key=str)
        assert len({s.stream_id for s in specs}) == len(specs)
        assert all(s.direction is direction for s in specs)
    by_priority = sorted(STREAMS[UP].values(), key=lambda s: s.priority)
    assert [s.name for s in by_priority] == [
        "ack",
        "task_status",
        "detection",
        "pose_node",
        "fiducial",
        "terrain_grid",
        "telemetry",
        "detection_image",
    ]
    assert STREAMS[UP]["telemetry"].reliability is Reliability.LATEST
    assert STREAMS[DOWN]["hazard_update"].reliability is Reliability.LATEST_RELIABLE
    assert STREAMS[DOWN]["task"].reliability is Reliability.RELIABLE
    assert STREAMS[DOWN]["hazard_broadcast"].reliability is Reliability.LATEST_RELIABLE
    assert STREAMS[DOWN]["ack_broadcast"].reliability is Reliability.LATEST
    assert [s.name for s in STREAMS[DOWN].values() if s.broadcast] == [
        "ack_broadcast",
        "hazard_broadcast",
    ]
    assert not any(s.broadcast for s in STREAMS[UP].values())


def test_stream_of_refuses_the_wrong_direction() -> None:
    with pytest.raises(ProtocolError, match=r"^GoToTask is not a uplink message$"):
        stream_of(UP, GoToTask(1, 0.0, []))
    with pytest.raises(ProtocolError, match=r"^Telemetry is not a downlink message$"):
        stream_of(DOWN, _sample(UP, Telemetry))
    with pytest.raises(ProtocolError, match=r"^Hazard is not a downlink message$"):
        stream_of(DOWN, Hazard(1, ObjectKind.HOSTILE, (0, 0), 1))


# ----------------------------------------------------------------------------- bad input


def _only_protocol_error(data: bytes, direction: Direction) -> None:
    """Decoding either succeeds with a valid frame or raises ProtocolError; nothing else."""
    try:
        frame = decode_frame(data, direction)
    except ProtocolError as err:
        assert str(err)
        return
    assert frame.version == PROTOCOL_VERSION and frame.seq >= 0


@pytest.mark.timeout(60)
@FUZZ
@given(data=st.binary(max_size=300), direction=st.sampled_from(Direction))
def test_random_bytes_give_only_protocol_error(data: bytes, direction: Direction) -> None:
    _only_protocol_error(data, direction)


@pytest.mark.timeout(60)
@FUZZ
@given(tail=st.binary(max_size=200), direction=st.sampled_from(Direction))
def test_random_message_bodies_give_only_protocol_error(tail: bytes, direction: Direction) -> None:
    # A valid frame header ([V, 1, ...]) so the fuzz reaches the message decoders.
    _only_protocol_error(bytes([0x93, V, 0x01]) + tail, direction)


all_messages = st.one_of(*[STRATEGIES[d][t].map(lambda m, d=d: (d, m)) for d, t in CASES])


def _mutate(data: st.DataObject, wire: bytes) -> bytes:
    buf = bytearray(wire)
    for _ in range(data.draw(st.integers(1, 4), label="mutations")):
        op = data.draw(st.sampled_from(["flip", "insert", "delete", "truncate"]))
        i = data.draw(st.integers(0, max(len(buf) - 1, 0)))
        if op == "flip" and buf:
            buf[i] ^= data.draw(st.integers(1, 255))
        elif op == "insert":
            buf.insert(i, data.draw(st.integers(0, 255)))
        elif op == "delete" and buf:
            del buf[i]
        else:
            del buf[i:]
    return bytes(buf)


@pytest.mark.timeout(60)
@FUZZ
@given(data=st.data(), seq=seqs)
def test_mutated_frames_give_only_protocol_error(data: st.DataObject, seq: int) -> None:
    direction, msg = data.draw(all_messages)
    mutated = _mutate(data, encode_frame(seq, msg))
    for d in Direction:
        _only_protocol_error(mutated, d)


msgpack_values = st.recursive(
    st.none() | st.booleans() | ints | st.floats() | texts | blobs,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(texts, inner, max_size=3),
    max_leaves=8,
)


def _replace(raw: Any, path: list[int], value: Any) -> Any:
    if not path:
        return value
    if not isinstance(raw, list) or not raw:
        return value
    out = list(raw)
    i = path[0] % len(out)
    out[i] = _replace(out[i], path[1:], value)
    return out


@pytest.mark.timeout(60)
@FUZZ
@given(
    data=st.data(),
    path=st.lists(st.integers(0, 20), min_size=1, max_size=5),
    value=msgpack_values,
)
def test_wrong_shapes_give_only_protocol_error(
    data: st.DataObject, path: list[int], value: Any
) -> None:
    direction, msg = data.draw(all_messages)
    raw = msgspec.msgpack.decode(encode_frame(1, msg))
    wrong = msgspec.msgpack.encode(_replace(raw, path, value))
    for d in Direction:
        _only_protocol_error(wrong, d)


def _raw(*frame: Any) -> bytes:
    return msgspec.msgpack.encode(list(frame))


GRID = [2, 5, 0.1, b""]
HAZARDS = [32, 1.0, [[1, 4, [0.0, 0.0], 5.0], [2, 1, [1.0, 1.0], 2.0]], [[3, [0.0, 0.0, 0.0]]]]


@pytest.mark.parametrize(
    ("frame", "direction", "expected"),
    [
        ([V, 3, [2, "5", *GRID[2:]]], UP, "TerrainGrid.node_index: expected int, got str"),
        ([V, 3, [*GRID[:2], "0.1", b""]], UP, "TerrainGrid.resolution_m: expected float, got str"),
        ([V, 3, [*GRID[:3], "data"]], UP, "TerrainGrid.data: expected bytes, got str"),
        (
            [V, 3, [32, 1.0, [[1, 4, [0.0, 0.0], "5"]], []]],
            DOWN,
            "HazardUpdate.hazards[0].radius_m: expected float, got str",
        ),
        (
            [V, 3, [*HAZARDS[:3], [[3, [0.0, 0.0, 0.0]], [4, [0.0, "x", 0.0]]]]],
            DOWN,
            "HazardUpdate.frames[1].map_from_odom[1]: expected float, got str",
        ),
        (
            [V, 3, [32, 1.0, [[1, 4, [0.0, 0.0], 5.0], [2, 77, [1.0, 1.0], 2.0]], []]],
            DOWN,
            "HazardUpdate.hazards[1].kind: invalid enum value 77",
        ),
        (
            [V, 3, [16, 1, 0.0, [[0.0, 1.0], [0.0, "1"]], 0.0]],
            DOWN,
            "GoToTask.waypoints_in_odom[1][1]: expected float, got str",
        ),
        ([V, 3, [0, [[1, "5", b""]]]], DOWN, "Ack.entries[0].through: expected int, got str"),
        (
            [V, 3, [33, "planner.clearance_m", [1]]],
            DOWN,
            "ParameterUpdate.value: expected bool | int | float | str, got array",
        ),
        ([V, 3, [7, 1, 9, 0.0, ""]], UP, "TaskStatus.state: invalid enum value 9"),
        ([V, 3, [7, 1, 1, 0.0, 5]], UP, "TaskStatus.detail: expected str, got int"),
        (
            [V, 3, [17, 1, 0.0, [1.0, 2.0], 1.0, 1]],
            DOWN,
            "NeutralizeTask.approved: expected bool, got int",
        ),  # noqa: E501
        ([V, "3", [0, []]], UP, "UplinkFrame.seq: expected int, got str"),
        ([99, 3, [0, []]], UP, f"uplink frame: protocol version 99, expected {V}"),
        ([0, 3, [99, "junk"]], DOWN, f"downlink frame: protocol version 0, expected {V}"),
        (["1", 3, [0, []]], UP, f"uplink frame: protocol version '1', expected {V}"),
        ([V, -1, [0, []]], UP, "uplink frame: negative sequence number"),
        ([V, 3, [99, []]], UP, "uplink frame: unknown message type tag 99"),
        ([V, 3, [16, 1, 0.0, [], 0.0]], UP, "uplink frame: unknown message type tag 16"),
        ([V, 3, [2, 5, "rle"]], DOWN, "downlink frame: unknown message type tag 2"),
        ([V, 3, "hello"], UP, "uplink frame: message is not a tagged array"),
        ([V, 3], UP, "uplink frame: expected [version, seq, message(, ack)]"),
    ],
)
def test_errors_name_the_field(frame: list[Any], direction: Direction, expected: str) -> None:
    with pytest.raises(ProtocolError) as info:
        decode_frame(_raw(*frame), direction)
    assert str(info.value) == expected


def test_malformed_msgpack_is_reported_as_such() -> None:
    with pytest.raises(ProtocolError, match=r"^uplink frame: malformed msgpack: "):
        decode_frame(b"\x93\x01\x01\xdd\xff\xff\xff\xff", UP)
    with pytest.raises(ProtocolError, match=r"^downlink frame: malformed msgpack: "):
        decode_frame(b"", DOWN)


def test_float64_beyond_float32_range_decodes_to_infinity() -> None:
    # An f32 field sent as float64 (another encoder) is rounded like any value: 1e300 -> inf.
    wire = _raw(V, 3, [4, 1, 2, 0.0, 1, [0.0, 0.0], [0.0, 0.0, 0.0], -1e300, 1.0, 0.5])
    msg = decode_frame(wire, UP).msg
    assert msg.radius_m == -math.inf and msg.height_m == 1.0
    assert Hazard(1, ObjectKind.HOSTILE, (1e39, 0.0), 3.5e38).radius_m == math.inf
