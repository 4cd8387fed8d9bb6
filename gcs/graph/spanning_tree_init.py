"""Initialization from minimum-uncertainty spanning trees (paper 4.6).

From every node with global orientation information (a prior on its pose) grow the
minimum-uncertainty spanning tree by Dijkstra projection; each tree predicts every pose it
reaches (``map_from_root * path``) with a propagated covariance. Each pose is initialised with
the information-weighted average of its predictions, taken on the manifold (Gauss-Newton in
the tangent space of the most certain prediction), which removes the discontinuities that a
single tree leaves between physically nearby nodes on different branches. Nodes no tree
reaches keep their given initial value (or the chained prediction of the component root).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from gcs.graph import se2
from gcs.graph.dijkstra_projection import Adjacency, dijkstra_projection
from gcs.graph.pose2_gauss_newton import Pose2Factors

__all__ = [
    "GlobalAnchor",
    "component_labels",
    "spanning_tree_from_factors",
    "spanning_tree_initialization",
]

FloatArray = NDArray[np.floating[Any]]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class GlobalAnchor:
    """A node with global information: its index, ``map_from_base`` and 3x3 covariance."""

    node: int
    map_from_base: FloatArray
    covariance: FloatArray


def _weighted_mean(preds: FloatArray, covs: FloatArray, *, iterations: int = 3) -> FloatArray:
    """Information-weighted manifold mean of poses ``preds`` (K, 3) with covariances."""
    k0 = int(np.argmin(np.trace(covs, axis1=1, axis2=2)))
    infos = np.linalg.inv(covs + 1e-12 * np.eye(3))
    mean = se2.weighted_mean(preds, infos, start=k0, iterations=iterations, tol=1e-12)
    return se2.pose_vec(mean)


def spanning_tree_initialization(
    n: int,
    ij: IntArray,
    z: FloatArray,
    cov: FloatArray,
    anchors: Sequence[GlobalAnchor],
    *,
    fallback: FloatArray | None = None,
) -> FloatArray:
    """Initial ``map_from_base`` (n, 3) for a pose graph (see module docstring).

    ``ij`` (M, 2), ``z`` (M, 3) ``i_from_j`` and ``cov`` (M, 3, 3) are the relative edges;
    ``anchors`` the nodes with global information (at least one). ``fallback`` (n, 3) gives the
    value of nodes that no tree reaches (default: identity).
    """
    if not anchors:
        raise ValueError("spanning-tree initialization needs at least one global anchor")
    adjacency = Adjacency.from_arrays(n, np.asarray(ij), np.asarray(z), np.asarray(cov))
    trees = [
        dijkstra_projection(
            adjacency, a.node, source_pose=a.map_from_base, source_covariance=a.covariance
        )
        for a in anchors
    ]
    out = np.zeros((n, 3)) if fallback is None else np.array(fallback, dtype=float)
    if len(trees) == 1:
        r = trees[0].reached
        out[r] = trees[0].poses[r]
        return out
    reached = np.array([t.reached for t in trees])
    for v in np.flatnonzero(reached.any(axis=0)):
        ks = np.flatnonzero(reached[:, v])
        if ks.size == 1:
            out[v] = trees[ks[0]].poses[v]
        else:
            preds = np.array([trees[k].poses[v] for k in ks])
            covs = np.array([trees[k].covariances[v] for k in ks])
            out[v] = _weighted_mean(preds, covs)
    return out


def component_labels(n: int, ij: IntArray) -> IntArray:
    """Connected-component label (n,) of every variable of a graph with edges ``ij`` (M, 2);
    a variable without edges is a component of its own. Labels are ``0..C-1`` in order of each
    component's smallest variable."""
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    adj = coo_matrix((np.ones(ij.shape[0]), (ij[:, 0], ij[:, 1])), shape=(n, n))
    _, labels = connected_components(adj, directed=False)
    # Relabel by smallest member so that labels do not depend on scipy's traversal order.
    first = np.full(labels.max() + 1 if n else 0, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n))
    rank = np.empty_like(first)
    rank[np.argsort(first, kind="stable")] = np.arange(first.size)
    return rank[labels].astype(np.int64)


def spanning_tree_from_factors(factors: Pose2Factors, current: FloatArray) -> FloatArray:
    """Spanning-tree initialization (n, 3) of a ``Pose2`` factor graph (paper 4.6).

    The anchors are the priors, the most informative one (largest ``det`` of its information)
    per connected component: one Dijkstra projection a component, so the cost stays
    ``O(M log n)`` however many priors there are. A component without a prior is anchored at its
    smallest variable's ``current`` pose (gauge freedom: any anchor gives the same optimum).
    Edge covariances are the inverses of the factors' information matrices.
    """
    n = factors.n
    current = np.asarray(current, dtype=np.float64).reshape(n, 3)
    if n == 0:
        return current.copy()
    labels = component_labels(n, factors.ij)
    best: dict[int, tuple[float, int]] = {}
    dets = np.linalg.det(factors.prior_info) if factors.prior_index.size else np.zeros(0)
    for k, (v, d) in enumerate(zip(factors.prior_index.tolist(), dets.tolist(), strict=True)):
        c = int(labels[v])
        if c not in best or d > best[c][0]:
            best[c] = (d, k)
    anchors: list[GlobalAnchor] = []
    tight = np.eye(3) * 1e-12
    for c in range(int(labels.max()) + 1):
        if c in best:
            k = best[c][1]
            v = int(factors.prior_index[k])
            cov = np.linalg.inv(factors.prior_info[k])
            anchors.append(GlobalAnchor(v, factors.prior_pose[k], cov))
        else:
            v = int(np.argmax(labels == c))
            anchors.append(GlobalAnchor(v, current[v], tight))
    cov = np.linalg.inv(factors.info) if factors.info.size else np.zeros((0, 3, 3))
    # One anchor a component: the trees do not overlap, so no averaging is needed.
    adjacency = Adjacency.from_arrays(n, factors.ij, factors.z, cov)
    out = current.copy()
    for a in anchors:
        tree = dijkstra_projection(
            adjacency, a.node, source_pose=a.map_from_base, source_covariance=a.covariance
        )
        out[tree.reached] = tree.poses[tree.reached]
    return out
