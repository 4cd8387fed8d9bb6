"""The on-board scan odometry's along-heading correction (ScanOdometryConfig.along_gate_sigma):
wheel slip the encoders cannot see (sand) is measured by the sweeps and taken out of the
pose; firm ground's small odometry error is left alone."""

from __future__ import annotations

import math

import numpy as np

from protocol.se2 import compose
from robot.odometry.scan_odometry import ScanOdometry, ScanOdometryConfig
from tests.robot.laser_room import box_segments, scan_in_base

#: A 14 x 8 m room with three boxes (x0, y0, x1, y1): every pose looks different.
_BOXES = [
    (-7.0, -4.0, 7.0, 4.0),
    (-3.0, 1.5, -2.2, 2.3),
    (2.0, -2.5, 3.2, -1.9),
    (4.5, 2.0, 5.0, 3.5),
]


def _segments() -> np.ndarray:
    return box_segments(_BOXES)


def _scan(pose: np.ndarray, segs: np.ndarray, beams: int = 361) -> np.ndarray:
    """Endpoints in base of a 360-degree laser at ``pose`` (nearest wall per beam)."""
    ang = np.linspace(-math.pi, math.pi, beams, endpoint=False)
    return scan_in_base(pose, segs, ang, max_range_m=20.0)


def _drive(over_count: float, config: ScanOdometryConfig) -> tuple[float, int]:
    """0.5 m steps east along the room, the odometry counting ``1 + over_count`` of each;
    each sweep's correction composed onto the pose. Returns the final along-track error and
    how many corrections moved the position."""
    segs = _segments()
    aid = ScanOdometry(config)
    true_pose = np.array([-5.5, -0.5, 0.0])
    pose = true_pose.copy()
    moved = 0
    for k in range(20):
        if k:
            true_pose = true_pose + np.array([0.5, 0.0, 0.0])
            pose = compose(pose, np.array([0.5 * (1.0 + over_count), 0.0, 0.0]))
        found = aid.observe(pose, _scan(true_pose, segs), 1.25 * k)
        if found is not None:
            moved += found.correction[0] != 0.0
            pose = compose(pose, np.asarray(found.correction))
            if k:
                assert found.step_m > 0.5
    return float(pose[0] - true_pose[0]), moved


def test_sand_slip_is_taken_out_along_the_heading() -> None:
    on = ScanOdometryConfig(along_gate_sigma=3.0)
    off = ScanOdometryConfig()
    # sand: the wheels count 40 % more than the body moves (0.2 m a 0.5 m sweep; the small
    # world's sand pit, 25-30 % of a 1 m sweep)
    error_off, moved_off = _drive(0.4, off)
    error_on, moved_on = _drive(0.4, on)
    assert error_off > 3.5 and moved_off == 0
    assert abs(error_on) < 0.1 and moved_on >= 15
    # firm ground (1 % off, 5 mm a sweep): within the match's noise, nothing moves
    error_firm, moved_firm = _drive(0.01, on)
    assert moved_firm == 0 and abs(error_firm) < 0.1
