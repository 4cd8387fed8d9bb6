"""The MAGIC rules (paper section 2) fire exactly when they should."""

from __future__ import annotations

import numpy as np
import pytest

from sim.rules import Event, Rules, RulesConfig

DT = 0.05


def _rules(
    *, statics=((0.0, 0.0),), hostiles=1, civilians=1, roles=("sensor", "sensor", "disruptor")
):
    return Rules(
        static_ids=list(range(10, 10 + len(statics))),
        static_xy_m=np.array(statics, dtype=float).reshape(-1, 2),
        hostile_ids=list(range(100, 100 + hostiles)),
        civilian_ids=list(range(200, 200 + civilians)),
        robot_roles=list(roles),
    )


def _step(
    r: Rules,
    t: float,
    *,
    robots,
    civilians=((50.0, 50.0),),
    hostiles=((80.0, 80.0),),
    lasered=None,
    view=None,
):
    n = len(robots)
    return r.step(
        t,
        robot_xy_m=np.array(robots, dtype=float),
        civilian_xy_m=np.array(civilians, dtype=float).reshape(-1, 2),
        hostile_xy_m=np.array(hostiles, dtype=float).reshape(-1, 2),
        lasered=np.full(n, -1) if lasered is None else np.array(lasered),
        hostile_in_view=np.zeros((n, len(r.hostile_ids)), bool) if view is None else np.array(view),
    )


FAR = (60.0, 0.0)


def test_static_ooi_triggers_at_2_5_m_and_blasts_10_m() -> None:
    r = _rules()
    assert _step(r, 0.0, robots=[(2.51, 0.0), FAR, FAR]) == []
    ev = _step(r, 0.05, robots=[(2.49, 0.0), (0.0, 9.99), (10.01, 0.0)], civilians=[(-9.0, 0.0)])
    kinds = [(e.kind, e.subject) for e in ev]
    assert kinds[0] == ("detonation", "static_ooi:10")
    assert ev[0].cause == "robot:0" and ev[0].time_s == 0.05
    assert ("robot_lost", "robot:0") in kinds and ("robot_lost", "robot:1") in kinds
    assert ("robot_lost", "robot:2") not in kinds
    assert ("civilian_harmed", "civilian:200") in kinds
    assert list(r.robot_alive) == [False, False, True]
    assert r.static_status == ["detonated"]
    assert _step(r, 0.1, robots=[(0.0, 0.0)] * 3) == []  # it is gone
    assert r.events == ev


def test_hostile_triggers_at_2_5_m_and_blasts_5_m() -> None:
    r = _rules(statics=())
    assert _step(r, 0.0, robots=[(2.51, 0.0), FAR, FAR], hostiles=[(0.0, 0.0)]) == []
    ev = _step(r, 0.05, robots=[(2.5, 0.0), (0.0, 4.99), (0.0, -5.01)], hostiles=[(0.0, 0.0)])
    assert [e.kind for e in ev] == ["detonation", "robot_lost", "robot_lost"]
    assert ev[0].subject == "hostile:100" and set(ev[0].robots) == {0, 1}
    assert r.hostile_status == ["detonated"]


def test_a_civilian_triggers_too() -> None:
    r = _rules()
    ev = _step(r, 1.0, robots=[FAR, FAR, FAR], civilians=[(0.0, 2.4)])
    assert ev[0].kind == "detonation" and ev[0].cause == "civilian:200"
    assert ev[1].kind == "civilian_harmed"


def test_laser_neutralizes_after_exactly_15_s() -> None:
    r = _rules()
    robots = [FAR, FAR, (5.0, 0.0)]
    t = 0.0
    for k in range(int(round(15.0 / DT))):
        t = k * DT
        assert _step(r, t, robots=robots, lasered=[-1, -1, 0]) == []
    ev = _step(r, 15.0, robots=robots, lasered=[-1, -1, 0])
    assert [(e.kind, e.subject, e.robots) for e in ev] == [("neutralized", "static_ooi:10", (2,))]
    assert r.static_status == ["neutralized"]
    assert _step(r, 0.0 + 15.05, robots=[(0.0, 0.0)] * 3) == []  # no longer dangerous


def test_a_line_of_sight_break_resets_the_laser_timer() -> None:
    r = _rules()
    robots = [FAR, FAR, (5.0, 0.0)]
    steps = int(round(30.0 / DT))
    neutralized_at = None
    for k in range(steps + 1):
        t = k * DT
        on = not (10.0 <= t < 10.2)  # the beam is blocked for 0.2 s
        ev = _step(r, t, robots=robots, lasered=[-1, -1, 0 if on else -1])
        if ev:
            neutralized_at = ev[0].time_s
            break
    assert neutralized_at == pytest.approx(10.2 + 15.0)


def test_only_disruptors_lasers_count() -> None:
    r = _rules()
    for k in range(int(round(20.0 / DT))):
        assert _step(r, k * DT, robots=[(5.0, 0.0), FAR, FAR], lasered=[0, 0, -1]) == []


def test_hostile_needs_two_sensor_robots_for_30_s() -> None:
    r = _rules(statics=())
    host = [(0.0, 0.0)]
    robots = [(6.0, 0.0), (-6.0, 0.0), (0.0, 6.0)]
    # one sensor robot and a disruptor are not enough
    for k in range(int(round(40.0 / DT))):
        assert _step(r, k * DT, robots=robots, hostiles=host, view=[[True], [False], [True]]) == []
    t0 = 40.0
    fired = None
    for k in range(int(round(31.0 / DT))):
        t = t0 + k * DT
        ev = _step(r, t, robots=robots, hostiles=host, view=[[True], [True], [False]])
        if ev:
            fired = ev[0]
            break
    assert fired is not None and fired.time_s == pytest.approx(t0 + 30.0)
    assert fired.subject == "hostile:100" and fired.robots == (0, 1)


def test_a_broken_visual_lock_restarts() -> None:
    r = _rules(statics=())
    host = [(0.0, 0.0)]
    robots = [(6.0, 0.0), (-6.0, 0.0), FAR]
    fired = None
    for k in range(int(round(60.0 / DT))):
        t = k * DT
        both = not (20.0 <= t < 20.05)
        ev = _step(r, t, robots=robots, hostiles=host, view=[[True], [both], [False]])
        if ev:
            fired = ev[0].time_s
            break
    assert fired == pytest.approx(20.05 + 30.0)


def test_rules_config_rejects_nonsense() -> None:
    with pytest.raises(ValueError, match="laser_hold_s must be finite and > 0"):
        RulesConfig(laser_hold_s=float("nan"))


def test_an_event_reads_as_one_line_for_people() -> None:
    assert str(Event(81.99999999999748, "neutralized", "static_ooi:0", "laser")) == (
        "t=82.0 s neutralized static_ooi:0 (laser)"
    )
    assert str(Event(3.0, "robot_lost", "robot:2")) == "t=3.0 s robot_lost robot:2"
