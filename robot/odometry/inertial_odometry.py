"""Inertially-aided odometry in the robot's private frame ``odom`` (paper 4.3.1).

Skid-steer wheels give serviceable forward translation but poor yaw (they slip when turning),
so:

* **translation** comes from the wheel encoders (mean of left and right), projected onto the
  horizontal plane with the current pitch, and scaled by a calibrated slip model: skid-steer
  wheels turn a little faster than the body moves over ground, more so while turning, so
  ``distance = wheel travel * (1 - wheel_slip_frac - wheel_slip_per_rad_s * |yaw rate|)``
  (the yaw rate from the gyro). Uncorrected, this bias is a systematic scale error (about 3%
  on the simulated robot) that cancels on out-and-back drives but not on the way out;
  calibrated the UMBmark way, by driving known straight and curved runs on hard ground
  (0 by default; ``robot.node.RobotNodeConfig`` carries the simulated MAGIC robot's
  calibration). Sand slips more: that is what loop closing at the GCS corrects (paper 4.1)
  and what the traversability map learns;
* **yaw** comes from the gyro, rotated from the body into the level frame with the current roll
  and pitch, minus an estimated zero-rate bias;
* **automatic zero-velocity recalibration**: the odometry itself notices stillness (gyro and
  accelerometer quiet over a window and no encoder motion; no command path from the planner is
  needed, so a robot that is bumped or sliding is not mistaken for still). The bias is a
  random-walk state per gyro axis (``gyro_bias_walk``) estimated by a scalar Kalman filter:
  every sample taken while still is a measurement of it with the gyro's white noise
  (``gyro_noise_density``), so a long stop averages optimally and an old estimate fades at
  the rate the bias really wanders;
* **roll and pitch** from the gravity vector: a complementary filter integrates the gyro and
  blends towards the accelerometer's gravity direction while the robot is not accelerating.

There are no loop closures: the trajectory in ``odom`` is never revised and stays smooth
(paper 4.1). Samples must arrive in time order per sensor; the two sensors may interleave.
:meth:`InertialOdometry.pose_at` interpolates recent poses, e.g. to de-skew LIDAR points.
"""

from __future__ import annotations

import math
from bisect import bisect_left
from collections import deque
from dataclasses import dataclass

import msgspec
import numpy as np

from protocol.se2 import wrap_angle
from protocol.sensors import ImuSample, WheelTicks

__all__ = ["InertialOdometry", "OdometryConfig", "OdometryIncrement"]

GRAVITY_M_S2 = 9.80665


class OdometryConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Tunables of :class:`InertialOdometry` (times in seconds of mission time)."""

    m_per_tick: float = 0.0007  # paper 4.3.1: about 0.7 mm per encoder tick
    # calibrated slip on hard ground: the fraction of wheel travel lost, and its growth per
    # rad/s of yaw rate (the gyro's) while turning
    wheel_slip_frac: float = 0.0
    wheel_slip_per_rad_s: float = 0.0
    still_window_s: float = 1.0
    still_gyro_std_rad_s: float = 0.02
    still_accel_std_m_s2: float = 0.1
    still_max_rate_rad_s: float = 0.1  # |gyro - bias| mean above this is motion, not bias
    gyro_noise_density_rad_s_sqrt_hz: float = 3e-4  # white noise of the gyro rate
    gyro_bias_walk_rad_s_sqrt_s: float = 2e-5  # how fast the zero-rate offset wanders
    gyro_bias_initial_std_rad_s: float = 0.05
    gravity_time_constant_s: float = 1.0  # attitude pull towards the gravity direction
    gravity_tolerance_m_s2: float = 0.5  # |accel| must be this close to g to trust it
    history_s: float = 20.0  # poses kept for pose_at

    def __post_init__(self) -> None:
        for name in (
            "m_per_tick",
            "still_window_s",
            "history_s",
            "gyro_noise_density_rad_s_sqrt_hz",
            "gyro_bias_initial_std_rad_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        for name in ("wheel_slip_frac", "wheel_slip_per_rad_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0 <= v < 0.5):
                raise ValueError(f"{name} must be in [0, 0.5), got {v}")


@dataclass(frozen=True, slots=True)
class OdometryIncrement:
    """Motion between two encoder readings: horizontal distance along the heading (m), the
    yaw change (rad) and the elapsed time (s). Feeds the pose-node covariance model."""

    distance_m: float
    dyaw_rad: float
    dt_s: float


class InertialOdometry:
    """Dead reckoning from wheel ticks and an IMU, in ``odom`` (see the module docstring)."""

    def __init__(self, config: OdometryConfig | None = None) -> None:
        self.config = config or OdometryConfig()
        self._x = 0.0
        self._y = 0.0
        self._yaw = 0.0
        self._roll = 0.0
        self._pitch = 0.0
        self._attitude_init = False
        self._bias = np.zeros(3)
        self._bias_var = np.full(3, self.config.gyro_bias_initial_std_rad_s**2)
        self._last_imu_t: float | None = None
        self._last_ticks: WheelTicks | None = None
        self._last_tick_motion_t = -math.inf
        self._window: deque[tuple[float, np.ndarray]] = deque()
        self._yaw_hist: deque[tuple[float, float]] = deque()
        self._pose_hist: deque[tuple[float, float, float]] = deque()  # t, x, y
        self.distance_m = 0.0
        self.is_still = False
        self.still_time_s = 0.0

    # ------------------------------------------------------------------ state

    @property
    def pose_in_odom(self) -> np.ndarray:
        """Current ``odom_from_base`` as ``(x_m, y_m, yaw_rad)``."""
        return np.array([self._x, self._y, float(wrap_angle(self._yaw))])

    @property
    def roll_pitch_rad(self) -> tuple[float, float]:
        return self._roll, self._pitch

    @property
    def gyro_bias_rad_s(self) -> np.ndarray:
        """Current estimate of the gyro zero-rate offset, body axes."""
        return self._bias.copy()

    # ------------------------------------------------------------------ IMU

    def add_imu(self, sample: ImuSample) -> None:
        """Integrate one IMU sample: attitude, yaw, stillness and bias."""
        t = sample.time_s
        gyro = np.asarray(sample.angular_velocity_rad_s, dtype=np.float64)
        accel = np.asarray(sample.linear_acceleration_m_s2, dtype=np.float64)
        if not (np.all(np.isfinite(gyro)) and np.all(np.isfinite(accel)) and math.isfinite(t)):
            raise ValueError(f"IMU sample at t={t}: non-finite values")
        if self._last_imu_t is not None and t <= self._last_imu_t:
            raise ValueError(
                f"IMU sample at t={t} is not after the previous one ({self._last_imu_t})"
            )
        cfg = self.config
        self._update_attitude(t, gyro, accel)
        omega = gyro - self._bias
        cr, cp = math.cos(self._roll), max(math.cos(self._pitch), 0.2)
        rate = (math.sin(self._roll) * omega[1] + cr * omega[2]) / cp
        if self._last_imu_t is not None:
            # a sample reports the rate over the interval it ends (as a rate gyro averaging
            # between reads does); trapezoids would smear every change of rate
            self._yaw += rate * (t - self._last_imu_t)
        self._yaw_hist.append((t, self._yaw))
        # stillness window and zero-velocity recalibration
        dt = 0.0 if self._last_imu_t is None else t - self._last_imu_t
        self._last_imu_t = t
        self._window.append((t, np.concatenate([gyro, accel])))
        while self._window and self._window[0][0] < t - cfg.still_window_s:
            self._window.popleft()
        self._update_still(gyro, dt)
        self._trim(t)

    def _update_attitude(self, t: float, gyro: np.ndarray, accel: np.ndarray) -> None:
        cfg = self.config
        roll_g = math.atan2(accel[1], accel[2])
        pitch_g = math.atan2(-accel[0], math.hypot(accel[1], accel[2]))
        if not self._attitude_init:
            self._roll, self._pitch = roll_g, pitch_g
            self._attitude_init = True
            return
        dt = t - (self._last_imu_t if self._last_imu_t is not None else t)
        omega = gyro - self._bias
        self._roll += omega[0] * dt
        self._pitch += omega[1] * dt
        if abs(float(np.linalg.norm(accel)) - GRAVITY_M_S2) < cfg.gravity_tolerance_m_s2:
            k = min(1.0, dt / cfg.gravity_time_constant_s)
            self._roll += k * float(wrap_angle(roll_g - self._roll))
            self._pitch += k * (pitch_g - self._pitch)

    def _update_still(self, gyro: np.ndarray, dt: float) -> None:
        cfg = self.config
        self._bias_var += cfg.gyro_bias_walk_rad_s_sqrt_s**2 * dt
        w = self._window
        span = w[-1][0] - w[0][0] if w else 0.0
        if len(w) < 5 or span < 0.8 * cfg.still_window_s or dt <= 0:
            self.is_still = False
            return
        data = np.stack([v for _, v in w])
        std = data.std(axis=0)
        mean_gyro = data[:, :3].mean(axis=0)
        still = (
            bool(np.all(std[:3] < cfg.still_gyro_std_rad_s))
            and bool(np.all(std[3:] < cfg.still_accel_std_m_s2))
            and float(np.max(np.abs(mean_gyro - self._bias))) < cfg.still_max_rate_rad_s
            and self._last_tick_motion_t < w[0][0]
        )
        if still:  # this sample measures the bias: Kalman update per axis
            meas_var = cfg.gyro_noise_density_rad_s_sqrt_hz**2 / dt
            gain = self._bias_var / (self._bias_var + meas_var)
            self._bias += gain * (gyro - self._bias)
            self._bias_var *= 1.0 - gain
            self.still_time_s += dt
        self.is_still = still

    # ------------------------------------------------------------------ encoders

    def add_ticks(self, ticks: WheelTicks) -> OdometryIncrement | None:
        """Integrate one encoder reading; returns the motion since the previous reading."""
        t = ticks.time_s
        if not math.isfinite(t):
            raise ValueError("wheel ticks: non-finite time")
        prev = self._last_ticks
        self._last_ticks = ticks
        if prev is None:
            self._pose_hist.append((t, self._x, self._y))
            return None
        if t <= prev.time_s:
            raise ValueError(
                f"wheel ticks at t={t} are not after the previous ones ({prev.time_s})"
            )
        dl = ticks.left_ticks - prev.left_ticks
        dr = ticks.right_ticks - prev.right_ticks
        if dl or dr:
            self._last_tick_motion_t = t
        cfg = self.config
        yaw0 = self._yaw_at(prev.time_s)
        yaw1 = self._yaw_at(t)
        rate = abs(yaw1 - yaw0) / (t - prev.time_s)
        scale = max(0.5, 1.0 - cfg.wheel_slip_frac - cfg.wheel_slip_per_rad_s * rate)
        ds = 0.5 * (dl + dr) * cfg.m_per_tick * math.cos(self._pitch) * scale
        mid = 0.5 * (yaw0 + yaw1)
        self._x += ds * math.cos(mid)
        self._y += ds * math.sin(mid)
        self.distance_m += abs(ds)
        self._pose_hist.append((t, self._x, self._y))
        return OdometryIncrement(ds, yaw1 - yaw0, t - prev.time_s)

    def _yaw_at(self, t: float) -> float:
        hist = self._yaw_hist
        if not hist:
            return self._yaw
        if t >= hist[-1][0]:
            return hist[-1][1]
        if t <= hist[0][0]:
            return hist[0][1]
        i = bisect_left(hist, t, key=lambda h: h[0])
        (t0, y0), (t1, y1) = hist[i - 1], hist[i]
        return y0 + (y1 - y0) * (t - t0) / (t1 - t0)

    def pose_at(self, t: float) -> np.ndarray:
        """``odom_from_base`` at time ``t``, interpolated within the kept history (clamped)."""
        hist = self._pose_hist
        if not hist:
            return self.pose_in_odom
        if t >= hist[-1][0]:
            x, y = hist[-1][1], hist[-1][2]
        elif t <= hist[0][0]:
            x, y = hist[0][1], hist[0][2]
        else:
            i = bisect_left(hist, t, key=lambda h: h[0])
            (t0, x0, y0), (t1, x1, y1) = hist[i - 1], hist[i]
            a = (t - t0) / (t1 - t0)
            x, y = x0 + a * (x1 - x0), y0 + a * (y1 - y0)
        return np.array([x, y, float(wrap_angle(self._yaw_at(t)))])

    def _trim(self, t: float) -> None:
        horizon = t - self.config.history_s
        while len(self._yaw_hist) > 2 and self._yaw_hist[1][0] < horizon:
            self._yaw_hist.popleft()
        while len(self._pose_hist) > 2 and self._pose_hist[1][0] < horizon:
            self._pose_hist.popleft()
