"""``magic bench loops`` part: the multi-resolution correlative matcher (issue 7; paper 4.3.3).

Grid pairs: 150 x 150 binary grids at 10 cm (15 m, the paper's average terrain map) of
ray-cast 360 deg scans (one-sided walls, occlusion) taken at two poses up to 1.5 m and 20 deg
apart, with nothing between them (a revisit of the same place, not a view through a wall), in
random urban worlds (:mod:`gcs.loops.synthetic_scenes`; buildings with doorways, fences,
cars), so the true ``a_from_b`` is known exactly. Each match searches the issue's
window, +-3 m and +-30 deg, around a guess off the truth by up to 1.5 m per axis and 15 deg.
Default :class:`~gcs.loops.correlative_matcher.MatcherConfig` throughout.

Metrics:

- ``matches_per_s``: matches per second of CPU time of one thread (``time.thread_time``, so
  other processes on a busy machine do not count), median over repeats of a pass through all
  pairs; each pair's reference table is built beforehand (a GCS builds one per pose node and
  matches it against many candidates). ``matches_per_s_wall`` the same in wall time;
  ``reference_table_ms`` the median time to build one table; ``matches_per_s_yaw_step_1cell``
  the throughput with Olson's finer rotation step (``yaw_step_cells=1``) for comparison.
- ``bnb_equals_bruteforce_frac``: fraction of pairs on which branch and bound returns the same
  score and discrete pose as exhaustive evaluation of every discretized transform
  (:func:`~gcs.loops.correlative_matcher.brute_force_match`), over synthetic pairs and pairs
  of real scans of the Intel Research Lab log (``../shared/datasets/laser``; skipped when the
  datasets are absent, ``bnb_pairs_real`` says how many were checked).
- ``match_err_p95_m`` / ``match_err_p95_deg``: 95th percentile of the refined estimate's
  translation / rotation error against the truth over all synthetic pairs (no pair is
  excluded, so a pair whose views share too little counts as it comes).
"""

from __future__ import annotations

__all__ = ["run"]

import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from gcs.loops.correlative_matcher import (
    CorrelativeMatcher,
    MatcherConfig,
    ReferenceTable,
    brute_force_match,
    grid_points,
    points_grid,
)
from gcs.loops.synthetic_scenes import random_world, scan_grid, scan_points
from mission.bench import median_time_s
from protocol.se2 import compose, relative, wrap_angle

RES_M = 0.1
LASER = Path(__file__).resolve().parents[2] / ".." / "shared" / "datasets" / "laser"

Pair = tuple[np.ndarray, tuple[float, float], np.ndarray, np.ndarray, np.ndarray]


def scan_pairs(n: int, *, seed: int = 7) -> list[Pair]:
    """``n`` pairs ``(grid_a, origin_a, points_b, truth_a_from_b, guess_a_from_b)``."""
    rng = np.random.default_rng(seed)
    out: list[Pair] = []
    while len(out) < n:
        world = random_world(rng, size_m=40.0, buildings=10, walls=15, boxes=40)
        a = np.array([*rng.uniform(-15.0, 15.0, 2), rng.uniform(-math.pi, math.pi)])
        b = compose(a, np.array([*rng.uniform(-1.5, 1.5, 2), rng.uniform(-0.35, 0.35)]))
        if not _line_of_sight(world, a, b):  # a wall between them: different places
            continue
        grid_a, origin_a = scan_grid(scan_points(world, a, rng=rng))
        grid_b, origin_b = scan_grid(scan_points(world, b, rng=rng))
        if grid_a.sum() < 150 or grid_b.sum() < 150:  # open space: nothing to match
            continue
        truth = relative(a, b)
        guess = truth + np.array([*rng.uniform(-1.5, 1.5, 2), rng.uniform(-0.26, 0.26)])
        pts_b = grid_points(grid_b, origin_m=origin_b, resolution_m=RES_M)
        out.append((grid_a, origin_a, pts_b, truth, guess))
    return out


def _line_of_sight(world: np.ndarray, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether nothing in ``world`` lies between the positions of poses ``a`` and ``b``."""
    d = b[:2] - a[:2]
    heading = np.array([a[0], a[1], math.atan2(d[1], d[0])])
    hit = scan_points(world, heading, n_beams=1, max_range_m=float(np.hypot(*d)) + 0.3)
    return len(hit) == 0


def _intel_pairs(n: int, *, seed: int = 5) -> list[Pair]:
    """Real scans of the corrected Intel log at most 1.5 m / 23 deg apart, far apart in time."""
    path = LASER / "intel-corrected.log.gz"
    if not path.is_file():
        return []
    from gcs.replay.carmen_log import read_carmen_log

    log = read_carmen_log(path)
    poses = log.base_in_log
    rng = np.random.default_rng(seed)
    out: list[Pair] = []
    while len(out) < n:
        i, j = (int(v) for v in rng.integers(0, len(log), 2))
        truth = relative(poses[i], poses[j])
        if abs(i - j) < 20 or np.hypot(*truth[:2]) > 1.5 or abs(truth[2]) > 0.4:
            continue
        grid_a, origin_a = points_grid(log.points_in_base(i), resolution_m=RES_M)
        guess = truth + np.array([*rng.uniform(-1.0, 1.0, 2), rng.uniform(-0.2, 0.2)])
        out.append((grid_a, origin_a, log.points_in_base(j), truth, guess))
    return out


def _throughput(
    matcher: CorrelativeMatcher,
    tables: list[ReferenceTable],
    pairs: list[Pair],
    repeats: int,
    clock: Callable[[], float],
) -> float:
    for table, pair in zip(tables, pairs, strict=True):  # warm-up (compiled, cached)
        matcher.match(table, pair[2], pair[4])
    samples = []
    for _ in range(repeats):
        t0 = clock()
        for table, pair in zip(tables, pairs, strict=True):
            matcher.match(table, pair[2], pair[4])
        samples.append(clock() - t0)
    return len(pairs) / statistics.median(samples)


def _same(a: object, b: object) -> bool:
    if a is None or b is None:
        return a is b
    return bool(
        a.score == b.score  # type: ignore[attr-defined]
        and np.array_equal(a.a_from_b_discrete, b.a_from_b_discrete)  # type: ignore[attr-defined]
    )


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    n_pairs = 40 if quick else 200
    n_brute = 12 if quick else 60
    n_real = 6 if quick else 30
    repeats = 5 if quick else 11
    progress("loops matcher: making scan pairs")
    pairs = scan_pairs(n_pairs)
    matcher = CorrelativeMatcher()
    tables = [matcher.reference_table(p[0], origin_m=p[1], resolution_m=RES_M) for p in pairs]
    out: dict[str, float] = {}

    progress("loops matcher: throughput")
    out["matches_per_s"] = _throughput(matcher, tables, pairs, repeats, time.thread_time)
    out["matches_per_s_wall"] = _throughput(matcher, tables, pairs, repeats, time.perf_counter)
    grid0, origin0 = pairs[0][0], pairs[0][1]
    out["reference_table_ms"] = 1000.0 * median_time_s(
        lambda: matcher.reference_table(grid0, origin_m=origin0, resolution_m=RES_M),
        repeats=3 * repeats,
    )
    fine = CorrelativeMatcher(MatcherConfig(yaw_step_cells=1.0))
    fine_tables = [fine.reference_table(p[0], origin_m=p[1], resolution_m=RES_M) for p in pairs]
    out["matches_per_s_yaw_step_1cell"] = _throughput(
        fine, fine_tables, pairs, max(3, repeats // 2), time.thread_time
    )

    progress("loops matcher: accuracy")
    err_m, err_deg = [], []
    for table, (_, _, pts, truth, guess) in zip(tables, pairs, strict=True):
        result = matcher.match(table, pts, guess)
        assert result is not None  # min_score 0: always a result
        err_m.append(float(np.hypot(*(result.a_from_b[:2] - truth[:2]))))
        err_deg.append(abs(math.degrees(float(wrap_angle(result.a_from_b[2] - truth[2])))))
    out["match_err_p95_m"] = float(np.percentile(err_m, 95))
    out["match_err_p50_m"] = float(np.percentile(err_m, 50))
    out["match_err_p95_deg"] = float(np.percentile(err_deg, 95))

    progress("loops matcher: branch and bound against brute force")
    real = _intel_pairs(n_real)
    checks = [(tables[k], pairs[k]) for k in range(n_brute)] + [
        (matcher.reference_table(p[0], origin_m=p[1], resolution_m=RES_M), p) for p in real
    ]
    same = 0
    for table, (_, _, pts, _, guess) in checks:
        same += _same(
            matcher.match(table, pts, guess), brute_force_match(matcher, table, pts, guess)
        )
    out["bnb_equals_bruteforce_frac"] = same / len(checks)
    out["bnb_pairs_checked"] = float(len(checks))
    out["bnb_pairs_real"] = float(len(real))
    return out
