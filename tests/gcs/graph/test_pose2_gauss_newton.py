from __future__ import annotations

import gtsam
import numpy as np
import pytest

from gcs.graph.block_cholesky import NotPositiveDefiniteError
from gcs.graph.pose2_gauss_newton import (
    Pose2Factors,
    exp_se2,
    gauss_newton_pose2,
    local_coordinates,
    log_se2,
    pose2_chi2,
)

ANGLES = [0.0, 1e-9, 3e-5, -2e-4, 0.01, 0.7, -2.5, 3.1]


def _problem(
    seed: int, n: int = 30, loops: int = 20, noise: float = 0.05
) -> tuple[Pose2Factors, gtsam.NonlinearFactorGraph, np.ndarray]:
    """A random trajectory with noisy odometry and loop edges (full information matrices)."""
    rng = np.random.default_rng(seed)
    truth = np.cumsum(rng.normal([0.5, 0.0, 0.4], 0.3, (n, 3)), axis=0)
    pairs = [(k, k + 1) for k in range(n - 1)]
    for _ in range(loops):
        a, b = (int(v) for v in rng.choice(n, 2, replace=False))
        pairs.append((a, b))
    ij = np.array(pairs)
    z = np.array(
        [
            gtsam.Pose2.Logmap(gtsam.Pose2(*truth[i]).between(gtsam.Pose2(*truth[j])))
            for i, j in pairs
        ]
    )
    z = exp_se2(z + rng.normal(0, noise, z.shape))
    root = rng.normal(0, 1, (len(pairs), 3, 3))
    info = root @ root.transpose(0, 2, 1) + 3 * np.eye(3)
    prior_info = np.diag([1e4, 1e4, 1e5])[None]
    factors = Pose2Factors(
        n=n,
        ij=ij,
        z=z,
        info=info,
        prior_index=np.array([0]),
        prior_pose=truth[:1],
        prior_info=prior_info,
    )
    fg = gtsam.NonlinearFactorGraph()
    for (i, j), zz, om in zip(ij.tolist(), z, info, strict=True):
        fg.add(
            gtsam.BetweenFactorPose2(
                i, j, gtsam.Pose2(*zz), gtsam.noiseModel.Gaussian.Information(om)
            )
        )
    fg.add(
        gtsam.PriorFactorPose2(
            0, gtsam.Pose2(*truth[0]), gtsam.noiseModel.Gaussian.Information(prior_info[0])
        )
    )
    return factors, fg, truth


def _values(poses: np.ndarray) -> gtsam.Values:
    values = gtsam.Values()
    for k, p in enumerate(poses):
        values.insert(k, gtsam.Pose2(*p))
    return values


@pytest.mark.parametrize("w", ANGLES)
def test_exp_log_match_gtsam(w: float) -> None:
    xi = np.array([0.3, -1.2, w])
    p = gtsam.Pose2.Expmap(xi)
    np.testing.assert_allclose(exp_se2(xi[None])[0], [p.x(), p.y(), p.theta()], atol=1e-12)
    np.testing.assert_allclose(log_se2(exp_se2(xi[None]))[0], xi, atol=1e-12)
    base = np.array([[1.0, 2.0, 2.9]])
    q = gtsam.Pose2(*base[0]).compose(p)
    np.testing.assert_allclose(
        local_coordinates(base, np.array([[q.x(), q.y(), q.theta()]]))[0], xi, atol=1e-10
    )


def test_chi2_matches_gtsam() -> None:
    factors, fg, truth = _problem(1)
    rng = np.random.default_rng(9)
    poses = truth + rng.normal(0, 0.3, truth.shape)
    assert pose2_chi2(factors, poses) == pytest.approx(2 * fg.error(_values(poses)), rel=1e-12)


@pytest.mark.parametrize("angle_noise", [0.0, 0.4])
def test_one_step_equals_gtsam_gauss_newton_step(angle_noise: float) -> None:
    """The linearization (Jacobians incl. Jr^-1 and the adjoint) and the solve are GTSAM's:
    one step from the same start lands on the same poses."""
    factors, fg, truth = _problem(2, noise=0.2)
    rng = np.random.default_rng(3)
    start = truth + rng.normal(0, [0.3, 0.3, angle_noise], truth.shape)
    start[0] = truth[0]
    ours = gauss_newton_pose2(factors, start, order=rng.permutation(factors.n), max_iterations=1)
    opt = gtsam.GaussNewtonOptimizer(fg, _values(start), gtsam.GaussNewtonParams())
    opt.iterate()
    theirs = gtsam.utilities.extractPose2(opt.values())
    assert ours.iterations == 1
    np.testing.assert_allclose(ours.poses, theirs, atol=1e-9)


def test_converges_to_gtsam_optimum() -> None:
    factors, fg, truth = _problem(4, n=60, loops=40, noise=0.1)
    rng = np.random.default_rng(4)
    start = truth + rng.normal(0, 0.2, truth.shape)
    ours = gauss_newton_pose2(factors, start, relative_error_tol=1e-12)
    params = gtsam.GaussNewtonParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(0.0)
    theirs = gtsam.GaussNewtonOptimizer(fg, _values(start), params).optimize()
    np.testing.assert_allclose(ours.poses, gtsam.utilities.extractPose2(theirs), atol=1e-7)
    assert ours.chi2 == pytest.approx(2 * fg.error(theirs), rel=1e-9)
    assert ours.chi2_history[0] == pytest.approx(pose2_chi2(factors, start))
    assert len(ours.chi2_history) == ours.iterations + 1
    # The ordering changes the factor, not the solution.
    other = gauss_newton_pose2(factors, start, order=rng.permutation(60), relative_error_tol=1e-12)
    np.testing.assert_allclose(other.poses, ours.poses, atol=1e-9)


def test_stopping_rule() -> None:
    factors, _, truth = _problem(5, noise=0.1)
    start = truth + 0.1
    assert gauss_newton_pose2(factors, start, max_iterations=2).iterations == 2
    assert gauss_newton_pose2(factors, start, error_tol=1e12).iterations == 1
    loose = gauss_newton_pose2(factors, start, relative_error_tol=0.5)
    tight = gauss_newton_pose2(factors, start, relative_error_tol=1e-12)
    assert loose.iterations < tight.iterations
    h = loose.chi2_history
    assert (h[-2] - h[-1]) / h[-2] < 0.5
    assert all((a - b) / a >= 0.5 for a, b in zip(h[:-2], h[1:-1], strict=True))


def test_gauge_freedom_without_prior_is_reported() -> None:
    factors, _, truth = _problem(6)
    free = Pose2Factors(n=factors.n, ij=factors.ij, z=factors.z, info=factors.info)
    with pytest.raises(NotPositiveDefiniteError, match="not positive definite"):
        gauss_newton_pose2(free, truth)


def test_bad_factors_are_rejected() -> None:
    z = np.zeros((1, 3))
    info = np.eye(3)[None]
    with pytest.raises(ValueError, match="factor 0 joins a variable to itself"):
        Pose2Factors(n=2, ij=np.array([[1, 1]]), z=z, info=info)
    with pytest.raises(ValueError, match=r"Pose2Factors.ij: indices must lie in 0..1"):
        Pose2Factors(n=2, ij=np.array([[0, 2]]), z=z, info=info)
    with pytest.raises(ValueError, match=r"Pose2Factors.info: expected shape \(1, 3, 3\)"):
        Pose2Factors(n=2, ij=np.array([[0, 1]]), z=z, info=np.eye(3))
    with pytest.raises(ValueError, match="Pose2Factors.z: not all finite"):
        Pose2Factors(n=2, ij=np.array([[0, 1]]), z=np.full((1, 3), np.nan), info=info)
    factors = Pose2Factors(n=2, ij=np.array([[0, 1]]), z=z, info=info)
    with pytest.raises(ValueError, match=r"poses must have shape \(2, 3\)"):
        gauss_newton_pose2(factors, np.zeros((3, 3)))
