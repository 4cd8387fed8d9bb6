"""Small synthetic worlds for the rasterization tests: walls on a 10 cm lattice and the binary
grids robots at given poses would send (the wall cells their rays reach, in ``base``)."""

from __future__ import annotations

import math

import numpy as np

from gcs.mapping.visibility import FREE, OCCUPIED, local_raster

RES_M = 0.1


def box_world(size_m: tuple[float, float], seed: int, boxes: int = 12) -> np.ndarray:
    """``walls`` ``(rows, cols)`` bool: random rectangle outlines (with gaps) and a fence;
    cell ``(r, c)`` covers ``(c, r) * RES_M`` in ``map``."""
    rng = np.random.default_rng(seed)
    rows, cols = round(size_m[1] / RES_M), round(size_m[0] / RES_M)
    walls = np.zeros((rows, cols), dtype=bool)
    for _ in range(boxes):
        r0, c0 = int(rng.integers(0, rows - 20)), int(rng.integers(0, cols - 20))
        h, w = int(rng.integers(10, 60)), int(rng.integers(10, 60))
        r1, c1 = min(r0 + h, rows - 1), min(c0 + w, cols - 1)
        walls[r0, c0:c1] = walls[r1, c0:c1] = True
        walls[r0:r1, c0] = walls[r0:r1, c1] = True
        gap = int(rng.integers(c0, max(c0 + 1, c1 - 8)))
        walls[r0, gap : gap + 8] = False
    walls[0, :] = walls[-1, :] = walls[:, 0] = walls[:, -1] = True
    return walls


def grid_at(
    walls: np.ndarray, pose: np.ndarray, *, window_cells: int = 150
) -> tuple[np.ndarray, tuple[float, float]]:
    """The grid a robot at ``pose`` (map) would send: wall cells of the window around it that
    border a cell visible from it, cropped to their bounding box; ``(grid, origin_in_base)``."""
    x, y, yaw = (float(v) for v in pose)
    half = window_cells * RES_M / 2
    centres = (np.arange(window_cells) + 0.5) * RES_M - half
    bx, by = np.meshgrid(centres, centres)
    c, s = math.cos(yaw), math.sin(yaw)
    i = np.floor((y + s * bx + c * by) / RES_M).astype(np.int64)
    j = np.floor((x + c * bx - s * by) / RES_M).astype(np.int64)
    inside = (i >= 0) & (j >= 0) & (i < walls.shape[0]) & (j < walls.shape[1])
    window = np.zeros((window_cells, window_cells), dtype=bool)
    window[inside] = walls[i[inside], j[inside]]
    seen = local_raster(window, (-half, -half), RES_M, free_range_m=2 * half)
    full = np.zeros_like(window, dtype=np.int8)
    r0 = round((seen.origin_in_base[1] + half) / RES_M)
    c0 = round((seen.origin_in_base[0] + half) / RES_M)
    h, w = seen.cells.shape
    a0, a1 = max(r0, 0), min(r0 + h, window_cells)
    b0, b1 = max(c0, 0), min(c0 + w, window_cells)
    full[a0:a1, b0:b1] = seen.cells[a0 - r0 : a1 - r0, b0 - c0 : b1 - c0]
    free = full == FREE
    near_free = np.zeros_like(free)
    near_free[1:, :] |= free[:-1, :]
    near_free[:-1, :] |= free[1:, :]
    near_free[:, 1:] |= free[:, :-1]
    near_free[:, :-1] |= free[:, 1:]
    hits = (full == OCCUPIED) & near_free
    rr, cc = np.flatnonzero(hits.any(axis=1)), np.flatnonzero(hits.any(axis=0))
    if len(rr) == 0:
        return np.zeros((0, 0), dtype=bool), (-half, -half)
    crop = hits[rr[0] : rr[-1] + 1, cc[0] : cc[-1] + 1]
    return crop, (-half + cc[0] * RES_M, -half + rr[0] * RES_M)


def drive(
    rng: np.random.Generator, size_m: tuple[float, float], steps: int, *, stop_every: int = 0
) -> np.ndarray:
    """A random drive of ``steps`` poses, 0.8 m apart, inside the world (``(steps, 3)``);
    with ``stop_every`` the robot stands still for two nodes every so often."""
    p = np.array([rng.uniform(3, size_m[0] - 3), rng.uniform(3, size_m[1] - 3), rng.uniform(-3, 3)])
    out = []
    for k in range(steps):
        if not (stop_every and k % stop_every in (1, 2)):
            p = p + np.array([0.8 * math.cos(p[2]), 0.8 * math.sin(p[2]), rng.normal(0, 0.25)])
            p[0] = float(np.clip(p[0], 2, size_m[0] - 2))
            p[1] = float(np.clip(p[1], 2, size_m[1] - 2))
        out.append(p.copy())
    return np.stack(out)
