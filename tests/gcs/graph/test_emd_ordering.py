from __future__ import annotations

import gtsam
import numpy as np
import pytest

from gcs.graph.emd_ordering import elimination_degrees, factor_nnz, minimum_degree_ordering
from gcs.graph.optimization import compute_ordering, ordering_keys, ordering_nnz


def reference_minimum_degree(n: int, edges: np.ndarray) -> tuple[list[int], list[int]]:
    """Textbook minimum degree on explicit neighbour sets (ties: smallest index)."""
    nbrs: dict[int, set[int]] = {v: set() for v in range(n)}
    for a, b in edges.tolist():
        if a != b:
            nbrs[a].add(b)
            nbrs[b].add(a)
    order, degs = [], []
    while nbrs:
        v = min(nbrs, key=lambda u: (len(nbrs[u]), u))
        ns = nbrs.pop(v)
        for u in ns:
            nbrs[u] |= ns - {u}
            nbrs[u].discard(v)
        order.append(v)
        degs.append(len(ns))
    return order, degs


def reference_fill(n: int, edges: np.ndarray, order: list[int]) -> list[int]:
    nbrs: dict[int, set[int]] = {v: set() for v in range(n)}
    for a, b in edges.tolist():
        if a != b:
            nbrs[a].add(b)
            nbrs[b].add(a)
    degs = []
    for v in order:
        ns = nbrs.pop(v)
        for u in ns:
            nbrs[u] |= ns - {u}
            nbrs[u].discard(v)
        degs.append(len(ns))
    return degs


def random_pose_graph_edges(rng: np.random.Generator, n: int, loops: int) -> np.ndarray:
    chain = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    extra = rng.integers(0, n, size=(loops, 2))
    return np.concatenate([chain, extra[extra[:, 0] != extra[:, 1]]])


@pytest.mark.parametrize("engine", ["bitset", "sparse"])
@pytest.mark.parametrize("seed", range(12))
def test_matches_reference_minimum_degree(seed: int, engine: str) -> None:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(5, 130))
    edges = random_pose_graph_edges(rng, n, int(rng.integers(0, 2 * n)))
    order, degs = minimum_degree_ordering(n, edges, engine=engine)  # type: ignore[arg-type]
    ref_order, ref_degs = reference_minimum_degree(n, edges)
    assert order.tolist() == ref_order
    assert degs.tolist() == ref_degs


@pytest.mark.parametrize("engine", ["bitset", "sparse"])
@pytest.mark.parametrize("seed", range(6))
def test_fill_of_any_ordering_matches_reference(seed: int, engine: str) -> None:
    rng = np.random.default_rng(100 + seed)
    n = 90
    edges = random_pose_graph_edges(rng, n, 60)
    order = rng.permutation(n)
    degs = elimination_degrees(n, edges, order, engine=engine)  # type: ignore[arg-type]
    assert degs.tolist() == reference_fill(n, edges, order.tolist())


def test_minimum_degree_beats_random_orderings() -> None:
    rng = np.random.default_rng(5)
    n = 200
    edges = random_pose_graph_edges(rng, n, 150)
    _, degs = minimum_degree_ordering(n, edges)
    for _ in range(5):
        assert degs.sum() <= elimination_degrees(n, edges, rng.permutation(n)).sum()


def test_nnz_matches_gtsam_symbolic_elimination() -> None:
    """Fill counted here equals the parents of GTSAM's own sequential elimination."""
    rng = np.random.default_rng(11)
    n = 60
    edges = random_pose_graph_edges(rng, n, 40)
    fg = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Unit.Create(3)
    for a, b in edges.tolist():
        fg.add(gtsam.BetweenFactorPose2(a, b, gtsam.Pose2(), noise))
    fg.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), noise))
    values = gtsam.Values()
    for k in range(n):
        values.insert(k, gtsam.Pose2(k, 0, 0))
    for kind in ("colamd", "metis", "natural", "emd"):
        ordering = compute_ordering(fg, kind)
        assert sorted(ordering_keys(ordering).tolist()) == list(range(n))
        bayes_net = fg.linearize(values).eliminateSequential(ordering)
        parents = sum(len(bayes_net.at(i).keys()) - 1 for i in range(bayes_net.size()))
        degs = elimination_degrees(n, edges, ordering_keys(ordering))
        assert int(degs.sum()) == parents
        assert ordering_nnz(fg, ordering) == factor_nnz(degs) == 6 * n + 9 * parents


def test_engines_agree_on_a_large_graph() -> None:
    rng = np.random.default_rng(21)
    n = 3000
    edges = random_pose_graph_edges(rng, n, 400)
    a = minimum_degree_ordering(n, edges, engine="bitset")
    b = minimum_degree_ordering(n, edges, engine="sparse")
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="unknown engine"):
        minimum_degree_ordering(2, np.array([[0, 1]]), engine="dense")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="edge endpoints"):
        minimum_degree_ordering(3, np.array([[0, 3]]))
    with pytest.raises(ValueError, match="permutation"):
        elimination_degrees(3, np.array([[0, 1]]), np.array([0, 0, 1]))
    order, degs = minimum_degree_ordering(0, np.zeros((0, 2), dtype=np.int64))
    assert order.size == degs.size == 0
