"""Correlative matching: branch and bound equals brute force; known transforms are found."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.loops.correlative_matcher import (
    CorrelativeMatcher,
    MatcherConfig,
    brute_force_match,
    grid_points,
)
from protocol.se2 import inverse, transform_points

RES = 0.1


def walls(rng: np.random.Generator, n: int = 10, extent: float = 14.0) -> np.ndarray:
    """Points sampled densely along random wall segments, in a world frame (metres)."""
    pts = []
    for _ in range(n):
        a = rng.uniform(-extent / 2, extent / 2, 2)
        ang = rng.choice([0.0, math.pi / 2]) + rng.normal(0, 0.05)
        length = rng.uniform(2.0, 8.0)
        t = np.arange(0, length, RES / 3)
        pts.append(a + np.outer(t, [math.cos(ang), math.sin(ang)]))
    return np.concatenate(pts)


def rasterize(
    points: np.ndarray, origin: tuple[float, float], shape: tuple[int, int]
) -> np.ndarray:
    g = np.zeros(shape, dtype=bool)
    c = np.floor((points[:, 0] - origin[0]) / RES).astype(int)
    r = np.floor((points[:, 1] - origin[1]) / RES).astype(int)
    ok = (r >= 0) & (r < shape[0]) & (c >= 0) & (c < shape[1])
    g[r[ok], c[ok]] = True
    return g


def scene_pair(seed: int, a_from_b: np.ndarray, *, noise_m: float = 0.02):
    """Reference grid around A (= world origin) and query grid around B = a_from_b."""
    rng = np.random.default_rng(seed)
    world = walls(rng)
    origin = (-7.5, -7.5)
    ref_grid = rasterize(world + rng.normal(0, noise_m, world.shape), origin, (150, 150))
    in_b = transform_points(inverse(a_from_b), world) + rng.normal(0, noise_m, world.shape)
    query_grid = rasterize(in_b, origin, (150, 150))
    return ref_grid, query_grid, origin


@pytest.mark.parametrize("seed", range(6))
def test_branch_and_bound_equals_brute_force_on_structured_pairs(seed: int) -> None:
    truth = np.array([0.8, -1.1, math.radians(12.0)])
    ref_grid, query_grid, origin = scene_pair(seed, truth)
    matcher = CorrelativeMatcher(
        MatcherConfig(search_xy_m=1.5, search_yaw_rad=math.radians(20), max_points=150)
    )
    ref = matcher.reference_table(ref_grid, origin_m=origin, resolution_m=RES)
    pts = grid_points(query_grid, origin_m=origin, resolution_m=RES)
    guess = truth + np.array([0.4, -0.3, math.radians(-6)])
    bnb = matcher.match(ref, pts, guess)
    brute = brute_force_match(matcher, ref, pts, guess)
    assert bnb is not None and brute is not None
    assert bnb.score == brute.score
    assert np.array_equal(bnb.a_from_b_discrete, brute.a_from_b_discrete)
    assert bnb.nodes_evaluated < brute.nodes_evaluated / 5  # the bound prunes
    # and it is the right answer
    assert np.hypot(*(bnb.a_from_b[:2] - truth[:2])) < 0.1
    assert abs(bnb.a_from_b[2] - truth[2]) < math.radians(1.5)
    assert 0.5 < bnb.normalized_score <= 1.0


@pytest.mark.parametrize("seed", range(10))
def test_branch_and_bound_equals_brute_force_on_random_grids(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    ref_grid = rng.random((40, 40)) < 0.08
    query_grid = rng.random((40, 40)) < 0.05
    matcher = CorrelativeMatcher(MatcherConfig(search_xy_m=0.8, search_yaw_rad=math.radians(10)))
    ref = matcher.reference_table(ref_grid, origin_m=(-2.0, -2.0), resolution_m=RES)
    pts = grid_points(query_grid, origin_m=(-2.0, -2.0), resolution_m=RES)
    guess = np.array([0.1, 0.0, 0.05])
    bnb = matcher.match(ref, pts, guess)
    brute = brute_force_match(matcher, ref, pts, guess)
    assert bnb is not None and brute is not None
    assert (bnb.score, *bnb.a_from_b_discrete) == (brute.score, *brute.a_from_b_discrete)


def test_min_score_prunes_and_agrees_with_brute_force() -> None:
    truth = np.array([0.3, 0.2, 0.1])
    ref_grid, query_grid, origin = scene_pair(7, truth)
    _, unrelated, _ = scene_pair(8, truth)  # another place entirely
    matcher = CorrelativeMatcher(MatcherConfig(search_xy_m=1.0, search_yaw_rad=math.radians(10)))
    ref = matcher.reference_table(ref_grid, origin_m=origin, resolution_m=RES)
    good = grid_points(query_grid, origin_m=origin, resolution_m=RES)
    bad = grid_points(unrelated, origin_m=origin, resolution_m=RES)
    free = matcher.match(ref, good, np.zeros(3))
    pruned = matcher.match(ref, good, np.zeros(3), min_score=0.6)
    assert free is not None and pruned is not None
    assert pruned.score == free.score and pruned.nodes_evaluated <= free.nodes_evaluated
    # a place that does not match is rejected after far fewer evaluations
    unpruned_bad = matcher.match(ref, bad, np.zeros(3))
    assert unpruned_bad is not None and unpruned_bad.normalized_score < 0.6
    assert matcher.match(ref, bad, np.zeros(3), min_score=0.6) is None
    assert brute_force_match(matcher, ref, bad, np.zeros(3), min_score=0.6) is None
    with pytest.raises(ValueError, match="min_score"):
        matcher.match(ref, good, np.zeros(3), min_score=1.5)


def test_covariance_is_positive_definite_and_small_for_a_good_match() -> None:
    truth = np.array([-0.5, 0.7, math.radians(-8.0)])
    ref_grid, query_grid, origin = scene_pair(42, truth)
    matcher = CorrelativeMatcher()
    ref = matcher.reference_table(ref_grid, origin_m=origin, resolution_m=RES)
    result = matcher.match(
        ref, grid_points(query_grid, origin_m=origin, resolution_m=RES), np.zeros(3)
    )
    assert np.all(np.linalg.eigvalsh(result.covariance) > 0)
    assert math.sqrt(result.covariance[0, 0]) < 0.1 and math.sqrt(result.covariance[2, 2]) < 0.05
    assert np.hypot(*(result.a_from_b[:2] - truth[:2])) < 0.1


def test_bad_input_is_refused() -> None:
    matcher = CorrelativeMatcher()
    with pytest.raises(ValueError, match="non-empty 2-D"):
        matcher.reference_table(np.zeros(5, bool), origin_m=(0.0, 0.0), resolution_m=RES)
    ref = matcher.reference_table(np.eye(20, dtype=bool), origin_m=(0.0, 0.0), resolution_m=RES)
    with pytest.raises(ValueError, match="finite"):
        matcher.match(ref, np.array([[np.nan, 0.0]]), np.zeros(3))
    with pytest.raises(ValueError, match="no points"):
        matcher.match(ref, np.zeros((0, 2)), np.zeros(3))
    with pytest.raises(ValueError, match="guess"):
        matcher.match(ref, np.ones((3, 2)), np.array([0.0, math.inf, 0.0]))
    with pytest.raises(ValueError, match="outlier"):
        MatcherConfig(outlier_likelihood=0.0)
