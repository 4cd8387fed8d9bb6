"""The GCS checks each odometry edge against the scan match of its two grids (a slipping wheel:
MAGIC's sand) and carries a fiducial to the teammate's node with its motion's uncertainty."""

from __future__ import annotations

import math

import numpy as np
import pytest

from compression import encode_grid, origin_cells_of
from gcs.graph.pose_graph import Provenance
from gcs.ground_station import (
    GroundStation,
    GroundStationConfig,
    OdometryCheckConfig,
    odometry_contradicted,
)
from gcs.loops.synthetic_scenes import random_world, scan_grid, scan_points
from protocol.messages import FiducialObservation, PoseNode, TerrainGrid, covariance_to_upper
from protocol.se2 import compose, relative

ODOM_COV = np.diag([0.03**2, 0.03**2, 0.005**2])  # what the simulated robots state per 1.2 m


def test_odometry_contradicted_needs_a_large_and_significant_difference() -> None:
    z = np.array([1.2, 0.0, 0.1])
    tight = np.diag([0.03**2, 0.03**2, 0.01**2])
    kw = {"chi2": 4.0, "min_diff_m": 0.08, "min_diff_rad": math.radians(3.0)}
    assert not odometry_contradicted(z, tight, z, tight, **kw)[0]
    # the wheels turned for 1.2 m, the body moved 0.9 m (sand): contradicted
    bad, value = odometry_contradicted(z, tight, np.array([0.9, 0.0, 0.1]), tight, **kw)
    assert bad and value > 4.0
    # 5 cm is within what a match and the odometry may disagree by: left alone
    assert not odometry_contradicted(z, tight, np.array([1.15, 0.0, 0.1]), tight, **kw)[0]
    # a large difference that the covariances allow is not a contradiction either
    loose = np.diag([0.5**2, 0.5**2, 0.1**2])
    assert not odometry_contradicted(z, loose, np.array([0.9, 0.0, 0.1]), loose, **kw)[0]
    # the difference is taken in the frame of b: a turned step is compared along itself
    zt = np.array([0.0, 1.2, math.pi / 2])
    assert odometry_contradicted(zt, tight, np.array([0.0, 0.9, math.pi / 2]), tight, **kw)[0]


def test_odometry_check_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="min_score"):
        OdometryCheckConfig(min_score=1.5)
    with pytest.raises(ValueError, match="chi2"):
        OdometryCheckConfig(chi2=0.0)


def _drive(
    slip: dict[int, float],
    *,
    check: bool,
    seed: int = 5,
    odometry_check: OdometryCheckConfig | None = None,
) -> tuple[GroundStation, float]:
    """A robot drives 16 m along a street of a random world; on the steps in ``slip`` its
    wheels report ``1 + slip`` times the distance the body moved. Returns the station and the
    final position error (m) of its estimate."""
    rng = np.random.default_rng(seed)
    world = random_world(rng, size_m=40.0)
    truth = np.array(
        [(x, 0.3 * math.sin(x / 3.0), 0.1 * math.cos(x / 3.0)) for x in np.arange(-8.0, 8.01, 1.0)]
    )
    odom = [truth[0]]
    for i in range(1, len(truth)):
        step = np.asarray(relative(truth[i - 1], truth[i]), dtype=float)
        step[:2] *= 1.0 + slip.get(i, 0.0)
        odom.append(compose(odom[-1], step))
    cfg = GroundStationConfig(odometry_check=odometry_check or OdometryCheckConfig(enabled=check))
    gs = GroundStation(cfg)
    cov = covariance_to_upper(ODOM_COV)
    for i, pose in enumerate(odom):
        delta = (0.0, 0.0, 0.0) if i == 0 else tuple(relative(odom[i - 1], pose))
        node = PoseNode(i, float(i), tuple(pose), delta, (0.0,) * 6 if i == 0 else cov)  # type: ignore[arg-type]
        grid, origin = scan_grid(scan_points(world, truth[i], rng=rng))
        msg = TerrainGrid(i, 0.1, encode_grid(grid, origin_cells=origin_cells_of(origin, 0.1)))
        assert gs.handle(0, node, now_s=float(i)) and gs.handle(0, msg, now_s=float(i))
        gs.step(now_s=float(i), budget_s=0.0)  # no loop closing: the check alone
    _, poses = gs.graph.poses(0)
    return gs, float(np.hypot(*(poses[-1, :2] - truth[-1, :2])))


def test_a_slipping_step_is_replaced_by_its_scan_match_and_a_clean_drive_is_untouched() -> None:
    slip = {5: 0.3, 6: 0.3, 7: 0.3, 8: 0.3}  # four steps of 1 m each read as 1.3 m
    plain, err_plain = _drive(slip, check=False)
    checked, err_checked = _drive(slip, check=True)
    assert err_plain > 1.0  # the slip went straight into the map
    assert checked.stats.odometry_replaced >= 3
    assert err_checked < 0.3 * err_plain
    # the replaced edges are the slipping ones and now hold the body's motion
    for e in checked.graph.edges(Provenance.ODOMETRY):
        i = e.key_b & 0xFFFFFFFF  # type: ignore[operator]
        if i in slip and abs(float(np.hypot(*e.z[:2])) - 1.0) < 0.1:
            assert e.covariance[0, 0] < 0.1**2
    assert plain.stats.odometry_checks == 0
    clean, err_clean = _drive({}, check=True)
    assert clean.stats.odometry_checks == 16 and clean.stats.odometry_replaced == 0
    assert err_clean < 0.05


def test_a_match_farther_from_the_step_than_slip_can_take_the_robot_is_not_taken() -> None:
    # step 5: the match puts the body 1 m ahead where the wheels say 1 m back, a difference of
    # 2 m on a 1 m step, which no slip makes (in the mission: a corridor's look-alike 1.7 m
    # behind a 1.2 m step); the same match is taken when the bound allows it
    gs, _ = _drive({5: -2.0}, check=True)
    assert gs.stats.odometry_implausible == 1 and gs.stats.odometry_replaced == 0
    loose = OdometryCheckConfig(max_slip_frac=3.0)
    gs, err = _drive({5: -2.0}, check=True, odometry_check=loose)
    assert gs.stats.odometry_implausible == 0 and gs.stats.odometry_replaced == 1
    assert err < 0.3
    with pytest.raises(ValueError, match="max_slip_frac"):
        OdometryCheckConfig(max_slip_frac=0.0)


def _teammates(seen_at_s: float) -> tuple[GroundStation, np.ndarray, np.ndarray, np.ndarray]:
    """Robot 0 (map) stands; robot 1 drives 1.2 m steps along x from (2, -1), a node at each
    whole second; robot 0 sees robot 1 at ``seen_at_s`` while it starts and stops between
    two of its nodes (it moved only in the first tenth of the interval)."""
    gs = GroundStation(GroundStationConfig(robots=(0, 1), fiducials_link_only=False))
    gs.add_start_hint(1, map_from_odom=(2.0, -1.0, 0.0), sigma_xy_m=0.3, sigma_yaw_rad=0.05)
    path0 = np.zeros((6, 3))
    path1 = np.array([(1.2 * k, 0.0, 0.0) for k in range(6)])
    cov = covariance_to_upper(ODOM_COV)
    for i in range(6):
        for rid, path in ((0, path0), (1, path1)):
            delta = (0.0, 0.0, 0.0) if i == 0 else tuple(relative(path[i - 1], path[i]))
            node = PoseNode(i, float(i), tuple(path[i]), delta, (0.0,) * 6 if i == 0 else cov)  # type: ignore[arg-type]
            assert gs.handle(rid, node, now_s=float(i))
    k = int(seen_at_s)
    true_in_odom1 = path1[k + 1] if seen_at_s > k else path1[k]  # early at the next node
    seen = relative(path0[0], compose(np.array([2.0, -1.0, 0.0]), true_in_odom1))
    tag_cov = np.diag([0.02**2, 0.02**2, 0.01**2])
    tag = FiducialObservation(0, seen_at_s, 1, 5, tuple(seen), covariance_to_upper(tag_cov))  # type: ignore[arg-type]
    assert gs.handle(0, tag, now_s=6.0)
    gs.step(now_s=6.0)
    return gs, path1, seen, tag_cov


def test_a_fiducial_is_carried_to_the_teammate_node_with_its_step_as_uncertainty() -> None:
    gs, path1, _, tag_cov = _teammates(2.5)
    assert gs.stats.fiducials == 1
    (edge,) = gs.graph.edges(Provenance.FIDUCIAL)
    assert edge.key_b == gs.key_of(1, 2)  # the last node before the sighting
    # the true relation of node 2 to the observer, and the edge's error within ~2 sigma
    true_z = relative(np.zeros(3), compose(np.array([2.0, -1.0, 0.0]), path1[2]))
    err = np.asarray(edge.z) - true_z
    sigma_x = math.sqrt(edge.covariance[0, 0])
    assert abs(err[0]) <= 2.0 * sigma_x and sigma_x > 0.3  # along the step: uncertain
    assert edge.covariance[1, 1] == pytest.approx(tag_cov[1, 1])  # across it: the tag's
    # the estimate of robot 1 stays where the hint and the tag agree (no jump of a step)
    _, poses = gs.graph.poses(1)
    assert np.all(np.abs(poses[:, 1] - (-1.0)) < 0.1)


def test_a_fiducial_at_the_teammate_node_time_is_exact() -> None:
    gs, path1, _, tag_cov = _teammates(3.0)
    (edge,) = gs.graph.edges(Provenance.FIDUCIAL)
    assert edge.key_b == gs.key_of(1, 3)
    np.testing.assert_allclose(edge.covariance, tag_cov, atol=1e-9)


def test_a_fiducial_between_telemetry_poses_of_a_standing_teammate_is_exact() -> None:
    """Robot 1 stands at its node 2 from t=2 s to t=2.9 s (its telemetry says so), then
    drives on: a sighting at 2.5 s is carried to node 2 exactly, with the tag's covariance."""
    from protocol.messages import AutonomyMode, Telemetry

    gs = GroundStation(GroundStationConfig(robots=(0, 1), fiducials_link_only=False))
    gs.add_start_hint(1, map_from_odom=(2.0, -1.0, 0.0), sigma_xy_m=0.3, sigma_yaw_rad=0.05)
    path0 = np.zeros((6, 3))
    path1 = np.array([(1.2 * k, 0.0, 0.0) for k in range(6)])
    cov = covariance_to_upper(ODOM_COV)
    for i in range(6):
        for rid, path in ((0, path0), (1, path1)):
            delta = (0.0, 0.0, 0.0) if i == 0 else tuple(relative(path[i - 1], path[i]))
            node = PoseNode(i, float(i), tuple(path[i]), delta, (0.0,) * 6 if i == 0 else cov)  # type: ignore[arg-type]
            assert gs.handle(rid, node, now_s=float(i))
        if i == 2:
            for t in (2.3, 2.9):  # standing at node 2's place
                tel = Telemetry(
                    t, tuple(path1[2]), (0.0, 0.0), (0.0, 0.0), 1.0, AutonomyMode.IDLE, 0
                )  # type: ignore[arg-type]
                assert gs.handle(1, tel, now_s=t)
    seen = relative(path0[0], compose(np.array([2.0, -1.0, 0.0]), path1[2]))
    tag_cov = np.diag([0.02**2, 0.02**2, 0.01**2])
    tag = FiducialObservation(0, 2.5, 1, 5, tuple(seen), covariance_to_upper(tag_cov))  # type: ignore[arg-type]
    assert gs.handle(0, tag, now_s=6.0)
    gs.step(now_s=6.0)
    (edge,) = gs.graph.edges(Provenance.FIDUCIAL)
    assert edge.key_b == gs.key_of(1, 2)
    np.testing.assert_allclose(edge.z, seen, atol=1e-6)
    np.testing.assert_allclose(edge.covariance, tag_cov, atol=1e-9)


def test_a_fiducial_read_off_the_wrong_face_is_refused_and_a_drifted_one_taken() -> None:
    """Robots the map already relates (both anchored by start hints): a sighting turned by
    176 deg (a tag read off the wrong face) is refused with a reason; one 1 m and 10 deg from
    the estimate (the drift a sighting corrects) is an edge; with the gate off both are."""

    def sighting(gate_chi2: float, dz: tuple[float, float, float]) -> GroundStation:
        cfg = GroundStationConfig(robots=(0, 1), fiducial_gate_chi2=gate_chi2)
        gs = GroundStation(cfg)
        gs.add_start_hint(1, map_from_odom=(2.0, -1.0, 0.0), sigma_xy_m=0.3, sigma_yaw_rad=0.05)
        for rid in (0, 1):
            node = PoseNode(0, 0.0, (0.0, 0.0, 0.0), (0.0,) * 3, (0.0,) * 6)  # type: ignore[arg-type]
            assert gs.handle(rid, node, now_s=0.0)
        seen = np.array([2.0, -1.0, 0.0]) + np.array(dz)  # robot 1's node 0 from robot 0's
        cov = covariance_to_upper(np.diag([0.02**2, 0.02**2, 0.01**2]))
        gs.handle(0, FiducialObservation(0, 0.0, 1, 5, tuple(seen), cov), now_s=0.5)  # type: ignore[arg-type]
        return gs

    flipped = sighting(16.27, (1.5, 0.3, math.radians(176.0)))
    assert flipped.stats.rejected["fiducial_inconsistent"] == 1
    assert not flipped.graph.edges(Provenance.FIDUCIAL)
    assert "176 deg from where the map has that teammate" in flipped.stats.errors[-1]
    drifted = sighting(16.27, (1.0, 0.0, math.radians(10.0)))
    assert len(drifted.graph.edges(Provenance.FIDUCIAL)) == 1
    ungated = sighting(0.0, (1.5, 0.3, math.radians(176.0)))
    assert len(ungated.graph.edges(Provenance.FIDUCIAL)) == 1
    with pytest.raises(ValueError, match="fiducial_gate_chi2"):
        GroundStationConfig(fiducial_gate_chi2=-1.0)


def test_a_fiducial_of_a_long_silent_teammate_is_refused_as_stale() -> None:
    """Robot 1's last pose node is 30 s older than the sighting: its stand-in could be 30 m
    away, so the sighting says nothing and is refused with its reason. (A stand-in's heading
    is loose by construction: the heading bound is lifted so the staleness rule alone acts.)"""
    gs = GroundStation(GroundStationConfig(robots=(0, 1), fiducial_max_sigma_yaw_rad=2 * math.pi))
    gs.add_start_hint(1, map_from_odom=(2.0, -1.0, 0.0), sigma_xy_m=0.3, sigma_yaw_rad=0.05)
    for rid in (0, 1):
        node = PoseNode(0, 0.0, (0.0, 0.0, 0.0), (0.0,) * 3, (0.0,) * 6)  # type: ignore[arg-type]
        assert gs.handle(rid, node, now_s=0.0)
    cov = covariance_to_upper(np.diag([0.02**2, 0.02**2, 0.01**2]))
    for seen_s, stale in ((1.0, 0), (30.0, 1)):
        tag = FiducialObservation(0, seen_s, 1, 5, (2.0, -1.0, 0.0), cov)  # type: ignore[arg-type]
        gs.handle(0, tag, now_s=seen_s)
        gs.step(now_s=seen_s + 6.0)  # it waited fiducial_wait_s for a later node of robot 1
        assert gs.stats.rejected["fiducial_stale"] == stale
    assert len(gs.graph.edges(Provenance.FIDUCIAL)) == 1
    assert "known only to" in gs.stats.errors[-1]
