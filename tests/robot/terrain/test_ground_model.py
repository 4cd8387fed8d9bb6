"""Ground model (paper 5.3, stage 1) against brute-force oracles."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.terrain.grid import GridGeometry
from robot.terrain.ground_model import cell_ground_bounds, ground_model, propagate_ground


def _chamfer(dr: int, dc: int) -> float:
    a, b = abs(dr), abs(dc)
    return (max(a, b) - min(a, b)) + math.sqrt(2) * min(a, b)


def test_cell_bounds_use_second_lowest_point() -> None:
    geo = GridGeometry((0.0, 0.0), 1.0, 2, 3)
    pts = np.array(
        [
            [0.5, 0.5, 3.0],
            [0.5, 0.5, -5.0],  # outlier: ignored, the second-lowest is used
            [0.5, 0.5, 1.0],
            [2.5, 1.5, 7.0],  # single point: its z
            [9.0, 0.5, -9.0],  # outside: ignored
        ]
    )
    b = cell_ground_bounds(pts, geo)
    assert b[0, 0] == 1.0
    assert b[1, 2] == 7.0
    assert np.isinf(b[0, 1]) and np.isinf(b[1, 0])


@pytest.mark.parametrize("seed", range(5))
def test_propagation_matches_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    rows, cols, res = 9, 11, 0.05
    bounds = np.full((rows, cols), np.inf)
    mask = rng.random((rows, cols)) < 0.15
    bounds[mask] = rng.uniform(-1, 1, mask.sum())
    got = propagate_ground(bounds, resolution_m=res, ground_slope_deg=20.0)
    k = math.tan(math.radians(20.0)) * res
    want = np.full((rows, cols), np.inf)
    src = np.argwhere(mask)
    for r in range(rows):
        for c in range(cols):
            for sr, sc in src:
                want[r, c] = min(want[r, c], bounds[sr, sc] + k * _chamfer(r - sr, c - sc))
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def _chamfer_cell_by_cell(g: np.ndarray, step: float, diag: float) -> np.ndarray:
    """The two-pass chamfer sweep one cell at a time (the kernel's form before session 13)."""
    rows, cols = g.shape
    for r in range(rows):
        for c in range(cols):
            v = g[r, c]
            if c > 0:
                v = min(v, g[r, c - 1] + step)
            if r > 0:
                v = min(v, g[r - 1, c] + step)
                if c > 0:
                    v = min(v, g[r - 1, c - 1] + diag)
                if c + 1 < cols:
                    v = min(v, g[r - 1, c + 1] + diag)
            g[r, c] = v
    for r in range(rows - 1, -1, -1):
        for c in range(cols - 1, -1, -1):
            v = g[r, c]
            if c + 1 < cols:
                v = min(v, g[r, c + 1] + step)
            if r + 1 < rows:
                v = min(v, g[r + 1, c] + step)
                if c + 1 < cols:
                    v = min(v, g[r + 1, c + 1] + diag)
                if c > 0:
                    v = min(v, g[r + 1, c - 1] + diag)
            g[r, c] = v
    return g


@pytest.mark.parametrize("frac", [0.02, 0.3, 0.9])
def test_propagation_equals_the_cell_by_cell_sweep_exactly(frac: float) -> None:
    # the row-at-a-time kernel takes each cell's minimum over the same candidates
    rng = np.random.default_rng(int(frac * 100))
    bounds = np.full((37, 53), np.inf)
    mask = rng.random(bounds.shape) < frac
    bounds[mask] = rng.normal(0.0, 0.3, mask.sum())
    got = propagate_ground(bounds, resolution_m=0.05, ground_slope_deg=20.0)
    rise = math.tan(math.radians(20.0)) * 0.05
    want = _chamfer_cell_by_cell(bounds.copy(), rise, rise * math.sqrt(2.0))
    np.testing.assert_array_equal(got, want)


def test_ground_under_canopy_stays_low() -> None:
    """Canopy points above observed ground do not raise the ground estimate."""
    geo = GridGeometry((0.0, 0.0), 0.1, 10, 10)
    xy = np.stack(np.meshgrid(np.arange(10) * 0.1 + 0.05, np.arange(10) * 0.1 + 0.05), -1)
    xy = xy.reshape(-1, 2)
    ground = np.c_[xy, np.zeros(len(xy))]
    canopy = np.c_[xy, np.full(len(xy), 1.8)]
    g = ground_model(np.vstack([ground, ground, canopy]), geo)
    assert np.all(g == 0.0)


def test_slope_prior_bounds_unobserved_cells() -> None:
    geo = GridGeometry((0.0, 0.0), 0.1, 1, 30)
    g = ground_model(np.array([[0.05, 0.05, 0.0], [0.05, 0.05, 0.0]]), geo, ground_slope_deg=20.0)
    np.testing.assert_allclose(g[0], math.tan(math.radians(20)) * 0.1 * np.arange(30))


def test_bad_slope_is_rejected() -> None:
    with pytest.raises(ValueError, match="ground_slope_deg"):
        propagate_ground(np.zeros((2, 2)), resolution_m=0.1, ground_slope_deg=95.0)
