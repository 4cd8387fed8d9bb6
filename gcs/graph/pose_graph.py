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
"""

from __future__ import annotations

import copy
import enum
import math
from dataclasses import dataclass, field

import gtsam
import msgspec
import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from gcs.graph import se2
from gcs.graph.keys import pose_key, split_key
from gcs.graph.optimization import METHODS, ORDERINGS, OrderingKind, SolveMethod, optimize_batch

__all__ = [
    "EdgeRecord",
    "NodeRecord",
    "PoseGraph",
    "PoseGraphConfig",
    "PoseGraphError",
    "PoseGraphSnapshot",
    "Provenance",
    "SolveSummary",
]

FloatArray = NDArray[np.float64]


class PoseGraphError(ValueError):
    """Bad input to the pose graph (unknown robot or key, non-finite value, bad covariance)."""


class Provenance(enum.Enum):
    """Where a factor came from."""

    ODOMETRY = "odometry"
    FIDUCIAL = "fiducial"
    LOOP_AUTO = "loop_auto"
    LOOP_OPERATOR = "loop_operator"
    PRIOR = "prior"


class PoseGraphConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Configuration of :class:`PoseGraph`.

    ``map_robot_id``'s first pose anchors ``map`` at ``map_from_odom`` (x m, y m, yaw rad) with
    the ``anchor_sigma_*``; other components get the broad ``weak_anchor_sigma_*``.
    """

    map_robot_id: int = 0
    map_from_odom: tuple[float, float, float] = (0.0, 0.0, 0.0)
    anchor_sigma_xy_m: float = 1e-4
    anchor_sigma_yaw_rad: float = 1e-5
    weak_anchor_sigma_xy_m: float = 1e3
    weak_anchor_sigma_yaw_rad: float = 1e2
    method: str = "lm"
    ordering: str = "colamd"
    max_iterations: int = 100
    relative_error_tol: float = 1e-6

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f"method: expected one of {', '.join(METHODS)}, got {self.method!r}")
        if self.ordering not in ORDERINGS:
            raise ValueError(
                f"ordering: expected one of {', '.join(ORDERINGS)}, got {self.ordering!r}"
            )
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
    try:
        np.linalg.cholesky(arr)
    except np.linalg.LinAlgError:
        raise PoseGraphError(
            f"{what}: covariance is singular or not positive definite "
            f"(eigenvalues {np.linalg.eigvalsh(arr).tolist()})"
        ) from None
    return arr.copy()


class PoseGraph:
    """Factor graph of all robots' trajectories with provenance, anchoring and edits.

    API: :meth:`add_pose` (a robot's next pose, odometry edge added), :meth:`add_edge`
    (fiducial / loop closure), :meth:`add_prior` (global information), :meth:`optimize`,
    :meth:`map_from_odom`, :meth:`pose`, :meth:`edges`, :meth:`rewind`, :meth:`remove_edges`,
    :meth:`snapshot` / :meth:`restore`, :meth:`factor_graph` (the GTSAM graph and values).
    """

    def __init__(self, config: PoseGraphConfig | None = None) -> None:
        self.config = config or PoseGraphConfig()
        self._nodes: dict[int, NodeRecord] = {}
        self._edges: dict[int, EdgeRecord] = {}
        self._estimate: dict[int, FloatArray] = {}
        self._last_key: dict[int, int] = {}
        self._next_edge_id = 0
        self._components: dict[int, int] | None = None

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
        return self._components

    def anchored_components(self) -> set[int]:
        """Labels of components fixed in ``map`` (map robot's first pose or a PRIOR edge)."""
        comp = self.components()
        out = {comp[e.key_a] for e in self._edges.values() if e.provenance is Provenance.PRIOR}
        map_key = pose_key(self.config.map_robot_id, 0)
        if map_key in comp:
            out.add(comp[map_key])
        return out

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
            z = se2.between(self._nodes[prev].odom_from_base, pose)
            estimate = se2.compose(self._estimate[prev], z)
        self._nodes[key] = NodeRecord(key, robot_id, index, float(time_s), pose)
        self._estimate[key] = estimate
        self._last_key[robot_id] = key
        self._components = None
        if prev is not None:
            self._append(prev, key, z, cov, Provenance.ODOMETRY, time_s)
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
        self._edges[edge_id] = EdgeRecord(edge_id, key_a, key_b, z, cov, provenance, float(time_s))
        self._components = None
        return edge_id

    def _move_component(self, label: int, key: int, target: FloatArray) -> None:
        """Rigidly move component ``label`` so pose ``key`` lands on ``target``."""
        delta = se2.compose(target, se2.inverse(self._estimate[key]))
        comp = self.components()
        keys = [k for k, c in comp.items() if c == label]
        moved = se2.compose(delta, np.array([self._estimate[k] for k in keys]))
        for k, p in zip(keys, moved, strict=True):
            self._estimate[k] = p

    # ---- edits ---------------------------------------------------------------------------

    def remove_edges(self, edge_ids: list[int]) -> list[EdgeRecord]:
        """Remove edges by id (odometry edges cannot be removed); returns the removed records."""
        for eid in edge_ids:
            if eid not in self._edges:
                raise PoseGraphError(f"remove: no edge with id {eid}")
            if self._edges[eid].provenance is Provenance.ODOMETRY:
                raise PoseGraphError(f"remove: edge {eid} is odometry and cannot be removed")
        removed = [self._edges.pop(eid) for eid in edge_ids]
        self._components = None
        return removed

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
        self._next_edge_id = max(self._next_edge_id, snapshot.next_edge_id)
        self._last_key = {}
        for key in sorted(self._nodes):
            self._last_key[self._nodes[key].robot_id] = key
        self._components = None

    # ---- solving -------------------------------------------------------------------------

    def factor_graph(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
        """The GTSAM graph (edges, map anchor, weak anchors) and the current estimate."""
        fg = gtsam.NonlinearFactorGraph()
        for e in self._edges.values():
            noise = gtsam.noiseModel.Gaussian.Covariance(e.covariance)
            if e.key_b is None:
                fg.add(gtsam.PriorFactorPose2(e.key_a, se2.pose2(e.z), noise))
            else:
                fg.add(gtsam.BetweenFactorPose2(e.key_a, e.key_b, se2.pose2(e.z), noise))
        cfg = self.config
        map_key = pose_key(cfg.map_robot_id, 0)
        if map_key in self._nodes:
            target = se2.compose(np.array(cfg.map_from_odom), self._nodes[map_key].odom_from_base)
            sig = [cfg.anchor_sigma_xy_m, cfg.anchor_sigma_xy_m, cfg.anchor_sigma_yaw_rad]
            noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(sig))
            fg.add(gtsam.PriorFactorPose2(map_key, se2.pose2(target), noise))
        anchored = self.anchored_components()
        roots: dict[int, int] = {}
        for key, label in sorted(self.components().items()):
            if label not in anchored and label not in roots:
                roots[label] = key
        weak = [
            cfg.weak_anchor_sigma_xy_m,
            cfg.weak_anchor_sigma_xy_m,
            cfg.weak_anchor_sigma_yaw_rad,
        ]
        weak_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array(weak))
        for key in roots.values():
            fg.add(gtsam.PriorFactorPose2(key, se2.pose2(self._estimate[key]), weak_noise))
        values = gtsam.Values()
        for key, p in self._estimate.items():
            values.insert(key, se2.pose2(p))
        return fg, values

    def set_estimate(self, values: gtsam.Values) -> None:
        """Replace the estimate with ``values`` (must hold every pose)."""
        for key in self._nodes:
            if not values.exists(key):
                raise PoseGraphError(f"set_estimate: no value for pose {split_key(key)}")
        for key in self._nodes:
            self._estimate[key] = se2.pose_vec(values.atPose2(key))

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
            method=method or self.config.method,  # type: ignore[arg-type]
            ordering=ordering or self.config.ordering,  # type: ignore[arg-type]
            max_iterations=self.config.max_iterations,
            relative_error_tol=self.config.relative_error_tol,
        )
        self.set_estimate(result.values)
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

    # ---- helpers -------------------------------------------------------------------------

    def _require_robot(self, robot_id: int) -> None:
        if robot_id not in self._last_key:
            raise PoseGraphError(f"unknown robot {robot_id} (known: {self.robots})")

    def _require_key(self, key: int, what: str) -> None:
        if key not in self._nodes:
            robot, index = split_key(key) if 0 <= key < (1 << 56) else (None, None)
            raise PoseGraphError(f"{what}: unknown pose (robot {robot}, index {index})")

    def __deepcopy__(self, memo: dict[int, object]) -> PoseGraph:
        other = PoseGraph(self.config)
        other.restore(self.snapshot())
        other._next_edge_id = self._next_edge_id
        return other

    def copy(self) -> PoseGraph:
        """An independent copy."""
        return copy.deepcopy(self)
