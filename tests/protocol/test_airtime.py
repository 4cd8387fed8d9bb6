"""Air time by demand and priority: bounded by capacity and links, max-min fair, a backlog
gets more than an idle robot."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.airtime import AirtimeConfig, AirtimeScheduler, allocate_airtime


@settings(max_examples=200, deadline=None)
@given(
    demand=st.dictionaries(st.integers(0, 30), st.floats(0, 1e5), min_size=1, max_size=12),
    capacity=st.floats(0, 2e5),
    floor=st.floats(0, 500),
    data=st.data(),
)
def test_grants_never_exceed_capacity_or_links(
    demand: dict[int, float], capacity: float, floor: float, data: st.DataObject
) -> None:
    link = {r: data.draw(st.sampled_from([0.0, 300.0, 5000.0, math.inf])) for r in demand}
    weights = {r: data.draw(st.floats(0.1, 10)) for r in demand}
    g = allocate_airtime(
        demand, capacity_bps=capacity, weights=weights, link_max_bps=link, floor_bps=floor
    )
    assert set(g) == set(demand)
    assert sum(g.values()) <= capacity * (1 + 1e-9) + 1e-6
    for r, v in g.items():
        assert 0 <= v <= link[r] + 1e-9
        if link[r] == 0:
            assert v == 0
    # every demand that fits is met
    if sum(min(d, link[r]) for r, d in demand.items()) + floor * len(demand) <= capacity:
        for r, d in demand.items():
            assert g[r] >= min(d, link[r]) - 1e-6


def test_a_backlog_gets_more_than_an_idle_robot_and_priority_counts() -> None:
    demand = {0: 20_000.0, 1: 200.0, 2: 200.0, 3: 0.0}
    g = allocate_airtime(demand, capacity_bps=10_000.0, floor_bps=150.0)
    assert g[0] > 10 * g[3] and g[1] >= 200.0 and g[3] == 150.0
    assert sum(g.values()) == pytest.approx(10_000.0)
    short = {0: 8000.0, 1: 8000.0}
    g = allocate_airtime(short, capacity_bps=6000.0, weights={0: 2.0, 1: 1.0})
    assert g[0] == pytest.approx(4000.0) and g[1] == pytest.approx(2000.0)


def test_scheduler_follows_measured_rate_and_reported_backlog() -> None:
    sched = AirtimeScheduler(AirtimeConfig(floor_bps=100.0))
    got = {0: 0, 1: 0}
    grants = {}
    for t in range(1, 31):
        got[0] += 100  # 800 bps
        got[1] += 10  # 80 bps
        backlog = {0: 0, 1: 50_000 if t >= 20 else 0}
        grants = sched.update(
            float(t), bytes_received=got, backlog_bytes=backlog, capacity_bps=20_000.0
        )
        if t == 19:
            assert grants[0] > grants[1]
    assert grants[1] > grants[0]  # the backlog now weighs more than the steady robot
    assert sum(grants.values()) <= 20_000.0 + 1e-6


def test_bad_configuration_is_refused_with_the_name() -> None:
    with pytest.raises(ValueError, match="capacity_bps"):
        allocate_airtime({0: 1.0}, capacity_bps=math.inf)
    with pytest.raises(ValueError, match="weight of robot 0"):
        allocate_airtime({0: 1.0}, capacity_bps=1.0, weights={0: 0.0})
    with pytest.raises(ValueError, match="drain_s"):
        AirtimeConfig(drain_s=0.0)
