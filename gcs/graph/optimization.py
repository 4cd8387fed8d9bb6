"""Optimization of the pose graph: batch Gauss-Newton / Levenberg-Marquardt / Dogleg with a
chosen variable ordering, and incremental iSAM2 for online use (paper 4.6).

Methods ``"gn"``, ``"lm"``, ``"dogleg"`` are GTSAM's optimizers. ``"block_lm"`` (the default)
and ``"block_gn"`` run on the compiled block Cholesky for graphs of ``BetweenFactorPose2`` and
``PriorFactorPose2`` with Gaussian noise (the same model, error and retraction as GTSAM;
GTSAM's multifrontal elimination spends ~20 ms on the 7 Mflop of manhattan_olson3500's factor,
mostly per-clique overhead; the compiled kernel ~1.3 ms):

- ``"block_lm"``: :func:`solve_pose2`, Levenberg-Marquardt
  (:mod:`gcs.graph.pose2_levenberg_marquardt`), which never accepts a step that raises the
  chi2 and takes the Gauss-Newton step where that is good (as fast as ``"block_gn"`` on
  manhattan_olson3500); when the estimate it reaches fails the chi2 test (chi2 above
  ``dof + 3 sqrt(2 dof)``, ``dof`` = residual dimensions minus variable dimensions: a local
  minimum, as Levenberg-Marquardt from chained odometry on manhattan_M3500b) it solves again
  from the minimum-uncertainty spanning-tree initialization (paper 4.6) and keeps the lower;
- ``"block_gn"``: plain Gauss-Newton (:mod:`gcs.graph.pose2_gauss_newton`), GTSAM's
  Gauss-Newton stopping rule; it stops at the first step that raises the chi2 and returns the
  estimate before that step, so from a poor start it can end far above the optimum.

Their result comes back as ``gtsam.Values`` and its chi2 is GTSAM's. :func:`optimize_pose2`
takes the factors as arrays (no per-factor Python work), e.g. from
:func:`pose2_factors_from_g2o`; :func:`optimize_batch` extracts them from the graph.

Orderings: ``"colamd"`` (GTSAM's COLAMD), ``"metis"`` (GTSAM's METIS), ``"natural"`` (key order)
and ``"emd"``, the exact minimum degree ordering of :mod:`gcs.graph.emd_ordering`, handed to
GTSAM as a custom ``gtsam.Ordering``. Fill-in is counted the same way for every ordering (the
non-zeros of the Cholesky factor of the Pose2 system, 3 scalars a variable).
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from typing import Any, Literal

import gtsam
import msgspec
import numpy as np
from numpy.typing import NDArray

from gcs.graph.block_cholesky import BlockSymbolic, symbolic_factorization
from gcs.graph.emd_ordering import elimination_degrees, factor_nnz, minimum_degree_ordering
from gcs.graph.g2o import G2oGraph, component_roots
from gcs.graph.pose2_gauss_newton import (
    Pose2Factors,
    gauss_newton_pose2,
    local_coordinates,
)
from gcs.graph.pose2_levenberg_marquardt import (
    LevenbergMarquardtConfig,
    levenberg_marquardt_pose2,
)
from gcs.graph.spanning_tree_init import spanning_tree_from_factors

__all__ = [
    "METHODS",
    "ORDERINGS",
    "BatchResult",
    "BlockMethod",
    "Isam2Config",
    "Isam2Solver",
    "OrderingKind",
    "Pose2Solution",
    "SolveMethod",
    "chi2",
    "chi2_test_threshold",
    "compute_ordering",
    "ordering_keys",
    "ordering_nnz",
    "optimize_batch",
    "optimize_pose2",
    "pose2_factors",
    "pose2_factors_from_g2o",
    "solve_pose2",
    "values_from_poses",
    "variable_adjacency",
]

IntArray = NDArray[np.int64]
OrderingKind = Literal["colamd", "metis", "natural", "emd"]
SolveMethod = Literal["gn", "lm", "dogleg", "block_gn", "block_lm"]
BlockMethod = Literal["block_lm", "block_gn"]
ORDERINGS: tuple[OrderingKind, ...] = ("colamd", "metis", "natural", "emd")
METHODS: tuple[SolveMethod, ...] = ("gn", "lm", "dogleg", "block_gn", "block_lm")
FloatArray = NDArray[np.floating[Any]]


def chi2(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> float:
    """``sum e' Omega e`` over all factors (twice GTSAM's error)."""
    return 2.0 * graph.error(values)


def variable_adjacency(graph: gtsam.NonlinearFactorGraph) -> tuple[IntArray, IntArray]:
    """``(keys, edges)``: the sorted keys of ``graph`` and its variable-adjacency pairs as (M, 2)
    indices into ``keys`` (every pair of variables that share a factor)."""
    key_lists = [f.keys() for f in map(graph.at, range(graph.size())) if f is not None]
    pairs = [ks for ks in key_lists if len(ks) == 2]
    for ks in key_lists:
        if len(ks) > 2:
            pairs.extend([ks[a], ks[b]] for a in range(len(ks)) for b in range(a + 1, len(ks)))
    raw = np.array(pairs, dtype=np.uint64).reshape(-1, 2)
    singles = np.array([ks[0] for ks in key_lists if len(ks) == 1], dtype=np.uint64)
    keys, inverse = np.unique(np.concatenate([raw.ravel(), singles]), return_inverse=True)
    edges = inverse[: raw.size].reshape(-1, 2).astype(np.int64)
    return keys.astype(np.int64), edges


def ordering_keys(ordering: gtsam.Ordering) -> IntArray:
    """The keys of a ``gtsam.Ordering`` in elimination order."""
    return np.array([ordering.at(i) for i in range(ordering.size())], dtype=np.int64)


def compute_ordering(graph: gtsam.NonlinearFactorGraph, kind: OrderingKind) -> gtsam.Ordering:
    """Variable ordering of ``graph`` by ``kind`` (see module docstring)."""
    if kind == "colamd":
        return gtsam.Ordering.ColamdNonlinearFactorGraph(graph)
    if kind == "metis":
        return gtsam.Ordering.MetisNonlinearFactorGraph(graph)
    if kind == "natural":
        return gtsam.Ordering.NaturalNonlinearFactorGraph(graph)
    if kind == "emd":
        keys, edges = variable_adjacency(graph)
        order, _ = minimum_degree_ordering(keys.size, edges)
        return gtsam.Ordering(keys[order].tolist())
    raise ValueError(f"unknown ordering {kind!r}; expected one of {', '.join(ORDERINGS)}")


def ordering_nnz(
    graph: gtsam.NonlinearFactorGraph, ordering: gtsam.Ordering, *, dim: int = 3
) -> int:
    """Non-zeros of the Cholesky factor of ``graph``'s normal equations under ``ordering``."""
    keys, edges = variable_adjacency(graph)
    order_idx = np.searchsorted(keys, ordering_keys(ordering))
    return factor_nnz(elimination_degrees(keys.size, edges, order_idx), dim=dim)


@dataclass(frozen=True)
class BatchResult:
    """Outcome of :func:`optimize_batch`: the estimate, its chi2, iterations and timings (s);
    for the block methods ``chi2_history`` (the solver's chi2 before the first and after every
    accepted step, of the run whose estimate is returned) and ``start`` (``"given"`` or
    ``"spanning_tree"``, the start that run began from)."""

    values: gtsam.Values
    chi2: float
    iterations: int
    ordering_s: float
    total_s: float
    chi2_history: tuple[float, ...] = ()
    start: str = "given"


def _optimizer(
    method: str,
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    ordering: gtsam.Ordering,
    *,
    max_iterations: int,
    relative_error_tol: float,
) -> gtsam.NonlinearOptimizer:
    """A GTSAM optimizer of ``method`` with a fixed ordering and stopping rule."""
    if method == "gn":
        gn = gtsam.GaussNewtonParams()
        _configure(gn, ordering, max_iterations, relative_error_tol)
        return gtsam.GaussNewtonOptimizer(graph, initial, gn)
    if method == "lm":
        lm = gtsam.LevenbergMarquardtParams()
        _configure(lm, ordering, max_iterations, relative_error_tol)
        return gtsam.LevenbergMarquardtOptimizer(graph, initial, lm)
    if method == "dogleg":
        dl = gtsam.DoglegParams()
        _configure(dl, ordering, max_iterations, relative_error_tol)
        return gtsam.DoglegOptimizer(graph, initial, dl)
    raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")


def _configure(
    params: gtsam.NonlinearOptimizerParams,
    ordering: gtsam.Ordering,
    max_iterations: int,
    relative_error_tol: float,
) -> None:
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_error_tol)
    params.setAbsoluteErrorTol(0.0)
    params.setOrdering(ordering)


def optimize_batch(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    *,
    method: SolveMethod = "block_lm",
    ordering: OrderingKind | gtsam.Ordering = "colamd",
    max_iterations: int = 100,
    relative_error_tol: float = 1e-5,
) -> BatchResult:
    """Maximum-likelihood estimate of ``graph`` from ``initial`` (paper 4.2, 4.6).

    The ordering is computed once (or given) and reused by every iteration. Iterations stop when
    the relative decrease of the error falls below ``relative_error_tol``. The block methods
    (``"block_lm"``, the default, and ``"block_gn"``; see the module docstring) read the factors
    out of ``graph`` first (see :func:`pose2_factors`; :func:`optimize_pose2` skips that when the
    arrays are at hand) and raise ``ValueError`` for a graph with other factors.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    if method in ("block_gn", "block_lm"):
        t0 = time.perf_counter()
        keys = np.asarray(initial.keys(), dtype=np.int64)
        res = optimize_pose2(
            graph,
            initial,
            pose2_factors(graph, keys),
            keys,
            method=method,  # type: ignore[arg-type]
            ordering=ordering,
            max_iterations=max_iterations,
            relative_error_tol=relative_error_tol,
        )
        return dataclasses.replace(res, total_s=time.perf_counter() - t0)
    t0 = time.perf_counter()
    order = compute_ordering(graph, ordering) if isinstance(ordering, str) else ordering
    t1 = time.perf_counter()
    opt = _optimizer(
        method,
        graph,
        initial,
        order,
        max_iterations=max_iterations,
        relative_error_tol=relative_error_tol,
    )
    values = opt.optimize()
    t2 = time.perf_counter()
    return BatchResult(
        values=values,
        chi2=chi2(graph, values),
        iterations=int(opt.iterations()),
        ordering_s=t1 - t0,
        total_s=t2 - t0,
    )


def _key_indices(keys: IntArray, raw: IntArray, what: str) -> IntArray:
    """Indices of ``raw`` keys in the sorted ``keys``; raises naming ``what`` for a missing key."""
    idx = np.searchsorted(keys, raw)
    found = idx < keys.size
    found[found] = keys[idx[found]] == raw[found]
    if not found.all():
        raise ValueError(f"{what} refers to key {int(raw[~found].ravel()[0])}, not a variable")
    return idx.astype(np.int64)


def pose2_factors(graph: gtsam.NonlinearFactorGraph, keys: IntArray) -> Pose2Factors:
    """``graph``'s ``BetweenFactorPose2`` and ``PriorFactorPose2`` factors as arrays over the
    variables ``keys`` (variable ``k`` is key ``keys[k]``, keys sorted ascending).

    Raises ``ValueError`` naming the factor index for any other factor, a non-Gaussian noise
    model (robust, constrained) or a key not in ``keys``. Costs a few microseconds a factor.
    """
    keys = np.asarray(keys, dtype=np.int64)
    if keys.size > 1 and not (np.diff(keys) > 0).all():
        raise ValueError("pose2_factors: keys must be sorted ascending without repeats")
    ij: list[list[int]] = []
    z: list[tuple[float, float, float]] = []
    sqrt_info: list[NDArray[np.float64]] = []
    prior_key: list[int] = []
    prior_pose: list[tuple[float, float, float]] = []
    prior_sqrt_info: list[NDArray[np.float64]] = []
    for m in range(graph.size()):
        f = graph.at(m)
        if f is None:
            continue
        noise = f.noiseModel() if hasattr(f, "noiseModel") else None
        if not isinstance(noise, gtsam.noiseModel.Gaussian) or noise.isConstrained():
            raise ValueError(
                f"pose2_factors: factor {m} ({type(f).__name__}) needs a Gaussian noise model, "
                f"got {type(noise).__name__}"
            )
        if isinstance(f, gtsam.BetweenFactorPose2):
            p = f.measured()
            ij.append(list(f.keys()))
            z.append((p.x(), p.y(), p.theta()))
            sqrt_info.append(noise.R())
        elif isinstance(f, gtsam.PriorFactorPose2):
            p = f.prior()
            prior_key.append(f.keys()[0])
            prior_pose.append((p.x(), p.y(), p.theta()))
            prior_sqrt_info.append(noise.R())
        else:
            raise ValueError(
                f"pose2_factors: factor {m} is a {type(f).__name__}; the block methods handle only "
                "BetweenFactorPose2 and PriorFactorPose2"
            )
    raw_ij = np.array(ij, dtype=np.int64).reshape(-1, 2)
    raw_prior = np.array(prior_key, dtype=np.int64)
    index_ij = _key_indices(keys, raw_ij, "pose2_factors: a between factor")
    index_prior = _key_indices(keys, raw_prior, "pose2_factors: a prior")

    def info(r: list[NDArray[np.float64]]) -> NDArray[np.float64]:
        a = np.array(r, dtype=np.float64).reshape(-1, 3, 3)
        return np.asarray(a.transpose(0, 2, 1) @ a)

    return Pose2Factors(
        n=int(keys.size),
        ij=index_ij,
        z=np.array(z, dtype=np.float64).reshape(-1, 3),
        info=info(sqrt_info),
        prior_index=index_prior,
        prior_pose=np.array(prior_pose, dtype=np.float64).reshape(-1, 3),
        prior_info=info(prior_sqrt_info),
    )


def pose2_factors_from_g2o(
    graph: G2oGraph, poses: FloatArray, *, prior_sigma: float | None = 1e-6
) -> tuple[Pose2Factors, IntArray]:
    """The factors of :func:`gcs.graph.g2o.to_gtsam` (same priors) as arrays, without GTSAM.

    ``poses`` (N, 3) are the values in ``graph.node_ids`` order; a prior sits at its value on
    the first vertex of every connected component (see :func:`gcs.graph.g2o.component_roots`).
    Returns the factors and the keys (``graph.node_ids``) of their variables.
    """
    keys = graph.node_ids
    if poses.shape != (keys.size, 3):
        raise ValueError(f"poses has shape {poses.shape}, expected {(keys.size, 3)}")
    roots = (
        np.searchsorted(keys, component_roots(graph))
        if prior_sigma is not None
        else np.zeros(0, dtype=np.int64)
    )
    sigma = 1.0 if prior_sigma is None else prior_sigma
    factors = Pose2Factors(
        n=int(keys.size),
        ij=np.searchsorted(keys, graph.edge_ij),
        z=graph.edge_z,
        info=graph.edge_info,
        prior_index=roots.astype(np.int64),
        prior_pose=poses[roots],
        prior_info=np.tile(np.eye(3) / sigma**2, (roots.size, 1, 1)),
    )
    return factors, keys


def values_from_poses(template: gtsam.Values, keys: IntArray, poses: FloatArray) -> gtsam.Values:
    """``gtsam.Values`` holding ``Pose2(poses[k])`` at ``keys[k]``, built as
    ``template.retract(Log(template^-1 poses))`` (one vectorized ``Log``, one ``VectorValues``
    insert a key and one C++ retraction: ~3 ms for 3500 poses where inserting ``Pose2`` objects
    one by one takes ~25 ms). ``template`` must hold exactly ``keys``, all ``Pose2``."""
    keys = np.asarray(keys, dtype=np.int64)
    base = gtsam.utilities.extractPose2(template)
    if base.shape != (keys.size, 3) or template.size() != keys.size:
        raise ValueError(
            f"values_from_poses: template holds {template.size()} values "
            f"({base.shape[0]} Pose2), expected {keys.size} Pose2"
        )
    if not np.array_equal(np.asarray(template.keys(), dtype=np.int64), keys):
        raise ValueError("values_from_poses: template keys differ from keys")
    xi = local_coordinates(base, poses)
    delta = gtsam.VectorValues()
    insert = delta.insert
    for key, row in zip(keys.tolist(), xi, strict=True):
        insert(key, row)
    return template.retract(delta)


def chi2_test_threshold(factors: Pose2Factors) -> float:
    """``dof + 3 sqrt(2 dof)``: the chi2 of an optimum lies below it unless the noise models are
    too confident (``dof`` = residual dimensions minus variable dimensions, the chi2
    distribution's mean; ``sqrt(2 dof)`` its standard deviation). A solve that ends above it is
    suspect of a local minimum."""
    dof = max(3 * (factors.ij.shape[0] + factors.prior_index.shape[0] - factors.n), 0)
    return float(dof + 3.0 * np.sqrt(2.0 * max(dof, 1)))


@dataclass(frozen=True)
class Pose2Solution:
    """Outcome of :func:`solve_pose2`: ``poses`` (n, 3), ``chi2``, ``iterations`` (accepted
    steps of the returned run), ``chi2_history`` of that run, ``start`` it began from
    (``"given"`` or ``"spanning_tree"``), and ``runs``: every run's ``(start, chi2_history)``
    (one or two) for inspection."""

    poses: FloatArray
    chi2: float
    iterations: int
    chi2_history: tuple[float, ...]
    start: str
    runs: tuple[tuple[str, tuple[float, ...]], ...]


#: ``block_lm`` checks its progress every this many accepted steps ...
_STALL_WINDOW = 10
#: ... and, above the chi2 test, gives up on a start that did not lower the chi2 this much.
_STALL_FACTOR = 2.0


@dataclass
class _LmRun:
    poses: FloatArray
    chi2: float
    history: list[float]
    final_lambda: float
    stop_reason: str

    @property
    def iterations(self) -> int:
        return max(len(self.history) - 1, 0)


def _levenberg_marquardt_windows(
    factors: Pose2Factors,
    sym: BlockSymbolic,
    cfg: LevenbergMarquardtConfig,
    run: _LmRun,
    budget: int,
    stall_above: float | None,
) -> _LmRun:
    """Continue ``run`` by up to ``budget`` accepted steps, ``_STALL_WINDOW`` at a time (each
    window resumes the last one's ``lambda``, so the path is the uninterrupted one). With
    ``stall_above``: stop (``"stalled"``) after a window that ended above that chi2 having
    lowered it by less than ``_STALL_FACTOR``: a start sliding slowly into a local minimum
    (manhattan_M3500b from chained odometry, a weak-loop ring) is left early for the tree."""
    while True:
        window = min(_STALL_WINDOW, max(budget, 0))
        lam = max(run.final_lambda, cfg.lambda_lower_bound, 1e-300)
        wcfg = msgspec.structs.replace(cfg, max_iterations=window, lambda_initial=lam)
        r = levenberg_marquardt_pose2(factors, run.poses, config=wcfg, symbolic=sym)
        new = r.chi2_history[1:] if run.history else r.chi2_history
        run = _LmRun(r.poses, r.chi2, run.history + list(new), r.final_lambda, "")
        budget -= r.iterations
        if r.stop_reason != "max_iterations":
            run.stop_reason = r.stop_reason
            return run
        if budget <= 0:
            break
        if stall_above is not None and r.chi2 > stall_above:
            if r.chi2_history[0] < _STALL_FACTOR * r.chi2:
                run.stop_reason = "stalled"
                return run
    run.stop_reason = "max_iterations"
    return run


def solve_pose2(
    factors: Pose2Factors,
    initial: FloatArray,
    *,
    order: IntArray | None = None,
    method: BlockMethod = "block_lm",
    config: LevenbergMarquardtConfig | None = None,
    restart_from_tree: bool = True,
) -> Pose2Solution:
    """Maximum-likelihood poses of ``factors`` from ``initial`` (n, 3), the GCS's batch solve.

    ``order`` is the elimination order (default: the exact minimum degree ordering of
    :mod:`gcs.graph.emd_ordering`, computed once for both runs).

    ``"block_lm"``: Levenberg-Marquardt from ``initial``. With ``restart_from_tree``, when its
    chi2 fails :func:`chi2_test_threshold` (a local minimum, or a start still sliding slowly
    towards one: after ``_STALL_WINDOW`` accepted steps that lowered a chi2 above the threshold
    by less than ``_STALL_FACTOR``, that run is paused), it solves again from the spanning-tree
    initialization (:func:`gcs.graph.spanning_tree_init.spanning_tree_from_factors`, anchored at
    the priors); a paused run that is still the lower one is then resumed. Returns the lower
    chi2. The result is never worse than ``initial``. ``config.max_iterations`` bounds each
    run's accepted steps (``max_linear_solves`` applies a window of steps at a time).

    ``"block_gn"``: plain Gauss-Newton (``config`` gives its ``max_iterations``,
    ``relative_error_tol`` and ``error_tol``).
    """
    cfg = config or LevenbergMarquardtConfig()
    if order is None:
        order, _ = minimum_degree_ordering(factors.n, factors.ij)
    if method == "block_gn":
        gn = gauss_newton_pose2(
            factors,
            initial,
            order=order,
            max_iterations=cfg.max_iterations,
            relative_error_tol=cfg.relative_error_tol,
            error_tol=cfg.error_tol,
        )
        return Pose2Solution(
            gn.poses,
            gn.chi2,
            gn.iterations,
            gn.chi2_history,
            "given",
            (("given", gn.chi2_history),),
        )
    if method != "block_lm":
        raise ValueError(f"solve_pose2: unknown method {method!r}; expected block_lm or block_gn")
    threshold = chi2_test_threshold(factors) if restart_from_tree else None
    sym = symbolic_factorization(factors.n, factors.ij, order)

    def start_run(poses: FloatArray) -> _LmRun:
        # No history yet: the first window's starts with the start's chi2.
        return _LmRun(np.asarray(poses), float("inf"), [], cfg.lambda_initial, "")

    given = _levenberg_marquardt_windows(
        factors, sym, cfg, start_run(initial), cfg.max_iterations, threshold
    )
    runs = {"given": given}
    if threshold is not None and given.chi2 > threshold:
        tree_start = spanning_tree_from_factors(factors, given.poses)
        runs["spanning_tree"] = _levenberg_marquardt_windows(
            factors, sym, cfg, start_run(tree_start), cfg.max_iterations, None
        )
        if given.stop_reason == "stalled" and given.chi2 < runs["spanning_tree"].chi2:
            runs["given"] = _levenberg_marquardt_windows(
                factors, sym, cfg, given, cfg.max_iterations - given.iterations, None
            )
    start = min(runs, key=lambda k: runs[k].chi2)
    best = runs[start]
    return Pose2Solution(
        best.poses,
        best.chi2,
        best.iterations,
        tuple(best.history),
        start,
        tuple((k, tuple(r.history)) for k, r in runs.items()),
    )


def optimize_pose2(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    factors: Pose2Factors,
    keys: IntArray,
    *,
    method: BlockMethod = "block_lm",
    ordering: OrderingKind | gtsam.Ordering = "emd",
    max_iterations: int = 100,
    relative_error_tol: float = 1e-5,
    initial_poses: FloatArray | None = None,
    restart_from_tree: bool = True,
) -> BatchResult:
    """:func:`solve_pose2` on the compiled block Cholesky (``"block_lm"`` or ``"block_gn"``, see
    the module docstring) with GTSAM types at the edges.

    ``factors`` are ``graph``'s factors as arrays over the variables ``keys`` (sorted, the keys
    of ``initial``); ``initial_poses`` (N, 3) the values of ``initial`` in that order when at
    hand (read from ``initial`` otherwise). ``"emd"`` orders from the arrays; the other
    orderings are GTSAM's on ``graph``. Returns ``gtsam.Values`` and GTSAM's chi2 of ``graph``.
    ``max_iterations`` bounds the linear solves of each run.
    """
    t0 = time.perf_counter()
    keys = np.asarray(keys, dtype=np.int64)
    if keys.size != factors.n:
        raise ValueError(f"optimize_pose2: {keys.size} keys for {factors.n} variables")
    if isinstance(ordering, str) and ordering == "emd":
        order, _ = minimum_degree_ordering(factors.n, factors.ij)
    else:
        gorder = compute_ordering(graph, ordering) if isinstance(ordering, str) else ordering
        order = _key_indices(keys, ordering_keys(gorder), "optimize_pose2: the ordering")
        if order.size != keys.size:
            raise ValueError(f"optimize_pose2: the ordering holds {order.size} of {keys.size} keys")
    t1 = time.perf_counter()
    start = gtsam.utilities.extractPose2(initial) if initial_poses is None else initial_poses
    res = solve_pose2(
        factors,
        start,
        order=order,
        method=method,
        config=LevenbergMarquardtConfig(
            max_iterations=max_iterations, relative_error_tol=relative_error_tol
        ),
        restart_from_tree=restart_from_tree,
    )
    values = values_from_poses(initial, keys, res.poses)
    return BatchResult(
        values=values,
        chi2=chi2(graph, values),
        iterations=res.iterations,
        ordering_s=t1 - t0,
        total_s=time.perf_counter() - t0,
        chi2_history=res.chi2_history,
        start=res.start,
    )


class Isam2Config(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """iSAM2 relinearization: variables whose update exceeds ``relinearize_threshold`` (tangent
    norm) are relinearized, checked every ``relinearize_skip`` updates; with
    ``partial_relinearization_check`` only in the part of the Bayes tree an update touches
    (about 1.6x faster per node on city10000, final chi2 within 0.1% of the batch optimum)."""

    relinearize_threshold: float = 0.1
    relinearize_skip: int = 10
    partial_relinearization_check: bool = True


class Isam2Solver:
    """Incremental smoothing and mapping (iSAM2) for online use.

    Feed new factors and the initial values of new variables with :meth:`update`; read the
    current estimate with :meth:`estimate` or :meth:`estimate_pose`. iSAM2 orders variables
    itself (constrained COLAMD on the affected part of its Bayes tree), so no ordering choice
    applies here.
    """

    def __init__(self, config: Isam2Config | None = None) -> None:
        self.config = config or Isam2Config()
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(self.config.relinearize_threshold)
        params.relinearizeSkip = self.config.relinearize_skip
        params.enablePartialRelinearizationCheck = self.config.partial_relinearization_check
        self._isam = gtsam.ISAM2(params)

    def update(
        self,
        new_factors: gtsam.NonlinearFactorGraph,
        new_values: gtsam.Values,
        *,
        remove_factor_indices: list[int] | None = None,
    ) -> list[int]:
        """Add factors and variables (and remove factors by index); returns the new indices."""
        if remove_factor_indices:
            result = self._isam.update(new_factors, new_values, remove_factor_indices)
        else:
            result = self._isam.update(new_factors, new_values)
        return list(result.getNewFactorsIndices())

    def estimate(self) -> gtsam.Values:
        """Current estimate of every variable (back-substitutes the whole Bayes tree)."""
        return self._isam.calculateEstimate()

    def estimate_pose(self, key: int) -> gtsam.Pose2:
        """Current estimate of one ``Pose2`` variable."""
        return self._isam.calculateEstimatePose2(key)

    @property
    def isam(self) -> gtsam.ISAM2:
        """The underlying ``gtsam.ISAM2`` (for marginals and statistics)."""
        return self._isam
