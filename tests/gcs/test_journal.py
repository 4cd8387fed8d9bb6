"""The GCS journal: a station rebuilt from it is the station that was never killed."""

from __future__ import annotations

import math
import sqlite3
from pathlib import Path

import numpy as np
import pytest

from compression import encode_grid, origin_cells_of
from gcs.graph.pose_graph import Provenance
from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.journal import GcsJournal, JournaledStation, JournalError, replay_journal
from protocol.messages import Detection, ObjectKind, PoseNode, TerrainGrid, covariance_to_upper
from protocol.se2 import compose, relative

DRIFT = np.diag([0.02**2, 0.02**2, 0.01**2])
INF = math.inf  # budgets by the progress clock only: a deterministic run


def _mission(seed: int) -> list[tuple[float, int, object]]:
    """Two robots drive out and back through one random world: ``(time_s, robot, message)``
    in arrival order (pose nodes, grids and a detection), for which the closer finds loops."""
    from gcs.loops.synthetic_scenes import random_world, scan_grid, scan_points

    rng = np.random.default_rng(seed)
    world = random_world(rng, size_m=40.0)
    out: list[tuple[float, int, object]] = []
    for robot, y in ((0, 0.5), (1, -2.0)):
        fwd = [(x, y, 0.0) for x in np.arange(-6.0, 6.01, 1.0)]
        back = [(x, y - 1.0, np.pi) for x in np.arange(6.0, -6.01, -1.0)]
        truth = np.array(fwd + back)
        odom = [truth[0]]
        for i in range(1, len(truth)):
            step = relative(truth[i - 1], truth[i])
            odom.append(compose(odom[-1], step + rng.multivariate_normal(np.zeros(3), DRIFT)))
        for i, pose in enumerate(odom):
            delta = (0.0, 0.0, 0.0) if i == 0 else tuple(relative(odom[i - 1], pose))
            cov = (0.0,) * 6 if i == 0 else covariance_to_upper(DRIFT)
            t = float(i) + 0.1 * robot
            out.append((t, robot, PoseNode(i, t, tuple(pose), delta, cov)))  # type: ignore[arg-type]
            grid, origin = scan_grid(scan_points(world, truth[i], rng=rng))
            data = encode_grid(grid, origin_cells=origin_cells_of(origin, 0.1))
            out.append((t, robot, TerrainGrid(i, 0.1, data)))
    out.append(
        (
            3.0,
            0,
            Detection(
                1, 3, 3.0, ObjectKind.STATIC_OOI, (2.0, 1.0), (0.01, 0.0, 0.01), 0.3, 0.6, 0.9
            ),
        )
    )
    out.sort(key=lambda item: item[0])
    return out


Event = tuple[float, int, object]  # (time_s, robot, message); robot -1 = a station step


def _schedule(items: list[tuple[float, int, object]]) -> list[Event]:
    """The GCS node's order: each message handed over as it comes, a step once a second."""
    out: list[Event] = []
    last_step = -1
    for t, robot, msg in items:
        out.append((t, robot, msg))
        if int(t) > last_step:
            last_step = int(t)
            out.append((float(last_step), -1, None))
    return out


def _feed(station: GroundStation | JournaledStation, events: list[Event]) -> None:
    """A journaled station commits after each batch (here: each event), before the link
    acknowledges, as the GCS node does."""
    for t, robot, msg in events:
        if robot < 0:
            station.step(now_s=t, budget_s=INF)
        else:
            station.handle(robot, msg, now_s=t)
        if isinstance(station, JournaledStation):
            station.commit()


def _state(
    gs: GroundStation,
) -> tuple[list[tuple[int, int | None, str, tuple[float, ...]]], np.ndarray]:
    edges = [
        (e.key_a, e.key_b, e.provenance.name, tuple(np.round(e.z, 12))) for e in gs.graph.edges()
    ]
    _, poses = gs.poses_in_map()
    return sorted(edges, key=repr), poses


def _config() -> GroundStationConfig:
    return GroundStationConfig(robots=(0, 1))


def test_a_station_resumed_from_its_journal_is_the_one_never_killed(tmp_path: Path) -> None:
    events = _schedule(_mission(seed=4))
    half = len(events) // 2

    never_killed = GroundStation(_config())
    _feed(never_killed, events)
    never_killed.add_start_hint(
        1, map_from_odom=(0.0, -2.5, 0.0), sigma_xy_m=1.0, sigma_yaw_rad=0.2
    )
    never_killed.step(now_s=40.0, budget_s=INF)
    assert len(never_killed.graph.edges(Provenance.LOOP_AUTO)) >= 3  # a run with closures

    path = tmp_path / "journal.sqlite"
    first = JournaledStation(GroundStation(_config()), GcsJournal.create(path, _config()))
    _feed(first, events[:half])
    # killed: the process dies without closing; only what was committed counts
    del first

    resumed, summary = JournaledStation.resume(path)
    assert summary.records["uplink"] + summary.records["step"] == half
    _feed(resumed, events[half:])
    resumed.add_start_hint(1, map_from_odom=(0.0, -2.5, 0.0), sigma_xy_m=1.0, sigma_yaw_rad=0.2)
    resumed.step(now_s=40.0, budget_s=INF)
    resumed.close()

    edges_a, poses_a = _state(never_killed)
    edges_b, poses_b = _state(resumed.station)
    assert edges_a == edges_b
    np.testing.assert_allclose(poses_b, poses_a, atol=1e-9)
    assert [h.hazard_id for h in resumed.station.hazards] == [
        h.hazard_id for h in never_killed.hazards
    ]
    assert resumed.station.stats.pose_nodes == never_killed.stats.pose_nodes

    # and a whole replay of the finished journal gives it once more (issue 17 item 3)
    again = GroundStation(_config())
    with_journal = GcsJournal.open(path)
    replay_journal(with_journal, again)
    with_journal.close()
    edges_c, poses_c = _state(again)
    assert edges_c == edges_a
    np.testing.assert_allclose(poses_c, poses_a, atol=1e-9)


def test_what_was_not_committed_is_all_a_crash_takes(tmp_path: Path) -> None:
    path = tmp_path / "j.sqlite"
    journal = GcsJournal.create(path, _config())
    journal.event("decision", 1.0, {"robot": 2, "task": "goto"})
    journal.commit()
    journal.event("decision", 2.0, {"robot": 3, "task": "goto"})  # not committed
    reader = GcsJournal.open(path)
    assert [r.json()["robot"] for r in reader.records()] == [2]
    reader.close()
    journal.commit()
    reader = GcsJournal.open(path)
    assert [r.json()["robot"] for r in reader.records()] == [2, 3]
    assert reader.counts() == {"decision": 2}
    reader.close()
    journal.close()


def test_operator_primitives_replay(tmp_path: Path) -> None:
    path = tmp_path / "j.sqlite"
    live = JournaledStation(GroundStation(_config()), GcsJournal.create(path, _config()))
    _feed(live, _schedule(_mission(seed=5)))
    live.add_start_hint(1, map_from_odom=(0.0, -2.5, 0.0), sigma_xy_m=1.0, sigma_yaw_rad=0.2)
    live.step(now_s=40.0, budget_s=INF)
    removed = live.rewind_closures(10.0)
    live.restart_loop_closer()
    live.step(now_s=41.0, budget_s=INF)
    live.close()
    assert removed > 0
    rebuilt, summary = JournaledStation.resume(path)
    assert {"start_hint", "rewind", "restart_closer"} <= set(summary.records)
    assert _state(rebuilt.station)[0] == _state(live.station)[0]
    rebuilt.close()


def test_bad_journals_are_refused_with_the_file_named(tmp_path: Path) -> None:
    path = tmp_path / "j.sqlite"
    GcsJournal.create(path, _config()).close()
    with pytest.raises(JournalError, match="a journal exists already"):
        GcsJournal.create(path, _config())
    with pytest.raises(JournalError, match="no journal there"):
        GcsJournal.open(tmp_path / "missing.sqlite")
    text = tmp_path / "notes.txt"
    text.write_text("hello, this is not a database\n" * 20)
    with pytest.raises(JournalError, match=r"notes.txt: not a journal"):
        GcsJournal.open(text)
    conn = sqlite3.connect(path)
    with conn:
        conn.execute("UPDATE meta SET value = '99' WHERE key = 'format'")
    conn.close()
    with pytest.raises(JournalError, match="journal format '99', this GCS reads 1 or 2"):
        GcsJournal.open(path)


def test_a_damaged_record_names_itself(tmp_path: Path) -> None:
    path = tmp_path / "j.sqlite"
    journal = GcsJournal.create(path, _config())
    journal.append("uplink", 2.5, b"\x93\x02\x00\xc1", robot_id=0)
    journal.uplink(0, "not a message", 3.0)  # refused by the station anyway: not journaled
    assert journal.unencodable == 1
    journal.close()
    reader = GcsJournal.open(path)
    with pytest.raises(JournalError, match=r"record 1 \(uplink at t=2.500 s\)"):
        replay_journal(reader, GroundStation(_config()))
    reader.close()


def test_an_idle_journal_commits_nothing(tmp_path: Path) -> None:
    """The GCS commits every spin (20 a second): only what was appended is written."""
    journal = GcsJournal.create(tmp_path / "j.sqlite", _config(), sync_period_s=0.0)
    assert journal.commit() is False  # nothing appended since it was created
    journal.event("operator", 1.0, {"command": "status"})
    assert journal.commit() is True
    wal = tmp_path / "j.sqlite-wal"
    size = wal.stat().st_size
    for _ in range(50):
        assert journal.commit() is False
    assert wal.stat().st_size == size  # no fsync, no WAL frame written while idle
    journal.close()


def test_an_operators_hazard_edit_is_journaled_and_replays(tmp_path: Path) -> None:
    from gcs.operator.grammar import parse_line
    from gcs.operator.handler import CommandHandler, OperatorContext
    from protocol.operator import OPERATOR_TASK_IDS_FROM

    path = tmp_path / "j.sqlite"
    live = JournaledStation(GroundStation(_config()), GcsJournal.create(path, _config()))
    _feed(live, _schedule(_mission(seed=5)))
    (hazard,) = live.station.hazards
    assert hazard.kind == ObjectKind.STATIC_OOI and hazard.radius_m > 0
    handler = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 1)
    ctx = OperatorContext(station=live, now_s=30.0, reports={})  # type: ignore[arg-type]
    out = handler.handle(parse_line(f"reclassify {hazard.hazard_id} civilian"), ctx)
    assert out.status == "ok", out.text
    assert live.station.hazards[0].kind == ObjectKind.CIVILIAN
    live.step(now_s=31.0, budget_s=INF)
    live.close()
    rebuilt, summary = JournaledStation.resume(path)
    assert summary.records.get("hazard_edit") == 1
    assert rebuilt.station.hazards == live.station.hazards  # the edit survives the resume
    rebuilt.close()
    fresh = GroundStation(_config())
    journal = GcsJournal.open(path)
    replay_journal(journal, fresh)
    journal.close()
    assert fresh.hazards[0].kind == ObjectKind.CIVILIAN
