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

Frames with nothing to find (issue 16: renders grew with the team, about 650 a mission-second
at 64 robots, most of the simulator's CPU). A robot's perception looks in an image for things
only: objects of interest, people, teammates' tags, and the clutter its LIDAR may take for a
candidate (trunks, posts, cars). When none of them is in the camera's frustum (bounding
spheres, :func:`in_frustum`) within ``subject_range_m`` (a teammate: within the range where its
tag still spans ``min_tag_px`` pixels), the frame holds terrain only (ground, walls, roofs,
fences) and the simulator answers with a flat image of ``empty_rgb`` instead of rendering it
(``skip_empty``; False: always render). The choice is a pure function of the recorded frame,
so runs stay repeatable.
"""

from __future__ import annotations

import math

import msgspec
import numpy as np

__all__ = ["CameraConfig", "camera_axes", "in_frustum", "intrinsics", "pan_angle"]


class CameraConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    hfov_deg: float = 60.0
    pan_rate_rad_s: float = 1.6
    pan_limit_rad: float = 2.6
    tilt_rad: float = -0.12
    history_s: float = 20.0
    near_m: float = 0.05
    far_m: float = 80.0
    # frames with nothing to find (module docstring): the robots' colour tests stop at 12 m
    # (robot.perception.image_memory), a tag needs about one pixel per cell (8) to decode
    skip_empty: bool = True
    subject_range_m: float = 25.0
    min_tag_px: float = 8.0
    empty_rgb: tuple[int, int, int] = (128, 128, 128)

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
        if not (math.isfinite(self.subject_range_m) and self.subject_range_m > 0):
            raise ValueError(f"subject_range_m must be > 0, got {self.subject_range_m}")
        if not (math.isfinite(self.min_tag_px) and self.min_tag_px > 0):
            raise ValueError(f"min_tag_px must be > 0, got {self.min_tag_px}")
        if len(self.empty_rgb) != 3 or not all(0 <= int(c) <= 255 for c in self.empty_rgb):
            raise ValueError(f"empty_rgb must be three values in [0, 255], got {self.empty_rgb}")


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


def in_frustum(
    eye_m: np.ndarray,
    forward: np.ndarray,
    up: np.ndarray,
    *,
    hfov_rad: float,
    vfov_rad: float,
    near_m: float,
    centers_m: np.ndarray,
    radii_m: np.ndarray,
    ranges_m: np.ndarray,
) -> np.ndarray:
    """Which spheres (``centers_m (N, 3)``, ``radii_m (N,)``) may show in a pinhole camera at
    ``eye_m`` looking along ``forward`` (``up`` its image's up) with full fields of view
    ``hfov_rad`` x ``vfov_rad``, nearer than ``ranges_m (N,)`` (sphere surface) and beyond
    ``near_m``: boolean ``(N,)``. Conservative: a sphere that touches the frustum counts."""
    centers = np.asarray(centers_m, dtype=float).reshape(-1, 3)
    r = np.asarray(radii_m, dtype=float).reshape(-1)
    d = centers - np.asarray(eye_m, dtype=float)
    f = np.asarray(forward, dtype=float)
    u = np.asarray(up, dtype=float)
    right = np.cross(f, u)
    z = d @ f
    x = np.abs(d @ right)
    y = np.abs(d @ u)
    th, tv = math.tan(hfov_rad / 2), math.tan(vfov_rad / 2)
    # a side plane through the eye at half-angle a: distance of the centre outside it is
    # |x| cos a - z sin a; the sphere touches the inside when that is <= r
    ch, cv = math.cos(hfov_rad / 2), math.cos(vfov_rad / 2)
    inside_h = x * ch - z * th * ch <= r
    inside_v = y * cv - z * tv * cv <= r
    near = z >= near_m - r
    close = np.sqrt(np.einsum("ij,ij->i", d, d)) - r <= np.asarray(ranges_m, dtype=float)
    return inside_h & inside_v & near & close
