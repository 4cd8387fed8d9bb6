"""Path following with limits, keep-out disks, stuck detection and traversability."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.messages import Hazard, HazardUpdate, ObjectKind, RobotFrame
from protocol.se2 import compose
from robot.control.keepout import KeepoutConfig, keepout_disks_in_odom, rasterize_disks
from robot.control.path_follower import (
    FollowerConfig,
    FollowStatus,
    PathFollower,
    motion_enters_keepout,
)
from robot.control.stuck_detector import StuckConfig, StuckDetector
from robot.control.traversability import (
    TraversabilityConfig,
    TraversabilityMap,
    traversability,
)
from robot.planning.planner import PathPlanner
from robot.terrain.grid import DRIVABLE, OBSTACLE, GridGeometry


def simulate(follower: PathFollower, pose: np.ndarray, *, steps: int, dt: float = 0.05, disks=None):
    """Unicycle kinematics driven by the follower; returns poses, commands, last status."""
    poses, cmds, status = [pose.copy()], [], FollowStatus.IDLE
    for _ in range(steps):
        cmd = follower.step(pose, dt, keepout_disks_in_odom=disks)
        cmds.append((cmd.linear_m_s, cmd.angular_rad_s))
        status = cmd.status
        pose = compose(pose, np.array([cmd.linear_m_s * dt, 0.0, cmd.angular_rad_s * dt]))
        poses.append(pose.copy())
        if status is FollowStatus.ARRIVED:
            break
    return np.array(poses), np.array(cmds), status


def test_follows_an_l_shaped_path_within_limits() -> None:
    cfg = FollowerConfig()
    follower = PathFollower(cfg)
    path = np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]])
    follower.set_path(path)
    poses, cmds, status = simulate(follower, np.zeros(3), steps=2000)
    assert status is FollowStatus.ARRIVED
    assert np.linalg.norm(poses[-1, :2] - path[-1]) <= cfg.goal_tolerance_m + 0.05
    # never far from the path (the corner is cut by at most about the lookahead)
    seg_d = [
        min(
            np.linalg.norm(p - np.clip(p, [0, 0], [5, 0])),
            np.linalg.norm(p - np.clip(p, [5, 0], [5, 5])),
        )
        for p in poses[:, :2]
    ]
    assert max(seg_d) < cfg.lookahead_m
    dv = np.abs(np.diff(cmds[:, 0])) / 0.05
    dw = np.abs(np.diff(cmds[:, 1])) / 0.05
    assert cmds[:, 0].max() <= cfg.max_speed_m_s + 1e-9
    assert np.abs(cmds[:, 1]).max() <= cfg.max_yaw_rate_rad_s + 1e-9
    assert dv.max() <= cfg.max_accel_m_s2 + 1e-9 and dw.max() <= cfg.max_yaw_accel_rad_s2 + 1e-9


def test_turns_in_place_towards_a_goal_behind() -> None:
    follower = PathFollower()
    follower.set_path(np.array([[-3.0, 0.0]]))
    _, cmds, status = simulate(follower, np.zeros(3), steps=20)
    assert np.allclose(cmds[:10, 0], 0.0) and np.all(np.abs(cmds[5:10, 1]) > 0.1)


def test_never_enters_a_keepout_disk_on_its_path() -> None:
    follower = PathFollower()
    follower.set_path(np.array([[0.0, 0.0], [10.0, 0.0]]))
    disks = np.array([[6.0, 0.0, 3.25]])  # a static OOI at 6 m: 2.5 m + 0.75 m margin
    poses, _, status = simulate(follower, np.zeros(3), steps=600, disks=disks)
    d = np.hypot(poses[:, 0] - 6.0, poses[:, 1])
    assert d.min() >= 3.25 - 1e-6
    assert status is FollowStatus.BLOCKED


def test_keepout_check_lets_a_robot_leave_a_disk() -> None:
    disks = np.array([[0.0, 0.0, 3.0]])
    pose = np.array([1.0, 0.0, 0.0])  # inside, facing away
    assert not motion_enters_keepout(pose, 0.5, 0.0, disks, horizon_s=1.0)
    assert motion_enters_keepout(np.array([1.0, 0.0, math.pi]), 0.5, 0.0, disks, horizon_s=1.0)


def test_hazards_convert_from_map_with_this_robots_frame() -> None:
    update = HazardUpdate(
        10.0,
        [
            Hazard(1, ObjectKind.STATIC_OOI, (10.0, 0.0), 0.0),
            Hazard(2, ObjectKind.HOSTILE, (0.0, 10.0), 6.0),
        ],
        [RobotFrame(3, (10.0, 0.0, math.pi / 2)), RobotFrame(4, (0.0, 0.0, 0.0))],
    )
    cfg = KeepoutConfig()
    disks = keepout_disks_in_odom(
        3, update, [(ObjectKind.HOSTILE, 1.0, 1.0), (ObjectKind.CIVILIAN, 2.0, 2.0)], config=cfg
    )
    # map_from_odom = (10, 0, 90°): the hazard at map (10, 0) is the odom origin
    assert np.allclose(disks[0], [0.0, 0.0, 2.5 + 0.75], atol=1e-5)
    # map (0, 10) -> odom: rotate (-10, 10) by -90° -> (10, 10); a larger reported radius wins
    assert np.allclose(disks[1], [10.0, 10.0, 6.0 + 0.75], atol=1e-4)
    assert np.allclose(disks[2], [1.0, 1.0, 5.75])  # own hostile detection; civilians add none
    assert len(disks) == 3
    # a robot the update does not place only keeps its own detections
    assert keepout_disks_in_odom(9, update).shape == (0, 3)


def test_rasterize_disks_marks_cell_centres_inside() -> None:
    grid = np.zeros((40, 40), dtype=bool)
    out = rasterize_disks(
        grid, np.array([[2.0, 2.0, 1.0]]), origin_in_odom=(0.0, 0.0), resolution_m=0.1
    )
    rows, cols = np.nonzero(out)
    centres = np.stack([(cols + 0.5) * 0.1, (rows + 0.5) * 0.1], axis=1)
    assert np.all(np.hypot(centres[:, 0] - 2.0, centres[:, 1] - 2.0) <= 1.0 + 1e-9)
    assert abs(out.sum() - math.pi * 100) < 20  # about pi r^2 / cell area
    assert not grid.any()  # the input is not modified


def test_stuck_when_commanded_but_not_moving() -> None:
    det = StuckDetector()
    pose = np.zeros(3)
    assert not any(det.update(0.1 * k, pose, 0.5, 0.0) for k in range(37))  # < 0.95 window
    assert det.update(4.0, pose, 0.5, 0.0)
    det.reset()
    moving = [det.update(0.1 * k, np.array([0.05 * k, 0.0, 0.0]), 0.5, 0.0) for k in range(100)]
    assert not any(moving)
    assert not det.update(20.0, pose, 0.0, 0.0)


def _stall(det: StuckDetector, t0: float, pose: np.ndarray, v: float, w: float) -> bool:
    """Command ``(v, w)`` for a detection window at ``pose`` without moving; the detection."""
    hit = any(det.update(t0 + 0.1 * k, pose, v, w) for k in range(41))
    det.reset()
    return hit


def test_stuck_escape_turns_against_the_refused_turn_then_starts_over_elsewhere() -> None:
    # a robot wedged diagonally in a doorway (small world seed 7): every clockwise turn and
    # straight move refused; backing up straight (the old recovery) forever kept it there
    det = StuckDetector(StuckConfig(escape_speed_m_s=0.3, escape_turn_rad_s=0.6))
    pose = np.array([3.0, 1.0, -2.17])
    assert _stall(det, 0.0, pose, 0.0, -1.2)
    assert det.escape_command == (-0.3, 0.0)  # first: straight back
    assert _stall(det, 10.0, pose, 0.0, -1.2)
    assert det.escape_command == (-0.3, 0.6)  # then back, turning counter-clockwise
    assert _stall(det, 20.0, pose, 0.0, -1.2)
    assert det.escape_command == (0.3, 0.6)  # then forward, counter-clockwise
    assert _stall(det, 30.0, pose, 0.0, -1.2)
    assert det.escape_command == (-0.3, -0.6)
    # stuck again 5 m away: another obstacle, the sequence starts over
    assert _stall(det, 40.0, pose + np.array([5.0, 0.0, 0.0]), 0.8, 0.0)
    assert det.escape_command == (-0.3, 0.0)
    assert _stall(det, 50.0, pose + np.array([5.0, 0.0, 0.0]), 0.8, 0.0)
    assert det.escape_command == (-0.3, 0.6)  # no turn was refused: counter-clockwise first


def test_stuck_marks_the_refused_ground_ahead_for_a_while() -> None:
    cfg = StuckConfig(mark_ahead_m=0.45, mark_half_width_m=0.3, remember_s=90.0)
    det = StuckDetector(cfg)
    geometry = GridGeometry((0.0, 0.0), 0.05, 80, 80)
    # a turn in place that is refused says nothing about the ground ahead
    assert _stall(det, 0.0, np.array([2.0, 2.0, 0.0]), 0.0, 1.0)
    assert not det.blocked_mask(geometry, 5.0).any()
    # pushing north (yaw pi/2) at an edge the map does not show
    assert _stall(det, 10.0, np.array([2.0, 2.0, math.pi / 2]), 0.8, 0.0)
    mask = det.blocked_mask(geometry, 15.0)
    centres = geometry.center_of(np.argwhere(mask))
    assert len(centres) > 0
    assert np.all(centres[:, 1] >= 2.0 + 0.45 - 0.05)  # ahead of the body's front
    assert np.all(centres[:, 1] <= 2.0 + 0.45 + 0.15)
    assert np.all(np.abs(centres[:, 0] - 2.0) <= 0.3 + 0.05)  # about the footprint's width
    assert centres[:, 0].max() - centres[:, 0].min() >= 0.5
    assert not det.blocked_mask(geometry, 10.0 + 4.0 + 91.0).any()  # forgotten after remember_s
    # reversing into something marks behind
    det2 = StuckDetector(cfg)
    assert _stall(det2, 0.0, np.array([2.0, 2.0, 0.0]), -0.3, 0.0)
    centres = geometry.center_of(np.argwhere(det2.blocked_mask(geometry, 5.0)))
    assert np.all(centres[:, 0] < 2.0 - 0.4)


def test_a_refused_edge_makes_the_planner_go_round() -> None:
    # a dock top the LIDAR sees as flat drivable ground to its edge: the goal straight ahead,
    # off the edge; the body refuses to go. With the edge marked, the plan goes another way
    geometry = GridGeometry((0.0, 0.0), 0.05, 120, 120)
    classes = np.full(geometry.shape, DRIVABLE, dtype=np.uint8)
    start, goal = np.array([3.0, 2.0]), np.array([3.0, 5.0])
    planner = PathPlanner()
    straight = planner.plan(classes, geometry, start, goal)
    assert straight.ok and straight.length_m < 3.1
    det = StuckDetector()
    assert _stall(det, 0.0, np.array([3.0, 2.0, math.pi / 2]), 0.9, 0.0)
    marked = classes.copy()
    marked[det.blocked_mask(geometry, 5.0)] = OBSTACLE
    around = planner.plan(marked, geometry, start + np.array([0.0, -0.45]), goal)
    assert around.ok
    near_edge = np.abs(around.path_in_odom[:, 1] - 2.5) < 0.1
    assert np.all(np.abs(around.path_in_odom[near_edge, 0] - 3.0) > 0.6)  # not through it


def test_traversability_eq1_and_learning() -> None:
    assert traversability(0.25, 0.5) == pytest.approx(0.5)
    assert traversability(0.9, 0.5) == 1.0
    assert traversability(0.3, 0.0) == 0.0
    cfg = TraversabilityConfig(resolution_m=1.0, spread_m=0.0, learning_rate=0.2)
    tm = TraversabilityMap(cfg)
    for _ in range(30):  # sand: half the requested speed
        tm.observe(2.5, 3.5, measured_m_s=0.3, requested_m_s=0.6)
        tm.observe(5.5, 5.5, measured_m_s=0.6, requested_m_s=0.6)
    tm.observe(7.5, 7.5, measured_m_s=0.0, requested_m_s=0.1)  # too slow to say anything
    assert len(tm) == 2
    cost = tm.cost_multiplier(GridGeometry((0.0, 0.0), 1.0, 10, 10))
    assert cost[3, 2] == pytest.approx(1 + 4.0 * 0.5, rel=0.01)
    assert cost[5, 5] == pytest.approx(1.0) and cost[0, 0] == 1.0
    # on a finer planning grid elsewhere in odom, the coarse cell covers its fine cells
    fine = tm.cost_multiplier(GridGeometry((2.0, 3.0), 0.25, 8, 8))
    assert (fine[:4, :4] > 2.9).all() and (fine[4:, :] == 1.0).all() and (fine[:, 4:] == 1.0).all()
    # an observation spreads over spread_m
    spread = TraversabilityMap(TraversabilityConfig(resolution_m=0.5, spread_m=1.0))
    spread.observe(0.0, 0.0, measured_m_s=0.5, requested_m_s=1.0)
    assert spread.t_at(0.8, 0.3) < 1.0 and spread.t_at(1.8, 0.0) == 1.0
    with pytest.raises(ValueError, match="non-finite"):
        tm.observe(1.0, 1.0, measured_m_s=math.nan, requested_m_s=1.0)
    with pytest.raises(ValueError, match="learning_rate"):
        TraversabilityConfig(learning_rate=0.0)


def test_planner_goes_around_slippery_ground_when_the_detour_is_cheap() -> None:
    geo = GridGeometry((-5.0, -5.0), 0.05, 200, 200)
    classes = np.full(geo.shape, DRIVABLE, dtype=np.uint8)
    tm = TraversabilityMap(TraversabilityConfig(resolution_m=0.5, spread_m=0.0, learning_rate=1.0))
    for x in np.arange(-0.75, 1.0, 0.5):  # a 2 m x 3 m patch of sand across the straight line
        for y in np.arange(-1.25, 1.5, 0.5):
            tm.observe(x, y, measured_m_s=0.7, requested_m_s=1.0)
    planner = PathPlanner()
    start, goal = (-4.0, 0.0), (4.0, 0.0)
    plain = planner.plan(classes, geo, start, goal)
    costly = planner.plan(classes, geo, start, goal, cost_multiplier=tm.cost_multiplier(geo))
    assert plain.ok and costly.ok
    through = lambda r: float(np.interp(0.0, r.path_in_odom[:, 0], r.path_in_odom[:, 1]))  # noqa: E731
    assert abs(through(plain)) < 0.1
    assert abs(through(costly)) > 1.5  # around the patch: +1 m of detour beats 2 m at 2.2x
    # a wide patch (no cheap way around) is crossed
    wide = TraversabilityMap(
        TraversabilityConfig(resolution_m=0.5, spread_m=0.0, learning_rate=1.0)
    )
    for x in np.arange(-0.75, 1.0, 0.5):
        for y in np.arange(-4.75, 5.0, 0.5):
            wide.observe(x, y, measured_m_s=0.7, requested_m_s=1.0)
    across = planner.plan(classes, geo, start, goal, cost_multiplier=wide.cost_multiplier(geo))
    assert across.ok and abs(through(across)) < 0.5


def _enters_keepout_stepwise(pose, v, w, disks, *, horizon_s, steps=10) -> bool:
    """The check one predicted step at a time (the form before it was vectorized): the oracle
    for :func:`motion_enters_keepout`."""
    if len(disks) == 0:
        return False
    x, y, th = (float(a) for a in pose)
    d_now = np.hypot(disks[:, 0] - x, disks[:, 1] - y)
    inside_now = d_now < disks[:, 2]
    dt = horizon_s / steps
    for _ in range(steps):
        x += v * dt * math.cos(th + 0.5 * w * dt)
        y += v * dt * math.sin(th + 0.5 * w * dt)
        th += w * dt
        d = np.hypot(disks[:, 0] - x, disks[:, 1] - y)
        if np.any(((d < disks[:, 2]) & ~inside_now) | (inside_now & (d < d_now - 1e-9))):
            return True
    return False


def test_keepout_check_equals_the_stepwise_prediction() -> None:
    rng = np.random.default_rng(3)
    hits = 0
    for _ in range(3000):
        n = int(rng.integers(0, 6))
        disks = np.column_stack(
            [rng.uniform(-4, 4, n), rng.uniform(-4, 4, n), rng.uniform(0.5, 3.5, n)]
        )
        pose = np.array([rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(-math.pi, math.pi)])
        v, w = float(rng.uniform(-1, 1)), float(rng.uniform(-1.2, 1.2))
        want = _enters_keepout_stepwise(pose, v, w, disks, horizon_s=1.5)
        assert motion_enters_keepout(pose, v, w, disks, horizon_s=1.5) == want
        hits += want
    assert 300 < hits < 2700  # both answers were exercised


def test_live_marks_say_whether_the_refused_mask_has_any_cell() -> None:
    cfg = StuckConfig(mark_ahead_m=0.45, mark_half_width_m=0.3, remember_s=90.0)
    det = StuckDetector(cfg)
    geometry = GridGeometry((0.0, 0.0), 0.05, 80, 80)
    assert not det.has_live_marks(0.0)
    assert _stall(det, 10.0, np.array([2.0, 2.0, math.pi / 2]), 0.8, 0.0)
    for now in (0.0, 10.0, 13.9, 14.1, 50.0, 104.0, 104.2, 200.0):
        assert det.has_live_marks(now) == bool(det.blocked_mask(geometry, now).any()), now


def test_scalar_clip_equals_numpys() -> None:
    from robot.control.path_follower import _clip

    rng = np.random.default_rng(4)
    values = [*rng.normal(0.0, 2.0, 2000).tolist(), 1.2, -1.2, 0.0, -0.0, math.inf, -math.inf]
    for x in values:
        for lo, hi in ((-1.2, 1.2), (-0.04, 0.04), (-0.15, 0.15)):
            want = float(np.clip(x, lo, hi))
            got = _clip(x, lo, hi)
            assert got == want and math.copysign(1.0, got) == math.copysign(1.0, want), (x, lo)
    assert math.isnan(_clip(math.nan, -1.0, 1.0)) and math.isnan(float(np.clip(math.nan, -1, 1)))
