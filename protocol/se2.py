"""Vectorized SE(2) for the frames of DESIGN section 3.

A pose ``(x_m, y_m, yaw_rad)`` is the transform ``a_from_b``: it maps points expressed in frame
``b`` into frame ``a``. Every function takes a single pose of shape ``(3,)`` or a batch of
shape ``(N, 3)`` (broadcasting between the two) and returns float64 arrays. Angles in results
are wrapped to ``[-pi, pi)``. Conventions match ``gtsam.Pose2``: ``compose(a, b)`` is
``a * b``, ``relative(a, b)`` is ``a.between(b)`` = ``inverse(a) * b``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["compose", "inverse", "relative", "transform_points", "wrap_angle"]

Array = NDArray[np.float64]


def wrap_angle(theta_rad: ArrayLike) -> Array:
    """Wrap angles to ``[-pi, pi)``."""
    t = np.asarray(theta_rad, dtype=np.float64)
    w = (t + np.pi) % (2.0 * np.pi) - np.pi
    # The modulo of a tiny negative number rounds up to 2 pi, giving pi: map it to -pi.
    return w - 2.0 * np.pi * (w >= np.pi)  # type: ignore[no-any-return]


def _poses(p: ArrayLike, name: str) -> Array:
    a = np.asarray(p, dtype=np.float64)
    if a.shape[-1:] != (3,) or a.ndim > 2:
        raise ValueError(f"{name}: expected a pose (3,) or poses (N, 3), got shape {a.shape}")
    return a


def _same_batch(a: Array, name_a: str, b: Array, name_b: str) -> None:
    if a.ndim == 2 and b.ndim == 2 and len(a) != len(b) and 1 not in (len(a), len(b)):
        raise ValueError(f"{name_b}: {len(b)} poses do not match the {len(a)} of {name_a}")


def compose(a_from_b: ArrayLike, b_from_c: ArrayLike) -> Array:
    """``a_from_c = a_from_b * b_from_c``."""
    ab = _poses(a_from_b, "a_from_b")
    bc = _poses(b_from_c, "b_from_c")
    _same_batch(ab, "a_from_b", bc, "b_from_c")
    c, s = np.cos(ab[..., 2]), np.sin(ab[..., 2])
    x = ab[..., 0] + c * bc[..., 0] - s * bc[..., 1]
    y = ab[..., 1] + s * bc[..., 0] + c * bc[..., 1]
    return np.stack([x, y, wrap_angle(ab[..., 2] + bc[..., 2])], axis=-1)


def inverse(a_from_b: ArrayLike) -> Array:
    """``b_from_a``."""
    ab = _poses(a_from_b, "a_from_b")
    c, s = np.cos(ab[..., 2]), np.sin(ab[..., 2])
    x = -c * ab[..., 0] - s * ab[..., 1]
    y = s * ab[..., 0] - c * ab[..., 1]
    return np.stack([x, y, wrap_angle(-ab[..., 2])], axis=-1)


def relative(world_from_a: ArrayLike, world_from_b: ArrayLike) -> Array:
    """``a_from_b = inverse(world_from_a) * world_from_b`` (gtsam's ``between``)."""
    wa = _poses(world_from_a, "world_from_a")
    wb = _poses(world_from_b, "world_from_b")
    _same_batch(wa, "world_from_a", wb, "world_from_b")
    c, s = np.cos(wa[..., 2]), np.sin(wa[..., 2])
    dx = wb[..., 0] - wa[..., 0]
    dy = wb[..., 1] - wa[..., 1]
    return np.stack(
        [c * dx + s * dy, -s * dx + c * dy, wrap_angle(wb[..., 2] - wa[..., 2])], axis=-1
    )


def transform_points(a_from_b: ArrayLike, points_in_b: ArrayLike) -> Array:
    """Map points ``(N, 2)`` (or ``(2,)``) from frame ``b`` into frame ``a`` by one pose."""
    ab = np.asarray(a_from_b, dtype=np.float64)
    if ab.shape != (3,):
        raise ValueError(f"a_from_b: expected one pose of shape (3,), got {ab.shape}")
    pts = np.asarray(points_in_b, dtype=np.float64)
    if pts.shape[-1:] != (2,) or pts.ndim > 2:
        raise ValueError(f"points_in_b: expected (2,) or (N, 2), got shape {pts.shape}")
    c, s = np.cos(ab[2]), np.sin(ab[2])
    rot = np.array([[c, -s], [s, c]])
    return pts @ rot.T + ab[:2]
