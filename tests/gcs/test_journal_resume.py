"""The journal wired into the GCS: a ground side killed and rebuilt from its journal is the one
never killed; a run's journal replays to the same graph (issue 17 items 1 and 3)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.journal import GcsJournal
from gcs.mission_control import MissionControl, MissionControlConfig
from mission.assembly import GcsGround
from mission.mission_replay import compare_replay, compare_stations, main
from tests.gcs.test_journal import _mission

INF = math.inf


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
    never = _ground(None)
    _turns(never, items, 0, 45)

    config = GroundStationConfig(robots=(0, 1))
    path = tmp_path / "journal.sqlite"
    first = _ground(GcsJournal.create(path, config))
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
    assert main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "replay_pose_diff_max_m 0" in out and "replay_edges_equal 1" in out
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty")]) == 2
    assert "no journal there" in capsys.readouterr().err
    np.testing.assert_equal(ground.station.stats.rejected_total, 0)
