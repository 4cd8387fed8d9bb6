from __future__ import annotations

import numpy as np
import pytest

from gcs.graph.block_cholesky import (
    BlockSymbolic,
    NotPositiveDefiniteError,
    block_slots,
    factorize,
    solve,
    symbolic_factorization,
)
from gcs.graph.emd_ordering import elimination_degrees, factor_nnz, minimum_degree_ordering


def _random_graph(rng: np.random.Generator, n: int, extra: int) -> np.ndarray:
    chain = [(k, k + 1) for k in range(n - 1)]
    loops = [tuple(rng.choice(n, 2, replace=False)) for _ in range(extra)]
    return np.array(chain + loops, dtype=np.int64)


def _assemble(
    rng: np.random.Generator, n: int, edges: np.ndarray, d: int
) -> tuple[np.ndarray, dict[tuple[int, int], np.ndarray]]:
    """A random SPD matrix with d x d blocks on the graph's pattern (dense and by block)."""
    h = np.zeros((n * d, n * d))
    for i, j in edges:
        a = rng.normal(size=(2 * d, d))
        idx = np.r_[i * d : i * d + d, j * d : j * d + d]
        h[np.ix_(idx, idx)] += a @ a.T
    h += np.eye(n * d)
    blocks = {
        (i, j): h[i * d : i * d + d, j * d : j * d + d].copy()
        for i in range(n)
        for j in range(n)
        if np.abs(h[i * d : i * d + d, j * d : j * d + d]).max() > 0
    }
    return h, blocks


def _values(sym: BlockSymbolic, blocks: dict[tuple[int, int], np.ndarray], d: int) -> np.ndarray:
    x = np.zeros((sym.nnz_blocks, d, d))
    for k in range(sym.n):
        for p in range(sym.colptr[k], sym.colptr[k + 1]):
            row_var, col_var = sym.order[sym.rows[p]], sym.order[k]
            x[p] = blocks.get((int(row_var), int(col_var)), np.zeros((d, d)))
    return x


@pytest.mark.parametrize("d", [1, 2, 3])
def test_factor_and_solve_match_dense(d: int) -> None:
    rng = np.random.default_rng(d)
    n = 40
    edges = _random_graph(rng, n, 25)
    h, blocks = _assemble(rng, n, edges, d)
    order = rng.permutation(n)
    sym = symbolic_factorization(n, edges, order)
    x = _values(sym, blocks, d)
    factorize(sym, x)
    # L L' reproduces the permuted matrix.
    lower = np.zeros((n * d, n * d))
    for k in range(n):
        for p in range(sym.colptr[k], sym.colptr[k + 1]):
            r = sym.rows[p]
            lower[r * d : r * d + d, k * d : k * d + d] = x[p]
    perm = (order[:, None] * d + np.arange(d)).ravel()
    np.testing.assert_allclose(lower @ lower.T, h[np.ix_(perm, perm)], atol=1e-9)
    rhs = rng.normal(size=(n, d))
    sol = solve(sym, x, rhs)
    np.testing.assert_allclose(sol.ravel(), np.linalg.solve(h, rhs.ravel()), atol=1e-9)


def test_pattern_size_matches_elimination_degrees() -> None:
    rng = np.random.default_rng(5)
    n = 200
    edges = _random_graph(rng, n, 120)
    for order in (rng.permutation(n), minimum_degree_ordering(n, edges)[0]):
        sym = symbolic_factorization(n, edges, order)
        degrees = elimination_degrees(n, edges, order)
        assert sym.nnz(3) == factor_nnz(degrees, dim=3)
        assert sym.nnz_blocks == n + int(degrees.sum())
        # The elimination tree's parent is the first off-diagonal row of each column.
        for k in range(n):
            first = sym.rows[sym.colptr[k] + 1] if sym.colptr[k + 1] - sym.colptr[k] > 1 else -1
            assert sym.parent[k] == first


def test_not_positive_definite_names_the_variable() -> None:
    edges = np.array([[0, 1], [1, 2]])
    sym = symbolic_factorization(3, edges, np.array([2, 0, 1]))
    x = np.zeros((sym.nnz_blocks, 3, 3))
    x[sym.colptr[:-1]] = np.eye(3)
    x[sym.colptr[sym.position[0]]] = -np.eye(3)
    with pytest.raises(NotPositiveDefiniteError, match="at variable 0"):
        factorize(sym, x)


def test_bad_input_is_rejected() -> None:
    edges = np.array([[0, 1], [1, 2]])
    with pytest.raises(ValueError, match="permutation"):
        symbolic_factorization(3, edges, np.array([0, 0, 1]))
    with pytest.raises(ValueError, match="edge endpoints"):
        symbolic_factorization(3, np.array([[0, 3]]), np.arange(3))
    sym = symbolic_factorization(3, edges, np.arange(3))
    with pytest.raises(ValueError, match=r"block \(0, 2\) is not in the factor's pattern"):
        block_slots(sym, np.array([[0, 2]]))
    with pytest.raises(ValueError, match="values must have shape"):
        factorize(sym, np.zeros((2, 3, 3)))
    with pytest.raises(ValueError, match="rhs must have shape"):
        solve(sym, np.zeros((sym.nnz_blocks, 3, 3)), np.zeros((3, 2)))
