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

Cost: ``O((n + m) log n)`` relaxations of 3x3 matrix products (pure Python/numpy).
"""

from __future__ import annotations

import heapq
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from gcs.graph import se2

__all__ = ["Adjacency", "ProjectionResult", "dijkstra_projection", "relative_covariance"]

FloatArray = NDArray[np.float64]
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

    ``steps[i]`` lists ``(j, step_i_from_j, step_covariance, edge_index)`` for both directions
    of every edge, so that queries need no per-edge adjoint computations.
    """

    def __init__(self, n: int) -> None:
        self.n = n
        self.steps: list[list[tuple[int, tuple[float, float, float], FloatArray, int]]] = [
            [] for _ in range(n)
        ]
        self.num_edges = 0

    @classmethod
    def from_arrays(cls, n: int, ij: IntArray, z: FloatArray, cov: FloatArray) -> Adjacency:
        """Adjacency of ``n`` nodes and edges ``ij`` (M, 2), ``z`` (M, 3), ``cov`` (M, 3, 3)."""
        adj = cls(n)
        for e in range(len(ij)):
            adj.add(int(ij[e, 0]), int(ij[e, 1]), z[e], cov[e], edge_index=e)
        return adj

    def add(
        self, i: int, j: int, z_i_from_j: FloatArray, cov: FloatArray, *, edge_index: int = -1
    ) -> None:
        """Add edge ``i -> j`` with measurement ``i_from_j`` and its covariance."""
        zf = (float(z_i_from_j[0]), float(z_i_from_j[1]), float(z_i_from_j[2]))
        ad = _ad(zf)
        self.steps[i].append((j, zf, np.asarray(cov, dtype=float), edge_index))
        self.steps[j].append((i, _inverse(zf), ad @ cov @ ad.T, edge_index))
        self.num_edges += 1


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
    poses = np.full((n, 3), np.nan)
    covs = np.full((n, 3, 3), np.inf)
    parent = np.full(n, -1, dtype=np.int64)
    parent_edge = np.full(n, -1, dtype=np.int64)
    best = np.full(n, np.inf)
    done = np.zeros(n, dtype=bool)
    p0 = np.zeros(3) if source_pose is None else np.asarray(source_pose, dtype=float)
    c0 = np.zeros((3, 3)) if source_covariance is None else np.asarray(source_covariance, float)
    pose_of: dict[int, tuple[float, float, float]] = {source: (p0[0], p0[1], p0[2])}
    cov_of: dict[int, FloatArray] = {source: c0}
    best[source] = float(np.trace(c0))
    heap: list[tuple[float, int]] = [(best[source], source)]
    steps = adjacency.steps
    while heap:
        tr, v = heapq.heappop(heap)
        if done[v] or tr > best[v]:
            continue
        if tr > max_trace:
            break
        done[v] = True
        pv, cv = pose_of[v], cov_of[v]
        poses[v] = pv
        covs[v] = cv
        if v == target:
            break
        for w, step, cstep, e in steps[v]:
            if done[w]:
                continue
            ad = _ad(_inverse(step))
            cw = ad @ cv @ ad.T + cstep
            t = cw[0, 0] + cw[1, 1] + cw[2, 2]
            if t < best[w]:
                best[w] = t
                cov_of[w] = cw
                pose_of[w] = _compose(pv, step)
                parent[w] = v
                parent_edge[w] = e
                heapq.heappush(heap, (t, w))
    unreached = ~done
    parent[unreached] = -1
    parent_edge[unreached] = -1
    return ProjectionResult(poses, covs, parent, parent_edge)


def relative_covariance(
    joint_cov: FloatArray, pose_a: FloatArray, pose_b: FloatArray
) -> FloatArray:
    """Covariance of ``a^-1 b`` (body frame of ``b``) from the 6x6 joint covariance of ``a, b``.

    First order: ``d(a^-1 b) = -Ad_{b^-1 a} da + db``. Used to compare exact marginals with
    :func:`dijkstra_projection`.
    """
    j = np.hstack([-se2.adjoint(se2.between(pose_b, pose_a)), np.eye(3)])
    return j @ joint_cov @ j.T
