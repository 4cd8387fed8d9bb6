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

from gcs.graph import se2
from gcs.graph.dijkstra_projection import Adjacency, dijkstra_projection

__all__ = ["GlobalAnchor", "spanning_tree_initialization"]

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
