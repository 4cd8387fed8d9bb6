"""The image memory of a continuously panning camera (paper 5.2.1, Fig. 13).

Panning towards an object once the LIDAR flags it would take a second or more, so the camera
pans all the time and the robot remembers its recent frames: for each, the time, the camera
pan and tilt, and the robot's pose in ``odom``. For a LIDAR candidate (an upright cylinder in
``odom``) :meth:`ImageMemory.choose` returns the newest remembered frame in which the object
projects *fully* inside the image (Fig. 13: object 1 -> image B, not the partial A; object 2
-> D, the newer of C and D); the node then asks the driver for that frame's image
(:class:`protocol.sensors.ImageRequest` with the frame's ``time_s``).

Pure: no I/O; frames older than ``history_s`` before the newest are forgotten.
"""

from __future__ import annotations

import bisect
import functools
import math
from dataclasses import dataclass

import msgspec
import numpy as np

from robot.perception.camera_model import CameraMountConfig, Intrinsics, project_in_base

__all__ = ["Candidate", "ImageMemory", "ImageMemoryConfig", "RememberedFrame", "cylinder_outline"]


class ImageMemoryConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``history_s``: how long frames are remembered (the driver's own history bounds what
    can be asked for: the simulator keeps ``camera.history_s`` = 20 s). ``margin_px``: an
    object must stay this far inside the image border. ``min_depth_m`` / ``max_range_m``:
    nearer or farther objects are not tested in that frame. ``width_px``/``height_px``/
    ``hfov_deg``: the images the node will request (pinhole, principal point at the centre).

    240 x 180 instead of 320 x 240 (the periodic tag images and the far colour tests; issue
    14, session 15, quick mission at 8183549, thread CPU at load 10-16): seeds 0 / 7 108.5 /
    100.3 CPU-s a run against 120.8 / 124.8 (render worker 22-23 -> 14-15), but seed 0 took
    a false closure (0 before) and seed 7 explored 0.871 (0.917), ATE 0.314 m (0.188). The
    tag images every 2 s alone (``PerceptionConfig.fiducial_period_s``): 109.9 / 114.0 CPU-s,
    ATE 0.342 / 0.332 m (0.166 / 0.188), a false closure on seed 0. Both stay as they are."""

    history_s: float = 15.0
    margin_px: float = 2.0
    min_depth_m: float = 0.3
    max_range_m: float = 12.0
    width_px: int = 320
    height_px: int = 240
    hfov_deg: float = 60.0
    mount: CameraMountConfig = CameraMountConfig()

    def __post_init__(self) -> None:
        if not 0 < self.history_s <= 600:
            raise ValueError(f"history_s must be in (0, 600], got {self.history_s}")
        if not 16 <= self.width_px <= 2048 or not 16 <= self.height_px <= 2048:
            raise ValueError("width_px and height_px must be in [16, 2048]")
        if not 10 <= self.hfov_deg <= 150:
            raise ValueError(f"hfov_deg must be in [10, 150], got {self.hfov_deg}")

    def intrinsics(self) -> Intrinsics:
        fx = self.width_px / 2 / math.tan(math.radians(self.hfov_deg) / 2)
        return Intrinsics(
            fx, fx, self.width_px / 2, self.height_px / 2, self.width_px, self.height_px
        )


@dataclass(frozen=True)
class RememberedFrame:
    """One frame of the panning camera: when, where the camera pointed, where the robot was."""

    time_s: float
    pan_rad: float
    tilt_rad: float
    pose_in_odom: tuple[float, float, float]


@dataclass(frozen=True)
class Candidate:
    """A LIDAR candidate: an upright cylinder standing at ``xy_in_odom`` from ``bottom_z_m``
    (in ``base`` height: 0 is the ground under the robot) up ``height_m``."""

    xy_in_odom: tuple[float, float]
    radius_m: float
    height_m: float
    bottom_z_m: float = 0.0


@functools.lru_cache(maxsize=8)
def _rim_angles(n: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of ``n`` angles around a rim (read-only: shared by every call)."""
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    cos_a, sin_a = np.cos(a), np.sin(a)
    cos_a.flags.writeable = False
    sin_a.flags.writeable = False
    return cos_a, sin_a


def cylinder_outline(
    c: Candidate, pose_in_odom: tuple[float, float, float], n: int = 12
) -> np.ndarray:
    """``(2n, 3)`` points in ``base`` (at ``pose_in_odom``) on the rims of the cylinder."""
    x, y, yaw = pose_in_odom
    cy, sy = math.cos(yaw), math.sin(yaw)
    dx, dy = c.xy_in_odom[0] - x, c.xy_in_odom[1] - y
    bx, by = cy * dx + sy * dy, -sy * dx + cy * dy
    cos_a, sin_a = _rim_angles(n)
    ring = np.stack([bx + c.radius_m * cos_a, by + c.radius_m * sin_a], axis=1)
    bot = np.column_stack([ring, np.full(n, c.bottom_z_m)])
    top = np.column_stack([ring, np.full(n, c.bottom_z_m + c.height_m)])
    return np.vstack([bot, top])


_ASIDE_MIN_RANGE_M = 1.0
_ASIDE_MARGIN_RAD = math.radians(15.0)
_ASIDE_MAX_TILT_RAD = 0.3


class ImageMemory:
    """Recent frames of the panning camera, oldest first (see the module docstring)."""

    def __init__(self, config: ImageMemoryConfig | None = None) -> None:
        self.config = config or ImageMemoryConfig()
        self._intrinsics = self.config.intrinsics()  # the same every call: computed once
        self._frames: list[RememberedFrame] = []
        self._times: list[float] = []
        self.out_of_order = 0  # frames refused: older than the newest remembered

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def frames(self) -> tuple[RememberedFrame, ...]:
        return tuple(self._frames)

    def record(self, frame: RememberedFrame) -> bool:
        """Remember ``frame``; refuses (False, counted) a non-finite or out-of-order one."""
        vals = (frame.time_s, frame.pan_rad, frame.tilt_rad, *frame.pose_in_odom)
        if not all(math.isfinite(v) for v in vals) or (
            self._times and frame.time_s <= self._times[-1]
        ):
            self.out_of_order += 1
            return False
        self._frames.append(frame)
        self._times.append(frame.time_s)
        cut = bisect.bisect_left(self._times, frame.time_s - self.config.history_s)
        if cut:
            del self._frames[:cut]
            del self._times[:cut]
        return True

    def projects_fully(self, frame: RememberedFrame, candidate: Candidate) -> bool:
        """Whether every rim point of ``candidate`` lands inside the image of ``frame``."""
        cfg = self.config
        if self._clearly_aside(frame, candidate):
            return False
        pts = cylinder_outline(candidate, frame.pose_in_odom)
        rng = float(np.hypot(pts[:, 0].mean(), pts[:, 1].mean()))
        if rng > cfg.max_range_m:
            return False
        intr = self._intrinsics
        uv, depth = project_in_base(
            pts, frame.pan_rad, frame.tilt_rad, intr, cfg.mount.camera_in_base_m
        )
        if np.any(depth < cfg.min_depth_m):
            return False
        m = cfg.margin_px
        return bool(
            np.all(uv[:, 0] >= m)
            and np.all(uv[:, 0] <= intr.width_px - m)
            and np.all(uv[:, 1] >= m)
            and np.all(uv[:, 1] <= intr.height_px - m)
        )

    def _clearly_aside(self, frame: RememberedFrame, candidate: Candidate) -> bool:
        """A necessary-condition test before the projection (issue 16: a sweep's candidates
        were projected into every remembered frame, newest first, most pointing elsewhere):
        True when the candidate's centre, at least ``_ASIDE_MIN_RANGE_M`` from the camera,
        lies beyond half the field of view plus its angular radius plus ``_ASIDE_MARGIN_RAD``
        from the camera's pan (the tilt bends the image's horizontal angle by less than
        that margin there, for tilts within ``_ASIDE_MAX_TILT_RAD``): then not every rim
        point lands in the image."""
        if abs(frame.tilt_rad) > _ASIDE_MAX_TILT_RAD:
            return False
        x, y, yaw = frame.pose_in_odom
        c, s_ = math.cos(yaw), math.sin(yaw)
        dx, dy = candidate.xy_in_odom[0] - x, candidate.xy_in_odom[1] - y
        cam = self.config.mount.camera_in_base_m
        bx, by = c * dx + s_ * dy - cam[0], -s_ * dx + c * dy - cam[1]
        h = math.hypot(bx, by)
        if h - candidate.radius_m < _ASIDE_MIN_RANGE_M:
            return False
        off = abs((math.atan2(by, bx) - frame.pan_rad + math.pi) % (2 * math.pi) - math.pi)
        half = math.radians(self.config.hfov_deg) / 2
        return off > half + math.asin(min(1.0, candidate.radius_m / h)) + _ASIDE_MARGIN_RAD

    def choose(
        self, candidate: Candidate, *, not_after_s: float = math.inf
    ) -> RememberedFrame | None:
        """The newest frame (at or before ``not_after_s``) in which ``candidate`` projects
        fully, or None (Fig. 13)."""
        for frame in reversed(self._frames):
            if frame.time_s <= not_after_s and self.projects_fully(frame, candidate):
                return frame
        return None
