"""Synthetic 2D worlds and range scans with known truth, for loop-closing tests and benchmarks.

Not an estimation algorithm: it makes data whose answer is known. A world is a set of wall
segments ``(M, 4)`` rows ``(x0, y0, x1, y1)`` in a world frame (metres): buildings (boxes
with doorways), free-standing walls and small boxes (cars, bins). A scan casts ``n_beams``
rays over 360 deg from a pose and keeps the first hit of each (with Gaussian range noise), as
a vertical-surface grid sees walls from one side and nothing behind them (paper 4.3.3). Its
grid is the binary image of the hits around the pose, in the pose's ``base`` frame, like the
robot's ``VerticalSurfaceGrid`` (cell ``(r, c)`` covers ``origin + (c, r) * resolution``).

Ray casting is vectorized over rays x segments: ``O(beams * segments)``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from protocol.se2 import transform_points

__all__ = [
    "box_segments",
    "corridor_world",
    "random_world",
    "scan_grid",
    "scan_points",
]

FloatArray = NDArray[np.float64]


def box_segments(
    cx: float, cy: float, w: float, h: float, yaw: float = 0.0, *, door_m: float = 0.0,
    door_side: int = 0,
) -> FloatArray:  # fmt: skip
    """The four walls ``(K, 4)`` of a ``w`` x ``h`` rectangle centred at ``(cx, cy)`` rotated
    by ``yaw``; with ``door_m > 0`` wall ``door_side`` (0..3) gets a centred gap that wide."""
    corners = np.array([[-w / 2, -h / 2], [w / 2, -h / 2], [w / 2, h / 2], [-w / 2, h / 2]])
    segs = []
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        length = float(np.hypot(*(b - a)))
        if door_m > 0 and k == door_side and door_m < length - 0.2:
            u = (b - a) / length
            mid = (a + b) / 2
            segs.append([*a, *(mid - u * door_m / 2)])
            segs.append([*(mid + u * door_m / 2), *b])
        else:
            segs.append([*a, *b])
    s = np.array(segs, dtype=np.float64)
    pose = np.array([cx, cy, yaw])
    p0 = transform_points(pose, s[:, :2])
    p1 = transform_points(pose, s[:, 2:])
    return np.hstack([p0, p1])


def random_world(
    rng: np.random.Generator,
    *,
    size_m: float = 60.0,
    buildings: int = 10,
    walls: int = 12,
    boxes: int = 25,
) -> FloatArray:
    """A random urban-ish world in ``[-size/2, size/2]^2``: buildings with a doorway, free
    walls (fences) and small boxes (cars, bins), axis-aligned up to a few degrees."""
    half = size_m / 2
    segs: list[FloatArray] = []
    for _ in range(buildings):
        w, h = rng.uniform(4.0, 12.0, 2)
        c = rng.uniform(-half + 6, half - 6, 2)
        yaw = rng.choice([0.0, math.pi / 2]) + rng.normal(0.0, 0.03)
        segs.append(box_segments(c[0], c[1], w, h, yaw, door_m=1.2, door_side=int(rng.integers(4))))
    for _ in range(walls):
        a = rng.uniform(-half, half, 2)
        ang = rng.choice([0.0, math.pi / 2]) + rng.normal(0.0, 0.05)
        length = rng.uniform(2.0, 10.0)
        b = a + length * np.array([math.cos(ang), math.sin(ang)])
        segs.append(np.array([[*a, *b]]))
    for _ in range(boxes):
        c = rng.uniform(-half, half, 2)
        w, h = rng.uniform(0.4, 2.0), rng.uniform(0.4, 4.5)
        segs.append(box_segments(c[0], c[1], w, h, rng.uniform(-math.pi, math.pi)))
    return np.concatenate(segs)


def corridor_world(
    *, length_m: float = 30.0, width_m: float = 2.4, offset_m: tuple[float, float] = (0.0, 0.0)
) -> FloatArray:
    """A straight corridor along x (two long walls) with identical doorway alcoves every 6 m:
    a perceptually aliased place (every stretch of it looks the same)."""
    ox, oy = offset_m
    segs = []
    x = -length_m / 2
    door = 1.0
    while x < length_m / 2:
        x_end = min(x + 6.0, length_m / 2)
        # walls with a doorway in the middle of each 6 m stretch, alcove behind it
        mid = x + 3.0
        for side in (-1.0, 1.0):
            y = side * width_m / 2
            segs.append([x, y, mid - door / 2, y])
            segs.append([mid + door / 2, y, x_end, y])
            yb = y + side * 1.0
            segs.append([mid - door / 2, y, mid - door / 2, yb])
            segs.append([mid + door / 2, y, mid + door / 2, yb])
            segs.append([mid - door / 2, yb, mid + door / 2, yb])
        x = x_end
    s = np.array(segs, dtype=np.float64)
    s[:, [0, 2]] += ox
    s[:, [1, 3]] += oy
    return s


def scan_points(
    segments: FloatArray,
    world_from_base: FloatArray,
    *,
    n_beams: int = 720,
    max_range_m: float = 12.0,
    noise_m: float = 0.01,
    rng: np.random.Generator | None = None,
) -> FloatArray:
    """First hits ``(N, 2)`` in ``base`` of ``n_beams`` rays over 360 deg from
    ``world_from_base`` (beams with no hit within ``max_range_m`` are dropped)."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    pose = np.asarray(world_from_base, dtype=np.float64)
    if pose.shape != (3,) or not np.all(np.isfinite(pose)):
        raise ValueError(f"world_from_base must be a finite pose (3,), got {world_from_base!r}")
    if n_beams < 1 or not max_range_m > 0:
        raise ValueError("need n_beams >= 1 and max_range_m > 0")
    angles = pose[2] + np.arange(n_beams) * (2.0 * math.pi / n_beams)
    d = np.stack([np.cos(angles), np.sin(angles)], axis=1)  # (B, 2)
    p0 = seg[:, :2] - pose[:2]  # (M, 2) relative to the sensor
    e = seg[:, 2:] - seg[:, :2]  # (M, 2)
    # solve t * d = p0 + u * e for t >= 0, 0 <= u <= 1
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]  # (B, M)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p0[None, :, 0] * e[None, :, 1] - p0[None, :, 1] * e[None, :, 0]) / den
        u = (p0[None, :, 0] * d[:, None, 1] - p0[None, :, 1] * d[:, None, 0]) / den
    ok = (np.abs(den) > 1e-12) & (t > 1e-6) & (u >= 0.0) & (u <= 1.0)
    t = np.where(ok, t, np.inf)
    r = t.min(axis=1)
    hit = r < max_range_m
    if rng is not None and noise_m > 0:
        r = r + rng.normal(0.0, noise_m, r.shape)
    rel = angles[hit] - pose[2]
    return np.stack([r[hit] * np.cos(rel), r[hit] * np.sin(rel)], axis=1)


def scan_grid(
    points_in_base: FloatArray, *, size_cells: int = 150, resolution_m: float = 0.1
) -> tuple[NDArray[np.bool_], tuple[float, float]]:
    """The ``size_cells`` square binary grid of the points, centred on the base:
    ``(grid, origin_in_base)``; points outside it are dropped."""
    half = size_cells * resolution_m / 2
    pts = np.asarray(points_in_base, dtype=np.float64).reshape(-1, 2)
    cells = np.floor((pts + half) / resolution_m).astype(np.int64)
    ok = np.all((cells >= 0) & (cells < size_cells), axis=1)
    grid = np.zeros((size_cells, size_cells), dtype=bool)
    grid[cells[ok, 1], cells[ok, 0]] = True
    return grid, (-half, -half)
