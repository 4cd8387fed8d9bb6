"""Odometry self-calibration in the loop closer (issue 19 item 4): a robot whose odometry
under-reads every turn by 8 % drives loops around city blocks; its matches give the turn scale,
the graph's odometry is corrected in place and the map ends near the unbiased one."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.pose_graph import PoseGraph, PoseGraphConfig, Provenance
from gcs.loops.loop_closer import LoopCloser, LoopCloserConfig
from gcs.loops.odometry_bias import OdometryBiasConfig
from tests.gcs.loops.team_sim import city_world, rigid_ate_rmse_m, route_poses, scan_of
from tests.gcs.loops.team_sim import street as s


def drive(
    turn_scale: float, *, calibrate: bool, seed: int = 4
) -> tuple[LoopCloser, np.ndarray, np.ndarray, list[int]]:
    """One robot around the blocks twice; odometry reads ``turn_scale`` times each turn."""
    rng = np.random.default_rng(seed)
    world = city_world(rng)
    lap = [(s(0), s(0)), (s(2), s(0)), (s(2), s(2)), (s(0), s(2)), (s(0), s(0))]
    lap2 = [(s(0), s(0)), (s(1), s(0)), (s(1), s(3)), (s(3), s(3)), (s(3), s(1)), (s(0), s(1))]
    truth = route_poses(lap + lap[1:] + lap2[1:], spacing_m=1.5)
    cfg = LoopCloserConfig(odometry_bias=OdometryBiasConfig(enabled=calibrate))
    graph = PoseGraph(PoseGraphConfig(map_robot_id=0))
    closer = LoopCloser(graph, cfg)
    odom = np.zeros(3)
    keys = []
    for t in range(len(truth)):
        cov = None
        if t > 0:
            step = se2.between(truth[t - 1], truth[t]).copy()
            d = max(float(np.hypot(*step[:2])), 0.05)
            sig = np.array([0.02 * d, 0.02 * d, math.radians(0.5) * math.sqrt(d) + 0.002])
            step[2] *= turn_scale
            odom = se2.compose(odom, step + rng.normal(0.0, 1.0, 3) * sig)
            cov = np.diag(sig**2)  # the noise only: the bias is unknown to the robot
        key = graph.add_pose(0, odom_from_base=odom, time_s=float(t), odometry_covariance=cov)
        keys.append(key)
        closer.add_scan(key, scan_of(world, truth[t], rng))
        report = closer.step(now_s=float(t), budget_s=1.0)
        if report.accepted_edge_ids:
            graph.optimize_incremental()
    closer.step(now_s=float(len(truth)), budget_s=1.0)
    graph.optimize()
    est = np.array([graph.pose(k) for k in keys])
    return closer, est, truth, keys


@pytest.fixture(scope="module")
def biased() -> tuple[LoopCloser, np.ndarray, np.ndarray, list[int]]:
    return drive(0.92, calibrate=True)


def closure_errors(closer: LoopCloser, truth: np.ndarray, keys: list[int]) -> np.ndarray:
    at = {k: i for i, k in enumerate(keys)}
    out = []
    for e in closer.graph.edges(Provenance.LOOP_AUTO):
        assert e.key_b is not None
        err = se2.between(se2.between(truth[at[e.key_a]], truth[at[e.key_b]]), e.z)
        out.append((math.hypot(err[0], err[1]), abs(float(se2.wrap_angle(err[2])))))
    return np.array(out).reshape(-1, 2)


def test_a_turn_scale_bias_is_estimated_and_fed_back(
    biased: tuple[LoopCloser, np.ndarray, np.ndarray, list[int]],
) -> None:
    closer, est, truth, keys = biased
    applied = closer.applied_turn_scales[0]
    assert applied.scale == pytest.approx(1 / 0.92, abs=0.01)
    assert closer.stats.odometry_recalibrations >= 1
    # the graph's odometry edges carry the correction; what the robot reported is kept
    _ids, _kb, z_reported, _cov = closer.graph.odometry_reported(0)
    odo = closer.graph.edges(Provenance.ODOMETRY)
    assert odo[5].z[2] == pytest.approx(applied.scale * z_reported[5, 2])
    err = closure_errors(closer, truth, keys)
    assert len(err) >= 20
    assert np.all(err[:, 0] <= 0.5) and np.all(err[:, 1] <= math.radians(5.0))
    # the map: far better than the biased odometry's and than closing without calibration
    odo_ate = rigid_ate_rmse_m(
        np.array([n.odom_from_base[:2] for n in closer.graph.nodes(0)]), truth[:, :2]
    )
    ate = rigid_ate_rmse_m(est[:, :2], truth[:, :2])
    _c, est_off, _t, _k = drive(0.92, calibrate=False)
    ate_off = rigid_ate_rmse_m(est_off[:, :2], truth[:, :2])
    assert ate < 0.5 * odo_ate
    assert ate < ate_off


def test_unbiased_odometry_is_left_alone() -> None:
    closer, est, truth, _keys = drive(1.0, calibrate=True, seed=5)
    fit = closer.turn_scales.get(0)
    assert fit is not None and fit.scale == pytest.approx(1.0, abs=0.01)
    applied = closer.applied_turn_scales.get(0)
    assert applied is None or applied.scale == pytest.approx(1.0, abs=0.01)
    assert rigid_ate_rmse_m(est[:, :2], truth[:, :2]) < 0.3


def test_configuration_is_checked() -> None:
    with pytest.raises(ValueError, match="window_k_sigma"):
        OdometryBiasConfig(window_k_sigma=0.0)
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert({"odometry_bias": {"bogus": 1}}, LoopCloserConfig)


def test_candidate_windows_hold_the_turn_scale_error_along_the_chain() -> None:
    """The odometry's sigmas hold no scale error: the candidates' yaw variance gets
    ``(e T)^2`` for the turning ``T`` between the two nodes, ``e`` the prior before a fit,
    up to a bound."""
    graph = PoseGraph(PoseGraphConfig(map_robot_id=0))
    closer = LoopCloser(graph, LoopCloserConfig())
    keys = [graph.add_pose(0, odom_from_base=np.zeros(3), time_s=0.0)]
    for t in range(1, 13):  # a full turn on a 3 m circle, 30 deg a step
        yaw = math.radians(30.0 * t)
        pose = np.array([3 * math.sin(yaw), 3 - 3 * math.cos(yaw), float(se2.wrap_angle(yaw))])
        keys.append(
            graph.add_pose(
                0, odom_from_base=pose, time_s=float(t), odometry_covariance=np.diag([1e-4] * 3)
            )
        )
    closer.step(now_s=13.0, budget_s=0.0)
    mirror = closer._sync()
    proj = closer._projection(keys[-1], max_trace=math.inf)
    widened = closer._with_turn_scale_error(keys[-1], mirror, proj.covariances)
    extra = widened[:, 2, 2] - proj.covariances[:, 2, 2]
    turned = np.radians(30.0 * (12 - np.arange(13)))  # from each node to the last
    order = [mirror.index[k] for k in keys]
    # at most a 20 deg sigma (max_turn_scale_yaw_rad): a symmetric hall's look-alikes
    expect = np.minimum(0.1 * turned, math.radians(20.0)) ** 2
    np.testing.assert_allclose(extra[order], expect, rtol=1e-9, atol=1e-12)
    assert expect[0] < (0.1 * turned[0]) ** 2  # the whole turn's 36 deg was capped
    assert np.array_equal(widened[:, :2, :2], proj.covariances[:, :2, :2])
