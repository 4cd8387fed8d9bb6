"""``magic run`` serves consoles (issue 15): the operator service on the run's GCS, reached
over real zenoh with the ``magic console`` command the run prints; a console's commands are
interactions in the mission report (paper Fig. 24), and the robot an operator sent somewhere
reports itself semi-autonomous, so the report's time and distance per autonomy mode (paper
Tables 4-5) have a real semi-autonomous share."""

from __future__ import annotations

import json
import math
import shlex
import time
from pathlib import Path
from typing import Any

import pytest

from gcs.console.client import ConsoleClient
from gcs.operator.grammar import parse_line
from gcs.operator.service import OperatorService
from mission.run import RunConfig, run_mission
from protocol import operator as op
from protocol.link import Link, LinkConfig

pytestmark = pytest.mark.slow

KEY = bytes(range(32))


@pytest.mark.timeout(1500)  # minutes of mission under a shared machine
def test_a_run_with_an_operator_reports_interactions_and_semi_autonomous_time(
    tmp_path: Path,
) -> None:
    services: list[OperatorService] = []
    hints: list[str] = []
    state: dict[str, Any] = {}

    def operators(link: Any, control: Any) -> OperatorService:
        services.append(OperatorService(link, key=KEY, control=control, status_period_s=0.5))
        return services[-1]

    def send(text: str) -> None:
        """A console's signed command, held until the GCS has it (it is carried out at the
        next ground turn: a mission time that does not depend on the machine's load)."""
        client: ConsoleClient = state["client"]
        signed = client.signed(parse_line(text))
        state["link"].publish(op.command_key(client.mission), op.encode(signed))
        deadline = time.monotonic() + 60.0
        while services[0]._pending.empty():
            assert time.monotonic() < deadline, f"the GCS never got {text!r}"
            time.sleep(0.01)

    def on_step(asm: Any) -> None:
        t = asm.sim.time_s
        if "client" not in state:
            words = shlex.split(hints[0])
            connect = words[words.index("--connect") + 1]
            mission = words[words.index("--mission") + 1]
            link = Link(LinkConfig(connect=(connect,), pump_period_s=0.0), mission=mission)
            state["link"], state["client"] = link, ConsoleClient(link, "tester", KEY)
        graph = asm.gcs.station.graph
        if "goal" not in state and t >= 4.0 and 0 in graph.robots:
            x, y, _ = graph.pose(graph.last_key(0))  # where robot 0 has been: reachable
            state["goal"] = (float(x), float(y))
        if "goto" not in state and t >= 15.0:
            gx, gy = state["goal"]
            x, y, _ = graph.pose(graph.last_key(0))
            state["goto"] = (t, math.dist((x, y), (gx, gy)))
            send(f"goto 0 {gx:.2f} {gy:.2f}")
        if "auto" not in state and t >= 35.0:
            state["auto"] = t
            send("auto 0")

    config = RunConfig(world="world/small.yaml", duration_s=50.0, seed=3)
    try:
        report = run_mission(
            config,
            out_dir=tmp_path / "run",
            operator=operators,
            on_console=hints.append,
            on_step=on_step,
        )
    finally:
        if "client" in state:
            state["client"].close()
            state["link"].close()
    assert report.interrupted is None
    assert hints and hints[0].startswith("magic console --connect tcp/127.0.0.1:"), hints
    assert state["goto"][1] > 1.0, f"robot 0 was already at its goal: {state['goto']}"
    m = report.metrics
    assert m["interactions"] == 2.0
    assert m["interactions_per_min"] == pytest.approx(2.0 / (50.0 / 60.0), rel=1e-3)
    assert m.get("mode_semi_autonomous_s", 0.0) > 2.0, m
    assert m.get("mode_semi_autonomous_m", 0.0) > 0.5, m
    assert m.get("mode_autonomous_s", 0.0) > m["mode_semi_autonomous_s"]
    doc = json.loads((tmp_path / "run" / "report.json").read_text())
    # robot 0 alone was semi-autonomous; every robot's modes cover the whole mission
    for r, per in doc["modes_s"].items():
        assert sum(per.values()) == pytest.approx(report.mission_s, abs=0.2), (r, per)
        assert (per.get("semi_autonomous", 0.0) > 0) == (r == "0"), (r, per)
    events = [e for e in doc["events"] if e["kind"] == "interaction"]
    assert [e["command"] for e in events] == [events[0]["command"], "auto 0"]
    assert events[0]["command"].startswith("goto 0 ") and events[0]["robots"] == [0]
    assert events[0]["t_s"] == pytest.approx(state["goto"][0], abs=0.5)
    md = (tmp_path / "run" / "report.md").read_text()
    assert "semi_autonomous" in md and "interactions per minute" in md


@pytest.mark.timeout(1500)  # minutes of mission under a shared machine
def test_a_run_no_console_talks_to_is_the_same_run_as_without_one() -> None:
    """The operator station on the GCS (status, presence, a command subscription) changes
    nothing in a run until a command arrives: the same figures bit for bit."""
    from mission.run import fields_differing

    config = RunConfig(duration_s=12.0, seed=0)
    services: list[OperatorService] = []

    def operators(link: Any, control: Any) -> OperatorService:
        services.append(OperatorService(link, key=KEY, control=control, status_period_s=0.2))
        return services[-1]

    served = run_mission(config, operator=operators).fields()
    plain = run_mission(config).fields()
    assert services and services[0].replies_sent == 0
    assert len(services[0].reports) == 4  # it heard every robot
    assert fields_differing(served, plain) == []
