"""Kinematic skid-steer robot bodies that follow the terrain (paper 3.1, 4.3.1).

All robots of a team are stepped together over numpy arrays (``O(N * footprint samples)``
per step, no physics engine): a commanded linear and angular velocity goes through
acceleration limits to the wheels; the body moves at the wheel velocities reduced by slip
(more when turning and on sand, with seeded noise), which is why encoder yaw is poor and a
gyro is needed (paper 4.3.1). A move is refused if the body's footprint would cover a
vertical structure or a step higher than ``climb_max_m`` (10 cm curbs are climbed, walls,
dock edges, cars and low canopies are not), make the footprint overlap another robot's
(oriented rectangles, ``robot_gap_m`` apart at least) or come closer to a person than their
radii allow; a refused translation stalls the wheels (no encoder counts). Height, pitch
and roll come from the ground height under the four wheels. A battery drains with time and
speed; a robot whose battery is empty, or that was disabled by a blast, does not move.

Frames: ``world_from_base`` pose ``(x, y, yaw)``; ``base`` has its origin on the ground
between the wheels, x forward, y left, z up (REP-103). Pitch is positive nose-down and roll
positive left-side-up (rotations about +y and +x).

Cost (issue 14, session 14: exact cuts, the same motion bit for bit): a step reuses the
footprint count of the pose the last step ended at and the transforms of an unchanged state,
and the oriented-rectangle test of a crowd is compiled (the numpy form stays as
:func:`footprints_overlap_reference`; 113 -> 5 us for 4 x 4 poses), as is the footprint
count (:meth:`SkidSteerBodies.blocked_count_reference`; 33 -> 4 us for 4 poses). In the
quick mission (small world, 300 mission-s, at 38fac2c, seeds 0 / 7, one run each at load
~12, thread CPU, reports identical) the bodies' step took 3.32 / 3.30 -> 3.02 / 3.13 CPU-s
with the first three (0038ba4); with the footprint count compiled too 3.16 / 3.39 (reports
identical; the runs' noise, +-5 % on this item, hides the ~0.3 CPU-s it saves).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numba as nb
import numpy as np

from sim.ground_truth import GroundTruth, step_map

__all__ = ["BodyState", "RobotBodyConfig", "SkidSteerBodies"]


class RobotBodyConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The MAGIC robot's body (paper 3.1): about 0.6 x 0.5 m, four wheels skid steer,
    a 720 Wh battery (4 h worst case, about twice that typically)."""

    length_m: float = 0.6
    width_m: float = 0.5
    wheelbase_m: float = 0.45
    track_m: float = 0.45
    radius_m: float = 0.38  # encloses the footprint: against people (discs)
    robot_gap_m: float = 0.02  # robots' footprints stay this far apart
    max_linear_m_s: float = 1.0
    max_angular_rad_s: float = 1.5
    max_linear_accel_m_s2: float = 1.0
    max_angular_accel_rad_s2: float = 3.0
    slip_linear: float = 0.02
    slip_linear_per_rad_s: float = 0.05
    slip_turn: float = 0.25
    slip_noise: float = 0.03
    climb_max_m: float = 0.12
    battery_wh: float = 720.0
    idle_power_w: float = 60.0
    drive_power_w: float = 120.0

    def __post_init__(self) -> None:
        for name in (
            "length_m",
            "width_m",
            "wheelbase_m",
            "track_m",
            "radius_m",
            "max_linear_m_s",
            "max_angular_rad_s",
            "max_linear_accel_m_s2",
            "max_angular_accel_rad_s2",
            "climb_max_m",
            "battery_wh",
            "robot_gap_m",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be finite and > 0, got {v}")
        for name in ("slip_linear", "slip_turn", "slip_noise", "slip_linear_per_rad_s"):
            v = getattr(self, name)
            if not 0.0 <= v < 1.0:
                raise ValueError(f"{name} must be in [0, 1), got {v}")


@dataclass
class BodyState:
    """Per-robot arrays, ``(N,)`` each unless stated."""

    pose: np.ndarray  # (N, 3) world_from_base x, y, yaw
    z_m: np.ndarray
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    wheel_linear_m_s: np.ndarray  # what the wheels do (accel-limited command)
    wheel_angular_rad_s: np.ndarray
    linear_m_s: np.ndarray  # what the body does (after slip and collisions)
    angular_rad_s: np.ndarray
    left_m: np.ndarray  # cumulative wheel travel (encoders)
    right_m: np.ndarray
    battery_wh: np.ndarray
    disabled: np.ndarray  # bool: blast or empty battery
    blocked_steps: np.ndarray  # int: steps a translation was refused


def footprints_overlap(
    a: np.ndarray, b: np.ndarray, *, half_length_m: float, half_width_m: float
) -> np.ndarray:
    """``(N, M)``: whether the rectangles ``2 half_length x 2 half_width`` at poses ``a``
    ``(N, 3)`` and ``b`` ``(M, 3)`` overlap (separating-axis test over the four edge normals;
    the numpy form is :func:`footprints_overlap_reference`: the same verdicts, compiled)."""
    out = np.empty((len(a), len(b)), dtype=bool)
    _footprints_overlap(
        np.ascontiguousarray(a[:, 0], dtype=np.float64),
        np.ascontiguousarray(a[:, 1], dtype=np.float64),
        np.cos(a[:, 2]),
        np.sin(a[:, 2]),
        np.ascontiguousarray(b[:, 0], dtype=np.float64),
        np.ascontiguousarray(b[:, 1], dtype=np.float64),
        np.cos(b[:, 2]),
        np.sin(b[:, 2]),
        float(half_length_m),
        float(half_width_m),
        out,
    )
    return out


@nb.njit(cache=True, nogil=True)
def _footprints_overlap(
    ax: np.ndarray,
    ay: np.ndarray,
    ac: np.ndarray,
    as_: np.ndarray,
    bx: np.ndarray,
    by: np.ndarray,
    bc: np.ndarray,
    bs: np.ndarray,
    hl: float,
    hw: float,
    out: np.ndarray,
) -> None:  # pragma: no cover - compiled (tested against footprints_overlap_reference)
    """The reference's arithmetic per pair, in its order (the cosines and sines computed by
    numpy outside; no fused multiply-adds: numba's default; the sums' signs of zero are
    taken off by ``abs`` in both)."""
    for i in range(len(ax)):
        for j in range(len(bx)):
            dx = bx[j] - ax[i]
            dy = by[j] - ay[i]
            sep = False
            for k in range(4):
                if k == 0:
                    x, y = ac[i], as_[i]
                elif k == 1:
                    x, y = -as_[i], ac[i]
                elif k == 2:
                    x, y = bc[j], bs[j]
                else:
                    x, y = -bs[j], bc[j]
                gap = abs(dx * x + dy * y)
                ea = hl * abs(ac[i] * x + as_[i] * y) + hw * abs(-as_[i] * x + ac[i] * y)
                eb = hl * abs(bc[j] * x + bs[j] * y) + hw * abs(-bs[j] * x + bc[j] * y)
                if gap > ea + eb:
                    sep = True
            out[i, j] = not sep


def footprints_overlap_reference(
    a: np.ndarray, b: np.ndarray, *, half_length_m: float, half_width_m: float
) -> np.ndarray:
    """``(N, M)``: whether the rectangles ``2 half_length x 2 half_width`` at poses ``a``
    ``(N, 3)`` and ``b`` ``(M, 3)`` overlap (separating-axis test over the four edge normals;
    numpy, the reference of :func:`footprints_overlap`)."""
    d = b[None, :, :2] - a[:, None, :2]  # (N, M, 2)
    ua = np.stack([np.cos(a[:, 2]), np.sin(a[:, 2])], axis=1)[:, None, :]  # (N, 1, 2)
    va = np.stack([-ua[..., 1], ua[..., 0]], axis=2)
    ub = np.stack([np.cos(b[:, 2]), np.sin(b[:, 2])], axis=1)[None, :, :]  # (1, M, 2)
    vb = np.stack([-ub[..., 1], ub[..., 0]], axis=2)

    def extent(u: np.ndarray, v: np.ndarray, axis: np.ndarray) -> np.ndarray:
        return half_length_m * np.abs(np.sum(u * axis, axis=2)) + half_width_m * np.abs(
            np.sum(v * axis, axis=2)
        )

    separated = np.zeros(d.shape[:2], dtype=bool)
    for axis in (ua, va, ub, vb):
        gap = np.abs(np.sum(d * axis, axis=2))
        separated |= gap > extent(ua, va, axis) + extent(ub, vb, axis)
    return ~separated


@nb.njit(cache=True, nogil=True)
def _blocked_count(
    poses: np.ndarray,
    c: np.ndarray,
    s: np.ndarray,
    foot: np.ndarray,
    res: float,
    blocked: np.ndarray,
) -> np.ndarray:  # pragma: no cover - compiled (tested against blocked_count_reference)
    """:meth:`SkidSteerBodies.blocked_count_reference`'s arithmetic per footprint sample, in
    its order (cosines and sines from numpy; truncation toward zero as ``astype``)."""
    ny, nx = blocked.shape
    out = np.zeros(len(poses), dtype=np.int64)
    for n in range(len(poses)):
        for k in range(len(foot)):
            fx = poses[n, 0] + c[n] * foot[k, 0] - s[n] * foot[k, 1]
            fy = poses[n, 1] + s[n] * foot[k, 0] + c[n] * foot[k, 1]
            j = int(fx / res)
            i = int(fy / res)
            if i < 0 or j < 0 or i >= ny or j >= nx or blocked[i, j]:
                out[n] += 1
    return out


def _footprint_offsets(length: float, width: float, spacing: float) -> np.ndarray:
    nx = int(math.ceil(length / spacing)) + 1
    ny = int(math.ceil(width / spacing)) + 1
    u, v = np.meshgrid(
        np.linspace(-length / 2, length / 2, nx), np.linspace(-width / 2, width / 2, ny)
    )
    return np.stack([u.ravel(), v.ravel()], axis=1)


class SkidSteerBodies:
    """The team's bodies on a ground truth (see the module docstring)."""

    def __init__(
        self,
        start_poses: np.ndarray,
        truth: GroundTruth,
        *,
        config: RobotBodyConfig | None = None,
        seed: int = 0,
    ) -> None:
        self.config = cfg = config or RobotBodyConfig()
        self.truth = truth
        self._rng = np.random.default_rng(seed)
        self._blocked = truth.vertical_occupancy | (step_map(truth.height_m) > cfg.climb_max_m)
        self._foot = _footprint_offsets(cfg.length_m, cfg.width_m, truth.resolution_m * 0.6)
        hw, ht = cfg.wheelbase_m / 2, cfg.track_m / 2
        # front-left, front-right, rear-left, rear-right
        self._wheels = np.array([[hw, ht], [hw, -ht], [-hw, ht], [-hw, -ht]])
        p = np.asarray(start_poses, dtype=np.float64).reshape(-1, 3)
        n = len(p)
        z = np.zeros(n)
        self.state = BodyState(
            pose=p.copy(),
            z_m=z.copy(),
            roll_rad=z.copy(),
            pitch_rad=z.copy(),
            wheel_linear_m_s=z.copy(),
            wheel_angular_rad_s=z.copy(),
            linear_m_s=z.copy(),
            angular_rad_s=z.copy(),
            left_m=z.copy(),
            right_m=z.copy(),
            battery_wh=np.full(n, cfg.battery_wh),
            disabled=np.zeros(n, dtype=bool),
            blocked_steps=np.zeros(n, dtype=np.int64),
        )
        # the footprint count of the pose each step ends at (a pure function of the pose: the
        # next step's "before" when nobody moved the bodies in between) and the transforms of
        # the state last asked for: reused while the inputs are equal, bit for bit
        self._count_of: tuple[bytes, np.ndarray] | None = None
        self._matrices_of: tuple[bytes, np.ndarray] | None = None
        self._terrain()

    @property
    def count(self) -> int:
        return len(self.state.pose)

    def blocked_count(self, poses: np.ndarray) -> np.ndarray:
        """Footprint samples of each pose ``(N, 3)`` that fall on blocked cells."""
        p = np.ascontiguousarray(poses, dtype=np.float64)
        return _blocked_count(  # type: ignore[no-any-return]
            p, np.cos(p[:, 2]), np.sin(p[:, 2]), self._foot, self.truth.resolution_m, self._blocked
        )

    def blocked_count_reference(self, poses: np.ndarray) -> np.ndarray:
        """:meth:`blocked_count` in numpy (its reference: the same counts)."""
        c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
        fx = (
            poses[:, None, 0]
            + c[:, None] * self._foot[None, :, 0]
            - s[:, None] * self._foot[None, :, 1]
        )
        fy = (
            poses[:, None, 1]
            + s[:, None] * self._foot[None, :, 0]
            + c[:, None] * self._foot[None, :, 1]
        )
        res = self.truth.resolution_m
        ny, nx = self._blocked.shape
        j = (fx / res).astype(np.int64)
        i = (fy / res).astype(np.int64)
        outside = (i < 0) | (j < 0) | (i >= ny) | (j >= nx)
        hit = self._blocked[np.clip(i, 0, ny - 1), np.clip(j, 0, nx - 1)] | outside
        return hit.sum(axis=1)  # type: ignore[no-any-return]

    def _terrain(self) -> None:
        st = self.state
        c, s = np.cos(st.pose[:, 2]), np.sin(st.pose[:, 2])
        wx = (
            st.pose[:, None, 0]
            + c[:, None] * self._wheels[None, :, 0]
            - s[:, None] * self._wheels[None, :, 1]
        )
        wy = (
            st.pose[:, None, 1]
            + s[:, None] * self._wheels[None, :, 0]
            + c[:, None] * self._wheels[None, :, 1]
        )
        h = self.truth.height_at(wx, wy).astype(np.float64)  # (N, 4)
        front, rear = h[:, :2].mean(1), h[:, 2:].mean(1)
        left, right = h[:, [0, 2]].mean(1), h[:, [1, 3]].mean(1)
        st.z_m = h.mean(1)
        st.pitch_rad = -np.arctan2(front - rear, self.config.wheelbase_m)
        st.roll_rad = np.arctan2(left - right, self.config.track_m)

    def step(
        self,
        dt_s: float,
        linear_cmd_m_s: np.ndarray,
        angular_cmd_rad_s: np.ndarray,
        *,
        others_xy_m: np.ndarray | None = None,
        others_radius_m: np.ndarray | None = None,
    ) -> None:
        """Advance every body by ``dt_s`` under the commands (``(N,)`` each, finite).

        ``others_xy_m`` / ``others_radius_m``: moving obstacles that are not robots (people).
        """
        cfg, st = self.config, self.state
        n = self.count
        v_cmd = np.clip(
            np.asarray(linear_cmd_m_s, np.float64), -cfg.max_linear_m_s, cfg.max_linear_m_s
        )
        w_cmd = np.clip(
            np.asarray(angular_cmd_rad_s, np.float64), -cfg.max_angular_rad_s, cfg.max_angular_rad_s
        )
        v_cmd = np.where(st.disabled, 0.0, v_cmd)
        w_cmd = np.where(st.disabled, 0.0, w_cmd)
        dv = cfg.max_linear_accel_m_s2 * dt_s
        dw = cfg.max_angular_accel_rad_s2 * dt_s
        vw = st.wheel_linear_m_s + np.clip(v_cmd - st.wheel_linear_m_s, -dv, dv)
        ww = st.wheel_angular_rad_s + np.clip(w_cmd - st.wheel_angular_rad_s, -dw, dw)
        vw = np.where(st.disabled, 0.0, vw)
        ww = np.where(st.disabled, 0.0, ww)

        i, j = self.truth.cells(st.pose[:, :2])
        terrain_slip = self.truth.slip[i, j].astype(np.float64)
        noise = self._rng.normal(0.0, cfg.slip_noise, size=(2, n))
        s_lin = np.clip(
            cfg.slip_linear
            + terrain_slip
            + cfg.slip_linear_per_rad_s * np.abs(ww)
            + noise[0] * 0.3,
            0.0,
            0.95,
        )
        s_turn = np.clip(cfg.slip_turn + terrain_slip * 0.5 + noise[1], 0.0, 0.95)
        v = vw * (1.0 - s_lin)
        w = ww * (1.0 - s_turn)

        yaw_mid = st.pose[:, 2] + 0.5 * w * dt_s
        cand = st.pose.copy()
        cand[:, 0] += v * np.cos(yaw_mid) * dt_s
        cand[:, 1] += v * np.sin(yaw_mid) * dt_s
        cand[:, 2] = (st.pose[:, 2] + w * dt_s + np.pi) % (2 * np.pi) - np.pi

        key = st.pose.tobytes()
        if self._count_of is not None and self._count_of[0] == key:
            before = self._count_of[1]
        else:
            before = self.blocked_count(st.pose)
        after = self.blocked_count(cand)
        ok = (after == 0) | (after < before)
        ok &= self._clear_of_others(cand, others_xy_m, others_radius_m)
        # A refused move may still turn in place.
        turn = st.pose.copy()
        turn[:, 2] = cand[:, 2]
        turn_after = self.blocked_count(turn)
        turn_ok = ~ok & ((turn_after == 0) | (turn_after < before))
        turn_ok &= self._clear_of_others(turn, others_xy_m, others_radius_m)
        new_pose = np.where(ok[:, None], cand, np.where(turn_ok[:, None], turn, st.pose))
        count = np.where(ok, after, np.where(turn_ok, turn_after, before))
        moved_dist = np.where(ok, v * dt_s, 0.0)
        st.blocked_steps += (~ok & (np.abs(v) > 1e-9)).astype(np.int64)
        # a refused translation stalls the wheels; a refused turn stops the turning too
        vw = np.where(ok, vw, 0.0)
        ww = np.where(ok | turn_ok, ww, 0.0)
        w = np.where(ok | turn_ok, w, 0.0)

        st.left_m += (vw - ww * cfg.track_m / 2) * dt_s
        st.right_m += (vw + ww * cfg.track_m / 2) * dt_s
        st.pose = new_pose
        self._count_of = (new_pose.tobytes(), count)
        st.wheel_linear_m_s = vw
        st.wheel_angular_rad_s = ww
        st.linear_m_s = np.where(ok, v, 0.0)
        st.angular_rad_s = w
        power_w = cfg.idle_power_w + cfg.drive_power_w * np.minimum(
            1.0, np.abs(moved_dist) / max(dt_s, 1e-9) / cfg.max_linear_m_s
        )
        st.battery_wh = np.maximum(
            0.0, st.battery_wh - np.where(st.disabled, 0.0, power_w) * dt_s / 3600
        )
        st.disabled |= st.battery_wh <= 0.0
        self._terrain()

    def _clear_of_others(
        self, cand: np.ndarray, others_xy: np.ndarray | None, others_r: np.ndarray | None
    ) -> np.ndarray:
        """True where ``cand`` does not make the footprint overlap another robot's (current or
        candidate pose; an overlap that already exists may only be left), nor come closer to a
        person than before below the sum of radii."""
        cfg = self.config
        r = cfg.radius_m
        old = self.state.pose[:, :2]
        new = cand[:, :2]
        n = len(old)
        ok = np.ones(n, dtype=bool)
        # two footprints cannot overlap farther apart than their circumscribed circles reach:
        # the oriented-rectangle tests (most of a step's cost) only run when some pair is near
        reach_m = 2.0 * math.hypot(cfg.length_m / 2, cfg.width_m / 2) + 2.0 * cfg.robot_gap_m
        if n > 1:
            d_new = np.minimum(
                np.linalg.norm(new[:, None, :] - old[None, :, :], axis=2),
                np.linalg.norm(new[:, None, :] - new[None, :, :], axis=2),
            )
            d_old = np.linalg.norm(old[:, None, :] - old[None, :, :], axis=2)
            np.fill_diagonal(d_new, np.inf)
            np.fill_diagonal(d_old, np.inf)
            if min(float(d_new.min()), float(d_old.min())) <= reach_m:
                half = {
                    "half_length_m": cfg.length_m / 2 + cfg.robot_gap_m / 2,
                    "half_width_m": cfg.width_m / 2 + cfg.robot_gap_m / 2,
                }
                pose = self.state.pose
                hit_new = footprints_overlap(cand, pose, **half)
                hit_new |= footprints_overlap(cand, cand, **half)
                hit_old = footprints_overlap(pose, pose, **half)
                np.fill_diagonal(hit_new, False)
                # disabled robots (wrecks) are obstacles too
                bad = hit_new & (~hit_old | (d_new < d_old))
                ok &= ~bad.any(axis=1)
        if others_xy is not None and len(others_xy):
            rr = np.asarray(others_r, np.float64)[None, :] + r
            d_new = np.linalg.norm(new[:, None, :] - others_xy[None, :, :], axis=2)
            d_old = np.linalg.norm(old[:, None, :] - others_xy[None, :, :], axis=2)
            ok &= ~((d_new < rr) & (d_new < d_old)).any(axis=1)
        return ok

    def world_from_base_matrices(self) -> np.ndarray:
        """``(N, 4, 4)`` homogeneous transforms ``world_from_base`` (yaw, pitch, roll, z)."""
        st = self.state
        key = b"".join(a.tobytes() for a in (st.pose, st.z_m, st.roll_rad, st.pitch_rad))
        if self._matrices_of is None or self._matrices_of[0] != key:
            self._matrices_of = (key, pose_matrices(st.pose, st.z_m, st.roll_rad, st.pitch_rad))
        return self._matrices_of[1].copy()


def pose_matrices(
    pose: np.ndarray, z_m: np.ndarray, roll_rad: np.ndarray, pitch_rad: np.ndarray
) -> np.ndarray:
    """``R = Rz(yaw) Ry(pitch) Rx(roll)`` with translation ``(x, y, z)``, batched."""
    cy, sy = np.cos(pose[:, 2]), np.sin(pose[:, 2])
    cp, sp = np.cos(pitch_rad), np.sin(pitch_rad)
    cr, sr = np.cos(roll_rad), np.sin(roll_rad)
    m = np.zeros((len(pose), 4, 4))
    m[:, 0, 0] = cy * cp
    m[:, 0, 1] = cy * sp * sr - sy * cr
    m[:, 0, 2] = cy * sp * cr + sy * sr
    m[:, 1, 0] = sy * cp
    m[:, 1, 1] = sy * sp * sr + cy * cr
    m[:, 1, 2] = sy * sp * cr - cy * sr
    m[:, 2, 0] = -sp
    m[:, 2, 1] = cp * sr
    m[:, 2, 2] = cp * cr
    m[:, 0, 3] = pose[:, 0]
    m[:, 1, 3] = pose[:, 1]
    m[:, 2, 3] = z_m
    m[:, 3, 3] = 1.0
    return m
