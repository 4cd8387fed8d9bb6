"""The GCS in its own process (``magic run --gcs-process``, :mod:`mission.lockstep_gcs`):
a run whose GCS process is killed is repeatable, wherever in the step the kill strikes."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.slow


def gcs_process_team(
    journal: Path, *, seed: int, mission: str, endpoint: str | None = None, **kw: Any
) -> Any:
    """``assemble`` of the small world's team as ``magic run --gcs-process`` has it: robot
    nodes in one worker process, the GCS in its own, journaling to ``journal``; this process
    listening on ``endpoint`` (default a free loopback port) under mission name ``mission``;
    ``kw`` further :func:`~mission.assembly.assemble` options."""
    from mission.assembly import assemble
    from mission.config import config_path, load_config
    from mission.lockstep import seed_streams
    from protocol.link import LinkConfig
    from protocol.loopback import free_loopback_port
    from protocol.radio import RadioConfig
    from sim.simulator import load_world_config

    world = load_world_config(config_path("world/small.yaml", "world"))
    radio_path = config_path("radio/magic2010.yaml", "radio")
    endpoint = endpoint or f"tcp/127.0.0.1:{free_loopback_port()}"
    return assemble(
        world,
        seeds=seed_streams(seed),
        radio=load_config(radio_path, RadioConfig),
        radio_path=str(radio_path),
        journal_path=journal,
        robot_processes=True,
        workers=1,
        gcs_process=True,
        link=LinkConfig(listen=(endpoint,)),
        mission_name=mission,
        **kw,
    )


def _killed_run(run_dir: Path, *, seed: int, duration_s: float, kill: str) -> dict[str, Any]:
    """A small-world lockstep run, the GCS in its own process, SIGKILLed at the middle step:
    ``kill`` ``"at_go"`` right after its turn was asked for (mid-turn), ``"after_turn"`` once
    it answered its turn (the turn's step, plan and downlink made). Returns what the journal
    holds after the kill and the robots' last task reports."""
    from gcs.journal import GcsJournal
    from mission.bench.chaos import _floor_loss
    from mission.lockstep import TeamOverProcesses
    from protocol.loopback import unique_mission

    journal = run_dir / "journal.sqlite"
    with gcs_process_team(
        journal,
        seed=seed,
        mission=unique_mission("gcs-repeat"),
        # the station steps every turn: the turn the kill strikes journals a step
        gcs_step_period_s=0.05,
    ) as asm:
        _floor_loss(asm.sim, 0.3)
        remote, team = asm.remote_gcs, asm.team
        assert isinstance(team, TeamOverProcesses)
        steps = int(round(duration_s / asm.sim.config.step_s))
        kill_step = steps // 2
        kill_time_s = 0.0
        for k in range(steps):
            if k == kill_step:
                kill_time_s = asm.sim.time_s + asm.sim.config.step_s

                def strike(r: Any = remote, t: float = kill_time_s) -> None:
                    if kill == "after_turn":
                        r._wait("turn", t, 60.0, restart=False)
                    r.kill()

                on_step: Callable[[], None] = strike
                team.step(on_step)
            else:
                team.report_link = k == steps - 1
                asm.step()
        assert remote.restarts == 1
        progress = {int(r): row for r, row in remote.figures["progress"].items()}
        gcs = dict(remote.figures["gcs"])
    reader = GcsJournal.open(journal)
    try:
        records = [
            (r.kind, round(r.time_s, 6), r.robot_id, r.body)
            for r in reader.records()
            if r.time_s >= kill_time_s - 1.0 and r.kind != "checkpoint"
        ]
    finally:
        reader.close()
    return {"records": records, "progress": progress, "gcs": gcs, "kill_time_s": kill_time_s}


def test_a_killed_gcs_process_resumes_the_same_way_wherever_in_its_turn_it_died(
    tmp_path: Path,
) -> None:
    """Same seed, same step of the kill: the GCS killed before it took its turn and killed
    after it answered its turn (the turn's station step, plan, tasks and downlink journaled)
    give the same run afterwards, record for record: a turn is committed with the step's end,
    so the journal a resume reads does not depend on the kill's moment in the turn. (Before,
    the turn was committed on its own: a kill after it left it in the journal, and the resumed
    GCS stepped and planned that time twice.)"""
    runs = {}
    for kill in ("at_go", "after_turn"):
        d = tmp_path / kill
        d.mkdir()
        runs[kill] = _killed_run(d, seed=3, duration_s=8.0, kill=kill)
    a, b = runs["at_go"], runs["after_turn"]
    assert a["kill_time_s"] == b["kill_time_s"]
    assert len(a["records"]) > 50  # the mission went on after the kill
    kinds = {r[0] for r in a["records"]}
    assert {"uplink", "step", "link"} <= kinds
    first = next(
        (i for i, (x, y) in enumerate(zip(a["records"], b["records"], strict=False)) if x != y),
        None,
    )
    assert first is None and len(a["records"]) == len(b["records"]), (
        f"journals differ from record {first}: "
        f"{a['records'][first][:3] if first is not None else len(a['records'])} vs "
        f"{b['records'][first][:3] if first is not None else len(b['records'])}"
    )
    assert a["progress"] == b["progress"]
    assert a["gcs"] == b["gcs"]


def test_a_console_reaches_the_gcs_in_its_own_process(tmp_path: Path) -> None:
    """``assemble(gcs_operator=...)`` (``magic run --gcs-process``) -> ``GcsSetup.operator``:
    the GCS process serves consoles as the in-process GCS does: a
    ``magic console``'s signed command, over zenoh to the GCS process, is carried out at its
    next turn (a PauseTask to robot 0, on the radio) and answered; its status reaches the
    console; the command is journaled."""
    import threading

    import mission.lockstep_gcs as lg
    from gcs.console.client import ConsoleClient
    from gcs.journal import GcsJournal
    from protocol import operator as op
    from protocol.link import Link, LinkConfig
    from protocol.loopback import free_loopback_port, unique_mission

    key_file = tmp_path / "operator.key"
    key = op.load_or_create_key(key_file, create=True)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("gcs-console")
    journal = tmp_path / "journal.sqlite"
    with gcs_process_team(
        journal,
        seed=1,
        mission=mission,
        endpoint=endpoint,
        gcs_standby=False,
        gcs_operator=lg.OperatorSetup(key_file=str(key_file)),  # as magic run --gcs-process
    ) as asm:
        console_link = Link(LinkConfig(connect=(endpoint,), pump_period_s=0.0), mission=mission)
        client = ConsoleClient(console_link, "alice", key)
        replies: list[Any] = []

        def operate() -> None:
            if client.wait_for_status(lambda s: bool(s.robots), 120.0):
                replies.append(client.send(op.Command("pause", "0"), timeout_s=120.0))

        thread = threading.Thread(target=operate, daemon=True)
        thread.start()
        try:
            steps = 0
            while thread.is_alive() and steps < 2000:
                asm.step()
                steps += 1
            thread.join(1.0)
            assert replies and replies[0] is not None, "no reply from the GCS process"
            reply = replies[0]
            assert reply.status == "ok", reply
            assert len(reply.task_ids) == 1
            for _ in range(40):  # the PauseTask goes out on the radio with the next steps
                asm.step()
        finally:
            client.close()
            console_link.close()
    reader = GcsJournal.open(journal)
    try:
        ops = [r.json() for r in reader.records(kind="operator")]
        downs = [r for r in reader.records(kind="downlink") if r.robot_id == 0]
    finally:
        reader.close()
    assert any("pause" in str(f) for f in ops), ops
    from protocol.messages import Direction, PauseTask, decode_frame

    paused = [decode_frame(r.body, Direction.DOWN).msg for r in downs]
    assert any(isinstance(m, PauseTask) and m.task_id == reply.task_ids[0] for m in paused)


def test_an_operators_pause_holds_across_a_kill_of_the_gcs_process(tmp_path: Path) -> None:
    """A console pauses robot 0, then the GCS process is killed with SIGKILL: the standby
    that takes over holds what the operators decided (its status, over zenoh, shows robot 0
    paused and the one interaction), and its planners give robot 0 no task afterwards (the
    resumed GCS had forgotten the pause: it tasked the robot to explore again and counted
    no interaction)."""
    import threading

    import mission.lockstep_gcs as lg
    from gcs.console.client import ConsoleClient
    from gcs.journal import GcsJournal
    from mission.lockstep import TeamOverProcesses
    from protocol import operator as op
    from protocol.link import Link, LinkConfig
    from protocol.loopback import free_loopback_port, unique_mission

    key_file = tmp_path / "operator.key"
    key = op.load_or_create_key(key_file, create=True)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("gcs-pause-kill")
    journal = tmp_path / "journal.sqlite"
    with gcs_process_team(
        journal,
        seed=1,
        mission=mission,
        endpoint=endpoint,
        gcs_operator=lg.OperatorSetup(key_file=str(key_file)),  # standby too, as magic run
    ) as asm:
        remote, team = asm.remote_gcs, asm.team
        assert isinstance(team, TeamOverProcesses)
        console_link = Link(LinkConfig(connect=(endpoint,), pump_period_s=0.0), mission=mission)
        client = ConsoleClient(console_link, "alice", key)
        replies: list[Any] = []

        def operate() -> None:
            if client.wait_for_status(lambda s: bool(s.robots), 120.0):
                replies.append(client.send(op.Command("pause", "0"), timeout_s=120.0))

        def row0(status: Any) -> Any:
            return next(r for r in status.robots if r.robot_id == 0)

        thread = threading.Thread(target=operate, daemon=True)
        thread.start()
        try:
            steps = 0
            while thread.is_alive() and steps < 2000:
                asm.step()
                steps += 1
            thread.join(1.0)
            assert replies and replies[0] is not None and replies[0].status == "ok", replies
            paused_at_s = replies[0].time_s
            for _ in range(40):  # the PauseTask on the radio; a status after it
                asm.step()
            assert client.wait_for_status(lambda s: s.time_s > paused_at_s, 30.0)
            before = client.status
            assert before is not None and row0(before).control == "paused"
            assert before.interactions == 1
            first_pid = remote.pid
            team.step(remote.kill)  # SIGKILL during its turn: the standby takes over
            killed_at_s = asm.sim.time_s
            assert remote.restarts == 1 and remote.pid != first_pid
            after = None
            for _ in range(400):  # until the resumed GCS's status comes
                asm.step()
                st = client.status
                if st is not None and st.time_s > killed_at_s + 0.5:
                    after = st
                    break
            assert after is not None, "no status from the resumed GCS"
            for _ in range(100):  # 5 mission-s on: its planners plan meanwhile
                asm.step()
        finally:
            client.close()
            console_link.close()
    assert row0(after).control == "paused", row0(after)
    assert after.interactions == before.interactions == 1
    # every robot as the killed GCS showed it (roles from their last reports), none unknown
    roles = {r.robot_id: r.role for r in before.robots}
    assert {r.robot_id: r.role for r in after.robots} == roles and "unknown" not in roles.values()
    reader = GcsJournal.open(journal)
    try:
        tasks_to_0 = [
            (r.time_s, r.json())
            for r in reader.records(kind="decision")
            if r.robot_id == 0 and "task_id" in r.json() and r.time_s > paused_at_s
        ]
    finally:
        reader.close()
    assert tasks_to_0 == [], f"the planners tasked the paused robot: {tasks_to_0}"
