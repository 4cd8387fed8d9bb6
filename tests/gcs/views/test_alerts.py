"""Alert rules (paper 6.3) on constructed dashboard rows."""

from __future__ import annotations

import math

import numpy as np

from gcs.views.alerts import AlertLog, AlertRules, AlertRulesConfig, Severity, Speaker
from gcs.views.operator_picture import ObjectSighting, RobotStatus


def row(
    rid: int = 1,
    *,
    age: float = 0.0,
    bps: float = 1000.0,
    battery: float = 0.9,
    stuck: bool = False,
    xy: tuple[float, float] = (0.0, 0.0),
    active: float = 100.0,
) -> RobotStatus:
    return RobotStatus(
        robot_id=rid,
        pose_in_map=np.array([xy[0], xy[1], 0.0]),
        linked=True,
        mode="autonomous",
        task="explore",
        task_kind="explore",
        battery_frac=battery,
        last_message_s=0.0,
        last_message_age_s=age,
        active_s=active,
        uplink_bps=bps,
        nodes=3,
        stuck=stuck,
        deadlock=False,
        trail_in_map=np.zeros((0, 2)),
        goal_in_map=None,
    )


def civilian(oid: int, xy: tuple[float, float]) -> ObjectSighting:
    return ObjectSighting(oid, "civilian", xy, 0.0, 0.0, 1, 1, 0.9)


def test_silence_warns_then_escalates_then_clears_once_each() -> None:
    rules = AlertRules()
    assert rules.evaluate([row(age=1.0)], [], 1.0) == []
    a = rules.evaluate([row(age=12.0)], [], 12.0)
    assert [(x.rule, x.severity) for x in a] == [("silence", Severity.WARNING)]
    assert rules.evaluate([row(age=20.0)], [], 20.0) == []  # still silent: no repeat
    a = rules.evaluate([row(age=61.0)], [], 61.0)
    assert [(x.rule, x.severity) for x in a] == [("silence", Severity.ERROR)]
    a = rules.evaluate([row(age=0.5)], [], 62.0)
    assert [(x.rule, x.severity, x.cleared) for x in a] == [("silence", Severity.INFO, True)]


def test_flicker_is_not_raised_again_within_repeat_s() -> None:
    rules = AlertRules(AlertRulesConfig(repeat_s=30.0))
    assert len(rules.evaluate([row(battery=0.2)], [], 0.0)) == 1
    assert len(rules.evaluate([row(battery=0.3)], [], 1.0)) == 1  # cleared
    assert rules.evaluate([row(battery=0.2)], [], 2.0) == []  # flicker: quiet
    assert rules.evaluate([row(battery=0.3)], [], 3.0) == []  # and its clearing too
    assert len(rules.evaluate([row(battery=0.2)], [], 40.0)) == 1


def test_battery_rate_stuck_and_civilian_rules() -> None:
    rules = AlertRules()
    rows = [
        row(1, battery=0.05),
        row(2, bps=5.0),
        row(3, bps=5.0, active=3.0),  # too young to judge its rate
        row(4, stuck=True),
        row(5, xy=(10.0, 0.0)),
        row(6, battery=math.nan),
    ]
    a = rules.evaluate(rows, [civilian(7, (11.0, 1.0)), civilian(8, (50.0, 0.0))], 100.0)
    got = {(x.rule, x.robot_id, x.severity) for x in a}
    assert got == {
        ("battery", 1, Severity.ERROR),
        ("message_rate", 2, Severity.WARNING),
        ("stuck", 4, Severity.WARNING),
        ("civilian", 5, Severity.WARNING),
    }
    assert "civilian 7" in next(x.text for x in a if x.rule == "civilian")
    assert set(rules.active) == {
        ("battery", "robot 1"),
        ("message_rate", "robot 2"),
        ("stuck", "robot 4"),
        ("civilian", "robot 5"),
    }


def test_log_keeps_text_lines_and_a_missing_speaker_is_silent() -> None:
    speaker = Speaker(command="no-such-tts-command-here")
    assert not speaker.available
    speaker.say("nothing happens")
    log = AlertLog(size=2, speaker=speaker)
    rules = AlertRules()
    for t in (12.0, 61.0, 62.0):
        log.extend(rules.evaluate([row(age=t if t < 62 else 0.0)], [], t))
    assert len(log.lines) == 2
    assert "ERROR" in log.text() and "cleared" in log.text()
