"""Multi-resolution correlative matching of two binary grids (paper 4.3.3; Olson 2009).

Given a *reference* grid (vertical surfaces around pose node A, in A's ``base`` frame) and a
*query* grid (around node B), find the rigid transform ``a_from_b`` that best aligns B's
occupied cells with A's, by exhaustive search over a window around a prior guess:

1. **Lookup table.** Each reference cell holds the log-likelihood of a point landing there:
   a Gaussian sensor-noise kernel (``sigma_m``) around the nearest occupied cell, mixed with an
   outlier floor, quantized to 0..255. The value decreases with the distance to the nearest
   occupied cell, so it is built as the maximum of a stamp of the kernel around every
   occupied cell (identical to a Euclidean distance transform, and faster on sparse grids).
2. **Query points** ("sampled from the set pixels" of B): centres of B's occupied cells,
   thinned to at most ``max_points`` (one per cell of the finest coarser grid that gets there).
3. **Score** of a candidate transform: the sum of table values under the transformed points.
   The window is discretized in translation (one reference cell) and rotation (the angle that
   moves the farthest point by ``yaw_step_cells`` cells; 1 is Olson's choice, the default 1.5
   costs two thirds of the rotations and the refinement below recovers the sub-step angle:
   measured p95 error unchanged on the benchmark pairs).
4. **Pyramid**: level ``k`` is a sliding 2^k x 2^k maximum of level 0, so one lookup per point
   upper-bounds the score of every translation in a 2^k x 2^k block. The paper used 8 levels;
   here as many as the window needs (``levels``, or automatic: top blocks of the largest
   power of two below the window's span, a few per rotation; 6 for +-3 m at 10 cm).
5. **Branch and bound**: for every rotation, blocks of the coarsest level are bounded, sorted,
   and refined depth-first, best child first; a block whose bound cannot beat the best
   complete score is pruned. The search starts from the exact score of the guess itself.
   A child block's per-point values never exceed its parent's, so a child is abandoned in the
   middle of its sum once ``sum so far + parent's remaining sum < best`` (prefix sums are kept
   per chunk of 32 points). The result is *exactly* the brute-force optimum over the
   discretized window, ties broken by the lowest (rotation, row, column) index
   (:func:`brute_force_match`, an independent bounds-checked loop, checks it).
6. **Refinement and covariance** from the response surface: scores around the optimum, read
   as log-likelihoods, weight the neighbouring transforms; their mean is the sub-cell estimate
   ``a_from_b`` and their spread the covariance (with a floor of the discretization). The
   discrete optimum stays available as ``a_from_b_discrete``. ``normalized_score`` is the
   score over its maximum possible (255 per query point).

Speed (numba kernels, ``cache=True``): the table is padded with zeros wide enough
(``2 * window + top block``) that every lookup of a point that can ever touch the grid stays
inside it, so a rotated point set is one flat ``int32`` index per point and scoring a
translation is a sum of lookups at one constant offset, without bounds or wrap-around checks;
points that can never touch the grid are dropped per rotation (they always score 0 and still
count in the normalization). Rotated index sets are computed once per rotation and shared by
all levels; the four children of a block are scored in one pass over the points.

Complexity: brute force is O(rotations x translations x points); branch and bound typically
evaluates a few hundred to a few thousand blocks. Tables are built once per reference grid
(:class:`ReferenceTable`, ~0.7 MB for a 150 x 150 grid and a +-3 m window) and reused for
every match against it.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

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
    "points_grid",
]


class MatcherConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Search window and models. Distances in metres, angles in radians.

    ``yaw_step_rad`` 0 picks the angle that moves the farthest query point by
    ``yaw_step_cells`` cells (see the module docstring). ``response_radius`` is the
    half-width, in discretization steps, of the neighbourhood of the optimum used for
    refinement and covariance; ``response_outer_radius`` > 0 (cells) also samples the
    translations every ``response_outer_stride`` cells that far at the best rotation, and
    when their spread is the larger it becomes the translation covariance (an ambiguous,
    corridor-like match then says so instead of reporting the inner neighbourhood's size).

    ``runner_up_radius_m`` > 0: after the best transform, the search runs again over the same
    window leaving out every translation within that distance of the best one (any rotation),
    pruned at ``runner_up_ratio`` times the best score: the best *other* explanation of the
    query, a look-alike place (:attr:`MatchResult.runner_up_score`). A view that fits two
    places nearly as well says nothing about which one it saw (Olson 2009 rejects matches
    whose best and second-best peaks are too close).
    """

    search_xy_m: float = 3.0
    search_yaw_rad: float = math.radians(30.0)
    yaw_step_rad: float = 0.0
    yaw_step_cells: float = 1.5
    sigma_m: float = 0.1  # sensor noise of the lookup kernel
    outlier_likelihood: float = 0.05  # floor of a point's likelihood, relative to a hit
    max_points: int = 400
    levels: int = 0  # pyramid levels; 0: automatic (see the module docstring)
    point_correlation: float = 16.0  # neighbouring wall points are not independent evidence
    response_radius: int = 2
    response_outer_radius: int = 0
    response_outer_stride: int = 2
    runner_up_radius_m: float = 0.0
    runner_up_ratio: float = 0.9

    def __post_init__(self) -> None:
        if not (math.isfinite(self.search_xy_m) and 0 <= self.search_xy_m <= 100):
            raise ValueError(f"search_xy_m must be in [0, 100], got {self.search_xy_m}")
        if not (math.isfinite(self.search_yaw_rad) and 0 <= self.search_yaw_rad <= math.pi):
            raise ValueError(f"search_yaw_rad must be in [0, pi], got {self.search_yaw_rad}")
        if not (math.isfinite(self.yaw_step_rad) and self.yaw_step_rad >= 0):
            raise ValueError(f"yaw_step_rad must be >= 0, got {self.yaw_step_rad}")
        if not (math.isfinite(self.yaw_step_cells) and self.yaw_step_cells > 0):
            raise ValueError(f"yaw_step_cells must be > 0, got {self.yaw_step_cells}")
        if not (self.sigma_m > 0 and 0 < self.outlier_likelihood < 1):
            raise ValueError("need sigma_m > 0 and 0 < outlier_likelihood < 1")
        if self.max_points < 1 or self.levels < 0 or self.levels > 12:
            raise ValueError("need max_points >= 1 and 0 <= levels <= 12")
        if not self.point_correlation > 0:
            raise ValueError(f"point_correlation must be > 0, got {self.point_correlation}")
        if not 1 <= self.response_radius <= 5:
            raise ValueError(f"response_radius must be in [1, 5], got {self.response_radius}")
        if not (math.isfinite(self.runner_up_radius_m) and self.runner_up_radius_m >= 0):
            raise ValueError(f"runner_up_radius_m must be >= 0, got {self.runner_up_radius_m}")
        if not 0 < self.runner_up_ratio <= 1:
            raise ValueError(f"runner_up_ratio must be in (0, 1], got {self.runner_up_ratio}")
        if not (0 <= self.response_outer_radius <= 50 and 1 <= self.response_outer_stride <= 10):
            raise ValueError(
                "need 0 <= response_outer_radius <= 50 and 1 <= response_outer_stride <= 10, "
                f"got {self.response_outer_radius}, {self.response_outer_stride}"
            )


@dataclass(frozen=True)
class MatchResult:
    """``a_from_b`` ``(x_m, y_m, yaw_rad)`` refined from the response surface, the discrete
    optimum of the search, the 3x3 covariance, the raw and normalized score (in [0, 1]), and
    how many branch-and-bound nodes were scored. ``runner_up_score``: with
    ``MatcherConfig.runner_up_radius_m``, the normalized score of the best transform at least
    that far from the best one when it reaches ``runner_up_ratio`` of the best, else 0;
    ``runner_up_a_from_b``: that transform (discrete), None when there is none."""

    a_from_b: np.ndarray
    a_from_b_discrete: np.ndarray
    covariance: np.ndarray
    score: int
    normalized_score: float
    nodes_evaluated: int
    runner_up_score: float = 0.0
    runner_up_a_from_b: np.ndarray | None = None


@dataclass(frozen=True)
class ReferenceTable:
    """The lookup pyramid of one reference grid (build once, match many times).

    ``pyramid`` is ``(levels, H * W)``: level ``k`` flattened row-major, ``H = h + 2 pad``,
    ``W = w + 2 pad``; the grid's cell ``(r, c)`` is at ``(r + pad) * W + c + pad``.
    ``n_xy`` is the translation half-window (cells) the padding was sized for.
    """

    pyramid: np.ndarray
    pad: int
    shape: tuple[int, int]  # (H, W) of each padded level
    grid_shape: tuple[int, int]  # (h, w) of the reference grid
    n_xy: int
    origin_m: tuple[float, float]  # centre of cell (0, 0) is origin + resolution / 2
    resolution_m: float
    loglik_per_unit: float  # log-likelihood per table unit

    @property
    def levels(self) -> int:
        return int(self.pyramid.shape[0])

    def level(self, k: int) -> np.ndarray:
        """Level ``k`` as a ``(H, W)`` view."""
        return self.pyramid[k].reshape(self.shape)


def grid_points(
    grid: np.ndarray, *, origin_m: tuple[float, float], resolution_m: float
) -> np.ndarray:
    """Centres ``(N, 2)`` of the occupied cells; cell (row, col) = origin + (col, row) * res."""
    rows, cols = np.nonzero(np.asarray(grid, dtype=bool))
    return np.stack(
        [origin_m[0] + (cols + 0.5) * resolution_m, origin_m[1] + (rows + 0.5) * resolution_m],
        axis=1,
    )


def points_grid(
    points_m: np.ndarray, *, resolution_m: float, margin_cells: int = 1
) -> tuple[np.ndarray, tuple[float, float]]:
    """Rasterize points ``(N, 2)`` into the smallest binary grid holding them (plus a margin).

    Returns ``(grid, origin_m)`` with cell ``(row, col)`` covering
    ``origin + (col, row) * resolution_m``; the inverse of :func:`grid_points` up to the
    bounding box (the origin is a multiple of ``resolution_m``, so cell centres round-trip).
    """
    pts = np.asarray(points_m, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        raise ValueError("points_grid: no points")
    if not np.all(np.isfinite(pts)):
        raise ValueError("points_grid: points must be finite")
    if not (resolution_m > 0 and math.isfinite(resolution_m)):
        raise ValueError(f"points_grid: resolution_m must be > 0, got {resolution_m}")
    cells = np.floor(pts / resolution_m).astype(np.int64)
    lo = cells.min(axis=0) - margin_cells
    hi = cells.max(axis=0) + margin_cells
    size = hi - lo + 1
    if size[0] * size[1] > 50_000_000:
        raise ValueError(f"points_grid: points span {size.tolist()} cells, too large a grid")
    grid = np.zeros((int(size[1]), int(size[0])), dtype=bool)
    grid[cells[:, 1] - lo[1], cells[:, 0] - lo[0]] = True
    return grid, (float(lo[0] * resolution_m), float(lo[1] * resolution_m))


def _thin(points: np.ndarray, max_points: int, resolution_m: float) -> np.ndarray:
    """At most ``max_points`` points: the first point of each cell of the finest grid
    (``resolution_m * 2^k``, ``k >= 1``) that gets there, in input order."""
    if len(points) <= max_points:
        return points
    keep = _thin_mask(points, max_points, resolution_m)
    return points[keep]


@numba.njit(cache=True)
def _thin_mask(points, max_points, resolution_m):  # type: ignore[no-untyped-def]
    n = points.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    x0 = points[:, 0].min()
    y0 = points[:, 1].min()
    span = max(points[:, 0].max() - x0, points[:, 1].max() - y0)
    cell = resolution_m
    while True:
        cell *= 2.0
        side = int(span / cell) + 1
        seen = np.zeros((side, side), dtype=np.bool_)
        k = 0
        for i in range(n):
            cx = min(int((points[i, 0] - x0) / cell), side - 1)
            cy = min(int((points[i, 1] - y0) / cell), side - 1)
            if seen[cy, cx]:
                keep[i] = False
            else:
                seen[cy, cx] = True
                keep[i] = True
                k += 1
        if k <= max_points:
            return keep


@numba.njit(cache=True)
def _stamp_max(rows, cols, stamp, out):  # type: ignore[no-untyped-def]
    """``out = max(out, stamp centred on each (rows[i], cols[i]))``, clipped to ``out``."""
    h, w = out.shape
    r = stamp.shape[0] // 2
    for i in range(rows.shape[0]):
        r0, c0 = rows[i] - r, cols[i] - r
        for dr in range(max(0, -r0), min(2 * r + 1, h - r0)):
            for dc in range(max(0, -c0), min(2 * r + 1, w - c0)):
                v = stamp[dr, dc]
                if v > out[r0 + dr, c0 + dc]:
                    out[r0 + dr, c0 + dc] = v


@numba.njit(cache=True, fastmath=True)
def _rotated_indices(points, yaws, x0, y0, ox, oy, res, pad, h, w, n_xy, block, width, idx, count):  # type: ignore[no-untyped-def]
    """Flat padded-table index of every point under every rotation (translation = guess).

    Keeps, per rotation, only the points whose lookups can ever reach a non-zero cell of some
    level (rows/cols in ``[pad - block + 1 - n_xy, pad + h - 1 + n_xy]``); they come first in
    ``idx[j]`` and ``count[j]`` says how many.
    """
    inv = 1.0 / res
    lo_r = pad - block + 1 - n_xy
    hi_r = pad + h - 1 + n_xy
    lo_c = pad - block + 1 - n_xy
    hi_c = pad + w - 1 + n_xy
    for j in range(yaws.shape[0]):
        c, s = math.cos(yaws[j]), math.sin(yaws[j])
        k = 0
        for i in range(points.shape[0]):
            px = c * points[i, 0] - s * points[i, 1] + x0
            py = s * points[i, 0] + c * points[i, 1] + y0
            fc = math.floor((px - ox) * inv)
            fr = math.floor((py - oy) * inv)
            if fr < lo_r - pad or fr > hi_r - pad or fc < lo_c - pad or fc > hi_c - pad:
                continue
            idx[j, k] = np.int32((int(fr) + pad) * width + int(fc) + pad)
            k += 1
        count[j] = k


@numba.njit(cache=True)
def _rotated_cells(points, yaws, x0, y0, ox, oy, res, rows, cols):  # type: ignore[no-untyped-def]
    """Unpadded ``(row, col)`` of every point under every rotation (the oracle's own path)."""
    for j in range(yaws.shape[0]):
        c, s = math.cos(yaws[j]), math.sin(yaws[j])
        for i in range(points.shape[0]):
            px = c * points[i, 0] - s * points[i, 1] + x0
            py = s * points[i, 0] + c * points[i, 1] + y0
            cols[j, i] = int(math.floor((px - ox) / res))
            rows[j, i] = int(math.floor((py - oy) / res))


@numba.njit(cache=True, inline="always", boundscheck=False)
def _score(level, idx, j, n, offset):  # type: ignore[no-untyped-def]
    s = 0
    for i in range(n):
        s += level[np.uint64(idx[j, i] + offset)]
    return s


@numba.njit(cache=True, inline="always")
def _before(j, ty, tx, bj, bty, btx):  # type: ignore[no-untyped-def]
    if j != bj:
        return j < bj
    if ty != bty:
        return ty < bty
    return tx < btx


@numba.njit(cache=True, inline="always")
def _excluded(ty, tx, size, ex_ty, ex_tx, ex_r2):  # type: ignore[no-untyped-def]
    """Whether every translation of the block ``[ty, ty + size) x [tx, tx + size)`` lies
    within ``sqrt(ex_r2)`` cells of ``(ex_ty, ex_tx)`` (never, for ``ex_r2 < 0``): its
    farthest corner does."""
    if ex_r2 < 0:
        return False
    dy = max(abs(ty - ex_ty), abs(ty + size - 1 - ex_ty))
    dx = max(abs(tx - ex_tx), abs(tx + size - 1 - ex_tx))
    return dy * dy + dx * dx <= ex_r2


#: Points per chunk of the early stop: bounds are checked, and prefix sums kept, per chunk.
CHUNK = 32


@numba.njit(cache=True, inline="always", boundscheck=False)
def _finish(level, idx, j, n, a0, ci, s, parent, parent_total, limit, out, c, store):  # type: ignore[no-untyped-def]
    """Continue one child's score from chunk ``ci`` alone, with the same early stop."""
    n_chunks = (n + CHUNK - 1) // CHUNK
    while ci < n_chunks:
        for k in range(ci * CHUNK, min(ci * CHUNK + CHUNK, n)):
            s += level[np.uint64(idx[j, k] + a0)]
        if store:
            out[c, ci] = s
        pp = parent[ci]
        ci += 1
        if s - pp < limit:
            return s + parent_total - pp
    return s


@numba.njit(cache=True, boundscheck=False)
def _quad(level, idx, j, n, off, d_col, d_row, parent, parent_total, best, out, store):  # type: ignore[no-untyped-def]
    """Scores of the four translations ``off``, ``+ d_col``, ``+ d_row``, ``+ d_row + d_col``
    (one pass over the points: one index load serves four lookups in nearby cache lines).

    With a ``parent`` (prefix sums, per chunk of ``CHUNK`` points, of the enclosing block's
    score at the level above, total ``parent_total >= 0``), a child is abandoned as soon as
    it provably falls below ``best``: every point's value in a sub-block is at most its value
    in the parent block, so ``score_c <= prefix_c + (parent_total - parent_prefix)``; that bound
    (``< best``) is returned for it. Once one child is abandoned the others continue one at a
    time. With ``store`` the children's prefix sums go to ``out[0..3]`` (complete only for
    children not abandoned).
    """
    s0 = s1 = s2 = s3 = 0
    pp = 0
    has_parent = parent_total >= 0
    limit = best - parent_total
    n_chunks = (n + CHUNK - 1) // CHUNK
    ci = 0
    while ci < n_chunks:
        for k in range(ci * CHUNK, min(ci * CHUNK + CHUNK, n)):
            a = idx[j, k] + off
            s0 += level[np.uint64(a)]
            s1 += level[np.uint64(a + d_col)]
            s2 += level[np.uint64(a + d_row)]
            s3 += level[np.uint64(a + d_row + d_col)]
        if store:
            out[0, ci] = s0
            out[1, ci] = s1
            out[2, ci] = s2
            out[3, ci] = s3
        ci += 1
        if has_parent:
            pp = parent[ci - 1]
            if min(min(s0, s1), min(s2, s3)) - pp < limit:
                break
    if ci >= n_chunks and not (has_parent and min(min(s0, s1), min(s2, s3)) - pp < limit):
        return s0, s1, s2, s3
    rem = parent_total - pp
    r0 = (
        s0 + rem
        if s0 - pp < limit
        else _finish(level, idx, j, n, off, ci, s0, parent, parent_total, limit, out, 0, store)
    )
    r1 = (
        s1 + rem
        if s1 - pp < limit
        else _finish(
            level, idx, j, n, off + d_col, ci, s1, parent, parent_total, limit, out, 1, store
        )
    )
    r2 = (
        s2 + rem
        if s2 - pp < limit
        else _finish(
            level, idx, j, n, off + d_row, ci, s2, parent, parent_total, limit, out, 2, store
        )
    )
    r3 = (
        s3 + rem
        if s3 - pp < limit
        else _finish(
            level, idx, j, n, off + d_row + d_col, ci, s3, parent, parent_total, limit, out, 3,
            store,
        )
    )  # fmt: skip
    return r0, r1, r2, r3


@numba.njit(cache=True, boundscheck=False)
def _branch_and_bound(pyramid, width, idx, count, n_xy, min_score, j_guess, ex_ty, ex_tx, ex_r2):  # type: ignore[no-untyped-def]
    """Exact best ``(score, j, ty, tx)`` over rotations ``j`` and translations ``|t| <= n_xy``
    (ties: lowest index), or ``score < min_score`` when nothing reaches ``min_score``.

    ``ex_r2 >= 0`` leaves out every translation within ``sqrt(ex_r2)`` cells of ``(ex_ty,
    ex_tx)``, at every rotation (the runner-up search, :meth:`CorrelativeMatcher.match`): a
    block lying wholly inside that disk is never bounded, a cell inside it never scored."""
    levels = pyramid.shape[0]
    n_yaw = idx.shape[0]
    n_chunks = (idx.shape[1] + CHUNK - 1) // CHUNK
    top = levels - 1
    block = 1 << top
    span = 2 * n_xy + 1
    nb = (span + block - 1) // block
    # start from the guess itself: an exact score, a valid candidate
    best = min_score - 1  # anything below the acceptance threshold is pruned
    bj = bty = btx = 1 << 30
    evaluated = 0
    if not _excluded(0, 0, 1, ex_ty, ex_tx, ex_r2):
        g = _score(pyramid[0], idx, j_guess, count[j_guess], 0)
        evaluated = 1
        if g > best:
            best, bj, bty, btx = g, j_guess, 0, 0
    # bound every top-level block of every rotation (four at a time), keeping the prefix
    # sums for the children's early stop
    cap = n_yaw * (nb + 1) * (nb + 1)
    bounds = np.empty(cap, dtype=np.int64)
    keys = np.empty((cap, 3), dtype=np.int64)
    top_sums = np.empty((cap, n_chunks), dtype=np.int64)
    quad_sums = np.empty((4, n_chunks), dtype=np.int64)
    no_parent = np.empty(0, dtype=np.int64)
    total = 0
    for j in range(n_yaw):
        n = count[j]
        for by in range(0, nb, 2):
            for bx in range(0, nb, 2):
                ty = -n_xy + by * block
                tx = -n_xy + bx * block
                q = _quad(
                    pyramid[top], idx, j, n, ty * width + tx, block, block * width, no_parent,
                    -1, 0, quad_sums, True,
                )  # fmt: skip
                for c in range(4):
                    cty = ty + (c >> 1) * block
                    ctx = tx + (c & 1) * block
                    if cty > n_xy or ctx > n_xy or _excluded(cty, ctx, block, ex_ty, ex_tx, ex_r2):
                        continue
                    bounds[total] = q[c]
                    keys[total, 0] = j
                    keys[total, 1] = cty
                    keys[total, 2] = ctx
                    top_sums[total, :] = quad_sums[c, :]
                    total += 1
    evaluated += total
    order = np.argsort(-bounds[:total], kind="mergesort")
    depth = 4 * levels + 8
    stack = np.empty((depth, 5), dtype=np.int64)
    sums = np.empty((depth, n_chunks), dtype=np.int64)
    child = np.empty((4, 3), dtype=np.int64)
    for o in order:
        b = bounds[o]
        if b < best:
            break  # sorted: nothing after can beat the best
        if b == best and not _before(keys[o, 0], keys[o, 1], keys[o, 2], bj, bty, btx):
            continue
        stack[0, 0] = top
        stack[0, 1] = keys[o, 0]
        stack[0, 2] = keys[o, 1]
        stack[0, 3] = keys[o, 2]
        stack[0, 4] = b
        sums[0, :] = top_sums[o]
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
            half = 1 << (lvl - 1)
            q = _quad(
                pyramid[lvl - 1], idx, j, count[j], ty * width + tx, half, half * width,
                sums[sp], bound, best, quad_sums, lvl > 1,
            )  # fmt: skip
            nc = 0
            for c in range(4):
                cty = ty + (c >> 1) * half
                ctx = tx + (c & 1) * half
                if cty > n_xy or ctx > n_xy or _excluded(cty, ctx, half, ex_ty, ex_tx, ex_r2):
                    continue
                evaluated += 1
                cb = q[c]
                if cb < best:
                    continue
                if lvl == 1:  # an exact score; children come in index order
                    if cb > best or _before(j, cty, ctx, bj, bty, btx):
                        best, bj, bty, btx = cb, j, cty, ctx
                    continue
                child[nc, 0] = c
                child[nc, 1] = cb
                nc += 1
            # push ascending (larger bound, then lower index, refined first)
            for a in range(nc):
                for b2 in range(a + 1, nc):
                    if child[b2, 1] < child[a, 1] or (
                        child[b2, 1] == child[a, 1] and child[b2, 0] > child[a, 0]
                    ):
                        for f in range(2):
                            tmp = child[a, f]
                            child[a, f] = child[b2, f]
                            child[b2, f] = tmp
            for a in range(nc):
                c = child[a, 0]
                stack[sp, 0] = lvl - 1
                stack[sp, 1] = j
                stack[sp, 2] = ty + (c >> 1) * half
                stack[sp, 3] = tx + (c & 1) * half
                stack[sp, 4] = child[a, 1]
                sums[sp, :] = quad_sums[c, :]
                sp += 1
    return best, bj, bty, btx, evaluated


@numba.njit(cache=True)
def _brute_force(table, rows, cols, n_xy, min_score):  # type: ignore[no-untyped-def]
    """Every rotation and translation, bounds-checked lookups in the unpadded level 0."""
    h, w = table.shape
    best = min_score - 1
    bj = bty = btx = 1 << 30
    for j in range(rows.shape[0]):
        for ty in range(-n_xy, n_xy + 1):
            for tx in range(-n_xy, n_xy + 1):
                s = 0
                for i in range(rows.shape[1]):
                    r = rows[j, i] + ty
                    c = cols[j, i] + tx
                    if 0 <= r < h and 0 <= c < w:
                        s += table[r, c]
                if s > best:
                    best, bj, bty, btx = s, j, ty, tx
    return best, bj, bty, btx


@numba.njit(cache=True, boundscheck=False)
def _response_surface(level0, width, idx, count, n_xy, j0, ty0, tx0, radius, yaws, res, scale):  # type: ignore[no-untyped-def]
    """Mean and covariance of ``(x, y, yaw)`` offsets around the optimum ``(j0, ty0, tx0)``,
    each neighbour weighted by ``exp(scale * (score - best))`` (its likelihood ratio).

    Returns ``(mean (3,), covariance (3, 3))``; x and y are offsets from the guess, yaw absolute.
    """
    j_lo, j_hi = max(0, j0 - radius), min(idx.shape[0], j0 + radius + 1)
    y_lo, y_hi = max(-n_xy, ty0 - radius), min(n_xy, ty0 + radius) + 1
    x_lo, x_hi = max(-n_xy, tx0 - radius), min(n_xy, tx0 + radius) + 1
    m = (j_hi - j_lo) * (y_hi - y_lo) * (x_hi - x_lo)
    xyz = np.empty((m, 3))
    sc = np.empty(m)
    k = 0
    best = -1.0
    for j in range(j_lo, j_hi):
        for ty in range(y_lo, y_hi):
            for tx in range(x_lo, x_hi):
                xyz[k, 0] = tx * res
                xyz[k, 1] = ty * res
                xyz[k, 2] = yaws[j]
                sc[k] = _score(level0, idx, j, count[j], ty * width + tx)
                best = max(best, sc[k])
                k += 1
    wsum = 0.0
    mu = np.zeros(3)
    for k in range(m):
        sc[k] = math.exp((sc[k] - best) * scale)
        wsum += sc[k]
        for a in range(3):
            mu[a] += sc[k] * xyz[k, a]
    mu /= wsum
    cov = np.zeros((3, 3))
    for k in range(m):
        wk = sc[k] / wsum
        for a in range(3):
            da = xyz[k, a] - mu[a]
            for b in range(3):
                cov[a, b] += wk * da * (xyz[k, b] - mu[b])
    return mu, cov


@numba.njit(cache=True, boundscheck=False)
def _outer_translation_cov(
    level0, width, idx, count, n_xy, j0, ty0, tx0, radius, stride, scale, best
):  # type: ignore[no-untyped-def]
    """Translation covariance (cells^2) over a strided grid of translations within ``radius``
    cells of the optimum, at the optimum's rotation, weighted like the response surface:
    it sees ambiguity (a ridge along a corridor) wider than the inner neighbourhood."""
    wsum = 0.0
    mx = 0.0
    my = 0.0
    sxx = sxy = syy = 0.0
    for dy in range(-radius, radius + 1, stride):
        ty = ty0 + dy
        if ty < -n_xy or ty > n_xy:
            continue
        for dx in range(-radius, radius + 1, stride):
            tx = tx0 + dx
            if tx < -n_xy or tx > n_xy:
                continue
            w = math.exp((_score(level0, idx, j0, count[j0], ty * width + tx) - best) * scale)
            wsum += w
            mx += w * dx
            my += w * dy
            sxx += w * dx * dx
            sxy += w * dx * dy
            syy += w * dy * dy
    mx /= wsum
    my /= wsum
    cov = np.empty((2, 2))
    cov[0, 0] = sxx / wsum - mx * mx
    cov[0, 1] = cov[1, 0] = sxy / wsum - mx * my
    cov[1, 1] = syy / wsum - my * my
    return cov


@dataclass(frozen=True)
class _Prepared:
    yaws: np.ndarray
    idx: np.ndarray  # int32 (n_yaw, n_points): live points first
    count: np.ndarray  # int64 (n_yaw,)
    points: np.ndarray  # thinned query points
    n_xy: int
    j_guess: int


class CorrelativeMatcher:
    """Aligns binary grids (see the module docstring)."""

    def __init__(self, config: MatcherConfig | None = None) -> None:
        self.config = config or MatcherConfig()

    def _n_xy(self, resolution_m: float) -> int:
        return int(math.ceil(self.config.search_xy_m / resolution_m - 1e-9))

    def _levels(self, resolution_m: float) -> int:
        if self.config.levels:
            return self.config.levels
        # top blocks of the largest power of two below the window span: a few blocks per
        # rotation bound far tighter than one block covering everything (measured: 10x)
        span = 2 * self._n_xy(resolution_m) + 1
        return max(1, int(math.ceil(math.log2(max(span, 2)))))

    def reference_table(
        self, grid: np.ndarray, *, origin_m: tuple[float, float], resolution_m: float
    ) -> ReferenceTable:
        """Build the lookup pyramid of a reference grid (cell (row, col) covers
        ``origin_m + (col, row) * resolution_m``)."""
        g = np.asarray(grid, dtype=bool)
        if g.ndim != 2 or g.size == 0:
            raise ValueError(f"reference grid must be a non-empty 2-D array, got shape {g.shape}")
        if not (resolution_m > 0 and math.isfinite(resolution_m)):
            raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
        if not all(math.isfinite(v) for v in origin_m):
            raise ValueError(f"origin_m must be finite, got {origin_m}")
        level0, loglik_per_unit = self._level0(g, resolution_m)
        levels = self._levels(resolution_m)
        n_xy = self._n_xy(resolution_m)
        block = 1 << (levels - 1)
        pad = 2 * n_xy + block  # see _rotated_indices: every live lookup stays inside
        h, w = g.shape
        hp, wp = h + 2 * pad, w + 2 * pad
        pyramid = np.zeros((levels, hp, wp), dtype=np.uint8)
        pyramid[0, pad : pad + h, pad : pad + w] = level0
        for k in range(1, levels):
            # level k = max of two level k-1 windows, rows then columns; it is non-zero only
            # where its 2^k window meets the grid: rows/cols [pad - 2^k + 1, pad + h)
            step = 1 << (k - 1)
            r0, r1, c0, c1 = pad - (1 << k) + 1, pad + h, pad - (1 << k) + 1, pad + w
            prev = pyramid[k - 1]
            rows = np.maximum(
                prev[r0:r1, c0 : c1 + step], prev[r0 + step : r1 + step, c0 : c1 + step]
            )
            pyramid[k, r0:r1, c0:c1] = np.maximum(
                rows[:, : c1 - c0], rows[:, step : step + c1 - c0]
            )
        return ReferenceTable(
            pyramid=pyramid.reshape(levels, hp * wp),
            pad=pad,
            shape=(hp, wp),
            grid_shape=(h, w),
            n_xy=n_xy,
            origin_m=(float(origin_m[0]), float(origin_m[1])),
            resolution_m=float(resolution_m),
            loglik_per_unit=loglik_per_unit,
        )

    def _level0(self, grid: np.ndarray, resolution_m: float) -> tuple[np.ndarray, float]:
        """Quantized log-likelihood of a point per cell, and the log-likelihood per unit.

        The value is a decreasing function of the distance to the nearest occupied cell, so
        it is the maximum over occupied cells of a stamp of that function around each: the
        stamp covers the radius where the kernel still quantizes above 0 (4 sigma with the
        defaults), which makes this O(occupied * stamp) instead of a distance transform.
        """
        cfg = self.config
        eps = cfg.outlier_likelihood
        lo, hi = math.log(eps), math.log(1.0 + eps)
        radius = int(math.ceil(8.0 * cfg.sigma_m / resolution_m))
        off = np.arange(-radius, radius + 1, dtype=np.float64) * resolution_m
        d2_m = off[:, None] ** 2 + off[None, :] ** 2
        loglik = np.log(np.exp(-0.5 * d2_m / cfg.sigma_m**2) + eps)
        stamp = np.round(255.0 * (loglik - lo) / (hi - lo)).astype(np.uint8)
        nz = np.nonzero(stamp.any(axis=1))[0]  # trim rings that quantize to 0
        r = int(max(radius - nz[0], nz[-1] - radius)) if len(nz) else 0
        stamp = np.ascontiguousarray(
            stamp[radius - r : radius + r + 1, radius - r : radius + r + 1]
        )
        rows, cols = np.nonzero(grid)
        level0 = np.zeros(grid.shape, dtype=np.uint8)
        _stamp_max(rows, cols, stamp, level0)
        return level0, (hi - lo) / 255.0

    def _prepare(
        self, ref: ReferenceTable, query_points_m: np.ndarray, guess: np.ndarray
    ) -> _Prepared:
        cfg = self.config
        pts = np.asarray(query_points_m, dtype=np.float64).reshape(-1, 2)
        if not np.all(np.isfinite(pts)):
            raise ValueError("query points must be finite")
        g = np.asarray(guess, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ValueError(f"guess must be a finite pose (3,), got {guess!r}")
        n_xy = self._n_xy(ref.resolution_m)
        if n_xy != ref.n_xy or self._levels(ref.resolution_m) != ref.levels:
            raise ValueError(
                f"reference table built for a window of {ref.n_xy} cells and {ref.levels} "
                f"levels; this matcher searches {n_xy} cells and "
                f"{self._levels(ref.resolution_m)} levels (build it with the same matcher)"
            )
        if len(pts) == 0:
            raise ValueError("the query has no points to match")
        pts = np.ascontiguousarray(_thin(pts, cfg.max_points, ref.resolution_m))
        r_max = float(np.sqrt(np.max(pts[:, 0] ** 2 + pts[:, 1] ** 2)))
        step = cfg.yaw_step_rad or cfg.yaw_step_cells * ref.resolution_m / max(
            r_max, ref.resolution_m
        )
        n_yaw = int(math.floor(cfg.search_yaw_rad / step + 1e-9))
        yaws = g[2] + step * np.arange(-n_yaw, n_yaw + 1)
        idx = np.empty((len(yaws), len(pts)), dtype=np.int32)
        count = np.empty(len(yaws), dtype=np.int64)
        ox, oy = ref.origin_m
        h, w = ref.grid_shape
        block = 1 << (ref.levels - 1)
        _rotated_indices(
            pts, yaws, g[0], g[1], ox, oy, ref.resolution_m, ref.pad, h, w, n_xy, block,
            ref.shape[1], idx, count,
        )  # fmt: skip
        return _Prepared(yaws, idx, count, pts, n_xy, n_yaw)

    def match(
        self,
        ref: ReferenceTable,
        query_points_m: np.ndarray,
        guess_a_from_b: np.ndarray,
        *,
        min_score: float = 0.0,
        runner_up_radius_m: float | None = None,
    ) -> MatchResult | None:
        """Best ``a_from_b`` in the window around ``guess_a_from_b`` (branch and bound).

        ``query_points_m``: points ``(N, 2)`` in B's frame (e.g. :func:`grid_points`).
        ``min_score``: normalized score a match must reach; below it the search prunes and
        returns None (as the brute-force oracle does with the same threshold).
        ``runner_up_radius_m``: this call's runner-up exclusion radius (None: the config's
        ``runner_up_radius_m``; 0: no runner-up search), so that a caller searches for
        look-alikes only where they matter.
        """
        if runner_up_radius_m is None:
            runner_up_radius_m = self.config.runner_up_radius_m
        if not (math.isfinite(runner_up_radius_m) and runner_up_radius_m >= 0):
            raise ValueError(f"runner_up_radius_m must be >= 0, got {runner_up_radius_m}")
        p = self._prepare(ref, query_points_m, guess_a_from_b)
        threshold = _threshold(min_score, len(p.points))
        best, j, ty, tx, evaluated = _branch_and_bound(
            ref.pyramid, ref.shape[1], p.idx, p.count, p.n_xy, threshold, p.j_guess, 0, 0, -1
        )
        if best < threshold:
            return None
        result = self._result(ref, p, guess_a_from_b, best, j, ty, tx, evaluated)
        radius = runner_up_radius_m / ref.resolution_m
        if radius <= 0:
            return result
        # the best other place (MatcherConfig.runner_up_radius_m), pruned at the ratio
        floor = max(threshold, int(math.ceil(self.config.runner_up_ratio * best - 1e-9)))
        second, j2, ty2, tx2, more = _branch_and_bound(
            ref.pyramid, ref.shape[1], p.idx, p.count, p.n_xy, floor, p.j_guess, ty, tx,
            radius * radius,
        )  # fmt: skip
        if second < floor:
            return dataclasses.replace(result, nodes_evaluated=result.nodes_evaluated + int(more))
        g = np.asarray(guess_a_from_b, dtype=np.float64)
        res = ref.resolution_m
        return dataclasses.replace(
            result,
            nodes_evaluated=result.nodes_evaluated + int(more),
            runner_up_score=float(second / (255.0 * len(p.points))),
            runner_up_a_from_b=np.array(
                [g[0] + int(tx2) * res, g[1] + int(ty2) * res, _wrap(float(p.yaws[int(j2)]))]
            ),
        )

    def _result(
        self,
        ref: ReferenceTable,
        p: _Prepared,
        guess: np.ndarray,
        best: int,
        j: int,
        ty: int,
        tx: int,
        evaluated: int,
    ) -> MatchResult:
        res = ref.resolution_m
        g = np.asarray(guess, dtype=np.float64)
        discrete = np.array([g[0] + tx * res, g[1] + ty * res, _wrap(float(p.yaws[j]))])
        mean, cov = self._response(ref, p, j, ty, tx)
        refined = np.array([g[0] + mean[0], g[1] + mean[1], _wrap(float(mean[2]))])
        norm = best / (255.0 * len(p.points))
        return MatchResult(refined, discrete, cov, int(best), float(norm), int(evaluated))

    def _response(
        self, ref: ReferenceTable, p: _Prepared, j: int, ty: int, tx: int
    ) -> tuple[np.ndarray, np.ndarray]:
        res = ref.resolution_m
        mu, cov = _response_surface(
            ref.pyramid[0], ref.shape[1], p.idx, p.count, p.n_xy, j, ty, tx,
            self.config.response_radius, p.yaws, res,
            ref.loglik_per_unit / self.config.point_correlation,
        )  # fmt: skip
        cfg = self.config
        if cfg.response_outer_radius > 0:
            best = _score(ref.pyramid[0], p.idx, j, p.count[j], ty * ref.shape[1] + tx)
            outer = _outer_translation_cov(
                ref.pyramid[0], ref.shape[1], p.idx, p.count, p.n_xy, j, ty, tx,
                cfg.response_outer_radius, cfg.response_outer_stride,
                ref.loglik_per_unit / cfg.point_correlation, best,
            ) * res**2  # fmt: skip
            if np.trace(outer) > cov[0, 0] + cov[1, 1]:
                # ambiguity wider than the inner neighbourhood: its translation block rules
                cov[:2, :2] = outer
                cov[:2, 2] = 0.0
                cov[2, :2] = 0.0
        step = float(p.yaws[1] - p.yaws[0]) if len(p.yaws) > 1 else 0.01
        cov[0, 0] += res**2 / 12.0  # floor: the discretization itself
        cov[1, 1] += res**2 / 12.0
        cov[2, 2] += step**2 / 12.0
        return mu, cov


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


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
    """The same search by exhaustive evaluation of every discretized transform (the oracle).

    It shares only the discretization with :meth:`CorrelativeMatcher.match`: points are
    rotated by their own loop and looked up with bounds checks in the unpadded level 0.
    """
    p = matcher._prepare(ref, query_points_m, guess_a_from_b)
    g = np.asarray(guess_a_from_b, dtype=np.float64)
    rows = np.empty((len(p.yaws), len(p.points)), dtype=np.int64)
    cols = np.empty_like(rows)
    ox, oy = ref.origin_m
    _rotated_cells(p.points, p.yaws, g[0], g[1], ox, oy, ref.resolution_m, rows, cols)
    h, w = ref.grid_shape
    table = np.ascontiguousarray(ref.level(0)[ref.pad : ref.pad + h, ref.pad : ref.pad + w])
    threshold = _threshold(min_score, len(p.points))
    best, j, ty, tx = _brute_force(table, rows, cols, p.n_xy, threshold)
    if best < threshold:
        return None
    evaluated = len(p.yaws) * (2 * p.n_xy + 1) ** 2
    return matcher._result(ref, p, g, best, j, ty, tx, evaluated)
