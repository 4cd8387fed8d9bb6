from __future__ import annotations

import gtsam
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from gcs.graph import se2

coord = st.floats(-50, 50, allow_nan=False)
angle = st.floats(-np.pi, np.pi - 1e-9, allow_nan=False)
pose = st.tuples(coord, coord, angle).map(np.array)


@given(pose, pose)
def test_matches_gtsam(a: np.ndarray, b: np.ndarray) -> None:
    ga, gb = se2.pose2(a), se2.pose2(b)
    np.testing.assert_allclose(se2.compose(a, b)[:2], se2.pose_vec(ga.compose(gb))[:2], atol=1e-9)
    np.testing.assert_allclose(se2.between(a, b)[:2], se2.pose_vec(ga.between(gb))[:2], atol=1e-9)
    np.testing.assert_allclose(se2.inverse(a)[:2], se2.pose_vec(ga.inverse())[:2], atol=1e-9)
    d = float(se2.wrap_angle(se2.between(a, b)[2] - ga.between(gb).theta()))
    assert abs(d) < 1e-9
    np.testing.assert_allclose(se2.adjoint(a), ga.AdjointMap(), atol=1e-12)


def test_vectorized() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(20, 3))
    b = rng.normal(size=(20, 3))
    out = se2.compose(a, b)
    for k in range(20):
        np.testing.assert_allclose(out[k], se2.compose(a[k], b[k]))


def test_propagate_covariance_matches_gtsam_marginal() -> None:
    # x1 = x0 * z with independent noises: GTSAM's marginal of x1 equals the propagation.
    cov0 = np.diag([0.01, 0.02, 0.003])
    covz = np.diag([0.04, 0.01, 0.002])
    z = np.array([2.0, 1.0, 0.7])
    fg = gtsam.NonlinearFactorGraph()
    fg.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), gtsam.noiseModel.Gaussian.Covariance(cov0)))
    fg.add(gtsam.BetweenFactorPose2(0, 1, se2.pose2(z), gtsam.noiseModel.Gaussian.Covariance(covz)))
    values = gtsam.Values()
    values.insert(0, gtsam.Pose2())
    values.insert(1, se2.pose2(z))
    marginal = gtsam.Marginals(fg, values).marginalCovariance(1)
    np.testing.assert_allclose(se2.propagate_covariance(cov0, z, covz), marginal, atol=1e-12)
