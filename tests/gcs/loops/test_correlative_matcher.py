"""Correlative matching: branch and bound equals brute force; known transforms are found."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from gcs.loops.correlative_matcher import (
    CorrelativeMatcher,
    MatcherConfig,
    brute_force_match,
    grid_points,
    points_grid,
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


# ---- tables, realistic scenes and real logs --------------------------------------------------


def test_pyramid_levels_are_sliding_maxima_of_the_kernel_table() -> None:
    """Level 0 is the quantized kernel of the Euclidean distance to the nearest wall (checked
    against OpenCV's exact distance transform); level k is the 2^k x 2^k forward sliding
    maximum of level 0 over the whole zero-padded table."""
    import cv2

    rng = np.random.default_rng(3)
    grid = rng.random((37, 53)) < 0.03
    cfg = MatcherConfig(search_xy_m=0.8)
    table = CorrelativeMatcher(cfg).reference_table(grid, origin_m=(0.0, 0.0), resolution_m=RES)
    dist = cv2.distanceTransform((~grid).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    eps = cfg.outlier_likelihood
    loglik = np.log(np.exp(-0.5 * (dist * RES / cfg.sigma_m) ** 2) + eps)
    lo, hi = math.log(eps), math.log(1 + eps)
    expected0 = np.round(255 * (loglik - lo) / (hi - lo)).astype(np.uint8)
    p = table.pad
    level0 = table.level(0)
    assert np.array_equal(level0[p : p + 37, p : p + 53], expected0)
    assert level0.sum() == expected0.sum()  # nothing outside the grid
    for k in range(1, table.levels):
        win = 1 << k
        padded = np.pad(level0, ((0, win), (0, win)))
        naive = np.zeros_like(level0)
        for dr in range(win):
            for dc in range(win):
                naive = np.maximum(
                    naive, padded[dr : dr + level0.shape[0], dc : dc + level0.shape[1]]
                )
        assert np.array_equal(table.level(k), naive), f"level {k}"


def _scene_pairs(n: int, seed: int):
    from gcs.loops.synthetic_scenes import random_world, scan_grid, scan_points
    from protocol.se2 import compose, relative

    rng = np.random.default_rng(seed)
    out = []
    while len(out) < n:
        world = random_world(rng, size_m=40.0, buildings=10, walls=15, boxes=40)
        a = np.array([*rng.uniform(-15, 15, 2), rng.uniform(-math.pi, math.pi)])
        b = compose(a, np.array([*rng.uniform(-1.5, 1.5, 2), rng.uniform(-0.35, 0.35)]))
        ga, oa = scan_grid(scan_points(world, a, rng=rng))
        gb, ob = scan_grid(scan_points(world, b, rng=rng))
        if ga.sum() < 200 or gb.sum() < 200:
            continue
        truth = relative(a, b)
        guess = truth + np.array([*rng.uniform(-1.5, 1.5, 2), rng.uniform(-0.25, 0.25)])
        out.append((ga, oa, gb, ob, truth, guess))
    return out


@pytest.mark.parametrize("seed", range(3))
def test_branch_and_bound_equals_brute_force_on_scans_with_the_full_window(seed: int) -> None:
    """150 x 150 ray-cast scans (one-sided walls, occlusion), +-3 m and +-30 deg."""
    matcher = CorrelativeMatcher()
    for ga, oa, gb, ob, truth, guess in _scene_pairs(2, seed):
        ref = matcher.reference_table(ga, origin_m=oa, resolution_m=RES)
        pts = grid_points(gb, origin_m=ob, resolution_m=RES)
        bnb = matcher.match(ref, pts, guess)
        brute = brute_force_match(matcher, ref, pts, guess)
        assert bnb is not None and brute is not None
        assert bnb.score == brute.score
        assert np.array_equal(bnb.a_from_b_discrete, brute.a_from_b_discrete)
        assert np.hypot(*(bnb.a_from_b[:2] - truth[:2])) < 0.1


def test_guess_far_from_the_grid_drops_points_and_still_equals_brute_force() -> None:
    """Points that can never reach the table score 0 (and count in the normalization)."""
    rng = np.random.default_rng(9)
    ref_grid = rng.random((60, 60)) < 0.05
    query = grid_points(rng.random((60, 60)) < 0.05, origin_m=(-3.0, -3.0), resolution_m=RES)
    matcher = CorrelativeMatcher(MatcherConfig(search_xy_m=1.0, search_yaw_rad=0.2))
    ref = matcher.reference_table(ref_grid, origin_m=(0.0, 0.0), resolution_m=RES)
    for guess in ([7.5, 3.0, 2.0], [-2.9, 6.4, -3.0], [30.0, 30.0, 0.0]):
        g = np.array(guess)
        bnb = matcher.match(ref, query, g)
        brute = brute_force_match(matcher, ref, query, g)
        assert bnb is not None and brute is not None
        assert (bnb.score, *bnb.a_from_b_discrete) == (brute.score, *brute.a_from_b_discrete)
        assert -math.pi <= bnb.a_from_b[2] < math.pi


def test_real_laser_scans_branch_and_bound_equals_brute_force(intel_log) -> None:  # type: ignore[no-untyped-def]
    """Corpus pairs: real Intel Research Lab scans near each other (corrected poses)."""
    from protocol.se2 import relative

    matcher = CorrelativeMatcher()
    poses = intel_log.base_in_log
    rng = np.random.default_rng(5)
    done = 0
    while done < 3:
        i, j = (int(v) for v in rng.integers(0, len(intel_log), 2))
        truth = relative(poses[i], poses[j])
        if abs(i - j) < 20 or np.hypot(*truth[:2]) > 1.5 or abs(truth[2]) > 0.4:
            continue
        ga, oa = points_grid(intel_log.points_in_base(i), resolution_m=RES)
        ref = matcher.reference_table(ga, origin_m=oa, resolution_m=RES)
        pts = intel_log.points_in_base(j)
        guess = truth + np.array([*rng.uniform(-1.0, 1.0, 2), rng.uniform(-0.2, 0.2)])
        bnb = matcher.match(ref, pts, guess)
        brute = brute_force_match(matcher, ref, pts, guess)
        assert bnb is not None and brute is not None
        assert (bnb.score, *bnb.a_from_b_discrete) == (brute.score, *brute.a_from_b_discrete)
        done += 1


def test_points_grid_round_trips_cell_centres() -> None:
    rng = np.random.default_rng(2)
    grid = rng.random((30, 45)) < 0.1
    pts = grid_points(grid, origin_m=(-1.2, 3.4), resolution_m=RES)
    back, origin = points_grid(pts, resolution_m=RES, margin_cells=0)
    again = grid_points(back, origin_m=origin, resolution_m=RES)
    assert np.allclose(np.sort(again, axis=0), np.sort(pts, axis=0))
    with pytest.raises(ValueError, match="no points"):
        points_grid(np.zeros((0, 2)), resolution_m=RES)


def test_a_table_from_another_window_is_refused() -> None:
    small = CorrelativeMatcher(MatcherConfig(search_xy_m=0.5))
    ref = small.reference_table(np.eye(20, dtype=bool), origin_m=(0.0, 0.0), resolution_m=RES)
    with pytest.raises(ValueError, match="same matcher"):
        CorrelativeMatcher().match(ref, np.ones((3, 2)), np.zeros(3))


def _brute_runner_up(
    matcher: CorrelativeMatcher, ref, pts: np.ndarray, guess: np.ndarray, ty0: int, tx0: int
) -> int:  # type: ignore[no-untyped-def]
    """The best score over every transform whose translation lies more than
    ``runner_up_radius_m`` from ``(ty0, tx0)`` (cells from the guess), by exhaustive search."""
    from gcs.loops.correlative_matcher import _rotated_cells

    p = matcher._prepare(ref, pts, guess)
    rows = np.empty((len(p.yaws), len(p.points)), dtype=np.int64)
    cols = np.empty_like(rows)
    ox, oy = ref.origin_m
    _rotated_cells(p.points, p.yaws, guess[0], guess[1], ox, oy, ref.resolution_m, rows, cols)
    h, w = ref.grid_shape
    table = ref.level(0)[ref.pad : ref.pad + h, ref.pad : ref.pad + w].astype(np.int64)
    r2 = (matcher.config.runner_up_radius_m / ref.resolution_m) ** 2
    best = -1
    for ty in range(-p.n_xy, p.n_xy + 1):
        for tx in range(-p.n_xy, p.n_xy + 1):
            if (ty - ty0) ** 2 + (tx - tx0) ** 2 <= r2:
                continue
            r, c = rows + ty, cols + tx
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            scores = np.where(inside, table[np.clip(r, 0, h - 1), np.clip(c, 0, w - 1)], 0)
            best = max(best, int(scores.sum(axis=1).max()))
    return best


@pytest.mark.parametrize("seed", range(6))
def test_runner_up_is_the_best_transform_outside_the_radius(seed: int) -> None:
    """The runner-up search (a second branch and bound with a disk left out around the best
    translation) finds exactly what exhaustive search finds outside that disk, when it reaches
    the ratio; and reports 0 when nothing does."""
    rng = np.random.default_rng(300 + seed)
    ref_grid = rng.random((40, 40)) < 0.08
    query_grid = rng.random((40, 40)) < 0.05
    cfg = MatcherConfig(
        search_xy_m=0.8,
        search_yaw_rad=math.radians(10),
        runner_up_radius_m=0.1 * (2 + seed),
        runner_up_ratio=0.5 if seed % 2 else 0.99,
    )
    matcher = CorrelativeMatcher(cfg)
    ref = matcher.reference_table(ref_grid, origin_m=(-2.0, -2.0), resolution_m=RES)
    pts = grid_points(query_grid, origin_m=(-2.0, -2.0), resolution_m=RES)
    guess = np.array([0.1, 0.0, 0.05])
    bnb = matcher.match(ref, pts, guess)
    assert bnb is not None
    plain = CorrelativeMatcher(msgspec.structs.replace(cfg, runner_up_radius_m=0.0))
    alone = plain.match(ref, pts, guess)
    assert alone is not None and alone.runner_up_score == 0.0
    assert (bnb.score, *bnb.a_from_b_discrete) == (alone.score, *alone.a_from_b_discrete)
    ty0 = round((bnb.a_from_b_discrete[1] - guess[1]) / RES)
    tx0 = round((bnb.a_from_b_discrete[0] - guess[0]) / RES)
    second = _brute_runner_up(matcher, ref, pts, guess, ty0, tx0)
    norm = second / (255.0 * len(matcher._prepare(ref, pts, guess).points))
    if second >= math.ceil(cfg.runner_up_ratio * bnb.score - 1e-9):
        assert bnb.runner_up_score == pytest.approx(norm)
    else:
        assert bnb.runner_up_score == 0.0


def test_a_place_repeated_along_a_corridor_has_a_runner_up_a_unique_one_none() -> None:
    """Two identical rooms 2 m apart: a view of one fits the other as well (a look-alike the
    window holds); a view of irregular walls has no second place near its best."""
    rng = np.random.default_rng(11)
    room = walls(rng, n=4, extent=1.5)
    world = np.concatenate([room, room + [2.0, 0.0]])
    matcher = CorrelativeMatcher(
        MatcherConfig(search_xy_m=3.0, search_yaw_rad=math.radians(10), runner_up_radius_m=1.0)
    )
    grid, origin = points_grid(world, resolution_m=RES)
    ref = matcher.reference_table(grid, origin_m=origin, resolution_m=RES)
    repeated = matcher.match(ref, room, np.zeros(3))
    assert repeated is not None and repeated.normalized_score > 0.9
    assert repeated.runner_up_score > 0.9 * repeated.normalized_score
    truth = np.array([0.4, -0.3, math.radians(5.0)])
    ref_grid, query_grid, origin = scene_pair(3, truth)
    ref = matcher.reference_table(ref_grid, origin_m=origin, resolution_m=RES)
    unique = matcher.match(ref, grid_points(query_grid, origin_m=origin, resolution_m=RES), truth)
    assert unique is not None and unique.normalized_score > 0.5
    assert unique.runner_up_score == 0.0
    with pytest.raises(ValueError, match="runner_up_ratio"):
        MatcherConfig(runner_up_ratio=0.0)
