"""Evaluation of on-robot autonomy against the simulator's ground truth (issue 4).

Ground truth reaches only ``mission/`` (DESIGN section 2). Two trials, shared by the
``robot`` benchmark and the tests:

* :func:`odometry_drive`: a robot in an open world drives a scripted zigzag (legs, stops, half
  turns in place: a UMBmark-like pattern whose stops give the gyro its zero-velocity
  recalibrations, paper 4.3.1); its inertially-aided odometry is compared with the truth.
  The odometry is configured from the simulated sensors' specification, as it would be from
  a datasheet.
* :func:`node_pipeline`: the whole robot node in lockstep with the simulator in the small
  world; CPU time of the node between consecutive sweeps and the uplink it produces.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import msgspec
import numpy as np

from protocol.messages import Direction, GoToTask
from protocol.meter import Meter
from protocol.radio_channel import RadioChannel
from protocol.se2 import relative, wrap_angle
from protocol.sensors import ImuSample, LidarSweep, VelocityCommand, WheelTicks
from robot.node import RobotNode, RobotNodeConfig
from robot.odometry.inertial_odometry import InertialOdometry, OdometryConfig
from sim.imu import ImuConfig
from sim.simulator import Simulator, SimulatorConfig
from sim.world_generator import BuildingsConfig, HumansConfig, ObjectsConfig, WorldConfig

__all__ = ["NodeTrial", "OdometryTrial", "node_pipeline", "odometry_drive", "open_world"]


def open_world(*, size_m: float = 140.0, seed: int = 5, robots: int = 1) -> WorldConfig:
    """A flat, empty world: nothing to hit, only ground and the robots."""
    base = WorldConfig()
    none = {"count": 0}
    return WorldConfig(
        seed=seed,
        size_m=(size_m, size_m),
        robots=msgspec.structs.replace(base.robots, sensors=robots, disruptors=0),
        buildings=BuildingsConfig(count=0),
        fences=msgspec.structs.replace(base.fences, **none),
        curbs=msgspec.structs.replace(base.curbs, **none),
        ramps=msgspec.structs.replace(base.ramps, **none),
        sand=msgspec.structs.replace(base.sand, **none),
        trees=msgspec.structs.replace(base.trees, **none),
        cars=msgspec.structs.replace(base.cars, **none),
        static_oois=ObjectsConfig(count=0),
        toxic_vats=ObjectsConfig(count=0),
        civilians=HumansConfig(count=0),
        hostiles=HumansConfig(count=0),
    )


def odometry_config_for(sim_config: SimulatorConfig) -> OdometryConfig:
    """Odometry tuned to the simulated sensors' specification (its "datasheet") and the
    body's nominal wheel slip on hard ground (what a calibration drive measures; the body
    slips ``slip_linear_per_rad_s`` per rad/s of *wheel* turn rate, the gyro sees the body's,
    ``1 - slip_turn`` of it)."""
    imu: ImuConfig = sim_config.imu
    body = sim_config.body
    return OdometryConfig(
        m_per_tick=sim_config.encoders.metres_per_tick,
        wheel_slip_frac=body.slip_linear,
        wheel_slip_per_rad_s=body.slip_linear_per_rad_s / (1.0 - body.slip_turn),
        gyro_noise_density_rad_s_sqrt_hz=max(
            imu.gyro_noise_rad_s * math.sqrt(sim_config.step_s), 1e-6
        ),
        gyro_bias_walk_rad_s_sqrt_s=max(imu.gyro_bias_walk_rad_s_per_sqrt_s, 1e-7),
    )


@dataclass(frozen=True)
class OdometryTrial:
    distance_m: float
    duration_s: float
    position_error_m: float
    heading_error_rad: float
    bias_error_rad_s: float  # after the first stop
    odometry_distance_m: float = math.nan  # what the odometry says it drove

    @property
    def distance_scale_error(self) -> float:
        """Relative error of the odometry's distance (wheel slip calibration, 4.3.1)."""
        return self.odometry_distance_m / max(self.distance_m, 1e-9) - 1.0

    @property
    def drift_frac(self) -> float:
        return self.position_error_m / max(self.distance_m, 1e-9)

    @property
    def heading_drift_deg_per_min(self) -> float:
        return math.degrees(abs(self.heading_error_rad)) / (self.duration_s / 60.0)


def odometry_drive(
    *,
    legs: int = 8,
    leg_s: float = 31.0,
    speed_m_s: float = 0.8,
    stop_s: float = 8.0,
    sim_config: SimulatorConfig | None = None,
    seed: int = 5,
    out_and_back: bool = True,
    slip_calibrated: bool = True,
) -> OdometryTrial:
    """Drive ``legs`` legs of ``leg_s`` at ``speed_m_s`` (gentle alternating curves), stopping
    ``stop_s`` and turning in place after each; about 200 m with the defaults.

    ``out_and_back``: half turns, so the legs go back and forth (a scale error of the wheel
    odometry largely cancels: this measures the heading's contribution); otherwise quarter
    turns alternately left and right, a serpentine that keeps going away from the start, so the
    final error shows the distance scale error: headings east, north, east, south, east, ...
    (half the distance ends up as displacement from the start). ``slip_calibrated=False``
    turns the odometry's wheel slip model off (to show what it corrects)."""
    base = sim_config or SimulatorConfig()
    lidar_off = msgspec.structs.replace(base.lidar, enabled=False)  # odometry needs no LIDAR
    cfg = msgspec.structs.replace(base, lidar=lidar_off, seed=seed)
    plan: list[tuple[float, float, float]] = [(5.0, 0.0, 0.0)]
    for k in range(legs):
        turn_rate = 0.6
        if out_and_back:
            turn = (math.pi / turn_rate, 0.0, turn_rate)
        else:
            sign = 1.0 if k % 4 in (0, 3) else -1.0
            turn = (0.5 * math.pi / turn_rate, 0.0, turn_rate * sign)
        plan += [
            (leg_s, speed_m_s, 0.02 * (-1) ** k),
            (stop_s, 0.0, 0.0),
            turn,
            (3.0, 0.0, 0.0),
        ]
    with Simulator(open_world(seed=seed), config=cfg) as sim:
        rid = sim.robot_ids[0]
        driver = sim.driver(rid)
        odo_cfg = odometry_config_for(cfg)
        if not slip_calibrated:
            odo_cfg = msgspec.structs.replace(
                odo_cfg, wheel_slip_frac=0.0, wheel_slip_per_rad_s=0.0
            )
        odo = InertialOdometry(odo_cfg)
        start = sim.robot_poses()[0].copy()
        prev = start[:2].copy()
        distance = 0.0
        bias_error = math.nan
        for i, (duration, v, w) in enumerate(plan):
            for _ in range(int(round(duration / cfg.step_s))):
                driver.send(VelocityCommand(sim.time_s, v, w))
                sim.step()
                for frame in driver.poll(0.0):
                    if isinstance(frame, ImuSample):
                        odo.add_imu(frame)
                    elif isinstance(frame, WheelTicks):
                        odo.add_ticks(frame)
                pos = sim.robot_poses()[0][:2]
                distance += float(np.hypot(*(pos - prev)))
                prev = pos.copy()
            if i == 2:  # after the first stop
                bias_error = float(odo.gyro_bias_rad_s[2] - sim.imus.gyro_bias[0, 2])
        truth = relative(start, sim.robot_poses()[0])
        est = odo.pose_in_odom
        return OdometryTrial(
            distance_m=distance,
            duration_s=sim.time_s,
            position_error_m=float(np.hypot(*(est[:2] - truth[:2]))),
            heading_error_rad=float(wrap_angle(est[2] - truth[2])),
            bias_error_rad_s=bias_error,
            odometry_distance_m=odo.distance_m,
        )


@dataclass(frozen=True)
class NodeTrial:
    cpu_ms_per_sweep: list[float]  # node CPU between consecutive sweeps (whole pipeline)
    uplink_bytes: int
    duration_s: float

    @property
    def uplink_bps(self) -> float:
        return self.uplink_bytes * 8.0 / self.duration_s


def node_pipeline(
    *,
    duration_s: float = 40.0,
    goal_odom: tuple[float, float] = (12.0, 2.0),
    config: RobotNodeConfig | None = None,
) -> NodeTrial:
    """Robot 0 of the small world drives to a goal; times its node per sweep (thread CPU)."""
    from mission.config import CONFIGS_DIR
    from sim.simulator import load_world_config

    with Simulator(load_world_config(CONFIGS_DIR / "world" / "small.yaml")) as sim:
        rid = sim.robot_ids[0]
        driver = sim.driver(rid)
        meter = Meter()
        uplink = RadioChannel(rid, Direction.UP, meter=meter)  # unlimited rate, metered
        node = RobotNode(rid, send=uplink.send, config=config)
        node.handle_downlink(GoToTask(1, 0.0, [goal_odom]))
        per_sweep: list[float] = []
        acc = 0.0
        for _ in range(int(round(duration_s / sim.config.step_s))):
            sim.step()
            frames = driver.poll(0.0)
            t0 = time.thread_time()
            for command in node.process(frames):
                driver.send(command)
            acc += time.thread_time() - t0
            uplink.poll(sim.time_s)
            if any(isinstance(f, LidarSweep) for f in frames):
                per_sweep.append(acc * 1000.0)
                acc = 0.0
        return NodeTrial(per_sweep[1:], meter.total_bytes(direction=Direction.UP), sim.time_s)
