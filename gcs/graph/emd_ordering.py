"""Exact minimum degree (EMD) variable ordering (paper 4.6, Table 1).

The classic minimum degree algorithm on the variables' adjacency graph, computed exactly on the
explicit elimination graph (no approximate degrees, no quotient-graph tricks): repeatedly
eliminate the variable of smallest current degree (ties: smallest index), connecting its
neighbours into a clique. The elimination graph is held as bitsets, one row of
``ceil(n / 64)`` words per variable, so memory is ``n^2 / 8`` bytes (12.5 MB at n = 10000) and
time ``O(sum_v (deg_v + 1) * n / 64)``.

The same kernel counts the fill of any ordering: the number of off-diagonal blocks of the
Cholesky factor is the sum, over eliminated variables, of their degree at elimination time.
With ``d``-dimensional variables the factor holds ``d(d+1)/2 + d^2 deg`` scalars per variable.
"""

from __future__ import annotations

import heapq

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["elimination_degrees", "factor_nnz", "minimum_degree_ordering"]

IntArray = NDArray[np.int64]

_M1 = np.uint64(0x5555555555555555)
_M2 = np.uint64(0x3333333333333333)
_M4 = np.uint64(0x0F0F0F0F0F0F0F0F)
_H01 = np.uint64(0x0101010101010101)


@numba.njit(cache=True, inline="always")
def _popcount(x: np.uint64) -> np.int64:
    x = x - ((x >> np.uint64(1)) & _M1)
    x = (x & _M2) + ((x >> np.uint64(2)) & _M2)
    x = (x + (x >> np.uint64(4))) & _M4
    return np.int64((x * _H01) >> np.uint64(56))


@numba.njit(cache=True)
def _build(n: int, edges: np.ndarray) -> np.ndarray:
    words = (n + 63) // 64
    adj = np.zeros((n, words), dtype=np.uint64)
    one = np.uint64(1)
    for e in range(edges.shape[0]):
        a, b = edges[e, 0], edges[e, 1]
        if a == b:
            continue
        adj[a, b >> 6] |= one << np.uint64(b & 63)
        adj[b, a >> 6] |= one << np.uint64(a & 63)
    return adj


@numba.njit(cache=True)
def _row_degree(adj: np.ndarray, v: int) -> np.int64:
    d = np.int64(0)
    for w in range(adj.shape[1]):
        d += _popcount(adj[v, w])
    return d


@numba.njit(cache=True)
def _eliminate(adj: np.ndarray, v: int, nbrs: np.ndarray) -> int:
    """Eliminate ``v``: write its neighbours into ``nbrs``, make them a clique; return count."""
    words = adj.shape[1]
    one = np.uint64(1)
    k = 0
    for w in range(words):
        x = adj[v, w]
        while x != 0:
            low = x & (~x + one)
            bit = _popcount(low - one)
            nbrs[k] = w * 64 + bit
            k += 1
            x ^= low
    vw = v >> 6
    vbit = one << np.uint64(v & 63)
    for t in range(k):
        u = nbrs[t]
        for w in range(words):
            adj[u, w] |= adj[v, w]
        adj[u, u >> 6] &= ~(one << np.uint64(u & 63))
        adj[u, vw] &= ~vbit
    for w in range(words):
        adj[v, w] = 0
    return k


@numba.njit(cache=True)
def _min_degree(n: int, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    adj = _build(n, edges)
    deg = np.zeros(n, dtype=np.int64)
    heap = [np.int64(0)] * 0
    for v in range(n):
        deg[v] = _row_degree(adj, v)
        heap.append(deg[v] * n + v)
    heapq.heapify(heap)
    alive = np.ones(n, dtype=np.bool_)
    order = np.empty(n, dtype=np.int64)
    elim_deg = np.empty(n, dtype=np.int64)
    nbrs = np.empty(n, dtype=np.int64)
    pos = 0
    while pos < n:
        item = heapq.heappop(heap)
        v = item % n
        if not alive[v] or item // n != deg[v]:
            continue
        k = _eliminate(adj, v, nbrs)
        alive[v] = False
        order[pos] = v
        elim_deg[pos] = k
        pos += 1
        for t in range(k):
            u = nbrs[t]
            d = _row_degree(adj, u)
            if d != deg[u]:
                deg[u] = d
                heapq.heappush(heap, d * n + u)
    return order, elim_deg


@numba.njit(cache=True)
def _fill(n: int, edges: np.ndarray, order: np.ndarray) -> np.ndarray:
    adj = _build(n, edges)
    nbrs = np.empty(n, dtype=np.int64)
    elim_deg = np.empty(n, dtype=np.int64)
    for pos in range(n):
        elim_deg[pos] = _eliminate(adj, order[pos], nbrs)
    return elim_deg


def _check(n: int, edges: IntArray) -> IntArray:
    edges = np.ascontiguousarray(np.asarray(edges, dtype=np.int64).reshape(-1, 2))
    if n < 0:
        raise ValueError(f"number of variables must be >= 0, got {n}")
    if edges.size and (edges.min() < 0 or edges.max() >= n):
        raise ValueError(f"edge endpoints must lie in 0..{n - 1}")
    return edges


def minimum_degree_ordering(n: int, edges: IntArray) -> tuple[IntArray, IntArray]:
    """Exact minimum degree ordering of ``n`` variables linked by ``edges`` (M, 2) indices.

    Returns ``(order, degrees)``: variable indices in elimination order and each one's degree
    when eliminated (the number of off-diagonal blocks it contributes to the factor).
    Ties are broken by the smallest index, so the result is deterministic.
    """
    edges = _check(n, edges)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    return _min_degree(n, edges)


def elimination_degrees(n: int, edges: IntArray, order: IntArray) -> IntArray:
    """Degree of each variable at its elimination under ``order`` (a permutation of 0..n-1)."""
    edges = _check(n, edges)
    order = np.ascontiguousarray(np.asarray(order, dtype=np.int64))
    if order.shape != (n,) or not np.array_equal(np.sort(order), np.arange(n)):
        raise ValueError(f"order must be a permutation of 0..{n - 1}")
    return _fill(n, edges, order)


def factor_nnz(degrees: IntArray, *, dim: int = 3) -> int:
    """Non-zeros of the triangular factor given :func:`elimination_degrees` (``dim`` a variable)."""
    degrees = np.asarray(degrees, dtype=np.int64)
    return int(degrees.size * dim * (dim + 1) // 2 + dim * dim * int(degrees.sum()))
