"""Absolute trajectory error (ATE) of an estimate against reference poses, after alignment.

The estimate lives in ``map`` and the reference in its own frame (a log's ``log`` frame, the
simulator's world), so the two are first related by the rigid transform ``reference_from_map``
minimizing the squared position differences (Horn 1987 / Umeyama 1991, planar, no scale):
with centred positions ``p`` (estimate) and ``q`` (reference), the rotation is
``atan2(Σ p×q, Σ p·q)`` and the translation maps the centroids. The ATE is the RMS of the
remaining position differences (Sturm et al. 2012's ATE, in 2-D); the heading error after
alignment is reported alongside. ``O(N)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol.se2 import compose, wrap_angle

__all__ = ["TrajectoryError", "align_se2", "trajectory_error"]

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TrajectoryError:
    """``reference_from_map`` alignment and the per-pose errors after it (``(N,)``)."""

    reference_from_map: FloatArray
    position_err_m: FloatArray
    yaw_err_rad: FloatArray

    @property
    def rmse_m(self) -> float:
        return float(np.sqrt(np.mean(self.position_err_m**2)))

    @property
    def max_m(self) -> float:
        return float(np.max(self.position_err_m))

    @property
    def yaw_rmse_deg(self) -> float:
        return math.degrees(float(np.sqrt(np.mean(self.yaw_err_rad**2))))


def _check(poses: ArrayLike, name: str) -> FloatArray:
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0:
        raise ValueError(f"{name}: expected poses (N, 3) with N >= 1, got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: non-finite pose")
    return p


def align_se2(estimate: ArrayLike, reference: ArrayLike) -> FloatArray:
    """``reference_from_map`` ``(3,)`` that best maps the estimate's positions onto the
    reference's (least squares). With one pose, or all positions equal, the headings fix the
    rotation instead."""
    est = _check(estimate, "estimate")
    ref = _check(reference, "reference")
    if est.shape != ref.shape:
        raise ValueError(f"estimate {est.shape} and reference {ref.shape} differ in shape")
    mp = est[:, :2].mean(axis=0)
    mq = ref[:, :2].mean(axis=0)
    p = est[:, :2] - mp
    q = ref[:, :2] - mq
    cross = float(np.sum(p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0]))
    dot = float(np.sum(p[:, 0] * q[:, 0] + p[:, 1] * q[:, 1]))
    if math.hypot(cross, dot) < 1e-12:
        d = wrap_angle(ref[:, 2] - est[:, 2])
        yaw = float(np.arctan2(np.sin(d).mean(), np.cos(d).mean()))
    else:
        yaw = math.atan2(cross, dot)
    c, s = math.cos(yaw), math.sin(yaw)
    t = mq - np.array([c * mp[0] - s * mp[1], s * mp[0] + c * mp[1]])
    return np.array([t[0], t[1], yaw])


def trajectory_error(estimate: ArrayLike, reference: ArrayLike) -> TrajectoryError:
    """Align ``estimate`` to ``reference`` (both ``(N, 3)``, pose ``k`` of one is pose ``k`` of
    the other) and return the errors that remain."""
    est = _check(estimate, "estimate")
    ref = _check(reference, "reference")
    t = align_se2(est, ref)
    aligned = compose(t, est)
    return TrajectoryError(
        reference_from_map=t,
        position_err_m=np.hypot(aligned[:, 0] - ref[:, 0], aligned[:, 1] - ref[:, 1]),
        yaw_err_rad=np.abs(wrap_angle(aligned[:, 2] - ref[:, 2])),
    )
