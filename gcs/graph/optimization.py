"""Optimization of the pose graph: batch Gauss-Newton / Levenberg-Marquardt / Dogleg with a
chosen variable ordering, and incremental iSAM2 for online use (paper 4.6).

Orderings: ``"colamd"`` (GTSAM's COLAMD), ``"metis"`` (GTSAM's METIS), ``"natural"`` (key order)
and ``"emd"``, the exact minimum degree ordering of :mod:`gcs.graph.emd_ordering`, handed to
GTSAM as a custom ``gtsam.Ordering``. Fill-in is counted the same way for every ordering (the
non-zeros of the Cholesky factor of the Pose2 system, 3 scalars a variable).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Literal

import gtsam
import numpy as np
from numpy.typing import NDArray

from gcs.graph.emd_ordering import elimination_degrees, factor_nnz, minimum_degree_ordering

__all__ = [
    "METHODS",
    "ORDERINGS",
    "BatchResult",
    "Isam2Solver",
    "OrderingKind",
    "SolveMethod",
    "chi2",
    "compute_ordering",
    "ordering_keys",
    "ordering_nnz",
    "optimize_batch",
    "variable_adjacency",
]

IntArray = NDArray[np.int64]
OrderingKind = Literal["colamd", "metis", "natural", "emd"]
SolveMethod = Literal["gn", "lm", "dogleg"]
ORDERINGS: tuple[OrderingKind, ...] = ("colamd", "metis", "natural", "emd")
METHODS: tuple[SolveMethod, ...] = ("gn", "lm", "dogleg")


def chi2(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> float:
    """``sum e' Omega e`` over all factors (twice GTSAM's error)."""
    return 2.0 * graph.error(values)


def variable_adjacency(graph: gtsam.NonlinearFactorGraph) -> tuple[IntArray, IntArray]:
    """``(keys, edges)``: the sorted keys of ``graph`` and its variable-adjacency pairs as (M, 2)
    indices into ``keys`` (every pair of variables that share a factor)."""
    key_lists = [graph.at(i).keys() for i in range(graph.size()) if graph.at(i) is not None]
    keys = np.unique(np.fromiter((k for ks in key_lists for k in ks), dtype=np.uint64))
    pairs: list[tuple[int, int]] = []
    for ks in key_lists:
        for a in range(len(ks)):
            for b in range(a + 1, len(ks)):
                pairs.append((ks[a], ks[b]))
    raw = np.array(pairs, dtype=np.uint64).reshape(-1, 2)
    edges = np.searchsorted(keys, raw).astype(np.int64)
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
    """Outcome of :func:`optimize_batch`: the estimate, its chi2, iterations and timings (s)."""

    values: gtsam.Values
    chi2: float
    iterations: int
    ordering_s: float
    total_s: float


def _params(
    method: SolveMethod, *, max_iterations: int, relative_error_tol: float
) -> gtsam.NonlinearOptimizerParams:
    if method == "gn":
        params = gtsam.GaussNewtonParams()
    elif method == "lm":
        params = gtsam.LevenbergMarquardtParams()
    elif method == "dogleg":
        params = gtsam.DoglegParams()
    else:
        raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")
    params.setMaxIterations(max_iterations)
    params.setRelativeErrorTol(relative_error_tol)
    params.setAbsoluteErrorTol(0.0)
    return params


def optimize_batch(
    graph: gtsam.NonlinearFactorGraph,
    initial: gtsam.Values,
    *,
    method: SolveMethod = "gn",
    ordering: OrderingKind | gtsam.Ordering = "colamd",
    max_iterations: int = 100,
    relative_error_tol: float = 1e-5,
) -> BatchResult:
    """Maximum-likelihood estimate of ``graph`` from ``initial`` (paper 4.2, 4.6).

    The ordering is computed once (or given) and reused by every iteration. Iterations stop when
    the relative decrease of the error falls below ``relative_error_tol``.
    """
    t0 = time.perf_counter()
    order = compute_ordering(graph, ordering) if isinstance(ordering, str) else ordering
    t1 = time.perf_counter()
    params = _params(method, max_iterations=max_iterations, relative_error_tol=relative_error_tol)
    params.setOrdering(order)
    if method == "gn":
        opt = gtsam.GaussNewtonOptimizer(graph, initial, params)
    elif method == "lm":
        opt = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    else:
        opt = gtsam.DoglegOptimizer(graph, initial, params)
    values = opt.optimize()
    t2 = time.perf_counter()
    return BatchResult(
        values=values,
        chi2=chi2(graph, values),
        iterations=int(opt.iterations()),
        ordering_s=t1 - t0,
        total_s=t2 - t0,
    )


class Isam2Solver:
    """Incremental smoothing and mapping (iSAM2) for online use.

    Feed new factors and the initial values of new variables with :meth:`update`; read the
    current estimate with :meth:`estimate`. iSAM2 orders variables itself (constrained COLAMD
    on the affected part of its Bayes tree), so no ordering choice applies here.
    """

    def __init__(self, *, relinearize_threshold: float = 0.1, relinearize_skip: int = 10) -> None:
        params = gtsam.ISAM2Params()
        params.setRelinearizeThreshold(relinearize_threshold)
        params.relinearizeSkip = relinearize_skip
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
        """Current estimate of every variable."""
        return self._isam.calculateEstimate()

    @property
    def isam(self) -> gtsam.ISAM2:
        """The underlying ``gtsam.ISAM2`` (for marginals and statistics)."""
        return self._isam
