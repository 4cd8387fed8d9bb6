"""Matching consecutive sweeps' obstacles: the displacement the wheels cannot see."""

from __future__ import annotations

import numpy as np
import pytest

from robot.odometry.scan_displacement import match_translation
from robot.terrain.grid import GridGeometry


def _scene(geo: GridGeometry, offset: tuple[float, float]) -> np.ndarray:
    """Pillars and a wall corner, seen from a robot whose odometry is off by ``offset``."""
    grid = np.zeros(geo.shape, dtype=bool)
    rng = np.random.default_rng(0)
    pts = [rng.uniform(-7, 7, 2) for _ in range(25)]
    pts += [np.array([x, 6.0]) for x in np.arange(-6, 6, 0.05)]
    pts += [np.array([6.0, y]) for y in np.arange(-6, 6, 0.05)]
    for p in pts:
        r, c = geo.cell_index(p + np.asarray(offset))
        if 0 <= r < geo.rows and 0 <= c < geo.cols:
            grid[r, c] = True
    return grid


@pytest.mark.parametrize("error", [(0.0, 0.0), (0.3, 0.0), (-0.15, 0.2), (0.45, -0.1)])
def test_recovers_the_odometry_error_between_sweeps(error: tuple[float, float]) -> None:
    prev_geo = GridGeometry.centered((0.0, 0.0), resolution_m=0.05, rows=400, cols=400)
    geo = GridGeometry.centered((1.0, 0.2), resolution_m=0.05, rows=400, cols=400)
    prev = _scene(prev_geo, (0.0, 0.0))
    now = _scene(geo, error)  # the newer sweep placed everything `error` too far
    match = match_translation(
        prev,
        prev_geo,
        now,
        geo,
        center_in_odom=(1.0, 0.2),
        direction_in_odom=(1.0, 0.0),
        radius_m=8.0,
        max_shift_m=0.5,
    )
    assert match is not None
    assert match.shift_in_odom == pytest.approx((-error[0], -error[1]), abs=0.051)
    assert match.agreeing >= 0.8 * match.cells


def test_a_wall_along_the_motion_cannot_tell_how_far_and_is_refused() -> None:
    geo = GridGeometry.centered((0.0, 0.0), resolution_m=0.05, rows=400, cols=400)
    wall = np.zeros(geo.shape, dtype=bool)
    wall[geo.cell_index((0.0, 2.0))[0], :] = True  # one long wall parallel to x
    match = match_translation(
        wall,
        geo,
        wall,
        geo,
        center_in_odom=(0.0, 0.0),
        direction_in_odom=(1.0, 0.0),
        radius_m=8.0,
        max_shift_m=0.5,
    )
    assert match is None
    empty = np.zeros(geo.shape, dtype=bool)  # nothing to see: nothing measured
    assert (
        match_translation(
            empty,
            geo,
            empty,
            geo,
            center_in_odom=(0.0, 0.0),
            direction_in_odom=(1.0, 0.0),
            radius_m=8.0,
            max_shift_m=0.5,
        )
        is None
    )
    with pytest.raises(ValueError, match="direction"):
        match_translation(
            wall,
            geo,
            wall,
            geo,
            center_in_odom=(0.0, 0.0),
            direction_in_odom=(0.0, 0.0),
            radius_m=8.0,
            max_shift_m=0.5,
        )
