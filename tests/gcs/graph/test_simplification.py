from __future__ import annotations

import gtsam
import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.dijkstra_projection import Adjacency, dijkstra_projection
from gcs.graph.g2o import reverse_edge
from gcs.graph.optimization import optimize_batch
from gcs.graph.simplification import merge_parallel_edges, simplify_graph


def noisy_graph(seed: int, n: int = 60):
    rng = np.random.default_rng(seed)
    truth = np.cumsum(rng.normal([0.8, 0.0, 0.15], 0.2, size=(n, 3)), axis=0)
    truth[:, 2] = se2.wrap_angle(truth[:, 2])
    pairs = [(k, k + 1) for k in range(n - 1)]
    # Redundant loop closures: bundles of near-duplicates and exact repeats.
    for a, b in [(2, 40), (3, 41), (4, 42), (2, 40), (41, 3), (10, 55), (11, 56), (20, 30)]:
        pairs.append((a, b))
    ij = np.array(pairs, dtype=np.int64)
    # Odometry is much more precise than loop closures (as on the robots).
    sig = np.where((ij[:, 1] - ij[:, 0] == 1)[:, None], [0.01, 0.01, 0.003], [0.05, 0.05, 0.02])
    z = se2.between(truth[ij[:, 0]], truth[ij[:, 1]]) + rng.normal(0, 1, (len(ij), 3)) * sig
    cov = np.array([np.diag(s**2) for s in sig])
    return truth, ij, z, cov


def solve(n, ij, z, cov, init):
    fg = gtsam.NonlinearFactorGraph()
    for (i, j), zz, c in zip(ij.tolist(), z, cov, strict=True):
        fg.add(
            gtsam.BetweenFactorPose2(i, j, se2.pose2(zz), gtsam.noiseModel.Gaussian.Covariance(c))
        )
    fg.add(gtsam.PriorFactorPose2(0, se2.pose2(init[0]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)))
    values = gtsam.Values()
    for k in range(n):
        values.insert(k, se2.pose2(init[k]))
    res = optimize_batch(fg, values, method="gn", relative_error_tol=1e-12)
    return np.array([se2.pose_vec(res.values.atPose2(k)) for k in range(n)]), res


@pytest.mark.parametrize("seed", range(3))
def test_keeps_maximum_likelihood_and_removes_redundant_edges(seed: int) -> None:
    n = 60
    truth, ij, z, cov = noisy_graph(seed, n)
    optimum, _ = solve(n, ij, z, cov, truth)
    simple = simplify_graph(n, ij, cov, optimum, alpha=2.0, z=z)
    assert len(simple.ij) < len(ij) - 2  # repeats merged and near-duplicates dropped
    assert len(simple.ij) >= n - 1
    # Zero residual at the original optimum, which therefore stays the optimum.
    np.testing.assert_allclose(
        se2.between(optimum[simple.ij[:, 0]], optimum[simple.ij[:, 1]]), simple.z, atol=1e-12
    )
    again, res = solve(n, simple.ij, simple.z, simple.cov, optimum)
    assert res.chi2 < 1e-12
    assert np.abs(again - optimum).max() < 1e-9
    # Every kept loop closure was informative when added; every dropped one is redundant.
    kept = {tuple(e) for e in simple.ij.tolist()}
    adj = Adjacency.from_arrays(n, simple.ij, simple.z, simple.cov)
    mij, _, mcov, _ = merge_parallel_edges(ij, z, cov)
    for (a, b), c in zip(mij.tolist(), mcov, strict=True):
        if (a, b) not in kept:
            proj = dijkstra_projection(adj, a, target=b)
            assert np.trace(proj.covariances[b]) <= 2.0 * np.trace(c)


def test_huge_alpha_keeps_a_spanning_tree() -> None:
    n = 60
    truth, ij, z, cov = noisy_graph(5, n)
    optimum, _ = solve(n, ij, z, cov, truth)
    simple = simplify_graph(n, ij, cov, optimum, alpha=1e9, z=z)
    assert len(simple.ij) == n - 1


def test_parallel_edges_merge_information() -> None:
    ij = np.array([[0, 1], [1, 0], [0, 1]])
    z = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    cov = np.tile(np.eye(3) * 0.04, (3, 1, 1))
    mij, mz, mcov, members = merge_parallel_edges(ij, z, cov)
    assert mij.tolist() == [[0, 1]] and members == [[0, 1, 2]]
    np.testing.assert_allclose(mz[0], [1.0, 0.0, 0.0], atol=1e-12)
    _, info_reversed = reverse_edge(z[1], np.linalg.inv(cov[1]))
    expected = 2 * np.linalg.inv(cov[0]) + info_reversed
    np.testing.assert_allclose(np.linalg.inv(mcov[0]), expected, rtol=1e-9, atol=1e-6)
