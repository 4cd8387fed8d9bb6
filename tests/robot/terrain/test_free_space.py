"""Free-space evidence along LIDAR beams (robot.terrain.free_space)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.terrain.free_space import ray_floor
from robot.terrain.grid import GridGeometry

GEO = GridGeometry((-5.0, -5.0), 0.1, 100, 100)


def _brute(points, sensors, ground, end_margin):  # type: ignore[no-untyped-def]
    out = np.full(GEO.shape, np.inf)
    for p, s in zip(points, sensors, strict=True):
        d = math.hypot(p[0] - s[0], p[1] - s[1])
        for u in np.arange(0.0, max(d - end_margin, 0.0), 0.001):  # 1 mm steps
            t = u / d
            x, y, z = s + t * (p - s)
            r, c = GEO.cell_index((x, y))
            if 0 <= r < GEO.rows and 0 <= c < GEO.cols:
                out[r, c] = min(out[r, c], z - ground[r, c])
    return np.maximum(out, 0.0)


def test_lowest_beam_per_cell_matches_fine_sampling() -> None:
    rng = np.random.default_rng(2)
    n = 40
    ang = rng.uniform(-math.pi, math.pi, n)
    dist = rng.uniform(0.5, 9.0, n)
    points = np.stack([dist * np.cos(ang), dist * np.sin(ang), rng.uniform(-0.1, 1.0, n)], 1)
    sensors = np.tile([0.2, 0.0, 0.52], (n, 1)) + rng.normal(0.0, 0.05, (n, 3))
    ground = rng.uniform(-0.05, 0.05, GEO.shape)
    got = ray_floor(points, sensors, GEO, ground, end_margin_m=0.15)
    ref = _brute(points, sensors, ground, 0.15)
    # exact traversal: the same cells (but for corners the 1 mm steps just miss) and the
    # same lowest heights (the continuous minimum is at most 1 mm of slope below)
    seen, fine = np.isfinite(got), np.isfinite(ref)
    assert (fine & ~seen).sum() == 0
    assert (seen & ~fine).sum() <= 0.01 * fine.sum()
    both = seen & fine
    slope = float(np.max(np.abs(points[:, 2] - sensors[:, 2]) / dist))
    assert np.all(got[both] <= ref[both] + 1e-9)
    assert np.all(got[both] >= ref[both] - slope * 0.0011 - 1e-9)


def test_the_end_of_each_beam_says_nothing() -> None:
    sensor = np.array([[0.0, 0.0, 0.5]])
    point = np.array([[3.0, 0.05, 0.5]])  # a level beam, 3 m, along a row of cells
    ground = np.zeros(GEO.shape)
    got = ray_floor(point, sensor, GEO, ground, end_margin_m=0.5)
    row = GEO.cell_index((0.0, 0.05))[0]
    crossed = np.flatnonzero(np.isfinite(got[row]))
    xs = GEO.center_of(np.stack([np.full(len(crossed), row), crossed], 1))[:, 0]
    assert xs.min() < 0.1 and 2.4 < xs.max() < 2.6  # stops 0.5 m before the return
    assert np.allclose(got[row, crossed], 0.5)
    assert np.isinf(got).sum() == got.size - len(crossed)


def test_bad_input_names_the_problem() -> None:
    ground = np.zeros(GEO.shape)
    with pytest.raises(ValueError, match="points_in_odom"):
        ray_floor(np.zeros((3, 2)), np.zeros(3), GEO, ground, end_margin_m=0.1)
    with pytest.raises(ValueError, match="sensors_in_odom"):
        ray_floor(np.zeros((1, 3)), np.full(3, np.nan), GEO, ground, end_margin_m=0.1)
    with pytest.raises(ValueError, match="ground_m"):
        ray_floor(np.zeros((1, 3)), np.zeros(3), GEO, np.zeros((2, 2)), end_margin_m=0.1)
    with pytest.raises(ValueError, match="end_margin_m"):
        ray_floor(np.zeros((1, 3)), np.zeros(3), GEO, ground, end_margin_m=-1.0)
