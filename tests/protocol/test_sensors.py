"""Sensor frames and robot commands: exact round trips with numpy fields, and ProtocolError."""

from __future__ import annotations

import struct
import tracemalloc
from typing import Any

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol.sensors import (
    CameraImage,
    ClockTick,
    ImageRequest,
    ImuSample,
    LaserPointerCommand,
    LidarSweep,
    RobotDriver,
    VelocityCommand,
    WheelTicks,
    decode_command,
    decode_sensor_frame,
    encode_command,
    encode_sensor_frame,
)
from protocol.wire import MAX_ARRAY_BYTES, PROTOCOL_VERSION, ProtocolError, enc_hook

FUZZ = settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
ENC = msgspec.msgpack.Encoder(enc_hook=enc_hook)

ints = st.integers(min_value=-(2**63), max_value=2**63 - 1)
f64 = st.floats()  # NaN included: frames are compared bit for bit


@st.composite
def lidar_sweeps(draw: st.DrawFn) -> LidarSweep:
    n = draw(st.integers(0, 40))
    return LidarSweep(
        sweep_index=draw(ints),
        time_s=draw(f64),
        duration_s=draw(f64),
        points_in_base=draw(hnp.arrays(np.float32, (n, 3))),
        point_time_s=draw(hnp.arrays(np.float32, (n,))),
    )


camera_images = st.builds(
    CameraImage,
    request_id=ints,
    time_s=f64,
    camera_pan_rad=f64,
    camera_tilt_rad=f64,
    fx_px=f64,
    fy_px=f64,
    cx_px=f64,
    cy_px=f64,
    rgb=hnp.arrays(np.uint8, st.tuples(st.integers(0, 12), st.integers(0, 12), st.just(3))),
)
wheel_ticks = st.builds(WheelTicks, time_s=f64, left_ticks=ints, right_ticks=ints)
imu_samples = st.builds(
    ImuSample,
    time_s=f64,
    angular_velocity_rad_s=st.tuples(f64, f64, f64),
    linear_acceleration_m_s2=st.tuples(f64, f64, f64),
)
clock_ticks = st.builds(ClockTick, time_s=f64)
SENSOR_FRAMES = {
    LidarSweep: lidar_sweeps(),
    CameraImage: camera_images,
    WheelTicks: wheel_ticks,
    ImuSample: imu_samples,
    ClockTick: clock_ticks,
}
COMMANDS = {
    VelocityCommand: st.builds(VelocityCommand, time_s=f64, linear_m_s=f64, angular_rad_s=f64),
    LaserPointerCommand: st.builds(
        LaserPointerCommand, time_s=f64, on=st.booleans(), pan_rad=f64, tilt_rad=f64
    ),
    ImageRequest: st.builds(
        ImageRequest, request_id=ints, time_s=f64, width_px=ints, height_px=ints
    ),
}


def assert_same(a: Any, b: Any) -> None:
    """Field-by-field identity: arrays by dtype, shape and bytes; floats bit for bit."""
    assert type(a) is type(b)
    for name in a.__struct_fields__:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray), name
            assert (x.dtype, x.shape) == (y.dtype, y.shape), name
            assert x.tobytes() == y.tobytes(), name
        else:
            assert type(x) is type(y), name
            assert msgspec.msgpack.encode(x) == msgspec.msgpack.encode(y), name


@pytest.mark.parametrize("cls", list(SENSOR_FRAMES), ids=lambda c: c.__name__)
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_sensor_frames_round_trip(cls: type, data: st.DataObject) -> None:
    frame = data.draw(SENSOR_FRAMES[cls])
    wire = encode_sensor_frame(frame)
    back = decode_sensor_frame(wire)
    assert_same(frame, back)
    assert encode_sensor_frame(back) == wire


@pytest.mark.parametrize("cls", list(COMMANDS), ids=lambda c: c.__name__)
@settings(max_examples=30, deadline=None)
@given(data=st.data())
def test_commands_round_trip(cls: type, data: st.DataObject) -> None:
    command = data.draw(COMMANDS[cls])
    wire = encode_command(command)
    back = decode_command(wire)
    assert_same(command, back)
    assert encode_command(back) == wire


def test_empty_sweep_round_trips() -> None:
    sweep = LidarSweep(4, 12.5, 1.25, np.zeros((0, 3), np.float32), np.zeros(0, np.float32))
    back = decode_sensor_frame(encode_sensor_frame(sweep))
    assert back.points_in_base.shape == (0, 3) and back.points_in_base.dtype == np.float32
    assert back.point_time_s.shape == (0,) and back.point_time_s.dtype == np.float32
    assert (back.sweep_index, back.time_s, back.duration_s) == (4, 12.5, 1.25)


def test_decoded_arrays_are_read_only() -> None:
    pts = np.arange(6, dtype=np.float32).reshape(2, 3)
    sweep = LidarSweep(0, 0.0, 1.25, pts, np.zeros(2, np.float32))
    back = decode_sensor_frame(encode_sensor_frame(sweep))
    with pytest.raises(ValueError, match="read-only"):
        back.points_in_base[0, 0] = 1.0
    np.testing.assert_array_equal(back.points_in_base, pts)


def test_image_request_defaults() -> None:
    back = decode_command(encode_command(ImageRequest(3, 1.5)))
    assert back == ImageRequest(3, 1.5, 320, 240)


# ----------------------------------------------------------------------------- violations


@pytest.mark.parametrize(
    ("make", "expected"),
    [
        (
            lambda: LidarSweep(0, 0.0, 1.0, np.zeros((2, 3)), np.zeros(2, np.float32)),
            "LidarSweep.points_in_base: expected dtype float32, got float64",
        ),
        (
            lambda: LidarSweep(0, 0.0, 1.0, np.zeros((2, 2), np.float32), np.zeros(2, np.float32)),
            "LidarSweep.points_in_base: expected shape (N, 3), got (2, 2)",
        ),
        (
            lambda: LidarSweep(0, 0.0, 1.0, np.zeros((2, 3), np.float32), np.zeros(3, np.float32)),
            "LidarSweep.point_time_s: expected shape (2), got (3,)",
        ),
        (
            lambda: CameraImage(0, 0.0, 0, 0, 1, 1, 0, 0, np.zeros((2, 2, 4), np.uint8)),
            "CameraImage.rgb: expected shape (N, N, 3), got (2, 2, 4)",
        ),
        (
            lambda: CameraImage(0, 0.0, 0, 0, 1, 1, 0, 0, [[[0, 0, 0]]]),
            "CameraImage.rgb: expected a numpy array, got list",
        ),
    ],
)
def test_construction_checks_name_the_field(make: Any, expected: str) -> None:
    with pytest.raises(ValueError) as info:
        make()
    assert str(info.value) == expected


def _case_id(value: Any) -> str | None:
    return value.split(": ", 1)[-1] if isinstance(value, str) else "case"


def _sensor(frame: list[Any], version: int = PROTOCOL_VERSION) -> bytes:
    return ENC.encode([version, frame])


F32_0 = np.zeros(0, np.float32)


@pytest.mark.parametrize(
    ("wire", "expected"),
    [
        (
            _sensor([1, 0, 0.0, 1.0, np.zeros((2, 3)), np.zeros(2, np.float32)]),
            "sensor frame: LidarSweep.points_in_base: expected dtype float32, got float64",
        ),
        (
            _sensor([1, 0, 0.0, 1.0, np.zeros((4, 2), np.float32), np.zeros(4, np.float32)]),
            "sensor frame: LidarSweep.points_in_base: expected shape (N, 3), got (4, 2)",
        ),
        (
            _sensor([1, 0, 0.0, 1.0, np.zeros((4, 3), np.float32), np.zeros((4, 1), np.float32)]),
            "sensor frame: LidarSweep.point_time_s: expected shape (4), got (4, 1)",
        ),
        (
            _sensor([1, 0, 0.0, 1.0, [[0.0, 0.0, 0.0]], F32_0]),
            "sensor frame: LidarSweep.points_in_base: expected array, got list",
        ),
        (
            _sensor([1, "0", 0.0, 1.0, np.zeros((0, 3), np.float32), F32_0]),
            "sensor frame: LidarSweep.sweep_index: expected int, got str",
        ),
        (
            _sensor([2, 0, 0.0, 0, 0, 1, 1, 0, 0, np.zeros((2, 2), np.uint8)]),
            "sensor frame: CameraImage.rgb: expected shape (N, N, 3), got (2, 2)",
        ),
        (
            _sensor([2, 0, 0.0, 0, 0, 1, 1, 0, 0, np.zeros((2, 2, 3), np.int8)]),
            "sensor frame: CameraImage.rgb: expected dtype uint8, got int8",
        ),
        (
            _sensor([4, 0.0, [0.0, 0.0], [0.0, 0.0, 9.81]]),
            "sensor frame: ImuSample.angular_velocity_rad_s: expected array of length 3, got 2",
        ),
        (
            _sensor([5, 1.0], version=99),
            f"sensor frame: protocol version 99, expected {PROTOCOL_VERSION}",
        ),
        (_sensor([16, 1.0, 0.0, 0.0]), "sensor frame: Invalid value 16"),
        (
            ENC.encode([PROTOCOL_VERSION, [1, 1.0, True, 0.0, 0.0]]),
            "robot command: Invalid value 1",
        ),
        (
            ENC.encode([PROTOCOL_VERSION, [17, 1.0, 1, 0.0, 0.0]]),
            "robot command: LaserPointerCommand.on: expected bool, got int",
        ),
        (
            ENC.encode([PROTOCOL_VERSION, [18, 3, 1.0, "320", 240]]),
            "robot command: ImageRequest.width_px: expected int, got str",
        ),
        (
            ENC.encode([0, [16, 1.0, 0.0, 0.0]]),
            f"robot command: protocol version 0, expected {PROTOCOL_VERSION}",
        ),
    ],
    ids=_case_id,
)
def test_bad_frames_name_the_field(wire: bytes, expected: str) -> None:
    decode = decode_command if expected.startswith("robot command") else decode_sensor_frame
    with pytest.raises(ProtocolError) as info:
        decode(wire)
    assert str(info.value) == expected


def _ext(code: int, ndim: int, shape: tuple[int, ...], nbytes: int) -> msgspec.msgpack.Ext:
    return msgspec.msgpack.Ext(
        1, struct.pack(f"<BB{len(shape)}I", code, ndim, *shape) + bytes(nbytes)
    )


@pytest.mark.parametrize(
    ("points", "expected"),
    [
        (
            _ext(1, 2, (2**32 - 1, 3), 0),
            f"array of shape (4294967295, 3) exceeds {MAX_ARRAY_BYTES} bytes",
        ),
        (_ext(1, 4, (2**31, 2**31, 2**31, 3), 0), f"exceeds {MAX_ARRAY_BYTES} bytes"),
        (_ext(12, 2, (1, 3), 12), "array extension has unknown dtype code 12"),
        (
            _ext(1, 2, (1000, 3), 12),
            "array of shape (1000, 3) and dtype float32 needs 12000 bytes, got 12",
        ),
        (_ext(1, 6, (1, 3, 1, 1, 1, 1), 12), "array extension has 6 dimensions, at most 4 allowed"),
        (msgspec.msgpack.Ext(1, b"\x01\x02\x01\x00"), "array extension shorter than its shape"),
        (msgspec.msgpack.Ext(42, b""), "unknown msgpack extension type 42"),
    ],
    ids=_case_id,
)
def test_hostile_array_headers(points: msgspec.msgpack.Ext, expected: str) -> None:
    wire = _sensor([1, 0, 0.0, 1.0, points, F32_0])
    tracemalloc.start()
    try:
        with pytest.raises(ProtocolError) as info:
            decode_sensor_frame(wire)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert str(info.value).startswith("sensor frame: ")
    assert expected in str(info.value)
    assert peak < 1_000_000


def test_frames_and_commands_do_not_mix() -> None:
    with pytest.raises(ProtocolError, match="^robot command: "):
        decode_command(encode_sensor_frame(ClockTick(1.0)))
    with pytest.raises(ProtocolError, match="^sensor frame: "):
        decode_sensor_frame(encode_command(VelocityCommand(1.0, 0.5, 0.0)))


def test_encode_failures_are_protocol_errors() -> None:
    with pytest.raises(ProtocolError, match=r"^cannot encode sensor frame object"):
        encode_sensor_frame(object())  # type: ignore[arg-type]
    with pytest.raises(ProtocolError, match=r"^cannot encode robot command WheelTicks"):
        encode_command(WheelTicks(0.0, 2**64, 0))  # type: ignore[arg-type]


def _only_protocol_error(data: bytes) -> None:
    for decode in (decode_sensor_frame, decode_command):
        try:
            decode(data)
        except ProtocolError as err:
            assert str(err)


@pytest.mark.timeout(60)
@FUZZ
@given(data=st.binary(max_size=300))
def test_random_bytes_give_only_protocol_error(data: bytes) -> None:
    _only_protocol_error(data)
    _only_protocol_error(b"\x92\x01" + data)  # a valid envelope head: reach the frame decoders


VALID = [
    encode_sensor_frame(
        LidarSweep(
            1,
            2.0,
            1.25,
            np.arange(12, dtype=np.float32).reshape(4, 3),
            np.linspace(0, 1, 4, dtype=np.float32),
        )
    ),
    encode_sensor_frame(
        CameraImage(1, 2.0, 0.1, 0.2, 300, 300, 160, 120, np.ones((2, 3, 3), np.uint8))
    ),
    encode_sensor_frame(ImuSample(1.0, (0.0, 0.1, 0.2), (0.0, 0.0, 9.81))),
    encode_sensor_frame(WheelTicks(1.0, 100, -100)),
    encode_command(LaserPointerCommand(1.0, True, 0.5, -0.1)),
    encode_command(ImageRequest(7, 3.0)),
]


@pytest.mark.timeout(60)
@FUZZ
@given(data=st.data())
def test_mutated_frames_give_only_protocol_error(data: st.DataObject) -> None:
    buf = bytearray(data.draw(st.sampled_from(VALID)))
    for _ in range(data.draw(st.integers(1, 4))):
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
    _only_protocol_error(bytes(buf))


def test_robot_driver_protocol_is_runtime_checkable() -> None:
    class Driver:
        robot_id = 3

        def poll(self, timeout_s: float) -> list[Any]:
            return []

        def send(self, command: Any) -> None:
            return None

    assert isinstance(Driver(), RobotDriver)
    assert not isinstance(object(), RobotDriver)
