"""Grids bent by turn-biased odometry (issue 19 item 4): a robot's node grid holds the scans of
its last metres brought into the node's frame by the odometry it *reported*. When that odometry
misreads turns, a grid made while the robot spun in place is a smear of copies rotated by up to
``(s - 1)`` times the spin, and every match against it is off in heading by a like amount. Such
matches agree with one another (all the grids are bent alike) and with the biased odometry, so
cycles pass them: the closer must bound the bend from its turn-scale knowledge and refuse them,
and accept them once the fit says the odometry is true."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.pose_graph import PoseGraph, PoseGraphConfig, Provenance
from gcs.loops.loop_closer import LoopCloser, LoopCloserConfig
from tests.gcs.loops.team_sim import city_world, rigid_ate_rmse_m, route_poses, scan_of
from tests.gcs.loops.team_sim import street as s

GRID_WINDOW_M = 2.0  # the robot's grid: its last 2 m of scans
CONFIG = LoopCloserConfig(grid_window_m=GRID_WINDOW_M)


def spin_route(spin_deg: float = 180.0) -> np.ndarray:
    """True node poses: around a block with a turn in place of ``spin_deg`` at its far corner
    (and back), then around it again past that corner."""
    lap = [(s(0), s(0)), (s(1), s(0)), (s(1), s(1)), (s(0), s(1)), (s(0), s(0))]
    legs = route_poses(lap + lap[1:], spacing_m=1.5)
    corner = int(np.argmin(np.hypot(legs[:, 0] - s(1), legs[:, 1] - s(1))))
    x, y, yaw = legs[corner]
    steps = int(round(spin_deg / 30.0))
    angles = [k * 30.0 for k in range(1, steps + 1)] + [k * 30.0 for k in range(steps - 1, -1, -1)]
    spin = np.array([(x, y, yaw + math.radians(a)) for a in angles])
    spin[:, 2] = se2.wrap_angle(spin[:, 2])
    return np.concatenate([legs[: corner + 1], spin, legs[corner + 1 :]])


def drive(turn_scale: float, config: LoopCloserConfig, *, seed: int = 3) -> dict[str, object]:
    """One robot along :func:`spin_route`; its odometry reads ``turn_scale`` times each turn and
    each node's grid is the scans of its last ``GRID_WINDOW_M`` joined by that odometry."""
    rng = np.random.default_rng(seed)
    world = city_world(rng)
    truth = spin_route()
    graph = PoseGraph(PoseGraphConfig(map_robot_id=0))
    closer = LoopCloser(graph, config)
    odom = [np.zeros(3)]
    travelled = [0.0]
    scans: list[np.ndarray] = []
    keys = []
    for t in range(len(truth)):
        cov = None
        if t > 0:
            step = se2.between(truth[t - 1], truth[t]).copy()
            d = float(np.hypot(*step[:2]))
            sig = np.array([0.01 * d + 0.005, 0.01 * d + 0.005, math.radians(0.3)])
            step[2] *= turn_scale
            odom.append(se2.compose(odom[-1], step + rng.normal(0.0, 1.0, 3) * sig))
            travelled.append(travelled[-1] + d)
            cov = np.diag(sig**2)  # the noise only: the bias is unknown to the robot
        key = graph.add_pose(0, odom_from_base=odom[t], time_s=float(t), odometry_covariance=cov)
        keys.append(key)
        scans.append(scan_of(world, truth[t], rng))
        window = [j for j in range(t + 1) if travelled[j] >= travelled[t] - GRID_WINDOW_M]
        points = []
        for j in window:  # joined by the reported odometry, as the robot does on board
            rel = se2.between(odom[t], odom[j])
            c, si = math.cos(rel[2]), math.sin(rel[2])
            p = scans[j]
            points.append(
                np.column_stack(
                    [rel[0] + c * p[:, 0] - si * p[:, 1], rel[1] + si * p[:, 0] + c * p[:, 1]]
                )
            )
        closer.add_scan(key, np.concatenate(points))
        report = closer.step(now_s=float(t), budget_s=5.0)
        if report.accepted_edge_ids or report.recalibrated_robots:
            graph.optimize_incremental()
    for t in range(len(truth), len(truth) + 3):
        closer.step(now_s=float(t), budget_s=5.0)
    graph.optimize()
    at = {k: i for i, k in enumerate(keys)}
    errors = []
    spin_closures = 0
    spun = {i for i in range(1, len(truth)) if np.hypot(*(truth[i, :2] - truth[i - 1, :2])) < 1e-9}
    for e in graph.edges(Provenance.LOOP_AUTO):
        assert e.key_b is not None
        ia, ib = at[e.key_a], at[e.key_b]
        err = se2.between(se2.between(truth[ia], truth[ib]), e.z)
        errors.append((float(np.hypot(*err[:2])), abs(float(se2.wrap_angle(err[2])))))
        spin_closures += ia in spun or ib in spun
    est = np.array([graph.pose(k) for k in keys])
    return {
        "closer": closer,
        "errors": np.array(errors).reshape(-1, 2),
        "spin_closures": spin_closures,
        "ate_m": rigid_ate_rmse_m(est[:, :2], truth[:, :2]),
        "odometry_ate_m": rigid_ate_rmse_m(np.array(odom)[:, :2], truth[:, :2]),
    }


def false_closures(errors: np.ndarray) -> int:
    return int(np.sum((errors[:, 0] > 0.5) | (errors[:, 1] > math.radians(5.0))))


@pytest.fixture(scope="module")
def biased() -> dict[str, object]:
    return drive(0.92, CONFIG)


def test_matches_on_bent_grids_are_refused(biased: dict[str, object]) -> None:
    closer = biased["closer"]
    assert isinstance(closer, LoopCloser)
    errors = biased["errors"]
    assert isinstance(errors, np.ndarray)
    assert closer.stats.distorted >= 1
    assert biased["spin_closures"] == 0  # the spin's grids are bent ~8 % of 180 deg
    assert len(errors) >= 20 and false_closures(errors) == 0
    assert float(np.max(errors[:, 1])) < math.radians(3.0)
    assert biased["ate_m"] < 0.05 * biased["odometry_ate_m"]  # type: ignore[operator]


def test_the_bend_bound_follows_the_turning_in_the_grid_and_the_scale_fit() -> None:
    graph = PoseGraph(PoseGraphConfig(map_robot_id=0))
    closer = LoopCloser(graph, CONFIG)
    off = LoopCloser(graph, LoopCloserConfig(grid_window_m=0.0))
    truth = spin_route(180.0)
    keys = [graph.add_pose(0, odom_from_base=truth[0], time_s=0.0)]
    for t in range(1, len(truth)):
        keys.append(
            graph.add_pose(
                0,
                odom_from_base=truth[t],
                time_s=float(t),
                odometry_covariance=np.diag([1e-4, 1e-4, 1e-5]),
            )
        )
    closer.step(now_s=float(len(truth)), budget_s=0.0)
    moved = np.hypot(*np.diff(truth[:, :2], axis=0).T)
    # the turn's far end: the corner's 90 deg and the spin's 180 deg within the grid's 2 m
    spin = int(np.flatnonzero(moved < 1e-9)[5]) + 1
    straight = 3  # on the first street: no turning within 2 m
    assert math.degrees(closer._window_turn_rad(keys[spin])) == pytest.approx(270.0, abs=1.0)
    assert closer._window_turn_rad(keys[straight]) == 0.0
    # before any fit, the prior (10 %) bounds the scale error
    assert closer._grid_distortion_rad(keys[spin], keys[straight]) == pytest.approx(
        0.1 * 1.5 * math.pi, rel=1e-3
    )
    assert off._grid_distortion_rad(keys[spin], keys[straight]) == 0.0
    # a grid bounded in turning (the replay's 30 deg) bends by at most the scale error times it
    capped = LoopCloser(
        graph, LoopCloserConfig(grid_window_m=GRID_WINDOW_M, grid_window_rad=math.radians(30.0))
    )
    assert math.degrees(capped._window_turn_rad(keys[spin])) == pytest.approx(30.0)
    assert capped._window_turn_rad(keys[straight]) == 0.0
    assert capped._grid_distortion_rad(keys[spin], keys[straight]) == pytest.approx(
        0.1 * math.radians(30.0), rel=1e-3
    )
    with pytest.raises(ValueError, match="grid_window_m"):
        LoopCloserConfig(grid_window_m=-1.0)
    with pytest.raises(ValueError, match="grid_window_rad"):
        LoopCloserConfig(grid_window_rad=0.0)
    with pytest.raises(ValueError, match="max_grid_distortion_rad"):
        LoopCloserConfig(max_grid_distortion_rad=0.0)


def test_true_odometry_releases_the_spin_closures() -> None:
    # before a fit the prior (10 %) bounds the bend, so spin matches wait; the fit on true
    # odometry (scale 1 +- ~1 %) bounds it within a degree or two and they are validated
    out = drive(1.0, CONFIG)
    closer = out["closer"]
    assert isinstance(closer, LoopCloser)
    fit = closer.turn_scales.get(0)
    assert fit is not None and fit.scale == pytest.approx(1.0, abs=0.01)
    assert false_closures(out["errors"]) == 0  # type: ignore[arg-type]
    assert out["spin_closures"] >= 2  # type: ignore[operator]
