"""Issue 4's odometry checks against the simulator's truth (default sensor noise)."""

from __future__ import annotations

import math
import statistics

import msgspec
import numpy as np
import pytest

from mission.evaluation import odometry_config_for, odometry_drive, open_world
from protocol.sensors import ImuSample, VelocityCommand, WheelTicks
from robot.node import RobotNodeConfig
from robot.odometry.inertial_odometry import InertialOdometry, OdometryConfig
from robot.odometry.pose_node_maker import PoseNodeConfig, PoseNodeMaker
from sim.simulator import Simulator, SimulatorConfig

pytestmark = pytest.mark.slow


def test_scripted_200m_drive_drift() -> None:
    trials = [odometry_drive(seed=seed) for seed in (5, 6, 7)]  # not one lucky draw
    for trial in trials:
        assert trial.distance_m > 190.0
        assert trial.drift_frac <= 0.02
    assert statistics.median(t.heading_drift_deg_per_min for t in trials) <= 1.0


def test_gyro_bias_converges_while_still() -> None:
    trial = odometry_drive(legs=1, leg_s=5.0, sim_config=SimulatorConfig())
    # 5 s still at the start, then 8 s after the first leg: the bias is learned to a few
    # hundredths of a degree per second
    assert abs(trial.bias_error_rad_s) < math.radians(0.05)


def test_wheel_slip_calibration_one_way() -> None:
    # skid-steer wheels over-count the distance by their slip (about 3% here); the calibrated
    # slip model removes that scale error, which an out-and-back drive would hide
    trial = odometry_drive(seed=6, legs=4, out_and_back=False)
    assert trial.distance_m > 90.0
    assert abs(trial.distance_scale_error) <= 0.003
    uncalibrated = odometry_drive(seed=6, legs=4, out_and_back=False, slip_calibrated=False)
    assert uncalibrated.distance_scale_error > 0.015


def test_robot_node_defaults_carry_the_simulated_robots_calibration() -> None:
    node_odometry = RobotNodeConfig().odometry
    datasheet = odometry_config_for(SimulatorConfig())
    assert node_odometry.m_per_tick == datasheet.m_per_tick
    assert node_odometry.wheel_slip_frac == pytest.approx(datasheet.wheel_slip_frac)
    assert node_odometry.wheel_slip_per_rad_s == pytest.approx(
        datasheet.wheel_slip_per_rad_s, abs=1e-3
    )
    assert node_odometry.gyro_noise_density_rad_s_sqrt_hz == pytest.approx(
        datasheet.gyro_noise_density_rad_s_sqrt_hz, rel=1e-2
    )
    assert node_odometry.gyro_bias_walk_rad_s_sqrt_s == datasheet.gyro_bias_walk_rad_s_sqrt_s


def _sand_crossing(
    odometry: OdometryConfig, *, seed: int = 5, weave_rad_s: float = 0.0
) -> tuple[float, float, float]:
    """Drive at 1 m/s (weaving by up to ``weave_rad_s``, 5 s a period) across an 8 m strip
    of 25 % wheel slip in the open world, making pose nodes as robot.node does (one a
    metre). Returns the odometry's distance error over the crossing (m), the pose nodes'
    distance error summed over it and their summed distance variance along the motion."""
    base = SimulatorConfig()
    cfg = msgspec.structs.replace(
        base, lidar=msgspec.structs.replace(base.lidar, enabled=False), seed=seed
    )
    odo = InertialOdometry(odometry)
    maker = PoseNodeMaker(PoseNodeConfig())
    nodes: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # odom pose, truth, cov
    with Simulator(open_world(seed=seed), config=cfg) as sim:
        drv = sim.driver(sim.robot_ids[0])
        p0 = sim.robot_poses()[0].copy()
        c, s = math.cos(p0[2]), math.sin(p0[2])
        res = sim.truth.resolution_m
        ys, xs = np.mgrid[0 : sim.truth.slip.shape[0], 0 : sim.truth.slip.shape[1]]
        along = (xs * res + res / 2 - p0[0]) * c + (ys * res + res / 2 - p0[1]) * s
        sim.truth.slip[(along > 8.0) & (along < 16.0)] = 0.25
        for k in range(int(26.0 / cfg.step_s)):
            t = k * cfg.step_s
            v, w = (0.0, 0.0) if t < 4.0 else (1.0, weave_rad_s * math.sin(2.0 * math.pi * t / 5.0))
            drv.send(VelocityCommand(sim.time_s, v, w))
            sim.step()
            for frame in drv.poll(0.0):
                if isinstance(frame, ImuSample):
                    odo.add_imu(frame)
                elif isinstance(frame, WheelTicks):
                    inc = odo.add_ticks(frame)
                    if inc is not None:
                        maker.add_increment(inc)
            pose = odo.pose_in_odom
            if maker.due(pose, sim.time_s):
                node = maker.make(pose, sim.time_s)
                cov = np.zeros((3, 3))
                cov[np.triu_indices(3)] = node.odom_covariance
                nodes.append((pose, sim.robot_poses()[0].copy(), cov))
    # the nodes from the one before the strip to the first beyond it
    a_on = [(p[0] - p0[0]) * c + (p[1] - p0[1]) * s for _, p, _ in nodes]
    i0 = max(i for i, a in enumerate(a_on) if a < 7.5)
    i1 = min(i for i, a in enumerate(a_on) if a > 16.5)
    err = var = 0.0
    for (pa, ta, _), (pb, tb, cov) in zip(nodes[i0:i1], nodes[i0 + 1 : i1 + 1], strict=True):
        d = math.hypot(*(pb[:2] - pa[:2]))
        err += d - math.hypot(*(tb[:2] - ta[:2]))
        u = (pb[:2] - pa[:2]) / max(d, 1e-9)
        cov = cov + np.triu(cov, 1).T
        var += float(u @ cov[:2, :2] @ u)
    odometry_err = math.hypot(*(nodes[i1][0][:2] - nodes[i0][0][:2])) - math.hypot(
        *(nodes[i1][1][:2] - nodes[i0][1][:2])
    )
    return odometry_err, err, var


def test_accelerometer_slip_over_sand_corrects_the_distance_and_says_how_sure() -> None:
    # the node's odometry with the accelerometer's slip turned on as measured (OdometryConfig,
    # accel_slip_step_m_s; robot.node keeps it off): a straight crossing, where the turn
    # traction sees nothing
    node = RobotNodeConfig().odometry
    off_err, _, off_var = _sand_crossing(msgspec.structs.replace(node, accel_slip_step_m_s=0.0))
    assert off_err > 2.0  # 25 % of the wheels' 10.7 m over the strip
    assert off_err > 10.0 * math.sqrt(off_var)  # and the nodes claim to be sure of it
    on = msgspec.structs.replace(node, accel_slip_step_m_s=0.1)
    odometry_err, err, var = _sand_crossing(on)
    assert err == pytest.approx(odometry_err, abs=0.01)  # the nodes chain the odometry
    assert abs(odometry_err) < 0.1 * off_err
    assert abs(err) < math.sqrt(var) < 0.6  # honest, and not so loose the GCS cannot use it
