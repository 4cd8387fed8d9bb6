"""Iterative smoothing of a relaxed path (paper 5.4, Fig. 16d; Richardson and Olson 2011).

The 8-connected path jitters between grid directions. Each iteration moves every interior
vertex a fraction ``weight`` toward the midpoint of its neighbours (a discrete Laplacian
step), but only when the move keeps the vertex's clearance at least
``min(target_clearance_m, its current clearance)`` and both adjacent segments free in
configuration space. So smoothing never takes away clearance the relaxation bought up to the
target, and never collides. Endpoints never move. ``O(iterations * K)``.
"""

from __future__ import annotations

import numba as nb
import numpy as np
from numpy.typing import NDArray

from robot.planning.path_relaxation import _bilinear, _check_path, _segment_free

__all__ = ["smooth_path"]


@nb.njit(cache=True, nogil=True)
def _smooth(path, clearance, blocked, target, weight, iterations):  # type: ignore[no-untyped-def]
    k = path.shape[0]
    for _ in range(iterations):
        moved = 0.0
        for i in range(1, k - 1):
            r = path[i, 0]
            c = path[i, 1]
            qr = r + weight * (0.5 * (path[i - 1, 0] + path[i + 1, 0]) - r)
            qc = c + weight * (0.5 * (path[i - 1, 1] + path[i + 1, 1]) - c)
            need = min(target, _bilinear(clearance, r, c))
            if _bilinear(clearance, qr, qc) < need:
                continue
            if not _segment_free(blocked, path[i - 1, 0], path[i - 1, 1], qr, qc):
                continue
            if not _segment_free(blocked, qr, qc, path[i + 1, 0], path[i + 1, 1]):
                continue
            moved = max(moved, abs(qr - r) + abs(qc - c))
            path[i, 0] = qr
            path[i, 1] = qc
        if moved < 1e-4:
            break
    return path


def smooth_path(
    path_cells: NDArray[np.float64],
    clearance_m: NDArray[np.float64],
    blocked: NDArray[np.bool_],
    *,
    target_clearance_m: float,
    weight: float = 0.5,
    iterations: int = 100,
) -> NDArray[np.float64]:
    """Smoothed copy of ``path_cells`` (``(K, 2)`` fractional (row, col)); see module doc."""
    p = _check_path(path_cells, blocked.shape)
    if clearance_m.shape != blocked.shape:
        raise ValueError(f"clearance_m {clearance_m.shape} and blocked {blocked.shape} differ")
    if not (0 < weight <= 1 and iterations >= 0):
        raise ValueError(f"need 0 < weight <= 1 and iterations >= 0, got {weight}, {iterations}")
    return _smooth(  # type: ignore[no-any-return]
        p,
        np.ascontiguousarray(clearance_m, dtype=np.float64),
        np.ascontiguousarray(blocked, dtype=np.bool_),
        float(target_clearance_m),
        float(weight),
        int(iterations),
    )
