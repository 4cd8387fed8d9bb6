"""The continuously panning camera and its image memory (paper 3.1, 5.2.1, Fig. 13).

The camera sits on a pan-tilt unit above the head and pans back and forth without stopping
(a triangle wave between ``-pan_limit_rad`` and ``+pan_limit_rad`` at ``pan_rate_rad_s``, each
robot with its own phase) at a fixed tilt. Its pose at any time is a pure function of the
robot's recorded ``world_from_base`` at that time, so the simulator can render, on request,
the image the camera would have taken at any recorded time (the robot node keeps the memory
of *when*; the simulator renders *what*): the robots and people are put back where they were,
the scene is rendered with PyBullet's TinyRenderer, and everything is put back.

Intrinsics: pinhole, square pixels, principal point at the centre, horizontal field of view
``hfov_deg`` (about 60 deg for MAGIC's Firefly MV with its lens).
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

__all__ = ["CameraConfig", "camera_axes", "intrinsics", "pan_angle"]


class CameraConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    hfov_deg: float = 60.0
    pan_rate_rad_s: float = 1.6
    pan_limit_rad: float = 2.6
    tilt_rad: float = -0.12
    history_s: float = 20.0
    near_m: float = 0.05
    far_m: float = 80.0

    def __post_init__(self) -> None:
        if not 10.0 <= self.hfov_deg <= 150.0:
            raise ValueError(f"hfov_deg must be in [10, 150], got {self.hfov_deg}")
        if not (math.isfinite(self.pan_rate_rad_s) and self.pan_rate_rad_s >= 0):
            raise ValueError(f"pan_rate_rad_s must be >= 0, got {self.pan_rate_rad_s}")
        if not 0 <= self.pan_limit_rad <= math.pi:
            raise ValueError(f"pan_limit_rad must be in [0, pi], got {self.pan_limit_rad}")
        if not abs(self.tilt_rad) < 1.5:
            raise ValueError(f"tilt_rad must be in (-1.5, 1.5), got {self.tilt_rad}")
        if not 0 < self.history_s <= 600:
            raise ValueError(f"history_s must be in (0, 600], got {self.history_s}")


def pan_angle(time_s: float, config: CameraConfig, *, phase_s: float = 0.0) -> float:
    """Pan (rad, relative to ``base``) at ``time_s``: a triangle wave of amplitude
    ``pan_limit_rad`` and slope ``pan_rate_rad_s``."""
    lim = config.pan_limit_rad
    if lim == 0 or config.pan_rate_rad_s == 0:
        return 0.0
    period = 4 * lim / config.pan_rate_rad_s
    u = ((time_s + phase_s) % period) / period  # 0..1
    # 0 -> 0, 0.25 -> +lim, 0.75 -> -lim, 1 -> 0
    tri = 4 * u if u < 0.25 else (2 - 4 * u if u < 0.75 else 4 * u - 4)
    return float(lim * tri)


def intrinsics(
    width_px: int, height_px: int, config: CameraConfig
) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` in pixels."""
    fx = width_px / 2 / math.tan(math.radians(config.hfov_deg) / 2)
    return fx, fx, width_px / 2, height_px / 2


def camera_axes(
    world_from_base: np.ndarray, camera_in_base_m: np.ndarray, pan_rad: float, tilt_rad: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eye position, forward and up unit vectors in ``world`` for one ``(4, 4)`` pose."""
    rot = world_from_base[:3, :3]
    eye = rot @ camera_in_base_m + world_from_base[:3, 3]
    cp, sp = math.cos(pan_rad), math.sin(pan_rad)
    ct, st = math.cos(tilt_rad), math.sin(tilt_rad)
    fwd = rot @ np.array([cp * ct, sp * ct, st])
    up = rot @ np.array([-cp * st, -sp * st, ct])
    return eye, fwd, up
