from __future__ import annotations

import gtsam
import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.dijkstra_projection import (
    Adjacency,
    dijkstra_projection,
    projected_trace,
    relative_covariance,
)


def random_graph(seed: int, n: int, loops: int):
    """Consistent (noise-free) random pose graph: truth, edges, covariances."""
    rng = np.random.default_rng(seed)
    truth = np.cumsum(rng.normal([0.7, 0.1, 0.3], [0.3, 0.3, 0.5], size=(n, 3)), axis=0)
    truth[:, 2] = se2.wrap_angle(truth[:, 2])
    pairs = [(k, k + 1) for k in range(n - 1)]
    while len(pairs) < n - 1 + loops:
        a, b = (int(v) for v in rng.integers(0, n, 2))
        if a != b:
            pairs.append((a, b))
    ij = np.array(pairs, dtype=np.int64)
    z = se2.between(truth[ij[:, 0]], truth[ij[:, 1]])
    covs = []
    for _ in range(len(ij)):
        m = rng.normal(size=(3, 3)) * [[0.1], [0.1], [0.03]]
        covs.append(m @ m.T + np.diag([1e-3, 1e-3, 1e-4]))
    return truth, ij, z, np.array(covs)


def exact_relative_covariances(truth, ij, z, cov, source):
    fg = gtsam.NonlinearFactorGraph()
    for (i, j), zz, c in zip(ij.tolist(), z, cov, strict=True):
        fg.add(
            gtsam.BetweenFactorPose2(i, j, se2.pose2(zz), gtsam.noiseModel.Gaussian.Covariance(c))
        )
    # Fix the source: its prior is far tighter than any edge.
    fg.add(
        gtsam.PriorFactorPose2(
            source, se2.pose2(truth[source]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-7)
        )
    )
    values = gtsam.Values()
    for k, p in enumerate(truth):
        values.insert(k, se2.pose2(p))
    marginals = gtsam.Marginals(fg, values)
    out = {}
    for v in range(len(truth)):
        if v == source:
            continue
        joint = marginals.jointMarginalCovariance(gtsam.KeyVector([source, v])).fullMatrix()
        out[v] = relative_covariance(joint, truth[source], truth[v])
    return out


@pytest.mark.parametrize("seed", range(6))
def test_upper_bounds_exact_marginals(seed: int) -> None:
    truth, ij, z, cov = random_graph(seed, n=25, loops=12)
    source = seed % 5
    exact = exact_relative_covariances(truth, ij, z, cov, source)
    proj = dijkstra_projection(Adjacency.from_arrays(25, ij, z, cov), source)
    assert proj.reached.all()
    for v, c_exact in exact.items():
        c_proj = proj.covariances[v]
        assert np.trace(c_proj) >= np.trace(c_exact) * (1 - 1e-6)
        # Stronger than the trace: the path covariance dominates in the PSD order.
        assert np.linalg.eigvalsh(c_proj - c_exact).min() > -1e-7 * np.trace(c_exact)
        # Predicted relative pose follows the (consistent) measurements.
        np.testing.assert_allclose(
            se2.between(proj.poses[source], proj.poses[v]),
            se2.between(truth[source], truth[v]),
            atol=1e-9,
        )


def test_exact_on_a_tree() -> None:
    truth, ij, z, cov = random_graph(9, n=15, loops=0)
    exact = exact_relative_covariances(truth, ij, z, cov, 0)
    proj = dijkstra_projection(Adjacency.from_arrays(15, ij, z, cov), 0)
    for v, c_exact in exact.items():
        np.testing.assert_allclose(proj.covariances[v], c_exact, rtol=1e-5, atol=1e-10)


def test_tree_structure_and_early_stop() -> None:
    truth, ij, z, cov = random_graph(4, n=30, loops=10)
    adj = Adjacency.from_arrays(30, ij, z, cov)
    proj = dijkstra_projection(adj, 3)
    assert proj.parent[3] == -1
    assert (proj.parent[np.arange(30) != 3] >= 0).all()
    for v in range(30):  # every node reaches the source through its parents
        seen = 0
        while v != 3:
            v = int(proj.parent[v])
            seen += 1
            assert seen <= 30
    tr = np.trace(proj.covariances, axis1=1, axis2=2)
    limit = float(np.median(tr))
    part = dijkstra_projection(adj, 3, max_trace=limit)
    assert part.reached.sum() < 30
    assert (np.trace(part.covariances[part.reached], axis1=1, axis2=2) <= limit).all()
    one = dijkstra_projection(adj, 3, target=int(np.argmax(tr)))
    np.testing.assert_allclose(
        one.covariances[int(np.argmax(tr))], proj.covariances[int(np.argmax(tr))]
    )


def test_unreached_component() -> None:
    adj = Adjacency(4)
    adj.add(0, 1, np.array([1.0, 0, 0]), np.eye(3) * 0.01)
    adj.add(2, 3, np.array([1.0, 0, 0]), np.eye(3) * 0.01)
    proj = dijkstra_projection(adj, 0)
    assert proj.reached.tolist() == [True, True, False, False]
    assert np.isinf(proj.covariances[2]).all()
    with pytest.raises(ValueError, match="source 9"):
        dijkstra_projection(adj, 9)


def test_incremental_adjacency_equals_bulk() -> None:
    truth, ij, z, cov = random_graph(3, n=40, loops=25)
    bulk = Adjacency.from_arrays(40, ij, z, cov)
    grown = Adjacency(40, capacity=1)  # forces the pools to grow several times
    for e in range(len(ij)):
        grown.add(int(ij[e, 0]), int(ij[e, 1]), z[e], cov[e], edge_index=e)
    assert grown.num_edges == bulk.num_edges == len(ij)
    for source in (0, 17):
        a = dijkstra_projection(bulk, source)
        b = dijkstra_projection(grown, source)
        np.testing.assert_allclose(a.poses, b.poses, atol=1e-12)
        np.testing.assert_allclose(a.covariances, b.covariances, rtol=1e-12)
        np.testing.assert_array_equal(a.parent_edge >= 0, b.parent_edge >= 0)
    with pytest.raises(ValueError, match="endpoints"):
        grown.add(0, 40, z[0], cov[0])
    with pytest.raises(ValueError, match="endpoints"):
        Adjacency.from_arrays(3, np.array([[0, 3]]), z[:1], cov[:1])


def test_projected_trace_is_the_projections_trace_at_the_target_query_after_query() -> None:
    truth, ij, z, cov = random_graph(5, 60, 25)
    adj = Adjacency.from_arrays(60, ij, z, cov)
    rng = np.random.default_rng(9)
    for _ in range(40):  # the scratch arrays are reused: every query starts clean
        a, b = (int(v) for v in rng.choice(60, 2, replace=False))
        limit = float(rng.choice([np.inf, rng.uniform(0.0, 0.5)]))
        full = dijkstra_projection(adj, a, target=b, max_trace=limit)
        want = float(np.trace(full.covariances[b])) if full.reached[b] else np.inf
        assert projected_trace(adj, a, b, limit) == want
    best, done, _cov, _touched = adj.scratch()
    assert np.all(np.isinf(best)) and not done.any()
    with pytest.raises(ValueError, match="out of range"):
        projected_trace(adj, 0, 60, 1.0)


def test_an_adjacency_grown_node_by_node_projects_as_one_built_whole() -> None:
    truth, ij, z, cov = random_graph(6, 50, 20)
    whole = Adjacency.from_arrays(50, ij, z, cov)
    grown = Adjacency(0)
    for m, (i, j) in enumerate(ij.tolist()):
        if max(i, j) >= grown.n:
            grown.add_nodes(max(i, j) + 1 - grown.n)
        grown.add(i, j, z[m], cov[m], edge_index=m)
    assert grown.n == 50 and grown.num_edges == whole.num_edges
    a = dijkstra_projection(whole, 3)
    b = dijkstra_projection(grown, 3)
    assert np.allclose(a.covariances, b.covariances) and np.allclose(a.poses, b.poses)
    assert projected_trace(grown, 3, 40, np.inf) == pytest.approx(
        float(np.trace(a.covariances[40]))
    )
    with pytest.raises(ValueError, match="count must be >= 0"):
        grown.add_nodes(-1)
