from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.replay.trajectory_error import align_se2, trajectory_error
from protocol.se2 import compose


def test_a_rigidly_moved_trajectory_has_zero_error() -> None:
    rng = np.random.default_rng(0)
    ref = np.column_stack([rng.uniform(-20, 20, (40, 2)), rng.uniform(-3, 3, 40)])
    moved = compose([3.0, -7.0, 2.5], ref)
    err = trajectory_error(moved, ref)
    assert err.rmse_m < 1e-9 and err.yaw_rmse_deg < 1e-7
    np.testing.assert_allclose(compose(err.reference_from_map, [3.0, -7.0, 2.5]), 0, atol=1e-9)


def test_the_alignment_is_the_least_squares_one_and_the_error_is_what_remains() -> None:
    # Two points 2 m apart; the estimate puts the second 0.2 m further: the best alignment
    # splits the difference, leaving 0.1 m at each end.
    ref = np.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    est = np.array([[0.0, 0.0, 0.0], [2.2, 0.0, 0.0]])
    err = trajectory_error(compose([1.0, 1.0, 0.7], est), ref)
    np.testing.assert_allclose(err.position_err_m, [0.1, 0.1], atol=1e-12)
    assert math.isclose(err.rmse_m, 0.1) and math.isclose(err.max_m, 0.1)
    # A brute-force search over the rotation finds no better one.
    est_moved = compose([1.0, 1.0, 0.7], est)
    best = align_se2(est_moved, ref)
    for dyaw in np.linspace(-0.01, 0.01, 21):
        t = best + [0.0, 0.0, dyaw]
        a = compose(t, est_moved)
        shift = (ref[:, :2] - a[:, :2]).mean(axis=0)
        sse = np.sum((a[:, :2] + shift - ref[:, :2]) ** 2)
        assert sse >= 0.02 - 1e-12


def test_single_pose_uses_its_heading_and_bad_input_is_named() -> None:
    t = align_se2([[1.0, 2.0, 0.5]], [[0.0, 0.0, 1.5]])
    np.testing.assert_allclose(compose(t, [1.0, 2.0, 0.5]), [0.0, 0.0, 1.5], atol=1e-12)
    with pytest.raises(ValueError, match="differ in shape"):
        align_se2(np.zeros((3, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="estimate: expected poses"):
        trajectory_error(np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(ValueError, match="reference: non-finite"):
        trajectory_error(np.zeros((1, 3)), [[np.nan, 0, 0]])
