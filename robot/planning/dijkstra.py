"""Minimum-distance paths by Dijkstra's algorithm on the 8-connected grid (paper 5.4, Fig. 16c).

Cells carry a traversal cost multiplier ``cost`` (``1`` free, ``> 1`` e.g. unknown terrain,
``inf`` blocked in configuration space). The graph joins each cell to its 8 neighbours; a move
of length ``L`` (1 or sqrt 2 cells, times ``resolution_m``) between cells ``u`` and ``v``
weighs ``L * (cost[u] + cost[v]) / 2``. A diagonal move is allowed only when both cells it
cuts between are passable, so paths never squeeze between two diagonal obstacles.

The search is a binary-heap Dijkstra (lazy deletion) compiled with numba, stopping when the
goal is settled: cells farther than the solution are never expanded, as in the paper's
Fig. 16(c). ``O(n log n)`` for ``n`` cells examined. It is checked against
``scipy.sparse.csgraph.dijkstra`` on the same graph (:func:`grid_graph`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

__all__ = ["DijkstraResult", "dijkstra_grid", "grid_graph"]

SQRT2 = math.sqrt(2.0)
_DR = np.array([-1, 1, 0, 0, -1, -1, 1, 1], dtype=np.int64)
_DC = np.array([0, 0, -1, 1, -1, 1, -1, 1], dtype=np.int64)


@dataclass(frozen=True)
class DijkstraResult:
    """``distance_m``: cost-weighted distance from the start of every settled cell (``inf``
    elsewhere); ``path_cells``: ``(K, 2)`` (row, col) from start to goal, empty if the goal is
    unreachable; ``length_m``: the goal's distance (``inf`` if unreachable)."""

    distance_m: NDArray[np.float64]
    path_cells: NDArray[np.int64]
    length_m: float

    @property
    def found(self) -> bool:
        return math.isfinite(self.length_m)


@nb.njit(cache=True, nogil=True)
def _heap_push(hk, hv, size, key, val):  # type: ignore[no-untyped-def]
    i = size
    hk[i] = key
    hv[i] = val
    while i > 0:
        p = (i - 1) >> 1
        if hk[p] <= key:
            break
        hk[i] = hk[p]
        hv[i] = hv[p]
        i = p
    hk[i] = key
    hv[i] = val
    return size + 1


@nb.njit(cache=True, nogil=True)
def _heap_pop(hk, hv, size):  # type: ignore[no-untyped-def]
    top_k = hk[0]
    top_v = hv[0]
    size -= 1
    key = hk[size]
    val = hv[size]
    i = 0
    while True:
        c = 2 * i + 1
        if c >= size:
            break
        if c + 1 < size and hk[c + 1] < hk[c]:
            c += 1
        if hk[c] >= key:
            break
        hk[i] = hk[c]
        hv[i] = hv[c]
        i = c
    if size > 0:
        hk[i] = key
        hv[i] = val
    return top_k, top_v, size


@nb.njit(cache=True, nogil=True)
def _dijkstra(cost, res, start, goal, dr, dc, astar):  # type: ignore[no-untyped-def]
    rows, cols = cost.shape
    n = rows * cols
    flat = cost.ravel()
    dist = np.full(n, np.inf)
    parent = np.full(n, -1, dtype=np.int32)
    done = np.zeros(n, dtype=np.bool_)
    cap = 8 * n + 8
    hk = np.empty(cap)
    hv = np.empty(cap, dtype=np.int32)
    size = 0
    dist[start] = 0.0
    gr = goal // cols
    gc = goal - gr * cols
    diag = res * 1.4142135623730951
    size = _heap_push(hk, hv, size, 0.0, start)
    while size > 0:
        _, u, size = _heap_pop(hk, hv, size)
        if done[u]:
            continue
        done[u] = True
        if u == goal:
            break
        d = dist[u]
        ur = u // cols
        uc = u - ur * cols
        cu = flat[u]
        for k in range(8):
            vr = ur + dr[k]
            vc = uc + dc[k]
            if vr < 0 or vr >= rows or vc < 0 or vc >= cols:
                continue
            v = vr * cols + vc
            cv = flat[v]
            if done[v] or not cv < np.inf:
                continue
            if k >= 4:
                if not (flat[ur * cols + vc] < np.inf and flat[vr * cols + uc] < np.inf):
                    continue
                nd = d + diag * 0.5 * (cu + cv)
            else:
                nd = d + res * 0.5 * (cu + cv)
            if nd < dist[v]:
                dist[v] = nd
                parent[v] = u
                key = nd
                if astar:  # octile distance to the goal: a consistent lower bound (cost >= 1)
                    ar = abs(vr - gr)
                    ac = abs(vc - gc)
                    key += res * (max(ar, ac) - min(ar, ac)) + diag * min(ar, ac)
                size = _heap_push(hk, hv, size, key, v)
    for i in range(n):
        if not done[i]:
            dist[i] = np.inf
    return dist.reshape(rows, cols), parent


def _check(cost: NDArray[np.float64], start: tuple[int, int], goal: tuple[int, int] | None) -> None:
    if cost.ndim != 2 or cost.size == 0:
        raise ValueError(f"cost: expected a non-empty 2D grid, got shape {cost.shape}")
    if np.isnan(cost).any() or (cost < 1.0).any():
        raise ValueError("cost: values must be >= 1 (free) or inf (blocked), no NaN")
    cells = [("start", start)] if goal is None else [("start", start), ("goal", goal)]
    for name, (r, c) in cells:
        if not (0 <= r < cost.shape[0] and 0 <= c < cost.shape[1]):
            raise ValueError(f"{name} cell ({r}, {c}) is outside the {cost.shape} grid")


def dijkstra_grid(
    cost: NDArray[np.float64],
    start: tuple[int, int],
    goal: tuple[int, int] | None,
    *,
    resolution_m: float = 1.0,
    astar: bool = False,
) -> DijkstraResult:
    """Minimum-cost 8-connected path from ``start`` to ``goal`` (``(row, col)`` cells).

    Unreachable goal (or blocked start/goal): ``length_m = inf`` and an empty path.
    ``goal=None`` settles every reachable cell (the full distance field, no path).

    ``astar=True`` orders the heap by distance plus the octile distance to the goal. With
    costs ``>= 1`` that heuristic never exceeds the cost of the remaining path and is
    consistent (``h(u) <= w(u, v) + h(v)``: octile distance is the exact free-grid distance and
    ``w`` is at least the step length), so the goal is settled at exactly Dijkstra's distance
    while far fewer cells are expanded; ``distance_m`` is then exact only for settled cells on
    the way, and the path may differ from Dijkstra's among equal-length ones.
    """
    cost = np.ascontiguousarray(cost, dtype=np.float64)
    _check(cost, start, goal)
    rows, cols = cost.shape
    s = int(start[0]) * cols + int(start[1])
    g = -1 if goal is None else int(goal[0]) * cols + int(goal[1])
    if not (np.isfinite(cost.flat[s]) and (g < 0 or np.isfinite(cost.flat[g]))):
        return DijkstraResult(np.full(cost.shape, np.inf), np.empty((0, 2), np.int64), math.inf)
    dist, parent = _dijkstra(cost, float(resolution_m), s, g, _DR, _DC, bool(astar and g >= 0))
    if g < 0:
        return DijkstraResult(dist, np.empty((0, 2), np.int64), math.inf)
    length = float(dist.flat[g])
    if not math.isfinite(length):
        return DijkstraResult(dist, np.empty((0, 2), np.int64), math.inf)
    chain = [g]
    while chain[-1] != s:
        chain.append(int(parent[chain[-1]]))
    idx = np.array(chain[::-1], dtype=np.int64)
    return DijkstraResult(dist, np.stack([idx // cols, idx % cols], axis=1), length)


def grid_graph(cost: NDArray[np.float64], *, resolution_m: float = 1.0) -> sp.csr_matrix:
    """The same graph as a scipy sparse matrix (for ``scipy.sparse.csgraph``; an oracle)."""
    rows, cols = cost.shape
    passable = np.isfinite(cost)
    src, dst, w = [], [], []
    idx = np.arange(rows * cols).reshape(rows, cols)
    for k in range(8):
        dr, dc = int(_DR[k]), int(_DC[k])
        r0, r1 = max(0, -dr), rows - max(0, dr)
        c0, c1 = max(0, -dc), cols - max(0, dc)
        u = (slice(r0, r1), slice(c0, c1))
        v = (slice(r0 + dr, r1 + dr), slice(c0 + dc, c1 + dc))
        ok = passable[u] & passable[v]
        length = resolution_m
        if dr and dc:
            ok &= passable[r0:r1, c0 + dc : c1 + dc] & passable[r0 + dr : r1 + dr, c0:c1]
            length = resolution_m * SQRT2
        src.append(idx[u][ok])
        dst.append(idx[v][ok])
        w.append(length * 0.5 * (cost[u][ok] + cost[v][ok]))
    n = rows * cols
    return sp.csr_matrix(
        (np.concatenate(w), (np.concatenate(src), np.concatenate(dst))), shape=(n, n)
    )
