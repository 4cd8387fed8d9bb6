"""The trajectory graph: the "highway" of waypoints robots have driven (paper 5.1.1, Fig. 12).

"It records a set of connected waypoints between which sensor robots are known to have
previously traveled. The planner uses the trajectory graph to cheaply compute a coarse path
between the robot and any long-distance goals." Disruptors travel only on it (paper 5.1.2).

Built from the pose graph's nodes at their *current* posterior (keys + poses in ``map``), so
it follows every re-optimization: poses are binned into ``spacing_m`` squares and each occupied
square becomes a waypoint at the mean of its poses (nearby poses of different robots merge);
consecutive poses of one robot (ordered by key) join their waypoints with a driven edge unless
they are more than ``max_step_m`` apart (a gap in the data is not a road); waypoints closer
than ``merge_m`` are joined as well (two robots driving side by side share a road). Edge
weights are the Euclidean distances between waypoints. Shortest paths by
``scipy.sparse.csgraph.dijkstra``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np
import scipy.sparse as sp
from numpy.typing import ArrayLike, NDArray
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

__all__ = ["TrajectoryGraph", "TrajectoryGraphConfig", "build_trajectory_graph"]


class TrajectoryGraphConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``spacing_m``: waypoint bin size; ``max_step_m``: longest driven edge; ``merge_m``:
    waypoints this close are joined; ``access_m``: farthest a point may be from the waypoint
    it enters or leaves the highway by."""

    spacing_m: float = 2.0
    max_step_m: float = 6.0
    merge_m: float = 1.5
    access_m: float = 8.0

    def __post_init__(self) -> None:
        for name in ("spacing_m", "max_step_m", "merge_m", "access_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"trajectory graph {name} must be finite and > 0, got {v}")


@dataclass(frozen=True)
class TrajectoryGraph:
    """``nodes_in_map`` ``(M, 2)`` waypoints; ``adjacency`` ``(M, M)`` CSR of edge lengths (m);
    ``node_of_pose`` ``(N,)`` waypoint of each input pose."""

    nodes_in_map: NDArray[np.float64]
    adjacency: sp.csr_matrix
    node_of_pose: NDArray[np.int64]
    access_m: float

    @property
    def size(self) -> int:
        return int(len(self.nodes_in_map))

    def nearest(
        self, points_in_map: ArrayLike, blocked: NDArray[np.bool_] | None = None
    ) -> NDArray[np.int64]:
        """``(N,)`` nearest waypoint of each point within ``access_m`` (-1 if none), skipping
        ``blocked`` waypoints."""
        pts = np.asarray(points_in_map, dtype=np.float64).reshape(-1, 2)
        out = np.full(len(pts), -1, dtype=np.int64)
        if self.size == 0 or len(pts) == 0:
            return out
        ok = np.ones(self.size, dtype=bool) if blocked is None else ~blocked
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return out
        d, j = cKDTree(self.nodes_in_map[idx]).query(pts, distance_upper_bound=self.access_m)
        hit = np.isfinite(d)
        out[hit] = idx[j[hit]]
        return out

    def graph(self, blocked: NDArray[np.bool_] | None = None) -> sp.csr_matrix:
        """The adjacency with every edge touching a ``blocked`` waypoint removed."""
        if blocked is None or not blocked.any():
            return self.adjacency
        keep = sp.diags((~blocked).astype(np.float64))
        g = (keep @ self.adjacency @ keep).tocsr()
        g.eliminate_zeros()
        return g

    def distances(
        self, sources: ArrayLike, blocked: NDArray[np.bool_] | None = None
    ) -> tuple[NDArray[np.float64], NDArray[np.int32]]:
        """``(S, M)`` highway distances from each source waypoint and the predecessors."""
        src = np.asarray(sources, dtype=np.int64).reshape(-1)
        if self.size == 0 or src.size == 0:
            return np.zeros((src.size, self.size)), np.zeros((src.size, self.size), np.int32)
        d, pred = dijkstra(
            self.graph(blocked), directed=False, indices=src, return_predecessors=True
        )
        return d, pred

    def path(self, predecessors: NDArray[np.int32], target: int) -> NDArray[np.int64]:
        """Waypoint indices from the source of ``predecessors`` (one row) to ``target``."""
        out = [int(target)]
        while predecessors[out[-1]] >= 0:
            out.append(int(predecessors[out[-1]]))
        return np.asarray(out[::-1], dtype=np.int64)


def build_trajectory_graph(
    robot_ids: ArrayLike,
    keys: ArrayLike,
    xy_in_map: ArrayLike,
    config: TrajectoryGraphConfig | None = None,
) -> TrajectoryGraph:
    """The highway of the poses ``xy_in_map`` ``(N, 2)`` of robots ``robot_ids`` ``(N,)``;
    ``keys`` ``(N,)`` increase along each robot's trajectory (pose-graph keys)."""
    cfg = config or TrajectoryGraphConfig()
    rid = np.asarray(robot_ids, dtype=np.int64).reshape(-1)
    key = np.asarray(keys, dtype=np.int64).reshape(-1)
    xy = np.asarray(xy_in_map, dtype=np.float64).reshape(-1, 2)
    if not (len(rid) == len(key) == len(xy)):
        raise ValueError(
            f"trajectory input: {len(rid)} robot ids, {len(key)} keys, {len(xy)} poses differ"
        )
    good: NDArray[np.bool_] = np.asarray(np.isfinite(xy).all(axis=1), dtype=bool)
    rid, key, xy = rid[good], key[good], xy[good]
    if len(xy) == 0:
        return TrajectoryGraph(
            np.zeros((0, 2)), sp.csr_matrix((0, 0)), np.zeros(0, np.int64), cfg.access_m
        )
    order = np.lexsort((key, rid))
    rid, xy = rid[order], xy[order]
    bins = np.floor(xy / cfg.spacing_m).astype(np.int64)
    _, node, counts = np.unique(bins, axis=0, return_inverse=True, return_counts=True)
    node = node.reshape(-1)
    m = len(counts)
    nodes = np.zeros((m, 2))
    np.add.at(nodes, node, xy)
    nodes /= counts[:, None]
    same = rid[1:] == rid[:-1]
    step = np.hypot(*(xy[1:] - xy[:-1]).T)
    driven = same & (step <= cfg.max_step_m) & (node[1:] != node[:-1])
    a = node[:-1][driven]
    b = node[1:][driven]
    pairs = cKDTree(nodes).query_pairs(cfg.merge_m, output_type="ndarray")
    if len(pairs):
        a = np.r_[a, pairs[:, 0]]
        b = np.r_[b, pairs[:, 1]]
    w = np.hypot(*(nodes[a] - nodes[b]).T)
    w = np.maximum(w, 1e-6)  # a zero weight would read as "no edge"
    adj = sp.coo_matrix((np.r_[w, w], (np.r_[a, b], np.r_[b, a])), shape=(m, m)).tocsr()
    adj.sum_duplicates()
    # duplicates summed their weights: restore the single length
    adj.data = np.hypot(
        *(nodes[adj.indices] - nodes[np.repeat(np.arange(m), np.diff(adj.indptr))]).T
    )
    adj.data = np.maximum(adj.data, 1e-6)
    inverse = np.empty(len(order), dtype=np.int64)
    inverse[order] = node
    full = np.full(len(good), -1, dtype=np.int64)
    full[np.flatnonzero(good)] = inverse
    return TrajectoryGraph(nodes, adj, full, cfg.access_m)
