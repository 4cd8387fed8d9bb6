"""People tracked across LIDAR sweeps with a constant-velocity Kalman filter (paper 2, 5.2).

Civilians and hostiles (the mobile OOIs) appear in a sweep as segments of human size
(:mod:`robot.perception.shape_classifier`, class ``person``). :class:`PersonTracker` keeps
tracks in the robot's private frame ``odom`` (smooth, never loop-closed: a track's velocity
there is the person's velocity over ground, whatever the robot does), one sweep at a time:

1. predict every track to the sweep's time with the constant-velocity model
   ``x' = x + v dt``, process noise of white acceleration ``accel_noise_m_s2``;
2. associate: gated nearest neighbour, each measurement to at most one track, pairs taken in
   order of increasing Mahalanobis distance, gate ``gate_sigma`` (and ``gate_max_m``);
3. update matched tracks (measurement noise ``meas_sigma_m``); start tentative tracks from
   unmatched measurements; a track is *confirmed* after ``confirm_hits`` hits and dropped
   after ``max_missed`` sweeps without one (``max_missed_tentative`` while tentative).

Colour (who is a hostile) belongs to the camera's colour classifier: it labels a track with
:meth:`PersonTracker.set_kind`; the label stays with the track id.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["PersonTrack", "PersonTracker", "TrackerConfig"]


class TrackerConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``meas_sigma_m``: a person segment's centre error (1 sigma); ``accel_noise_m_s2``:
    white-acceleration process noise (people start, stop and turn); ``init_speed_sigma_m_s``:
    prior on a new track's velocity; gates and life cycle as in the module docstring."""

    meas_sigma_m: float = 0.08
    accel_noise_m_s2: float = 0.6
    init_speed_sigma_m_s: float = 1.5
    gate_sigma: float = 4.0
    gate_max_m: float = 2.0
    confirm_hits: int = 2
    max_missed: int = 4
    max_missed_tentative: int = 1

    def __post_init__(self) -> None:
        for name in ("meas_sigma_m", "accel_noise_m_s2", "init_speed_sigma_m_s", "gate_sigma"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v}")
        if self.confirm_hits < 1 or self.max_missed < 0 or self.max_missed_tentative < 0:
            raise ValueError("need confirm_hits >= 1, max_missed >= 0, max_missed_tentative >= 0")


@dataclass
class PersonTrack:
    """State ``x = (x_m, y_m, vx_m_s, vy_m_s)`` in ``odom`` with covariance ``p`` (4x4) at
    ``time_s``: after an update, the later of the sweep's time and the track's last
    measurement's (extrapolate ``position_m + velocity_m_s * (t - time_s)`` for another t)."""

    track_id: int
    x: NDArray[np.float64]
    p: NDArray[np.float64]
    time_s: float
    hits: int = 1
    missed: int = 0
    confirmed: bool = False
    kind: int = 0  # protocol.messages.ObjectKind value set by the colour hook (0: unknown)
    history: list[tuple[float, float, float]] = field(default_factory=list)

    @property
    def position_m(self) -> NDArray[np.float64]:
        return self.x[:2].copy()

    @property
    def velocity_m_s(self) -> NDArray[np.float64]:
        return self.x[2:].copy()

    @property
    def position_cov(self) -> NDArray[np.float64]:
        return self.p[:2, :2].copy()

    @property
    def velocity_cov(self) -> NDArray[np.float64]:
        return self.p[2:, 2:].copy()


class PersonTracker:
    """Constant-velocity tracks of people in ``odom`` (see the module docstring)."""

    def __init__(self, config: TrackerConfig | None = None) -> None:
        self.config = config or TrackerConfig()
        self.tracks: list[PersonTrack] = []
        self._next_id = 1
        self.time_s: float | None = None
        self.rejected_measurements = 0

    def _predict(self, t: PersonTrack, time_s: float) -> None:
        dt = time_s - t.time_s
        if dt <= 0:
            return
        f = np.eye(4)
        f[0, 2] = f[1, 3] = dt
        q = self.config.accel_noise_m_s2**2
        g = np.array([[dt * dt / 2, 0], [0, dt * dt / 2], [dt, 0], [0, dt]])
        t.x = f @ t.x
        t.p = f @ t.p @ f.T + q * (g @ g.T)
        t.time_s = time_s

    def update(
        self,
        time_s: float,
        positions_in_odom: ArrayLike,
        *,
        measurement_times_s: ArrayLike | None = None,
    ) -> list[PersonTrack]:
        """Advance to ``time_s`` with this sweep's person positions ``(n, 2)`` (odom); returns
        the confirmed tracks. ``measurement_times_s`` ``(n,)``: when each position was
        measured (default: all at ``time_s``); a track is predicted to its measurement's
        own time before the update, so the points of a sweep need not share one instant.
        Non-finite rows are skipped and counted (``rejected_measurements``); a time earlier
        than the last is a ValueError."""
        cfg = self.config
        if not math.isfinite(time_s):
            raise ValueError(f"PersonTracker.update: time_s must be finite, got {time_s}")
        if self.time_s is not None and time_s < self.time_s:
            raise ValueError(
                f"PersonTracker.update: time_s {time_s} is before the last update {self.time_s}"
            )
        self.time_s = time_s
        z = np.asarray(positions_in_odom, dtype=np.float64).reshape(-1, 2)
        if measurement_times_s is None:
            tz = np.full(len(z), time_s)
        else:
            tz = np.asarray(measurement_times_s, dtype=np.float64).reshape(-1)
            if tz.shape[0] != z.shape[0]:
                raise ValueError(
                    f"PersonTracker.update: {tz.shape[0]} measurement times for {len(z)} positions"
                )
        ok = np.isfinite(z).all(axis=1) & np.isfinite(tz)
        self.rejected_measurements += int((~ok).sum())
        z, tz = z[ok], tz[ok]
        r = cfg.meas_sigma_m**2 * np.eye(2)
        pairs: list[tuple[float, int, int]] = []
        for i, t in enumerate(self.tracks):
            # each measurement against the track predicted to that measurement's time:
            # position covariance P_pp + dt (P_pv + P_vp) + dt^2 P_vv + q dt^4 / 4, all
            # measurements at once (closed-form 2x2 inverse)
            dt = np.maximum(tz - t.time_s, 0.0)
            d = z - (t.x[:2] + dt[:, None] * t.x[2:])
            p = t.p
            q = cfg.accel_noise_m_s2**2 * dt**4 / 4 + cfg.meas_sigma_m**2
            cross = p[:2, 2:] + p[2:, :2]
            a = p[0, 0] + dt * cross[0, 0] + dt**2 * p[2, 2] + q
            b = p[0, 1] + dt * (p[0, 3] + p[2, 1]) + dt**2 * p[2, 3]
            c = p[1, 1] + dt * cross[1, 1] + dt**2 * p[3, 3] + q
            det = a * c - b * b
            m2 = (c * d[:, 0] ** 2 - 2 * b * d[:, 0] * d[:, 1] + a * d[:, 1] ** 2) / det
            eu = np.hypot(d[:, 0], d[:, 1])
            for jj in np.flatnonzero((m2 <= cfg.gate_sigma**2) & (eu <= cfg.gate_max_m)).tolist():
                pairs.append((float(m2[jj]), i, int(jj)))
        pairs.sort()
        used_t: set[int] = set()
        used_z: set[int] = set()
        h = np.zeros((2, 4))
        h[0, 0] = h[1, 1] = 1.0
        for _, i, j in pairs:
            if i in used_t or j in used_z:
                continue
            used_t.add(i)
            used_z.add(j)
            t = self.tracks[i]
            self._predict(t, float(tz[j]))
            s = t.p[:2, :2] + r
            k = t.p[:, :2] @ np.linalg.inv(s)
            t.x = t.x + k @ (z[j] - t.x[:2])
            t.p = (np.eye(4) - k @ h) @ t.p
            t.p = 0.5 * (t.p + t.p.T)
            t.hits += 1
            t.missed = 0
            t.confirmed = t.confirmed or t.hits >= cfg.confirm_hits
            t.history.append((float(tz[j]), float(z[j, 0]), float(z[j, 1])))
            del t.history[:-20]
        keep: list[PersonTrack] = []
        for i, t in enumerate(self.tracks):
            if i not in used_t:
                t.missed += 1
            limit = cfg.max_missed if t.confirmed else cfg.max_missed_tentative
            if t.missed <= limit:
                keep.append(t)
        for j in range(len(z)):
            if j in used_z:
                continue
            p0 = np.diag(
                [cfg.meas_sigma_m**2, cfg.meas_sigma_m**2] + [cfg.init_speed_sigma_m_s**2] * 2
            )
            keep.append(
                PersonTrack(
                    self._next_id,
                    np.array([z[j, 0], z[j, 1], 0.0, 0.0]),
                    p0,
                    float(tz[j]),
                    confirmed=cfg.confirm_hits <= 1,
                    history=[(float(tz[j]), float(z[j, 0]), float(z[j, 1]))],
                )
            )
            self._next_id += 1
        # every track at least at the sweep's time: ``position_m`` is "now" for the caller
        # (a track measured later in the sweep keeps its own, later, time)
        for t in keep:
            self._predict(t, time_s)
        self.tracks = keep
        return self.confirmed()

    def confirmed(self) -> list[PersonTrack]:
        return [t for t in self.tracks if t.confirmed]

    def set_kind(self, track_id: int, kind: int) -> None:
        """The colour hook: label track ``track_id`` (an ``ObjectKind`` value, e.g. HOSTILE)."""
        for t in self.tracks:
            if t.track_id == track_id:
                t.kind = int(kind)
                return
        raise KeyError(f"no person track {track_id}")
