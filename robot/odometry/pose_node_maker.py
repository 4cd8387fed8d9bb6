"""Pose nodes: samples of the robot's trajectory with their odometry constraints (paper 4.2).

A robot reports a new node when it moved or turned enough since the last one (MAGIC: about one
every 1.25 s sweep while moving). Each node carries the odometry constraint from the previous
node, ``previous_from_current``, with a covariance grown from the motion itself: every encoder
increment ``(ds, dyaw)`` is composed onto the running delta and its covariance propagated with
the Jacobians of that composition,

    Σ ← F Σ Fᵀ + G Q Gᵀ,   Q = diag(σ_ds², σ_dyaw²),
    σ_ds² = slip²·|ds| + σ_detected²,   σ_dyaw² = turn²·|dyaw| + gyro_noise²·dt,

with variances per metre driven, per radian turned and per second elapsed, so the result does
not depend on how often the encoders are read. Long, twisting segments are less certain than
short straight ones; a robot standing still accumulates only the gyro's random walk.
``σ_detected²`` is the increment's own ``distance_var_m2``: slip the odometry detected (turn
skid against the gyro, or the LIDAR's measured displacement against the wheels';
:mod:`robot.odometry.inertial_odometry`), so a node across sand or mud tells the GCS its
distance is uncertain and the scan matches and loop closures there win (a slip of 0.3 m in
a 1.2 m step at the nominal 0.03 m was a chi2 of 100 against them). Poses are SE(2) in
``odom``.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

from protocol.messages import PoseNode
from protocol.se2 import relative, wrap_angle
from robot.odometry.inertial_odometry import OdometryIncrement

__all__ = ["PoseNodeConfig", "PoseNodeMaker"]

_TRIU = (0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)


class PoseNodeConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """When to start a node and how uncertain odometry is."""

    min_distance_m: float = 1.0
    min_turn_rad: float = 0.26  # about 15°
    max_interval_s: float = 30.0  # a node at least this often, even when still
    slip_std_m_per_sqrt_m: float = 0.03  # distance error std after 1 m driven
    turn_std_rad_per_sqrt_rad: float = 0.02  # yaw error std after turning 1 rad
    gyro_noise_rad_per_sqrt_s: float = 0.002  # yaw random walk from the gyro
    min_std_m: float = 0.005  # floor keeping covariances positive definite
    min_std_rad: float = 0.001


class PoseNodeMaker:
    """Turns the odometry stream into :class:`~protocol.messages.PoseNode` messages."""

    def __init__(self, config: PoseNodeConfig | None = None) -> None:
        self.config = config or PoseNodeConfig()
        self._next_index = 0
        self._last_pose: np.ndarray | None = None
        self._last_time_s = -math.inf
        self._delta = np.zeros(3)
        self._cov = np.zeros((3, 3))
        self._distance_since_m = 0.0

    @property
    def nodes_made(self) -> int:
        return self._next_index

    def add_increment(self, inc: OdometryIncrement) -> None:
        """Compose one odometry increment onto the delta since the last node."""
        cfg = self.config
        ds, dyaw = inc.distance_m, inc.dyaw_rad
        th = self._delta[2] + 0.5 * dyaw
        c, s = math.cos(th), math.sin(th)
        f = np.array([[1.0, 0.0, -ds * s], [0.0, 1.0, ds * c], [0.0, 0.0, 1.0]])
        g = np.array([[c, -0.5 * ds * s], [s, 0.5 * ds * c], [0.0, 1.0]])
        q = np.diag(
            [
                cfg.slip_std_m_per_sqrt_m**2 * abs(ds) + inc.distance_var_m2,
                cfg.turn_std_rad_per_sqrt_rad**2 * abs(dyaw)
                + cfg.gyro_noise_rad_per_sqrt_s**2 * inc.dt_s,
            ]
        )
        self._cov = f @ self._cov @ f.T + g @ q @ g.T
        self._delta = np.array(
            [self._delta[0] + ds * c, self._delta[1] + ds * s, self._delta[2] + dyaw]
        )
        self._distance_since_m += abs(ds)

    def add_distance_variance(self, var_m2: float) -> None:
        """Add ``var_m2`` to the variance of the distance driven since the last node, along
        the direction of that motion (e.g. the square of a shortfall the LIDAR measured,
        :meth:`robot.odometry.inertial_odometry.InertialOdometry.observe_displacement`):
        the node made next tells the GCS its step may be that much shorter or longer."""
        if not (math.isfinite(var_m2) and var_m2 >= 0):
            raise ValueError(f"add_distance_variance: expected a finite var >= 0, got {var_m2}")
        if var_m2 == 0:
            return
        d = self._delta[:2]
        n = math.hypot(d[0], d[1])
        u = d / n if n > 1e-9 else np.array([math.cos(self._delta[2]), math.sin(self._delta[2])])
        self._cov[:2, :2] += var_m2 * np.outer(u, u)

    def due(self, pose_in_odom: np.ndarray, time_s: float) -> bool:
        """Whether a node should be made now (first node, moved, turned, or too long since)."""
        if self._last_pose is None:
            return True
        cfg = self.config
        rel = relative(self._last_pose, pose_in_odom)
        return bool(
            math.hypot(rel[0], rel[1]) >= cfg.min_distance_m
            or abs(self._delta[2]) >= cfg.min_turn_rad
            or time_s - self._last_time_s >= cfg.max_interval_s
        )

    def make(self, pose_in_odom: np.ndarray, time_s: float) -> PoseNode:
        """Emit the node at ``pose_in_odom`` and start accumulating the next constraint.

        The constraint is the relative pose between the two node poses (exactly consistent with
        the trajectory in ``odom``); its covariance is the one propagated along the way.
        """
        cfg = self.config
        pose = np.asarray(pose_in_odom, dtype=np.float64)
        if self._last_pose is None:
            delta = np.zeros(3)
            cov = np.diag([cfg.min_std_m**2, cfg.min_std_m**2, cfg.min_std_rad**2])
        else:
            delta = relative(self._last_pose, pose)
            cov = self._cov + np.diag([cfg.min_std_m**2, cfg.min_std_m**2, cfg.min_std_rad**2])
        node = PoseNode(
            node_index=self._next_index,
            time_s=time_s,
            pose_in_odom=(float(pose[0]), float(pose[1]), float(wrap_angle(pose[2]))),
            odom_delta=(float(delta[0]), float(delta[1]), float(delta[2])),
            odom_covariance=tuple(float(cov[i, j]) for i, j in _TRIU),  # type: ignore[arg-type]
        )
        self._next_index += 1
        self._last_pose = pose
        self._last_time_s = time_s
        self._delta = np.zeros(3)
        self._cov = np.zeros((3, 3))
        self._distance_since_m = 0.0
        return node
