"""Dijkstra projection: upper bounds on relative pose uncertainty (Bosse 2004; Olson 2008).

Paper 4.6 and 4.7 use it wherever marginals are needed: the covariance of the relative pose
``source^-1 * v`` is propagated along the path from ``source`` to ``v`` that minimises the trace
of the propagated covariance, composing the edges' Gaussians. A single path ignores the
information of every other path, so the result bounds the exact conditional covariance from
above (checked against GTSAM's exact marginals in the tests).

Conventions: edge ``e`` links indices ``ij[e] = (i, j)`` with measurement ``z[e] = i_from_j``
and covariance ``cov[e]`` in the tangent space of ``j`` (GTSAM ``BetweenFactorPose2``);
traversing it backwards uses ``z^-1`` with covariance ``Ad_z cov Ad_z'``. Covariances of the
results are in the body frame of the reached pose, with the source fixed.

Cost: ``O((n + m) log n)`` relaxations of 3x3 matrix products, compiled with numba.
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from gcs.graph import se2

__all__ = [
    "Adjacency",
    "ProjectionResult",
    "dijkstra_projection",
    "projected_trace",
    "relative_covariance",
]

FloatArray = NDArray[np.floating[Any]]
IntArray = NDArray[np.int64]


def _ad(p: Sequence[float]) -> FloatArray:
    c, s = math.cos(p[2]), math.sin(p[2])
    return np.array([[c, -s, p[1]], [s, c, -p[0]], [0.0, 0.0, 1.0]])


def _compose(a: Sequence[float], b: Sequence[float]) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    th = a[2] + b[2]
    th = (th + math.pi) % (2.0 * math.pi) - math.pi
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], th)


def _inverse(a: Sequence[float]) -> tuple[float, float, float]:
    c, s = math.cos(a[2]), math.sin(a[2])
    return (-c * a[0] - s * a[1], s * a[0] - c * a[1], -a[2])


class Adjacency:
    """Directed traversal steps of an undirected edge set, grown edge by edge.

    Every edge ``i -> j`` is stored in both directions in array pools (linked lists per node),
    each direction with its step ``from_i_to_j`` pose and step covariance, so that edges can be
    added in O(1) between queries (Algorithm 1 alternates the two) and the compiled search
    needs no per-edge adjoint of the measurement.
    """

    def __init__(self, n: int, *, capacity: int = 16) -> None:
        self.n = n
        self.num_edges = 0
        self._size = 0
        cap = max(2, 2 * capacity)
        self.head = np.full(n, -1, dtype=np.int64)
        self.next = np.full(cap, -1, dtype=np.int64)
        self.to = np.zeros(cap, dtype=np.int64)
        self.edge = np.zeros(cap, dtype=np.int64)
        self.step = np.zeros((cap, 3))
        self.step_cov = np.zeros((cap, 3, 3))
        # scratch of projected_trace, kept between queries (reset where a query wrote)
        self._scratch: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None

    def scratch(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Per-node work arrays of :func:`projected_trace` (best trace, settled, covariance,
        touched list), allocated once: a query then costs what it visits, not ``O(n)``."""
        if self._scratch is None or len(self._scratch[0]) != self.n:
            self._scratch = (
                np.full(self.n, np.inf),
                np.zeros(self.n, dtype=np.bool_),
                np.zeros((self.n, 3, 3)),
                np.zeros(self.n, dtype=np.int64),
            )
        return self._scratch

    @classmethod
    def from_arrays(cls, n: int, ij: IntArray, z: FloatArray, cov: FloatArray) -> Adjacency:
        """Adjacency of ``n`` nodes and edges ``ij`` (M, 2), ``z`` (M, 3), ``cov`` (M, 3, 3)."""
        ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
        m = len(ij)
        adj = cls(n, capacity=max(m, 1))
        if m == 0:
            return adj
        if ij.min() < 0 or ij.max() >= n:
            raise ValueError(f"edge endpoints must lie in 0..{n - 1}")
        z = np.asarray(z, dtype=float).reshape(m, 3)
        cov = np.asarray(cov, dtype=float).reshape(m, 3, 3)
        ad = _ad_batch(z)
        slots = np.arange(2 * m)
        adj.to[0::2][:m], adj.to[1::2][:m] = ij[:, 1], ij[:, 0]
        adj.edge[0 : 2 * m : 2] = np.arange(m)
        adj.edge[1 : 2 * m : 2] = np.arange(m)
        adj.step[0 : 2 * m : 2] = z
        adj.step[1 : 2 * m : 2] = se2.inverse(z)
        adj.step_cov[0 : 2 * m : 2] = cov
        adj.step_cov[1 : 2 * m : 2] = ad @ cov @ ad.transpose(0, 2, 1)
        src = np.empty(2 * m, dtype=np.int64)
        src[0::2], src[1::2] = ij[:, 0], ij[:, 1]
        _link_all(adj.head, adj.next, src, slots)
        adj._size = 2 * m
        adj.num_edges = m
        return adj

    def add_nodes(self, count: int) -> None:
        """Append ``count`` nodes without edges (indices ``n .. n + count - 1``): a mirror of
        a growing graph extends its adjacency instead of rebuilding it
        (:meth:`gcs.graph.pose_graph.PoseGraph.additions_since`)."""
        if count < 0:
            raise ValueError(f"add_nodes: count must be >= 0, got {count}")
        if count:
            self.head = np.concatenate([self.head, np.full(count, -1, dtype=np.int64)])
            self.n += count
            self._scratch = None

    def _grow(self) -> None:
        cap = 2 * len(self.next)
        self.next = np.concatenate([self.next, np.full(cap - len(self.next), -1, np.int64)])
        self.to = np.resize(self.to, cap)
        self.edge = np.resize(self.edge, cap)
        self.step = np.resize(self.step, (cap, 3))
        self.step_cov = np.resize(self.step_cov, (cap, 3, 3))

    def add(
        self, i: int, j: int, z_i_from_j: FloatArray, cov: FloatArray, *, edge_index: int = -1
    ) -> None:
        """Add edge ``i -> j``: measurement ``i_from_j`` and its covariance (both directions)."""
        if not (0 <= i < self.n and 0 <= j < self.n):
            raise ValueError(f"edge {i} -> {j}: endpoints must lie in 0..{self.n - 1}")
        if self._size + 2 > len(self.next):
            self._grow()
        z = np.asarray(z_i_from_j, dtype=float)
        cov = np.asarray(cov, dtype=float)
        ad = se2.adjoint(z)
        for slot, src, dst, step, scov in (
            (self._size, i, j, z, cov),
            (self._size + 1, j, i, se2.inverse(z), ad @ cov @ ad.T),
        ):
            self.to[slot] = dst
            self.edge[slot] = edge_index
            self.step[slot] = step
            self.step_cov[slot] = scov
            self.next[slot] = self.head[src]
            self.head[src] = slot
        self._size += 2
        self.num_edges += 1


def _ad_batch(z: FloatArray) -> FloatArray:
    c, s = np.cos(z[:, 2]), np.sin(z[:, 2])
    out = np.zeros((len(z), 3, 3))
    out[:, 0, 0], out[:, 0, 1], out[:, 0, 2] = c, -s, z[:, 1]
    out[:, 1, 0], out[:, 1, 1], out[:, 1, 2] = s, c, -z[:, 0]
    out[:, 2, 2] = 1.0
    return out


@numba.njit(cache=True)
def _link_all(head: np.ndarray, nxt: np.ndarray, src: np.ndarray, slots: np.ndarray) -> None:
    for k in range(src.size):
        nxt[slots[k]] = head[src[k]]
        head[src[k]] = slots[k]


@dataclass(frozen=True)
class ProjectionResult:
    """Result of :func:`dijkstra_projection` for every node (index order).

    ``poses`` (n, 3): ``source_pose * path`` (NaN where unreached); ``covariances`` (n, 3, 3)
    (inf where unreached); ``parent`` / ``parent_edge`` (n,): the shortest-path tree (the
    minimum-uncertainty spanning tree), -1 at the source and at unreached nodes.
    """

    poses: FloatArray
    covariances: FloatArray
    parent: IntArray
    parent_edge: IntArray

    @property
    def reached(self) -> NDArray[np.bool_]:
        """Nodes the projection reached."""
        return np.isfinite(self.poses[:, 0])


@numba.njit(cache=True)
def _stepped_cov(
    cov_v: np.ndarray, st: np.ndarray, cov_step: np.ndarray, ad: np.ndarray
) -> np.ndarray:
    """Covariance of ``x_w = x_v * st`` (in ``w``'s frame): ``Ad cov_v Ad' + cov_step`` with
    ``Ad`` the adjoint of the inverse step, written into the caller's scratch ``ad`` (its last
    row stays ``(0, 0, 1)``)."""
    c, s = math.cos(st[2]), math.sin(st[2])
    ix = -c * st[0] - s * st[1]
    iy = s * st[0] - c * st[1]
    ad[0, 0], ad[0, 1], ad[0, 2] = c, s, iy
    ad[1, 0], ad[1, 1], ad[1, 2] = -s, c, -ix
    return ad @ cov_v @ ad.T + cov_step


@numba.njit(cache=True)
def _search(
    head: np.ndarray,
    nxt: np.ndarray,
    to: np.ndarray,
    edge: np.ndarray,
    step: np.ndarray,
    step_cov: np.ndarray,
    source: int,
    p0: np.ndarray,
    c0: np.ndarray,
    target: int,
    max_trace: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    n = head.size
    poses = np.full((n, 3), np.nan)
    covs = np.full((n, 3, 3), np.inf)
    cand_pose = np.zeros((n, 3))
    cand_cov = np.zeros((n, 3, 3))
    parent = np.full(n, -1, dtype=np.int64)
    parent_edge = np.full(n, -1, dtype=np.int64)
    best = np.full(n, np.inf)
    done = np.zeros(n, dtype=np.bool_)
    cand_pose[source] = p0
    cand_cov[source] = c0
    best[source] = c0[0, 0] + c0[1, 1] + c0[2, 2]
    heap = [(best[source], source)]
    ad = np.zeros((3, 3))
    ad[2, 2] = 1.0
    while len(heap) > 0:
        tr, v = heapq.heappop(heap)
        if done[v] or tr > best[v]:
            continue
        if tr > max_trace:
            break
        done[v] = True
        poses[v] = cand_pose[v]
        covs[v] = cand_cov[v]
        if v == target:
            break
        pv = cand_pose[v]
        cv = cand_cov[v]
        cv_, sv = math.cos(pv[2]), math.sin(pv[2])
        slot = head[v]
        while slot >= 0:
            w = to[slot]
            if not done[w]:
                st = step[slot]
                cw = _stepped_cov(cv, st, step_cov[slot], ad)
                t = cw[0, 0] + cw[1, 1] + cw[2, 2]
                if t < best[w]:
                    best[w] = t
                    cand_cov[w] = cw
                    th = pv[2] + st[2]
                    cand_pose[w, 0] = pv[0] + cv_ * st[0] - sv * st[1]
                    cand_pose[w, 1] = pv[1] + sv * st[0] + cv_ * st[1]
                    cand_pose[w, 2] = (th + math.pi) % (2.0 * math.pi) - math.pi
                    parent[w] = v
                    parent_edge[w] = edge[slot]
                    heapq.heappush(heap, (t, w))
            slot = nxt[slot]
    for v in range(n):
        if not done[v]:
            parent[v] = -1
            parent_edge[v] = -1
    return poses, covs, parent, parent_edge


def dijkstra_projection(
    adjacency: Adjacency,
    source: int,
    *,
    source_pose: FloatArray | None = None,
    source_covariance: FloatArray | None = None,
    target: int | None = None,
    max_trace: float = math.inf,
) -> ProjectionResult:
    """Minimum-trace covariance paths from ``source`` (see module docstring).

    ``source_pose`` / ``source_covariance`` (default identity / zero) start the propagation.
    The search stops early once ``target`` is settled or the smallest open trace exceeds
    ``max_trace`` (nodes beyond stay unreached).
    """
    n = adjacency.n
    if not 0 <= source < n:
        raise ValueError(f"source {source} out of range 0..{n - 1}")
    p0 = np.zeros(3) if source_pose is None else np.asarray(source_pose, dtype=float)
    c0 = np.zeros((3, 3)) if source_covariance is None else np.asarray(source_covariance, float)
    poses, covs, parent, parent_edge = _search(
        adjacency.head,
        adjacency.next,
        adjacency.to,
        adjacency.edge,
        adjacency.step,
        adjacency.step_cov,
        int(source),
        np.ascontiguousarray(p0),
        np.ascontiguousarray(c0),
        -1 if target is None else int(target),
        float(max_trace),
    )
    return ProjectionResult(poses, covs, parent, parent_edge)


def projected_trace(adjacency: Adjacency, source: int, target: int, max_trace: float) -> float:
    """Trace of the Dijkstra-projection covariance of ``source^-1 * target`` (the minimum
    over paths, source fixed), or ``inf`` when the target is not reached within
    ``max_trace``: what :func:`dijkstra_projection` with ``target`` and ``max_trace`` gives
    for that one node, at the cost of the nodes the search visits rather than of the whole
    graph (Algorithm 1 asks once per edge: at 15,000 poses the per-query ``O(n)`` arrays of
    the full projection dominated)."""
    n = adjacency.n
    if not (0 <= source < n and 0 <= target < n):
        raise ValueError(f"source {source} / target {target} out of range 0..{n - 1}")
    best, done, cand_cov, touched = adjacency.scratch()
    return float(
        _trace_to(
            adjacency.head,
            adjacency.next,
            adjacency.to,
            adjacency.step,
            adjacency.step_cov,
            int(source),
            int(target),
            float(max_trace),
            best,
            done,
            cand_cov,
            touched,
        )
    )


@numba.njit(cache=True)
def _trace_to(
    head: np.ndarray,
    nxt: np.ndarray,
    to: np.ndarray,
    step: np.ndarray,
    step_cov: np.ndarray,
    source: int,
    target: int,
    max_trace: float,
    best: np.ndarray,
    done: np.ndarray,
    cand_cov: np.ndarray,
    touched: np.ndarray,
) -> float:
    # the same relaxation as _search (covariances only: they do not depend on the poses),
    # on scratch arrays that are put back to their initial state for the nodes touched
    n_touched = 1
    touched[0] = source
    best[source] = 0.0
    cand_cov[source] = 0.0
    heap = [(0.0, source)]
    result = np.inf
    ad = np.zeros((3, 3))
    ad[2, 2] = 1.0
    while len(heap) > 0:
        tr, v = heapq.heappop(heap)
        if done[v] or tr > best[v]:
            continue
        if tr > max_trace:
            break
        done[v] = True
        if v == target:
            result = tr
            break
        cv = cand_cov[v]
        slot = head[v]
        while slot >= 0:
            w = to[slot]
            if not done[w]:
                cw = _stepped_cov(cv, step[slot], step_cov[slot], ad)
                t = cw[0, 0] + cw[1, 1] + cw[2, 2]
                if t < best[w]:
                    if best[w] == np.inf:
                        touched[n_touched] = w
                        n_touched += 1
                    best[w] = t
                    cand_cov[w] = cw
                    heapq.heappush(heap, (t, w))
            slot = nxt[slot]
    for k in range(n_touched):
        best[touched[k]] = np.inf
        done[touched[k]] = False
    return result


def relative_covariance(
    joint_cov: FloatArray, pose_a: FloatArray, pose_b: FloatArray
) -> FloatArray:
    """Covariance of ``a^-1 b`` (body frame of ``b``) from the 6x6 joint covariance of ``a, b``.

    First order: ``d(a^-1 b) = -Ad_{b^-1 a} da + db``. Used to compare exact marginals with
    :func:`dijkstra_projection`.
    """
    j = np.hstack([-se2.adjoint(se2.between(pose_b, pose_a)), np.eye(3)])
    return j @ joint_cov @ j.T
