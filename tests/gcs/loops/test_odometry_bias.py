"""Turn-scale estimation from closures on a constructed trajectory (issue 19 item 4)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.loops.odometry_bias import (
    OdometryBiasConfig,
    TurnScale,
    debias_odometry,
    estimate_turn_scale,
)


@pytest.mark.parametrize("true_scale", [1 / 0.92, 1 / 1.08, 1.0])
def test_recovers_a_known_turn_scale(true_scale: float) -> None:
    rng = np.random.default_rng(3)
    # odometry turning between closure pairs (a robot driving loops), closures measuring the
    # true heading change with 0.5 deg noise, and 10 % false closures
    turn = rng.uniform(-12.0, 12.0, 200)
    sigma = math.radians(0.5)
    yaw = (true_scale * turn + rng.normal(0, sigma, 200) + math.pi) % (2 * math.pi) - math.pi
    yaw[::10] = rng.uniform(-math.pi, math.pi, 20)
    est = estimate_turn_scale(turn, yaw, np.full(200, sigma**2))
    assert est.scale == pytest.approx(true_scale, abs=0.005)
    assert est.rejected >= 15 and est.used >= 150  # the false ones gated out


def test_no_closure_keeps_the_prior_and_bad_input_is_named() -> None:
    cfg = OdometryBiasConfig(prior_sigma=0.2)
    est = estimate_turn_scale(np.array([0.1]), np.array([0.1]), np.array([1e-4]), cfg)
    assert est == TurnScale(scale=1.0, sigma=0.2)  # too little turning to say anything
    with pytest.raises(ValueError, match="lengths differ"):
        estimate_turn_scale(np.zeros(2), np.zeros(3), np.ones(2))


def test_debias_scales_the_yaw_and_widens_its_variance() -> None:
    z = np.array([[1.0, 0.0, 0.5]])
    cov = np.diag([0.01, 0.01, 0.001])[None]
    zz, cc = debias_odometry(z, cov, TurnScale(scale=1.1, sigma=0.1))
    assert zz[0] == pytest.approx([1.0, 0.0, 0.55])
    assert cc[0, 2, 2] == pytest.approx(0.001 + 0.05**2)
    assert z[0, 2] == 0.5  # input untouched


def test_scatter_beyond_the_stated_noise_widens_the_estimate() -> None:
    rng = np.random.default_rng(7)
    turn = rng.uniform(-6.0, 6.0, 100)
    stated = math.radians(0.05)
    cfg = OdometryBiasConfig(min_sigma=1e-9, gate_sigma=1e3)  # neither floor nor gate binds
    honest = estimate_turn_scale(
        turn, 1.05 * turn + rng.normal(0, stated, 100), np.full(100, stated**2), cfg
    )
    # the same closures, scattered 30 times more than they state (look-alikes, distorted
    # grids): the estimate says it knows less
    loose = estimate_turn_scale(
        turn, 1.05 * turn + rng.normal(0, 30 * stated, 100), np.full(100, stated**2), cfg
    )
    assert honest.scale == pytest.approx(1.05, abs=0.001)
    assert loose.scale == pytest.approx(1.05, abs=0.005)
    assert loose.sigma > 2.5 * honest.sigma
    # and many closures over one stretch know no more than the best one of them
    assert honest.sigma >= stated / np.abs(turn).max() - 1e-12


@pytest.mark.parametrize("true_scale", [1 / 0.92, 1 / 1.08])
def test_bent_grids_are_modelled_not_followed(true_scale: float) -> None:
    # Closures between grids that join scans by the biased odometry: each grid's content is
    # turned by (1 - s) m on average (m: its mean turning back to its scans), so the match
    # measures s T - (s - 1)(m_a - m_b). Robots that turn within their grids (|m| up to
    # 90 deg) pull a fit that ignores it towards 1; the offset model recovers s.
    rng = np.random.default_rng(5)
    n = 300
    turn = rng.uniform(-3.0, 3.0, n)
    m_a, m_b = rng.uniform(-1.6, 1.6, n), rng.uniform(-1.6, 1.6, n)
    m_a[: n // 3] = turn[: n // 3]  # spins: a grid holding the whole turn between the nodes
    m_b[: n // 3] = 0.0
    sigma = math.radians(0.5)
    yaw = true_scale * turn - (true_scale - 1) * (m_a - m_b) + rng.normal(0, sigma, n)
    yaw = (yaw + math.pi) % (2 * math.pi) - math.pi
    bend = np.hypot(np.abs(m_a), np.abs(m_b))  # no larger than the window's turning here
    var = np.full(n, sigma**2)
    modelled = estimate_turn_scale(turn, yaw, var, bend_turn_rad=bend, bend_offset_rad=m_a - m_b)
    ignored = estimate_turn_scale(turn, yaw, var)
    assert modelled.scale == pytest.approx(true_scale, abs=0.01)
    assert abs(ignored.scale - true_scale) > 2 * abs(modelled.scale - true_scale)
    with pytest.raises(ValueError, match="lengths differ"):
        estimate_turn_scale(turn, yaw, var, bend_offset_rad=np.zeros(3))
