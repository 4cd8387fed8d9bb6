"""Multi-resolution correlative matching of two binary grids (paper 4.3.3; Olson 2009).

Given a *reference* grid (vertical surfaces around pose node A, in A's ``base`` frame) and a
*query* grid (around node B), find the rigid transform ``a_from_b`` that best aligns B's
occupied cells with A's, by exhaustive search over a window around a prior guess:

1. **Lookup table.** Each reference cell holds the log-likelihood of a point landing there:
   a Gaussian sensor-noise kernel (``sigma_m``) around the nearest occupied cell, mixed with an
   outlier floor, quantized to 0..255 (via a Euclidean distance transform).
2. **Query points**: centres of B's occupied cells, thinned to at most ``max_points``.
3. **Score** of a candidate transform: the sum of table values under the transformed points.
   The window is discretized in translation (one reference cell) and rotation (the angle that
   moves the farthest point by one cell).
4. **Pyramid**: level ``k`` is a sliding 2^k x 2^k maximum of level 0, so one lookup per point
   upper-bounds the score of every translation in a 2^k x 2^k block. The paper used 8 levels;
   here as many as the window needs (``levels``, or automatic).
5. **Branch and bound**: for every rotation, blocks of the coarsest level are bounded, sorted,
   and refined best-first; a block whose bound cannot beat the best complete score is pruned.
   The result is *exactly* the brute-force optimum over the discretized window, ties broken
   by the lowest (rotation, row, column) index (:func:`brute_force_match` checks it).
6. **Refinement and covariance** from the response surface: scores around the optimum, read
   as log-likelihoods, weight the neighbouring transforms; their mean is the sub-cell estimate
   ``a_from_b`` and their spread the covariance (with a floor of the discretization). The
   discrete optimum stays available as ``a_from_b_discrete``. ``normalized_score`` is the
   score over its maximum possible.

Complexity: brute force is O(rotations x translations x points); branch and bound typically
evaluates a few thousand blocks. Tables are built once per reference grid
(:class:`ReferenceTable`) and reused for every match against it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import msgspec
import numba
import numpy as np

__all__ = [
    "CorrelativeMatcher",
    "MatchResult",
    "MatcherConfig",
    "ReferenceTable",
    "brute_force_match",
    "grid_points",
]


class MatcherConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Search window and models. Distances in metres, angles in radians."""

    search_xy_m: float = 3.0
    search_yaw_rad: float = math.radians(30.0)
    yaw_step_rad: float = 0.0  # 0: resolution / farthest query point
    sigma_m: float = 0.1  # sensor noise of the lookup kernel
    outlier_likelihood: float = 0.05  # floor of a point's likelihood, relative to a hit
    max_points: int = 400
    levels: int = 0  # pyramid levels; 0: enough that the top block covers the window
    point_correlation: float = 16.0  # neighbouring wall points are not independent evidence

    def __post_init__(self) -> None:
        if not (self.search_xy_m >= 0 and self.search_yaw_rad >= 0):
            raise ValueError("search window must be >= 0")
        if not (self.sigma_m > 0 and 0 < self.outlier_likelihood < 1):
            raise ValueError("need sigma_m > 0 and 0 < outlier_likelihood < 1")
        if self.max_points < 1 or self.levels < 0 or self.levels > 12:
            raise ValueError("need max_points >= 1 and 0 <= levels <= 12")


@dataclass(frozen=True)
class MatchResult:
    """``a_from_b`` ``(x_m, y_m, yaw_rad)`` refined from the response surface, the discrete
    optimum of the search, the 3x3 covariance, the raw and normalized score (in [0, 1]), and
    how many branch-and-bound nodes were scored."""

    a_from_b: np.ndarray
    a_from_b_discrete: np.ndarray
    covariance: np.ndarray
    score: int
    normalized_score: float
    nodes_evaluated: int


@dataclass(frozen=True)
class ReferenceTable:
    """The lookup pyramid of one reference grid (build once, match many times)."""

    pyramid: np.ndarray  # uint8 (levels, H + 2P, W + 2P)
    pad: int
    origin_m: tuple[float, float]  # centre of cell (0, 0) is origin + resolution / 2
    resolution_m: float
    loglik_per_unit: float  # log-likelihood per table unit


def grid_points(
    grid: np.ndarray, *, origin_m: tuple[float, float], resolution_m: float
) -> np.ndarray:
    """Centres ``(N, 2)`` of the occupied cells; cell (row, col) = origin + (col, row) * res."""
    rows, cols = np.nonzero(np.asarray(grid, dtype=bool))
    return np.stack(
        [origin_m[0] + (cols + 0.5) * resolution_m, origin_m[1] + (rows + 0.5) * resolution_m],
        axis=1,
    )


def _thin(points: np.ndarray, max_points: int, resolution_m: float) -> np.ndarray:
    """At most ``max_points`` points, one per cell of the coarsest grid that gets there."""
    if len(points) <= max_points:
        return points
    cell = resolution_m
    while True:
        cell *= 2.0
        keys = np.floor(points / cell).astype(np.int64)
        _, first = np.unique(keys[:, 0] * 1_000_003 + keys[:, 1], return_index=True)
        if len(first) <= max_points:
            return points[np.sort(first)]


@numba.njit(cache=True)
def _max_pool(src: np.ndarray, step: int, dst: np.ndarray) -> None:
    h, w = src.shape
    for r in range(h):
        for c in range(w):
            m = src[r, c]
            if r + step < h:
                m = max(m, src[r + step, c])
                if c + step < w:
                    m = max(m, src[r + step, c + step])
            if c + step < w:
                m = max(m, src[r, c + step])
            dst[r, c] = m


@numba.njit(cache=True)
def _rotated_cells(points, yaws, x0, y0, ox, oy, res, pad, rows, cols):  # type: ignore[no-untyped-def]
    for j in range(yaws.shape[0]):
        c, s = math.cos(yaws[j]), math.sin(yaws[j])
        for i in range(points.shape[0]):
            px = c * points[i, 0] - s * points[i, 1] + x0
            py = s * points[i, 0] + c * points[i, 1] + y0
            cols[j, i] = int(math.floor((px - ox) / res)) + pad
            rows[j, i] = int(math.floor((py - oy) / res)) + pad


@numba.njit(cache=True, inline="always")
def _score(table, rows, cols, j, ty, tx):  # type: ignore[no-untyped-def]
    h, w = table.shape
    s = 0
    for i in range(rows.shape[1]):
        r = rows[j, i] + ty
        c = cols[j, i] + tx
        if 0 <= r < h and 0 <= c < w:
            s += table[r, c]
    return s


@numba.njit(cache=True, inline="always")
def _before(j, ty, tx, bj, bty, btx):  # type: ignore[no-untyped-def]
    if j != bj:
        return j < bj
    if ty != bty:
        return ty < bty
    return tx < btx


@numba.njit(cache=True)
def _branch_and_bound(pyramid, rows, cols, n_xy, min_score):  # type: ignore[no-untyped-def]
    levels = pyramid.shape[0]
    n_yaw = rows.shape[0]
    top = levels - 1
    block = 1 << top
    span = 2 * n_xy + 1
    nb = (span + block - 1) // block
    # bound every top-level block of every rotation
    count = n_yaw * nb * nb
    bounds = np.empty(count, dtype=np.int64)
    keys = np.empty((count, 3), dtype=np.int64)
    k = 0
    for j in range(n_yaw):
        for by in range(nb):
            for bx in range(nb):
                ty = -n_xy + by * block
                tx = -n_xy + bx * block
                bounds[k] = _score(pyramid[top], rows, cols, j, ty, tx)
                keys[k, 0] = j
                keys[k, 1] = ty
                keys[k, 2] = tx
                k += 1
    order = np.argsort(-bounds, kind="mergesort")
    best = min_score - 1  # anything below the acceptance threshold is pruned
    bj = bty = btx = 1 << 30
    evaluated = count
    stack = np.empty((4 * levels * 4 + 8, 5), dtype=np.int64)
    for o in order:
        b = bounds[o]
        if b < best or (
            b == best and not _before(keys[o, 0], keys[o, 1], keys[o, 2], bj, bty, btx)
        ):
            continue
        sp = 0
        stack[0, 0] = top
        stack[0, 1] = keys[o, 0]
        stack[0, 2] = keys[o, 1]
        stack[0, 3] = keys[o, 2]
        stack[0, 4] = b
        sp = 1
        while sp > 0:
            sp -= 1
            lvl = stack[sp, 0]
            j = stack[sp, 1]
            ty = stack[sp, 2]
            tx = stack[sp, 3]
            bound = stack[sp, 4]
            if bound < best or (bound == best and not _before(j, ty, tx, bj, bty, btx)):
                continue
            if lvl == 0:
                if ty <= n_xy and tx <= n_xy:  # level 0 bounds are exact scores
                    best = bound
                    bj, bty, btx = j, ty, tx
                continue
            half = 1 << (lvl - 1)
            child = np.empty((4, 4), dtype=np.int64)
            nc = 0
            for dy in range(2):
                for dx in range(2):
                    cty = ty + dy * half
                    ctx = tx + dx * half
                    if cty > n_xy or ctx > n_xy:
                        continue
                    child[nc, 0] = cty
                    child[nc, 1] = ctx
                    child[nc, 2] = _score(pyramid[lvl - 1], rows, cols, j, cty, ctx)
                    nc += 1
                    evaluated += 1
            # push ascending so the most promising child is refined first
            for a in range(nc):
                for b2 in range(a + 1, nc):
                    if child[b2, 2] < child[a, 2]:
                        for f in range(3):
                            tmp = child[a, f]
                            child[a, f] = child[b2, f]
                            child[b2, f] = tmp
            for a in range(nc):
                stack[sp, 0] = lvl - 1
                stack[sp, 1] = j
                stack[sp, 2] = child[a, 0]
                stack[sp, 3] = child[a, 1]
                stack[sp, 4] = child[a, 2]
                sp += 1
    return best, bj, bty, btx, evaluated


@numba.njit(cache=True)
def _brute_force(table, rows, cols, n_xy, min_score):  # type: ignore[no-untyped-def]
    best = min_score - 1
    bj = bty = btx = 1 << 30
    for j in range(rows.shape[0]):
        for ty in range(-n_xy, n_xy + 1):
            for tx in range(-n_xy, n_xy + 1):
                s = _score(table, rows, cols, j, ty, tx)
                if s > best:
                    best, bj, bty, btx = s, j, ty, tx
    return best, bj, bty, btx


@numba.njit(cache=True)
def _neighbourhood(table, rows, cols, n_xy, j0, ty0, tx0, radius, out):  # type: ignore[no-untyped-def]
    k = 0
    for j in range(max(0, j0 - radius), min(rows.shape[0], j0 + radius + 1)):
        for ty in range(max(-n_xy, ty0 - radius), min(n_xy, ty0 + radius) + 1):
            for tx in range(max(-n_xy, tx0 - radius), min(n_xy, tx0 + radius) + 1):
                out[k, 0] = j
                out[k, 1] = ty
                out[k, 2] = tx
                out[k, 3] = _score(table, rows, cols, j, ty, tx)
                k += 1
    return k


class CorrelativeMatcher:
    """Aligns binary grids (see the module docstring)."""

    def __init__(self, config: MatcherConfig | None = None) -> None:
        self.config = config or MatcherConfig()

    def _levels(self, resolution_m: float) -> int:
        if self.config.levels:
            return self.config.levels
        # top blocks of the largest power of two below the window span: a few blocks per
        # rotation bound far tighter than one block covering everything (measured: 10x)
        span = 2 * int(math.ceil(self.config.search_xy_m / resolution_m)) + 1
        return max(1, int(math.ceil(math.log2(max(span, 2)))))

    def reference_table(
        self, grid: np.ndarray, *, origin_m: tuple[float, float], resolution_m: float
    ) -> ReferenceTable:
        """Build the lookup pyramid of a reference grid."""
        g = np.asarray(grid, dtype=bool)
        if g.ndim != 2 or g.size == 0:
            raise ValueError(f"reference grid must be a non-empty 2-D array, got shape {g.shape}")
        if not (resolution_m > 0 and math.isfinite(resolution_m)):
            raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
        cfg = self.config
        eps = cfg.outlier_likelihood
        if g.any():
            dist_cells = cv2.distanceTransform(
                (~g).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE
            )
        else:
            dist_cells = np.full(g.shape, np.inf, dtype=np.float32)
        d_m = dist_cells.astype(np.float64) * resolution_m
        loglik = np.log(np.exp(-0.5 * (d_m / cfg.sigma_m) ** 2) + eps)
        lo, hi = math.log(eps), math.log(1.0 + eps)
        level0 = np.round(255.0 * (loglik - lo) / (hi - lo)).astype(np.uint8)
        levels = self._levels(resolution_m)
        pad = (1 << (levels - 1)) - 1
        h, w = g.shape
        pyramid = np.zeros((levels, h + 2 * pad, w + 2 * pad), dtype=np.uint8)
        pyramid[0, pad : pad + h, pad : pad + w] = level0
        for k in range(1, levels):
            _max_pool(pyramid[k - 1], 1 << (k - 1), pyramid[k])
        return ReferenceTable(pyramid, pad, origin_m, resolution_m, (hi - lo) / 255.0)

    def _prepare(
        self, ref: ReferenceTable, query_points_m: np.ndarray, guess: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        cfg = self.config
        pts = np.asarray(query_points_m, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(pts)):
            raise ValueError("query points must be finite")
        g = np.asarray(guess, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ValueError(f"guess must be a finite pose (3,), got {guess!r}")
        pts = _thin(pts, cfg.max_points, ref.resolution_m)
        r_max = float(np.max(np.hypot(pts[:, 0], pts[:, 1]))) if len(pts) else 1.0
        step = cfg.yaw_step_rad or ref.resolution_m / max(r_max, ref.resolution_m)
        n_yaw = int(math.floor(cfg.search_yaw_rad / step + 1e-9))
        yaws = g[2] + step * np.arange(-n_yaw, n_yaw + 1)
        n_xy = int(math.ceil(cfg.search_xy_m / ref.resolution_m - 1e-9))
        rows = np.empty((len(yaws), len(pts)), dtype=np.int64)
        cols = np.empty_like(rows)
        ox, oy = ref.origin_m
        _rotated_cells(pts, yaws, g[0], g[1], ox, oy, ref.resolution_m, ref.pad, rows, cols)
        return yaws, rows, cols, n_xy

    def match(
        self,
        ref: ReferenceTable,
        query_points_m: np.ndarray,
        guess_a_from_b: np.ndarray,
        *,
        min_score: float = 0.0,
    ) -> MatchResult | None:
        """Best ``a_from_b`` in the window around ``guess_a_from_b`` (branch and bound).

        ``query_points_m``: points ``(N, 2)`` in B's frame (e.g. :func:`grid_points`).
        ``min_score``: normalized score a match must reach; below it the search prunes and
        returns None (as the brute-force oracle does with the same threshold).
        """
        yaws, rows, cols, n_xy = self._prepare(ref, query_points_m, guess_a_from_b)
        if rows.shape[1] == 0:
            raise ValueError("the query has no points to match")
        threshold = _threshold(min_score, rows.shape[1])
        best, j, ty, tx, evaluated = _branch_and_bound(ref.pyramid, rows, cols, n_xy, threshold)
        if best < threshold:
            return None
        return self._result(ref, yaws, rows, cols, n_xy, guess_a_from_b, best, j, ty, tx, evaluated)

    def _result(
        self, ref, yaws, rows, cols, n_xy, guess, best, j, ty, tx, evaluated
    ) -> MatchResult:  # type: ignore[no-untyped-def]
        res = ref.resolution_m
        g = np.asarray(guess, dtype=np.float64)
        discrete = np.array([g[0] + tx * res, g[1] + ty * res, yaws[j]])
        mean, cov = self._response_surface(ref, yaws, rows, cols, n_xy, j, ty, tx, best)
        refined = np.array([g[0] + mean[0], g[1] + mean[1], mean[2]])
        norm = best / (255.0 * rows.shape[1])
        return MatchResult(refined, discrete, cov, int(best), float(norm), int(evaluated))

    def _response_surface(self, ref, yaws, rows, cols, n_xy, j, ty, tx, best):  # type: ignore[no-untyped-def]
        radius = 3
        out = np.empty(((2 * radius + 1) ** 3, 4), dtype=np.int64)
        n = _neighbourhood(ref.pyramid[0], rows, cols, n_xy, j, ty, tx, radius, out)
        nb = out[:n]
        scale = ref.loglik_per_unit / self.config.point_correlation
        w = np.exp((nb[:, 3] - best) * scale)
        w /= w.sum()
        res = ref.resolution_m
        xyz = np.stack([nb[:, 2] * res, nb[:, 1] * res, yaws[nb[:, 0]]], axis=1)
        mu = w @ xyz
        d = xyz - mu
        cov = (d * w[:, None]).T @ d
        step = float(yaws[1] - yaws[0]) if len(yaws) > 1 else 0.01
        return mu, cov + np.diag([res**2 / 12.0, res**2 / 12.0, step**2 / 12.0])


def _threshold(min_score: float, n_points: int) -> int:
    if not 0.0 <= min_score <= 1.0:
        raise ValueError(f"min_score must be in [0, 1], got {min_score}")
    return int(math.ceil(min_score * 255.0 * n_points - 1e-9))


def brute_force_match(
    matcher: CorrelativeMatcher,
    ref: ReferenceTable,
    query_points_m: np.ndarray,
    guess_a_from_b: np.ndarray,
    *,
    min_score: float = 0.0,
) -> MatchResult | None:
    """The same search by exhaustive evaluation of every discretized transform (the oracle)."""
    yaws, rows, cols, n_xy = matcher._prepare(ref, query_points_m, guess_a_from_b)
    if rows.shape[1] == 0:
        raise ValueError("the query has no points to match")
    table = np.ascontiguousarray(ref.pyramid[0])
    threshold = _threshold(min_score, rows.shape[1])
    best, j, ty, tx = _brute_force(table, rows, cols, n_xy, threshold)
    if best < threshold:
        return None
    evaluated = rows.shape[0] * (2 * n_xy + 1) ** 2
    return matcher._result(ref, yaws, rows, cols, n_xy, guess_a_from_b, best, j, ty, tx, evaluated)
