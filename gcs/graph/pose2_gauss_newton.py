"""Gauss-Newton for ``Pose2`` graphs on a compiled block Cholesky (paper 4.2, 4.6).

The same problem as GTSAM's ``BetweenFactorPose2`` / ``PriorFactorPose2`` graph, with the same
error and retraction (this GTSAM build uses the exponential map for ``Pose2``):

- between factor ``(i, j, z, Omega)``: ``e = Log(z^-1 x_i^-1 x_j)``, cost ``e' Omega e``;
- prior ``(i, p, Omega)``: ``e = Log(p^-1 x_i)``;
- update ``x <- x Exp(delta)`` with ``delta`` solving the normal equations ``H delta = -g``.

Jacobians (right perturbations): ``de/d(delta_j) = Jr^-1(e)``,
``de/d(delta_i) = -Jr^-1(e) Ad(h^-1)`` with ``h = x_i^-1 x_j``. Linearization and assembly of
``H`` into the pattern of the factor happen in one compiled pass over the factors, so an
iteration costs one sweep over the edges plus one numeric factorization
(:mod:`gcs.graph.block_cholesky`); the symbolic factorization is computed once per solve.

Stopping rule as GTSAM's ``GaussNewtonOptimizer``: after each step, stop when the relative
decrease of the chi2 falls below ``relative_error_tol`` (or the chi2 below
``error_tol``), or after ``max_iterations`` steps. The chi2 of the new estimate is the
by-product of the next linearization, so the check costs nothing extra. A step that raises the
chi2 also stops the loop (its relative decrease is negative); unlike GTSAM, the estimate before
that step is returned, never the worse one. Plain Gauss-Newton has no remedy for such a step:
from a poor start it can stop orders of magnitude above the optimum (manhattan from its
spanning-tree start, manhattan_M3500b from any start); :mod:`gcs.graph.pose2_levenberg_marquardt`
is the solver that does not.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from gcs.graph.block_cholesky import (
    BlockSymbolic,
    block_slots,
    factorize,
    solve,
    symbolic_factorization,
)

__all__ = [
    "GaussNewtonResult",
    "Pose2Factors",
    "exp_se2",
    "gauss_newton_pose2",
    "linearize_pose2",
    "local_coordinates",
    "log_se2",
    "pose2_chi2",
]

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.floating[Any]]

_SMALL_ANGLE = 1e-4


def _empty_info() -> FloatArray:
    return np.zeros((0, 3, 3))


@dataclass(frozen=True)
class Pose2Factors:
    """A ``Pose2`` factor graph as arrays over variables ``0..n-1``.

    ``ij`` (M, 2) variable indices, ``z`` (M, 3) measured ``i_from_j`` poses, ``info`` (M, 3, 3)
    information matrices (tangent order ``(x, y, theta)``); priors ``prior_index`` (K,),
    ``prior_pose`` (K, 3) and ``prior_info`` (K, 3, 3). Checked on construction.
    """

    n: int
    ij: IntArray
    z: FloatArray
    info: FloatArray
    prior_index: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    prior_pose: FloatArray = field(default_factory=lambda: np.zeros((0, 3)))
    prior_info: FloatArray = field(default_factory=_empty_info)

    def __post_init__(self) -> None:
        def arr(name: str, dtype: type, shape: tuple[int, ...]) -> None:
            a: NDArray[Any] = np.ascontiguousarray(np.asarray(getattr(self, name), dtype=dtype))
            want = tuple(a.shape[0] if s < 0 else s for s in shape)
            if a.ndim != len(shape) or a.shape != want:
                raise ValueError(f"Pose2Factors.{name}: expected shape {shape}, got {a.shape}")
            object.__setattr__(self, name, a)

        arr("ij", np.int64, (-1, 2))
        m = self.ij.shape[0]
        arr("z", np.float64, (m, 3))
        arr("info", np.float64, (m, 3, 3))
        arr("prior_index", np.int64, (-1,))
        k = self.prior_index.shape[0]
        arr("prior_pose", np.float64, (k, 3))
        arr("prior_info", np.float64, (k, 3, 3))
        if self.n < 0:
            raise ValueError(f"Pose2Factors.n must be >= 0, got {self.n}")
        for name, idx in (("ij", self.ij), ("prior_index", self.prior_index)):
            if idx.size and (idx.min() < 0 or idx.max() >= self.n):
                raise ValueError(f"Pose2Factors.{name}: indices must lie in 0..{self.n - 1}")
        loops = np.flatnonzero(self.ij[:, 0] == self.ij[:, 1])
        if loops.size:
            raise ValueError(f"Pose2Factors.ij: factor {int(loops[0])} joins a variable to itself")
        for name in ("z", "info", "prior_pose", "prior_info"):
            if not np.isfinite(getattr(self, name)).all():
                raise ValueError(f"Pose2Factors.{name}: not all finite")


@dataclass(frozen=True)
class GaussNewtonResult:
    """The estimate ``poses`` (n, 3), its ``chi2``, the number of steps taken, the chi2 before
    each step and after the last (``chi2_history``) and the symbolic factorization used. When
    the last step raised the chi2, ``poses`` and ``chi2`` are those before it (the lowest of
    the history) and ``rejected_last_step`` is set."""

    poses: FloatArray
    chi2: float
    iterations: int
    chi2_history: tuple[float, ...]
    symbolic: BlockSymbolic
    rejected_last_step: bool = False


@numba.njit(cache=True, inline="always")
def _wrap(a: float) -> float:
    return np.arctan2(np.sin(a), np.cos(a))


@numba.njit(cache=True, inline="always")
def _ab(w: float) -> tuple[float, float]:
    """``(sin w / w, (1 - cos w) / w)``, by series near zero."""
    if abs(w) < _SMALL_ANGLE:
        w2 = w * w
        return 1.0 - w2 / 6.0, w / 2.0 - w * w2 / 24.0
    return np.sin(w) / w, (1.0 - np.cos(w)) / w


@numba.njit(cache=True)
def _log(x: float, y: float, w: float, out: np.ndarray) -> None:
    a, b = _ab(w)
    den = a * a + b * b
    out[0] = (a * x + b * y) / den
    out[1] = (-b * x + a * y) / den
    out[2] = w


@numba.njit(cache=True)
def _log_jr_inv(
    x: float, y: float, w: float, c: float, s: float, e: np.ndarray, jinv: np.ndarray
) -> None:
    """``e = Log`` of the pose ``(x, y, w)`` (``w`` wrapped, ``c, s`` its cosine and sine)
    and the inverse right Jacobian ``Jr^-1(e)`` of SE(2) into ``jinv``."""
    if abs(w) < _SMALL_ANGLE:
        w2 = w * w
        a, b = 1.0 - w2 / 6.0, w / 2.0 - w * w2 / 24.0
    else:
        a, b = s / w, (1.0 - c) / w
    den = a * a + b * b
    m00, m01, m10, m11 = a / den, -b / den, b / den, a / den
    r1, r2 = m00 * x - m01 * y, -m10 * x + m11 * y
    e[0], e[1], e[2] = r1, r2, w
    if abs(w) < _SMALL_ANGLE:
        w2 = w * w
        u1 = -r2 / 2.0 + r1 * w / 6.0 + r2 * w2 / 24.0
        u2 = r1 / 2.0 + r2 * w / 6.0 - r1 * w2 / 24.0
    else:
        u1 = (w * r1 - r2 + r2 * c - r1 * s) / (w * w)
        u2 = (r1 + w * r2 - r1 * c - r2 * s) / (w * w)
    jinv[0, 0], jinv[0, 1], jinv[0, 2] = m00, m01, -(m00 * u1 + m01 * u2)
    jinv[1, 0], jinv[1, 1], jinv[1, 2] = m10, m11, -(m10 * u1 + m11 * u2)
    jinv[2, 0], jinv[2, 1], jinv[2, 2] = 0.0, 0.0, 1.0


@numba.njit(cache=True)
def _mul(a: np.ndarray, b: np.ndarray, out: np.ndarray) -> None:
    """``out = a b`` for 3 x 3 matrices."""
    for r in range(3):
        a0, a1, a2 = a[r, 0], a[r, 1], a[r, 2]
        for c in range(3):
            out[r, c] = a0 * b[0, c] + a1 * b[1, c] + a2 * b[2, c]


@numba.njit(cache=True)
def _add_at_b(x: np.ndarray, slot: int, a: np.ndarray, b: np.ndarray, transpose: bool) -> None:
    """``x[slot] += a' b`` (or its transpose) for 3 x 3 matrices."""
    for r in range(3):
        for c in range(3):
            v = a[0, r] * b[0, c] + a[1, r] * b[1, c] + a[2, r] * b[2, c]
            if transpose:
                x[slot, c, r] += v
            else:
                x[slot, r, c] += v


@numba.njit(cache=True)
def _add_at_v(g: np.ndarray, k: int, a: np.ndarray, v: np.ndarray) -> None:
    """``g[k] += a' v``."""
    for r in range(3):
        g[k, r] += a[0, r] * v[0] + a[1, r] * v[1] + a[2, r] * v[2]


@numba.njit(cache=True)
def _between_error(
    poses: np.ndarray, i: int, j: int, z: np.ndarray, e: np.ndarray
) -> tuple[float, float, float]:
    """Error of one between factor into ``e``; returns ``h = x_i^-1 x_j``."""
    ci, si = np.cos(poses[i, 2]), np.sin(poses[i, 2])
    dx, dy = poses[j, 0] - poses[i, 0], poses[j, 1] - poses[i, 1]
    hx, hy = ci * dx + si * dy, -si * dx + ci * dy
    hth = poses[j, 2] - poses[i, 2]
    cz, sz = np.cos(z[2]), np.sin(z[2])
    ex, ey = hx - z[0], hy - z[1]
    _log(cz * ex + sz * ey, -sz * ex + cz * ey, _wrap(hth - z[2]), e)
    return hx, hy, hth


@numba.njit(cache=True)
def _prior_error(poses: np.ndarray, i: int, p: np.ndarray, e: np.ndarray) -> None:
    cp, sp = np.cos(p[2]), np.sin(p[2])
    dx, dy = poses[i, 0] - p[0], poses[i, 1] - p[1]
    _log(cp * dx + sp * dy, -sp * dx + cp * dy, _wrap(poses[i, 2] - p[2]), e)


@numba.njit(cache=True)
def _quad(e: np.ndarray, om: np.ndarray) -> float:
    v = 0.0
    for r in range(3):
        for c in range(3):
            v += e[r] * om[r, c] * e[c]
    return v


@numba.njit(cache=True)
def _chi2(
    poses: np.ndarray,
    ij: np.ndarray,
    z: np.ndarray,
    info: np.ndarray,
    prior_index: np.ndarray,
    prior_pose: np.ndarray,
    prior_info: np.ndarray,
) -> float:
    e = np.empty(3)
    total = 0.0
    for m in range(ij.shape[0]):
        _between_error(poses, ij[m, 0], ij[m, 1], z[m], e)
        total += _quad(e, info[m])
    for k in range(prior_index.shape[0]):
        _prior_error(poses, prior_index[k], prior_pose[k], e)
        total += _quad(e, prior_info[k])
    return total


@numba.njit(cache=True)
def _linearize(
    poses: np.ndarray,
    ij: np.ndarray,
    z: np.ndarray,
    info: np.ndarray,
    prior_index: np.ndarray,
    prior_pose: np.ndarray,
    prior_info: np.ndarray,
    position: np.ndarray,
    diag_slot: np.ndarray,
    edge_slot: np.ndarray,
    x: np.ndarray,
    g: np.ndarray,
) -> float:
    """Assemble ``H`` (lower blocks in the factor's pattern) into ``x`` and ``g``; return chi2.

    Cosines and sines of the poses' angles are computed once a pose; those of relative angles
    follow from the angle addition formulas.
    """
    x[:] = 0.0
    g[:] = 0.0
    cp, sp = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    e = np.empty(3)
    oe = np.empty(3)
    jinv = np.empty((3, 3))
    ai = np.empty((3, 3))
    oai = np.empty((3, 3))
    oaj = np.empty((3, 3))
    two_pi = 2.0 * np.pi
    total = 0.0
    for m in range(ij.shape[0]):
        i, j = ij[m, 0], ij[m, 1]
        ci, si, cj, sj = cp[i], sp[i], cp[j], sp[j]
        dx, dy = poses[j, 0] - poses[i, 0], poses[j, 1] - poses[i, 1]
        # h = x_i^-1 x_j, then E = z^-1 h; e = Log(E).
        hx, hy = ci * dx + si * dy, -si * dx + ci * dy
        ch, sh = cj * ci + sj * si, sj * ci - cj * si
        cz, sz = np.cos(z[m, 2]), np.sin(z[m, 2])
        ex, ey = hx - z[m, 0], hy - z[m, 1]
        d = poses[j, 2] - poses[i, 2] - z[m, 2]
        w = d - two_pi * np.round(d / two_pi)
        _log_jr_inv(
            cz * ex + sz * ey, -sz * ex + cz * ey, w, ch * cz + sh * sz, sh * cz - ch * sz, e, jinv
        )
        om = info[m]
        for r in range(3):
            oe[r] = om[r, 0] * e[0] + om[r, 1] * e[1] + om[r, 2] * e[2]
        total += e[0] * oe[0] + e[1] * oe[1] + e[2] * oe[2]
        # Ad(h^-1) = [[R_h', [ty; -tx]], [0, 0, 1]] with h^-1 = (t, -hth), t = -R_h' (hx, hy).
        tx, ty = -(ch * hx + sh * hy), -(-sh * hx + ch * hy)
        for r in range(3):
            j0, j1, j2 = jinv[r, 0], jinv[r, 1], jinv[r, 2]
            ai[r, 0] = -(j0 * ch - j1 * sh)
            ai[r, 1] = -(j0 * sh + j1 * ch)
            ai[r, 2] = -(j0 * ty - j1 * tx + j2)
        _mul(om, ai, oai)
        _mul(om, jinv, oaj)
        _add_at_b(x, diag_slot[i], ai, oai, False)
        _add_at_b(x, diag_slot[j], jinv, oaj, False)
        # Block (max position, min position) of L's pattern holds H[row var, col var].
        _add_at_b(x, edge_slot[m], ai, oaj, position[i] < position[j])
        _add_at_v(g, i, ai, oe)
        _add_at_v(g, j, jinv, oe)
    for k in range(prior_index.shape[0]):
        i = prior_index[k]
        c0, s0 = np.cos(prior_pose[k, 2]), np.sin(prior_pose[k, 2])
        dx, dy = poses[i, 0] - prior_pose[k, 0], poses[i, 1] - prior_pose[k, 1]
        d = poses[i, 2] - prior_pose[k, 2]
        w = d - two_pi * np.round(d / two_pi)
        cw, sw = cp[i] * c0 + sp[i] * s0, sp[i] * c0 - cp[i] * s0
        _log_jr_inv(c0 * dx + s0 * dy, -s0 * dx + c0 * dy, w, cw, sw, e, jinv)
        om = prior_info[k]
        for r in range(3):
            oe[r] = om[r, 0] * e[0] + om[r, 1] * e[1] + om[r, 2] * e[2]
        total += e[0] * oe[0] + e[1] * oe[1] + e[2] * oe[2]
        _mul(om, jinv, oaj)
        _add_at_b(x, diag_slot[i], jinv, oaj, False)
        _add_at_v(g, i, jinv, oe)
    return total


@numba.njit(cache=True)
def _retract(poses: np.ndarray, delta: np.ndarray) -> None:
    """``x <- x Exp(delta)`` for every pose, angles wrapped to ``(-pi, pi]``."""
    for k in range(poses.shape[0]):
        vx, vy, w = delta[k, 0], delta[k, 1], delta[k, 2]
        a, b = _ab(w)
        tx, ty = a * vx - b * vy, b * vx + a * vy
        c, s = np.cos(poses[k, 2]), np.sin(poses[k, 2])
        poses[k, 0] += c * tx - s * ty
        poses[k, 1] += s * tx + c * ty
        poses[k, 2] = _wrap(poses[k, 2] + w)


@numba.njit(cache=True)
def _local(base: np.ndarray, poses: np.ndarray, out: np.ndarray) -> None:
    for k in range(poses.shape[0]):
        c, s = np.cos(base[k, 2]), np.sin(base[k, 2])
        dx, dy = poses[k, 0] - base[k, 0], poses[k, 1] - base[k, 1]
        _log(c * dx + s * dy, -s * dx + c * dy, _wrap(poses[k, 2] - base[k, 2]), out[k])


def local_coordinates(base: FloatArray, poses: FloatArray) -> FloatArray:
    """``Log(base_k^-1 pose_k)`` for poses (N, 3): the tangent vectors ``xi`` with
    ``base_k Exp(xi_k) = pose_k`` (GTSAM ``Pose2.localCoordinates``)."""
    b = np.ascontiguousarray(np.asarray(base, dtype=np.float64).reshape(-1, 3))
    p = np.ascontiguousarray(np.asarray(poses, dtype=np.float64).reshape(-1, 3))
    if b.shape != p.shape:
        raise ValueError(f"base and poses differ in shape: {b.shape} vs {p.shape}")
    out = np.empty_like(p)
    _local(b, p, out)
    return out


def log_se2(poses: FloatArray) -> FloatArray:
    """``Log`` of poses (N, 3) -> tangent vectors (N, 3) (``Pose2.Logmap``)."""
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    return local_coordinates(np.zeros_like(p), p)


def exp_se2(xi: FloatArray) -> FloatArray:
    """``Exp`` of tangent vectors (N, 3) -> poses (N, 3) (``Pose2.Expmap``)."""
    v = np.ascontiguousarray(np.asarray(xi, dtype=np.float64).reshape(-1, 3))
    poses = np.zeros_like(v)
    _retract(poses, v)
    return poses


def _check_poses(factors: Pose2Factors, poses: FloatArray) -> FloatArray:
    out = np.array(poses, dtype=np.float64, order="C")
    if out.shape != (factors.n, 3):
        raise ValueError(f"poses must have shape ({factors.n}, 3), got {out.shape}")
    if not np.isfinite(out).all():
        raise ValueError("poses: not all finite")
    return out


def pose2_chi2(factors: Pose2Factors, poses: FloatArray) -> float:
    """``sum e' Omega e`` over all factors at ``poses`` (n, 3)."""
    p = _check_poses(factors, poses)
    f = factors
    return float(_chi2(p, f.ij, f.z, f.info, f.prior_index, f.prior_pose, f.prior_info))


def linearize_pose2(
    factors: Pose2Factors, poses: FloatArray, sym: BlockSymbolic
) -> tuple[FloatArray, FloatArray, float]:
    """Normal equations of ``factors`` at ``poses`` (n, 3) in the pattern of ``sym``: the lower
    blocks of ``H`` as :func:`gcs.graph.block_cholesky.factorize` takes them, the gradient
    ``g = sum J' Omega e`` (n, 3) and the chi2; the step solves ``H delta = -g``."""
    f = factors
    p = _check_poses(f, poses)
    if sym.n != f.n:
        raise ValueError(f"symbolic factorization of {sym.n} variables, factors have {f.n}")
    lhs = np.zeros((sym.nnz_blocks, 3, 3))
    rhs = np.zeros((f.n, 3))
    args = (f.ij, f.z, f.info, f.prior_index, f.prior_pose, f.prior_info)
    slots = (sym.position, sym.colptr[sym.position], block_slots(sym, f.ij))
    total = float(_linearize(p, *args, *slots, lhs, rhs))
    return lhs, rhs, total


def gauss_newton_pose2(
    factors: Pose2Factors,
    initial: FloatArray,
    *,
    order: IntArray | None = None,
    max_iterations: int = 100,
    relative_error_tol: float = 1e-5,
    error_tol: float = 0.0,
) -> GaussNewtonResult:
    """Maximum-likelihood poses (n, 3) of ``factors`` by Gauss-Newton from ``initial`` (n, 3).

    ``order`` is the elimination order of the variables (a permutation of ``0..n-1``; default
    the natural order); see the module docstring for the model and the stopping rule. Raises
    :class:`gcs.graph.block_cholesky.NotPositiveDefiniteError` when the normal equations are
    singular (e.g. a component without a prior).
    """
    f = factors
    poses = _check_poses(f, initial)
    n = f.n
    order = np.arange(n, dtype=np.int64) if order is None else np.asarray(order, dtype=np.int64)
    sym = symbolic_factorization(n, f.ij, order)
    diag_slot = sym.colptr[sym.position]
    edge_slot = block_slots(sym, f.ij)
    x = np.zeros((sym.nnz_blocks, 3, 3))
    g = np.zeros((n, 3))
    history: list[float] = []
    args = (f.ij, f.z, f.info, f.prior_index, f.prior_pose, f.prior_info)
    steps = 0
    previous = np.empty_like(poses)
    while True:
        chi2 = float(_linearize(poses, *args, sym.position, diag_slot, edge_slot, x, g))
        history.append(chi2)
        if steps > 0:
            before = history[-2]
            if chi2 <= error_tol or (before > 0 and (before - chi2) / before < relative_error_tol):
                break
        if steps >= max_iterations:
            break
        factorize(sym, x)
        delta = solve(sym, x, -g)
        previous[:] = poses
        _retract(poses, delta)
        steps += 1
    rejected = steps > 0 and not history[-1] <= history[-2]
    return GaussNewtonResult(
        poses=previous if rejected else poses,
        chi2=history[-2] if rejected else history[-1],
        iterations=steps,
        chi2_history=tuple(history),
        symbolic=sym,
        rejected_last_step=rejected,
    )
