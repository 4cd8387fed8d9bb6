"""Stuck detection and escape: the robot is asked to move but does not (paper 5.4's "no path"
cousin).

Stuck when, for ``window_s``, the commanded speed is substantial while the pose moved less
than ``min_progress_m`` and turned less than ``min_turn_rad``. The body refuses a motion its
LIDAR map cannot explain: a drop-off (the map sees no negative obstacles, paper 5.3: a robot
on the small world's loading dock drove at its edge for 120 s), a door jamb the map places a
few centimetres off that a turning corner catches (seed 7: a robot wedged diagonally in a
doorway from 205 s, every clockwise turn and straight move refused, a counter-clockwise turn
free). Two things follow from each detection (issue 14):

* **escape** (:attr:`StuckDetector.escape_command`): backing up straight, the old recovery,
  is the first of a sequence; each further detection within ``escape_reset_m`` of the last
  tries the next motion, turning *against* the turn that was refused (the follower always
  turns the short way, into the jamb again), reversing then going forward:
  ``(-v, 0)``, ``(-v, +w)``, ``(+v, +w)``, ``(-v, -w)``, ``(+v, -w)`` with ``+w`` opposite the
  refused turn; a detection farther away starts over.
* **memory of refused ground** (:meth:`StuckDetector.blocked_mask`): a refused *translation*
  marks a strip across the way it pushed, ``mark_ahead_m`` ahead of the body's centre (behind
  when reversing), ``2 * mark_half_width_m`` wide, for ``remember_s``: the planner then treats
  it as an obstacle (the terrain map's 15 s memory, and the map cleared on each detection,
  never held it), and plans another way (the dock's ramp) instead of re-driving into the
  same edge. Marks are in the robot's ``odom``; ``remember_s`` is short enough for its drift.

Pure logic over poses in ``odom`` (metres, radians, seconds); the node feeds every control
period and applies the escape for its back-up time.
"""

from __future__ import annotations

import math
from collections import deque

import msgspec
import numpy as np
from numpy.typing import NDArray

from robot.terrain.grid import GridGeometry

__all__ = ["StuckConfig", "StuckDetector"]


class StuckConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Detection: ``window_s``, ``min_command_m_s``, ``min_progress_m``, ``min_turn_rad``.
    Escape: ``escape_speed_m_s`` and ``escape_turn_rad_s`` of the escape motions,
    ``escape_reset_m`` (module docstring). Memory: ``mark_ahead_m`` (the footprint's front is
    0.3 m ahead of its centre), ``mark_half_width_m``, ``remember_s``, ``max_marks``
    (``remember_s = 0``: no memory). The strip is 2 m wide: what refuses a body is mostly
    an edge or a wall (0.6 m strips took the dock's robot along its edge and never off it in
    300 s; 2 m strips got it down the ramp 95 s after it was trapped, seed 0)."""

    window_s: float = 4.0
    min_command_m_s: float = 0.2
    min_progress_m: float = 0.15
    min_turn_rad: float = 0.2
    escape_speed_m_s: float = 0.3
    escape_turn_rad_s: float = 0.6
    escape_reset_m: float = 1.0
    mark_ahead_m: float = 0.45
    mark_half_width_m: float = 1.0
    remember_s: float = 90.0
    max_marks: int = 64

    def __post_init__(self) -> None:
        for name in ("window_s", "escape_reset_m", "mark_ahead_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"stuck.{name} must be finite and > 0, got {v}")
        for name in (
            "min_command_m_s",
            "min_progress_m",
            "min_turn_rad",
            "escape_speed_m_s",
            "escape_turn_rad_s",
            "mark_half_width_m",
            "remember_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"stuck.{name} must be finite and >= 0, got {v}")
        if self.max_marks < 1:
            raise ValueError(f"stuck.max_marks must be >= 1, got {self.max_marks}")


class StuckDetector:
    """See the module docstring. :meth:`update` every control period; on True, drive
    :attr:`escape_command` for the back-up time and plan with :meth:`blocked_mask`."""

    def __init__(self, config: StuckConfig | None = None) -> None:
        self.config = config or StuckConfig()
        self._hist: deque[tuple[float, float, float, float, float, float]] = deque()
        #: the motion to try now, ``(linear_m_s, angular_rad_s)`` (set by each detection)
        self.escape_command: tuple[float, float] = (-self.config.escape_speed_m_s, 0.0)
        self._escapes = 0  # detections in a row near _last_xy
        self._last_xy: NDArray[np.float64] | None = None
        # (x, y, push direction rad, when) in odom: where a translation was refused
        self._marks: deque[tuple[float, float, float, float]] = deque(maxlen=self.config.max_marks)

    @property
    def marks_in_odom(self) -> NDArray[np.float64]:
        """``(K, 4)``: ``(x, y, direction_rad, time_s)`` of each remembered refusal."""
        return np.array(self._marks, dtype=np.float64).reshape(-1, 4)

    def update(
        self, t_s: float, pose_in_odom: np.ndarray, commanded_m_s: float, commanded_rad_s: float
    ) -> bool:
        """Record one control period; True when the robot is stuck (then
        :attr:`escape_command` is the motion to try, and a refused translation is marked)."""
        cfg = self.config
        x, y, th = (float(v) for v in pose_in_odom)
        trying = (
            abs(commanded_m_s) >= cfg.min_command_m_s
            or abs(commanded_rad_s) >= 2 * cfg.min_turn_rad
        )
        if not trying:
            self._hist.clear()
            return False
        self._hist.append((t_s, x, y, th, commanded_m_s, commanded_rad_s))
        while self._hist and self._hist[0][0] < t_s - cfg.window_s:
            self._hist.popleft()
        t0, x0, y0, th0, _, _ = self._hist[0]
        if t_s - t0 < 0.95 * cfg.window_s:
            return False
        moved = math.hypot(x - x0, y - y0)
        turned = abs(math.remainder(th - th0, 2 * math.pi))
        stuck = moved < cfg.min_progress_m and turned < cfg.min_turn_rad
        if stuck:
            self._on_stuck(t_s, np.array([x, y]), th)
        return stuck

    def _on_stuck(self, t_s: float, xy: NDArray[np.float64], yaw_rad: float) -> None:
        cfg = self.config
        cmds = np.array([(h[4], h[5]) for h in self._hist])
        v_mean = float(cmds[:, 0].mean())
        w_mean = float(cmds[:, 1].mean())
        if self._last_xy is None or float(np.hypot(*(xy - self._last_xy))) > cfg.escape_reset_m:
            self._escapes = 0
        self._last_xy = xy.copy()
        # +w turns against the refused turn (counter-clockwise when none was asked)
        s = -1.0 if w_mean > 0.05 else 1.0
        v, w = cfg.escape_speed_m_s, s * cfg.escape_turn_rad_s
        sequence = ((-v, 0.0), (-v, w), (v, w), (-v, -w), (v, -w))
        self.escape_command = sequence[self._escapes % len(sequence)]
        self._escapes += 1
        if cfg.remember_s > 0 and abs(v_mean) >= cfg.min_command_m_s:
            push = yaw_rad if v_mean > 0 else yaw_rad + math.pi
            self._marks.append((float(xy[0]), float(xy[1]), push, t_s))

    def has_live_marks(self, now_s: float) -> bool:
        """Whether any refusal is remembered at ``now_s`` (within ``remember_s`` before it):
        without one :meth:`blocked_mask` is all False, and a caller can skip building it."""
        remember_s = self.config.remember_s
        return any(0.0 <= now_s - t <= remember_s for _, _, _, t in self._marks)

    def blocked_mask(self, geometry: GridGeometry, now_s: float) -> NDArray[np.bool_]:
        """Cells of the grid laid out by ``geometry`` (in ``odom``) that refused translations
        within ``remember_s`` before ``now_s`` mark: a strip ``2 * mark_half_width_m`` wide
        across the push direction, ``mark_ahead_m`` ahead of where the robot stood."""
        cfg = self.config
        out = np.zeros(geometry.shape, dtype=bool)
        res = geometry.resolution_m
        step = 0.5 * res
        offsets = np.arange(-cfg.mark_half_width_m, cfg.mark_half_width_m + 1e-9, step)
        depth = np.arange(0.0, 2 * res + 1e-9, step)  # two cells deep: no gap to slip through
        for x, y, push, t in self._marks:
            if now_s - t > cfg.remember_s or t > now_s:
                continue
            fwd = np.array([math.cos(push), math.sin(push)])
            left = np.array([-fwd[1], fwd[0]])
            along = cfg.mark_ahead_m + depth
            pts = (
                np.array([x, y]) + along[:, None, None] * fwd + offsets[None, :, None] * left
            ).reshape(-1, 2)
            rc = geometry.cell_of(pts)
            ok = (
                (rc[:, 0] >= 0)
                & (rc[:, 0] < geometry.rows)
                & (rc[:, 1] >= 0)
                & (rc[:, 1] < geometry.cols)
            )
            out[rc[ok, 0], rc[ok, 1]] = True
        return out

    def reset(self) -> None:
        """Forget the window (after a detection, or a pause); the escape sequence and the
        marks are kept."""
        self._hist.clear()
