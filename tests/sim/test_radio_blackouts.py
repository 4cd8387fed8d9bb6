"""Scheduled radio blackouts (issue 17): a robot's radio is off for its outages, on time, and
a seeded schedule repeats."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from protocol.config import load_config
from sim.radio_model import RadioBlackouts, blackout_schedule
from sim.simulator import Simulator, SimulatorConfig
from tests.sim.simworlds import make_world


def test_active_is_the_union_of_half_open_intervals() -> None:
    b = RadioBlackouts([(3, 10.0, 5.0), (7, 12.0, 1.0), (3, 14.0, 4.0)], [7, 3])
    assert b.active(9.99).tolist() == [False, False]
    assert b.active(10.0).tolist() == [False, True]
    assert b.active(12.5).tolist() == [True, True]
    assert b.active(13.0).tolist() == [False, True]  # robot 7's ended: half open
    assert b.active(17.9).tolist() == [False, True]  # robot 3's two overlap: the union
    assert b.active(18.0).tolist() == [False, False]
    edges = [b.next_edge_s(t) for t in (0.0, 10.0, 12.0, 13.0, 14.0, 15.0, 18.0)]
    assert edges == [10.0, 12.0, 13.0, 14.0, 15.0, 18.0, math.inf]


@pytest.mark.parametrize(
    ("entry", "words"),
    [
        ((9, 1.0, 1.0), "no robot 9"),
        ((0, -1.0, 1.0), "start_s"),
        ((0, math.nan, 1.0), "start_s"),
        ((0, 1.0, 0.0), "duration_s"),
        ((0, 1.0, math.inf), "duration_s"),
    ],
)
def test_bad_entries_are_named(entry: tuple[int, float, float], words: str) -> None:
    with pytest.raises(ValueError, match=rf"radio_blackouts\[1\].*{words}"):
        RadioBlackouts([(0, 0.0, 1.0), entry], [0, 1])


def test_schedule_is_seeded_fits_its_window_and_never_overlaps_per_robot() -> None:
    kw = dict(per_robot=2, duration_s=60.0, start_s=20.0, end_s=300.0)
    a = blackout_schedule([0, 1, 2], seed=5, **kw)  # type: ignore[arg-type]
    assert a == blackout_schedule([0, 1, 2], seed=5, **kw)  # type: ignore[arg-type]
    assert a != blackout_schedule([0, 1, 2], seed=6, **kw)  # type: ignore[arg-type]
    assert len(a) == 6
    for rid in (0, 1, 2):
        mine = sorted((s, s + d) for r, s, d in a if r == rid)
        assert len(mine) == 2 and mine[0][1] <= mine[1][0]
        assert mine[0][0] >= 20.0 and mine[1][1] <= 300.0
    with pytest.raises(ValueError, match="do not fit"):
        blackout_schedule([0], per_robot=3, duration_s=60.0, start_s=0.0, end_s=150.0, seed=0)


def test_config_loads_blackouts_and_rejects_unknown_keys(tmp_path) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / "sim.yaml"
    path.write_text("radio_blackouts: [[0, 30.0, 60.0], [1, 100, 60]]\n")
    cfg = load_config(path, SimulatorConfig)
    assert cfg.radio_blackouts == ((0, 30.0, 60.0), (1, 100.0, 60.0))
    path.write_text("radio_blackout: [[0, 30.0, 60.0]]\n")
    with pytest.raises(Exception, match="radio_blackout"):
        load_config(path, SimulatorConfig)
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert({"radio_blackouts": [[0, "soon", 1.0]]}, SimulatorConfig)


def test_a_blacked_out_robot_gets_nothing_on_time_and_the_other_keeps_its_link() -> None:
    world = make_world(robots=[(5.0, 10.0, 0.0, "sensor"), (6.0, 12.0, 0.0, "sensor")])
    # the outage starts and ends between two radio updates (period 1 s): edges on time
    cfg = SimulatorConfig(seed=0, radio_blackouts=((1, 0.52, 0.5),))
    with pytest.raises(ValueError, match="no robot 4"):
        Simulator(world, config=SimulatorConfig(radio_blackouts=((4, 1.0, 1.0),)))
    with Simulator(world, config=cfg) as sim:
        seen: list[tuple[float, float, float]] = []
        while sim.time_s < 1.5:
            sim.step()
            g = sim.radio_grants()
            seen.append((sim.time_s, g[0].uplink_bps, g[1].uplink_bps))
    t = np.array([s[0] for s in seen])
    up0 = np.array([s[1] for s in seen])
    up1 = np.array([s[2] for s in seen])
    off = (t >= 0.52 - 1e-9) & (t < 1.02 - 1e-9)
    assert np.all(up1[off] == 0.0) and np.all(up1[~off] > 0.0)
    assert np.all(up0 > 0.0)
    # alone on the air, robot 0 gets the whole share while robot 1 is off
    assert up0[off].min() > up0[~off].max()


def _lockstep_run() -> list[tuple[float, int, str]]:
    from mission.lockstep import TeamInLockstep, seed_streams
    from protocol.messages import HazardUpdate, RobotFrame
    from protocol.radio import RadioConfig

    world = make_world(robots=[(5.0, 10.0, 0.0, "sensor"), (6.0, 12.0, 0.0, "sensor")])
    cfg = SimulatorConfig(seed=0, radio_blackouts=((0, 2.0, 3.0),))
    radio = RadioConfig()
    arrived: list[tuple[float, int, str]] = []
    with Simulator(world, config=cfg, radio=radio) as sim:
        with TeamInLockstep(
            sim,
            radio=radio,
            seeds=seed_streams(3),
            on_ground_message=lambda rid, m: arrived.append((sim.time_s, rid, repr(m))),
        ) as team:
            frames = [RobotFrame(r, (0.0, 0.0, 0.0)) for r in sim.robot_ids]
            while sim.time_s < 7.0:
                team.step(lambda: team.ground.broadcast(HazardUpdate(sim.time_s, [], frames)))
    return arrived


def test_a_lockstep_run_with_a_blackout_repeats_exactly() -> None:
    a = _lockstep_run()
    assert a == _lockstep_run()
    robot0 = [t for t, rid, _ in a if rid == 0]
    assert robot0 and not [t for t in robot0 if 2.0 + 1e-6 < t < 5.0 - 1e-6]
    assert [t for t in robot0 if t >= 5.0 - 1e-6]  # what it held arrived afterwards
