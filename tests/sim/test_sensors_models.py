"""Sensor models without PyBullet: IMU (gyro bias random walk, gravity), encoders, the
nodding LIDAR's pattern and schedule, the panning camera, tag textures, patrol routes."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from sim.actors import PatrolRoutes
from sim.apriltag import tag_texture
from sim.camera import CameraConfig, camera_axes, pan_angle
from sim.imu import EncoderConfig, ImuConfig, Imus, wheel_ticks
from sim.lidar import LidarConfig, NoddingLidars, beam_directions
from sim.world_generator import Human


def test_gyro_has_noise_and_a_bias_random_walk_and_accel_sees_gravity() -> None:
    n, dt, steps = 200, 0.05, 400
    imus = Imus(n, config=ImuConfig(), seed=1)
    zero = np.zeros(n)
    slope = math.radians(15.0)
    pitch = np.full(n, -slope)  # nose up on a 15 deg ramp, standing still
    bias0 = imus.gyro_bias.copy()
    for _ in range(steps):
        gyro, accel = imus.sample(
            dt, linear_m_s=zero, angular_rad_s=zero, roll_rad=zero, pitch_rad=pitch
        )
    drift = imus.gyro_bias - bias0
    expected = ImuConfig().gyro_bias_walk_rad_s_per_sqrt_s * math.sqrt(steps * dt)
    assert drift.std() == pytest.approx(expected, rel=0.15)  # random walk: grows with sqrt(t)
    assert (gyro - imus.gyro_bias).std() == pytest.approx(ImuConfig().gyro_noise_rad_s, rel=0.1)
    assert accel[:, 0].mean() == pytest.approx(9.81 * math.sin(slope), abs=0.01)
    assert accel[:, 2].mean() == pytest.approx(9.81 * math.cos(slope), abs=0.01)


def test_accelerometer_sees_forward_and_centripetal_acceleration() -> None:
    imus = Imus(1, config=ImuConfig(accel_noise_m_s2=0.0, accel_bias_m_s2=0.0), seed=0)
    z = np.zeros(1)
    imus.sample(0.1, linear_m_s=np.array([0.5]), angular_rad_s=z, roll_rad=z, pitch_rad=z)
    _, acc = imus.sample(
        0.1, linear_m_s=np.array([0.6]), angular_rad_s=np.array([1.0]), roll_rad=z, pitch_rad=z
    )
    assert acc[0] == pytest.approx([1.0, 0.6, 9.81])


def test_encoder_ticks_are_0_7_mm() -> None:
    t = wheel_ticks(np.array([0.0007 * 10 + 1e-6, 1.0]), np.array([-0.0007, 0.0]), EncoderConfig())
    assert t.tolist() == [[10, -1], [1428, 0]]


def test_lidar_pattern_covers_270_deg_and_nods_up_and_down() -> None:
    cfg = LidarConfig(beams=5, lines_per_sweep=4, tilt_min_deg=-30, tilt_max_deg=30)
    d = beam_directions(cfg, math.radians(20))
    assert np.allclose(np.linalg.norm(d, axis=1), 1.0)
    flat = beam_directions(cfg, 0.0)
    az = np.degrees(np.arctan2(flat[:, 1], flat[:, 0]))
    assert az[0] == pytest.approx(-135) and az[-1] == pytest.approx(135)
    assert d[2, 2] == pytest.approx(math.sin(math.radians(20)))  # straight ahead: tilted up
    lidars = NoddingLidars(2, config=cfg, lidar_in_base_m=(0.2, 0.0, 0.5))
    due = lidars.due(0.0)
    assert due == [(0, 0, 0)]  # robot 1's phase is staggered
    mats = np.repeat(np.eye(4)[None], 2, axis=0)
    tilts = []
    t = 0.0
    for _ in range(16):
        t += cfg.sweep_period_s / cfg.lines_per_sweep / 2
        for r, sweep, line in lidars.due(t):
            if r == 0:
                _, end, dirs = lidars.rays([(r, sweep, line)], mats)
                tilts.append((sweep, round(math.degrees(math.asin(dirs[2, 2])))))
    # sweep 0 goes up from -30 deg (its first line was taken above), sweep 1 comes down
    assert tilts[:8] == [(0, -10), (0, 10), (0, 30), (1, 30), (1, 10), (1, -10), (1, -30), (2, -30)]


def test_camera_pans_back_and_forth_continuously() -> None:
    cfg = CameraConfig(pan_rate_rad_s=1.0, pan_limit_rad=2.0)
    ts = np.arange(0.0, 16.0, 0.01)
    pans = np.array([pan_angle(t, cfg) for t in ts])
    assert pans.max() == pytest.approx(2.0, abs=0.01) and pans.min() == pytest.approx(
        -2.0, abs=0.01
    )
    assert np.abs(np.diff(pans)).max() <= 0.01 + 1e-9  # no jumps
    eye, fwd, up = camera_axes(np.eye(4), np.array([0.0, 0.0, 0.9]), math.pi / 2, 0.0)
    assert eye.tolist() == [0.0, 0.0, 0.9]
    assert np.allclose(fwd, [0, 1, 0]) and np.allclose(up, [0, 0, 1])


@pytest.mark.parametrize("tag_id", [0, 7, 586])
def test_tag_texture_decodes_to_its_id(tag_id: int) -> None:
    tex = tag_texture(tag_id, face_m=0.2, tag_size_m=0.137)
    det = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
        cv2.aruco.DetectorParameters(),
    )
    corners, ids, _ = det.detectMarkers(cv2.cvtColor(tex, cv2.COLOR_RGB2GRAY))
    assert ids is not None and ids.ravel().tolist() == [tag_id]
    side_px = np.linalg.norm(corners[0][0][0] - corners[0][0][1])
    assert side_px / len(tex) == pytest.approx(0.137 / 0.2, abs=0.004)  # 13.7 cm of 20 cm
    with pytest.raises(ValueError, match="0..586"):
        tag_texture(587)


def test_patrol_routes_walk_closed_loops_at_constant_speed() -> None:
    square = Human(0, "hostile", ((0.0, 0.0), (4.0, 0.0), (4.0, 3.0)), 1.0, 0.25, 1.7, (1, 0, 0, 1))
    still = Human(1, "civilian", ((5.0, 5.0),), 1.0, 0.25, 1.7, (0, 0, 1, 1))
    routes = PatrolRoutes((square, still))
    assert routes.positions(0.0).tolist() == [[0.0, 0.0], [5.0, 5.0]]
    assert routes.positions(2.0)[0].tolist() == pytest.approx([2.0, 0.0])
    assert routes.positions(5.5)[0].tolist() == pytest.approx([4.0, 1.5])
    assert routes.positions(12.0 + 2.0)[0].tolist() == pytest.approx([2.0, 0.0])  # loop: 12 m
    assert routes.positions(99.0)[1].tolist() == [5.0, 5.0]
