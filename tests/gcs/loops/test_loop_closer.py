"""The loop closer over a real pose graph: a simulated team, aliasing, budgets, operator
primitives, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.keys import pose_key
from gcs.graph.pose_graph import PoseGraph, Provenance
from gcs.loops.loop_closer import LoopCloser, LoopCloserConfig
from gcs.loops.synthetic_scenes import corridor_world
from tests.gcs.loops.team_sim import (
    TeamResult,
    city_world,
    noisy_odometry,
    route_poses,
    run_team,
    scan_of,
)
from tests.gcs.loops.team_sim import street as s

FALSE_M = 0.5
FALSE_RAD = math.radians(3.0)


def team_routes() -> list[np.ndarray]:
    """Four robots leave a staging area on the bottom street and come back through streets
    the others drove: revisits within and across robots."""
    wps = [
        [(s(0), s(0)), (s(0), s(2)), (s(2), s(2)), (s(2), s(0)), (s(0), s(0))],
        [(s(0) + 2, s(0)), (s(1), s(0)), (s(1), s(3)), (s(3), s(3)), (s(3), s(1)), (s(0), s(1))],
        [(s(0) + 4, s(0)), (s(3), s(0)), (s(3), s(2)), (s(1), s(2)), (s(1), s(0))],
        [(s(0) + 6, s(0)), (s(2), s(0)), (s(2), s(3)), (s(0), s(3)), (s(0), s(1))],
    ]
    return [route_poses(w, spacing_m=1.5) for w in wps]


@pytest.fixture(scope="module")
def team() -> TeamResult:
    rng = np.random.default_rng(2)
    world = city_world(rng)
    hint = (0.5, 0.05)  # the operator places robots 1..3 at the staging area
    return run_team(world, team_routes(), rng=rng, hints={1: hint, 2: hint, 3: hint})


def false_closures(result: TeamResult) -> int:
    return sum(1 for d, a in result.closure_errors() if d > FALSE_M or a > FALSE_RAD)


def test_four_robots_close_loops_across_robots_without_false_closures(team: TeamResult) -> None:
    assert team.cross_robot_closures() >= 20
    assert false_closures(team) == 0
    stats = team.closer.stats
    assert stats.accepted == len(team.graph.edges(Provenance.LOOP_AUTO)) > 0
    assert stats.matches >= stats.hypotheses >= stats.accepted
    # the map is right: well under the odometry's drift
    assert team.ate_rmse_m() < 0.25
    drift = [
        float(
            np.hypot(
                *(se2.compose(r.truth[0], se2.between(r.odom[0], r.odom[-1])) - r.truth[-1])[:2]
            )
        )
        for r in team.robots
    ]
    assert max(drift) > 1.0  # there was something to correct


def test_a_robot_with_no_seed_stays_unlinked() -> None:
    rng = np.random.default_rng(4)
    world = city_world(rng)
    routes = [r[:40] for r in team_routes()[:2]]
    result = run_team(world, routes, rng=rng, hints={})
    comps = result.graph.components()
    assert comps[pose_key(0, 0)] != comps[pose_key(1, 0)]
    assert result.cross_robot_closures() == 0
    assert false_closures(result) == 0


def test_aliased_corridors_a_confident_false_match_is_rejected() -> None:
    """Two identical corridors 12 m apart: the scan of corridor B matches corridor A's
    perfectly (perceptual aliasing), so the operator's suggestion scores high; the graph
    (odometry from A to B) contradicts it, so cycle validation rejects it, twice over."""
    world = np.concatenate(
        [corridor_world(length_m=24.0), corridor_world(length_m=24.0, offset_m=(0.0, 12.0))]
    )
    rng = np.random.default_rng(7)
    truth = route_poses([(-10.0, 0.0), (14.0, 0.0), (14.0, 12.0), (-10.0, 12.0)], spacing_m=1.0)
    odom, covs = noisy_odometry(truth, rng)
    graph = PoseGraph()
    closer = LoopCloser(graph)
    keys = []
    for t, (o, p) in enumerate(zip(odom, truth, strict=True)):
        keys.append(
            graph.add_pose(
                0,
                odom_from_base=o,
                time_s=float(t),
                odometry_covariance=None if t == 0 else covs[t - 1],
            )
        )
        closer.add_scan(keys[-1], scan_of(world, p, rng))
    # nodes in corridor A and the nodes of B at the same x (driven the other way)
    in_a = [i for i, p in enumerate(truth) if abs(p[1]) < 1e-9 and -8 <= p[0] <= 8]
    pairs = []
    for i in in_a[::4]:
        j = int(np.argmin([abs(q[0] - truth[i][0]) + 100 * abs(q[1] - 12.0) for q in truth]))
        pairs.append((keys[i], keys[j]))
    proposed = []
    for ka, kb in pairs[:2]:
        alias = np.array([0.0, 0.0, math.pi])  # "B is where A was, facing back"
        result = closer.suggest(ka, kb, alias, wide=False)
        assert result.normalized_score > 0.8  # a confident, wrong match
        true_rel = se2.between(truth[keys.index(ka)], truth[keys.index(kb)])
        assert np.hypot(*(result.a_from_b - true_rel)[:2]) > 10.0
        proposed.append(closer.propose(ka, kb, result, time_s=float(len(truth))))
    report = closer.step(now_s=float(len(truth)), budget_s=0.0)
    assert report.rejected == 2 and closer.stats.rejected_by_cycle == 2
    assert not closer.pending_hypotheses
    assert not [e for e in graph.edges(Provenance.LOOP_AUTO) if (e.key_a, e.key_b) in pairs]


def _route_run(
    seed: int = 5, laps: int = 1
) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """One robot of the team routes, ``laps`` times: noisy odometry, its covariances and the
    scans."""
    rng = np.random.default_rng(seed)
    world = city_world(rng)
    lap = team_routes()[0]
    route = np.concatenate([lap] + [lap[1:]] * (laps - 1))
    odom, covs = noisy_odometry(route, rng)
    return odom, covs, [scan_of(world, p, rng) for p in route]


def _route_graph(seed: int = 5) -> tuple[PoseGraph, list[int], list[np.ndarray]]:
    """The graph of :func:`_route_run` (nodes only, no scans yet), its keys and the scans."""
    odom, covs, scans = _route_run(seed)
    graph = PoseGraph()
    keys = [
        graph.add_pose(
            0,
            odom_from_base=odom[t],
            time_s=float(t),
            odometry_covariance=None if t == 0 else covs[t - 1],
        )
        for t in range(len(odom))
    ]
    return graph, keys, scans


def test_budget_and_match_rate_bound_the_work() -> None:
    graph, keys, scans = _route_graph()
    cfg = LoopCloserConfig(matches_per_s=5.0, max_burst_matches=5)
    closer = LoopCloser(graph, cfg)
    for k, pts in zip(keys, scans, strict=True):
        closer.add_scan(k, pts)
    report = closer.step(now_s=float(len(keys)), budget_s=0.0)
    assert report.matches == 0 and report.budget_exhausted  # no time: nothing done

    def cost() -> float:  # tokens spent: a wide match costs wide_match_cost
        st = closer.stats
        return st.matches + (closer.config.wide_match_cost - 1) * st.wide_matches

    report = closer.step(now_s=float(len(keys)), budget_s=5.0)
    assert report.matches > 0 and cost() <= 5.0  # the burst
    assert report.budget_exhausted and report.queued > 0  # candidates wait for tokens
    # message time moving on adds no tokens: only progress (nodes added) does
    report = closer.step(now_s=float(len(keys)) + 100.0, budget_s=5.0)
    assert report.matches == 0 and report.budget_exhausted
    graph.add_pose(
        0, odom_from_base=graph.pose(keys[-1]), time_s=0.0, odometry_covariance=np.eye(3)
    )
    report = closer.step(now_s=0.0, budget_s=5.0)  # one node: 5 tokens, even at t = 0
    assert report.matches > 0 and cost() <= 10.0
    assert closer.progress_s == pytest.approx((len(keys) + 1) * cfg.nominal_s_per_node)


@pytest.mark.parametrize("clock", ["frozen", "coarse", "jumping", "backwards"])
def test_bad_clocks_change_nothing(clock: str) -> None:
    """The same nodes and scans, stepped after every node with a good clock and a bad one:
    the same matches, hypotheses and closures (issue 19 item 3)."""

    odom, covs, scans = _route_run(seed=7, laps=2)

    def run(times: list[float]) -> tuple[int, int, int, list[tuple[int, int]]]:
        graph = PoseGraph()
        closer = LoopCloser(graph, LoopCloserConfig(max_burst_matches=8, matches_per_s=2.0))
        for t in range(len(odom)):  # nodes and scans as they come, a step after each
            key = graph.add_pose(
                0,
                odom_from_base=odom[t],
                time_s=times[t],
                odometry_covariance=None if t == 0 else covs[t - 1],
            )
            closer.add_scan(key, scans[t])
            closer.step(now_s=times[t], budget_s=30.0)
        autos = sorted((e.key_a, e.key_b) for e in graph.edges(Provenance.LOOP_AUTO))
        return closer.stats.matches, closer.stats.hypotheses, closer.stats.accepted, autos

    n = len(odom)
    good = [float(i) for i in range(n)]
    bad = {
        "frozen": [5.0] * n,
        "coarse": [float(60 * (i // 40)) for i in range(n)],
        "jumping": [float(i + (1e4 if i % 17 == 0 else 0)) for i in range(n)],
        "backwards": [float(n - i) for i in range(n)],
    }[clock]
    want = run(good)
    got = run(bad)
    assert want[0] >= 20 and want[2] > 0  # the run matches and closes loops at all
    assert got == want


def test_rewind_restart_and_suggest(team: TeamResult) -> None:
    graph = team.graph.copy()
    closer = LoopCloser(graph, team.closer.config)
    for k in team.closer.scanned_keys:
        closer.add_scan(k, team.closer._scans[k])
    autos = graph.edges(Provenance.LOOP_AUTO)
    cut = sorted(e.time_s for e in autos)[len(autos) // 2]
    later = [e for e in autos if e.time_s > cut]
    assert closer.rewind(cut) == len(later) > 0
    assert len(graph.edges(Provenance.LOOP_AUTO)) == len(autos) - len(later)
    assert not closer.pending_hypotheses
    # suggest: two nodes of different robots near each other, from the current estimate
    a, b = pose_key(1, 2), pose_key(2, 1)  # 0.5 m apart on the bottom street
    result = closer.suggest(a, b)
    true_rel = se2.between(team.truth_by_key[a], team.truth_by_key[b])
    assert np.hypot(*(result.a_from_b - true_rel)[:2]) < 0.15
    assert result.normalized_score > 0.5
    assert len(graph.edges(Provenance.LOOP_OPERATOR)) == 3  # suggest adds nothing
    eid = closer.operator_edge(a, b, result, time_s=1e3)
    assert graph.edges(Provenance.LOOP_OPERATOR)[-1].edge_id == eid
    # restart: every pair may be tried again
    closer.restart()
    # a generous wall budget: under load, candidate generation alone can take seconds
    report = closer.step(now_s=1e3, budget_s=30.0)
    assert report.matches > 0


def test_bad_scans_are_refused_and_counted() -> None:
    graph = PoseGraph()
    key = graph.add_pose(3, odom_from_base=(0.0, 0.0, 0.0), time_s=0.0)
    closer = LoopCloser(graph)
    with pytest.raises(ValueError, match="robot 3 pose 7 is not in the graph"):
        closer.add_scan(pose_key(3, 7), np.zeros((50, 2)))
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        closer.add_scan(key, np.zeros((50, 3)))
    with pytest.raises(ValueError, match="non-finite"):
        closer.add_scan(key, np.full((50, 2), np.nan))
    with pytest.raises(ValueError, match="not a pose key"):
        closer.add_scan(-5, np.zeros((50, 2)))
    closer.add_scan(key, np.zeros((3, 2)))
    assert closer.stats.scans_too_small == 1 and closer.scanned_keys == []
    with pytest.raises(ValueError, match="window"):
        LoopCloserConfig(candidates=LoopCloserConfig().candidates.__class__(window_xy_m=2.0))
    with pytest.raises(ValueError, match="budget_s"):
        closer.step(now_s=0.0, budget_s=-1.0)
