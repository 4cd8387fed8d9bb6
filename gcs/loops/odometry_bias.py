"""Online estimate of an odometry turn-scale bias from loop closures (paper 4.2, 4.5).

The paper calibrates the gyro online (4.2) because a heading that drifts with the turning
corrupts everything downstream. A log's odometry can carry the same defect: a wheel-base or
gyro scale error makes every heading increment ``s`` times the reported one (a robot that
under-reads its turns by 8 % has ``s = 1.087``). The pose-node model's sigmas do not cover it,
so around a loop the odometry looks far more certain than it is: candidate windows come out
too small and cycles through odometry are judged against the wrong noise.

Model, per robot: the true heading change between its nodes ``i < j`` is ``s * T_ij`` where
``T_ij`` is the odometry's unwrapped turning between them (sum of the wrapped increments).
A closure of the same robot measures the heading ``d_ij`` with variance ``v_closure``; the
residual ``r_ij = wrap(d_ij - T_ij) = (s - 1) T_ij + noise``, the noise's variance being the
closure's plus the odometry's own along the chain. With a Gaussian prior ``s ~ N(1, σ0²)``
the estimate of ``s - 1`` is the information-weighted least squares over the closures (its
standard deviation widened by the Birge ratio when the residuals scatter more than stated, and
never below the best single closure's ``sqrt(v) / |T|``: closures over one stretch of odometry
share its noise, so they are not independent evidence); closures
whose residual is more than ``gate_sigma`` standard deviations off the current fit are left
out (they are false, or the fit is not yet good), and the fit is iterated a few times.

:func:`estimate_turn_scale` is pure (arrays in, :class:`TurnScale` out);
:func:`debias_odometry` applies an estimate to odometry increments: the yaw corrected by the
scale and its variance widened by the scale's remaining uncertainty ``(σ_s T)²``, so that a
graph search over the corrected increments (candidate windows, cycle paths) is honest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

__all__ = ["OdometryBiasConfig", "TurnScale", "debias_odometry", "estimate_turn_scale"]

FloatArray = NDArray[Any]


class OdometryBiasConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Turn-scale estimation (unitless scale, radians).

    ``prior_sigma`` the turn scale's uncertainty before any closure (0.1: a calibration within
    10 %); ``gate_sigma`` how many standard deviations off the fit a closure's residual may be;
    ``min_turn_rad`` closures spanning less turning than this say nothing about the scale and
    are not used (20 deg: a match's heading is good to about 1 deg, a 10 % scale error over
    20 deg is 2 deg; at 45 deg a robot with few long turns between revisits starved the fit:
    ACES with turns scaled by 1.08, 19 samples of 82, no fit, ATE 7.3 m, 0.20 m at 20 deg);
    ``max_turn_rad`` nor more than this (the residual's wrap is ambiguous beyond
    ``pi / (prior bias)``); ``iterations`` of the gated fit; ``min_sigma`` a floor on the
    estimate's standard deviation (closures accepted against biased odometry lean towards it,
    and the scale may drift: the estimate is never trusted more than this).

    Applying an estimate (:class:`~gcs.loops.loop_closer.LoopCloser`, unless ``enabled`` is
    off): it is fitted once at least ``min_used`` matches took part (12: Intel with turns scaled
    by 1.08 had 18 of 65, the loop's 15 each 30 deg off, and never calibrated at 20), and fed
    back into the graph's odometry when it differs from 1 (the calibration the robot reported)
    by more than ``apply_sigma`` standard deviations (of the larger of its statistical sigma and
    half its floored one), and later when it differs from the one in use by more than
    ``reapply_sigma`` of its statistical sigma (once a bias is established the better estimate
    is used: ACES with turns scaled by 1.08 kept 0.9293 against a fit of 0.9239 +- 0.003, truth
    0.9259, at 2 floored sigmas, and ended at 0.83 m).
    ``window_k_sigma``: a match is evidence only when its search window holds the heading
    change this many standard deviations either side of the current estimate (a window that
    cannot hold the truth returns a look-alike).
    ``restart_change``: a correction that moves the scale by more than this since the last
    full re-match makes the loop closer match every pair again (windows and guesses were
    wrong); a smaller one re-checks the hypotheses the graph rejected and searches for new
    pairs only. ``refit_growth``: after a correction the scale is fitted again only once the
    robot's matches grew by this factor (each correction re-matches; a fit on the same evidence
    would only chase its noise).
    """

    prior_sigma: float = 0.1
    min_sigma: float = 0.003
    gate_sigma: float = 3.0
    min_turn_rad: float = math.radians(20.0)
    max_turn_rad: float = 20.0
    iterations: int = 4
    enabled: bool = True
    min_used: int = 12
    apply_sigma: float = 3.0
    reapply_sigma: float = 1.0
    window_k_sigma: float = 2.0
    restart_change: float = 0.1
    refit_growth: float = 1.5

    def __post_init__(self) -> None:
        for name in (
            "prior_sigma",
            "min_sigma",
            "gate_sigma",
            "min_turn_rad",
            "max_turn_rad",
            "apply_sigma",
            "reapply_sigma",
            "window_k_sigma",
            "restart_change",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v}")
        if self.iterations < 1:
            raise ValueError(f"iterations: expected >= 1, got {self.iterations}")
        if not (math.isfinite(self.refit_growth) and self.refit_growth >= 1):
            raise ValueError(f"refit_growth: expected >= 1, got {self.refit_growth}")
        if self.min_used < 1:
            raise ValueError(f"min_used: expected >= 1, got {self.min_used}")


@dataclass(frozen=True)
class TurnScale:
    """A turn-scale estimate: true turning = ``scale`` times the odometry's; ``sigma`` its
    standard deviation; ``used`` closures in the fit, ``rejected`` gated out;
    ``statistical_sigma`` the standard deviation from the closures' scatter alone (Birge
    ratio, ``min_sigma``), without the single-closure floor (None: as ``sigma``)."""

    scale: float = 1.0
    sigma: float = 0.1
    used: int = 0
    rejected: int = 0
    statistical_sigma: float | None = None


def _wrap(a: FloatArray) -> FloatArray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi  # type: ignore[no-any-return]


def estimate_turn_scale(
    turn_rad: FloatArray,
    closure_yaw_rad: FloatArray,
    variance_rad2: FloatArray,
    config: OdometryBiasConfig | None = None,
    *,
    bend_turn_rad: FloatArray | None = None,
    bend_offset_rad: FloatArray | None = None,
) -> TurnScale:
    """Fit ``s`` from closures of one robot (module docstring).

    ``turn_rad`` ``(K,)`` the odometry's unwrapped turning ``T`` between each closure's nodes
    (from ``a`` to ``b`` for a closure ``a_from_b``), ``closure_yaw_rad`` the closures'
    measured yaw of ``a_from_b``, ``variance_rad2`` the residual's noise variance (closure plus
    odometry along the chain). ``bend_turn_rad`` ``(K,)`` (optional, default 0): the turning
    ``W`` within the closure's grids (a grid joined by the biased odometry is bent by about
    ``(s - 1) W``, so the closure's heading is off by as much): the residual's variance then
    includes ``((|s - 1| + sigma) W / 2)^2`` at the current estimate, in the gate and the
    weights (not in the single-closure floor: that would tie the fit's uncertainty to its
    prior). ``bend_offset_rad`` ``(K,)`` (optional, default 0): the grids' mean bend per unit
    of scale error, ``m_a - m_b`` with ``m`` the mean turning from a grid's node back to its
    scans: a grid's content is turned by ``(1 - s) m`` on average, so the match measures
    ``s T - (s - 1)(m_a - m_b)`` and the residual is ``(s - 1)(T - m_a + m_b)``: the
    regressor is ``T`` less the offset (bent grids otherwise pull the fit towards 1).
    Raises ``ValueError`` on mismatched or non-finite input.
    """
    cfg = config or OdometryBiasConfig()
    t = np.asarray(turn_rad, dtype=np.float64).ravel()
    d = np.asarray(closure_yaw_rad, dtype=np.float64).ravel()
    v = np.asarray(variance_rad2, dtype=np.float64).ravel()
    bw = (
        np.zeros(len(t))
        if bend_turn_rad is None
        else np.abs(np.asarray(bend_turn_rad, dtype=np.float64).ravel())
    )
    off = (
        np.zeros(len(t))
        if bend_offset_rad is None
        else np.asarray(bend_offset_rad, dtype=np.float64).ravel()
    )
    if not (len(t) == len(d) == len(v) == len(bw) == len(off)):
        raise ValueError(
            f"estimate_turn_scale: lengths differ ({len(t)}, {len(d)}, {len(v)}, {len(bw)}, "
            f"{len(off)})"
        )
    if not (
        np.all(np.isfinite(t))
        and np.all(np.isfinite(d))
        and np.all(v > 0)
        and np.all(np.isfinite(bw))
        and np.all(np.isfinite(off))
    ):
        raise ValueError("estimate_turn_scale: non-finite turns/yaws or non-positive variances")
    r = _wrap(d - t)  # (s - 1) (T - offset) + noise
    t = t - off  # the regressor
    keep = (np.abs(t) >= cfg.min_turn_rad) & (np.abs(t) <= cfg.max_turn_rad)
    t, r, v, bw = t[keep], r[keep], v[keep], bw[keep]
    if len(t) == 0:
        return TurnScale(sigma=cfg.prior_sigma)
    prior_info = 1.0 / cfg.prior_sigma**2
    bias = 0.0
    sigma = cfg.prior_sigma
    statistical = sigma
    inlier = np.ones(len(t), dtype=bool)
    for _ in range(cfg.iterations):
        # the residual's variance includes the current scale uncertainty along T, and the
        # grids' bend at the current estimate
        bent_v = v + (0.5 * (abs(bias) + sigma) * bw) ** 2
        total_v = bent_v + (sigma * t) ** 2
        inlier = (r - bias * t) ** 2 <= cfg.gate_sigma**2 * total_v
        w = inlier / bent_v
        info = prior_info + float(np.sum(w * t * t))
        bias = float(np.sum(w * t * r)) / info
        # Residuals more scattered than their stated variances (look-alike matches, grids
        # distorted by the very bias, samples sharing one stretch of odometry) mean the
        # closures know less than they say: widen by the Birge ratio sqrt(chi2 / dof).
        n_in = int(inlier.sum())
        birge = 1.0
        if n_in > 1:
            birge = math.sqrt(max(1.0, float(np.sum(w * (r - bias * t) ** 2)) / (n_in - 1)))
        # Closures over one stretch share its odometry noise: together they know the scale
        # no better than the best single one does (its noise over its turning).
        single = float(np.min(np.sqrt(v[inlier]) / np.abs(t[inlier]))) if n_in else 0.0
        statistical = max(birge / math.sqrt(info), cfg.min_sigma)
        sigma = max(statistical, single)
    return TurnScale(
        scale=1.0 + bias,
        sigma=sigma,
        used=int(inlier.sum()),
        rejected=int((~inlier).sum()),
        statistical_sigma=statistical,
    )


def debias_odometry(
    z: FloatArray, covariance: FloatArray, estimate: TurnScale
) -> tuple[FloatArray, FloatArray]:
    """Odometry increments ``z`` ``(N, 3)`` (``a_from_b``) and covariances ``(N, 3, 3)`` (body
    frame of ``b``) with the yaw scaled by ``estimate.scale`` and its variance widened by
    ``(estimate.sigma * yaw)^2``. Returns new arrays."""
    zz = np.array(z, dtype=np.float64, copy=True).reshape(-1, 3)
    cc = np.array(covariance, dtype=np.float64, copy=True).reshape(-1, 3, 3)
    yaw = zz[:, 2].copy()
    zz[:, 2] = yaw * estimate.scale
    cc[:, 2, 2] += (estimate.sigma * yaw) ** 2
    return zz, cc
