"""Graph simplification, Algorithm 1 of the paper (section 4.7).

``Graph-Simplify(G, alpha)``: start from the nodes of ``G`` with no edges; for every edge ``e``
of ``G`` (after merging repeated edges between the same two nodes, which is lossless for
Gaussian edges), compute the Dijkstra-projection covariance ``Sigma`` between its endpoints in
the new graph; keep ``e`` if ``trace(Sigma) > alpha * trace(cov(e))``, i.e. if it reduces the
relative uncertainty of its endpoints by at least a factor ``alpha``. Kept edges are
re-expressed with zero residual at the maximum-likelihood solution of ``G`` (measurement
``x_a^-1 x_b`` of the given optimum, covariance unchanged), so the simplified graph has the
same maximum-likelihood solution. Erroneous edges of ``G`` are thereby baked in: simplify only
a graph in a known-good state.

Each query stops as soon as the far endpoint is settled or the open traces exceed
``alpha * trace(cov(e))`` (then the edge is kept), so a query touches only the neighbourhood
the decision needs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

from gcs.graph import se2
from gcs.graph.dijkstra_projection import Adjacency, projected_trace
from gcs.graph.g2o import merge_gaussian_edges, reverse_edge

__all__ = ["SimplificationConfig", "SimplifiedGraph", "merge_parallel_edges", "simplify_graph"]

FloatArray = NDArray[np.floating[Any]]
IntArray = NDArray[np.int64]


class SimplificationConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``alpha``: keep an edge if the projected relative covariance of its endpoints has more than
    ``alpha`` times the edge's covariance trace. The paper gives no value; 5 keeps the loop
    closures that add substantially new information on the Manhattan graphs."""

    alpha: float = 5.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.alpha) and self.alpha > 0):
            raise ValueError(f"alpha: expected a positive finite number, got {self.alpha}")


@dataclass(frozen=True)
class SimplifiedGraph:
    """Output of :func:`simplify_graph`.

    ``ij`` (K, 2), ``z`` (K, 3) zero-residual ``i_from_j`` at the given optimum, ``cov``
    (K, 3, 3); ``source_edges[k]`` lists the input edge indices merged into kept edge ``k``.
    """

    ij: IntArray
    z: FloatArray
    cov: FloatArray
    source_edges: tuple[tuple[int, ...], ...]


def merge_parallel_edges(
    ij: IntArray, z: FloatArray, cov: FloatArray
) -> tuple[IntArray, FloatArray, FloatArray, list[list[int]]]:
    """Merge edges between the same two nodes (either direction) losslessly.

    Returns ``(ij, z, cov, members)`` with one edge per node pair, in order of first occurrence,
    and the input indices merged into each.
    """
    groups: dict[tuple[int, int], list[int]] = {}
    for m, (i, j) in enumerate(np.asarray(ij).tolist()):
        groups.setdefault((min(i, j), max(i, j)), []).append(m)
    out_ij, out_z, out_cov, members = [], [], [], []
    for group in groups.values():
        first = group[0]
        out_ij.append(ij[first])
        members.append(group)
        if len(group) == 1:
            out_z.append(z[first])
            out_cov.append(cov[first])
            continue
        zs, infos = [], []
        for m in group:
            zm, im = z[m], np.linalg.inv(cov[m])
            if ij[m][0] != ij[first][0]:
                zm, im = reverse_edge(zm, im)
            zs.append(zm)
            infos.append(im)
        zm, im, _ = merge_gaussian_edges(np.array(zs), np.array(infos))
        out_z.append(zm)
        out_cov.append(np.linalg.inv(im))
    return (
        np.array(out_ij, dtype=np.int64).reshape(-1, 2),
        np.array(out_z, dtype=float).reshape(-1, 3),
        np.array(out_cov, dtype=float).reshape(-1, 3, 3),
        members,
    )


def simplify_graph(
    n: int,
    ij: IntArray,
    cov: FloatArray,
    optimum: FloatArray,
    *,
    alpha: float = 5.0,
    z: FloatArray | None = None,
) -> SimplifiedGraph:
    """Algorithm 1 on ``n`` nodes with edges ``ij`` (M, 2) and covariances ``cov`` (M, 3, 3).

    ``optimum`` (n, 3) is the maximum-likelihood solution of the input graph (its
    ``optimize(G)``). ``z`` (M, 3) is needed only to merge repeated edges (their covariances
    are merged; the zero-residual measurement comes from ``optimum`` in any case).
    """
    if not alpha > 0:
        raise ValueError(f"alpha must be positive, got {alpha}")
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    optimum = np.asarray(optimum, dtype=float)
    if optimum.shape != (n, 3):
        raise ValueError(f"optimum has shape {optimum.shape}, expected {(n, 3)}")
    z_in = se2.between(optimum[ij[:, 0]], optimum[ij[:, 1]]) if z is None else np.asarray(z)
    mij, _, mcov, members = merge_parallel_edges(ij, z_in, np.asarray(cov, dtype=float))
    zero_residual = se2.between(optimum[mij[:, 0]], optimum[mij[:, 1]])
    adjacency = Adjacency(n)
    kept: list[int] = []
    for e in range(len(mij)):
        a, b = int(mij[e, 0]), int(mij[e, 1])
        threshold = alpha * float(np.trace(mcov[e]))
        if projected_trace(adjacency, a, b, threshold) > threshold:  # inf: not reached
            adjacency.add(a, b, zero_residual[e], mcov[e], edge_index=e)
            kept.append(e)
    idx = np.array(kept, dtype=np.int64)
    return SimplifiedGraph(
        ij=mij[idx],
        z=zero_residual[idx],
        cov=mcov[idx],
        source_edges=tuple(tuple(members[e]) for e in kept),
    )
