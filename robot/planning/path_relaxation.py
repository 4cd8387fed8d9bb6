"""Bounded clearance relaxation of a minimum-distance path (paper 5.4, Fig. 16d; Richardson
and Olson 2011).

Dijkstra's path hugs the configuration-space boundary: it has no margin for localization
error. Each interior vertex whose clearance (distance to the nearest obstacle, from the
distance transform of the obstacle map) is below ``clearance_m`` is pushed up the clearance
gradient in steps of ``step_m``, as long as its clearance grows, it stays within
``max_offset_m`` of where Dijkstra put it, and the segments to its neighbours stay free in
configuration space. A vertex stops at ``clearance_m``: the clearance added is bounded, so the
path takes the middle of a doorway but not of a wide hallway. The endpoints never move.

Guarantees (tested): every vertex's clearance is at least its clearance before relaxation,
and every segment is free in configuration space. ``O(iterations * K)`` for ``K`` vertices.

Path coordinates are fractional cells ``(row, col)``: ``(r, c)`` is the center of cell
``(r, c)``, as :meth:`robot.terrain.grid.GridGeometry.center_of` maps them.
"""

from __future__ import annotations

import math

import cv2
import numba as nb
import numpy as np
from numpy.typing import NDArray

__all__ = ["clearance_field", "path_clearance", "relax_path", "segments_free"]


def clearance_field(obstacle: NDArray[np.bool_], *, resolution_m: float) -> NDArray[np.float64]:
    """Euclidean distance (m) from every cell center to the nearest ``obstacle`` cell center
    (cv2.distanceTransform, precise mask); ``inf``-free: a map without obstacles gets
    ``rows + cols`` cells everywhere."""
    obs = np.asarray(obstacle)
    if obs.ndim != 2 or obs.dtype != np.bool_:
        raise ValueError(f"obstacle: expected a 2D bool grid, got {obs.dtype} {obs.shape}")
    if not obs.any():
        return np.full(obs.shape, float(sum(obs.shape)) * resolution_m)
    free = (~obs).astype(np.uint8)
    d = cv2.distanceTransform(free, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return d.astype(np.float64) * resolution_m


@nb.njit(cache=True, nogil=True)
def _bilinear(f, r, c):  # type: ignore[no-untyped-def]
    rows, cols = f.shape
    r = min(max(r, 0.0), rows - 1.0)
    c = min(max(c, 0.0), cols - 1.0)
    r0 = min(int(math.floor(r)), rows - 2) if rows > 1 else 0
    c0 = min(int(math.floor(c)), cols - 2) if cols > 1 else 0
    fr = r - r0
    fc = c - c0
    r1 = min(r0 + 1, rows - 1)
    c1 = min(c0 + 1, cols - 1)
    top = f[r0, c0] * (1 - fc) + f[r0, c1] * fc
    bot = f[r1, c0] * (1 - fc) + f[r1, c1] * fc
    return top * (1 - fr) + bot * fr


@nb.njit(cache=True, nogil=True)
def _free_at(blocked, r, c):  # type: ignore[no-untyped-def]
    ri = int(math.floor(r + 0.5))
    ci = int(math.floor(c + 0.5))
    if ri < 0 or ci < 0 or ri >= blocked.shape[0] or ci >= blocked.shape[1]:
        return False
    return not blocked[ri, ci]


@nb.njit(cache=True, nogil=True)
def _segment_free(blocked, r0, c0, r1, c1):  # type: ignore[no-untyped-def]
    n = int(math.ceil(max(abs(r1 - r0), abs(c1 - c0)) * 4.0)) + 1
    for k in range(n + 1):
        t = k / n
        if not _free_at(blocked, r0 + (r1 - r0) * t, c0 + (c1 - c0) * t):
            return False
    return True


@nb.njit(cache=True, nogil=True)
def _segments_free(path, blocked):  # type: ignore[no-untyped-def]
    for i in range(path.shape[0] - 1):
        if not _segment_free(blocked, path[i, 0], path[i, 1], path[i + 1, 0], path[i + 1, 1]):
            return False
    if path.shape[0] == 1:
        return _free_at(blocked, path[0, 0], path[0, 1])
    return True


@nb.njit(cache=True, nogil=True)
def _relax(path, clearance, blocked, target, step, max_offset, iterations):  # type: ignore[no-untyped-def]
    orig = path.copy()
    k = path.shape[0]
    for _ in range(iterations):
        moved = False
        for i in range(1, k - 1):
            r = path[i, 0]
            c = path[i, 1]
            d = _bilinear(clearance, r, c)
            if d >= target:
                continue
            gr = _bilinear(clearance, r + 0.5, c) - _bilinear(clearance, r - 0.5, c)
            gc = _bilinear(clearance, r, c + 0.5) - _bilinear(clearance, r, c - 0.5)
            norm = math.sqrt(gr * gr + gc * gc)
            if norm < 1e-12:
                continue
            qr = r + step * gr / norm
            qc = c + step * gc / norm
            if (qr - orig[i, 0]) ** 2 + (qc - orig[i, 1]) ** 2 > max_offset * max_offset:
                continue
            if _bilinear(clearance, qr, qc) <= d:
                continue
            if not _segment_free(blocked, path[i - 1, 0], path[i - 1, 1], qr, qc):
                continue
            if not _segment_free(blocked, qr, qc, path[i + 1, 0], path[i + 1, 1]):
                continue
            path[i, 0] = qr
            path[i, 1] = qc
            moved = True
        if not moved:
            break
    return path


@nb.njit(cache=True, nogil=True)
def _vertex_clearance(path, clearance):  # type: ignore[no-untyped-def]
    out = np.empty(path.shape[0])
    for i in range(path.shape[0]):
        out[i] = _bilinear(clearance, path[i, 0], path[i, 1])
    return out


def _check_path(path: NDArray[np.float64], shape: tuple[int, ...]) -> NDArray[np.float64]:
    p = np.array(path, dtype=np.float64, copy=True)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) == 0:
        raise ValueError(f"path: expected shape (K, 2) with K >= 1, got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise ValueError("path: coordinates are not finite")
    return p


def path_clearance(path: NDArray[np.float64], clearance: NDArray[np.float64]) -> NDArray:
    """Clearance (m) at each vertex, bilinear in the clearance field."""
    return _vertex_clearance(_check_path(path, clearance.shape), clearance)  # type: ignore[no-any-return]


def segments_free(path: NDArray[np.float64], blocked: NDArray[np.bool_]) -> bool:
    """Whether the polyline stays in free configuration space (sampled every 1/4 cell)."""
    return bool(_segments_free(_check_path(path, blocked.shape), np.asarray(blocked, dtype=bool)))


def relax_path(
    path_cells: NDArray[np.float64],
    clearance_m: NDArray[np.float64],
    blocked: NDArray[np.bool_],
    *,
    resolution_m: float,
    target_clearance_m: float,
    step_m: float,
    max_offset_m: float,
    iterations: int,
) -> NDArray[np.float64]:
    """Relaxed copy of ``path_cells`` (``(K, 2)`` fractional (row, col)); see module doc.

    ``clearance_m``: :func:`clearance_field` of the obstacles; ``blocked``: configuration
    space. The input path must itself be free in ``blocked``.
    """
    p = _check_path(path_cells, blocked.shape)
    if clearance_m.shape != blocked.shape:
        raise ValueError(f"clearance_m {clearance_m.shape} and blocked {blocked.shape} differ")
    if not (step_m > 0 and max_offset_m >= 0 and iterations >= 0 and resolution_m > 0):
        raise ValueError("need step_m > 0, max_offset_m >= 0, iterations >= 0, resolution_m > 0")
    return _relax(  # type: ignore[no-any-return]
        p,
        np.ascontiguousarray(clearance_m, dtype=np.float64),
        np.ascontiguousarray(blocked, dtype=np.bool_),
        float(target_clearance_m),
        float(step_m / resolution_m),
        float(max_offset_m / resolution_m),
        int(iterations),
    )
