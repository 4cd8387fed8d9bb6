"""Bounded travel distances on the planning grid (paper 5.1.1: "the acquisition cost is
estimated as the distance a robot must travel to reach the goal").

Dijkstra's algorithm from one cell over the 8-connected traversable cells (a diagonal move only
when both cells it cuts between are traversable, so paths never squeeze between two diagonal
obstacles), moves of ``resolution_m`` and ``sqrt(2) * resolution_m``. The search stops at
``limit_m``: the paper first searches only "up to a set distance away, e.g. 20 m", which keeps
the cost of a plan proportional to the searched disc rather than to the map. Checked against
``scipy.sparse.csgraph.dijkstra`` (``limit``) on the same graph in the tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba as nb
import numpy as np
from numpy.typing import NDArray

__all__ = ["GridDistances", "grid_distances"]

_DR = np.array([-1, 1, 0, 0, -1, -1, 1, 1], dtype=np.int64)
_DC = np.array([0, 0, -1, 1, -1, 1, -1, 1], dtype=np.int64)


@dataclass(frozen=True)
class GridDistances:
    """Travel distances from ``start`` over the window of the grid the search could reach:
    ``distance_m`` ``(h, w)`` covers rows ``offset[0]..`` and columns ``offset[1]..`` (``inf``
    beyond the limit or unreachable); ``parent`` the window-flat index of each settled cell's
    predecessor (-1 at the start and for unsettled cells). Use :meth:`at` and
    :meth:`path_cells` with full-grid cells."""

    start: tuple[int, int]
    offset: tuple[int, int]
    distance_m: NDArray[np.float64]
    parent: NDArray[np.int32]

    def at(self, cells: NDArray[np.int64]) -> NDArray[np.float64]:
        """``(N,)`` distances of full-grid ``cells`` ``(N, 2)`` (``inf`` outside the window)."""
        rc = np.asarray(cells, dtype=np.int64).reshape(-1, 2) - np.asarray(self.offset)
        h, w = self.distance_m.shape
        ok = (rc[:, 0] >= 0) & (rc[:, 0] < h) & (rc[:, 1] >= 0) & (rc[:, 1] < w)
        out = np.full(len(rc), np.inf)
        out[ok] = self.distance_m[rc[ok, 0], rc[ok, 1]]
        return out

    def path_cells(self, goal: tuple[int, int]) -> NDArray[np.int64]:
        """``(K, 2)`` full-grid cells from ``start`` to ``goal`` (empty if not reached)."""
        if not math.isfinite(float(self.at(np.asarray([goal]))[0])):
            return np.zeros((0, 2), dtype=np.int64)
        h, w = self.distance_m.shape
        out = []
        u = (goal[0] - self.offset[0]) * w + (goal[1] - self.offset[1])
        while u >= 0:
            out.append(u)
            u = int(self.parent[u])
        flat = np.asarray(out[::-1], dtype=np.int64)
        return np.stack([flat // w + self.offset[0], flat % w + self.offset[1]], axis=1)


@nb.njit(cache=True, nogil=True)
def _bounded_dijkstra(passable, res, start, limit, dr, dc):  # type: ignore[no-untyped-def]
    rows, cols = passable.shape
    n = rows * cols
    flat = passable.ravel()
    dist = np.full(n, np.inf)
    parent = np.full(n, -1, dtype=np.int32)
    done = np.zeros(n, dtype=np.bool_)
    cap = 1024
    hk = np.empty(cap)
    hv = np.empty(cap, dtype=np.int64)
    size = 0
    dist[start] = 0.0
    hk[0] = 0.0
    hv[0] = start
    size = 1
    diag = res * 1.4142135623730951
    while size > 0:
        # pop the minimum (binary heap, lazy deletion)
        d = hk[0]
        u = hv[0]
        size -= 1
        key = hk[size]
        val = hv[size]
        i = 0
        while True:
            ch = 2 * i + 1
            if ch >= size:
                break
            if ch + 1 < size and hk[ch + 1] < hk[ch]:
                ch += 1
            if hk[ch] >= key:
                break
            hk[i] = hk[ch]
            hv[i] = hv[ch]
            i = ch
        if size > 0:
            hk[i] = key
            hv[i] = val
        if done[u]:
            continue
        done[u] = True
        ur = u // cols
        uc = u - ur * cols
        for k in range(8):
            vr = ur + dr[k]
            vc = uc + dc[k]
            if vr < 0 or vr >= rows or vc < 0 or vc >= cols:
                continue
            v = vr * cols + vc
            if done[v] or not flat[v]:
                continue
            if k >= 4:
                if not (flat[ur * cols + vc] and flat[vr * cols + uc]):
                    continue
                nd = d + diag
            else:
                nd = d + res
            if nd > limit or nd >= dist[v]:
                continue
            dist[v] = nd
            parent[v] = u
            if size == cap:  # grow the heap
                cap *= 2
                hk2 = np.empty(cap)
                hv2 = np.empty(cap, dtype=np.int64)
                hk2[:size] = hk[:size]
                hv2[:size] = hv[:size]
                hk = hk2
                hv = hv2
            j = size
            size += 1
            while j > 0:
                p = (j - 1) // 2
                if hk[p] <= nd:
                    break
                hk[j] = hk[p]
                hv[j] = hv[p]
                j = p
            hk[j] = nd
            hv[j] = v
    for i in range(n):
        if not done[i]:
            dist[i] = np.inf
            parent[i] = -1
    return dist.reshape(rows, cols), parent


def grid_distances(
    passable: NDArray[np.bool_],
    start: tuple[int, int],
    *,
    resolution_m: float,
    limit_m: float = math.inf,
) -> GridDistances:
    """Travel distances from ``start`` over ``passable`` cells up to ``limit_m``. The start cell
    itself need not be passable (a robot standing in a wall's clearance band drives out)."""
    grid = np.ascontiguousarray(passable, dtype=np.bool_)
    if grid.ndim != 2:
        raise ValueError(f"passable must be 2-D, got shape {grid.shape}")
    r, c = int(start[0]), int(start[1])
    if not (0 <= r < grid.shape[0] and 0 <= c < grid.shape[1]):
        raise ValueError(f"start {start} is outside the grid of shape {grid.shape}")
    if not (resolution_m > 0 and limit_m >= 0):
        raise ValueError(f"need resolution_m > 0 and limit_m >= 0, got {resolution_m}, {limit_m}")
    rows, cols = grid.shape
    r0, r1, c0, c1 = 0, rows, 0, cols
    if math.isfinite(limit_m):
        # nothing beyond limit_m can be settled: search only that window (the cost of a plan
        # then follows the searched disc, not the map)
        k = int(math.ceil(limit_m / resolution_m)) + 1
        r0, r1, c0, c1 = max(0, r - k), min(rows, r + k + 1), max(0, c - k), min(cols, c + k + 1)
    win = np.ascontiguousarray(grid[r0:r1, c0:c1])
    dist, parent = _bounded_dijkstra(
        win, float(resolution_m), (r - r0) * win.shape[1] + (c - c0), float(limit_m), _DR, _DC
    )
    return GridDistances((r, c), (r0, c0), dist, parent)
