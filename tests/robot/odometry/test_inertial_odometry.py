"""Inertially-aided odometry on synthetic skid-steer drives with known truth.

The simulator-based checks of issue 4 (200 m scripted drive) live with the simulator tests;
here the sensor models are explicit so each property can be isolated.
"""

from __future__ import annotations

import math
from typing import Any

import msgspec
import numpy as np
import pytest

from protocol.se2 import wrap_angle
from protocol.sensors import ImuSample, WheelTicks
from robot.odometry.inertial_odometry import (
    GRAVITY_M_S2,
    InertialOdometry,
    OdometryConfig,
    OdometryIncrement,
)
from robot.odometry.pose_node_maker import PoseNodeMaker

M_PER_TICK = 0.0007
ACCEL_SLIP_STEP_M_S = 0.1  # the measured setting (robot.odometry.inertial_odometry)


def drive(
    segments: list[tuple[float, float, float]],
    *,
    rate_hz: float = 100.0,
    bias0: float = 0.0,
    bias_walk: float = 0.0,
    gyro_noise: float = 0.0,
    slip_std: float = 0.0,
    seed: int = 0,
    odo: InertialOdometry | None = None,
) -> tuple[InertialOdometry, np.ndarray, float]:
    """Drive ``(duration_s, v_m_s, w_rad_s)`` segments; returns odometry, true pose, distance."""
    rng = np.random.default_rng(seed)
    odo = odo or InertialOdometry(OdometryConfig(m_per_tick=M_PER_TICK))
    dt = 1.0 / rate_hz
    x = y = yaw = 0.0
    bias = bias0
    left = right = 0.0
    t = 0.0
    dist = 0.0
    half_track = 0.25
    v_prev = 0.0  # the accelerometer feels every change of speed (here all within a sample)
    odo.add_imu(ImuSample(0.0, (0.0, 0.0, bias), (0.0, 0.0, GRAVITY_M_S2)))
    odo.add_ticks(WheelTicks(0.0, 0, 0))
    for duration, v, w in segments:
        for _ in range(int(round(duration * rate_hz))):
            t += dt
            yaw_mid = yaw + 0.5 * w * dt
            x += v * dt * math.cos(yaw_mid)
            y += v * dt * math.sin(yaw_mid)
            yaw += w * dt
            dist += abs(v) * dt
            slip = 1.0 + slip_std * rng.standard_normal() if (v or w) else 1.0
            left += (v - w * half_track) * dt * slip / M_PER_TICK
            right += (v + w * half_track) * dt * slip / M_PER_TICK
            bias += bias_walk * math.sqrt(dt) * rng.standard_normal()
            vib = 0.3 * rng.standard_normal(3) if (v or w) else 0.002 * rng.standard_normal(3)
            gyro = (0.0, 0.0, w + bias + gyro_noise / math.sqrt(dt) * rng.standard_normal())
            accel = (vib[0] + (v - v_prev) / dt, vib[1], GRAVITY_M_S2 + vib[2])
            v_prev = v
            odo.add_imu(ImuSample(t, gyro, accel))
            odo.add_ticks(WheelTicks(t, int(left), int(right)))
    return odo, np.array([x, y, float(wrap_angle(yaw))]), dist


def test_noise_free_drive_matches_truth() -> None:
    odo, truth, dist = drive(
        [(10.0, 1.0, 0.0), (5.0, 0.5, 0.3), (10.0, 1.0, -0.2), (3.0, 0.0, 0.5)]
    )
    est = odo.pose_in_odom
    assert np.hypot(*(est[:2] - truth[:2])) < 0.005 * dist
    assert abs(float(wrap_angle(est[2] - truth[2]))) < 1e-3
    # |distance| also sums the encoders' quantization jitter (0.7 mm ticks) when turning
    assert odo.distance_m == pytest.approx(dist, rel=3e-3)


def test_gyro_bias_converges_while_still() -> None:
    odo, _, _ = drive([(30.0, 0.0, 0.0)], bias0=0.02, gyro_noise=3e-4)
    # 29 s of still samples at 3e-4 rad/s/sqrt(Hz): the estimate's std is about 6e-5 rad/s
    assert odo.gyro_bias_rad_s[2] == pytest.approx(0.02, abs=3e-4)
    assert odo.is_still


def test_turning_in_place_at_constant_rate_is_not_taken_for_stillness() -> None:
    odo, truth, _ = drive([(20.0, 0.0, 0.3)], bias0=0.0)
    assert not odo.is_still
    assert abs(odo.gyro_bias_rad_s[2]) < 1e-6  # the turn rate was not learned as bias
    assert abs(float(wrap_angle(odo.pose_in_odom[2] - truth[2]))) < 1e-3


def test_zero_velocity_recalibration_bounds_heading_drift() -> None:
    """A drifting gyro bias with regular stops: heading drift stays under 1° per minute and
    position drift under 2% of the distance; without stops it would not."""
    stop_and_go = []
    for k in range(10):  # about 200 m in 10 min with 10 s stops
        stop_and_go += [(10.0, 0.0, 0.0), (40.0, 0.5, 0.05 * (-1) ** k)]
    # MEMS-grade gyro: 0.01 rad/s initial bias wandering 2e-5 rad/s/sqrt(s), white noise
    # 3e-4 rad/s/sqrt(Hz); 5% wheel slip noise per sample
    kw: dict[str, Any] = {
        "bias0": 0.01,
        "bias_walk": 2e-5,
        "gyro_noise": 3e-4,
        "slip_std": 0.05,
        "seed": 3,
    }
    odo, truth, dist = drive(stop_and_go, **kw)
    minutes = sum(d for d, _, _ in stop_and_go) / 60.0
    heading_err_deg = abs(math.degrees(float(wrap_angle(odo.pose_in_odom[2] - truth[2]))))
    assert dist > 190.0
    assert heading_err_deg / minutes <= 1.0
    assert np.hypot(*(odo.pose_in_odom[:2] - truth[:2])) <= 0.02 * dist
    # the same drive with recalibration disabled drifts far more
    frozen = InertialOdometry(OdometryConfig(m_per_tick=M_PER_TICK, still_window_s=1e9))
    odo2, truth2, _ = drive(stop_and_go, odo=frozen, **kw)
    frozen_err = abs(math.degrees(float(wrap_angle(odo2.pose_in_odom[2] - truth2[2]))))
    assert frozen_err > 5 * heading_err_deg


def test_roll_and_pitch_from_gravity() -> None:
    odo = InertialOdometry()
    roll, pitch = 0.1, -0.2
    g = GRAVITY_M_S2
    accel = (
        -g * math.sin(pitch),
        g * math.sin(roll) * math.cos(pitch),
        g * math.cos(roll) * math.cos(pitch),
    )
    for i in range(500):
        odo.add_imu(ImuSample(0.01 * (i + 1), (0.0, 0.0, 0.0), accel))
    r, p = odo.roll_pitch_rad
    assert r == pytest.approx(roll, abs=1e-3)
    assert p == pytest.approx(pitch, abs=1e-3)


def test_pose_at_interpolates_history() -> None:
    odo, _, _ = drive([(10.0, 1.0, 0.0)])
    assert odo.pose_at(5.0)[0] == pytest.approx(5.0, abs=0.002)
    assert odo.pose_at(5.005)[0] == pytest.approx(5.005, abs=0.002)  # between readings
    assert odo.pose_at(-1.0)[0] == pytest.approx(odo.pose_at(0.0)[0])


def test_bad_samples_are_refused_with_clear_errors() -> None:
    odo = InertialOdometry()
    odo.add_imu(ImuSample(1.0, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
    with pytest.raises(ValueError, match="non-finite"):
        odo.add_imu(ImuSample(2.0, (math.nan, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
    with pytest.raises(ValueError, match="not after"):
        odo.add_imu(ImuSample(0.5, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
    odo.add_ticks(WheelTicks(1.0, 0, 0))
    with pytest.raises(ValueError, match="not after"):
        odo.add_ticks(WheelTicks(1.0, 5, 5))
    with pytest.raises(ValueError, match="m_per_tick"):
        OdometryConfig(m_per_tick=0.0)


def test_pose_nodes_chain_exactly_and_covariance_grows_with_motion() -> None:
    odo = InertialOdometry(OdometryConfig(m_per_tick=M_PER_TICK))
    maker = PoseNodeMaker()
    nodes = []
    rng = np.random.default_rng(0)
    t, x, yaw, left, right = 0.0, 0.0, 0.0, 0.0, 0.0
    for _ in range(2000):  # 20 s at 1 m/s with a gentle turn
        t += 0.01
        w = 0.1
        yaw += w * 0.01
        x += 0.01
        left += (1.0 - 0.25 * w) * 0.01 / M_PER_TICK
        right += (1.0 + 0.25 * w) * 0.01 / M_PER_TICK
        odo.add_imu(
            ImuSample(t, (0.0, 0.0, w), tuple(rng.normal(0, 0.01, 3) + [0, 0, GRAVITY_M_S2]))
        )
        inc = odo.add_ticks(WheelTicks(t, int(left), int(right)))
        if inc is not None:
            maker.add_increment(inc)
        if maker.due(odo.pose_in_odom, t):
            nodes.append(maker.make(odo.pose_in_odom, t))
    assert [n.node_index for n in nodes] == list(range(len(nodes)))
    assert 15 <= len(nodes) <= 25  # about one per metre
    # composing the deltas reproduces each node's pose (float32 on the wire)
    from protocol.se2 import compose

    pose = np.array(nodes[0].pose_in_odom)
    for n in nodes[1:]:
        pose = compose(pose, np.array(n.odom_delta))
        assert np.allclose(pose[:2], n.pose_in_odom[:2], atol=1e-3)
    for n in nodes[1:]:
        c = np.array(n.odom_covariance)
        cov = np.array([[c[0], c[1], c[2]], [c[1], c[3], c[4]], [c[2], c[4], c[5]]])
        assert np.all(np.linalg.eigvalsh(cov) > 0)
        # distance variance grows per metre: 0.03 m std after 1 m (default config)
        d = np.hypot(*n.odom_delta[:2])
        assert math.sqrt(cov[0, 0]) == pytest.approx(0.03 * math.sqrt(d), rel=0.3)


def _skid_drive(
    odo: InertialOdometry,
    maker: PoseNodeMaker,
    *,
    seconds: float,
    turn_traction: float,
    distance_traction: float,
    t0: float = 0.0,
    pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ticks: tuple[float, float] = (0.0, 0.0),
) -> tuple[float, tuple[float, float, float], tuple[float, float], list[float]]:
    """A weaving drive at 0.9 m/s on a skid-steer (effective track 0.6 m) whose body turns
    ``turn_traction`` and moves ``distance_traction`` of what its wheels ask (the gyro sees the
    body). Returns the end time, the true pose, the tick counts and each node's distance std."""
    dt = 0.05
    t, (x, y, yaw), (left, right) = t0, pose, ticks
    stds = []
    for _ in range(int(round(seconds / dt))):
        t += dt
        wheel_w = 0.3 * math.sin(2.0 * math.pi * t / 4.0)
        body_w, body_v = wheel_w * turn_traction, 0.9 * distance_traction
        x += body_v * dt * math.cos(yaw + 0.5 * body_w * dt)
        y += body_v * dt * math.sin(yaw + 0.5 * body_w * dt)
        yaw += body_w * dt
        left += (0.9 - 0.3 * wheel_w) * dt / M_PER_TICK
        right += (0.9 + 0.3 * wheel_w) * dt / M_PER_TICK
        odo.add_imu(ImuSample(t, (0.0, 0.0, body_w), (0.0, 0.0, GRAVITY_M_S2)))
        inc = odo.add_ticks(WheelTicks(t, int(left), int(right)))
        if inc is not None:
            maker.add_increment(inc)
        if maker.due(odo.pose_in_odom, t):
            node = maker.make(odo.pose_in_odom, t)
            stds.append(math.sqrt(node.odom_covariance[0] + node.odom_covariance[3]))
    return t, (x, y, yaw), (left, right), stds


def test_slip_seen_as_skid_grows_the_node_covariance_and_corrects_the_distance() -> None:
    # hard ground (the wheels' turn is the gyro's), then 12 s of sand: the body turns 83% and
    # moves 75% of what the wheels ask, as on the simulated robot in its sand pits
    skid = OdometryConfig(
        m_per_tick=M_PER_TICK, effective_track_m=0.6, slip_per_skid=1.5, slip_std_per_skid=1.0
    )
    results = {}
    for name, cfg in (("off", OdometryConfig(m_per_tick=M_PER_TICK)), ("skid", skid)):
        odo, maker = InertialOdometry(cfg), PoseNodeMaker()
        odo.add_imu(ImuSample(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
        odo.add_ticks(WheelTicks(0.0, 0, 0))
        t, pose, ticks, hard = _skid_drive(
            odo, maker, seconds=10.0, turn_traction=1.0, distance_traction=1.0
        )
        assert odo.turn_traction == pytest.approx(1.0, abs=0.02) or name == "off"
        hard_error = math.hypot(odo.pose_in_odom[0] - pose[0], odo.pose_in_odom[1] - pose[1])
        t, pose, ticks, sand = _skid_drive(
            odo, maker, seconds=12.0, turn_traction=0.83, distance_traction=0.75,
            t0=t, pose=pose, ticks=ticks,
        )  # fmt: skip
        error = math.hypot(odo.pose_in_odom[0] - pose[0], odo.pose_in_odom[1] - pose[1])
        results[name] = (hard, hard_error, sand, error, odo)
    off_hard, off_hard_error, off_sand, off_error, off = results["off"]
    on_hard, on_hard_error, on_sand, on_error, on = results["skid"]
    # hard ground: nothing changes (same nodes, same covariances, same pose)
    assert on_hard == pytest.approx(off_hard, rel=1e-9)
    assert on_hard_error == pytest.approx(off_hard_error, abs=1e-9)
    # sand: the loss of turn traction is measured, the nodes say their distance is uncertain
    assert on.turn_traction == pytest.approx(0.83, abs=0.02)
    assert math.isnan(off.turn_traction)
    assert max(off_sand) < 0.05
    assert np.median(on_sand[-4:]) > 0.15  # each ~1.1 m node slipped ~0.3 m
    # and the distance is corrected by the calibrated share: most of the 2.7 m error is gone
    assert off_error > 2.0
    assert on_error < 0.3 * off_error


def test_lidar_measured_displacement_moves_the_traction_and_reports_the_error() -> None:
    cfg = OdometryConfig(m_per_tick=M_PER_TICK, displacement_gain=0.5, traction_memory_m=3.0)
    odo = InertialOdometry(cfg)
    assert odo.observe_displacement(odometry_m=1.0, measured_m=0.98, sigma_m=0.05) == 0.0
    assert odo.traction == 1.0  # within the measurement's sigma: noise, not slip
    error = odo.observe_displacement(odometry_m=1.2, measured_m=0.9, sigma_m=0.1)
    assert error == pytest.approx(-0.3)  # signed: measured - odometry
    assert odo.traction < 0.9  # half way from 1 towards 0.75
    # later distances are scaled by it, and it relaxes as the robot drives on
    odo.add_imu(ImuSample(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
    odo.add_ticks(WheelTicks(0.0, 0, 0))
    ticks = int(1.0 / M_PER_TICK)
    inc = odo.add_ticks(WheelTicks(1.0, ticks, ticks))
    assert inc is not None and inc.distance_m == pytest.approx(0.87, abs=0.02)
    for k in range(2, 12):
        odo.add_ticks(WheelTicks(float(k), k * ticks, k * ticks))
    assert odo.traction == pytest.approx(1.0, abs=0.01)
    # never below min_traction, whatever a bad match claims; bad input is refused
    odo.observe_displacement(odometry_m=1.0, measured_m=-5.0)
    assert odo.traction >= cfg.min_traction
    with pytest.raises(ValueError, match="odometry_m"):
        odo.observe_displacement(odometry_m=0.0, measured_m=0.5)
    with pytest.raises(ValueError, match="measured_m"):
        odo.observe_displacement(odometry_m=1.0, measured_m=math.nan)
    # the default (gain 0) only reports: the odometry is as before
    plain = InertialOdometry(OdometryConfig(m_per_tick=M_PER_TICK))
    plain.observe_displacement(odometry_m=1.0, measured_m=0.5)
    assert plain.traction == 1.0


def test_a_measured_shortfall_grows_the_next_node_along_its_motion() -> None:
    maker = PoseNodeMaker()
    maker.make(np.zeros(3), 0.0)
    maker.add_increment(OdometryIncrement(0.6, 0.0, 0.5))
    maker.add_increment(OdometryIncrement(0.6, 0.0, 0.5))
    maker.add_distance_variance(0.25**2)
    node = maker.make(np.array([1.2, 0.0, 0.0]), 1.0)
    c = node.odom_covariance  # upper triangle: xx, xy, xt, yy, yt, tt
    assert math.sqrt(c[0]) == pytest.approx(math.hypot(0.25, 0.03 * math.sqrt(1.2)), rel=0.02)
    assert math.sqrt(c[3]) < 0.02  # across the motion: unchanged
    after = maker.make(np.array([1.2, 0.0, 0.0]), 2.0)  # the next node does not carry it
    assert after.odom_covariance[0] < 1e-3
    with pytest.raises(ValueError, match="add_distance_variance"):
        maker.add_distance_variance(-1.0)


def test_lidar_aided_heading_learns_the_gyro_bias_while_driving() -> None:
    """No stop after the start: a bias 0.01 rad/s off drifts the unaided heading 34 deg in a
    minute; heading innovations every 1.25 s (the scans' view, 0.15 deg noise) correct it and
    estimate the bias, so the heading stays within a degree and the bias within 1e-3 rad/s."""
    rng = np.random.default_rng(4)
    sweep_s, var = 1.25, math.radians(0.15) ** 2
    aided = InertialOdometry(OdometryConfig(m_per_tick=M_PER_TICK))
    unaided = InertialOdometry(OdometryConfig(m_per_tick=M_PER_TICK))
    dt, bias, yaw, t = 0.01, 0.01, 0.0, 0.0
    last_fix = 0.0
    errors = []
    for odo in (aided, unaided):
        odo.add_imu(ImuSample(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
    for k in range(6000):  # 60 s weaving at 0.8 m/s
        t = (k + 1) * dt
        w = 0.3 * math.sin(0.5 * t)
        yaw += w * dt
        sample = ImuSample(t, (0.0, 0.0, w + bias), (0.0, 0.0, GRAVITY_M_S2 + 0.3))
        for odo in (aided, unaided):
            odo.add_imu(sample)
        if t - last_fix >= sweep_s - 1e-9:
            innovation = float(wrap_angle(yaw - aided.pose_in_odom[2])) + rng.normal(0, 0.0026)
            aided.correct_heading(
                0.8 * innovation,
                innovation_rad=innovation,
                innovation_var_rad2=var,
                since_s=t - last_fix,
            )
            last_fix = t
            errors.append(abs(float(wrap_angle(aided.pose_in_odom[2] - yaw))))
    assert abs(float(wrap_angle(unaided.pose_in_odom[2] - yaw))) > math.radians(30.0)
    assert max(errors[10:]) < math.radians(1.0)
    assert aided.gyro_bias_rad_s[2] == pytest.approx(bias, abs=1e-3)
    assert aided.scan_bias_updates == len(errors) and aided.heading_corrections == len(errors)
    # the history turns with the heading: the pose a moment ago is the corrected one too
    assert abs(float(wrap_angle(aided.pose_at(t - 0.005)[2] - yaw))) < math.radians(1.0)
    # no innovation, or an interval outside the configured range: no bias measurement
    aided.correct_heading(0.0, innovation_rad=0.1, innovation_var_rad2=var, since_s=30.0)
    aided.correct_heading(0.01)
    assert aided.scan_bias_updates == len(errors)
    with pytest.raises(ValueError, match="dyaw_rad"):
        aided.correct_heading(math.nan)


def test_lidar_traction_governs_while_measured_and_its_error_comes_out_of_the_position() -> None:
    """Sand (the body turns 83 % and moves 75 % of what the wheels ask) measured by the LIDAR
    every 1.25 s (the true displacement, 3 cm off): the first measurement sets the distance
    scale and its error is taken out of the position; firm ground after it is not under-counted
    by the turn traction the sand left (the hold), and the measurements there change nothing."""
    cfg = OdometryConfig(
        m_per_tick=M_PER_TICK, effective_track_m=0.6, slip_per_skid=1.5, slip_std_per_skid=1.0,
        displacement_gain=1.0, displacement_gate_sigma=3.0, traction_hold_m=3.0,
    )  # fmt: skip
    results: dict[str, list[float]] = {}
    for name, use_lidar in (("wheels", False), ("lidar", True)):
        odo, maker = InertialOdometry(cfg), PoseNodeMaker()
        odo.add_imu(ImuSample(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
        odo.add_ticks(WheelTicks(0.0, 0, 0))
        t, pose, ticks = 0.0, (0.0, 0.0, 0.0), (0.0, 0.0)
        errors = []
        for k, (turn, dist) in enumerate([(0.83, 0.75)] * 8 + [(1.0, 1.0)] * 4):
            a_odo, a_true = odo.pose_in_odom, pose
            t, pose, ticks, _ = _skid_drive(
                odo, maker, seconds=1.25, turn_traction=turn, distance_traction=dist,
                t0=t, pose=pose, ticks=ticks,
            )  # fmt: skip
            b_odo = odo.pose_in_odom
            travel = math.hypot(b_odo[0] - a_odo[0], b_odo[1] - a_odo[1])
            made_good = math.hypot(pose[0] - a_true[0], pose[1] - a_true[1])
            made_good += 0.03 * (-1) ** k  # the match's noise
            if use_lidar:
                error = odo.observe_displacement(
                    odometry_m=travel,
                    measured_m=made_good,
                    sigma_m=0.04,
                    scale_used=odo.distance_scale_between(t - 1.25, t),
                )
                u = (b_odo[:2] - a_odo[:2]) / travel
                odo.shift_position(*(error * u))
                if k >= 9:  # firm ground measured: within the noise, nothing moves
                    assert error == 0.0
            errors.append(math.hypot(odo.pose_in_odom[0] - pose[0], odo.pose_in_odom[1] - pose[1]))
        results[name] = errors
    # the wheels alone: the turn traction the sand left under-counts the firm ground after it
    wheels, lidar = results["wheels"], results["lidar"]
    assert wheels[-1] > 0.25 and wheels[-1] > 2 * wheels[7]
    # with the LIDAR: the first sweep's slip (within the gate with its noise) stays, the
    # sand's scale is taken from the second, firm ground after it is measured as such
    assert max(lidar) < lidar[0] + 0.04
    assert lidar[-1] < 0.5 * wheels[-1]


def test_shift_position_moves_the_history_with_the_pose() -> None:
    odo = InertialOdometry(OdometryConfig(m_per_tick=M_PER_TICK))
    odo.add_imu(ImuSample(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
    odo.add_ticks(WheelTicks(0.0, 0, 0))
    for k in range(1, 11):
        odo.add_imu(ImuSample(0.1 * k, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
        odo.add_ticks(WheelTicks(0.1 * k, 100 * k, 100 * k))
    before = odo.pose_at(0.5)
    odo.shift_position(-0.2, 0.1)
    assert odo.pose_in_odom[:2] == pytest.approx([10 * 100 * M_PER_TICK - 0.2, 0.1])
    assert odo.pose_at(0.5)[:2] == pytest.approx(before[:2] + np.array([-0.2, 0.1]))
    with pytest.raises(ValueError, match="shift_position"):
        odo.shift_position(math.nan, 0.0)


def drive_over_slip(
    segments: list[tuple[float, float, float]],
    *,
    config: OdometryConfig,
    rate_hz: float = 20.0,
    accel_noise: float = 0.03,
    seed: int = 0,
    weave_rad_s: float = 0.0,
) -> tuple[InertialOdometry, float, list[OdometryIncrement]]:
    """Straight ``(duration_s, wheel_speed_m_s, slip)`` segments: the wheels turn at the
    speed (reaching it at 1 m/s^2), the body moves ``1 - slip`` of it (sand the encoders do
    not see); the accelerometer feels the body's changes of speed. ``weave_rad_s``: the
    wheels also weave left and right at up to this rate (period 4 s), the body turning
    ``1 - slip / 2`` of it, as the simulator's skid steer does. Returns the odometry, the
    true distance and the increments."""
    rng = np.random.default_rng(seed)
    odo = InertialOdometry(config)
    dt = 1.0 / rate_hz
    t = wheel_v = body_v = wheel = dist = turn = 0.0
    odo.add_imu(ImuSample(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, GRAVITY_M_S2)))
    odo.add_ticks(WheelTicks(0.0, 0, 0))
    incs = []
    for duration, v, slip in segments:
        for _ in range(int(round(duration * rate_hz))):
            t += dt
            wheel_v += float(np.clip(v - wheel_v, -dt, dt))
            new_body_v = wheel_v * (1.0 - slip)
            ax = (new_body_v - body_v) / dt + accel_noise * rng.standard_normal()
            body_v = new_body_v
            wheel += wheel_v * dt
            dist += body_v * dt
            az = GRAVITY_M_S2 + accel_noise * rng.standard_normal()
            w = weave_rad_s * math.sin(0.5 * math.pi * t) if wheel_v > 0 else 0.0
            turn += w * 0.25 * dt  # half the 0.5 m track
            gyro = (0.0, 0.0, w * (1.0 - 0.5 * slip))
            odo.add_imu(ImuSample(t, gyro, (ax, 0.0, az)))
            left, right = int((wheel - turn) / M_PER_TICK), int((wheel + turn) / M_PER_TICK)
            inc = odo.add_ticks(WheelTicks(t, left, right))
            if inc is not None:
                incs.append(inc)
    return odo, dist, incs


def test_accelerometer_sees_the_slip_the_wheels_cannot() -> None:
    """Sand (25 % slip) crossed at 0.8 m/s: the body slows when it enters and speeds up when
    it leaves while the wheels keep turning alike; the accelerometer measures both steps, the
    distance over the sand is scaled by the traction they give, and its variance grows."""
    sand = [(3.0, 0.0, 0.0), (6.0, 0.8, 0.0), (8.0, 0.8, 0.25), (6.0, 0.8, 0.0), (2.0, 0.0, 0.0)]
    on = OdometryConfig(m_per_tick=M_PER_TICK, accel_slip_step_m_s=ACCEL_SLIP_STEP_M_S)
    odo, dist, incs = drive_over_slip(sand, config=on)
    assert odo.accel_slip_steps == 2  # in, out
    assert abs(odo.distance_m - dist) < 0.1
    assert sum(i.distance_var_m2 for i in incs) > 0.3 * (0.3 * 0.25) ** 2 * 6.0
    off = OdometryConfig(m_per_tick=M_PER_TICK, accel_slip_step_m_s=0.0)
    odo_off, dist_off, incs_off = drive_over_slip(sand, config=off)
    assert odo_off.accel_slip_steps == 0
    assert odo_off.distance_m - dist_off > 1.2  # the slip, 0.25 of 6.4 m, uncorrected
    assert sum(i.distance_var_m2 for i in incs_off) == 0.0


def test_leaving_the_sand_ends_the_turn_traction_learnt_on_it() -> None:
    """Weaving over the sand, the body turns less than the wheels: the turn traction learns a
    loss. Leaving it (the accelerometer's step back), that loss is the sand's, not the firm
    ground's: the distance after the sand is not scaled by it."""
    cfg = OdometryConfig(
        m_per_tick=M_PER_TICK,
        effective_track_m=0.5,
        slip_per_skid=1.5,
        accel_slip_step_m_s=ACCEL_SLIP_STEP_M_S,
    )
    segs = [(3.0, 0.0, 0.0), (5.0, 0.8, 0.0), (8.0, 0.8, 0.25)]
    odo, dist, _ = drive_over_slip(segs, config=cfg, weave_rad_s=0.6)
    assert odo.skid_loss > 0.1  # learnt on the sand
    on_sand = odo.distance_m - dist
    odo, dist, _ = drive_over_slip(segs + [(8.0, 0.8, 0.0)], config=cfg, weave_rad_s=0.6)
    assert odo.accel_slip_steps == 2
    assert abs(odo.distance_m - dist - on_sand) < 0.1  # 6.3 m after the sand, as driven


def test_accelerometer_slip_is_forgotten_when_the_wheels_stop() -> None:
    """A stop in the sand ends what is known of the ground: the traction returns to 1."""
    on = OdometryConfig(m_per_tick=M_PER_TICK, accel_slip_step_m_s=ACCEL_SLIP_STEP_M_S)
    odo, _, _ = drive_over_slip([(3.0, 0.0, 0.0), (5.0, 0.8, 0.0), (4.0, 0.8, 0.25)], config=on)
    assert odo.inertial_traction == pytest.approx(0.75, abs=0.03)
    odo, _, _ = drive_over_slip(
        [(3.0, 0.0, 0.0), (5.0, 0.8, 0.0), (4.0, 0.8, 0.25), (2.0, 0.0, 0.25)], config=on
    )
    assert odo.inertial_traction == 1.0
    # and so is the turn traction learnt weaving over the sand: after a stop at its edge, the
    # firm ground beyond is driven at the calibrated scale
    skid = msgspec.structs.replace(on, effective_track_m=0.5, slip_per_skid=1.5)
    segs = [(3.0, 0.0, 0.0), (5.0, 0.8, 0.0), (8.0, 0.8, 0.25), (2.0, 0.0, 0.25)]
    odo, dist, _ = drive_over_slip(segs, config=skid, weave_rad_s=0.6)
    at_stop = odo.distance_m - dist
    odo, dist, _ = drive_over_slip(segs + [(8.0, 0.8, 0.0)], config=skid, weave_rad_s=0.6)
    assert abs(odo.distance_m - dist - at_stop) < 0.1


def test_accelerometer_slip_ignores_starts_stops_and_noise() -> None:
    """Firm ground with the wheels' own starts, stops and changes of speed (the body follows
    them) and an accelerometer three times as noisy as the simulated one: no slip step is
    seen, the distance stays right."""
    firm = []
    for k in range(12):
        firm += [(2.0, 0.0, 0.0), (5.0, 0.3 + 0.06 * k, 0.0), (3.0, 0.9 - 0.05 * k, 0.0)]
    odo, dist, _ = drive_over_slip(
        firm,
        config=OdometryConfig(m_per_tick=M_PER_TICK, accel_slip_step_m_s=ACCEL_SLIP_STEP_M_S),
        accel_noise=0.1,
        seed=4,
    )
    assert dist > 50.0
    assert odo.accel_slip_steps == 0
    assert abs(odo.distance_m - dist) < 0.005 * dist


def test_accelerometer_slip_ignores_wheel_count_jitter() -> None:
    """The wheels' counts jitter 5 % per 100 Hz reading (the zero-velocity drive's slip
    noise): one reading's speed change is noise; the means over the windows see no step."""
    stop_and_go = []
    for k in range(4):
        stop_and_go += [(5.0, 0.0, 0.0), (40.0, 0.5, 0.05 * (-1) ** k)]
    on = OdometryConfig(m_per_tick=M_PER_TICK, accel_slip_step_m_s=ACCEL_SLIP_STEP_M_S)
    odo, _, _ = drive(stop_and_go, odo=InertialOdometry(on), slip_std=0.05, seed=3)
    assert odo.accel_slip_steps == 0
