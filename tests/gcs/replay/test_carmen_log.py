from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from gcs.replay.carmen_log import (
    CarmenLogError,
    beam_angles_rad,
    parse_carmen_log,
    read_carmen_log,
)


def _flaser(ranges: list[float], pose: tuple[float, float, float], t: float) -> str:
    r = " ".join(f"{v:g}" for v in ranges)
    p = " ".join(repr(v) for v in pose)
    return f"FLASER {len(ranges)} {r} {p} {p} {t:g} host {t:g}"


def test_beam_angles_follow_carmen() -> None:
    a180 = beam_angles_rad(180)
    assert math.isclose(a180[0], math.radians(-89.5)) and math.isclose(a180[-1], math.radians(89.5))
    np.testing.assert_allclose(np.diff(a180), math.radians(1.0))
    a181 = beam_angles_rad(181)
    assert math.isclose(a181[0], -math.pi / 2) and math.isclose(a181[90], 0.0, abs_tol=1e-15)
    a361 = beam_angles_rad(361)
    np.testing.assert_allclose([a361[0], a361[-1]], [-math.pi / 2, math.pi / 2])
    a5 = beam_angles_rad(5)
    np.testing.assert_allclose(a5, np.linspace(-math.pi / 2, math.pi / 2, 5))
    with pytest.raises(ValueError, match="at least 2 beams"):
        beam_angles_rad(1)


def test_flaser_scans_poses_times_offset_and_points() -> None:
    ranges = [1.0] * 181
    ranges[90] = 2.0  # straight ahead
    ranges[0] = 81.83  # no return
    ranges[180] = 8.183  # no return (8 m mode)
    text = "\n".join(
        [
            "# a comment",
            "PARAM robot_frontlaser_offset 0.5 nohost 0",
            "ODOM 0 0 0 0 0 0 0.1 host 0.1",
            _flaser(ranges, (1.0, 2.0, math.pi / 2), 10.5),
            "NEFF 15",
            _flaser(ranges, (1.0, 3.0, math.pi / 2), 11.5),
        ]
    )
    log = parse_carmen_log(text, path="mem.log")
    assert len(log) == 2 and log.ranges_m.shape == (2, 181)
    assert log.line_numbers.tolist() == [4, 6]
    assert log.skipped == {"ODOM": 1, "NEFF": 1}
    assert log.has_timestamps and log.time_s.tolist() == [10.5, 11.5]
    assert log.laser_offset_m == 0.5
    np.testing.assert_allclose(log.laser_in_log[0], [1.0, 2.0, math.pi / 2])
    # The base is 0.5 m behind the laser along the heading (+y here).
    np.testing.assert_allclose(log.base_in_log[0], [1.0, 1.5, math.pi / 2], atol=1e-12)
    pts = log.points_in_base(0)
    assert pts.shape == (179, 2)  # both sentinels dropped
    ahead = pts[np.argmax(pts[:, 0])]
    np.testing.assert_allclose(ahead, [2.5, 0.0], atol=1e-12)  # offset + range
    valid = log.valid_mask()
    assert not valid[0, 0] and not valid[0, 180] and valid[0, 1:180].all()
    assert log.points_in_base(1, max_range_m=1.5).shape == (178, 2)
    with pytest.raises(IndexError, match="scan 2 out of range"):
        log.points_in_base(2)
    second = log.subset([1])
    assert len(second) == 1 and second.time_s.tolist() == [11.5]
    np.testing.assert_array_equal(second.base_in_log, log.base_in_log[1:])
    assert len(log.subset(slice(0, 1))) == 1


def test_dpslam_format_uses_the_preceding_odometry() -> None:
    r = " ".join(["1.5"] * 181)
    text = f"Odometry 1 2 0.5\nLaser 181 {r}\nOdometry 2 2 0.7\nLaser 181 {r}\n"
    log = parse_carmen_log(text)
    assert len(log) == 2 and not log.has_timestamps and np.isnan(log.time_s).all()
    np.testing.assert_allclose(log.odometry_in_log, [[1, 2, 0.5], [2, 2, 0.7]])
    np.testing.assert_allclose(log.base_in_log, log.odometry_in_log)
    assert log.points_in_base(0).shape == (181, 2)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("Laser 3 1 1 1\n", r"mem:1: Laser before any Odometry"),
        ("Odometry 1 2\n", r"mem:1: Odometry needs x y theta"),
        ("Odometry 1 2 x\n", r"mem:1: Odometry pose"),
        ("Odometry 0 0 0\nLaser 3 1 1\n", r"mem:2: Laser with 3 beams has 2 ranges"),
        ("Odometry 0 0 0\nLaser three 1 1 1\n", r"mem:2: Laser beam count: expected an integer"),
        ("FLASER 3 1 1 1 0 0 0\n", r"mem:1: FLASER with 3 beams needs 14 fields"),
        ("FLASER 1000000 1\n", r"mem:1: FLASER beam count: 1000000 is not a plausible"),
        ("FLASER 3 1 nan 1 0 0 0 0 0 0 1 h 1\n", r"mem:1: FLASER ranges: non-finite"),
        ("ODOM 0 0 0\n", r"mem: no laser scans .* found ODOM x1"),
        ("", r"mem: no laser scans .* found nothing"),
        (
            "Odometry 0 0 0\nLaser 3 1 1 1\nLaser 4 1 1 1 1\n",
            r"mem:3: scan has 4 beams .* first scan's 3",
        ),
    ],
)
def test_malformed_logs_name_file_and_line(text: str, match: str) -> None:
    with pytest.raises(CarmenLogError, match=match):
        parse_carmen_log(text, path="mem")


def test_read_plain_and_gzip(tmp_path: Path) -> None:
    text = _flaser([2.0] * 180, (0.0, 0.0, 0.0), 1.0) + "\n"
    (tmp_path / "a.log").write_text(text)
    with gzip.open(tmp_path / "a.log.gz", "wt") as fh:
        fh.write(text)
    a = read_carmen_log(tmp_path / "a.log")
    b = read_carmen_log(tmp_path / "a.log.gz")
    np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
    assert b.path.endswith("a.log.gz")
    with pytest.raises(CarmenLogError, match="cannot read"):
        read_carmen_log(tmp_path / "missing.log")
    (tmp_path / "bad.log.gz").write_bytes(b"not gzip at all")
    with pytest.raises(CarmenLogError, match="bad.log.gz: cannot read"):
        read_carmen_log(tmp_path / "bad.log.gz")


def test_real_logs(laser_dir: Path) -> None:
    duke = read_carmen_log(laser_dir / "dpslam_loop5.log")
    assert duke.ranges_m.shape == (551, 181) and not duke.has_timestamps
    # 8.183 / 8.191 m are the SICK's "no return": none survive as points.
    pts = np.concatenate([duke.points_in_base(i) for i in range(len(duke))])
    assert np.hypot(pts[:, 0], pts[:, 1]).max() < 8.18
    intel = read_carmen_log(laser_dir / "intel-corrected.log.gz")
    assert intel.ranges_m.shape == (910, 180) and intel.has_timestamps
    assert intel.skipped["ODOM"] > 0 and intel.laser_offset_m == 0.0
    # A corrected log: the laser pose is the corrected pose; the odometry fields repeat it.
    np.testing.assert_allclose(intel.odometry_in_log, intel.laser_in_log)
    # Consecutive scans of the corrected log are at most a few metres apart.
    steps = np.hypot(*np.diff(intel.base_in_log[:, :2], axis=0).T)
    assert steps.max() < 3.0
