"""The GCS pose graph: every robot's trajectory as GTSAM ``Pose2`` variables (paper 4.2).

Variables are robot poses ``map_from_base`` keyed by :mod:`gcs.graph.keys`. Every factor is
kept as an :class:`EdgeRecord` with its provenance (odometry, fiducial, automatic or
operator-suggested loop closure, prior) and the mission time it was added, so operators can
list, rewind and restore them (paper 6.1).

Unknown relative starts (UvA manifold, report 5.4): each robot's chain begins as its own
connected component. The component that holds the configured map robot's first pose is
anchored by a strong prior that fixes ``map`` (``PoseGraphConfig.map_from_odom``); a component
with a ``PRIOR`` edge (global position/orientation) is anchored by it; every other component
gets a weak anchor (a broad prior at its current estimate, which only fixes the gauge and never
pulls). When an edge links two components, the unanchored one is moved rigidly so the new edge
holds exactly, and its weak anchor disappears: the components have merged. Removing edges may
split components again; anchors are derived from the current edges at every solve.

For every robot ``map_from_odom = map_from_base(latest) * odom_from_base(latest)^-1`` follows
from the posterior.

Solver faults. iSAM2's incremental state can go bad on a long mission (GTSAM raises
``Indeterminate linear system detected while working near variable ...`` on a graph that solves
in batch and in a fresh iSAM2), and an estimate can come back non-finite. Neither ever raises
out of :meth:`PoseGraph.optimize_incremental`: the graph re-solves in batch (:meth:`optimize`)
from the last good estimate, seeds a fresh iSAM2 from the result and reports a
:class:`SolverFault`; if the batch solve fails too, the last good estimate stays and the next
call tries again. Every node and edge is kept either way. :meth:`PoseGraph.inject_solver_fault`
makes the next iSAM2 updates fail for real (a degenerate factor GTSAM refuses, or a NaN
measurement), for tests and the robustness bench.
"""

from __future__ import annotations

import collections
import copy
import enum
import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import gtsam
import msgspec
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from gcs.graph import se2
from gcs.graph.dijkstra_projection import Adjacency, ProjectionResult, dijkstra_projection
from gcs.graph.g2o import G2oGraph, initial_poses
from gcs.graph.keys import pose_key, split_key
from gcs.graph.optimization import (
    Isam2Config,
    Isam2Solver,
    OrderingKind,
    SolveMethod,
    optimize_batch,
)
from gcs.graph.simplification import simplify_graph
from gcs.graph.spanning_tree_init import GlobalAnchor, spanning_tree_initialization

__all__ = [
    "AutoSimplifyConfig",
    "ChangeMark",
    "EdgeRecord",
    "GraphAdditions",
    "NodeRecord",
    "OdometryCorrection",
    "PoseGraph",
    "PoseGraphConfig",
    "PoseGraphError",
    "PoseGraphSnapshot",
    "Provenance",
    "SolveSummary",
    "SolverFault",
    "SolverFaultKind",
]

log = logging.getLogger("magic.gcs.graph")

#: Largest condition number (largest / smallest eigenvalue) of an accepted covariance. GTSAM's
#: iSAM2 raises its indeterminate-system error on an edge of condition 1e8 that joins two
#: components (measured: eigenvalues 1e-4, 1e-6 and 1e-12 m^2 rotated 0.7 rad; 1e7 solves), a
#: graph with such an edge still solves in batch; the data sets' worst edge is 8.5e6
#: (manhattan.g2o). Inputs from robots meet a tighter bound at the GCS's door
#: (``GroundStationConfig.max_covariance_condition``).
MAX_COVARIANCE_CONDITION = 1e10

#: Kinds of injected solver faults (:meth:`PoseGraph.inject_solver_fault`).
SolverFaultKind = Literal["indeterminate", "nan"]

#: GTSAM key of the variable an injected ``"indeterminate"`` fault constrains (a
#: ``gtsam.Symbol`` key: never a pose key, see :mod:`gcs.graph.keys`).
_FAULT_KEY = int(gtsam.symbol("z", 0))

FloatArray = NDArray[np.floating[Any]]
_Arrays = tuple[NDArray[np.int64], FloatArray, FloatArray]


#: A robot's odometry model (:meth:`PoseGraph.set_odometry_correction`): reported increments
#: ``a_from_b`` ``(N, 3)`` and covariances ``(N, 3, 3)`` in, the increments and covariances the
#: graph should use out (same shapes, new arrays).
OdometryCorrection = Callable[[FloatArray, FloatArray], tuple[FloatArray, FloatArray]]

#: Estimate writes :meth:`PoseGraph.moved_since` remembers.
_MOVED_LOG = 64

#: How weakly :meth:`PoseGraph.from_g2o` bridges a gap in a g2o graph's odometry chain.
GAP_SIGMA_XY_M = 1e3
GAP_SIGMA_YAW_RAD = math.pi


class PoseGraphError(ValueError):
    """Bad input to the pose graph (unknown robot or key, non-finite value, bad covariance)."""


class Provenance(enum.Enum):
    """Where a factor came from."""

    ODOMETRY = "odometry"
    FIDUCIAL = "fiducial"
    LOOP_AUTO = "loop_auto"
    LOOP_OPERATOR = "loop_operator"
    PRIOR = "prior"


class AutoSimplifyConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """When the graph simplifies itself (paper 4.7, :meth:`PoseGraph.simplify_if_due`).

    The paper's optimization time grew faster than the graph because loop closures raise the
    average node degree; its operators ran Algorithm 1 "at most 2-3 times per hour", on a
    graph in a known-good state. Here it is due once the graph holds ``min_poses`` poses,
    its relative edges per pose exceed ``max_edges_per_pose`` (a bare chain has just under
    1) and ``min_interval_s`` mission seconds have passed since the last one; ``alpha`` is
    Algorithm 1's (:class:`gcs.graph.simplification.SimplificationConfig`). At 100 robots
    (15,000 poses, 20,000 edges) one simplification took 3.6 s on this machine.
    """

    min_poses: int = 10000
    max_edges_per_pose: float = 1.2
    min_interval_s: float = 1200.0
    alpha: float = 5.0

    def __post_init__(self) -> None:
        if self.min_poses < 2:
            raise ValueError(f"min_poses: expected at least 2, got {self.min_poses}")
        for name in ("max_edges_per_pose", "alpha"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v}")
        if not (math.isfinite(self.min_interval_s) and self.min_interval_s >= 0):
            raise ValueError(f"min_interval_s: expected seconds >= 0, got {self.min_interval_s}")


class PoseGraphConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Configuration of :class:`PoseGraph`.

    ``map_robot_id``'s first pose anchors ``map`` at ``map_from_odom`` (x m, y m, yaw rad) with
    the ``anchor_sigma_*``; other components get the ``weak_anchor_sigma_*``. A weak anchor is a
    prior at the current estimate of a component with no other absolute information, so its
    residual stays zero at the optimum whatever its strength: it fixes only the gauge. Moderate
    sigmas keep the linear systems well conditioned (iSAM2 rejects near-singular ones).
    """

    map_robot_id: int = 0
    map_from_odom: tuple[float, float, float] = (0.0, 0.0, 0.0)
    anchor_sigma_xy_m: float = 1e-4
    anchor_sigma_yaw_rad: float = 1e-5
    weak_anchor_sigma_xy_m: float = 10.0
    weak_anchor_sigma_yaw_rad: float = 1.0
    method: SolveMethod = "block_lm"
    ordering: OrderingKind = "colamd"
    max_iterations: int = 100
    relative_error_tol: float = 1e-6
    isam2: Isam2Config = msgspec.field(default_factory=Isam2Config)
    # None: never by itself (operators' rewinds need the edges Algorithm 1 would merge)
    auto_simplify: AutoSimplifyConfig | None = None

    def __post_init__(self) -> None:
        for name in (
            "anchor_sigma_xy_m",
            "anchor_sigma_yaw_rad",
            "weak_anchor_sigma_xy_m",
            "weak_anchor_sigma_yaw_rad",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v}")


@dataclass(frozen=True)
class NodeRecord:
    """A pose variable: its robot, index, mission time and reported ``odom_from_base``."""

    key: int
    robot_id: int
    index: int
    time_s: float
    odom_from_base: FloatArray


@dataclass(frozen=True)
class EdgeRecord:
    """A factor with its provenance.

    For a relative edge ``z`` is ``a_from_b`` (``key_b`` set); for a ``PRIOR`` ``z`` is
    ``map_from_base`` of ``key_a`` and ``key_b`` is ``None``. ``covariance`` is 3x3 in the
    tangent space of ``b`` (GTSAM ``Pose2`` order x, y, theta).
    """

    edge_id: int
    key_a: int
    key_b: int | None
    z: FloatArray
    covariance: FloatArray
    provenance: Provenance
    time_s: float


@dataclass(frozen=True)
class PoseGraphSnapshot:
    """Immutable copy of a :class:`PoseGraph`'s nodes, edges and estimate."""

    nodes: dict[int, NodeRecord]
    edges: dict[int, EdgeRecord]
    estimate: dict[int, FloatArray]
    next_edge_id: int


@dataclass(frozen=True)
class SolveSummary:
    """Result of :meth:`PoseGraph.optimize`: chi2 of the solved graph (anchors included)."""

    chi2: float
    iterations: int
    total_s: float
    components: int = field(default=1)


@dataclass(frozen=True)
class SolverFault:
    """An incremental solve that failed, and what the graph did about it.

    ``error``: what failed (the exception's type and first line, or the non-finite estimate).
    ``action``: what was done, one line. ``recovered``: the estimate is a fresh batch solution
    (False: the last good estimate was kept and the next solve tries again).
    """

    error: str
    action: str
    recovered: bool


@dataclass(frozen=True)
class ChangeMark:
    """A point in a :class:`PoseGraph`'s history (:meth:`PoseGraph.change_mark`): its epoch
    (bumped by every change other than an addition) and how many nodes and edges had been
    added by then."""

    epoch: int
    nodes: int
    edges: int


@dataclass(frozen=True)
class GraphAdditions:
    """What was added to a graph since a :class:`ChangeMark`
    (:meth:`PoseGraph.additions_since`): node keys and edges (priors included) in the order
    they were added, and the mark of now."""

    node_keys: list[int]
    edges: list[EdgeRecord]
    mark: ChangeMark


def _check_pose(p: object, what: str) -> FloatArray:
    arr = np.asarray(p, dtype=float)
    if arr.shape != (3,):
        raise PoseGraphError(f"{what}: expected (x, y, theta), got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PoseGraphError(f"{what}: non-finite value {arr.tolist()}")
    return arr.copy()


def _check_cov(c: object, what: str) -> FloatArray:
    arr = np.asarray(c, dtype=float)
    if arr.shape != (3, 3):
        raise PoseGraphError(f"{what}: covariance must be 3x3, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PoseGraphError(f"{what}: covariance has non-finite entries")
    if not np.allclose(arr, arr.T, rtol=1e-9, atol=1e-12):
        raise PoseGraphError(f"{what}: covariance is not symmetric")
    eig = np.linalg.eigvalsh(arr)
    try:
        np.linalg.cholesky(arr)
    except np.linalg.LinAlgError:
        eig = np.minimum(eig, 0.0)  # reported as not positive definite below
    if not (eig[0] > 0 and eig[-1] <= MAX_COVARIANCE_CONDITION * eig[0]):
        raise PoseGraphError(
            f"{what}: covariance is singular or not positive definite "
            f"(eigenvalues {np.linalg.eigvalsh(arr).tolist()}, condition limit "
            f"{MAX_COVARIANCE_CONDITION:g})"
        )
    return arr.copy()


class PoseGraph:
    """Factor graph of all robots' trajectories with provenance, anchoring and edits.

    API: :meth:`add_pose` (a robot's next pose, odometry edge added), :meth:`add_edge`
    (fiducial / loop closure), :meth:`add_prior` (global information), :meth:`optimize`
    (batch), :meth:`optimize_incremental` (iSAM2), :meth:`initialize_from_spanning_trees`,
    :meth:`projection` (Dijkstra projection), :meth:`simplify` (Algorithm 1),
    :meth:`map_from_odom`, :meth:`pose`, :meth:`edges`, :meth:`rewind`, :meth:`remove_edges`,
    :meth:`snapshot` / :meth:`restore`, :meth:`factor_graph` (the GTSAM graph and values),
    :meth:`from_g2o` / :meth:`to_g2o`.
    """

    def __init__(self, config: PoseGraphConfig | None = None) -> None:
        self.config = config or PoseGraphConfig()
        self._nodes: dict[int, NodeRecord] = {}
        self._edges: dict[int, EdgeRecord] = {}
        self._estimate: dict[int, FloatArray] = {}
        self._last_key: dict[int, int] = {}
        self._next_edge_id = 0
        self._components: dict[int, int] | None = None  # kept up to date on additions
        self._next_label = 0
        self._isam: Isam2Solver | None = None
        self._isam_mark: ChangeMark | None = None  # what iSAM2 holds: the graph up to here
        self._isam_anchors: set[tuple[str, int]] = set()
        self._isam_stale = True
        self._injected_faults: list[SolverFaultKind] = []
        # odometry edges whose measurement was changed: what the robot reported
        self._reported: dict[int, tuple[FloatArray, FloatArray]] = {}
        self._corrections: dict[int, OdometryCorrection] = {}
        # incremental views (change_mark / additions_since / estimate_revision): keys and edge
        # ids in the order added; the epoch moves on every other change
        self._node_log: list[int] = []
        self._edge_log: list[int] = []
        self._epoch = 0
        self._last_simplified_s = -math.inf
        self._relative_count: tuple[ChangeMark, int] | None = None
        self._prior_cache: tuple[ChangeMark, list[int]] | None = None
        # the estimate as the last solve wrote it, in node order (None: written since)
        self._est_cache: tuple[NDArray[np.int64], FloatArray] | None = None
        self._estimate_revision = 0
        self._moved: collections.deque[tuple[int, NDArray[np.int64]]] = collections.deque(
            maxlen=_MOVED_LOG
        )

    # ---- queries -------------------------------------------------------------------------

    @property
    def robots(self) -> list[int]:
        """Ids of robots with at least one pose."""
        return sorted(self._last_key)

    def nodes(self, robot_id: int | None = None) -> list[NodeRecord]:
        """Pose records (of one robot, or all), in key order."""
        if robot_id is not None:
            self._require_robot(robot_id)
        return [
            n for k, n in sorted(self._nodes.items()) if robot_id is None or n.robot_id == robot_id
        ]

    def pose(self, key: int) -> FloatArray:
        """Current estimate ``map_from_base`` of pose ``key``."""
        self._require_key(key, "pose")
        return self._estimate[key].copy()

    def poses(self, robot_id: int) -> tuple[NDArray[np.int64], FloatArray]:
        """``(keys, map_from_base (N, 3))`` of one robot's trajectory."""
        nodes = self.nodes(robot_id)
        keys = np.array([n.key for n in nodes], dtype=np.int64)
        return keys, np.array([self._estimate[n.key] for n in nodes]).reshape(-1, 3)

    def last_key(self, robot_id: int) -> int:
        """Key of the latest pose of ``robot_id``."""
        self._require_robot(robot_id)
        return self._last_key[robot_id]

    def map_from_odom(self, robot_id: int) -> FloatArray:
        """``map_from_odom/<robot>`` (x, y, yaw) implied by the posterior of its latest pose."""
        key = self.last_key(robot_id)
        node = self._nodes[key]
        return se2.compose(self._estimate[key], se2.inverse(node.odom_from_base))

    def edges(
        self,
        provenance: Provenance | tuple[Provenance, ...] | None = None,
        *,
        after_time_s: float | None = None,
    ) -> list[EdgeRecord]:
        """Edges in insertion order, optionally of given provenance(s) and added after a time."""
        if isinstance(provenance, Provenance):
            provenance = (provenance,)
        return [
            e
            for e in self._edges.values()
            if (provenance is None or e.provenance in provenance)
            and (after_time_s is None or e.time_s > after_time_s)
        ]

    @property
    def node_count(self) -> int:
        """Number of poses (O(1), unlike ``len(nodes())``)."""
        return len(self._nodes)

    @property
    def edge_count(self) -> int:
        """Number of edges, priors included (O(1))."""
        return len(self._edges)

    def change_mark(self) -> ChangeMark:
        """The graph's present point in its history, for :meth:`additions_since`."""
        return ChangeMark(self._epoch, len(self._node_log), len(self._edge_log))

    def additions_since(self, mark: ChangeMark) -> GraphAdditions | None:
        """The nodes and edges added since ``mark``, in the order added, or None when
        anything else changed since (an edge removed or re-measured, an odometry correction,
        a restore, a simplification): then a consumer's copy must be rebuilt whole.

        Cost: O(what was added). A consumer that mirrors the graph (e.g. the loop closer's
        arrays for Dijkstra projections) keeps the returned ``mark`` and extends its copy
        instead of re-reading every node and edge at each step.
        """
        if mark.epoch != self._epoch or mark.nodes > len(self._node_log):
            return None
        edges = [self._edges[eid] for eid in self._edge_log[mark.edges :]]
        return GraphAdditions(list(self._node_log[mark.nodes :]), edges, self.change_mark())

    @property
    def estimate_revision(self) -> int:
        """Counts the estimate writes (solves, rigid moves of a component, re-initializations,
        restores) that moved at least one existing pose; a new pose's first estimate does
        not count (it is an addition: :meth:`additions_since`)."""
        return self._estimate_revision

    def moved_since(self, revision: int) -> NDArray[np.int64] | None:
        """Keys (sorted, unique) whose estimate changed after ``revision`` (an
        :attr:`estimate_revision` read earlier), or None when that is too long ago to tell
        (the last ``_MOVED_LOG`` writes are kept): then treat every pose as moved. After an
        iSAM2 update only the poses it actually moved are listed, so a consumer (frames,
        rasterization, a mirror of the estimate) updates those alone."""
        if revision >= self._estimate_revision:
            return np.zeros(0, dtype=np.int64)
        if not self._moved or self._moved[0][0] > revision + 1:
            return None
        parts = [keys for rev, keys in self._moved if rev > revision]
        return np.unique(np.concatenate(parts)) if parts else np.zeros(0, dtype=np.int64)

    def _note_moved(self, keys: NDArray[np.int64] | list[int]) -> None:
        arr = np.asarray(keys, dtype=np.int64).reshape(-1)
        if arr.size:
            self._estimate_revision += 1
            self._moved.append((self._estimate_revision, arr))

    def components(self) -> dict[int, int]:
        """Connected component label of every key (relative edges only)."""
        if self._components is None:
            keys = sorted(self._nodes)
            index = {k: i for i, k in enumerate(keys)}
            rel = [e for e in self._edges.values() if e.key_b is not None]
            rows = np.array([index[e.key_a] for e in rel], dtype=np.int64)
            cols = np.array([index[e.key_b] for e in rel], dtype=np.int64)  # type: ignore[index]
            mat = coo_matrix((np.ones(rows.size), (rows, cols)), shape=(len(keys), len(keys)))
            _, labels = connected_components(mat, directed=False)
            self._components = {k: int(labels[i]) for k, i in index.items()}
            self._next_label = int(labels.max()) + 1 if labels.size else 0
        return self._components

    def anchored_components(self) -> set[int]:
        """Labels of components fixed in ``map`` (map robot's first pose or a PRIOR edge)."""
        comp = self.components()
        out = {comp[k] for k in self._prior_keys()}
        map_key = pose_key(self.config.map_robot_id, 0)
        if map_key in comp:
            out.add(comp[map_key])
        return out

    def _prior_keys(self) -> list[int]:
        """Keys with a ``PRIOR`` edge (with repeats), kept up to date from the additions."""
        cache = self._prior_cache
        if cache is not None:
            added = self.additions_since(cache[0])
            if added is not None:
                keys = cache[1]
                if added.edges:
                    keys = keys + [e.key_a for e in added.edges if e.key_b is None]
                self._prior_cache = (added.mark, keys)
                return keys
        keys = [e.key_a for e in self._edges.values() if e.provenance is Provenance.PRIOR]
        self._prior_cache = (self.change_mark(), keys)
        return keys

    # ---- building ------------------------------------------------------------------------

    def add_pose(
        self,
        robot_id: int,
        *,
        odom_from_base: FloatArray | tuple[float, float, float],
        time_s: float,
        odometry_covariance: FloatArray | None = None,
    ) -> int:
        """Append the next pose of ``robot_id`` (reported in its private frame ``odom/<id>``).

        The first pose of a robot starts a new component; later poses add an ``ODOMETRY`` edge
        from the previous pose with ``odometry_covariance`` (required then). Returns the key.
        """
        pose = _check_pose(odom_from_base, f"robot {robot_id} odom_from_base")
        if not math.isfinite(time_s):
            raise PoseGraphError(f"robot {robot_id}: non-finite time {time_s}")
        prev = self._last_key.get(robot_id)
        index = 0 if prev is None else split_key(prev)[1] + 1
        key = pose_key(robot_id, index)
        if prev is None:
            map_from_odom = (
                np.array(self.config.map_from_odom, dtype=float)
                if robot_id == self.config.map_robot_id
                else np.zeros(3)
            )
            estimate = se2.compose(map_from_odom, pose)
        else:
            if odometry_covariance is None:
                raise PoseGraphError(f"robot {robot_id} pose {index}: odometry covariance missing")
            cov = _check_cov(odometry_covariance, f"robot {robot_id} pose {index} odometry")
            z: FloatArray = se2.between(self._nodes[prev].odom_from_base, pose)
            reported = (z, cov)
            correct = self._corrections.get(robot_id)
            if correct is not None:
                zz, cc = correct(z.reshape(1, 3), cov.reshape(1, 3, 3))
                what = f"robot {robot_id} pose {index} corrected odometry"
                z = _check_pose(np.asarray(zz).reshape(3), what)
                cov = _check_cov(np.asarray(cc).reshape(3, 3), what)
            estimate = se2.compose(self._estimate[prev], z)
        pose.setflags(write=False)
        self._nodes[key] = NodeRecord(key, robot_id, index, float(time_s), pose)
        self._node_log.append(key)
        self._estimate[key] = estimate
        self._last_key[robot_id] = key
        if self._components is not None:
            if prev is None:
                self._components[key] = self._next_label
                self._next_label += 1
            else:
                self._components[key] = self._components[prev]
        if prev is not None:
            eid = self._append(prev, key, z, cov, Provenance.ODOMETRY, time_s)
            if robot_id in self._corrections:
                self._reported[eid] = reported
        return key

    def add_edge(
        self,
        key_a: int,
        key_b: int,
        *,
        a_from_b: FloatArray | tuple[float, float, float],
        covariance: FloatArray,
        provenance: Provenance,
        time_s: float,
    ) -> int:
        """Add a relative constraint ``a_from_b`` between two existing poses; returns its id.

        If it links two components, the unanchored one is moved rigidly onto the constraint.
        """
        self._require_key(key_a, "edge")
        self._require_key(key_b, "edge")
        what = f"{provenance.value} edge {split_key(key_a)} -> {split_key(key_b)}"
        if key_a == key_b:
            raise PoseGraphError(f"{what}: connects a pose to itself")
        if provenance is Provenance.PRIOR:
            raise PoseGraphError(f"{what}: use add_prior for priors")
        z = _check_pose(a_from_b, what)
        cov = _check_cov(covariance, what)
        if not math.isfinite(time_s):
            raise PoseGraphError(f"{what}: non-finite time {time_s}")
        comp = self.components()
        ca, cb = comp[key_a], comp[key_b]
        if ca != cb:
            anchored = self.anchored_components()
            if cb not in anchored:
                self._move_component(cb, key_b, se2.compose(self._estimate[key_a], z))
            elif ca not in anchored:
                self._move_component(ca, key_a, se2.compose(self._estimate[key_b], se2.inverse(z)))
        return self._append(key_a, key_b, z, cov, provenance, time_s)

    def add_prior(
        self,
        key: int,
        *,
        map_from_base: FloatArray | tuple[float, float, float],
        covariance: FloatArray,
        time_s: float,
    ) -> int:
        """Add global information on pose ``key`` (e.g. a manual alignment); returns its id.

        An unanchored component is moved rigidly onto the prior first.
        """
        self._require_key(key, "prior")
        what = f"prior on {split_key(key)}"
        z = _check_pose(map_from_base, what)
        cov = _check_cov(covariance, what)
        comp = self.components()
        if comp[key] not in self.anchored_components():
            self._move_component(comp[key], key, z)
        return self._append(key, None, z, cov, Provenance.PRIOR, time_s)

    def _append(
        self,
        key_a: int,
        key_b: int | None,
        z: FloatArray,
        cov: FloatArray,
        provenance: Provenance,
        time_s: float,
    ) -> int:
        edge_id = self._next_edge_id
        self._next_edge_id += 1
        z.setflags(write=False)
        cov.setflags(write=False)
        self._edges[edge_id] = EdgeRecord(edge_id, key_a, key_b, z, cov, provenance, float(time_s))
        self._edge_log.append(edge_id)
        comp = self._components
        if comp is not None and key_b is not None and comp[key_a] != comp[key_b]:
            keep, gone = comp[key_a], comp[key_b]
            for k, label in comp.items():
                if label == gone:
                    comp[k] = keep
        return edge_id

    def _move_component(self, label: int, key: int, target: FloatArray) -> None:
        """Rigidly move component ``label`` so pose ``key`` lands on ``target``."""
        delta = se2.compose(target, se2.inverse(self._estimate[key]))
        comp = self.components()
        keys = [k for k, c in comp.items() if c == label]
        moved = se2.compose(delta, np.array([self._estimate[k] for k in keys]))
        for k, p in zip(keys, moved, strict=True):
            self._estimate[k] = p
        self._est_cache = None
        self._note_moved(sorted(keys))
        self._isam_stale = True

    # ---- edits ---------------------------------------------------------------------------

    def remove_edges(self, edge_ids: list[int]) -> list[EdgeRecord]:
        """Remove edges by id (odometry edges cannot be removed); returns the removed records."""
        for eid in edge_ids:
            if eid not in self._edges:
                raise PoseGraphError(f"remove: no edge with id {eid}")
            if self._edges[eid].provenance is Provenance.ODOMETRY:
                raise PoseGraphError(f"remove: edge {eid} is odometry and cannot be removed")
        removed = [self._edges.pop(eid) for eid in edge_ids]
        if removed:
            self._epoch += 1
        self._components = None
        self._isam_stale = True
        return removed

    def update_edges(self, updates: dict[int, tuple[FloatArray, FloatArray]]) -> list[EdgeRecord]:
        """Replace the measurement and covariance of existing edges in place:
        ``{edge_id: (z, covariance)}`` (``z`` as the edge states it: ``a_from_b``, or
        ``map_from_base`` for a prior). Ids, ends, provenance and times stay; what an odometry
        edge first reported is kept (:meth:`odometry_reported`). Returns the previous records.

        Everything is checked before anything changes (a bad entry raises
        :class:`PoseGraphError` naming the edge, and no edge is touched). The estimate is not
        changed: optimize next. iSAM2 is re-seeded from the whole graph at the next
        :meth:`optimize_incremental` (its factors are the old measurements); a batch
        :meth:`optimize` first makes that re-seed start at the new optimum.
        """
        checked: dict[int, tuple[FloatArray, FloatArray]] = {}
        for eid, (z, cov) in updates.items():
            if eid not in self._edges:
                raise PoseGraphError(f"update: no edge with id {eid}")
            e = self._edges[eid]
            what = f"update of {e.provenance.value} edge {eid}"
            checked[eid] = (_check_pose(z, what), _check_cov(cov, what))
        previous = []
        for eid, (z, cov) in checked.items():
            e = self._edges[eid]
            previous.append(e)
            if e.provenance is Provenance.ODOMETRY:
                self._reported.setdefault(eid, (e.z, e.covariance))
            z.setflags(write=False)
            cov.setflags(write=False)
            self._edges[eid] = EdgeRecord(eid, e.key_a, e.key_b, z, cov, e.provenance, e.time_s)
        if checked:
            self._isam_stale = True
            self._epoch += 1
        return previous

    def odometry_reported(
        self, robot_id: int
    ) -> tuple[NDArray[np.int64], NDArray[np.int64], FloatArray, FloatArray]:
        """A robot's odometry edges as the robot reported them, in chain order:
        ``(edge_ids, keys_b, z (N, 3), covariances (N, 3, 3))`` (``keys_b[k]`` the pose each
        edge reaches), whatever correction the graph applies now."""
        self._require_robot(robot_id)
        rows = sorted(
            (e for e in self._edges.values() if e.provenance is Provenance.ODOMETRY
             and self._nodes[e.key_a].robot_id == robot_id),
            key=lambda e: e.key_b or 0,
        )  # fmt: skip
        z = [self._reported[e.edge_id][0] if e.edge_id in self._reported else e.z for e in rows]
        cov = [
            self._reported[e.edge_id][1] if e.edge_id in self._reported else e.covariance
            for e in rows
        ]
        return (
            np.array([e.edge_id for e in rows], dtype=np.int64),
            np.array([e.key_b for e in rows], dtype=np.int64),
            np.array(z, dtype=np.float64).reshape(-1, 3),
            np.array(cov, dtype=np.float64).reshape(-1, 3, 3),
        )

    def set_odometry_correction(self, robot_id: int, correct: OdometryCorrection | None) -> int:
        """Use ``correct`` (None: nothing) as ``robot_id``'s odometry model from now on.

        Every odometry edge of the robot is re-expressed from what the robot reported (never
        from an earlier correction: corrections do not compound), and every later one as
        :meth:`add_pose` adds it; e.g. a turn-scale estimate (:mod:`gcs.loops.odometry_bias`)
        scales the yaw of each increment and widens its variance. Raises
        :class:`PoseGraphError` (nothing changed) when ``correct`` returns bad numbers.
        Returns how many edges were rewritten; optimize next (see :meth:`update_edges`).
        """
        ids, _keys, z0, cov0 = self.odometry_reported(robot_id)
        if correct is None:
            z, cov = z0, cov0
        else:
            z, cov = correct(z0.copy(), cov0.copy())
            z = np.asarray(z, dtype=np.float64)
            cov = np.asarray(cov, dtype=np.float64)
            if z.shape != z0.shape or cov.shape != cov0.shape:
                raise PoseGraphError(
                    f"odometry correction of robot {robot_id}: expected shapes {z0.shape} and "
                    f"{cov0.shape}, got {z.shape} and {cov.shape}"
                )
        self.update_edges({int(eid): (z[i], cov[i]) for i, eid in enumerate(ids.tolist())})
        if correct is None:
            self._corrections.pop(robot_id, None)
        else:
            self._corrections[robot_id] = correct
        return len(ids)

    def rewind(
        self,
        after_time_s: float,
        *,
        provenance: tuple[Provenance, ...] = (Provenance.LOOP_AUTO,),
    ) -> list[EdgeRecord]:
        """Operator "rewind" (paper 6.1): remove edges of ``provenance`` (default automatic
        loop closures) added after ``after_time_s``; returns them. Call :meth:`optimize` next."""
        return self.remove_edges(
            [e.edge_id for e in self.edges(provenance, after_time_s=after_time_s)]
        )

    def snapshot(self) -> PoseGraphSnapshot:
        """A copy of the whole graph and estimate, for :meth:`restore`."""
        return PoseGraphSnapshot(
            nodes=dict(self._nodes),
            edges=dict(self._edges),
            estimate={k: v.copy() for k, v in self._estimate.items()},
            next_edge_id=self._next_edge_id,
        )

    def restore(self, snapshot: PoseGraphSnapshot) -> None:
        """Return to ``snapshot`` exactly (nodes, edges, estimate); later additions are dropped."""
        self._nodes = dict(snapshot.nodes)
        self._edges = dict(snapshot.edges)
        self._estimate = {k: v.copy() for k, v in snapshot.estimate.items()}
        self._est_cache = None
        self._next_edge_id = max(self._next_edge_id, snapshot.next_edge_id)
        self._last_key = {}
        for key in sorted(self._nodes):
            self._last_key[self._nodes[key].robot_id] = key
        self._node_log = sorted(self._nodes)
        self._edge_log = list(self._edges)
        self._epoch += 1
        self._note_moved(self._node_log)
        self._components = None
        self._isam_stale = True

    # ---- solving -------------------------------------------------------------------------

    @staticmethod
    def _edge_factor(e: EdgeRecord) -> gtsam.NonlinearFactor:
        noise = gtsam.noiseModel.Gaussian.Covariance(e.covariance)
        if e.key_b is None:
            return gtsam.PriorFactorPose2(e.key_a, se2.pose2(e.z), noise)
        return gtsam.BetweenFactorPose2(e.key_a, e.key_b, se2.pose2(e.z), noise)

    def _anchor_factors(self) -> dict[tuple[str, int], gtsam.NonlinearFactor]:
        """The map anchor and the weak anchors of unanchored components, by (kind, key)."""
        cfg = self.config
        out: dict[tuple[str, int], gtsam.NonlinearFactor] = {}
        map_key = pose_key(cfg.map_robot_id, 0)
        if map_key in self._nodes:
            target = se2.compose(np.array(cfg.map_from_odom), self._nodes[map_key].odom_from_base)
            sig = [cfg.anchor_sigma_xy_m, cfg.anchor_sigma_xy_m, cfg.anchor_sigma_yaw_rad]
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(sig))
            out[("map", map_key)] = gtsam.PriorFactorPose2(map_key, se2.pose2(target), noise)
        anchored = self.anchored_components()
        comp = self.components()
        keys = np.fromiter(comp.keys(), dtype=np.int64, count=len(comp))
        labels = np.fromiter(comp.values(), dtype=np.int64, count=len(comp))
        # each unanchored component's smallest key, in key order (one sort in numpy: a
        # Python sort of every (key, label) took a tenth of a solve at 15,000 poses)
        order = np.lexsort((keys, labels))
        first = np.ones(len(order), dtype=bool)
        first[1:] = labels[order][1:] != labels[order][:-1]
        heads = order[first]
        free = np.array([int(lb) not in anchored for lb in labels[heads]], dtype=bool)
        roots = {int(labels[i]): int(keys[i]) for i in heads[free][np.argsort(keys[heads[free]])]}
        weak = [
            cfg.weak_anchor_sigma_xy_m,
            cfg.weak_anchor_sigma_xy_m,
            cfg.weak_anchor_sigma_yaw_rad,
        ]
        weak_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(weak))
        for key in roots.values():
            pose = se2.pose2(self._estimate[key])
            out[("weak", key)] = gtsam.PriorFactorPose2(key, pose, weak_noise)
        return out

    def factor_graph(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The GTSAM graph (edges, map anchor, weak anchors) and the current estimate."""
        fg = gtsam.NonlinearFactorGraph()
        for e in self._edges.values():
            fg.add(self._edge_factor(e))
        for factor in self._anchor_factors().values():
            fg.add(factor)
        values = gtsam.Values()
        for key, p in self._estimate.items():
            values.insert(key, se2.pose2(p))
        return fg, values

    def optimize_incremental(self) -> SolverFault | None:
        """Online update with iSAM2: push the edges and poses added since the last call.

        Removals, restores, component merges and anchor changes re-seed iSAM2 from the whole
        graph (they are rare operator or topology events); otherwise the update is incremental.

        Never raises on a solver failure (module docstring): an exception out of iSAM2's update
        or estimate, or a non-finite estimate, is answered by a batch re-solve from the last
        good estimate and a fresh iSAM2 seeded from it; the returned :class:`SolverFault` says
        what failed and what was done (None: the update went through). The estimate only ever
        changes to a finite one.
        """
        try:
            self._isam_step()
            return None
        except Exception as err:  # GTSAM raises RuntimeError; bindings may raise others
            error = _describe(err)
        return self._recover(error)

    def _isam_step(self) -> None:
        anchors = self._anchor_factors()
        if self._isam is None or self._isam_stale or not self._isam_anchors <= anchors.keys():
            self._isam = None  # a failure below leaves no half-seeded solver behind
            self._isam_stale = True
            solver = Isam2Solver(self.config.isam2)
            fg, values = self.factor_graph()
            self._isam_update(solver, fg, values)
            self._isam = solver
            self._isam_mark = self.change_mark()
            self._isam_anchors = set(anchors)
            self._isam_stale = False
        else:
            # what was added since iSAM2 last took the graph (any other change made it stale):
            # O(additions), not set differences over every edge and node
            added = None if self._isam_mark is None else self.additions_since(self._isam_mark)
            if added is None:
                self._isam_stale = True
                self._isam_step()
                return
            fg = gtsam.NonlinearFactorGraph()
            for e in added.edges:
                fg.add(self._edge_factor(e))
            for name in anchors.keys() - self._isam_anchors:
                fg.add(anchors[name])
            values = gtsam.Values()
            for key in added.node_keys:
                values.insert(key, se2.pose2(self._estimate[key]))
            # From here on iSAM2 holds the new factors whatever happens: if it fails it is
            # re-seeded, so mark it stale until the update is through.
            self._isam_stale = True
            self._isam_update(self._isam, fg, values)
            self._isam_mark = added.mark
            self._isam_anchors |= anchors.keys()
            self._isam_stale = False
        self._assign_estimate(self._isam.estimate(), "iSAM2")

    def _isam_update(
        self, solver: Isam2Solver, fg: gtsam.NonlinearFactorGraph, values: gtsam.Values
    ) -> None:
        """``solver.update``, with an injected fault added to the update when one is due."""
        if self._injected_faults:
            kind = self._injected_faults.pop(0)
            fg = gtsam.NonlinearFactorGraph(fg)
            values = gtsam.Values(values)
            if kind == "indeterminate":
                # a prior that leaves a new variable's heading free: GTSAM's elimination hits
                # a zero pivot and raises its IndeterminantLinearSystemException
                values.insert(_FAULT_KEY, gtsam.Pose2())
                free_yaw = gtsam.noiseModel.Diagonal.Precisions(np.array([1.0, 1.0, 0.0]))
                fg.add(gtsam.PriorFactorPose2(_FAULT_KEY, gtsam.Pose2(), free_yaw))
            else:  # "nan": a measurement that makes every pose it reaches NaN
                key = max(self._nodes)
                noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([1.0, 1.0, 1.0]))
                nan = gtsam.Pose2(math.nan, math.nan, math.nan)
                fg.add(gtsam.PriorFactorPose2(key, nan, noise))
        solver.update(fg, values)

    def _recover(self, error: str) -> SolverFault:
        """Batch re-solve from the last good estimate, then a fresh iSAM2 seeded from it."""
        self._isam = None
        self._isam_stale = True
        last_good = {k: v.copy() for k, v in self._estimate.items()}
        try:
            summary = self.optimize()
            if not math.isfinite(summary.chi2):
                raise FloatingPointError(f"batch solve ended with chi2 {summary.chi2}")
        except Exception as err:
            self._estimate = last_good
            self._est_cache = None
            fault = SolverFault(
                error=error,
                action=f"batch re-solve failed too ({_describe(err)}); kept the last good "
                "estimate, will retry at the next solve",
                recovered=False,
            )
            log.error("solver fault: %s; %s", fault.error, fault.action)
            return fault
        action = f"batch re-solved ({summary.iterations} iterations, chi2 {summary.chi2:.6g})"
        try:
            self._isam_step()
            action += ", fresh iSAM2 seeded from it"
        except Exception as err:
            self._isam = None
            self._isam_stale = True
            action += f"; re-seeding iSAM2 failed ({_describe(err)}), retried at the next solve"
        fault = SolverFault(error=error, action=action, recovered=True)
        log.warning("solver fault: %s; %s", fault.error, fault.action)
        return fault

    def inject_solver_fault(self, kind: SolverFaultKind = "indeterminate", count: int = 1) -> None:
        """Make the next ``count`` iSAM2 updates fail for real (tests, robustness bench).

        ``"indeterminate"``: the update also carries a prior on a spare variable that leaves
        its heading free, so GTSAM itself raises its indeterminate-system ``RuntimeError`` in
        ``ISAM2.update``. ``"nan"``: the update carries a NaN measurement on the newest pose, so
        iSAM2's estimate comes back non-finite. The injected factor only ever lives in the
        iSAM2 that fails; the graph's own nodes and edges are untouched.
        """
        if kind not in ("indeterminate", "nan"):
            raise ValueError(f"inject_solver_fault: unknown kind {kind!r}")
        if count < 0:
            raise ValueError(f"inject_solver_fault: count must be >= 0, got {count}")
        self._injected_faults.extend([kind] * count)

    def _assign_estimate(self, values: gtsam.Values, source: str) -> None:
        """Take every pose from ``values``; raises (estimate untouched) if one is missing or
        non-finite. Only the poses whose value changed are written (and listed for
        :meth:`moved_since`): after an iSAM2 update most of a large graph has not moved.

        The poses are read in one call (``gtsam.utilities.extractPose2``, key order) rather
        than one ``atPose2`` per key: at 15,000 poses that took most of a step's solve."""
        keys = np.fromiter(self._nodes, dtype=np.int64, count=len(self._nodes))
        new = self._values_matrix(values, keys, source)
        bad = ~np.isfinite(new).all(axis=1)
        if bad.any():
            first = int(keys[int(np.argmax(bad))])
            raise FloatingPointError(
                f"{source} estimate is non-finite at {int(bad.sum())} poses, e.g. "
                f"{split_key(first)}"
            )
        if not len(keys):
            return
        cache = self._est_cache
        m = 0 if cache is None else len(cache[0])
        if cache is not None and m <= len(keys) and np.array_equal(cache[0], keys[:m]):
            # nodes are only ever appended: the last write covers all but the newest
            old = np.empty_like(new)
            old[:m] = cache[1]
            tail = [self._estimate[int(k)] for k in keys[m:]]
            old[m:] = np.array(tail, dtype=float).reshape(-1, 3)
        else:
            old = np.array([self._estimate[int(k)] for k in keys], dtype=float).reshape(-1, 3)
        changed = np.any(new != old, axis=1)
        moved = keys[changed]
        for k, p in zip(moved.tolist(), new[changed], strict=True):
            self._estimate[k] = p
        self._est_cache = (keys, new)
        self._note_moved(np.sort(moved))

    def _values_matrix(
        self, values: gtsam.Values, keys: NDArray[np.int64], source: str
    ) -> FloatArray:
        """``(len(keys), 3)`` poses of ``keys`` in ``values`` (PoseGraphError naming a missing
        one)."""
        have = np.asarray(values.keys(), dtype=np.int64)
        order: NDArray[np.intp] | None = None
        if have.size > 1 and not bool(np.all(have[1:] > have[:-1])):
            order = np.argsort(have, kind="stable")  # GTSAM lists keys sorted; be sure
            have = have[order]
        pos = np.searchsorted(have, keys)
        found = pos < len(have)
        found[found] = have[pos[found]] == keys[found]
        if not found.all():
            missing = int(keys[int(np.argmin(found))])
            raise PoseGraphError(f"{source}: no value for pose {split_key(missing)}")
        try:
            every = np.asarray(gtsam.utilities.extractPose2(values), dtype=float)
        except Exception:  # a binding without it: one pose at a time
            every = np.zeros((0, 3))
        if order is not None and every.shape == (len(have), 3):
            every = every[order]
        if every.shape != (len(have), 3):  # values that are not all Pose2
            return np.array(
                [se2.pose_vec(values.atPose2(int(k))) for k in keys], dtype=float
            ).reshape(-1, 3)
        return every[pos]

    def set_estimate(self, values: gtsam.Values) -> None:
        """Replace the estimate with ``values`` (must hold every pose, all finite)."""
        try:
            self._assign_estimate(values, "set_estimate")
        except FloatingPointError as err:
            raise PoseGraphError(str(err)) from None

    def optimize(
        self,
        *,
        method: SolveMethod | None = None,
        ordering: OrderingKind | None = None,
    ) -> SolveSummary:
        """Batch maximum-likelihood solve from the current estimate; updates the estimate."""
        if not self._nodes:
            return SolveSummary(chi2=0.0, iterations=0, total_s=0.0, components=0)
        fg, values = self.factor_graph()
        result = optimize_batch(
            fg,
            values,
            method=method or self.config.method,
            ordering=ordering or self.config.ordering,
            max_iterations=self.config.max_iterations,
            relative_error_tol=self.config.relative_error_tol,
        )
        self._assign_estimate(result.values, "batch")
        self._isam_stale = True
        return SolveSummary(
            chi2=result.chi2,
            iterations=result.iterations,
            total_s=result.total_s,
            components=len(set(self.components().values())),
        )

    def marginal_covariance(self, key: int) -> FloatArray:
        """Marginal covariance (3x3, body frame of the pose) of ``key`` at the current estimate."""
        self._require_key(key, "marginal")
        fg, values = self.factor_graph()
        return np.asarray(gtsam.Marginals(fg, values).marginalCovariance(key))

    # ---- uncertainty, initialization, simplification (paper 4.6, 4.7) ----------------------

    def _relative_arrays(
        self,
    ) -> tuple[
        list[int], dict[int, int], list[EdgeRecord], NDArray[np.int64], FloatArray, FloatArray
    ]:
        keys = sorted(self._nodes)
        index = {k: i for i, k in enumerate(keys)}
        rel = [e for e in self._edges.values() if e.key_b is not None]
        ij = np.array([[index[e.key_a], index[e.key_b]] for e in rel], dtype=np.int64)  # type: ignore[index]
        z = np.array([e.z for e in rel], dtype=float).reshape(-1, 3)
        cov = np.array([e.covariance for e in rel], dtype=float).reshape(-1, 3, 3)
        return keys, index, rel, ij.reshape(-1, 2), z, cov

    def projection(
        self, source_key: int, *, target_key: int | None = None, max_trace: float = math.inf
    ) -> tuple[NDArray[np.int64], ProjectionResult]:
        """Dijkstra projection from ``source_key`` over the relative edges (paper 4.6).

        Returns ``(keys, result)``: row ``i`` of ``result`` belongs to ``keys[i]``; covariances
        bound the relative uncertainty ``source^-1 * pose`` from above (loop-closure candidate
        search uses them to size its search windows).
        """
        self._require_key(source_key, "projection")
        if target_key is not None:
            self._require_key(target_key, "projection")
        keys, index, _, ij, z, cov = self._relative_arrays()
        adjacency = Adjacency.from_arrays(len(keys), ij, z, cov)
        result = dijkstra_projection(
            adjacency,
            index[source_key],
            target=None if target_key is None else index[target_key],
            max_trace=max_trace,
        )
        return np.array(keys, dtype=np.int64), result

    def initialize_from_spanning_trees(self) -> None:
        """Re-initialize the estimate from minimum-uncertainty spanning trees (paper 4.6).

        The global anchors are the ``PRIOR`` edges and the map robot's first pose; each pose
        they reach gets the weighted average of the trees' predictions. Poses of components
        without global information keep their estimate.
        """
        keys, index, _, ij, z, cov = self._relative_arrays()
        anchors = [
            GlobalAnchor(index[e.key_a], e.z, e.covariance)
            for e in self._edges.values()
            if e.provenance is Provenance.PRIOR
        ]
        cfg = self.config
        map_key = pose_key(cfg.map_robot_id, 0)
        if map_key in self._nodes:
            target = se2.compose(np.array(cfg.map_from_odom), self._nodes[map_key].odom_from_base)
            sig = np.array([cfg.anchor_sigma_xy_m, cfg.anchor_sigma_xy_m, cfg.anchor_sigma_yaw_rad])
            anchors.append(GlobalAnchor(index[map_key], target, np.diag(sig**2)))
        if not anchors:
            return
        current = np.array([self._estimate[k] for k in keys])
        init = spanning_tree_initialization(len(keys), ij, z, cov, anchors, fallback=current)
        for k, p in zip(keys, init, strict=True):
            self._estimate[k] = p
        self._est_cache = None
        self._note_moved(keys)
        self._isam_stale = True

    def simplify(self, *, alpha: float = 5.0) -> list[EdgeRecord]:
        """Algorithm 1 (paper 4.7) on the relative edges at the current estimate.

        Call :meth:`optimize` first: kept edges are re-expressed with zero residual at the
        current estimate, which stays the maximum-likelihood solution. Repeated edges are merged;
        a merged edge keeps the provenance and id of its first member and the latest time.
        Priors are untouched. Returns the removed records (take a :meth:`snapshot` first to
        be able to undo: the current state is baked into the kept edges).
        """
        keys, _, rel, ij, z, cov = self._relative_arrays()
        estimate = np.array([self._estimate[k] for k in keys])
        simple = simplify_graph(len(keys), ij, cov, estimate, alpha=alpha, z=z)
        kept_ids: set[int] = set()
        replaced: dict[int, EdgeRecord] = {}
        for (i, j), zk, ck, members in zip(
            simple.ij.tolist(), simple.z, simple.cov, simple.source_edges, strict=True
        ):
            first = rel[members[0]]
            replaced[first.edge_id] = EdgeRecord(
                edge_id=first.edge_id,
                key_a=keys[i],
                key_b=keys[j],
                z=zk,
                covariance=ck,
                provenance=first.provenance,
                time_s=max(rel[m].time_s for m in members),
            )
            kept_ids.add(first.edge_id)
        removed = [e for e in rel if e.edge_id not in kept_ids]
        self._edges = {
            eid: replaced.get(eid, e)
            for eid, e in self._edges.items()
            if e.key_b is None or eid in kept_ids
        }
        self._edge_log = list(self._edges)
        self._epoch += 1
        self._components = None
        self._isam_stale = True
        return removed

    def relative_edge_count(self) -> int:
        """Edges between two poses (priors left out); counted once per change."""
        mark = self.change_mark()
        if self._relative_count is None or self._relative_count[0] != mark:
            n = sum(1 for e in self._edges.values() if e.key_b is not None)
            self._relative_count = (mark, n)
        return self._relative_count[1]

    def simplify_due(self, now_s: float) -> bool:
        """Whether :attr:`PoseGraphConfig.auto_simplify` asks for a simplification now
        (:class:`AutoSimplifyConfig`: size, edges per pose, time since the last one)."""
        cfg = self.config.auto_simplify
        if cfg is None or len(self._nodes) < cfg.min_poses:
            return False
        if now_s - self._last_simplified_s < cfg.min_interval_s:
            return False
        return self.relative_edge_count() > cfg.max_edges_per_pose * len(self._nodes)

    def simplify_if_due(self, now_s: float) -> list[EdgeRecord]:
        """Algorithm 1 (:meth:`simplify`, ``AutoSimplifyConfig.alpha``) when
        :meth:`simplify_due`; returns the removed edges (empty: not due).

        Call it right after a successful solve, on a graph in a known-good state (no closure
        awaiting validation, no solver fault): the kept edges are re-expressed at the current
        estimate, which is taken as the optimum. Consumers see the change through
        :meth:`additions_since` (None: rebuild) and iSAM2 is re-seeded at the next solve.
        """
        if not self.simplify_due(now_s):
            return []
        cfg = self.config.auto_simplify
        assert cfg is not None
        self._last_simplified_s = float(now_s)
        removed = self.simplify(alpha=cfg.alpha)
        log.info(
            "graph simplified at %.1f s: %d edges removed, %d poses, %d edges left",
            now_s,
            len(removed),
            len(self._nodes),
            len(self._edges),
        )
        return removed

    # ---- g2o -------------------------------------------------------------------------------

    @classmethod
    def from_g2o(
        cls,
        graph: G2oGraph,
        *,
        robot_id: int = 0,
        period_s: float = 1.0,
        config: PoseGraphConfig | None = None,
    ) -> PoseGraph:
        """A one-robot pose graph from a g2o graph whose vertices ``0..N-1`` form an odometry
        chain (``i -> i+1`` edges become ``ODOMETRY``, the others ``LOOP_AUTO``). Pose ``i``
        is stamped ``i * period_s``; the estimate starts from chained odometry.

        A chain with gaps (no ``k-1 -> k`` edge) is crossed by the relative pose of the spanning
        tree over all edges (:func:`gcs.graph.g2o.initial_poses`): each gap becomes an
        ``ODOMETRY`` edge stating it with ``GAP_SIGMA_XY_M`` / ``GAP_SIGMA_YAW_RAD``, which keeps
        the robot's chain whole and carries next to no information (a weight 1e-6 of a
        metre-sigma edge), so the optimum is the file's.
        """
        ids = graph.node_ids
        if ids.size and not np.array_equal(ids, np.arange(ids.size)):
            raise PoseGraphError("from_g2o: vertex ids must be 0..N-1")
        cfg = config or PoseGraphConfig(map_robot_id=robot_id)
        out = cls(cfg)
        start = initial_poses(graph, "chained").poses
        chain: dict[int, int] = {}
        for m, (i, j) in enumerate(graph.edge_ij.tolist()):
            if abs(i - j) == 1 and min(i, j) not in chain:
                chain[min(i, j)] = m
        covs = np.linalg.inv(graph.edge_info)
        # The robot's odometry: each stretch chains its own edges; a gap is crossed by the
        # start's relative pose (the odometry edges are measured from consecutive odom poses).
        odo = np.array(start, dtype=float, copy=True)
        for k in range(1, ids.size):
            link = chain.get(k - 1)
            if link is None:
                step = se2.between(start[k - 1], start[k])
            elif graph.edge_ij[link, 0] == k - 1:
                step = graph.edge_z[link]
            else:
                step = se2.inverse(graph.edge_z[link])
            odo[k] = se2.compose(odo[k - 1], step)
        gap_cov = np.diag([GAP_SIGMA_XY_M**2, GAP_SIGMA_XY_M**2, GAP_SIGMA_YAW_RAD**2])
        for k in range(ids.size):
            if k == 0:
                out.add_pose(robot_id, odom_from_base=odo[0], time_s=0.0)
                continue
            m_or_none = chain.get(k - 1)
            if m_or_none is None:
                cov = gap_cov
            else:
                cov = covs[m_or_none]
                if graph.edge_ij[m_or_none, 0] != k - 1:  # stated k -> k-1: as k-1 -> k
                    ad = se2.adjoint(graph.edge_z[m_or_none])
                    cov = ad @ cov @ ad.T
            out.add_pose(
                robot_id, odom_from_base=odo[k], time_s=k * period_s, odometry_covariance=cov
            )
        for m, (i, j) in enumerate(graph.edge_ij.tolist()):
            if chain.get(min(i, j)) == m:
                continue
            out.add_edge(
                pose_key(robot_id, i),
                pose_key(robot_id, j),
                a_from_b=graph.edge_z[m],
                covariance=covs[m],
                provenance=Provenance.LOOP_AUTO,
                time_s=max(i, j) * period_s,
            )
        return out

    def to_g2o(self) -> G2oGraph:
        """The relative edges and current estimate as a g2o graph (vertex ids are the keys)."""
        keys = np.array(sorted(self._nodes), dtype=np.int64)
        rel = [e for e in self._edges.values() if e.key_b is not None]
        return G2oGraph(
            vertex_ids=keys,
            vertex_poses=np.array([self._estimate[int(k)] for k in keys]).reshape(-1, 3),
            edge_ij=np.array([[e.key_a, e.key_b] for e in rel], dtype=np.int64).reshape(-1, 2),
            edge_z=np.array([e.z for e in rel]).reshape(-1, 3),
            edge_info=np.linalg.inv(np.array([e.covariance for e in rel]).reshape(-1, 3, 3)),
        )

    # ---- helpers -------------------------------------------------------------------------

    def _require_robot(self, robot_id: int) -> None:
        if robot_id not in self._last_key:
            raise PoseGraphError(f"unknown robot {robot_id} (known: {self.robots})")

    def _require_key(self, key: int, what: str) -> None:
        if key not in self._nodes:
            robot, index = split_key(key) if 0 <= key < (1 << 56) else (None, None)
            raise PoseGraphError(f"{what}: unknown pose (robot {robot}, index {index})")

    def __setstate__(self, state: dict[str, Any]) -> None:
        """Unpickle; a graph pickled before the incremental views (issue 16) gets them built
        from its nodes and edges, and iSAM2 re-seeded at the next solve."""
        self.__dict__.update(state)
        d = self.__dict__
        if "_node_log" not in d:
            d["_node_log"] = sorted(self._nodes)
            d["_edge_log"] = list(self._edges)
        d.setdefault("_epoch", 0)
        d.setdefault("_estimate_revision", 0)
        d.setdefault("_moved", collections.deque(maxlen=_MOVED_LOG))
        d.setdefault("_last_simplified_s", -math.inf)
        d.setdefault("_relative_count", None)
        d.setdefault("_prior_cache", None)
        d.setdefault("_est_cache", None)
        d.setdefault("_isam", None)
        if "_isam_mark" not in d:
            d.pop("_isam_edges", None)
            d.pop("_isam_keys", None)
            d["_isam_mark"] = None
            d["_isam_stale"] = True

    def __deepcopy__(self, memo: dict[int, object]) -> PoseGraph:
        other = PoseGraph(self.config)
        other.restore(self.snapshot())
        other._next_edge_id = self._next_edge_id
        other._reported = dict(self._reported)
        other._corrections = dict(self._corrections)
        return other

    def copy(self) -> PoseGraph:
        """An independent copy."""
        return copy.deepcopy(self)


def _describe(err: BaseException) -> str:
    """``Type: message`` of an exception on one line, without GTSAM's long explanation."""
    text = " ".join(str(err).split())
    text = text.split(" Thrown when", 1)[0]
    if len(text) > 160:
        text = text[:157] + "..."
    return f"{type(err).__name__}: {text}" if text else type(err).__name__
