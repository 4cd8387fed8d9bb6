"""`magic gcs` with the operator station: a console's signed command reaches the robot over
zenoh and the radio, the views record while the node runs, the options are checked."""

from __future__ import annotations

import argparse
import threading
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from gcs.console.client import ConsoleClient
from gcs.ground_station import GroundStationConfig
from gcs.node import GcsProcess
from gcs.operator.node_hooks import add_operator_arguments, check_operator_arguments
from gcs.operator.service import ModeLedger, OperatorService
from protocol import operator as op
from protocol.clock import ManualClock
from protocol.link import Link, LinkConfig
from protocol.loopback import open_pair
from protocol.messages import AutonomyMode, PauseTask, Telemetry
from tests.gcs.test_ground_station import grid_msg, nodes_along, straight

KEY = bytes(range(32, 64))


def test_console_command_reaches_the_robot_and_views_record(tmp_path: Path) -> None:
    clock = ManualClock()
    gcs_link, robot_link = open_pair(clock=clock)
    console_link = Link(
        LinkConfig(connect=gcs_link.config.listen, pump_period_s=0.0), mission=gcs_link.mission
    )
    proc = GcsProcess(gcs_link, clock, GroundStationConfig(robots=(0,)), step_period_s=0.5)
    rrd = tmp_path / "gcs.rrd"
    proc.operator = OperatorService(
        gcs_link, key=KEY, views=[f"save {rrd}"], control=proc.control, status_period_s=0.2
    )
    got: list[object] = []
    robot0 = robot_link.robot_endpoint(0, on_message=got.append)
    client = ConsoleClient(console_link, "alice", KEY)
    stop = threading.Event()

    def spin() -> None:
        while not stop.is_set():
            clock.set(clock.now() + 0.1)
            robot_link.pump()
            gcs_link.pump()
            proc.spin_once(timeout_s=0.01)

    thread = threading.Thread(target=spin, daemon=True)
    try:
        assert proc.radio.wait_for_robot(0, 10.0)
        wall = np.zeros((40, 40), dtype=bool)
        wall[30, :] = True
        for i, node in enumerate(nodes_along(straight(8))):
            robot0.send(node)
            robot0.send(grid_msg(i, wall))
            robot0.send(Telemetry(float(i), node.pose_in_odom, (0.5, 0.0), (0.0, 0.0), 0.9,
                                  AutonomyMode.AUTONOMOUS, 5))  # fmt: skip
        thread.start()
        assert client.wait_for_status(lambda s: any(r.robot_id == 0 for r in s.robots), 20.0)
        reply = client.send(op.Command("pause", "0"), timeout_s=20.0)
        assert reply is not None and reply.status == "ok", reply
        assert reply.interaction and len(reply.task_ids) == 1

        def paused() -> bool:
            return any(isinstance(m, PauseTask) and m.task_id == reply.task_ids[0] for m in got)

        deadline = threading.Event()
        for _ in range(200):
            if paused():
                break
            deadline.wait(0.05)
        assert paused(), f"robot 0 never got its PauseTask: {got}"
        bad = client.send_raw(
            op.sign(bytes(32), client.mission, "alice", client.seq.next(), op.Command("status")),
            timeout_s=20.0,
        )
        assert bad is not None and bad.reason == "forged"
    finally:
        stop.set()
        if thread.is_alive():
            thread.join(5.0)
        client.close()
        proc.close()
        console_link.close()
        robot_link.close()
        gcs_link.close()
    entities = {c.entity_path for c in RrdReader(rrd).stream() if c.num_rows}
    assert {"/world/robots", "/world/map", "/world/graph/odometry", "/dashboard/table"} <= entities


def _args(tmp_path: Path, *argv: str) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    add_operator_arguments(p)
    return p.parse_args([*argv, "--operator-key", str(tmp_path / "k.key")])


def test_operator_options_are_checked(tmp_path: Path) -> None:
    check_operator_arguments(_args(tmp_path, "--rerun", "connect", "127.0.0.1:9876"))
    assert not (tmp_path / "k.key").exists()  # made at the first command, not before
    op.load_or_create_key(tmp_path / "k.key")
    check_operator_arguments(_args(tmp_path))
    check_operator_arguments(
        _args(tmp_path, "--rerun", "serve", "--rerun-save", str(tmp_path / "a.rrd"))
    )
    with pytest.raises(ValueError, match="--rerun: expected spawn"):
        check_operator_arguments(_args(tmp_path, "--rerun", "sapwn"))
    with pytest.raises(ValueError, match="takes no address"):
        check_operator_arguments(_args(tmp_path, "--rerun", "spawn", "1.2.3.4:5"))
    with pytest.raises(ValueError, match=".rrd"):
        check_operator_arguments(_args(tmp_path, "--rerun-save", str(tmp_path / "a.txt")))
    with pytest.raises(ValueError, match="does not exist"):
        check_operator_arguments(_args(tmp_path, "--rerun-save", str(tmp_path / "no/a.rrd")))
    (tmp_path / "k.key").chmod(0o644)
    with pytest.raises(ValueError, match="--operator-key: .*chmod 600"):
        check_operator_arguments(_args(tmp_path))


def test_a_gcs_without_a_key_file_makes_it_at_the_first_command(tmp_path: Path) -> None:
    gcs_link, console_side = open_pair()
    path = tmp_path / "conf" / "operator.key"
    try:
        service = OperatorService(gcs_link, key_file=path)
        assert service.verifier is None and not path.exists()
        verifier = service._get_verifier()
        assert verifier is not None and path.stat().st_mode & 0o777 == 0o600
        signed = op.sign(
            op.load_or_create_key(path), gcs_link.mission, "a", 10**18, op.Command("status")
        )
        assert verifier.check(op.encode(signed))[1] == "ok"
        service.close()
    finally:
        console_side.close()
        gcs_link.close()


def test_commands_kept_and_refused_are_journaled(tmp_path: Path) -> None:
    from gcs.ground_station import GroundStation
    from gcs.journal import GcsJournal

    journal = GcsJournal.create(tmp_path / "j.sqlite", GroundStationConfig())
    gcs_link, other = open_pair()
    try:
        service = OperatorService(gcs_link, key=KEY, journal=journal)
        station = GroundStation()
        good = op.sign(KEY, gcs_link.mission, "alice", 10**18, op.Command("status"))
        forged = op.sign(bytes(32), gcs_link.mission, "eve", 10**18 + 1, op.Command("pause", "all"))
        service._on_command("", op.encode(good))
        service._on_command("", op.encode(forged))
        service.after_step(now_s=3.0, station=station, send=lambda r, m: None)
        journal.commit()
        recs = [r.json() for r in journal.records() if r.kind == "operator"]
        assert [(r["operator"], r["status"], r["reason"]) for r in recs] == [
            ("alice", "ok", ""),
            ("eve", "refused", "forged"),
        ]
        service.close()
    finally:
        journal.close()
        other.close()
        gcs_link.close()


def test_a_resumed_service_holds_the_journaled_operator_decisions(tmp_path: Path) -> None:
    """Commands carried out by one service, journaled; a new service on the same journal
    (a GCS resumed after a kill) restores them: robot 0 still paused, the interactions
    counted, and the planners' held set (MissionControl.operator_controlled) given back at
    once. A journal with no operator record restores nothing."""
    from gcs.ground_station import GroundStation
    from gcs.journal import GcsJournal

    class Control:  # the planners' sets the service keeps equal to the operators' decisions
        def __init__(self) -> None:
            self.operator_controlled: set[int] = set()
            self.approved: set[int] = set()

    path = tmp_path / "j.sqlite"
    journal = GcsJournal.create(path, GroundStationConfig())
    gcs_link, other = open_pair()
    station = GroundStation()
    for msg in nodes_along(straight(3)):
        station.handle(0, msg, now_s=1.0)
    try:
        fresh = OperatorService(gcs_link, key=KEY, journal=journal, control=Control())
        assert not fresh.restore_operator()  # nothing journaled yet
        fresh.close()
        service = OperatorService(gcs_link, key=KEY, journal=journal)
        tele = Telemetry(2.0, (1.0, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.5, AutonomyMode.PAUSED, 3)
        journal.uplink(1, tele, 2.0)  # what robot 1 last said (the station's uplink)
        for seq, cmd in enumerate((op.Command("pause", "0"), op.Command("status"))):
            signed = op.sign(KEY, gcs_link.mission, "alice", 10**18 + seq, cmd)
            service._on_command("", op.encode(signed))
        service.after_step(now_s=3.0, station=station, send=lambda r, m: None)
        journal.commit()
        assert service.handler.control_of(0) == "paused"
        service.close()
        journal.abandon()  # killed: what was committed is what the next one reads
        journal = GcsJournal.open(path)
        control = Control()
        resumed = OperatorService(gcs_link, key=KEY, journal=journal, control=control)
        assert resumed.restore_operator()
        assert resumed.handler.control_of(0) == "paused"
        assert resumed.handler.paused == service.handler.paused
        assert resumed.handler.interactions == service.handler.interactions
        assert resumed.status(station).interactions == 1
        assert control.operator_controlled == {0}
        # the robots' last reports: status shows robot 1 as the killed GCS last heard it
        assert resumed.reports[1].telemetry == tele and resumed.reports[1].last_heard_s == 2.0
        (row,) = [r for r in resumed.status(station).robots if r.robot_id == 1]
        assert row.mode == "paused" and row.battery_frac == 0.5
        resumed.close()
    finally:
        journal.close()
        other.close()
        gcs_link.close()


def test_a_resumed_service_keeps_the_autonomy_mode_ledger(tmp_path: Path) -> None:
    """The time and distance per autonomy mode survive a GCS kill: the ledger journaled with
    the operator records every ``ledger_period_s`` and the telemetry journaled after it give
    a resumed service the killed one's ledger exactly; a damaged ledger record starts afresh."""
    from gcs.ground_station import GroundStation
    from gcs.journal import GcsJournal

    def tele(t: float, x: float, mode: AutonomyMode) -> Telemetry:
        return Telemetry(t, (x, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.9, mode, 3)

    path = tmp_path / "j.sqlite"
    journal = GcsJournal.create(path, GroundStationConfig())
    gcs_link, other = open_pair()
    station = GroundStation()
    try:
        service = OperatorService(gcs_link, key=KEY, journal=journal, ledger_period_s=10.0)
        service.after_step(now_s=0.5, station=station, send=lambda r, m: None)
        assert not [r for r in journal.records() if r.kind == "operator"]  # nothing heard
        heard = [
            (1, tele(1.0, 0.0, AutonomyMode.AUTONOMOUS)),
            (1, tele(3.0, 2.0, AutonomyMode.AUTONOMOUS)),
            (2, tele(3.0, 5.0, AutonomyMode.PAUSED)),
            (2, tele(4.0, 5.0, AutonomyMode.PAUSED)),
        ]
        for rid, msg in heard:
            journal.uplink(rid, msg, msg.time_s)
            service.observe(rid, msg, now_s=msg.time_s, station=station)
        service.after_step(now_s=4.0, station=station, send=lambda r, m: None)
        service.after_step(now_s=5.0, station=station, send=lambda r, m: None)  # not yet due
        later = [
            (1, tele(6.0, 3.0, AutonomyMode.TELEOPERATED)),
            (1, tele(7.0, 3.5, AutonomyMode.AUTONOMOUS)),
        ]
        for rid, msg in later:  # after the ledger record: from the journaled telemetry
            journal.uplink(rid, msg, msg.time_s)
            service.observe(rid, msg, now_s=msg.time_s, station=station)
        journal.commit()
        assert len([r for r in journal.records() if r.kind == "operator"]) == 1
        assert service.ledger.time_s == {"autonomous": 5.0, "paused": 1.0, "teleoperated": 1.0}
        service.close()
        journal.abandon()
        journal = GcsJournal.open(path)
        resumed = OperatorService(gcs_link, key=KEY, journal=journal)
        resumed.restore_operator()
        assert resumed.ledger.state() == service.ledger.state()
        assert resumed.metrics()["distance_m_autonomous"] == pytest.approx(3.0)
        resumed.close()
        journal.event("operator", 8.0, {"ledger": {"time_s": 3}, "handler": None})
        damaged = OperatorService(gcs_link, key=KEY, journal=journal)
        damaged.restore_operator()  # logged, not raised: the ledger starts afresh
        assert damaged.ledger.state() == ModeLedger().state()
        damaged.close()
    finally:
        journal.close()
        other.close()
        gcs_link.close()


def test_failed_views_are_journaled(tmp_path: Path) -> None:
    """Issue 17 (paper 7): what the operators could not see is in the journal. A picture that
    cannot be built (its map is no occupancy map) and a viewer that is not there (nothing
    listens on the port; found by the views' own thread) each become a ``view`` record with
    its kind, text and count at a following step; the GCS goes on, the next picture is built,
    and a journal with view records still rebuilds its station."""
    import socket

    from gcs.ground_station import GroundStation
    from gcs.journal import GcsJournal, rebuild_station

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])  # closed again: nothing listens there
    journal = GcsJournal.create(tmp_path / "j.sqlite", GroundStationConfig())
    gcs_link, other = open_pair()
    service = OperatorService(
        gcs_link, key=KEY, journal=journal, views=[f"connect 127.0.0.1:{port}"]
    )
    assert service.views is not None and service.builder is not None

    def views() -> list[dict[str, object]]:
        return [r.json() for r in journal.records() if r.kind == "view"]

    try:
        station = GroundStation()
        for node in nodes_along(straight(4)):
            station.handle(0, node, now_s=node.time_s)
        station.step(now_s=2.0)
        # the map layer is due in the first picture: a bad map fails the picture, not the GCS
        service.after_step(now_s=2.0, station=station, send=lambda r, m: None, occupancy="map")
        build = [v for v in views() if v["kind"] == "build"]
        assert len(build) == 1 and "expected an OccupancyMap" in str(build[0]["text"]), views()
        wait = threading.Event()
        for k in range(200):  # the unreachable viewer is found by the views' own thread
            if (
                any(v["kind"] == "connect" for v in views())
                and service.views.stats.published
                and service.builder.map_version
            ):
                break
            service.after_step(now_s=3.0 + k, station=station, send=lambda r, m: None)
            wait.wait(0.05)
        connect = [v for v in views() if v["kind"] == "connect"]
        assert len(connect) == 1 and "unreachable" in str(connect[0]["text"]), views()
        assert service.views.stats.published >= 1  # the pictures after the bad one were built
        assert service.builder.map_version >= 1  # with their map
        assert service.view_failures == sum(int(str(v["count"])) for v in views())
    finally:
        service.close()
        other.close()
        gcs_link.close()
    journal.commit()
    kinds = [v["kind"] for v in views()]
    assert kinds.count("build") == 1 and kinds.count("connect") >= 1, kinds
    _, summary = rebuild_station(journal)
    assert summary.records.get("view") == len(kinds)
    journal.close()
