"""Trajectory scores against hand-computed answers: pose interpolation (headings across the
-pi/pi seam), closure errors and the false-closure rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mission.report.trajectory_scoring import (
    ate_rmse_m,
    closure_errors,
    false_closures,
    interpolate_poses,
    rigid_world_from_map,
)
from protocol.se2 import compose, relative


def test_interpolation_is_linear_and_takes_the_short_arc() -> None:
    t = np.array([0.0, 1.0, 2.0])
    p = np.array([[0.0, 0.0, 3.0], [1.0, 2.0, -3.0], [3.0, 2.0, -3.0]])
    q = interpolate_poses(t, p, np.array([0.5, 1.5, -1.0, 5.0]))
    assert q[0, :2] == pytest.approx([0.5, 1.0])
    # 3.0 -> -3.0 rad is a 0.283 rad turn through pi, not 6 rad back through 0
    assert abs(q[0, 2]) == pytest.approx(math.pi, abs=1e-9)
    assert q[1] == pytest.approx([2.0, 2.0, -3.0])
    assert q[2] == pytest.approx(p[0])  # before the track: its first pose
    assert q[3] == pytest.approx(p[-1])
    assert np.isnan(interpolate_poses(np.zeros(0), np.zeros((0, 3)), np.array([1.0]))).all()


def test_closure_errors_and_false_rule() -> None:
    rng = np.random.default_rng(3)
    truth_a = rng.uniform(-10, 10, (4, 3))
    truth_b = rng.uniform(-10, 10, (4, 3))
    z = relative(truth_a, truth_b)
    z[1] = compose(z[1], [0.3, 0.4, 0.0])  # 0.5 m off: not false (strictly more is)
    z[2] = compose(z[2], [0.0, 0.0, math.radians(6.0)])
    z[3] = compose(z[3], [0.6, 0.0, 0.0])
    err_m, err_rad = closure_errors(z, truth_a, truth_b)
    assert err_m == pytest.approx([0.0, 0.5, 0.0, 0.6], abs=1e-9)
    assert err_rad == pytest.approx([0.0, 0.0, math.radians(6.0), 0.0], abs=1e-9)
    assert false_closures(err_m, err_rad).tolist() == [False, False, True, True]
    assert closure_errors(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)))[0].size == 0


def test_ate_is_zero_after_a_rigid_motion() -> None:
    rng = np.random.default_rng(1)
    truth = np.column_stack([rng.uniform(0, 20, (30, 2)), rng.uniform(-3, 3, 30)])
    moved = compose(np.array([5.0, -2.0, 0.4]), truth)
    assert ate_rmse_m(moved, truth) == pytest.approx(0.0, abs=1e-9)


def test_the_rigid_alignment_is_the_transform_the_ate_removes() -> None:
    """A map turned and shifted against the world: the alignment recovers ``world_from_map``
    exactly, and with noise the positions it maps leave the ATE's residual."""
    rng = np.random.default_rng(2)
    truth = np.column_stack([rng.uniform(0, 40, (50, 2)), rng.uniform(-3, 3, 50)])
    world_from_map = np.array([3.0, -7.5, math.radians(1.2)])
    in_map = relative(np.repeat(world_from_map[None], len(truth), axis=0), truth)
    np.testing.assert_allclose(rigid_world_from_map(in_map, truth), world_from_map, atol=1e-9)
    noisy = in_map + np.column_stack([rng.normal(0, 0.1, (50, 2)), np.zeros(50)])
    back = compose(rigid_world_from_map(noisy, truth), noisy)
    rms = math.sqrt(np.mean(np.sum((back[:, :2] - truth[:, :2]) ** 2, axis=1)))
    assert rms == pytest.approx(ate_rmse_m(noisy, truth), rel=1e-9)
