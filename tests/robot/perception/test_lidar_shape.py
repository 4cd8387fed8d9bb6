"""Shape detector pieces on constructed scenes with known answers (paper 5.2.1)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from robot.perception.person_tracker import PersonTracker
from robot.perception.segmentation import segment_sweep
from robot.perception.shape_classifier import (
    DEFAULT_THRESHOLDS_PATH,
    ThresholdFileError,
    load_thresholds,
    save_thresholds,
)
from robot.perception.shape_features import aligned_rectangle, arc_length, ransac_circle


def _ground(rng: np.random.Generator, n: int = 4000) -> np.ndarray:
    xy = rng.uniform(-10, 10, size=(n, 2))
    return np.column_stack([xy, rng.normal(0, 0.005, n)])


def _cylinder(cx: float, cy: float, r: float, h: float, sensor=(0.0, 0.0)) -> np.ndarray:
    facing = math.atan2(sensor[1] - cy, sensor[0] - cx)
    a = facing + np.linspace(-1.4, 1.4, 25)
    z = np.arange(0.15, h, 0.1)
    aa, zz = np.meshgrid(a, z)
    return np.column_stack([cx + r * np.cos(aa.ravel()), cy + r * np.sin(aa.ravel()), zz.ravel()])


def test_cylinder_next_to_a_wall_stays_apart() -> None:
    rng = np.random.default_rng(0)
    cyl = _cylinder(4.0, 0.0, 0.25, 0.8)
    yy, zz = np.meshgrid(np.arange(-2, 2, 0.05), np.arange(0.15, 2.5, 0.1))
    wall = np.column_stack([np.full(yy.size, 4.35), yy.ravel(), zz.ravel()])
    seg = segment_sweep(np.vstack([_ground(rng), cyl, wall]), (0.0, 0.0))
    tops = sorted(round(s.top_m, 1) for s in seg.segments if len(s.xyz) > 20)
    assert 0.8 in tops or 0.7 in tops
    small = [s for s in seg.segments if s.top_m < 1.0 and len(s.xyz) > 20]
    assert len(small) == 1
    assert np.ptp(small[0].xyz[:, 0]) < 0.4  # the wall (x = 4.35) is not in it


def test_nan_rows_are_skipped_and_counted() -> None:
    rng = np.random.default_rng(1)
    pts = np.vstack([_ground(rng), _cylinder(3.0, 1.0, 0.25, 0.8)])
    pts[[5, 9, 11]] = np.nan
    seg = segment_sweep(pts, (0.0, 0.0))
    assert seg.dropped_nonfinite == 3
    assert any(abs(s.top_m - 0.75) < 0.1 for s in seg.segments)


def test_features_against_hand_computed_values() -> None:
    sq = np.array([[0, 0], [2, 0], [2, 1], [0, 1], [1, 0.5]], float)
    c, s = math.cos(0.5), math.sin(0.5)
    rot = sq @ np.array([[c, s], [-s, c]])
    length, breadth, _, _ = aligned_rectangle(rot)
    assert length == pytest.approx(2.0, abs=0.01) and breadth == pytest.approx(1.0, abs=0.01)
    a = np.linspace(-math.pi / 2, math.pi / 2, 30)
    arc = np.column_stack([1 + 0.3 * np.cos(a), 2 + 0.3 * np.sin(a)])
    fit = ransac_circle(arc)
    assert fit is not None
    centre, r, inl = fit
    assert r == pytest.approx(0.3, abs=1e-6) and np.allclose(centre, [1, 2]) and inl.all()
    assert arc_length(arc, centre, r) == pytest.approx(0.3 * math.pi, rel=1e-6)


def test_thresholds_file_round_trip_and_errors(tmp_path: Path) -> None:
    th = load_thresholds(DEFAULT_THRESHOLDS_PATH)
    assert {"cylinder", "person"} <= set(th.boxes)
    out = tmp_path / "t.json"
    save_thresholds(out, th)
    back = load_thresholds(out)
    assert np.allclose(back.boxes["cylinder"].lo, th.boxes["cylinder"].lo)
    out.write_text("{not json")
    with pytest.raises(ThresholdFileError, match="not a readable JSON"):
        load_thresholds(out)
    doc = json.loads(DEFAULT_THRESHOLDS_PATH.read_text())
    doc["version"] = 99
    out.write_text(json.dumps(doc))
    with pytest.raises(ThresholdFileError, match="version 99"):
        load_thresholds(out)
    doc["version"] = 1
    doc["feature_names"] = ["a"]
    out.write_text(json.dumps(doc))
    with pytest.raises(ThresholdFileError, match="feature_names"):
        load_thresholds(out)
    with pytest.raises(ThresholdFileError, match="no such"):
        load_thresholds(tmp_path / "missing.json")


def test_tracker_estimates_a_walking_velocity() -> None:
    rng = np.random.default_rng(2)
    tr = PersonTracker()
    v = np.array([-0.6, 0.3])
    for k in range(12):
        t = 1.25 * k
        p = np.array([8.0, -2.0]) + v * t + rng.normal(0, 0.05, 2)
        tracks = tr.update(t, [p, [np.nan, 0.0]])
    assert len(tracks) == 1
    assert np.linalg.norm(tracks[0].velocity_m_s - v) < 0.15
    assert tr.rejected_measurements == 12
