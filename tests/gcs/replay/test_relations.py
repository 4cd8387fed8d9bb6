from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gcs.replay.carmen_log import read_carmen_log
from gcs.replay.relations import (
    Relations,
    RelationsFileError,
    align_relations,
    estimate_time_offset_s,
    match_relations,
    parse_relations,
    read_relations,
    relations_error,
)
from protocol.se2 import compose, relative


def _trajectory(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = np.zeros((n, 3))
    for k in range(1, n):
        poses[k] = compose(poses[k - 1], [rng.uniform(0.2, 1.0), 0.0, rng.normal(0, 0.3)])
    return poses


def _relations_of(poses: np.ndarray, times: np.ndarray, pairs: list[tuple[int, int]]) -> str:
    lines = []
    for i, j in pairs:
        d = relative(poses[i], poses[j])
        fields = (times[i], times[j], d[0], d[1], 0.0, 0.0, 0.0, d[2])
        lines.append(" ".join(repr(float(v)) for v in fields))
    return "\n".join(lines) + "\n"


def test_parse_and_errors(tmp_path: Path) -> None:
    rel = parse_relations("# comment\n1.0 2.0 0.5 0.1 0 0 0 0.2  # trailing\n")
    assert len(rel) == 1 and rel.t1_s.tolist() == [1.0] and rel.t2_s.tolist() == [2.0]
    np.testing.assert_allclose(rel.t1_from_t2, [[0.5, 0.1, 0.2]])
    with pytest.raises(RelationsFileError, match=r"f:2: expected 8 fields"):
        parse_relations("1 2 0 0 0 0 0 0\n1 2 3\n", path="f")
    with pytest.raises(RelationsFileError, match=r"f:1: could not convert"):
        parse_relations("1 2 x 0 0 0 0 0\n", path="f")
    with pytest.raises(RelationsFileError, match=r"f:1: non-finite"):
        parse_relations("1 2 inf 0 0 0 0 0\n", path="f")
    with pytest.raises(RelationsFileError, match="f: no relations"):
        parse_relations("# nothing\n", path="f")
    with pytest.raises(RelationsFileError, match="cannot read"):
        read_relations(tmp_path / "missing.relations")


def test_exact_poses_give_zero_error_and_a_perturbation_its_size() -> None:
    poses = _trajectory(50)
    times = 100.0 + np.arange(50) * 0.7
    pairs = [(k, k + 1) for k in range(49)] + [(3, 40), (10, 45)]
    rel = parse_relations(_relations_of(poses, times, pairs))
    m = match_relations(rel, times)
    assert len(m) == len(pairs) and m.total == len(pairs)
    assert m.i.tolist()[:3] == [0, 1, 2] and m.j.tolist()[-1] == 45
    exact = relations_error(poses, m)
    assert exact.count == len(pairs)
    assert exact.trans_mean_m < 1e-9 and exact.rot_mean_rad < 1e-9 and exact.epsilon < 1e-15
    # The metric does not depend on the frame the poses are given in.
    moved = compose([5.0, -3.0, 1.0], poses)
    assert relations_error(moved, m).trans_mean_m < 1e-9
    # Rotate pose 45 by 0.1 rad about itself: only the relations touching it, (44, 45) and
    # (10, 45), see it, exactly in yaw.
    bent = poses.copy()
    bent[45, 2] += 0.1
    err = relations_error(bent, m)
    touched = (m.i == 45) | (m.j == 45)
    np.testing.assert_allclose(err.rot_rad[touched], 0.1, atol=1e-12)
    assert err.rot_rad[~touched].max() < 1e-12
    assert math.isclose(err.rot_mean_rad, 0.1 * touched.sum() / len(pairs), rel_tol=1e-9)
    # Shift pose 20 by 0.3 m: the relations from 19 and to 21 see exactly that much.
    shifted = poses.copy()
    shifted[20, :2] += [0.3, 0.0]
    err = relations_error(shifted, m)
    touched = (m.i == 20) | (m.j == 20)
    np.testing.assert_allclose(err.trans_m[touched], 0.3, atol=1e-12)
    assert math.isclose(err.trans_mean_m, 0.3 * 2 / len(pairs), rel_tol=1e-9)
    assert math.isclose(err.trans_std_m, float(np.std(err.trans_m)))


def test_clock_offset_is_found_and_only_unambiguous_stamps_match() -> None:
    poses = _trajectory(200, seed=2)
    rng = np.random.default_rng(3)
    times = np.cumsum(rng.uniform(0.5, 2.0, 200))
    offset = 976052857.3372
    pairs = [(k, k + 1) for k in range(0, 199, 2)] + [(5, 150), (7, 160)]
    text = _relations_of(poses, times + offset, pairs)
    # Relations of the original, denser log: stamps between this log's scans never match.
    text += f"{float(times[30] + offset + 0.1)!r} {float(times[31] + offset)!r} 0.3 0 0 0 0 0\n"
    rel = parse_relations(text)
    # The log stores its times rounded to 10 ms, like the corrected Intel log.
    stored = np.round(times, 2)
    d = estimate_time_offset_s(rel, stored)
    assert abs(d - offset) < 0.005
    m = match_relations(rel, stored, time_offset_s=d, tolerance_s=0.006)
    assert len(m) == len(pairs) and m.total == len(pairs) + 1
    assert relations_error(poses, m).trans_mean_m < 1e-9
    # Two relation stamps within the tolerance of one pose: that pose is ambiguous, dropped.
    t60, t90 = float(times[60] + offset + 0.004), float(times[90] + offset)
    close = text + f"{t60!r} {t90!r} 1 0 0 0 0 0\n"
    m2 = match_relations(parse_relations(close), stored, time_offset_s=d, tolerance_s=0.006)
    assert 60 not in m2.i.tolist() + m2.j.tolist() and len(m2) == len(pairs) - 1
    with pytest.raises(ValueError, match="tolerance_s must be > 0"):
        match_relations(rel, stored, tolerance_s=0.0)


def test_unrelated_clocks_are_refused() -> None:
    rng = np.random.default_rng(4)
    log_times = np.sort(rng.uniform(0, 1000, 900))
    t1 = np.sort(rng.uniform(5000, 6000, 500))
    rel = Relations(t1_s=t1, t2_s=t1 + rng.uniform(0.5, 3, 500), t1_from_t2=np.zeros((500, 3)))
    with pytest.raises(ValueError, match="timestamps agree on a clock offset"):
        estimate_time_offset_s(rel, log_times)
    with pytest.raises(ValueError, match="times must be finite"):
        estimate_time_offset_s(rel, [np.nan, 1.0])
    with pytest.raises(ValueError, match="no relation falls on these poses"):
        relations_error(np.zeros((900, 3)), match_relations(rel, log_times))


def test_intel_corrected_log_agrees_with_its_relations(laser_dir: Path) -> None:
    """The corrected Intel poses against Kuemmerle et al.'s relations: the offset between the
    log's clock and the relations' absolute stamps is found, about a hundred relations fall on
    scans, and their error is centimetres (their paper reports 3.1 cm / 1.3 deg for graph
    mapping on this log)."""
    log = read_carmen_log(laser_dir / "intel-corrected.log.gz")
    rel = read_relations(laser_dir / "intel.relations")
    d = estimate_time_offset_s(rel, log.time_s)
    assert abs(d - 976052857.337) < 0.01
    m = match_relations(rel, log.time_s, time_offset_s=d)
    assert 90 <= len(m) <= 130 and m.total == 2984
    err = relations_error(log.base_in_log, m)
    assert err.trans_mean_m < 0.05 and err.rot_mean_deg < 1.5
    # The same relations against a trajectory bent by 3 deg per scan are far off.
    steps = relative(log.base_in_log[:-1], log.base_in_log[1:])
    steps[:, 2] += math.radians(3.0)
    bent = [log.base_in_log[0]]
    for s in steps:
        bent.append(compose(bent[-1], s))
    worse = relations_error(np.asarray(bent), m)
    assert worse.trans_mean_m > 5 * err.trans_mean_m and worse.rot_mean_deg > 5 * err.rot_mean_deg


def test_a_restamped_log_is_aligned_by_geometry() -> None:
    """A log whose stamps were rewritten (time since its start, each off by up to 50 ms) shares
    no stamp with its relations: the poses decide the offset, and the relations fall on the
    scans within half the scan period."""
    poses = _trajectory(800, seed=3)
    rng = np.random.default_rng(5)
    raw = 5000.0 + np.cumsum(rng.uniform(0.15, 0.35, len(poses)))
    log_times = raw - raw[0] + 0.2 + rng.uniform(-0.05, 0.05, len(poses))
    pairs = [(i, i + 3) for i in range(0, len(poses) - 3, 4)]
    rel = parse_relations(_relations_of(poses, raw, pairs), path="restamped.relations")
    with pytest.raises(ValueError, match="restamped.relations: only .* agree"):
        estimate_time_offset_s(rel, log_times)
    a = align_relations(rel, log_times, poses)
    assert a.method == "geometry" and abs(a.offset_s - (raw[0] - 0.2)) < 0.06
    assert a.votes >= 0.9 * len(rel) and a.runner_up < 0.2 * a.votes
    m = match_relations(rel, log_times, time_offset_s=a.offset_s, tolerance_s=a.tolerance_s)
    assert len(m) >= 0.9 * len(rel)
    assert relations_error(poses, m).trans_mean_m < 1e-6
    # Relations of another trajectory fit no offset: one line naming the file.
    other = parse_relations(
        _relations_of(_trajectory(800, seed=9), raw, pairs), path="other.relations"
    )
    with pytest.raises(ValueError, match="other.relations: no clock offset fits") as info:
        align_relations(other, log_times, poses)
    assert len(str(info.value)) < 200 and "\n" not in str(info.value)


def test_fr079_relations_match_the_corrected_log(laser_dir: Path) -> None:
    """The corrected Freiburg 079 log was re-stamped (time since its start; no stamp equals a
    relation stamp minus one offset): geometry aligns it, and almost all relations match."""
    log = read_carmen_log(laser_dir / "freiburg-079-corrected.log.gz")
    rel = read_relations(laser_dir / "fr079.relations")
    with pytest.raises(ValueError, match="agree on a clock offset"):
        estimate_time_offset_s(rel, log.time_s)
    a = align_relations(rel, log.time_s, log.odometry_in_log)
    assert a.method == "geometry" and abs(a.offset_s - 1211.42) < 0.1
    m = match_relations(rel, log.time_s, time_offset_s=a.offset_s, tolerance_s=a.tolerance_s)
    assert len(m) >= 1600 and m.total == 1685
    err = relations_error(log.base_in_log, m)
    assert err.trans_mean_m < 0.08 and err.rot_mean_deg < 1.0
    # Its first 300 scans: 7 stamps agree on an offset 23 s off by chance, and few relations
    # fall on so short a stretch: refused in one line, never aligned to the wrong offset.
    with pytest.raises(ValueError, match="no clock offset fits"):
        align_relations(rel, log.time_s[:300], log.odometry_in_log[:300])
