"""Sensor frames and commands between a robot's hardware (or the simulator) and its node.

This is the driver contract (DESIGN section 1): the simulator produces these frames and takes
these commands; a robot node consumes and sends them, either in the same process or over zenoh
(``magic/<mission>/sim/robot/<id>/...``). They are *not* radio traffic and are not metered.

The sensors follow the MAGIC robot (paper 3.1): a planar LIDAR nodding on a servo (one 3D sweep
per 1.25 s, about 50k points), a panning camera, wheel encoders and a 6-DOF IMU. All
quantities are in the robot body frame ``base`` (x forward, y left, z up) unless a name says
otherwise; times are mission-clock seconds.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import msgspec
import numpy as np

from protocol.wire import (
    PROTOCOL_VERSION,
    ProtocolError,
    check_array,
    dec_hook,
    describe_path,
    enc_hook,
    ext_hook,
)

__all__ = [
    "BatteryState",
    "CameraImage",
    "ClockTick",
    "ImageRequest",
    "ImuSample",
    "LaserPointerCommand",
    "LidarSweep",
    "RobotCommand",
    "RobotDriver",
    "SensorFrame",
    "VelocityCommand",
    "WheelTicks",
    "decode_command",
    "decode_sensor_frame",
    "encode_command",
    "encode_sensor_frame",
]

F3 = tuple[float, float, float]


class _Frame(msgspec.Struct, array_like=True, frozen=True, gc=False):
    pass


class LidarSweep(_Frame, tag=1, frozen=True):
    """One 3D sweep of the nodding LIDAR (paper 3.1: 270° planar scanner, sweep every 1.25 s).

    ``points_in_base`` is ``(N, 3)`` float32, each point in the body frame *at the instant it
    was measured* (the robot moves during a sweep: de-skew with odometry and
    ``point_time_s``). ``point_time_s`` is ``(N,)`` float32, seconds after ``time_s``. Points
    come scan line by scan line, each line in beam order; the points of a line share its time.
    ``sweep_index`` counts sweeps from 0.
    """

    sweep_index: int
    time_s: float
    duration_s: float
    points_in_base: np.ndarray
    point_time_s: np.ndarray

    def __post_init__(self) -> None:
        pts = check_array("LidarSweep.points_in_base", self.points_in_base, "float32", (None, 3))
        check_array("LidarSweep.point_time_s", self.point_time_s, "float32", (pts.shape[0],))


class CameraImage(_Frame, tag=2, frozen=True):
    """An RGB image (``(H, W, 3)`` uint8) with the camera pose and pinhole intrinsics.

    ``camera_pan_rad`` / ``camera_tilt_rad``: camera heading and elevation relative to
    ``base``; intrinsics in pixels. ``request_id`` echoes the :class:`ImageRequest` that asked
    for it (0 for an unsolicited image).
    """

    request_id: int
    time_s: float
    camera_pan_rad: float
    camera_tilt_rad: float
    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    rgb: np.ndarray

    def __post_init__(self) -> None:
        check_array("CameraImage.rgb", self.rgb, "uint8", (None, None, 3))


class WheelTicks(_Frame, tag=3, frozen=True):
    """Cumulative encoder counts of the left and right wheel sides (skid steer)."""

    time_s: float
    left_ticks: int
    right_ticks: int


class ImuSample(_Frame, tag=4, frozen=True):
    """Gyro (rad/s) and accelerometer (m/s², gravity included: +9.81 on z when level)."""

    time_s: float
    angular_velocity_rad_s: F3
    linear_acceleration_m_s2: F3


class BatteryState(_Frame, tag=6, frozen=True):
    """Remaining battery charge as a fraction of full, in [0, 1]."""

    time_s: float
    charge_frac: float


class ClockTick(_Frame, tag=5, frozen=True):
    """The mission clock, published by the simulator (or a real-time clock source)."""

    time_s: float


SensorFrame = LidarSweep | CameraImage | WheelTicks | ImuSample | ClockTick | BatteryState


class VelocityCommand(_Frame, tag=16, frozen=True):
    """Drive at ``linear_m_s`` forward and ``angular_rad_s`` counter-clockwise (body frame)."""

    time_s: float
    linear_m_s: float
    angular_rad_s: float


class LaserPointerCommand(_Frame, tag=17, frozen=True):
    """Point the disruptor's laser (paper 2) at ``pan_rad``/``tilt_rad`` in ``base``; ``on``."""

    time_s: float
    on: bool
    pan_rad: float
    tilt_rad: float


class ImageRequest(_Frame, tag=18, frozen=True):
    """Ask for the camera image at the camera pose recorded at ``time_s`` (paper 5.2's image
    memory of a continuously panning camera); answered by a :class:`CameraImage`."""

    request_id: int
    time_s: float
    width_px: int = 320
    height_px: int = 240


RobotCommand = VelocityCommand | LaserPointerCommand | ImageRequest


@runtime_checkable
class RobotDriver(Protocol):
    """What a robot node needs from its hardware; the simulator implements it.

    ``poll`` returns the frames that arrived since the last call, oldest first, waiting at most
    ``timeout_s`` for the first one (an empty list on timeout). ``send`` delivers a command.
    """

    robot_id: int

    def poll(self, timeout_s: float) -> list[SensorFrame]: ...

    def send(self, command: RobotCommand) -> None: ...


class _SensorEnvelope(msgspec.Struct, array_like=True, frozen=True, gc=False):
    version: int
    frame: SensorFrame


class _CommandEnvelope(msgspec.Struct, array_like=True, frozen=True, gc=False):
    version: int
    command: RobotCommand


_ENCODER = msgspec.msgpack.Encoder(enc_hook=enc_hook)
_SENSOR_DECODER = msgspec.msgpack.Decoder(_SensorEnvelope, dec_hook=dec_hook, ext_hook=ext_hook)
_COMMAND_DECODER = msgspec.msgpack.Decoder(_CommandEnvelope, dec_hook=dec_hook, ext_hook=ext_hook)


def _encode(obj: Any, kind: str) -> bytes:
    try:
        return _ENCODER.encode((PROTOCOL_VERSION, obj))
    except (TypeError, ValueError, OverflowError, NotImplementedError) as err:
        raise ProtocolError(f"cannot encode {kind} {type(obj).__name__}: {err}") from None


def _describe(envelope: type, data: bytes, text: str) -> str:
    """msgspec's ``problem - at `$path``` with the path named by field (``LidarSweep.time_s``)."""
    problem, sep, path = text.rpartition(" - at `$")
    if not sep:
        return text.replace("`", "")
    try:
        raw = msgspec.msgpack.decode(data, ext_hook=lambda code, buf: None)
        where = describe_path(envelope, raw, path.rstrip("`"))
    except Exception:  # noqa: BLE001 - fall back to msgspec's own text
        return text.replace("`", "")
    problem = problem.replace("`", "")
    if where.startswith(envelope.__name__):  # the whole frame: its own check names the field
        return problem
    return f"{where}: {problem[:1].lower() + problem[1:]}"


def _decode(decoder: msgspec.msgpack.Decoder[Any], data: bytes, kind: str) -> Any:
    try:
        env = decoder.decode(data)
    except ProtocolError as err:
        raise ProtocolError(f"{kind}: {err}") from None
    except Exception as err:  # noqa: BLE001 - every failure must surface as ProtocolError
        raise ProtocolError(f"{kind}: {_describe(decoder.type, data, str(err))}") from None
    if env.version != PROTOCOL_VERSION:
        raise ProtocolError(f"{kind}: protocol version {env.version}, expected {PROTOCOL_VERSION}")
    return env


def encode_sensor_frame(frame: SensorFrame) -> bytes:
    return _encode(frame, "sensor frame")


def decode_sensor_frame(data: bytes) -> SensorFrame:
    """Decode a sensor frame; any problem raises :class:`ProtocolError`."""
    return _decode(_SENSOR_DECODER, data, "sensor frame").frame  # type: ignore[no-any-return]


def encode_command(command: RobotCommand) -> bytes:
    return _encode(command, "robot command")


def decode_command(data: bytes) -> RobotCommand:
    """Decode a robot command; any problem raises :class:`ProtocolError`."""
    return _decode(_COMMAND_DECODER, data, "robot command").command  # type: ignore[no-any-return]
