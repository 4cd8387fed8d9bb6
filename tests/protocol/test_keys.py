"""Zenoh key expressions: radio keys round-trip through parse_radio_key; bad parts are refused."""

from __future__ import annotations

from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol import keys
from protocol.keys import RadioKey, parse_radio_key
from protocol.messages import STREAMS, Direction

UP, DOWN = Direction.UP, Direction.DOWN
missions = st.from_regex(r"[A-Za-z0-9_.\-]+", fullmatch=True).filter(lambda s: "\n" not in s)
streams = st.sampled_from(
    [(d, name) for d in Direction for name, spec in STREAMS[d].items() if not spec.broadcast]
)


@settings(max_examples=150, deadline=None)
@given(mission=missions, robot_id=st.integers(0, 10**9), stream=streams)
def test_radio_keys_round_trip(mission: str, robot_id: int, stream: tuple[Direction, str]) -> None:
    direction, name = stream
    key = keys.radio(mission, robot_id, direction, name)
    assert key == f"magic/{mission}/robot/{robot_id}/{direction.value}/{name}"
    assert parse_radio_key(key) == RadioKey(mission, robot_id, direction, name)


def test_every_stream_has_a_key() -> None:
    for direction in Direction:
        for name, spec in STREAMS[direction].items():
            if spec.broadcast:
                key = keys.broadcast("m", name)
                assert key == f"magic/m/broadcast/down/{name}"
                assert keys.parse_broadcast_key(key) == name
                with pytest.raises(ValueError, match="no downlink stream"):
                    keys.radio("m", 0, direction, name)
                continue
            key = keys.radio("m", 0, direction, name)
            assert parse_radio_key(key).stream == name
            assert keys.parse_broadcast_key(key) is None
    assert keys.radio("field-trial_2.b", 13, UP, "pose_node") == (
        "magic/field-trial_2.b/robot/13/up/pose_node"
    )


@pytest.mark.parametrize("mission", ["", "a/b", "a b", "*", "**", "a$b", "m\n", "m?", "é", "a#b"])
def test_invalid_mission_names(mission: str) -> None:
    with pytest.raises(ValueError, match=r"^mission "):
        keys.radio(mission, 1, UP, "ack")
    with pytest.raises(ValueError, match=r"^mission "):
        keys.sim_clock(mission)
    with pytest.raises(ValueError, match=r"^mission "):
        keys.radio_wildcard(mission, DOWN)


@pytest.mark.parametrize("robot_id", [-1, -100, True, 1.0, "3", None])
def test_invalid_robot_ids(robot_id: Any) -> None:
    with pytest.raises(ValueError, match=r"^robot id .*: expected a non-negative int$"):
        keys.radio("m", robot_id, UP, "ack")
    with pytest.raises(ValueError, match=r"^robot id "):
        keys.sim_sensors("m", robot_id)


@pytest.mark.parametrize(
    ("direction", "stream"),
    [(UP, "task"), (DOWN, "telemetry"), (UP, "nosuch"), (DOWN, ""), (UP, "up")],
)
def test_unknown_streams(direction: Direction, stream: str) -> None:
    with pytest.raises(ValueError, match=rf"^no {direction.value}link stream named '{stream}'$"):
        keys.radio("m", 1, direction, stream)


@pytest.mark.parametrize(
    "key",
    [
        "",
        "magic",
        "magic/m/robot/1/up",
        "magic/m/robot/1/up/ack/extra",
        "/magic/m/robot/1/up/ack",
        "magik/m/robot/1/up/ack",
        "magic/m/robots/1/up/ack",
        "magic/m/robot/-1/up/ack",
        "magic/m/robot/x/up/ack",
        "magic/m/robot/01/up/ack",
        "magic/m/robot/\uff11/up/ack",  # a fullwidth digit: str.isdigit() says yes
        "magic/m/robot/1 /up/ack",
        "magic/m/robot/*/up/ack",
        "magic/m/robot/1/sideways/ack",
        "magic/m/robot/1/UP/ack",
        "magic//robot/1/up/ack",
        "magic/a b/robot/1/up/ack",
        "magic/*/robot/1/up/ack",
        "magic/m/sim/robot/1/sensors",
    ],
)
def test_malformed_keys(key: str) -> None:
    with pytest.raises(ValueError, match=r"^not a radio key: ") as info:
        parse_radio_key(key)
    assert repr(key) in str(info.value)


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        ("magic/m/robot/1/up/task", "radio key 'magic/m/robot/1/up/task': no uplink stream 'task'"),
        (
            "magic/m/robot/2/down/pose_node",
            "radio key 'magic/m/robot/2/down/pose_node': no downlink stream 'pose_node'",
        ),
        ("magic/m/robot/0/up/*", "radio key 'magic/m/robot/0/up/*': no uplink stream '*'"),
    ],
)
def test_unknown_stream_in_key(key: str, expected: str) -> None:
    with pytest.raises(ValueError) as info:
        parse_radio_key(key)
    assert str(info.value) == expected


def test_other_keys() -> None:
    assert keys.radio_wildcard("m", UP) == "magic/m/robot/*/up/*"
    assert keys.radio_wildcard("m", DOWN, 4) == "magic/m/robot/4/down/*"
    assert keys.gcs("m", "state/graph") == "magic/m/gcs/state/graph"
    assert keys.gcs("m", "command") == "magic/m/gcs/command"
    assert keys.sim_clock("m") == "magic/m/sim/clock"
    assert keys.sim_sensors("m", 2) == "magic/m/sim/robot/2/sensors"
    assert keys.sim_commands("m", 2) == "magic/m/sim/robot/2/commands"
    assert keys.sim_radio("m", 5) == "magic/m/sim/radio/5"
    assert keys.sim_radio("m", None) == "magic/m/sim/radio/*"
    assert keys.sim_truth("m", "poses") == "magic/m/sim/truth/poses"
    with pytest.raises(ValueError, match=r"^gcs topic ''"):
        keys.gcs("m", "state//graph")
    with pytest.raises(ValueError, match=r"^truth topic 'a/b'"):
        keys.sim_truth("m", "a/b")
    with pytest.raises(ValueError, match=r"^robot id -2"):
        keys.sim_radio("m", -2)


def test_broadcast_keys_refuse_unicast_streams_and_name_the_key() -> None:
    with pytest.raises(ValueError, match="no broadcast stream named 'task'"):
        keys.broadcast("m", "task")
    with pytest.raises(ValueError, match="magic/m/broadcast/down/task"):
        keys.parse_broadcast_key("magic/m/broadcast/down/task")
    assert keys.broadcast_wildcard("m") == "magic/m/broadcast/down/*"
