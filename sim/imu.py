"""Proprioceptive sensors: the 6-DOF IMU and the wheel encoders (paper 3.1, 4.3.1).

Gyro: true body rates plus white noise and a bias that performs a random walk (MEMS zero-rate
output, paper 4.3.1: the reason for automatic zero-velocity recalibration). Accelerometer:
specific force in ``base`` (gravity included: +9.81 m/s^2 on z when level) plus white noise and
a constant bias. Encoders: cumulative ticks of the left and right wheel sides at ``0.7 mm`` per
tick; they count what the wheels did, not what the body did (slip is invisible to them).
All robots at once over ``(N,)`` arrays; seeded.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

__all__ = ["EncoderConfig", "ImuConfig", "Imus", "wheel_ticks"]

GRAVITY_M_S2 = 9.81


class ImuConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Noise per sample (``*_noise``: standard deviations) and the gyro bias random walk
    (``gyro_bias_walk_rad_s_per_sqrt_s``: standard deviation growth per sqrt(second))."""

    gyro_noise_rad_s: float = 0.003
    gyro_bias_initial_rad_s: float = 0.005
    gyro_bias_walk_rad_s_per_sqrt_s: float = 0.0002
    accel_noise_m_s2: float = 0.03
    accel_bias_m_s2: float = 0.02

    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")


class EncoderConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    metres_per_tick: float = 0.0007

    def __post_init__(self) -> None:
        if not (math.isfinite(self.metres_per_tick) and self.metres_per_tick > 0):
            raise ValueError(f"metres_per_tick must be > 0, got {self.metres_per_tick}")


def wheel_ticks(left_m: np.ndarray, right_m: np.ndarray, config: EncoderConfig) -> np.ndarray:
    """Cumulative ticks ``(N, 2)`` (int64) of the left and right sides."""
    return np.floor(np.stack([left_m, right_m], axis=1) / config.metres_per_tick).astype(np.int64)


class Imus:
    """The IMUs of ``count`` robots."""

    def __init__(self, count: int, *, config: ImuConfig, seed: int = 0) -> None:
        self.config = config
        self._rng = np.random.default_rng(seed)
        self.gyro_bias = self._rng.normal(0.0, config.gyro_bias_initial_rad_s, size=(count, 3))
        self.accel_bias = self._rng.normal(0.0, config.accel_bias_m_s2, size=(count, 3))
        self._prev: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def sample(
        self,
        dt_s: float,
        *,
        linear_m_s: np.ndarray,
        angular_rad_s: np.ndarray,
        roll_rad: np.ndarray,
        pitch_rad: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Gyro ``(N, 3)`` rad/s and accelerometer ``(N, 3)`` m/s^2 after a step of ``dt_s``
        that ended with the body at these velocities and attitude."""
        cfg = self.config
        n = len(linear_m_s)
        if self._prev is None:
            self._prev = (linear_m_s.copy(), roll_rad.copy(), pitch_rad.copy())
        v0, r0, p0 = self._prev
        dt = max(dt_s, 1e-9)
        rates = np.stack([(roll_rad - r0) / dt, (pitch_rad - p0) / dt, angular_rad_s], axis=1)
        self.gyro_bias += self._rng.normal(
            0.0, cfg.gyro_bias_walk_rad_s_per_sqrt_s * math.sqrt(dt), size=(n, 3)
        )
        gyro = rates + self.gyro_bias + self._rng.normal(0.0, cfg.gyro_noise_rad_s, size=(n, 3))
        # acceleration in the yaw-aligned level frame, then into base: f = R_lb^T (a + g)
        a = np.stack(
            [(linear_m_s - v0) / dt, linear_m_s * angular_rad_s, np.full(n, GRAVITY_M_S2)], axis=1
        )
        cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
        cr, sr = np.cos(roll_rad), np.sin(roll_rad)
        # R_lb = Ry(pitch) Rx(roll); rows of its transpose applied to a
        fx = cp * a[:, 0] - sp * a[:, 2]
        fy = sp * sr * a[:, 0] + cr * a[:, 1] + cp * sr * a[:, 2]
        fz = sp * cr * a[:, 0] - sr * a[:, 1] + cp * cr * a[:, 2]
        accel = np.stack([fx, fy, fz], axis=1) + self.accel_bias
        accel += self._rng.normal(0.0, cfg.accel_noise_m_s2, size=(n, 3))
        self._prev = (linear_m_s.copy(), roll_rad.copy(), pitch_rad.copy())
        return gyro, accel
