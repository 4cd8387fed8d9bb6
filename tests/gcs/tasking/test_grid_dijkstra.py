"""Bounded grid Dijkstra against scipy.sparse.csgraph.dijkstra on the same graph."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from gcs.tasking.grid_dijkstra import grid_distances


def _graph(passable: np.ndarray, res: float) -> sp.csr_matrix:
    rows, cols = passable.shape
    a, b, w = [], [], []
    for r in range(rows):
        for c in range(cols):
            if not passable[r, c]:
                continue
            for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1), (-1, -1), (-1, 1), (1, -1), (1, 1)):
                rr, cc = r + dr, c + dc
                if not (0 <= rr < rows and 0 <= cc < cols) or not passable[rr, cc]:
                    continue
                if dr and dc and not (passable[r, cc] and passable[rr, c]):
                    continue
                a.append(r * cols + c)
                b.append(rr * cols + cc)
                w.append(res * (math.sqrt(2) if dr and dc else 1.0))
    return sp.csr_matrix((w, (a, b)), shape=(rows * cols, rows * cols))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_scipy_with_and_without_limit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    passable = rng.random((30, 40)) > 0.3
    passable[12, 17] = True
    g = _graph(passable, 0.5)
    ref = dijkstra(g, indices=12 * 40 + 17).reshape(30, 40)
    cells = np.argwhere(np.ones((30, 40), dtype=bool))
    got = grid_distances(passable, (12, 17), resolution_m=0.5)
    full = got.at(cells).reshape(30, 40)
    assert np.allclose(np.nan_to_num(full, posinf=-1), np.nan_to_num(ref, posinf=-1))
    lim = dijkstra(g, indices=12 * 40 + 17, limit=6.0).reshape(30, 40)
    got = grid_distances(passable, (12, 17), resolution_m=0.5, limit_m=6.0)
    assert got.distance_m.shape == (26, 27)  # only the window the limit allows is searched
    within = got.at(cells).reshape(30, 40)
    assert np.allclose(np.nan_to_num(within, posinf=-1), np.nan_to_num(lim, posinf=-1))
    # the path is a chain of neighbours whose length is the distance
    for dist in (full, within):
        goal = tuple(int(v) for v in np.argwhere(np.isfinite(dist))[-1])
        res = got if dist is within else grid_distances(passable, (12, 17), resolution_m=0.5)
        path = res.path_cells(goal)  # type: ignore[arg-type]
        steps = np.hypot(*np.diff(path, axis=0).T) * 0.5
        assert path[0].tolist() == [12, 17] and path[-1].tolist() == list(goal)
        assert steps.sum() == pytest.approx(dist[goal])


def test_bad_start_is_named() -> None:
    with pytest.raises(ValueError, match="outside the grid"):
        grid_distances(np.ones((3, 3), bool), (5, 0), resolution_m=1.0)
