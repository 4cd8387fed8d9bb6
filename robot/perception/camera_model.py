"""The robot's pan-tilt camera as a pinhole model: where a point in ``base`` lands in an image.

The camera sits at ``camera_in_base_m`` on the pan-tilt unit (paper 3.1, Fig. 8b) and pans
about ``base`` z then tilts (elevation); the frame of a :class:`protocol.sensors.CameraImage`
states its pan, tilt and intrinsics, so nothing here guesses them. Camera frame (OpenCV):
x right, y down, z along the optical axis.

The pan schedule (the camera pans continuously, a triangle wave between ``-pan_limit_rad`` and
``+pan_limit_rad`` at ``pan_rate_rad_s``, paper 5.2.1) is the robot's sensor config; its phase
is learnt from the ``(time_s, camera_pan_rad)`` of images received (:func:`fit_pan_phase`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import msgspec
import numpy as np

__all__ = [
    "CameraMountConfig",
    "Intrinsics",
    "base_from_camera",
    "fit_pan_phase",
    "pan_at",
    "project_in_base",
]


class CameraMountConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The robot's camera: mount point in ``base`` and pan schedule (the MAGIC robot's: the
    simulator's robot geometry and camera config, checked equal in the tests)."""

    camera_in_base_m: tuple[float, float, float] = (-0.12, 0.0, 0.92)
    pan_rate_rad_s: float = 1.6
    pan_limit_rad: float = 2.6
    tilt_rad: float = -0.12

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in self.camera_in_base_m):
            raise ValueError(f"camera_in_base_m must be finite, got {self.camera_in_base_m}")
        if not (math.isfinite(self.pan_rate_rad_s) and self.pan_rate_rad_s >= 0):
            raise ValueError(f"pan_rate_rad_s must be >= 0, got {self.pan_rate_rad_s}")
        if not 0 <= self.pan_limit_rad <= math.pi:
            raise ValueError(f"pan_limit_rad must be in [0, pi], got {self.pan_limit_rad}")


class Intrinsics(msgspec.Struct, frozen=True):
    """Pinhole intrinsics (pixels) and image size."""

    fx_px: float
    fy_px: float
    cx_px: float
    cy_px: float
    width_px: int
    height_px: int

    def matrix(self) -> np.ndarray:
        return np.array(
            [[self.fx_px, 0.0, self.cx_px], [0.0, self.fy_px, self.cy_px], [0.0, 0.0, 1.0]]
        )


def base_from_camera(
    pan_rad: float, tilt_rad: float, camera_in_base_m: Sequence[float]
) -> np.ndarray:
    """``(4, 4)`` transform taking camera-frame (OpenCV) points to ``base``."""
    cp, sp = math.cos(pan_rad), math.sin(pan_rad)
    ct, st = math.cos(tilt_rad), math.sin(tilt_rad)
    f0, f1, f2 = cp * ct, sp * ct, st
    u0, u1, u2 = -cp * st, -sp * st, ct
    fwd = np.array([f0, f1, f2])
    up = np.array([u0, u1, u2])
    # fwd x up, written out: the same products and differences as np.cross (bit for bit)
    # without its dispatch, which dominated this function (called per frame and candidate)
    right = np.array([f1 * u2 - f2 * u1, f2 * u0 - f0 * u2, f0 * u1 - f1 * u0])
    m = np.eye(4)
    m[:3, 0] = right
    m[:3, 1] = -up
    m[:3, 2] = fwd
    m[:3, 3] = camera_in_base_m
    return m


def project_in_base(
    points_in_base: np.ndarray,
    pan_rad: float,
    tilt_rad: float,
    intrinsics: Intrinsics,
    camera_in_base_m: Sequence[float],
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels ``(N, 2)`` (u right, v down) and depths ``(N,)`` (m along the optical axis) of
    ``(N, 3)`` points in ``base``. A depth <= 0 means behind the camera (pixel meaningless)."""
    p = np.asarray(points_in_base, dtype=float).reshape(-1, 3)
    m = base_from_camera(pan_rad, tilt_rad, camera_in_base_m)
    cam = (p - m[:3, 3]) @ m[:3, :3]
    z = cam[:, 2]
    safe = np.where(z > 1e-9, z, 1e-9)
    u = intrinsics.fx_px * cam[:, 0] / safe + intrinsics.cx_px
    v = intrinsics.fy_px * cam[:, 1] / safe + intrinsics.cy_px
    return np.stack([u, v], axis=1), z


def pan_at(time_s: float, config: CameraMountConfig, phase_s: float) -> float:
    """Pan (rad) of the triangle-wave schedule at ``time_s`` with phase ``phase_s``."""
    lim, rate = config.pan_limit_rad, config.pan_rate_rad_s
    if lim == 0 or rate == 0:
        return 0.0
    period = 4 * lim / rate
    u = ((time_s + phase_s) % period) / period
    tri = 4 * u if u < 0.25 else (2 - 4 * u if u < 0.75 else 4 * u - 4)
    return float(lim * tri)


def fit_pan_phase(
    samples: Sequence[tuple[float, float]], config: CameraMountConfig, *, step_s: float = 0.01
) -> tuple[float, float]:
    """The phase (s) of the pan schedule that best explains ``(time_s, pan_rad)`` samples
    (e.g. from received images) and its RMS residual (rad). One sample leaves two phases
    (panning left or right); two samples a few tenths of a second apart settle it."""
    if not samples:
        raise ValueError("fit_pan_phase: no (time_s, pan_rad) samples")
    lim, rate = config.pan_limit_rad, config.pan_rate_rad_s
    if lim == 0 or rate == 0:
        return 0.0, float(np.sqrt(np.mean([p**2 for _, p in samples])))
    period = 4 * lim / rate
    phases = np.arange(0.0, period, step_s)
    t = np.array([s[0] for s in samples])
    p = np.array([s[1] for s in samples])
    u = ((t[None, :] + phases[:, None]) % period) / period
    tri = np.where(u < 0.25, 4 * u, np.where(u < 0.75, 2 - 4 * u, 4 * u - 4)) * lim
    err = np.sqrt(np.mean((tri - p[None, :]) ** 2, axis=1))
    k = int(np.argmin(err))
    return float(phases[k]), float(err[k])
