"""Laser-aided odometry (robot.odometry.scan_odometry): a turn-scale error in the odometry is
taken out by the scans; a step without a usable scan keeps the odometry."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.se2 import compose
from robot.odometry.scan_odometry import (
    ScanOdometry,
    ScanOdometryConfig,
    ScanOdometryStats,
    constant_velocity_window,
    match_step,
    refine_odometry,
)
from tests.robot.laser_room import box_segments, scan_in_base

#: A 12 x 8 m room with three boxes (x0, y0, x1, y1): asymmetric, so every pose looks different.
_BOXES = [
    (-6.0, -4.0, 6.0, 4.0),
    (-3.0, 1.5, -2.2, 2.3),
    (2.0, -2.5, 3.2, -1.9),
    (4.5, 2.0, 5.0, 3.5),
]


def _segments() -> np.ndarray:
    return box_segments(_BOXES)


def _scan(pose: np.ndarray, segs: np.ndarray, beams: int = 181) -> np.ndarray:
    """Endpoints in base of a 180-degree laser at ``pose`` (nearest wall per beam)."""
    ang = np.linspace(-math.pi / 2, math.pi / 2, beams)
    return scan_in_base(pose, segs, ang, max_range_m=10.0)


def _chain(steps: np.ndarray, start: np.ndarray) -> np.ndarray:
    out = [start]
    for dx, dy, dyaw in steps:
        x, y, yaw = out[-1]
        c, s = math.cos(yaw), math.sin(yaw)
        out.append(np.array([x + c * dx - s * dy, y + s * dx + c * dy, yaw + dyaw]))
    return np.array(out)


def _truth() -> np.ndarray:
    """A drive with a full turn in place and a curve: 0.1 m / 3 deg steps."""
    steps = [(0.1, 0.0, 0.0)] * 10 + [(0.0, 0.0, math.radians(6.0))] * 30
    steps += [(0.1, 0.0, math.radians(3.0))] * 20
    return _chain(np.array(steps), np.array([-4.0, -1.0, 0.0]))


def test_a_turn_scale_error_is_taken_out_by_the_scans() -> None:
    truth = _truth()
    segs = _segments()
    scans = [_scan(p, segs) for p in truth]
    true_steps = np.array([_rel(a, b) for a, b in zip(truth[:-1], truth[1:], strict=True)])
    odom = _chain(true_steps * [1.0, 1.0, 1.08], truth[0])  # a gyro reading turns 8 % long
    stats = ScanOdometryStats()
    refined = refine_odometry(odom, scans, ScanOdometryConfig(), stats)
    assert stats.matched >= len(truth) - 3
    end_yaw_odom = abs(_wrap(odom[-1, 2] - truth[-1, 2]))
    end_yaw = abs(_wrap(refined[-1, 2] - truth[-1, 2]))
    assert end_yaw_odom > math.radians(19.0)  # 8 % of 240 deg
    assert end_yaw < math.radians(1.5)
    assert np.hypot(*(refined[-1, :2] - truth[-1, :2])) < 0.15
    assert np.allclose(refined[0], odom[0])


def test_a_step_without_a_scan_keeps_the_odometry() -> None:
    truth = _truth()[:12]
    segs = _segments()
    scans = [_scan(p, segs) for p in truth]
    scans[5] = np.zeros((0, 2))  # the laser lost one sweep
    odom = truth + np.array([0.0, 0.0, 0.0])
    stats = ScanOdometryStats()
    refined = refine_odometry(odom, scans, ScanOdometryConfig(), stats)
    assert stats.weak == 1
    step_odom = _rel(odom[4], odom[5])
    step_refined = _rel(refined[4], refined[5])
    assert np.allclose(step_odom, step_refined, atol=1e-9)
    # a step across lost scans (longer than max_step_m) is not matched either
    jumped = refine_odometry(
        odom,
        scans,
        ScanOdometryConfig(max_step_m=0.05, max_step_rad=0.01),
        stats := ScanOdometryStats(),
    )
    assert stats.matched == 0 and np.allclose(jumped, odom)
    # matched steps of exact odometry stay within the search's resolution of it
    assert np.abs(refined[:, :2] - truth[:, :2]).max() < 0.03


def test_a_corridor_keeps_the_odometry_along_it_and_measures_the_heading() -> None:
    # two long parallel walls: along the corridor the scan says nothing
    segs = np.array([(-50.0, -1.0, 50.0, -1.0), (-50.0, 1.0, 50.0, 1.0)])
    pose = np.array([0.0, 0.0, 0.0])
    scan_map = _scan(pose, segs, beams=361)
    truth_next = np.array([0.1, 0.0, 0.0])
    predicted = np.array([0.2, 0.05, math.radians(1.5)])  # 0.1 m long, 5 cm aside, 1.5 deg off
    found = match_step(scan_map, _scan(truth_next, segs, 361), predicted, 0.0, ScanOdometryConfig())
    assert found is not None
    pose_m, cov = found
    assert abs(pose_m[1] - truth_next[1]) < 0.03
    assert abs(pose_m[2] - truth_next[2]) < math.radians(0.3)
    assert cov[0, 0] > 10 * cov[1, 1]  # along the corridor: flat response


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="2 scans for 3"):
        refine_odometry(np.zeros((3, 3)), [np.zeros((0, 2))] * 2)
    with pytest.raises(ValueError, match="sigma_m"):
        ScanOdometryConfig(sigma_m=0.0)
    assert refine_odometry(np.zeros((0, 3)), []).shape == (0, 3)


def _rel(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, _wrap(b[2] - a[2])])


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


def test_one_scan_at_a_time_holds_a_drifting_heading() -> None:
    """ScanOdometry, as the robot runs it: each sweep's correction composed onto the odometry
    pose it was taken at; a gyro drifting 0.3 deg a sweep (18 deg over the drive) is held
    to the scans' accuracy, and a scan of nothing is no correction."""
    truth = _truth()
    segs = _segments()
    aid = ScanOdometry(ScanOdometryConfig())
    pose = truth[0].copy()
    drift = math.radians(0.3)
    errors, innovations = [], []
    for k, true_pose in enumerate(truth):
        if k:
            step = _rel(truth[k - 1], true_pose)
            pose = compose(pose, step + np.array([0.0, 0.0, drift]))
        found = aid.observe(pose, _scan(true_pose, segs), 1.25 * k)
        if found is not None:
            pose = compose(pose, np.asarray(found.correction))
            assert found.since_s == pytest.approx(1.25)
            innovations.append(found.innovation_yaw_rad)
        errors.append(abs(_wrap(pose[2] - true_pose[2])))
    assert aid.stats.matched >= len(truth) - 3 and aid.stats.rejected == 0
    assert drift * len(truth) > math.radians(18.0)
    assert max(errors) < math.radians(1.0)
    # the raw innovation is the drift since the last sweep, seen by the scan
    assert abs(np.median(innovations) + drift) < math.radians(0.1)
    assert aid.observe(pose, np.zeros((0, 2)), 1.25 * len(truth)) is None
    with pytest.raises(ValueError, match="scan must be"):
        aid.observe(pose, np.zeros((3, 3)), 1e3)


def test_one_scan_at_a_time_refuses_an_implausible_heading() -> None:
    """A match whose heading the odometry cannot have drifted to (the room seen turned by
    1.5 deg in one sweep of a good gyro) is refused and counted, not applied."""
    truth = _truth()[:12]
    segs = _segments()
    tight = ScanOdometryConfig(odometry_sigma_rad=math.radians(0.05), odometry_turn_share_sigma=0.0)
    aid = ScanOdometry(tight)
    for k, true_pose in enumerate(truth[:-1]):
        aid.observe(true_pose, _scan(true_pose, segs), float(k))
    assert aid.stats.matched == len(truth) - 2
    wrong = truth[-1] + np.array([0.0, 0.0, math.radians(1.5)])
    assert aid.observe(wrong, _scan(truth[-1], segs), 20.0) is None
    assert aid.stats.rejected == 1


def test_the_likelihood_field_equals_the_gaussian_of_the_distance_everywhere() -> None:
    # the field takes an exp only near the returns (beyond, float32 holds exactly 0): it
    # must equal the Gaussian of the whole distance transform, cell for cell
    import cv2

    from robot.odometry.scan_odometry import _field

    cfg = ScanOdometryConfig()
    pts = np.vstack([_scan(p, _segments()) for p in _truth()[::15]])
    field, x0, y0 = _field(pts, cfg)
    res = cfg.field_resolution_m
    occupied = np.full(field.shape, 255, dtype=np.uint8)
    rows = ((pts[:, 1] - y0) / res).astype(np.int64)
    occupied[rows, ((pts[:, 0] - x0) / res).astype(np.int64)] = 0
    dist = cv2.distanceTransform(occupied, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * res
    want = np.exp(-0.5 * (dist / cfg.sigma_m) ** 2).astype(np.float32)
    assert field.dtype == np.float32
    np.testing.assert_array_equal(field, want)
    assert 0.05 < float(np.mean(field > 0)) < 0.95  # both kinds of cell were there


def test_thinning_keeps_the_first_point_of_each_cell_as_unique_rows_do() -> None:
    from robot.odometry.scan_odometry import _thin

    rng = np.random.default_rng(1)
    for n in (1, 2, 7, 300, 5000):
        pts = rng.normal(0.0, 6.0, (n, 2))
        pts[n // 2 :] = pts[: n - n // 2] + rng.normal(0.0, 0.03, (n - n // 2, 2))
        cells = np.floor(pts / 0.1).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        want = pts[np.sort(first)]
        if len(want) > 240:
            want = want[np.linspace(0, len(want) - 1, 240).astype(np.int64)]
        np.testing.assert_array_equal(_thin(pts, 240, 0.1), want)


def test_absent_odometry_is_bridged_by_the_laser() -> None:
    """The encoders drop out for 15 steps (the odometry frozen, the scans still coming): a
    constant-velocity prior and a widened search carry the chain through the full turn in
    place; with no scans there either, the prior's steps are kept and listed."""
    truth = _truth()
    segs = _segments()
    scans = [_scan(p, segs) for p in truth]
    odom = truth.copy()
    odom[20:35] = odom[19]  # frozen from step 20 to 34
    after = np.array([_rel(truth[34], p) for p in truth[35:]])
    odom[35:] = np.array([compose(odom[19], a) for a in after])
    absent = np.zeros(len(truth), dtype=bool)
    absent[20:35] = True
    stats = ScanOdometryStats()
    refined = refine_odometry(odom, scans, ScanOdometryConfig(), stats, absent=absent)
    assert stats.bridged == 15 and stats.prior_steps == []
    across = _rel(refined[19], refined[35])
    true_across = _rel(truth[19], truth[35])
    # 96 deg turned in place on the laser alone (measured: 9 cm off at the end)
    assert np.hypot(*(across[:2] - true_across[:2])) < 0.15
    assert abs(_wrap(across[2] - true_across[2])) < math.radians(1.0)
    frozen = refine_odometry(odom, scans, ScanOdometryConfig())  # told nothing: a standstill
    assert abs(_wrap(_rel(frozen[19], frozen[35])[2] - true_across[2])) > math.radians(60)
    # without scans in the stretch the prior (the last step, here a 6 deg turn) is kept
    blind = [s if not absent[k] else np.zeros((0, 2)) for k, s in enumerate(scans)]
    stats = ScanOdometryStats()
    kept = refine_odometry(odom, blind, ScanOdometryConfig(), stats, absent=absent)
    assert stats.prior_steps == list(range(20, 35)) and stats.bridged == 0
    prior = _rel(kept[19], kept[20])
    np.testing.assert_allclose(prior, _rel(kept[18], kept[19]), atol=1e-9)


def test_the_bridge_window_is_the_logs_own_departure_from_constant_velocity() -> None:
    cfg = ScanOdometryConfig()
    steady = _chain(np.array([(0.1, 0.0, 0.0)] * 30), np.zeros(3))
    none = np.zeros(len(steady), dtype=bool)
    window = constant_velocity_window(steady, none, None, cfg)
    assert window.half_xy_m == cfg.max_shift_m and window.half_yaw_rad == cfg.min_turn_window_rad
    jerky = _chain(np.array([(0.1, 0.0, 0.0), (0.5, 0.0, 0.3)] * 15), np.zeros(3))
    window = constant_velocity_window(jerky, none, None, cfg)
    assert window.half_xy_m == pytest.approx(cfg.bridge_margin * 0.4)
    assert window.half_yaw_rad == pytest.approx(cfg.bridge_margin * 0.3)
    # the steps that are absent say nothing about the robot's motion
    gone = none.copy()
    gone[1:] = True
    assert constant_velocity_window(jerky, gone, None, cfg).half_xy_m == cfg.max_step_m
    with pytest.raises(ValueError, match="absent has 3 scans"):
        refine_odometry(np.zeros((4, 3)), [np.zeros((0, 2))] * 4, absent=np.zeros(3, bool))
