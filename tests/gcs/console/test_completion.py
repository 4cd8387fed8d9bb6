"""Console completion offers the right candidates for partial input; macros load and check."""

from __future__ import annotations

from pathlib import Path

import pytest

from gcs.console.completion import candidates
from gcs.console.macros import load_macros
from protocol.config import ConfigError
from protocol.operator import GcsStatus, HazardRow, RobotRow


def _status() -> GcsStatus:
    robots = [
        RobotRow(0, "sensor", "autonomous", "explore", "planner", (1.0, 2.0, 0.0), 5.0, 0.9),
        RobotRow(1, "sensor", "idle", "none", "planner", None, 5.0, 0.8),
        RobotRow(12, "sensor", "paused", "task 3", "paused", (3.0, 1.0, 0.0), 5.0, 0.7),
        RobotRow(3, "disruptor", "idle", "none", "planner", (0.0, 0.0, 0.0), 5.0, 0.9),
    ]
    hazards = [
        HazardRow(4, "static_ooi", (10.0, 2.0), "pending_approval"),
        HazardRow(7, "static_ooi", (12.0, 5.0), "approved"),
    ]
    return GcsStatus(1, "m", 6.0, robots, hazards)


def words(text: str) -> list[str]:
    return [c for c, _ in candidates(text, _status())]


def test_commands_and_local_words() -> None:
    assert words("p") == ["pause"]
    assert words("re") == ["resume", "relay", "reclassify", "rewind", "restart-loops"]
    assert set(words("")) >= {"goto", "status", "help", "quit"}
    assert words("help go") == ["goto"]
    assert words("xyz ") == []


def test_robot_ids_groups_and_comma_lists() -> None:
    assert words("pause 1") == ["1", "12"]
    assert words("goto s") == ["sensors"]
    assert words("pause d") == ["disruptors"]
    assert words("resume 0,1") == ["0,1", "0,12"]
    assert words("auto 0,i") == ["0,idle"]
    assert "all" in words("status ")
    assert words("goto 3 ") == []  # a number comes next: nothing to offer
    assert words("relay ") == ["0", "1", "12", "3"]


def test_ooi_ids_kinds_parameters_and_poses() -> None:
    assert words("approve ") == ["4"]  # only what may still be approved
    assert words("reclassify ") == ["4", "7"]
    assert words("reclassify 4 ci") == ["civilian"]
    assert words("neutralize 4 ") == ["3"]  # the disruptors
    assert words("set tel") == ["telemetry_period_s"]
    assert words("closure 1") == ["1:", "12:"]
    assert words("closure 12:l") == ["12:last"]
    assert words("set telemetry_period_s 1 ") == words("pause ")


def test_shipped_macros_load_and_bad_ones_are_named(tmp_path: Path) -> None:
    macros = load_macros()
    assert macros["f1"].commands == ("auto all", "resume all")
    bad = tmp_path / "m.yaml"
    bad.write_text("f1:\n  commands: ['paus all']\n")
    with pytest.raises(ConfigError, match=r"f1.commands\[0\].*did you mean 'pause'"):
        load_macros(bad)
    bad.write_text("f13:\n  commands: ['status']\n")
    with pytest.raises(ConfigError, match="function key"):
        load_macros(bad)
    bad.write_text("f2:\n  command: ['status']\n")
    with pytest.raises(ConfigError, match="command"):
        load_macros(bad)


def test_the_bar_names_the_usage_of_the_command_being_typed() -> None:
    """Numbers cannot be completed: the status bar's second line says what comes next."""
    from gcs.console.client import ConsoleClient
    from gcs.console.repl import Console
    from protocol.link import Link, LinkConfig

    link = Link(LinkConfig(listen=("tcp/127.0.0.1:0",), pump_period_s=0.0), mission="bar")
    client = ConsoleClient(link, "tester", bytes(32))
    try:
        console = Console(client)
        bar = console.toolbar("")
        assert "NOT CONNECTED" in bar and "\n" not in bar
        bar = console.toolbar("pause all; goto 0 3")
        assert bar.splitlines()[1].startswith(" goto ROBOTS X_M Y_M: "), bar
        assert "\n" not in console.toolbar("paus")  # not a command (yet): no usage line
    finally:
        client.close()
        link.close()
