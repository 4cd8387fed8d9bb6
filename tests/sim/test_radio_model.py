"""The radio model: range, walls, relays, and a shared capacity never exceeded (4.1)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mission.config import load_config
from protocol.radio import RadioConfig
from sim.radio_model import RadioModel
from tests.sim.simworlds import REPO

RES = 0.1


def _model(walls_x=(), *, config: RadioConfig | None = None) -> RadioModel:
    occ = np.zeros((400, 4000), dtype=bool)  # 400 m x 40 m
    for x in walls_x:
        occ[:, int(x / RES) : int(x / RES) + 2] = True
    return RadioModel(
        config or RadioConfig(), occupancy=occ, resolution_m=RES, gcs_xy_m=(1.0, 20.0)
    )


def test_magic2010_config_loads_with_the_model_parameters() -> None:
    cfg = load_config(REPO / "configs/radio/magic2010.yaml", RadioConfig)
    assert cfg.shared_capacity_bps == 115_200.0
    assert cfg.range_m > 0 and 0 < cfg.uplink_fraction < 1


def test_quality_falls_with_distance_and_walls() -> None:
    m = _model(walls_x=(60.0, 70.0))
    gcs = np.array([[1.0, 20.0]] * 4)
    q = m.quality(gcs, np.array([[20.0, 20.0], [100.0, 20.0], [65.0, 20.0], [75.0, 20.0]]))
    assert q[0] == 1.0 and q[1] < 1.0
    assert m.walls_between(gcs[:1], np.array([[75.0, 20.0]]))[0] == 2
    assert 0.0 < q[2] < 1.0 and q[3] < q[2]
    far = m.quality(gcs[:1], np.array([[200.0, 20.0]]))
    assert far[0] == 0.0  # beyond range_m


def test_disconnected_robot_gets_nothing_and_a_relay_extends_coverage() -> None:
    m = _model()
    xy = np.array([[100.0, 20.0], [200.0, 20.0]])
    s = m.update(xy, alive=np.array([True, True]), relay=np.array([False, False]))
    assert s.grants[1].uplink_bps == 0.0 and s.hops[1] == 0
    assert s.grants[0].uplink_bps > 0
    s = m.update(xy, alive=np.array([True, True]), relay=np.array([True, False]))
    assert s.grants[1].uplink_bps > 0 and s.hops[1] == 2 and s.next_hop[1] == 0
    # a dead relay relays nothing
    s = m.update(xy, alive=np.array([False, True]), relay=np.array([True, False]))
    assert s.grants[1].uplink_bps == 0.0 and s.grants[0].uplink_bps == 0.0


def test_the_capacity_is_shared_among_transmitting_robots() -> None:
    m = _model()
    xy = np.array([[10.0, 20.0], [12.0, 20.0], [14.0, 20.0]])
    s = m.update(xy, alive=np.ones(3, bool), relay=np.zeros(3, bool))
    total = sum(g.uplink_bps + g.downlink_bps for g in s.grants)
    assert total == pytest.approx(115_200.0)
    assert s.grants[0].uplink_bps == pytest.approx(115_200.0 / 3 * 0.75)
    s = m.update(
        xy,
        alive=np.ones(3, bool),
        relay=np.zeros(3, bool),
        transmitting=np.array([True, False, False]),
    )
    assert s.grants[0].uplink_bps + s.grants[0].downlink_bps == pytest.approx(115_200.0)


@settings(max_examples=60, deadline=None)
@given(
    xy=st.lists(st.tuples(st.floats(0, 399), st.floats(0, 39)), min_size=1, max_size=20),
    relay_bits=st.integers(0, 2**20 - 1),
    dead_bits=st.integers(0, 2**20 - 1),
    walls=st.lists(st.floats(5, 390), max_size=6),
)
def test_grants_never_exceed_the_shared_capacity(xy, relay_bits, dead_bits, walls) -> None:
    m = _model(walls_x=walls)
    n = len(xy)
    relay = np.array([(relay_bits >> k) & 1 for k in range(n)], bool)
    alive = ~np.array([(dead_bits >> k) & 1 for k in range(n)], bool)
    s = m.update(np.array(xy), alive=alive, relay=relay)
    air = sum(
        (g.uplink_bps + g.downlink_bps) * max(int(h), 1)
        for g, h in zip(s.grants, s.hops, strict=True)
    )
    assert air <= 115_200.0 * (1 + 1e-9)
    for g, h, a in zip(s.grants, s.hops, alive, strict=True):
        assert 0.0 <= g.loss < 1.0
        assert (g.uplink_bps > 0) == (h > 0)
        assert a or g.uplink_bps == 0.0
        assert h <= m.config.relay_max_hops
