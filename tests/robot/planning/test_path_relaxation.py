"""Bounded clearance relaxation and smoothing (paper 5.4, Fig. 16d)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from robot.planning.config_space import configuration_space
from robot.planning.dijkstra import dijkstra_grid
from robot.planning.path_relaxation import (
    clearance_field,
    path_clearance,
    relax_path,
    segments_free,
)
from robot.planning.path_smoothing import smooth_path

RES = 0.05
RADIUS = 0.3
TARGET = 0.6


def _doorway() -> np.ndarray:
    """10 x 10 m room split by a wall at row 100 with a 1.6 m doorway."""
    obstacle = np.zeros((200, 200), dtype=bool)
    obstacle[0, :] = obstacle[-1, :] = obstacle[:, 0] = obstacle[:, -1] = True
    obstacle[99:101, :] = True
    obstacle[99:101, 90:122] = False  # doorway: columns 90..121 (1.6 m)
    return obstacle


def _hallway() -> np.ndarray:
    """A 4 m wide hallway along the columns."""
    obstacle = np.zeros((120, 300), dtype=bool)
    obstacle[:20, :] = True
    obstacle[100:, :] = True
    return obstacle


def _dijkstra_path(obstacle, start, goal):  # type: ignore[no-untyped-def]
    blocked = configuration_space(obstacle, robot_radius_m=RADIUS, resolution_m=RES)
    cost = np.where(blocked, np.inf, 1.0)
    found = dijkstra_grid(cost, start, goal, resolution_m=RES)
    assert found.found
    return found.path_cells.astype(float), blocked, clearance_field(obstacle, resolution_m=RES)


def _relax(path, clearance, blocked):  # type: ignore[no-untyped-def]
    return relax_path(
        path,
        clearance,
        blocked,
        resolution_m=RES,
        target_clearance_m=TARGET,
        step_m=0.025,
        max_offset_m=0.8,
        iterations=60,
    )


def test_clearance_field_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    obstacle = rng.random((30, 40)) < 0.02
    got = clearance_field(obstacle, resolution_m=RES)
    obs = np.argwhere(obstacle)
    rr, cc = np.mgrid[0:30, 0:40]
    d = np.sqrt(((rr[..., None] - obs[:, 0]) ** 2 + (cc[..., None] - obs[:, 1]) ** 2).min(-1))
    np.testing.assert_allclose(got, d * RES, atol=1e-3 * RES)


def test_relaxation_centres_the_doorway_and_never_loses_clearance() -> None:
    obstacle = _doorway()
    path, blocked, clearance = _dijkstra_path(obstacle, (20, 20), (180, 30))
    before = path_clearance(path, clearance)
    relaxed = _relax(path, clearance, blocked)
    after = path_clearance(relaxed, clearance)
    assert np.all(after >= before - 1e-12)
    assert segments_free(relaxed, blocked)
    assert np.array_equal(relaxed[[0, -1]], path[[0, -1]])
    # Dijkstra grazes the jamb at the robot radius; relaxation brings the crossing to the
    # middle of the 1.6 m doorway (0.8 m from both jambs, above the 0.6 m target).
    crossing = np.abs(relaxed[:, 0] - 100) < 3
    assert before[np.abs(path[:, 0] - 100) < 3].min() < RADIUS + 2 * RES
    assert after[crossing].min() >= TARGET - RES


def test_relaxation_is_bounded_in_a_wide_hallway() -> None:
    obstacle = _hallway()
    path, blocked, clearance = _dijkstra_path(obstacle, (30, 10), (30, 290))
    relaxed = _relax(path, clearance, blocked)
    after = path_clearance(relaxed, clearance)
    middle = slice(30, len(relaxed) - 30)
    # Reaches the target clearance but is not pushed to the hallway's centre (2 m).
    assert after[middle].min() >= TARGET - RES
    assert after[middle].max() <= TARGET + 2 * RES


def test_smoothing_keeps_clearance_and_reduces_jitter() -> None:
    obstacle = _doorway()
    path, blocked, clearance = _dijkstra_path(obstacle, (20, 20), (180, 150))
    relaxed = _relax(path, clearance, blocked)
    before = path_clearance(relaxed, clearance)
    smooth = smooth_path(relaxed, clearance, blocked, target_clearance_m=TARGET, iterations=100)
    after = path_clearance(smooth, clearance)
    assert np.all(after >= np.minimum(TARGET, before) - 1e-9)
    assert segments_free(smooth, blocked)
    assert np.array_equal(smooth[[0, -1]], relaxed[[0, -1]])

    def turning(p: np.ndarray) -> float:
        d = np.diff(p, axis=0)
        a = np.arctan2(d[:, 0], d[:, 1])
        return float(np.abs(np.angle(np.exp(1j * np.diff(a)))).sum())

    assert turning(smooth) < 0.5 * turning(relaxed)


def test_bad_input_names_the_problem() -> None:
    blocked = np.zeros((5, 5), dtype=bool)
    clearance = np.ones((5, 5))
    with pytest.raises(ValueError, match="path"):
        relax_path(
            np.zeros((3, 3)),
            clearance,
            blocked,
            resolution_m=RES,
            target_clearance_m=1,
            step_m=0.1,
            max_offset_m=1,
            iterations=1,
        )
    with pytest.raises(ValueError, match="path"):
        smooth_path(np.array([[np.nan, 0.0]]), clearance, blocked, target_clearance_m=1)
    with pytest.raises(ValueError, match="clearance_m"):
        smooth_path(np.zeros((2, 2)), np.ones((4, 4)), blocked, target_clearance_m=1)
    with pytest.raises(ValueError, match="obstacle"):
        clearance_field(np.zeros((3, 3)), resolution_m=RES)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 100_000))
def test_relax_then_smooth_on_random_maps(seed: int) -> None:
    """Collision-free, endpoints fixed, and every vertex keeps at least
    min(target, its clearance on Dijkstra's path)."""
    rng = np.random.default_rng(seed)
    obstacle = np.zeros((80, 80), dtype=bool)
    for _ in range(int(rng.integers(3, 12))):
        r, c = rng.integers(0, 80, 2)
        h, w = rng.integers(2, 15, 2)
        obstacle[r : r + h, c : c + w] = True
    blocked = configuration_space(obstacle, robot_radius_m=RADIUS, resolution_m=RES)
    free = np.argwhere(~blocked)
    if len(free) < 2:
        return
    start, goal = (tuple(int(v) for v in free[i]) for i in rng.choice(len(free), 2))
    found = dijkstra_grid(np.where(blocked, np.inf, 1.0), start, goal, resolution_m=RES)  # type: ignore[arg-type]
    if not found.found:
        return
    clearance = clearance_field(obstacle, resolution_m=RES)
    path = found.path_cells.astype(float)
    before = path_clearance(path, clearance)
    final = smooth_path(
        _relax(path, clearance, blocked), clearance, blocked, target_clearance_m=TARGET
    )
    assert segments_free(final, blocked)
    assert np.array_equal(final[[0, -1]], path[[0, -1]])
    assert np.all(path_clearance(final, clearance) >= np.minimum(TARGET, before) - 1e-9)
