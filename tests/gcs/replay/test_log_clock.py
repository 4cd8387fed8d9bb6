from __future__ import annotations

import numpy as np
import pytest

from gcs.replay.log_clock import check_clock


def _good(n: int = 200, period_s: float = 0.2, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 1000.0 + np.cumsum(rng.uniform(0.5, 1.5, n) * period_s)  # type: ignore[no-any-return]


def test_a_good_clock_is_used_as_is() -> None:
    t = _good()
    c = check_clock(t)
    assert c.ok and c.lines() == [] and not c.rewritten
    np.testing.assert_allclose(c.time_s, t)
    assert 0.15 < c.period_s < 0.25 and not c.repaired.any()


def test_frozen_clock_gets_the_default_period() -> None:
    c = check_clock(np.zeros(50), default_period_s=0.25)
    assert [a.kind for a in c.anomalies] == ["frozen"] and c.rewritten
    np.testing.assert_allclose(np.diff(c.time_s), 0.25)
    assert len(c.lines()) == 1 and "every stamp 0" in c.lines()[0]


def test_coarse_clock_is_detected_and_spread_over_the_scans() -> None:
    # %g-printed Unix time: 1.13486e+09 changing every 1e4 s, 20 000 scans over 1.2e5 s.
    true = 1.13486e9 + np.arange(20000) * 6.0
    stamps = np.round(true / 1e4) * 1e4
    c = check_clock(stamps)
    assert [a.kind for a in c.anomalies] == ["coarse"]
    assert c.period_s == pytest.approx(6.0, rel=0.1)  # the span over the scan count
    assert np.all(np.diff(c.time_s) > 0)
    # A short log sees two values: its span says nothing, the default period is used.
    short = check_clock(np.r_[np.full(30, 1.13486e9), np.full(30, 1.13487e9)])
    assert [a.kind for a in short.anomalies] == ["coarse"] and short.period_s == 0.5


def test_jump_is_replaced_by_the_median_period_and_good_stretches_kept() -> None:
    t = _good()
    jumped = t.copy()
    jumped[120:] += 4.29e9
    c = check_clock(jumped)
    assert [a.kind for a in c.anomalies] == ["jump"] and c.anomalies[0].first_scan == 120
    dt = np.diff(c.time_s)
    assert dt.max() < 1.0
    np.testing.assert_allclose(dt[:119], np.diff(t)[:119])
    np.testing.assert_allclose(dt[120:], np.diff(t)[120:], atol=1e-5)  # float64 at 4e9 s
    assert dt[119] == pytest.approx(c.period_s)


def test_backwards_steps_and_too_fast_motion() -> None:
    t = _good()
    t[50] = t[49] - 0.3  # one stamp out of order: two steps are odd, one negative
    odom = np.zeros((len(t), 3))
    odom[:, 0] = np.arange(len(t)) * 0.05
    t[100:] -= t[100] - t[99] - 0.001  # 1 ms for a 1 m step: 1000 m/s
    odom[100:, 0] += 1.0
    c = check_clock(t, odometry=odom)
    kinds = {a.kind: a for a in c.anomalies}
    assert set(kinds) == {"backwards", "too_fast"}
    assert kinds["backwards"].first_scan == 50 and kinds["too_fast"].first_scan == 100
    assert np.all(np.diff(c.time_s) >= 0)
    assert all(len(line) < 200 for line in c.lines())


def test_no_timestamps_and_tiny_logs() -> None:
    c = check_clock(np.full(10, np.nan), default_period_s=0.5)
    assert [a.kind for a in c.anomalies] == ["none"]
    np.testing.assert_allclose(c.time_s, np.arange(10) * 0.5)
    assert check_clock([5.0]).ok
    with pytest.raises(ValueError, match="default_period_s"):
        check_clock([1.0, 2.0], default_period_s=0.0)
