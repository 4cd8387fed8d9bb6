"""Free-space evidence along LIDAR rays: how low a beam passed over each cell (paper 5.3).

A beam that travelled from the sensor to its return crossed every cell on the way at some
height above that cell's ground: nothing stood in that cell up to that height when the beam
passed (we cannot see through solid things, the same argument as the ground model's). Per
sweep, :func:`ray_floor` keeps, for each cell, the *lowest* height above the ground model at
which a beam crossed it. The fusion (:mod:`robot.terrain.map_fusion`) uses it to drop an old
obstacle mark once later sweeps saw beams pass *below the top* of what was marked there: the
trail a moving teammate leaves in a pessimistic 15 s memory. The MAGIC robots' sparse sweeps
see the ground itself only along scan lines, but their beams cross far more of it.

The last ``end_margin_m`` of each beam is not used: the return lies there, and a beam that
grazes a surface in a cell partly occupied by it must not clear that cell.

Frames: everything in ``odom``, heights relative to the ground model of the same sweep
(:mod:`robot.terrain.ground_model`), metres. ``O(sum of beam lengths / resolution)``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from robot.terrain.grid import GridGeometry

__all__ = ["ray_floor"]


@nb.njit(cache=True, nogil=True)
def _ray_floor(sx, sy, sz, px, py, pz, ox, oy, res, ground, end_margin, out):  # type: ignore[no-untyped-def]
    rows, cols = ground.shape
    x1 = ox + cols * res
    y1 = oy + rows * res
    for i in range(px.shape[0]):
        dx = px[i] - sx[i]
        dy = py[i] - sy[i]
        dz = pz[i] - sz[i]
        d = math.sqrt(dx * dx + dy * dy)
        length = d - end_margin
        if length <= 0.0:
            continue
        # t in [0, 1] runs along the beam; clip [0, length / d] to the grid's box (slabs)
        t0 = 0.0
        t1 = length / d
        if abs(dx) < 1e-12:
            if sx[i] < ox or sx[i] >= x1:
                continue
        else:
            a = (ox - sx[i]) / dx
            b = (x1 - sx[i]) / dx
            t0 = max(t0, min(a, b))
            t1 = min(t1, max(a, b))
        if abs(dy) < 1e-12:
            if sy[i] < oy or sy[i] >= y1:
                continue
        else:
            a = (oy - sy[i]) / dy
            b = (y1 - sy[i]) / dy
            t0 = max(t0, min(a, b))
            t1 = min(t1, max(a, b))
        if t0 >= t1:
            continue
        # exact grid traversal (Amanatides and Woo): every cell the segment crosses
        tm = t0 + 1e-9
        c = min(max(int(math.floor((sx[i] + dx * tm - ox) / res)), 0), cols - 1)
        r = min(max(int(math.floor((sy[i] + dy * tm - oy) / res)), 0), rows - 1)
        step_c = 1 if dx > 0 else -1
        step_r = 1 if dy > 0 else -1
        if abs(dx) < 1e-12:
            next_tx = np.inf
            delta_tx = np.inf
        else:
            edge = ox + (c + (1 if dx > 0 else 0)) * res
            next_tx = (edge - sx[i]) / dx
            delta_tx = res / abs(dx)
        if abs(dy) < 1e-12:
            next_ty = np.inf
            delta_ty = np.inf
        else:
            edge = oy + (r + (1 if dy > 0 else 0)) * res
            next_ty = (edge - sy[i]) / dy
            delta_ty = res / abs(dy)
        t_in = t0
        while t_in < t1 and 0 <= r < rows and 0 <= c < cols:
            t_out = min(next_tx, next_ty, t1)
            h = sz[i] + dz * min(t_in, t_out) if dz >= 0 else sz[i] + dz * t_out
            h -= ground[r, c]
            if h < out[r, c]:
                out[r, c] = h
            if next_tx < next_ty:
                c += step_c
                t_in = next_tx
                next_tx += delta_tx
            else:
                r += step_r
                t_in = next_ty
                next_ty += delta_ty
    return out


def ray_floor(
    points_in_odom: NDArray[np.float64],
    sensors_in_odom: NDArray[np.float64],
    geometry: GridGeometry,
    ground_m: NDArray[np.float64],
    *,
    end_margin_m: float,
) -> NDArray[np.float64]:
    """Lowest height (m, >= 0) above ``ground_m`` at which a beam from ``sensors_in_odom``
    (``(N, 3)``, the sensor's position when it measured each point, or ``(3,)`` for all) to
    ``points_in_odom`` (``(N, 3)``) crossed each cell of ``geometry``; ``inf`` where none did.
    Every cell a beam's horizontal projection crosses counts (exact grid traversal), with
    the beam's lowest height inside it, up to ``end_margin_m`` before the return."""
    pts = np.asarray(points_in_odom, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_in_odom: expected shape (N, 3), got {pts.shape}")
    sensors = np.broadcast_to(np.asarray(sensors_in_odom, dtype=np.float64), pts.shape)
    if not np.all(np.isfinite(sensors)):
        raise ValueError("sensors_in_odom: not finite")
    if ground_m.shape != geometry.shape:
        raise ValueError(f"ground_m: shape {ground_m.shape} does not match grid {geometry.shape}")
    if not (math.isfinite(end_margin_m) and end_margin_m >= 0):
        raise ValueError(f"end_margin_m must be finite and >= 0, got {end_margin_m}")
    out = np.full(geometry.shape, np.inf)
    _ray_floor(
        np.ascontiguousarray(sensors[:, 0]),
        np.ascontiguousarray(sensors[:, 1]),
        np.ascontiguousarray(sensors[:, 2]),
        np.ascontiguousarray(pts[:, 0]),
        np.ascontiguousarray(pts[:, 1]),
        np.ascontiguousarray(pts[:, 2]),
        float(geometry.origin_m[0]),
        float(geometry.origin_m[1]),
        float(geometry.resolution_m),
        np.ascontiguousarray(ground_m, dtype=np.float64),
        float(end_margin_m),
        out,
    )
    return np.maximum(out, 0.0)
