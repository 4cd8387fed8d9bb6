"""Following a planned path with speed and acceleration limits (paper 5.4's last stage).

Pure pursuit on the path in ``odom``: steer towards the point ``lookahead_m`` ahead along the
path, turn in place when that point is far off the heading (skid steer can), slow down near
the goal and in tight turns, and limit linear and angular acceleration so commands are
smooth. Every command is then checked against keep-out disks (hazards): the follower stops
rather than let the predicted motion enter one (:func:`motion_enters_keepout`).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import msgspec
import numpy as np

from protocol.se2 import wrap_angle

__all__ = ["FollowStatus", "FollowerConfig", "PathFollower", "motion_enters_keepout"]


class FollowerConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    max_speed_m_s: float = 1.0
    max_accel_m_s2: float = 0.8
    max_yaw_rate_rad_s: float = 1.2
    max_yaw_accel_rad_s2: float = 3.0
    lookahead_m: float = 0.8
    goal_tolerance_m: float = 0.3
    turn_in_place_rad: float = 0.9  # heading error beyond which the robot turns on the spot
    slow_radius_m: float = 1.5  # decelerate within this distance of the goal
    yaw_gain: float = 2.0
    keepout_horizon_s: float = 1.5


class FollowStatus(enum.Enum):
    IDLE = "idle"
    FOLLOWING = "following"
    ARRIVED = "arrived"
    BLOCKED = "blocked"  # the next motion would enter a keep-out disk


@dataclass(frozen=True, slots=True)
class Command:
    linear_m_s: float
    angular_rad_s: float
    status: FollowStatus


def motion_enters_keepout(
    pose_in_odom: np.ndarray,
    linear_m_s: float,
    angular_rad_s: float,
    disks_in_odom: np.ndarray,
    *,
    horizon_s: float,
    steps: int = 10,
) -> bool:
    """Whether driving at the given velocities for ``horizon_s`` enters any disk ``(x, y, r)``
    (one it is not already inside: a robot inside a disk may still drive out of it)."""
    if len(disks_in_odom) == 0:
        return False
    disks = np.asarray(disks_in_odom, dtype=np.float64)
    x, y, th = (float(v) for v in pose_in_odom)
    d_now = np.hypot(disks[:, 0] - x, disks[:, 1] - y)
    inside_now = d_now < disks[:, 2]
    dt = horizon_s / steps
    # the predicted positions in scalar arithmetic (cheap), then every step against every
    # disk in one array expression: called every control period, the per-step array calls
    # cost more than the test
    xs = np.empty(steps)
    ys = np.empty(steps)
    for k in range(steps):
        x += linear_m_s * dt * math.cos(th + 0.5 * angular_rad_s * dt)
        y += linear_m_s * dt * math.sin(th + 0.5 * angular_rad_s * dt)
        th += angular_rad_s * dt
        xs[k], ys[k] = x, y
    d = np.hypot(disks[None, :, 0] - xs[:, None], disks[None, :, 1] - ys[:, None])
    entering = (d < disks[None, :, 2]) & ~inside_now
    deeper = inside_now & (d < d_now - 1e-9)
    return bool(np.any(entering | deeper))


def _clip(x: float, lo: float, hi: float) -> float:
    """``float(np.clip(x, lo, hi))`` for floats, the same comparisons (NaN kept), without
    numpy's call overhead on scalars (three a control period)."""
    if x != x:
        return x
    x = x if x > lo else lo
    return x if x < hi else hi


class PathFollower:
    """Pure pursuit with limits; call :meth:`step` at the control rate."""

    def __init__(self, config: FollowerConfig | None = None) -> None:
        self.config = config or FollowerConfig()
        self._path = np.zeros((0, 2))
        # the path's segments, their lengths and the arc length at each vertex: fixed while
        # the path is, asked for at every control period (_lookahead_point)
        self._seg = np.zeros((0, 2))
        self._seg_len = np.zeros(0)
        self._arc = np.zeros(1)
        self._v = 0.0
        self._w = 0.0
        self._progress = 0  # index of the path segment we are on

    def set_path(self, path_in_odom: np.ndarray) -> None:
        """Follow ``path_in_odom`` ``(N, 2)`` (N >= 1) from now on; empty path: stop."""
        # a copy: the segments below are kept, the caller's array may change
        path = np.array(path_in_odom, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(path)):
            raise ValueError("path_in_odom contains non-finite points")
        self._path = path
        self._seg = path[1:] - path[:-1]
        self._seg_len = np.hypot(self._seg[:, 0], self._seg[:, 1])
        self._arc = np.concatenate([[0.0], np.cumsum(self._seg_len)])
        self._progress = 0

    @property
    def has_path(self) -> bool:
        return len(self._path) > 0

    @property
    def remaining_path_in_odom(self) -> np.ndarray:
        """``(K, 2)`` the path still ahead, from the segment last reached (empty: none)."""
        return self._path[self._progress :]

    def _lookahead_point(self, pos: np.ndarray) -> tuple[np.ndarray, float]:
        """The point ``lookahead_m`` of arc length beyond ``pos``'s projection onto the path,
        and the straight distance to the goal. Progress only moves forward along the path
        (searching a window ahead), so a path that doubles back is followed in order."""
        path = self._path
        if len(path) == 1:
            return path[0], float(np.linalg.norm(path[0] - pos))
        cfg = self.config
        seg, seg_len, arc = self._seg, self._seg_len, self._arc
        lo = self._progress
        # segments starting within the window, plus the one the window ends in
        hi = int(np.searchsorted(arc, arc[lo] + 4.0 * cfg.lookahead_m + 1.0, side="right")) + 1
        hi = min(max(hi, lo + 2), len(seg))
        a, ab, ln = path[lo:hi], seg[lo:hi], seg_len[lo:hi]
        t = np.clip(np.einsum("ij,ij->i", pos - a, ab) / np.maximum(ln**2, 1e-12), 0.0, 1.0)
        proj = a + t[:, None] * ab
        k = int(np.argmin(np.hypot(proj[:, 0] - pos[0], proj[:, 1] - pos[1])))
        i = lo + k
        self._progress = i
        s_target = min(arc[i] + t[k] * seg_len[i] + cfg.lookahead_m, arc[-1])
        j = min(int(np.searchsorted(arc, s_target, side="right")) - 1, len(seg) - 1)
        frac = (s_target - arc[j]) / max(seg_len[j], 1e-12)
        point = path[j] + min(frac, 1.0) * seg[j]
        return point, float(np.linalg.norm(path[-1] - pos))

    def step(
        self,
        pose_in_odom: np.ndarray,
        dt_s: float,
        *,
        keepout_disks_in_odom: np.ndarray | None = None,
        speed_limit_m_s: float | None = None,
    ) -> Command:
        """The velocity command for this control period."""
        cfg = self.config
        pos = np.asarray(pose_in_odom[:2], dtype=np.float64)
        status = FollowStatus.FOLLOWING
        if not self.has_path:
            v_des = w_des = 0.0
            status = FollowStatus.IDLE
        else:
            target, to_goal = self._lookahead_point(pos)
            if to_goal <= cfg.goal_tolerance_m:
                v_des = w_des = 0.0
                status = FollowStatus.ARRIVED
            else:
                bearing = math.atan2(target[1] - pos[1], target[0] - pos[0])
                err = float(wrap_angle(bearing - float(pose_in_odom[2])))
                w_des = _clip(cfg.yaw_gain * err, -cfg.max_yaw_rate_rad_s, cfg.max_yaw_rate_rad_s)
                vmax = min(cfg.max_speed_m_s, speed_limit_m_s or math.inf)
                if abs(err) > cfg.turn_in_place_rad:
                    v_des = 0.0
                else:
                    v_des = vmax * math.cos(err) * min(1.0, to_goal / cfg.slow_radius_m + 0.2)
        v, w = self._limit(v_des, w_des, dt_s)
        disks = keepout_disks_in_odom
        if disks is not None and motion_enters_keepout(
            np.asarray(pose_in_odom), v, w, disks, horizon_s=cfg.keepout_horizon_s
        ):
            v, w = 0.0, 0.0  # a hard stop is the safe reaction; the planner routes around
            self._v, self._w = 0.0, 0.0
            status = FollowStatus.BLOCKED
        return Command(v, w, status)

    def _limit(self, v_des: float, w_des: float, dt_s: float) -> tuple[float, float]:
        cfg = self.config
        dv = _clip(v_des - self._v, -cfg.max_accel_m_s2 * dt_s, cfg.max_accel_m_s2 * dt_s)
        dw = _clip(
            w_des - self._w, -cfg.max_yaw_accel_rad_s2 * dt_s, cfg.max_yaw_accel_rad_s2 * dt_s
        )
        self._v += dv
        self._w += dw
        return self._v, self._w
