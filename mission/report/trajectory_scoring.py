"""The GCS's pose graph scored against the true trajectories (issue 14 item 3; paper 7).

* :func:`interpolate_poses`: a robot's true pose at any time from a recorded truth track
  (positions linear, heading along the shorter arc), so that every pose node can be scored
  at its own time (a node's time is its sweep's end, not the step that delivered it).
* :func:`closure_errors`: each accepted loop closure's ``a_from_b`` against the true relative
  pose of its two nodes; a *false* closure is off by more than ``max_m`` or ``max_rad`` (the
  issue's 0.5 m / 5 deg).
* ATE RMSE is :func:`mission.team_mapping.ate_rmse_m` (rigid 2D alignment, no scale),
  re-exported here; :func:`rigid_world_from_map` is that alignment as a pose, so that the map
  can be scored in it too (``occupancy_f1_aligned``: the map's shape apart from where the
  GCS's frame was anchored).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from mission.team_mapping import ate_rmse_m
from protocol.se2 import relative, wrap_angle

__all__ = [
    "ate_rmse_m",
    "closure_errors",
    "false_closures",
    "interpolate_poses",
    "rigid_world_from_map",
]


def interpolate_poses(
    times_s: NDArray[np.float64], poses: NDArray[np.float64], query_s: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Poses ``(M, 3)`` at ``query_s`` ``(M,)`` from a track ``times_s`` ``(N,)`` (increasing)
    and ``poses`` ``(N, 3)``; queries outside the track take its end poses. NaN poses (a robot
    not yet or no longer tracked) propagate."""
    t = np.asarray(times_s, dtype=np.float64)
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    q = np.asarray(query_s, dtype=np.float64).reshape(-1)
    if len(t) == 0:
        return np.full((len(q), 3), np.nan)
    if len(t) == 1:
        return np.repeat(p[:1], len(q), axis=0)
    j = np.clip(np.searchsorted(t, q), 1, len(t) - 1)
    t0, t1 = t[j - 1], t[j]
    w = np.clip((q - t0) / np.maximum(t1 - t0, 1e-12), 0.0, 1.0)[:, None]
    a, b = p[j - 1], p[j]
    xy = a[:, :2] + w * (b[:, :2] - a[:, :2])
    yaw = wrap_angle(a[:, 2] + w[:, 0] * wrap_angle(b[:, 2] - a[:, 2]))
    return np.column_stack([xy, yaw])


def rigid_world_from_map(
    map_from_base: NDArray[np.float64], world_from_base: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``world_from_map`` ``(3,)``: the rigid 2D transform (Umeyama without scale, as
    :func:`ate_rmse_m`) that takes the estimated positions ``map_from_base`` ``(N, 3)`` closest
    to the true ``world_from_base`` ``(N, 3)`` in least squares."""
    e = np.asarray(map_from_base, dtype=np.float64)[:, :2]
    t = np.asarray(world_from_base, dtype=np.float64)[:, :2]
    me, mt = e.mean(axis=0), t.mean(axis=0)
    u, _, vt = np.linalg.svd((e - me).T @ (t - mt))
    d = np.sign(np.linalg.det(u @ vt))
    r = (u @ np.diag([1.0, d]) @ vt).T
    xy = mt - r @ me
    return np.array([xy[0], xy[1], math.atan2(r[1, 0], r[0, 0])])


def closure_errors(
    a_from_b: NDArray[np.float64],
    truth_a: NDArray[np.float64],
    truth_b: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(error_m (N,), error_rad (N,))`` of closures ``a_from_b`` ``(N, 3)`` against the true
    ``world_from_base`` of their nodes ``truth_a``, ``truth_b`` ``(N, 3)``."""
    z = np.asarray(a_from_b, dtype=np.float64).reshape(-1, 3)
    if len(z) == 0:
        return np.zeros(0), np.zeros(0)
    true_rel = relative(np.asarray(truth_a, float).reshape(-1, 3), np.asarray(truth_b, float))
    err_m = np.hypot(z[:, 0] - true_rel[:, 0], z[:, 1] - true_rel[:, 1])
    err_rad = np.abs(wrap_angle(z[:, 2] - true_rel[:, 2]))
    return err_m, err_rad


def false_closures(
    error_m: NDArray[np.float64],
    error_rad: NDArray[np.float64],
    *,
    max_m: float = 0.5,
    max_rad: float = math.radians(5.0),
) -> NDArray[np.bool_]:
    """Which closures are false: off by more than ``max_m`` or ``max_rad`` (NaN: unknown truth,
    not counted)."""
    return (np.asarray(error_m) > max_m) | (np.asarray(error_rad) > max_rad)
