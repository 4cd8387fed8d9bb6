"""Two rasterizations of one graph laid over each other: near free space over far free space.

Latest-wins fusion (:mod:`gcs.mapping.rasterization`) lets a later node's free ray erase a wall
an earlier node saw. Far from the node the rays are long and graze walls whose returns are
sparse, so walls erode: in the small world at 300 mission-s, with the true poses, 13% of the
wall surface the map had observed was missing (recall 0.87) with rays of 7.5 m, 4% with rays
of 4 m; but 4 m rays know 30% less of the site (what exploration needs). So the GCS rasterizes
twice (the same nodes and poses) and lays the *near* map (short free rays, wider wall gaps)
over the *far* one (:func:`overlay`): every cell the near map knows takes its value (its walls
are erased only by free space seen from close by), every other cell the far map's. Measured
on the same replayed run (seed 7): F1 0.915 -> 0.946 with true poses, 0.52 -> 0.58 with the
GCS's, explored fraction unchanged (0.849).
"""

from __future__ import annotations

import numpy as np

from gcs.mapping.rasterization import UNKNOWN, OccupancyMap

__all__ = ["overlay"]


def overlay(top: OccupancyMap, bottom: OccupancyMap) -> OccupancyMap:
    """``bottom`` with every cell ``top`` knows (free or occupied) replaced by ``top``'s value.

    Both maps must lie on one lattice of ``map`` (same resolution, origins a whole number of
    cells apart; a rasterizer's maps always do); the result covers both. ``O(cells)``.
    Raises ValueError when the lattices differ."""
    if top.values.size == 0:
        return bottom
    if bottom.values.size == 0:
        return top
    res = bottom.resolution_m
    if not np.isclose(top.resolution_m, res, rtol=0.0, atol=1e-12):
        raise ValueError(f"overlay: resolutions differ ({top.resolution_m} vs {res} m)")
    o_top = np.asarray(top.origin_in_map, dtype=float) / res
    o_bot = np.asarray(bottom.origin_in_map, dtype=float) / res
    c_top, c_bot = np.round(o_top).astype(np.int64), np.round(o_bot).astype(np.int64)
    if np.any(np.abs(o_top - c_top) > 1e-6) or np.any(np.abs(o_bot - c_bot) > 1e-6):
        raise ValueError("overlay: origins are not on one lattice of whole cells")
    lo = np.minimum(c_top, c_bot)  # (col, row) of the result's cell (0, 0)
    hi = np.maximum(c_top + top.values.shape[::-1], c_bot + bottom.values.shape[::-1])
    out = np.full((int(hi[1] - lo[1]), int(hi[0] - lo[0])), UNKNOWN, dtype=np.int8)
    for m, c in ((bottom, c_bot), (top, c_top)):
        r0, k0 = int(c[1] - lo[1]), int(c[0] - lo[0])
        h, w = m.values.shape
        view = out[r0 : r0 + h, k0 : k0 + w]
        known = m.values != UNKNOWN
        view[known] = m.values[known]
    origin = (float(lo[0] * res), float(lo[1] * res))
    if np.array_equal(lo, c_bot) and out.shape == bottom.values.shape:
        origin = bottom.origin_in_map  # bit for bit the bottom's corner
    return OccupancyMap(out, origin, res)
