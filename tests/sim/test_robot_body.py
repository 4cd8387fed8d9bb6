"""Kinematic skid-steer bodies: walls stop them, 10 cm curbs do not, slip, battery (3.1)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sim.ground_truth import rasterize
from sim.robot_body import RobotBodyConfig, SkidSteerBodies, footprints_overlap, pose_matrices
from sim.world_generator import Solid
from tests.sim.simworlds import box, make_world


def _bodies(solids, starts, **kw):
    world = make_world(solids=solids, robots=[(x, y, yaw, "sensor") for x, y, yaw in starts], **kw)
    return SkidSteerBodies(np.array(starts, dtype=float), rasterize(world), seed=3)


def _drive(b: SkidSteerBodies, v: float, w: float, seconds: float, dt: float = 0.05) -> list:
    poses = []
    n = b.count
    for _ in range(int(round(seconds / dt))):
        b.step(dt, np.full(n, v), np.full(n, w))
        poses.append(b.state.pose.copy())
    return poses


def test_robot_cannot_drive_through_a_wall_or_a_thin_fence() -> None:
    wall = box("wall", 10.0, 5.0, 10.15, 15.0, 2.5)
    fence = box("fence", 10.0, 15.5, 10.05, 19.5, 2.0)
    b = _bodies([wall, fence], [(7.0, 10.0, 0.0), (7.0, 17.0, 0.0)])
    poses = np.array(_drive(b, 1.0, 0.0, 8.0))
    front = poses[:, :, 0] + RobotBodyConfig().length_m / 2
    assert front[:, 0].max() <= 10.0 + 1e-6  # the wall's face
    assert front[:, 1].max() <= 10.0 + 1e-6  # the fence's face
    assert front[-1, 0] > 9.7 and front[-1, 1] > 9.7  # they did get there
    assert (b.state.blocked_steps > 0).all()
    assert np.allclose(b.state.wheel_linear_m_s, 0.0)  # stalled against it


def test_robot_never_passes_walls_from_any_angle() -> None:
    room = [
        box("wall", 8, 8, 22, 8.15, 2.5),
        box("wall", 8, 11.85, 22, 12, 2.5),
        box("wall", 8, 8, 8.15, 12, 2.5),
        box("wall", 21.85, 8, 22, 12, 2.5),
    ]
    starts = [(12.0, 10.0, a) for a in np.linspace(-math.pi, math.pi, 7, endpoint=False)]
    b = _bodies(room, starts)
    for k in range(6):
        poses = np.array(_drive(b, 1.0, 0.8 * (-1) ** k, 4.0))
        assert (poses[:, :, 0] > 8.15 + 0.2).all() and (poses[:, :, 0] < 21.85 - 0.2).all()
        assert (poses[:, :, 1] > 8.15 + 0.2).all() and (poses[:, :, 1] < 11.85 - 0.2).all()


def test_robot_climbs_a_10cm_curb_but_not_a_15cm_step() -> None:
    curb = box("curb", 10.0, 5.0, 16.0, 9.0, 0.10, layer="ground")
    step = box("step", 10.0, 11.0, 16.0, 15.0, 0.15, layer="ground")
    b = _bodies([curb, step], [(8.0, 7.0, 0.0), (8.0, 13.0, 0.0)])
    poses = np.array(_drive(b, 0.6, 0.0, 8.0))
    assert poses[-1, 0, 0] > 12.0  # over the curb
    assert b.state.z_m[0] == pytest.approx(0.10, abs=1e-6)
    assert poses[:, 1, 0].max() + 0.3 < 10.0  # stopped at the step
    assert b.state.z_m[1] == pytest.approx(0.0)


def test_terrain_following_on_a_15_degree_ramp() -> None:
    slope = math.radians(15.0)
    length = 0.5 / math.tan(slope)
    ramp = Solid(
        "ramp", "wedge", "ground", (10.0 + length / 2, 10.0, 0.25), (length / 2, 1.0, 0.25)
    )
    dock = box("dock", 10.0 + length, 8.5, 14.0 + length, 11.5, 0.5, layer="ground")
    b = _bodies([ramp, dock], [(8.0, 10.0, 0.0)])
    pitches = []
    for _ in range(240):
        b.step(0.05, np.array([0.5]), np.array([0.0]))
        pitches.append(b.state.pitch_rad[0])
    assert min(pitches) == pytest.approx(-slope, abs=0.03)  # nose up on the ramp
    assert b.state.z_m[0] == pytest.approx(0.5)  # on the dock
    assert b.state.pose[0, 0] > 10.0 + length + 1.0


def test_roll_on_a_sideways_curb() -> None:
    curb = box("curb", 5.0, 10.0, 25.0, 14.0, 0.10, layer="ground")
    b = _bodies([curb], [(8.0, 10.0, 0.0)])  # left wheels on the curb, right wheels off
    assert b.state.roll_rad[0] == pytest.approx(math.atan2(0.10, 0.45), abs=1e-6)


def test_slip_when_turning_and_more_on_sand() -> None:
    b = _bodies([], [(10.0, 10.0, 0.0)])
    _drive(b, 0.0, 1.0, 3.0)
    enc_yaw = (b.state.right_m[0] - b.state.left_m[0]) / RobotBodyConfig().track_m
    true_yaw = np.unwrap([0.0, b.state.pose[0, 2]])[1]
    assert enc_yaw > 0 and true_yaw < 0.9 * enc_yaw  # encoders overestimate yaw (4.3.1)

    def travelled(sand: bool) -> float:
        world_sand = [(5.0, 5.0, 25.0, 15.0, 0.25)] if sand else []
        bb = _bodies([], [(8.0, 10.0, 0.0)], sand=world_sand)
        _drive(bb, 1.0, 0.0, 5.0)
        wheel = (bb.state.left_m[0] + bb.state.right_m[0]) / 2
        return (bb.state.pose[0, 0] - 8.0) / wheel

    assert travelled(sand=True) < travelled(sand=False) - 0.15


def test_acceleration_limits_and_battery_and_disabled_robots() -> None:
    b = _bodies([], [(8.0, 10.0, 0.0), (8.0, 14.0, 0.0)])
    b.step(0.05, np.array([1.0, 1.0]), np.array([0.0, 0.0]))
    assert b.state.wheel_linear_m_s[0] == pytest.approx(
        RobotBodyConfig().max_linear_accel_m_s2 * 0.05
    )
    b.state.disabled[1] = True
    start = b.state.pose.copy()
    battery = b.state.battery_wh.copy()
    _drive(b, 1.0, 0.0, 2.0)
    assert b.state.battery_wh[0] < battery[0]
    assert np.allclose(b.state.pose[1], start[1])  # a disabled robot does not move
    b.state.battery_wh[0] = 1e-6
    _drive(b, 1.0, 0.0, 0.5)
    assert b.state.disabled[0]  # empty battery


def test_robots_do_not_drive_through_each_other_or_people() -> None:
    b = _bodies([], [(8.0, 10.0, 0.0), (12.0, 10.0, math.pi)])
    for _ in range(120):
        b.step(
            0.05,
            np.array([1.0, 1.0]),
            np.array([0.0, 0.0]),
            others_xy_m=np.array([[10.0, 14.0]]),
            others_radius_m=np.array([0.3]),
        )
        d = np.linalg.norm(b.state.pose[0, :2] - b.state.pose[1, :2])
        assert d >= RobotBodyConfig().length_m  # head on: the footprints never overlap
    assert d < 0.7  # and they did meet
    for _ in range(40):  # turning in place must not sweep a corner through the other
        b.step(0.05, np.array([0.0, 0.0]), np.array([1.5, 0.0]))
        half = {"half_length_m": 0.3, "half_width_m": 0.25}
        assert not footprints_overlap(b.state.pose[:1], b.state.pose[1:], **half)[0, 0]


def test_robots_pass_each_other_side_by_side() -> None:
    # footprints 0.5 m wide, centres 0.6 m apart sideways: they pass (a disc model of the
    # 0.38 m enclosing radius would block them)
    b = _bodies([], [(8.0, 10.0, 0.0), (12.0, 10.6, math.pi)])
    _drive(b, 1.0, 0.0, 5.0)
    assert b.state.pose[0, 0] > 11.5 and b.state.pose[1, 0] < 8.5
    assert (b.state.blocked_steps == 0).all()


def _clear_of_robots_reference(b: SkidSteerBodies, cand: np.ndarray) -> np.ndarray:
    """The robot-robot rule of ``_clear_of_others`` with every oriented-rectangle test run
    (no distance shortcut): the oracle for the shortcut."""
    cfg = b.config
    old, new = b.state.pose[:, :2], cand[:, :2]
    d_new = np.minimum(
        np.linalg.norm(new[:, None] - old[None], axis=2),
        np.linalg.norm(new[:, None] - new[None], axis=2),
    )
    d_old = np.linalg.norm(old[:, None] - old[None], axis=2)
    np.fill_diagonal(d_new, np.inf)
    np.fill_diagonal(d_old, np.inf)
    half = {
        "half_length_m": cfg.length_m / 2 + cfg.robot_gap_m / 2,
        "half_width_m": cfg.width_m / 2 + cfg.robot_gap_m / 2,
    }
    pose = b.state.pose
    hit_new = footprints_overlap(cand, pose, **half) | footprints_overlap(cand, cand, **half)
    hit_old = footprints_overlap(pose, pose, **half)
    np.fill_diagonal(hit_new, False)
    return ~(hit_new & (~hit_old | (d_new < d_old))).any(axis=1)  # type: ignore[no-any-return]


@pytest.mark.parametrize("spread_m", [0.6, 1.0, 2.0, 6.0])
def test_robot_clearance_shortcut_agrees_with_every_rectangle_test(spread_m: float) -> None:
    """Far-apart robots skip the rectangle tests (a speed-up): the verdicts are those of the
    full test, for crowds from touching to far apart."""
    rng = np.random.default_rng(int(spread_m * 10))
    b = _bodies([], [(20.0, 20.0, 0.0)] * 5)
    for _ in range(300):
        b.state.pose = np.column_stack(
            [20 + rng.uniform(0, spread_m, (5, 2)), rng.uniform(-math.pi, math.pi, 5)]
        )
        cand = b.state.pose + rng.normal(0.0, [0.05, 0.05, 0.1], (5, 3))
        got = b._clear_of_others(cand, None, None)
        assert np.array_equal(got, _clear_of_robots_reference(b, cand))


def test_kept_footprint_counts_and_transforms_are_those_computed_afresh() -> None:
    """A step reuses the last step's footprint count of the pose it starts from and the
    transforms of an unchanged state (speed): the same motion as counting and computing
    afresh, also when the poses are moved between steps."""
    wall = box("wall", 10.0, 5.0, 10.15, 15.0, 2.5)
    starts = [(8.6, 10.0, 0.3), (7.0, 12.0, -0.2), (8.9, 7.0, 0.0)]
    kept, fresh = _bodies([wall], starts), _bodies([wall], starts)
    rng = np.random.default_rng(5)
    for step in range(120):
        if step % 40 == 39:  # someone moves the bodies (a test, a reset)
            moved = kept.state.pose + rng.normal(0.0, 0.2, kept.state.pose.shape)
            kept.state.pose, fresh.state.pose = moved.copy(), moved.copy()
        v, w = rng.uniform(0.2, 1.0, 3), rng.uniform(-0.3, 0.3, 3)
        kept.step(0.05, v, w)
        fresh._count_of = None
        fresh.step(0.05, v, w)
        assert np.array_equal(kept.state.pose, fresh.state.pose)
        assert np.array_equal(kept.state.blocked_steps, fresh.state.blocked_steps)
        m = kept.world_from_base_matrices()
        m[:] = 0.0  # the caller's copy: the kept transforms are untouched
        st = fresh.state
        expected = pose_matrices(st.pose, st.z_m, st.roll_rad, st.pitch_rad)
        assert np.array_equal(kept.world_from_base_matrices(), expected)
    assert (kept.state.blocked_steps > 0).any()  # the wall was met


def test_compiled_footprint_overlaps_are_the_numpy_verdicts() -> None:
    """The compiled separating-axis test (speed) gives the numpy reference's verdicts, for
    crowds from overlapping to touching to apart, and for equal and opposite headings."""
    from sim.robot_body import footprints_overlap_reference

    rng = np.random.default_rng(8)
    half = {"half_length_m": 0.38, "half_width_m": 0.3}
    agree = 0
    for _ in range(400):
        a = np.column_stack([rng.uniform(0, 2.0, (5, 2)), rng.uniform(-math.pi, math.pi, 5)])
        b = np.column_stack([rng.uniform(0, 2.0, (4, 2)), rng.uniform(-math.pi, math.pi, 4)])
        b[0] = a[0] + [0.76, 0.0, 0.0]  # touching end to end
        b[1, 2] = a[1, 2] + math.pi
        got = footprints_overlap(a, b, **half)
        assert np.array_equal(got, footprints_overlap_reference(a, b, **half))
        agree += int(got.sum())
    assert 0 < agree < 400 * 20


def test_compiled_footprint_counts_are_the_numpy_counts() -> None:
    """The compiled footprint count (speed) is the numpy reference's, along walls, on the
    map's edges and off the map."""
    wall = box("wall", 10.0, 5.0, 10.15, 15.0, 2.5)
    b = _bodies([wall], [(9.0, 10.0, 0.0)])
    rng = np.random.default_rng(9)
    poses = np.column_stack(
        [rng.uniform(-1.0, 22.0, (3000, 2)), rng.uniform(-math.pi, math.pi, 3000)]
    )
    got = b.blocked_count(poses)
    assert np.array_equal(got, b.blocked_count_reference(poses))
    assert got.dtype == np.int64 and 0 < int((got > 0).sum()) < len(poses)
