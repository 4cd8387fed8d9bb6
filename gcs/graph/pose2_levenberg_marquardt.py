"""Levenberg-Marquardt for ``Pose2`` graphs on the compiled block Cholesky (paper 4.2, 4.6).

The model, error, Jacobians and retraction are those of :mod:`gcs.graph.pose2_gauss_newton`
(GTSAM's ``BetweenFactorPose2`` / ``PriorFactorPose2``); this module adds the trust region that
plain Gauss-Newton lacks. Gauss-Newton takes every step of the linearized problem: far from the
optimum (a badly wrapped start, a chain of rotation noise) the step can raise the chi2 by orders
of magnitude, and then there is nothing to do but stop. Here each step solves the damped normal
equations ``(H + lambda D) delta = -g`` and is accepted only when the chi2 really falls
(``chi2_new < chi2``) and by at least ``min_model_fidelity`` of the decrease the linear model
predicted (``pred = -g' delta + lambda delta' D delta``). A rejected step multiplies ``lambda``
by ``lambda_factor`` and is solved again from the same linearization; an accepted one divides
it. This is GTSAM's ``LevenbergMarquardtOptimizer`` schedule (``lambdaInitial`` 1e-5, factor
10, lower bound 0, upper bound 1e5, fidelity 1e-3, ``D = I``), except that a step whose chi2
rises is never accepted (GTSAM accepts a step of near-zero predicted decrease regardless). From
the same start it follows GTSAM's path: on every shipped graph and on weak-loop rings it ends
on the chi2 GTSAM LM ends on. ``schedule="nielsen"`` is Nielsen's (GTSAM's
``useFixedLambdaFactor=false``); ``diagonal_damping`` Marquardt's ``D = diag(H)``. Both were
tried: they reach other local minima (sometimes lower, e.g. 4997 / 4727 on manhattan_M3500b
from the spanning tree against the fixed schedule's 5137; sometimes far higher, e.g. on
weak-loop rings from the tree), so the default stays GTSAM's.

Multi-modal problems (a ring closed by one weak loop, heavy rotation noise) have local minima
that no local method escapes from a bad start; :func:`gcs.graph.optimization.solve_pose2`
restarts from the spanning-tree initialization when the chi2 test fails.

Why Levenberg-Marquardt rather than Powell's dogleg: the damped system is positive definite
for any ``lambda > 0``, so a graph whose normal equations are singular or nearly so (a free
component, a weak loop) still gets a descent step, and its path from a bad start interpolates
between Gauss-Newton and gradient descent in every direction at once instead of along one
dogleg path; it is also the optimizer the project's reference optimum comes from (GTSAM LM).
Dogleg's cheaper rejections (no refactorization) matter little here: on the shipped graphs
almost every step is accepted.

Speed where Gauss-Newton is good: with ``lambda`` 1e-5 the damped step is the Gauss-Newton
step, and the candidate is linearized straight away (into a second buffer) because the chi2 is
a by-product of the linearization: an accepted step costs what a Gauss-Newton iteration costs
(one linearization, one numeric factorization, one solve) plus two array copies. A rejected
step wastes one linearization.

Stopping rule (as GTSAM's): after an accepted step, stop when the relative decrease of the
chi2 falls below ``relative_error_tol`` (or the chi2 below ``error_tol``); stop when a rejected
step changed the chi2 by less than that relative amount (the model is as good as it gets), when
``lambda`` exceeds ``lambda_upper_bound``, or after ``max_iterations`` accepted steps
(``max_linear_solves`` solves).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import msgspec
import numba
import numpy as np
from numpy.typing import NDArray

from gcs.graph.block_cholesky import (
    BlockSymbolic,
    NotPositiveDefiniteError,
    block_slots,
    factorize,
    solve,
    symbolic_factorization,
)
from gcs.graph.pose2_gauss_newton import (
    Pose2Factors,
    _check_poses,
    _linearize,
    _retract,
)

__all__ = [
    "LevenbergMarquardtConfig",
    "LevenbergMarquardtResult",
    "levenberg_marquardt_pose2",
]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.floating[Any]]


class LevenbergMarquardtConfig(
    msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True
):
    """Schedule and stopping rule (see module docstring); defaults are GTSAM's LM defaults.

    ``max_iterations`` counts accepted steps (GTSAM's iterations), ``max_linear_solves`` all
    damped solves, rejected ones included;
    ``diagonal_damping`` damps with ``lambda diag(H)`` (clamped below by
    ``min_diagonal``) instead of ``lambda I``.
    """

    lambda_initial: float = 1e-5
    lambda_factor: float = 10.0
    lambda_lower_bound: float = 0.0
    lambda_upper_bound: float = 1e5
    min_model_fidelity: float = 1e-3
    max_iterations: int = 100
    max_linear_solves: int = 1000
    relative_error_tol: float = 1e-5
    error_tol: float = 0.0
    diagonal_damping: bool = False
    min_diagonal: float = 1e-6
    schedule: Literal["fixed", "nielsen"] = "fixed"

    def __post_init__(self) -> None:
        if not self.lambda_initial > 0.0:
            raise ValueError(f"lambda_initial must be > 0, got {self.lambda_initial}")
        if not self.lambda_factor > 1.0:
            raise ValueError(f"lambda_factor must be > 1, got {self.lambda_factor}")
        if not 0.0 <= self.lambda_lower_bound <= self.lambda_initial <= self.lambda_upper_bound:
            raise ValueError(
                "need 0 <= lambda_lower_bound <= lambda_initial <= lambda_upper_bound, got "
                f"{self.lambda_lower_bound}, {self.lambda_initial}, {self.lambda_upper_bound}"
            )
        if self.max_iterations < 0:
            raise ValueError(f"max_iterations must be >= 0, got {self.max_iterations}")


@dataclass(frozen=True)
class LevenbergMarquardtResult:
    """The estimate ``poses`` (n, 3) and its ``chi2``; ``iterations`` accepted steps,
    ``linear_solves`` all damped solves (rejected ones included); ``chi2_history`` the chi2
    before the first step and after every accepted step (non-increasing by construction);
    ``lambda_history`` the ``lambda`` each accepted step was solved with; ``final_lambda``;
    ``stop_reason`` one of ``"converged"``, ``"error_tol"``, ``"max_iterations"``,
    ``"max_linear_solves"``, ``"lambda_upper_bound"``; ``symbolic`` the factorization's
    pattern."""

    poses: FloatArray
    chi2: float
    iterations: int
    linear_solves: int
    chi2_history: tuple[float, ...]
    lambda_history: tuple[float, ...]
    final_lambda: float
    stop_reason: str
    symbolic: BlockSymbolic


@numba.njit(cache=True)
def _damp(
    src: np.ndarray, dst: np.ndarray, diag_slot: np.ndarray, lam: float, scaled: bool, floor: float
) -> None:
    """Add ``lambda D`` (``D = I`` or ``diag(src)``) to the diagonal blocks of ``dst``, a copy
    of ``src`` (copied by the caller: ``np.copyto`` is a memcpy, 4x a compiled loop)."""
    for k in range(diag_slot.shape[0]):
        s = diag_slot[k]
        for r in range(3):
            if scaled:
                dst[s, r, r] += lam * max(src[s, r, r], floor)
            else:
                dst[s, r, r] += lam


@numba.njit(cache=True)
def _predicted_decrease(
    g: np.ndarray,
    delta: np.ndarray,
    src: np.ndarray,
    diag_slot: np.ndarray,
    lam: float,
    scaled: bool,
    floor: float,
) -> float:
    """Decrease of the linearized chi2 by ``delta`` solving ``(H + lambda D) delta = -g``:
    ``-g' delta + lambda delta' D delta`` (variable ``k``'s diagonal block at ``diag_slot[k]``)."""
    total = 0.0
    for k in range(delta.shape[0]):
        s = diag_slot[k]
        for r in range(3):
            d = delta[k, r]
            w = lam * max(src[s, r, r], floor) if scaled else lam
            total += -g[k, r] * d + w * d * d
    return total


def levenberg_marquardt_pose2(
    factors: Pose2Factors,
    initial: FloatArray,
    *,
    order: IntArray | None = None,
    config: LevenbergMarquardtConfig | None = None,
    symbolic: BlockSymbolic | None = None,
) -> LevenbergMarquardtResult:
    """Maximum-likelihood poses (n, 3) of ``factors`` by Levenberg-Marquardt from ``initial``.

    ``order`` is the elimination order (default natural), or ``symbolic`` a symbolic
    factorization of ``factors`` from an earlier call (a resumed run: pass the previous
    ``final_lambda`` as ``lambda_initial`` and the path is the uninterrupted one's). Never
    returns an estimate worse than
    ``initial``: every accepted step lowers the chi2. A component without a prior (gauge
    freedom) is handled by the damping (its steps have no component in the null space), but it
    can keep ``lambda`` from falling; anchor every component for a fast solve.
    """
    cfg = config or LevenbergMarquardtConfig()
    f = factors
    poses = _check_poses(f, initial)
    n = f.n
    if symbolic is None:
        order = np.arange(n, dtype=np.int64) if order is None else np.asarray(order, np.int64)
        sym = symbolic_factorization(n, f.ij, order)
    elif symbolic.n != n:
        raise ValueError(f"symbolic factorization of {symbolic.n} variables, factors have {n}")
    else:
        sym = symbolic
    diag_slot = sym.colptr[sym.position]
    edge_slot = block_slots(sym, f.ij)
    args = (f.ij, f.z, f.info, f.prior_index, f.prior_pose, f.prior_info)
    slots = (sym.position, diag_slot, edge_slot)
    # Linearization at the current estimate (h, g) and at the candidate (h_new, g_new): an
    # accepted candidate's linearization is the next iteration's, so it is never redone.
    h = np.zeros((sym.nnz_blocks, 3, 3))
    g = np.zeros((n, 3))
    h_new = np.zeros_like(h)
    g_new = np.zeros_like(g)
    damped = np.zeros_like(h)
    candidate = np.empty_like(poses)
    chi2 = float(_linearize(poses, *args, *slots, h, g))
    history = [chi2]
    lambdas: list[float] = []
    lam = cfg.lambda_initial
    nu = 2.0  # Nielsen's growth factor
    solves = 0
    scaled, floor = cfg.diagonal_damping, cfg.min_diagonal
    stop = "max_iterations"

    def increase(lam: float, nu: float) -> tuple[float, float]:
        if cfg.schedule == "nielsen":
            return lam * nu, nu * 2.0
        # GTSAM's fixed factor; lambda can reach 0 only through lambda_lower_bound = 0.
        return (lam if lam > 0.0 else cfg.lambda_initial) * cfg.lambda_factor, nu

    while len(lambdas) < cfg.max_iterations:
        if chi2 <= cfg.error_tol:
            break
        if lam > cfg.lambda_upper_bound:
            stop = "lambda_upper_bound"
            break
        if solves >= cfg.max_linear_solves:
            stop = "max_linear_solves"
            break
        solves += 1
        np.copyto(damped, h)
        _damp(h, damped, diag_slot, lam, scaled, floor)
        try:
            factorize(sym, damped)
        except NotPositiveDefiniteError:
            # Singular at this lambda (a free gauge, lambda ~ 0): damp more and retry.
            lam, nu = increase(lam, nu)
            continue
        delta = solve(sym, damped, -g)
        pred = float(_predicted_decrease(g, delta, h, diag_slot, lam, scaled, floor))
        candidate[:] = poses
        _retract(candidate, delta)
        chi2_new = float(_linearize(candidate, *args, *slots, h_new, g_new))
        decrease = chi2 - chi2_new
        # Finite and lower, and the linear model predicted the decrease well enough.
        if np.isfinite(chi2_new) and decrease > 0.0 and decrease > cfg.min_model_fidelity * pred:
            poses, candidate = candidate, poses
            h, h_new = h_new, h
            g, g_new = g_new, g
            lambdas.append(lam)
            chi2 = chi2_new
            history.append(chi2)
            if cfg.schedule == "nielsen":
                rho = decrease / pred if pred > 0.0 else 1.0
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * min(rho, 1.0) - 1.0) ** 3)
                nu = 2.0
            else:
                lam /= cfg.lambda_factor
            lam = max(cfg.lambda_lower_bound, lam)
            if decrease / history[-2] < cfg.relative_error_tol:
                stop = "converged"
                break
        else:
            if np.isfinite(chi2_new) and abs(decrease) < cfg.relative_error_tol * chi2:
                stop = "converged"
                break
            lam, nu = increase(lam, nu)
    if chi2 <= cfg.error_tol:
        stop = "error_tol"
    return LevenbergMarquardtResult(
        poses=poses,
        chi2=chi2,
        iterations=len(lambdas),
        linear_solves=solves,
        chi2_history=tuple(history),
        lambda_history=tuple(lambdas),
        final_lambda=lam,
        stop_reason=stop,
        symbolic=sym,
    )
