"""The journal wired into the GCS: a ground side killed and rebuilt from its journal is the one
never killed; a run's journal replays to the same graph (issue 17 items 1 and 3)."""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.journal import (
    GcsJournal,
    JournalError,
    load_station,
    rebuild_station,
    resume_control,
    save_station,
)
from gcs.mission_control import MissionControl, MissionControlConfig
from mission.assembly import GcsGround
from mission.mission_replay import compare_replay, compare_stations, main
from tests.gcs.test_journal import _mission

INF = math.inf


def _journal(path: Path, checkpoint_period_s: float = 30.0) -> GcsJournal:
    config = GroundStationConfig(robots=(0, 1))
    return GcsJournal.create(path, config, checkpoint_period_s=checkpoint_period_s)


def _ground(journal: GcsJournal | None) -> GcsGround:
    config = GroundStationConfig(robots=(0, 1))
    control = MissionControl(GroundStation(config), MissionControlConfig(plan_period_s=4.0))
    return GcsGround(control, lockstep=True, step_period_s=1.0, journal=journal)


def _turns(ground: GcsGround, items: list[tuple[float, int, object]], t_from: int, t_to: int):  # type: ignore[no-untyped-def]
    """The lockstep order: each second's messages arrive, then the ground's turn."""
    tasks = []
    for t in range(t_from, t_to):
        for when, robot, msg in items:
            if t - 1 < when <= t:
                ground.on_message(robot, msg)
        tasks += [m for _, m in ground.turn(float(t)) if hasattr(m, "task_id")]
    return tasks


def test_a_gcs_killed_and_rebuilt_from_its_journal_is_the_one_never_killed(tmp_path: Path) -> None:
    items = _mission(seed=4)
    # never killed, journaled alike: the same checkpoints (each re-seeds iSAM2) at 0 and 30 s
    never = _ground(_journal(tmp_path / "never.sqlite"))
    _turns(never, items, 0, 45)

    path = tmp_path / "journal.sqlite"
    first = _ground(_journal(path))
    first_tasks = _turns(first, items, 0, 20)
    assert first_tasks, "the planners sent tasks before the kill"
    resumed, rebuild_s = first.crash_and_resume()
    assert rebuild_s < 5.0
    # the rebuilt station is the killed one, edge for edge and pose for pose
    at_kill = compare_stations(first.station, resumed.station)
    assert at_kill.nodes_equal and at_kill.edges_equal and at_kill.pose_diff_max_m <= 1e-9
    # the allocator starts past every task id it used
    assert resumed.control.allocator._next_id > max(t.task_id for t in first_tasks)
    assert sum(resumed.control.tasks_sent.values()) == len(first_tasks)
    _turns(resumed, items, 20, 45)

    end = compare_stations(never.station, resumed.station)
    assert end.nodes_equal and end.edges_equal, end
    assert end.pose_diff_max_m <= 1e-9
    assert len(never.station.graph.edges()) == end.edges > 30
    # a node the robot sends again after the restart is a duplicate, not a second node
    nodes = resumed.station.stats.pose_nodes
    again = next(m for _, r, m in items if r == 0 and type(m).__name__ == "PoseNode")
    resumed.on_message(0, again)
    resumed.turn(46.0)
    assert resumed.station.stats.pose_nodes == nodes
    assert resumed.station.stats.duplicates == 1
    assert resumed.journal is not None
    resumed.journal.close()

    # replay of the whole journal (issue 17 item 3): same graph as the live one
    diff = compare_replay(path, resumed.station)
    assert diff.ok(1e-3) and diff.pose_diff_max_m <= 1e-9


def test_magic_replay_of_a_run_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = GroundStationConfig(robots=(0, 1))
    ground = _ground(GcsJournal.create(tmp_path / "journal.sqlite", config))
    _turns(ground, _mission(seed=5), 0, 30)
    assert ground.journal is not None
    ground.journal.close()
    from mission.replay import main as magic_replay

    assert magic_replay([str(tmp_path)]) == 0  # magic replay RUN_DIR
    out = capsys.readouterr().out
    assert "replay_pose_diff_max_m 0" in out and "replay_edges_equal 1" in out
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty")]) == 2
    assert "no journal there" in capsys.readouterr().err
    np.testing.assert_equal(ground.station.stats.rejected_total, 0)


def test_magic_gcs_killed_and_resumed_continues_the_robots_radio_streams(tmp_path: Path) -> None:
    """``magic gcs --resume`` over real zenoh: the robot keeps its link (and its sequence
    numbers); the new GCS takes the next nodes, acknowledges them (the robot's queue drains),
    sends it HazardUpdates it accepts, and a node the robot sends again is a duplicate."""
    from gcs.journal import resume_control
    from gcs.node import GcsProcess
    from protocol.clock import ManualClock
    from protocol.link import Link, LinkConfig
    from protocol.loopback import free_loopback_port, unique_mission
    from protocol.messages import HazardUpdate
    from tests.gcs.test_ground_station import nodes_along, straight

    clock = ManualClock()
    mission = unique_mission("resume")
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    robot_link = Link(
        LinkConfig(listen=(endpoint,), pump_period_s=0.0), mission=mission, clock=clock
    )
    gcs_cfg = LinkConfig(listen=(), connect=(endpoint,), pump_period_s=0.0)
    updates: list[float] = []
    robot = robot_link.robot_endpoint(
        0, on_message=lambda m: updates.append(m.time_s) if isinstance(m, HazardUpdate) else None
    )
    nodes = nodes_along(straight(12))
    config = GroundStationConfig(robots=(0,))
    path = tmp_path / "journal.sqlite"
    links = [Link(gcs_cfg, mission=mission, clock=clock)]
    try:
        proc = GcsProcess(links[0], clock, config, journal=GcsJournal.create(path, config))

        def spin(until) -> None:  # type: ignore[no-untyped-def]
            for _ in range(400):
                if until():
                    return
                clock.set(clock.now() + 0.25)
                robot_link.pump()
                proc.spin_once(timeout_s=0.02)
            raise AssertionError(f"timed out: {proc.status_line()}, {robot.channel.pending()}")

        assert proc.radio.wait_for_robot(0, 10.0) and robot.wait_for_gcs(10.0)
        for node in nodes[:6]:
            robot.send(node)
        s1 = proc.station.stats
        spin(lambda: s1.pose_nodes == 6 and robot.channel.pending() == 0 and updates)
        # killed: nothing closed, nothing more committed; its link goes with the process
        assert proc.journal is not None
        proc.journal.abandon()
        proc.close()
        links[0].close()
        killed_s = clock.now()

        links.append(Link(gcs_cfg, mission=mission, clock=clock))
        proc = GcsProcess(links[1], clock, resumed=resume_control(path))
        assert proc.link_state["robots"] == 1 and proc.station.stats.pose_nodes == 6
        assert proc.radio.wait_for_robot(0, 10.0)
        for node in nodes[6:]:
            robot.send(node)
        robot.send(nodes[3])  # the robot sends an old node again
        s2 = proc.station.stats
        spin(
            lambda: (
                s2.pose_nodes == 12
                and s2.duplicates == 1
                and robot.channel.pending() == 0
                and updates[-1] > killed_s
            )
        )
        keys, _ = proc.station.poses_in_map()
        assert len(set(keys.tolist())) == 12 and s2.rejected_total == 0
        assert robot.channel.stats.duplicates_dropped == 0  # nothing delivered twice to it
        proc.close()
    finally:
        for link in links:
            link.close()
        robot_link.close()


def test_a_gcs_resumed_from_a_checkpoint_is_the_one_never_killed(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Checkpoints bound a restart (only the records after the latest replay) and change
    nothing: resumed from one, from scratch, or never killed, the station is the same."""
    items = _mission(seed=4)
    never = _ground(_journal(tmp_path / "never.sqlite", checkpoint_period_s=10.0))
    _turns(never, items, 0, 45)
    unjournaled = _ground(None)  # no checkpoints: iSAM2 never re-seeded
    _turns(unjournaled, items, 0, 45)

    path = tmp_path / "journal.sqlite"
    first = _ground(_journal(path, checkpoint_period_s=10.0))
    _turns(first, items, 0, 25)
    assert first.journal is not None
    first.journal.commit()
    records_at_kill = first.journal.last_seq
    scratch = tmp_path / "scratch.sqlite"  # the same journal, to resume without checkpoint
    with sqlite3.connect(scratch) as copy, sqlite3.connect(path) as src:
        src.backup(copy)
    resumed, _ = first.crash_and_resume()  # from the checkpoint at 20 s

    reader = GcsJournal.open(path)
    saved = reader.latest_checkpoint()
    assert saved is not None and saved[1] == 20.0  # the latest only (0, 10 and 20 s taken)
    assert reader.counts()["checkpoint"] == 3
    station, summary = rebuild_station(reader)
    reader.close()
    assert summary.checkpoint_seq == saved[0] and summary.last_seq == records_at_kill
    tail = records_at_kill - saved[0]
    assert 0 < tail < records_at_kill / 3, "only the records after the checkpoint replay"
    assert compare_stations(first.station, station).pose_diff_max_m == 0.0
    from_scratch = resume_control(scratch, first.control.config, from_checkpoint=False)
    assert from_scratch.summary.checkpoint_seq == 0
    for other in (resumed.station, from_scratch.control.station):
        at_kill = compare_stations(first.station, other)
        assert at_kill.nodes_equal and at_kill.edges_equal and at_kill.pose_diff_max_m == 0.0

    _turns(resumed, items, 25, 45)
    end = compare_stations(never.station, resumed.station)
    assert end.nodes_equal and end.edges_equal and end.pose_diff_max_m <= 1e-9, end
    # against a station without checkpoints: iSAM2's incremental state is path dependent, so
    # re-seeding it at a checkpoint moves poses a little (1.3 mm here) and the closer may
    # take a different closure; the same nodes, the map within a centimetre
    plain = compare_stations(unjournaled.station, resumed.station)
    assert plain.nodes_equal and plain.pose_diff_max_m <= 0.01, plain
    assert resumed.journal is not None
    resumed.journal.close()
    # the whole journal replayed (checkpoints as barriers) is the live station too
    assert compare_replay(path, resumed.station).pose_diff_max_m <= 1e-9

    # a damaged checkpoint is refused, logged, and the whole journal replays instead
    with sqlite3.connect(path) as conn:
        (state,) = conn.execute("SELECT state FROM checkpoints").fetchone()
        damaged = bytes(state[:100]) + bytes([state[100] ^ 0x01]) + bytes(state[101:])
        conn.execute("UPDATE checkpoints SET state = ?", (damaged,))
    reader = GcsJournal.open(path)
    with pytest.raises(JournalError, match=r"checkpoint at record \d+ \(t=40.000 s\): SHA-256"):
        reader.latest_checkpoint()
    with caplog.at_level("WARNING", logger="gcs.journal"):
        again, summary = rebuild_station(reader)
    reader.close()
    assert "replaying the whole journal instead" in caplog.text
    assert summary.checkpoint_seq == 0
    assert compare_stations(resumed.station, again).pose_diff_max_m <= 1e-9


def test_a_checkpoint_loads_only_what_a_station_is_made_of() -> None:
    """The checkpoint loader runs no code a damaged or planted pickle names."""
    import os
    import pickle

    with pytest.raises(JournalError, match=r"names posix.system"):
        load_station(pickle.dumps(os.system))
    with pytest.raises(JournalError, match="not a saved station"):
        load_station(pickle.dumps({"graph": 1}))
    with pytest.raises(JournalError, match="not a saved station"):
        load_station(b"\x80\x05garbage")
    station = GroundStation(GroundStationConfig(robots=(0, 1)))
    again = load_station(save_station(station))
    assert again.config == station.config and len(again.graph.nodes()) == 0


def test_a_checkpoint_loads_on_a_python_that_pickles_enums_by_name(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Python 3.11.0-3.11.4 pickle an enum member as ``getattr(cls, name)``, which the loader
    refuses: the checkpoint saves members by value on every Python (a fresh clone's system
    3.11.2 lost every checkpoint to this)."""
    from gcs.graph.pose_graph import Provenance

    def by_name(self: Provenance, proto: int) -> object:
        return getattr, (type(self), self.name)

    monkeypatch.setattr(Provenance, "__reduce_ex__", by_name)
    ground = _ground(None)
    _turns(ground, _mission(seed=4), 0, 8)
    assert any(e.provenance is Provenance.ODOMETRY for e in ground.station.graph.edges())
    state = save_station(ground.station)
    assert b"getattr" not in state
    again = load_station(state)
    assert compare_stations(ground.station, again).pose_diff_max_m == 0.0


def test_a_resume_reads_only_what_follows_the_checkpoint_and_the_link_ledger(
    tmp_path: Path,
) -> None:
    """Restart time stays flat in the journal's length: the tasks' bookkeeping comes with the
    checkpoint and the radio's state with the newest ``link`` record; only what follows them
    is read (the records before them are deleted here, and the resume is unchanged)."""
    from gcs.node import LinkLedger
    from protocol.messages import GoToTask

    items = _mission(seed=4)
    path = tmp_path / "journal.sqlite"
    first = _ground(_journal(path, checkpoint_period_s=10.0))
    _turns(first, items, 0, 25)
    assert first.journal is not None
    journal = first.journal
    # the radio's side, as the GCS process journals it: every uplink message and reliable
    # downlink task with its record, and the ledger in a link record now and then
    ledger = LinkLedger()
    for k, (_, robot, msg) in enumerate(items):
        seq = journal.uplink(robot, msg, 25.0)
        assert seq is not None
        first.control.handle(robot, msg, now_s=25.0)  # again: duplicates, as a replay sees
        ledger.uplink(robot, msg, seq)
        if k % 7 == 0:
            task = GoToTask(900 + k, 25.0, [(1.0, 2.0)])
            ledger.downlink(robot, "task", journal.downlink(robot, task, k + 1, 25.0) or 0)
        if k == len(items) - 5:
            journal.event("link", 25.0, {"robots": {}, "broadcast": {}, "ledger": ledger.to_json()})
    journal.commit()
    sent = dict(first.control.tasks_sent)
    assert sent and journal.tasks_sent == sent
    saved = journal.latest_checkpoint()
    assert saved is not None and saved[1] == 20.0
    whole = LinkLedger.from_journal(journal)
    assert whole.records_read == 4  # the uplink records after the ledger, not the journal
    assert (whole.up, whole.node_seqs, whole.grid_seq, whole.down_seqs) == (
        ledger.up,
        ledger.node_seqs,
        ledger.grid_seq,
        ledger.down_seqs,
    )
    journal.abandon()
    first.journal = None

    with sqlite3.connect(path) as conn:  # what precedes the checkpoint is never read
        link_seq = conn.execute("SELECT MAX(seq) FROM records WHERE kind = 'link'").fetchone()[0]
        keep = {link_seq} | {s for v in ledger.node_seqs.values() for s in v}
        keep |= set(ledger.grid_seq.values()) | {s for v in ledger.down_seqs.values() for s in v}
        gone = conn.execute(
            "DELETE FROM records WHERE seq < ? AND kind IN ('decision', 'uplink', 'downlink') "
            f"AND seq NOT IN ({','.join(map(str, keep))})",
            (saved[0],),
        ).rowcount
    assert gone > 50
    resumed = resume_control(path, first.control.config)
    assert dict(resumed.control.tasks_sent) == sent
    assert resumed.control.allocator._next_id > journal.last_task_id > 0
    at_kill = compare_stations(first.station, resumed.control.station)
    assert at_kill.nodes_equal and at_kill.edges_equal and at_kill.pose_diff_max_m == 0.0
    again = LinkLedger.from_journal(resumed.journal)
    assert again.up == ledger.up and again.records_read == 4
    resumed.journal.close()


def test_a_checkpoint_saved_by_other_code_is_not_loaded(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A checkpoint pickles the station's objects: one saved by another version of the code
    (whose classes may lack attributes this one has) is refused, and the journal replays."""
    import json

    from gcs.journal import CODE_FINGERPRINT

    path = tmp_path / "journal.sqlite"
    ground = _ground(_journal(path, checkpoint_period_s=5.0))
    _turns(ground, _mission(seed=4), 0, 8)
    assert ground.journal is not None
    ground.journal.close()
    reader = GcsJournal.open(path)
    seq = reader.latest_checkpoint()[0]  # type: ignore[index]
    body = json.loads(reader.record(seq).body)  # type: ignore[union-attr]
    assert body["code"] == CODE_FINGERPRINT
    reader.close()
    with sqlite3.connect(path) as conn:
        body["code"] = "0123456789abcdef"
        conn.execute("UPDATE records SET body = ? WHERE seq = ?", (json.dumps(body).encode(), seq))
    reader = GcsJournal.open(path)
    with pytest.raises(JournalError, match="saved by other code"):
        reader.latest_checkpoint()
    with caplog.at_level("WARNING", logger="gcs.journal"):
        station, summary = rebuild_station(reader)
    reader.close()
    assert summary.checkpoint_seq == 0 and "replaying the whole journal" in caplog.text
    assert compare_stations(ground.station, station).pose_diff_max_m <= 1e-9


def test_a_resumed_gcs_gives_its_allocator_back_the_robots_assignments(tmp_path: Path) -> None:
    """The planners' assignments survive a kill (``assignments`` records): the resumed
    allocator knows which task each robot carries out, its goal, purpose and deadline, and
    its first plan does not replace them (a fresh allocator gave every robot a new goal)."""
    items = _mission(seed=4)
    path = tmp_path / "journal.sqlite"
    first = _ground(_journal(path))
    first_tasks = _turns(first, items, 0, 20)
    assert first_tasks
    before = dict(first.control.allocator.assignments)
    assert before, "robots had tasks at the kill"
    resumed, _ = first.crash_and_resume()
    after = resumed.control.allocator.assignments
    assert sorted(after) == sorted(before)
    for rid, a in before.items():
        b = after[rid]
        assert (b.task_id, b.purpose, b.issued_s, b.hazard_id) == (
            a.task_id,
            a.purpose,
            a.issued_s,
            a.hazard_id,
        )
        assert b.timeout_s == a.timeout_s
        if a.goal_in_map is None:
            assert b.goal_in_map is None
        else:
            assert b.goal_in_map is not None
            assert np.allclose(b.goal_in_map, a.goal_in_map, atol=0, rtol=0)
        if a.route_in_map is not None:
            assert b.route_in_map is not None
            assert np.array_equal(np.asarray(b.route_in_map), np.asarray(a.route_in_map))
    # its first plan keeps the robots' live tasks: none is replaced at once
    again = [m for _, m in resumed.turn(20.0) if hasattr(m, "task_id")]
    replaced = {m.task_id for m in again} & {a.task_id for a in before.values()}
    assert not replaced
    now = resumed.control.allocator.assignments
    kept = [rid for rid, a in before.items() if rid in now and now[rid].task_id == a.task_id]
    assert kept, "the robots' tasks go on"
    assert resumed.journal is not None
    resumed.journal.close()


def test_a_standby_that_followed_the_journal_takes_over_as_a_rebuild_would(
    tmp_path: Path,
) -> None:
    """A warm standby's :class:`JournalFollower` reads the journal while its writer runs
    (between the writer's commits, on its own connection; a checkpoint passes meanwhile),
    never sees what the writer had not committed when it died, and takes over with the
    station, task bookkeeping and assignments :func:`resume_control` rebuilds from the same
    journal; the run goes on to the station of a GCS never killed. Taking over applies only
    what the writer committed after the follower's last read."""
    from gcs.journal import JournalFollower

    items = _mission(seed=4)
    never = _ground(_journal(tmp_path / "never.sqlite", checkpoint_period_s=10.0))
    _turns(never, items, 0, 45)

    path = tmp_path / "journal.sqlite"
    first = _ground(_journal(path, checkpoint_period_s=10.0))
    _turns(first, items, 0, 4)
    follower = JournalFollower(path)
    assert follower.seq == first.journal.last_seq  # type: ignore[union-attr]
    for t in range(4, 24, 3):
        _turns(first, items, t, t + 3)
        assert follower.catch_up() > 0
    _turns(first, items, 24, 25)  # committed after the follower's last read
    assert first.journal is not None
    committed = first.journal.last_seq
    first.journal.event("decision", 25.0, {"task": "GoToTask", "task_id": 99}, robot_id=0)
    first.journal.abandon()  # killed: the record above was never committed
    scratch = tmp_path / "scratch.sqlite"  # the journal as the kill left it, to rebuild
    with sqlite3.connect(scratch) as copy, sqlite3.connect(path) as src:
        src.backup(copy)

    took = follower.take_over(first.control.config)
    assert took.summary.last_seq == committed == took.journal.last_seq
    assert 0 < sum(took.summary.records.values()) < committed / 10  # the last records only
    rebuilt = resume_control(scratch, first.control.config)
    for other in (first.control, rebuilt.control):
        at_kill = compare_stations(other.station, took.control.station)
        assert at_kill.nodes_equal and at_kill.edges_equal and at_kill.pose_diff_max_m == 0.0
    assert took.control.tasks_sent == rebuilt.control.tasks_sent == first.control.tasks_sent
    assert took.control.allocator._next_id == rebuilt.control.allocator._next_id
    assert took.journal.assignments == rebuilt.journal.assignments
    # its caches are a replay's from the first record, whenever it started (it loads no
    # checkpoint): the rasterizer never drew (a loaded checkpoint's had: it reuses submaps
    # drawn within a pose tolerance), so the planners' next map is the same whatever the
    # follower's start, and is a full replay's cell for cell
    scratch_control = resume_control(scratch, first.control.config, from_checkpoint=False)
    replayed = scratch_control.control.station
    for a, b in (
        (took.control.station.rasterizer, replayed.rasterizer),
        (took.control.station.near_rasterizer, replayed.near_rasterizer),
    ):
        if a is None:
            assert b is None
            continue
        drawn = [[(m.nodes, m.row0, m.col0, m.codes.tobytes()) for m in r._submaps] for r in (a, b)]
        assert drawn[0] == drawn[1] and not any(codes for *_, codes in drawn[0])
        poses = replayed.poses_in_map()
        assert np.array_equal(a.rasterize(poses).values, b.rasterize(poses).values)
    scratch_control.journal.close()
    from gcs.journal import latest_heard

    heard = latest_heard(rebuilt.journal)  # what the robots last said, as a rebuild reads it
    assert heard and {r: h.time_s for r, h in follower.heard.items()} == {
        r: h.time_s for r, h in heard.items()
    }
    assert all(follower.heard[r].telemetry == h.telemetry for r, h in heard.items())
    rebuilt.journal.close()

    ground = GcsGround(took.control, lockstep=True, step_period_s=1.0, journal=took.journal)
    _turns(ground, items, 25, 45)
    end = compare_stations(never.station, ground.station)
    assert end.nodes_equal and end.edges_equal and end.pose_diff_max_m <= 1e-9, end
    took.journal.close()
    assert compare_replay(path, ground.station).pose_diff_max_m <= 1e-9


def test_a_resumed_gcs_keeps_the_neutralizations_failed_views(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The allocator's failed views (a neutralization that failed for want of line of sight:
    the OOI and where the disruptor stood, so the next dispatch goes to another side) go into
    the ``assignments`` record when they change and come back to a resumed GCS's allocator,
    from a rebuild and from a warm standby alike; a damaged row is left out, named in the log,
    and the resume goes on."""
    import json

    from gcs.journal import JournalFollower

    items = _mission(seed=4)
    path = tmp_path / "journal.sqlite"
    first = _ground(_journal(path))
    follower = JournalFollower(path)
    _turns(first, items, 0, 10)
    alloc = first.control.allocator
    # what the allocator records when a neutralization fails for want of line of sight
    alloc.restore_failed_views([(12.5, -3.25, 9.0, -1.0)])
    _turns(first, items, 10, 12)
    assert first.journal is not None
    rec = first.journal.latest_record("assignments")
    assert rec is not None and rec.json()["failed_views"] == [[12.5, -3.25, 9.0, -1.0]]
    alloc.restore_failed_views([*alloc.failed_views, (4.0, 4.0, 1.0, 1.0)])
    _turns(first, items, 12, 14)
    views = alloc.failed_views
    scratch = tmp_path / "scratch.sqlite"
    with sqlite3.connect(scratch) as copy, sqlite3.connect(path) as src:
        src.backup(copy)
    resumed, _ = first.crash_and_resume()
    assert resumed.control.allocator.failed_views == views
    follower.catch_up()
    took = follower.take_over(first.control.config)
    assert took.control.allocator.failed_views == views
    took.journal.close()
    # a damaged row in the newest assignments record: left out, the rest restored
    with sqlite3.connect(scratch) as db:
        seq, body = db.execute(
            "SELECT seq, body FROM records WHERE kind = 'assignments' ORDER BY seq DESC LIMIT 1"
        ).fetchone()
        fields = json.loads(body)
        fields["failed_views"][0] = [12.5, "x", 9.0]
        db.execute("UPDATE records SET body = ? WHERE seq = ?", (json.dumps(fields).encode(), seq))
    with caplog.at_level("ERROR", logger="gcs.journal"):
        damaged = resume_control(scratch, first.control.config)
    assert damaged.control.allocator.failed_views == views[1:]
    assert "failed_views[0]" in caplog.text
    damaged.journal.close()
    assert resumed.journal is not None
    resumed.journal.close()
