"""The nodding LIDAR: a 270 deg planar scanner on a servo, one 3D sweep per 1.25 s (paper 3.1).

The scan plane tilts about the sensor's y axis from ``tilt_min_deg`` to ``tilt_max_deg`` and
back (alternate sweeps go up and down); a sweep is ``lines_per_sweep`` scan lines of ``beams``
beams over ``fov_deg``. The MAGIC robot's Hokuyo UTM-30LX gave about 50k points per sweep
(1081 beams x 40 Hz x 1.25 s); the default here is sparser so that large teams simulate in
real time; ``beams`` and ``lines_per_sweep`` restore the full density.

:class:`NoddingLidars` schedules the lines of every robot (staggered phases), builds all rays
due in a simulator step as one numpy batch (cast by the caller, in chunks of at most 16384),
and accumulates the hits into :class:`~protocol.sensors.LidarSweep` frames. Each point is in
``base`` at the instant its line was cast (the pose used to cast it); ``point_time_s`` is
relative to the sweep's first line. Noise: Gaussian range noise ``range_noise_m``; returns
beyond ``range_max_m`` or below ``range_min_m`` and hits on the robot itself are dropped.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

from protocol.sensors import LidarSweep

__all__ = ["LidarConfig", "NoddingLidars", "beam_directions"]


class LidarConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The nodding LIDAR (see the module docstring). ``sweep_period_s`` 1.5 (17 % fewer rays
    and sweeps) measured on the quick mission (issue 14, session 15, at 8183549 with the
    perception's 2 s tag images at 240 x 180 and a prototype 10 Hz control in the robot
    node, seeds 0 / 7): 98.2 / 94.5 CPU-s a run (ray casts 10.5 -> 9.3, the nodes' sweeps
    24 -> 21) against 120.8 / 124.8 at HEAD, but explored 0.925 / 0.754 (0.935 / 0.917),
    ATE 0.245 / 0.315 m (0.166 / 0.188): not kept. Fewer ``beams`` were not measured: the
    shape classifier's features assume 1.5 deg beams (robot.perception.shape_features)."""

    enabled: bool = True
    beams: int = 181
    fov_deg: float = 270.0
    lines_per_sweep: int = 25
    sweep_period_s: float = 1.25
    tilt_min_deg: float = -40.0
    tilt_max_deg: float = 20.0
    range_min_m: float = 0.1
    range_max_m: float = 30.0
    range_noise_m: float = 0.01

    def __post_init__(self) -> None:
        if not 2 <= self.beams <= 4096:
            raise ValueError(f"beams must be in [2, 4096], got {self.beams}")
        if not 1 <= self.lines_per_sweep <= 1000:
            raise ValueError(f"lines_per_sweep must be in [1, 1000], got {self.lines_per_sweep}")
        if not 0 < self.fov_deg <= 360:
            raise ValueError(f"fov_deg must be in (0, 360], got {self.fov_deg}")
        if not (math.isfinite(self.sweep_period_s) and self.sweep_period_s > 0):
            raise ValueError(f"sweep_period_s must be > 0, got {self.sweep_period_s}")
        if not -90 <= self.tilt_min_deg <= self.tilt_max_deg <= 90:
            raise ValueError("need -90 <= tilt_min_deg <= tilt_max_deg <= 90")
        if not 0 <= self.range_min_m < self.range_max_m <= 200:
            raise ValueError("need 0 <= range_min_m < range_max_m <= 200")
        if not 0 <= self.range_noise_m <= 1:
            raise ValueError(f"range_noise_m must be in [0, 1], got {self.range_noise_m}")

    @property
    def rays_per_sweep(self) -> int:
        return self.beams * self.lines_per_sweep


def beam_directions(config: LidarConfig, tilt_rad: float) -> np.ndarray:
    """Unit directions ``(beams, 3)`` in ``base`` of one scan line at servo tilt ``tilt_rad``
    (positive up): the plane ``(cos a, sin a, 0)`` rotated about y by ``-tilt``."""
    half = math.radians(config.fov_deg) / 2
    a = np.linspace(-half, half, config.beams)
    c = math.cos(tilt_rad)
    s = math.sin(tilt_rad)
    return np.stack([np.cos(a) * c, np.sin(a), np.cos(a) * s], axis=1)


class NoddingLidars:
    """The LIDARs of ``count`` robots mounted at ``lidar_in_base_m``."""

    def __init__(
        self,
        count: int,
        *,
        config: LidarConfig,
        lidar_in_base_m: tuple[float, float, float],
        seed: int = 0,
        start_s: float = 0.0,
    ) -> None:
        self.config = config
        self.count = count
        self._rng = np.random.default_rng(seed)
        self._origin = np.array(lidar_in_base_m, dtype=np.float64)
        self.line_period_s = config.sweep_period_s / config.lines_per_sweep
        tilts = np.radians(
            np.linspace(config.tilt_min_deg, config.tilt_max_deg, config.lines_per_sweep)
        )
        # directions of every line for upward (index 0) and downward (index 1) sweeps
        up = np.stack([beam_directions(config, float(t)) for t in tilts])
        self._dirs = (up, up[::-1].copy())
        # staggered phases so sweeps of different robots end at different steps
        self._phase = start_s + np.arange(count) * (self.line_period_s / max(count, 1))
        self._sweep = np.zeros(count, dtype=np.int64)
        self._line = np.zeros(count, dtype=np.int64)
        self._sweep_t0 = np.full(count, np.nan)
        self._pts: list[list[np.ndarray]] = [[] for _ in range(count)]
        self._times: list[list[np.ndarray]] = [[] for _ in range(count)]
        self.rays_cast = 0

    def due(self, now_s: float) -> list[tuple[int, int, int]]:
        """``(robot, sweep, line)`` whose scheduled time is ``<= now_s`` (not yet cast)."""
        out: list[tuple[int, int, int]] = []
        for r in range(self.count):
            while True:
                t = (
                    self._phase[r]
                    + self._sweep[r] * self.config.sweep_period_s
                    + self._line[r] * self.line_period_s
                )
                if t > now_s + 1e-9:
                    break
                out.append((r, int(self._sweep[r]), int(self._line[r])))
                self._line[r] += 1
                if self._line[r] == self.config.lines_per_sweep:
                    self._line[r] = 0
                    self._sweep[r] += 1
        return out

    def rays(
        self, due: list[tuple[int, int, int]], world_from_base: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """World ray origins and ends ``(R, 3)`` for the due lines, and their base directions
        (even sweeps tilt up, odd sweeps down)."""
        if not due:
            z = np.zeros((0, 3))
            return z, z, z
        dirs_base = []
        robots = []
        for r, sweep, line in due:
            dirs_base.append(self._dirs[sweep % 2][line])
            robots.append(np.full(self.config.beams, r))
        d = np.concatenate(dirs_base)
        rid = np.concatenate(robots)
        m = world_from_base[rid]
        origin = m[:, :3, :3] @ self._origin + m[:, :3, 3]
        d_world = np.einsum("nij,nj->ni", m[:, :3, :3], d)
        return origin, origin + d_world * self.config.range_max_m, d

    def accept(
        self,
        due: list[tuple[int, int, int]],
        now_s: float,
        dirs_base: np.ndarray,
        fraction: np.ndarray,
        self_hit: np.ndarray,
    ) -> list[tuple[int, LidarSweep]]:
        """Turn the cast lines into points; returns the sweeps completed by them."""
        cfg = self.config
        done: list[tuple[int, LidarSweep]] = []
        b = cfg.beams
        rng_all = fraction * cfg.range_max_m
        if cfg.range_noise_m > 0:
            rng_all = rng_all + self._rng.normal(0.0, cfg.range_noise_m, size=len(rng_all))
        keep_all = (
            (fraction < 1.0)
            & ~self_hit
            & (rng_all >= cfg.range_min_m)
            & (rng_all < cfg.range_max_m)
        )
        pts_all_lines = (self._origin + dirs_base * rng_all[:, None]).astype(np.float32)
        for k, (r, sweep, line) in enumerate(due):
            sl = slice(k * b, (k + 1) * b)
            keep = keep_all[sl]
            if line == 0 or math.isnan(self._sweep_t0[r]):
                self._sweep_t0[r] = now_s
                self._pts[r] = []
                self._times[r] = []
            pts = pts_all_lines[sl][keep]
            self._pts[r].append(pts)
            self._times[r].append(np.full(len(pts), now_s - self._sweep_t0[r], dtype=np.float32))
            if line == cfg.lines_per_sweep - 1:
                t0 = float(self._sweep_t0[r])
                pts_all = (
                    np.concatenate(self._pts[r]) if self._pts[r] else np.zeros((0, 3), np.float32)
                )
                times = (
                    np.concatenate(self._times[r]) if self._times[r] else np.zeros(0, np.float32)
                )
                done.append(
                    (
                        r,
                        LidarSweep(
                            sweep_index=sweep,
                            time_s=t0,
                            duration_s=now_s - t0,
                            points_in_base=pts_all,
                            point_time_s=times,
                        ),
                    )
                )
                self._pts[r] = []
                self._times[r] = []
                self._sweep_t0[r] = np.nan
        self.rays_cast += len(due) * b
        return done
