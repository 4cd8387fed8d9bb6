"""Up-detector (paper 5.3, Eq. 2) against a brute-force pairwise oracle."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robot.terrain.grid import GridGeometry
from robot.terrain.up_detector import filter_height_range, up_detector


def _brute(z_min, z_max, a, b, iterations, fill=None):  # type: ignore[no-untyped-def]
    """A is an obstacle iff z_max(A) - (z_low(B) + a*l) > b for some B within Manhattan
    distance iterations + 1 (B = A included with l = 0)."""
    low = z_min if fill is None else np.where(np.isfinite(z_min), z_min, fill)
    rows, cols = z_min.shape
    reach = iterations + 1
    out = np.zeros((rows, cols), dtype=bool)
    for r in range(rows):
        for c in range(cols):
            if not np.isfinite(z_max[r, c]):
                continue
            best = np.inf
            for rr in range(max(0, r - reach), min(rows, r + reach + 1)):
                for cc in range(max(0, c - reach), min(cols, c + reach + 1)):
                    ell = abs(rr - r) + abs(cc - c)
                    if ell <= reach:
                        best = min(best, low[rr, cc] + a * ell)
            out[r, c] = z_max[r, c] - best > b
    return out


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    iterations=st.integers(0, 4),
    fill=st.booleans(),
)
def test_message_passing_equals_brute_force(seed: int, iterations: int, fill: bool) -> None:
    rng = np.random.default_rng(seed)
    rows, cols = 8, 9
    observed = rng.random((rows, cols)) < 0.6
    lo = rng.uniform(0, 0.3, (rows, cols))
    hi = lo + rng.uniform(0, 0.2, (rows, cols))
    z_min = np.where(observed, lo, np.inf)
    z_max = np.where(observed, hi, -np.inf)
    ground = rng.uniform(-0.1, 0.2, (rows, cols)) if fill else None
    got = up_detector(
        z_min, z_max, slope_per_cell_m=0.02, step_m=0.05, iterations=iterations, ground_m=ground
    )
    want = _brute(z_min, z_max, 0.02, 0.05, iterations, ground)
    np.testing.assert_array_equal(got, want)


def test_marks_only_the_higher_cell_of_a_step() -> None:
    z = np.array([[0.0, 0.0, 0.0, 0.2, 0.2, 0.2]])
    got = up_detector(z, z, slope_per_cell_m=0.02, step_m=0.05, iterations=2)
    # The low side is never marked; the top cells within reach of the step are.
    assert not got[0, :3].any()
    assert got[0, 3:].all()


def test_slope_below_the_climbable_slope_is_drivable() -> None:
    z = (np.arange(40) * 0.015)[None, :]  # rise 1.5 cm per cell, a = 2 cm
    assert not up_detector(z, z, slope_per_cell_m=0.02, step_m=0.03, iterations=2).any()


def test_filter_drops_overhead_and_below_ground_points() -> None:
    geo = GridGeometry((0.0, 0.0), 1.0, 1, 2)
    ground = np.array([[0.0, 0.5]])
    pts = np.array([[0.5, 0.5, 0.3], [0.5, 0.5, 1.9], [0.5, 0.5, -0.2], [1.5, 0.5, 0.6]])
    z_min, z_max = filter_height_range(pts, geo, ground, overhead_clearance_m=1.0)
    assert z_min[0, 0] == 0.3 and z_max[0, 0] == 0.3
    assert z_min[0, 1] == 0.6 and z_max[0, 1] == 0.6


def test_bad_input_names_the_problem() -> None:
    with pytest.raises(ValueError, match="z_min"):
        up_detector(np.zeros((2, 2)), np.zeros((3, 2)), slope_per_cell_m=0, step_m=0, iterations=1)
    with pytest.raises(ValueError, match="iterations"):
        up_detector(np.zeros((2, 2)), np.zeros((2, 2)), slope_per_cell_m=0, step_m=0, iterations=-1)
    with pytest.raises(ValueError, match="ground_m"):
        filter_height_range(
            np.zeros((1, 3)),
            GridGeometry((0, 0), 1, 2, 2),
            np.zeros((3, 3)),
            overhead_clearance_m=1,
        )
