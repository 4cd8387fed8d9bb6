from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.g2o import chained_odometry, read_g2o, to_gtsam
from gcs.graph.optimization import optimize_batch
from gcs.graph.pose2_gauss_newton import Pose2Factors
from gcs.graph.spanning_tree_init import (
    GlobalAnchor,
    component_labels,
    spanning_tree_from_factors,
    spanning_tree_initialization,
)


def test_consistent_graph_is_reproduced_from_each_anchor() -> None:
    rng = np.random.default_rng(0)
    n = 40
    truth = np.cumsum(rng.normal([0.7, 0.0, 0.3], 0.3, size=(n, 3)), axis=0)
    truth[:, 2] = se2.wrap_angle(truth[:, 2])
    pairs = [(k, k + 1) for k in range(n - 1)] + [(0, 20), (5, 33), (12, 39)]
    ij = np.array(pairs)
    z = se2.between(truth[ij[:, 0]], truth[ij[:, 1]])
    cov = np.tile(np.diag([0.01, 0.01, 0.001]), (len(ij), 1, 1))
    anchors = [GlobalAnchor(k, truth[k], np.eye(3) * 1e-4) for k in (0, 25)]
    init = spanning_tree_initialization(n, ij, z, cov, anchors)
    np.testing.assert_allclose(se2.between(truth, init), 0.0, atol=1e-9)


def test_weighted_average_of_trees() -> None:
    # A chain 0-1-2 with anchors at both ends that disagree: pose 1 gets the average.
    ij = np.array([[0, 1], [1, 2]])
    z = np.array([[1.0, 0, 0], [1.0, 0, 0]])
    cov = np.tile(np.diag([0.01, 0.01, 1e-6]), (2, 1, 1))
    anchors = [
        GlobalAnchor(0, np.zeros(3), np.eye(3) * 1e-8),
        GlobalAnchor(2, np.array([2.2, 0.0, 0.0]), np.eye(3) * 1e-8),
    ]
    init = spanning_tree_initialization(3, ij, z, cov, anchors)
    np.testing.assert_allclose(init[1], [1.1, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(init[2], [2.2, 0.0, 0.0], atol=1e-6)
    with pytest.raises(ValueError, match="at least one global anchor"):
        spanning_tree_initialization(3, ij, z, cov, [])


@pytest.mark.slow
def test_m3500b_tree_init_beats_odometry_and_lago(posegraph_dir: Path) -> None:
    g = read_g2o(posegraph_dir / "manhattan_M3500b.g2o")
    n = len(g.node_ids)
    cov = np.linalg.inv(g.edge_info)
    init = spanning_tree_initialization(
        n, g.edge_ij, g.edge_z, cov, [GlobalAnchor(0, np.zeros(3), np.eye(3) * 1e-12)]
    )
    fg, values = to_gtsam(g, poses=init)
    tree = optimize_batch(fg, values, method="dogleg", relative_error_tol=1e-6, max_iterations=200)
    fg_odo, v_odo = to_gtsam(g, poses=chained_odometry(g))
    lago = optimize_batch(
        fg_odo,
        gtsam.lago.initialize(fg_odo),
        method="dogleg",
        relative_error_tol=1e-6,
        max_iterations=200,
    )
    assert tree.chi2 <= lago.chi2
    assert tree.chi2 < 2.5e4


def test_spanning_tree_from_factors_one_tree_a_component() -> None:
    """Two components: the one with priors grows from its most informative prior, the one
    without from its smallest variable at its current pose; a lone variable keeps its pose."""
    step = np.array([1.0, 0.0, 0.5])
    ij = np.array([[0, 1], [1, 2], [3, 4]])
    factors = Pose2Factors(
        n=6,
        ij=ij,
        z=np.tile(step, (3, 1)),
        info=np.tile(np.eye(3) * 100.0, (3, 1, 1)),
        prior_index=np.array([0, 2]),
        prior_pose=np.array([[5.0, 5.0, 0.0], [0.0, 0.0, 0.0]]),
        prior_info=np.array([np.eye(3), np.eye(3) * 1e6]),
    )
    assert component_labels(6, ij).tolist() == [0, 0, 0, 1, 1, 2]
    current = np.arange(18, dtype=float).reshape(6, 3)
    out = spanning_tree_from_factors(factors, current)
    np.testing.assert_allclose(out[2], [0.0, 0.0, 0.0])  # the stronger prior wins
    np.testing.assert_allclose(se2.compose(out[1], step), out[2], atol=1e-12)
    np.testing.assert_allclose(out[3], current[3])
    np.testing.assert_allclose(out[4], se2.compose(current[3], step), atol=1e-12)
    np.testing.assert_allclose(out[5], current[5])
