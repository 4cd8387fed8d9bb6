"""Grid Dijkstra (paper 5.4) against scipy.sparse.csgraph.dijkstra on the same graph."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.csgraph import dijkstra as scipy_dijkstra

from robot.planning.dijkstra import dijkstra_grid, grid_graph


def _random_cost(rng: np.random.Generator, rows: int, cols: int) -> np.ndarray:
    cost = np.ones((rows, cols))
    cost[rng.random((rows, cols)) < 0.25] = np.inf
    soft = (rng.random((rows, cols)) < 0.3) & np.isfinite(cost)
    cost[soft] = rng.uniform(1.0, 4.0, soft.sum())
    return cost


def _path_cost(cost: np.ndarray, path: np.ndarray, res: float) -> float:
    total = 0.0
    for (r0, c0), (r1, c1) in zip(path[:-1], path[1:], strict=True):
        dr, dc = abs(r1 - r0), abs(c1 - c0)
        assert max(dr, dc) == 1, "consecutive cells must be 8-neighbours"
        if dr and dc:  # no corner cutting
            assert np.isfinite(cost[r0, c1]) and np.isfinite(cost[r1, c0])
        step = res * (math.sqrt(2) if dr and dc else 1.0)
        total += step * 0.5 * (cost[r0, c0] + cost[r1, c1])
    return total


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 100_000),
    rows=st.integers(1, 25),
    cols=st.integers(1, 25),
    astar=st.booleans(),
)
def test_equals_scipy(seed: int, rows: int, cols: int, astar: bool) -> None:
    rng = np.random.default_rng(seed)
    cost = _random_cost(rng, rows, cols)
    start = (int(rng.integers(rows)), int(rng.integers(cols)))
    goal = (int(rng.integers(rows)), int(rng.integers(cols)))
    res = 0.05
    got = dijkstra_grid(cost, start, goal, resolution_m=res, astar=astar)
    ref = scipy_dijkstra(grid_graph(cost, resolution_m=res), indices=start[0] * cols + start[1])
    want = ref[goal[0] * cols + goal[1]]
    if not (np.isfinite(cost[start]) and np.isfinite(cost[goal])) or not np.isfinite(want):
        assert not got.found and len(got.path_cells) == 0
        return
    assert got.length_m == pytest.approx(want, rel=1e-12, abs=1e-12)
    assert tuple(got.path_cells[0]) == start and tuple(got.path_cells[-1]) == goal
    assert _path_cost(cost, got.path_cells, res) == pytest.approx(want, rel=1e-12, abs=1e-12)
    if not astar:  # every settled cell carries scipy's distance
        settled = np.isfinite(got.distance_m)
        np.testing.assert_allclose(got.distance_m[settled], ref.reshape(rows, cols)[settled])


@pytest.mark.parametrize("astar", [False, True])
def test_large_grid_equals_scipy(astar: bool) -> None:
    rng = np.random.default_rng(5)
    cost = _random_cost(rng, 200, 200)
    cost[0, 0] = cost[199, 199] = 1.0
    got = dijkstra_grid(cost, (0, 0), (199, 199), resolution_m=0.05, astar=astar)
    ref = scipy_dijkstra(grid_graph(cost, resolution_m=0.05), indices=0)[-1]
    assert got.length_m == pytest.approx(ref, rel=1e-12)


def test_walled_off_goal_is_not_found() -> None:
    cost = np.ones((10, 10))
    cost[:, 5] = np.inf
    got = dijkstra_grid(cost, (0, 0), (9, 9))
    assert not got.found and got.path_cells.shape == (0, 2)


def test_diagonal_gap_is_closed() -> None:
    cost = np.ones((2, 2))
    cost[0, 1] = cost[1, 0] = np.inf
    assert not dijkstra_grid(cost, (0, 0), (1, 1)).found


def test_bad_input_names_the_problem() -> None:
    with pytest.raises(ValueError, match="goal cell"):
        dijkstra_grid(np.ones((3, 3)), (0, 0), (3, 0))
    with pytest.raises(ValueError, match="start cell"):
        dijkstra_grid(np.ones((3, 3)), (-1, 0), (1, 1))
    with pytest.raises(ValueError, match="cost"):
        dijkstra_grid(np.full((3, 3), np.nan), (0, 0), (1, 1))
    with pytest.raises(ValueError, match="cost"):
        dijkstra_grid(np.full((3, 3), 0.5), (0, 0), (1, 1))
