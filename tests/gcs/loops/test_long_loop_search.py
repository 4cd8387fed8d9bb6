"""Long-loop candidates (gcs.loops.long_loop_search) through the real LoopCloser: a loop of
more than 200 m whose odometry drifted beyond the regular search's window closes with place
recognition, and never falsely (perceptually aliased corridors)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.pose_graph import PoseGraph, Provenance
from gcs.loops.cycle_validation import CycleValidationConfig
from gcs.loops.long_loop_search import LongLoopConfig, LongLoopMatch, LongLoopSearch
from gcs.loops.loop_closer import LoopCloser, LoopCloserConfig
from gcs.loops.synthetic_scenes import corridor_world
from tests.gcs.loops.team_sim import city_world, noisy_odometry, route_poses, scan_of, street

FALSE_M, FALSE_RAD = 0.5, math.radians(5.0)


@pytest.fixture
def released(monkeypatch: pytest.MonkeyPatch) -> set[tuple[int, int]]:
    """Pairs the long-loop source released as hypotheses (to tell its closures apart)."""
    pairs: set[tuple[int, int]] = set()
    propose = LongLoopSearch.propose

    def recording(self: LongLoopSearch, key: int, **kw: object) -> list[LongLoopMatch]:
        out = propose(self, key, **kw)  # type: ignore[arg-type]
        pairs.update((m.key_a, m.key_b) for m in out)
        return out

    monkeypatch.setattr(LongLoopSearch, "propose", recording)
    return pairs


def _drive(
    world: np.ndarray,
    truth: np.ndarray,
    rng: np.random.Generator,
    config: LoopCloserConfig,
    *,
    yaw_sigma_deg: float,
) -> tuple[PoseGraph, LoopCloser, list[int]]:
    """One robot along ``truth``: noisy odometry, a scan per node, a closer step per node and
    an optimization whenever a closure was accepted (as the ground station does)."""
    odom, covs = noisy_odometry(truth, rng, sigma_yaw_rad=math.radians(yaw_sigma_deg))
    graph = PoseGraph()
    closer = LoopCloser(graph, config)
    keys: list[int] = []
    for t, (o, p) in enumerate(zip(odom, truth, strict=True)):
        cov = None if t == 0 else covs[t - 1]
        keys.append(graph.add_pose(0, odom_from_base=o, time_s=float(t), odometry_covariance=cov))
        closer.add_scan(keys[-1], scan_of(world, p, rng))
        if closer.step(now_s=float(t), budget_s=10.0).accepted_edge_ids:
            graph.optimize()
    return graph, closer, keys


def _closures(
    graph: PoseGraph, keys: list[int], truth: np.ndarray, only: set[tuple[int, int]] | None = None
) -> tuple[int, int, int]:
    """(closures, closures spanning more than 100 nodes = 100 m, false closures), of all
    automatic closures or ``only`` those between these pairs."""
    at = {k: i for i, k in enumerate(keys)}
    n = span = bad = 0
    for e in graph.edges(Provenance.LOOP_AUTO):
        assert e.key_b is not None
        if only is not None and (e.key_a, e.key_b) not in only:
            continue
        i, j = at[e.key_a], at[e.key_b]
        err = se2.between(se2.between(truth[i], truth[j]), e.z)
        n += 1
        span += abs(i - j) > 100
        bad += math.hypot(err[0], err[1]) > FALSE_M or abs(err[2]) > FALSE_RAD
    return n, span, bad


def _city_loop() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    world = city_world(rng, blocks=4)
    a, b = street(0, 4), street(4, 4)
    # around the 4 x 4 blocks (224 m) and 20 m along the start again
    truth = route_poses([(a, a), (b, a), (b, b), (a, b), (a, a), (a + 20.0, a)], spacing_m=1.0)
    return world, truth


def test_a_long_loop_beyond_the_regular_window_closes_only_with_place_recognition(
    released: set[tuple[int, int]],
) -> None:
    world, truth = _city_loop()
    off = LoopCloserConfig(long_loops=LongLoopConfig(enabled=False))
    on = LoopCloserConfig()  # on by default
    results = {}
    for name, cfg in (("off", off), ("on", on)):
        graph, closer, keys = _drive(world, truth, np.random.default_rng(4), cfg, yaw_sigma_deg=1.2)
        est = np.array([graph.pose(k) for k in keys])
        end = se2.between(est[0], est[-1]) - se2.between(truth[0], truth[-1])
        results[name] = (*_closures(graph, keys, truth), math.hypot(end[0], end[1]), closer)
        if name == "on":
            assert _closures(graph, keys, truth, released)[2] == 0  # none of its closures false
    _n_off, span_off, bad_off, end_off, _ = results["off"]
    _n_on, span_on, bad_on, end_on, closer = results["on"]
    assert span_off == 0 and end_off > 3.0  # the regular search cannot close it
    assert closer.long_loops is not None and closer.long_loops.stats.confirmed > 0
    assert span_on >= 2 and bad_on <= bad_off  # two: a cycle confirmed them
    assert end_on < 1.0 < end_off


def test_aliased_corridors_long_loop_matches_never_close_falsely(
    released: set[tuple[int, int]],
) -> None:
    """Two identical corridors 12 m apart driven through after a long, drifting detour: every
    stretch of either looks like every other. Place recognition proposes look-alikes; none
    may become a closure."""
    world = np.concatenate(
        [corridor_world(length_m=30.0), corridor_world(length_m=30.0, offset_m=(0.0, 12.0))]
    )
    truth = route_poses(
        [(-14.0, 0.0), (14.0, 0.0), (14.0, 12.0), (-14.0, 12.0), (-14.0, 0.0), (14.0, 0.0)],
        spacing_m=1.0,
    )
    cfg = LoopCloserConfig(long_loops=LongLoopConfig(enabled=True))
    graph, closer, keys = _drive(world, truth, np.random.default_rng(8), cfg, yaw_sigma_deg=2.0)
    assert closer.long_loops is not None and closer.long_loops.stats.matches > 0  # exercised
    assert _closures(graph, keys, truth, released)[2] == 0


def test_config_checks() -> None:
    with pytest.raises(ValueError, match="min_cycle_hypotheses >= 2"):
        LoopCloserConfig(
            long_loops=LongLoopConfig(enabled=True),
            validation=CycleValidationConfig(min_cycle_hypotheses=1),
        )
    with pytest.raises(ValueError, match="top_k"):
        LongLoopConfig(top_k=0)
    with pytest.raises(ValueError, match="window_yaw_rad"):
        LongLoopConfig(window_yaw_rad=4.0)
    assert LoopCloser(PoseGraph()).long_loops is not None  # on by default
    off = LoopCloserConfig(long_loops=LongLoopConfig(enabled=False))
    assert LoopCloser(PoseGraph(), off).long_loops is None  # off: nothing runs


def test_the_bench_counts_revisits_after_long_loops_and_their_closures() -> None:
    from mission.bench.robustness_long_loops import long_loop_revisits

    # a 4 x 30 m square driven twice at 1 m spacing: the second lap revisits the first
    side = np.arange(30.0)
    lap = np.concatenate(
        [
            np.stack([side, 0 * side], 1),
            np.stack([30 + 0 * side, side], 1),
            np.stack([30 - side, 30 + 0 * side], 1),
            np.stack([0 * side, 30 - side], 1),
        ]
    )
    xy = np.concatenate([lap, lap])
    ref = np.hstack([xy, np.zeros((len(xy), 1))])
    revisits, closed = long_loop_revisits(ref, np.zeros((0, 2), dtype=np.int64))
    # every node of lap 2 (120 m after lap 1's), and lap 1's last two, back at its start
    assert revisits == 122 and closed == 0
    closures = np.array([[125, 5], [126, 6], [10, 15]])  # two long, one short (not counted)
    assert long_loop_revisits(ref, closures) == (122, 2)
