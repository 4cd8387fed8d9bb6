"""``magic run`` end to end: simulator, robot nodes and the ground side over real zenoh."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path

import msgspec
import pytest

from mission.cli import main
from mission.run import RunConfig, fields_differing, run_mission

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow


def test_team_drives_scripted_goals_over_the_radio_link() -> None:
    """``magic run --scripted`` (4 robots, 2 goals each, 100 s): the comparison mode (the
    mission itself: tests/mission/test_mission.py)."""
    config = RunConfig(scripted=True, duration_s=100.0, goals_per_robot=2)
    report = run_mission(config)
    assert report.mission_s == pytest.approx(config.duration_s)
    assert len(report.robots) == 4
    summary = report.summary()
    print("magic run:", summary)  # the numbers, for the record (pytest -s)
    for p in report.robots.values():
        assert p.alive
        # every robot makes real progress on its own (at least one goal; the team's share
        # below): on a fresh clone's first CI run this run took another way (robot 1: one
        # deadlock, 1 of 2 goals, the team 7 of 8) where a run alone gives 8 of 8, the same
        # code and seed: a difference in the test process's history, not yet found
        assert p.goals_succeeded >= 1
        assert p.distance_m > 10.0
        assert p.pose_nodes >= 3 and p.terrain_grids == p.pose_nodes  # arrived over the link
        assert p.uplink_bytes > 0
    # most goals are reached (measured: 8 of 8 for seed 0; 4 goals in 180 s: 16 of 16 for
    # seeds 0, 1 and 3, 15 of 16 for seed 2)
    assert summary["goals_sent"] == 4 * config.goals_per_robot
    assert summary["goals_succeeded"] >= 0.75 * summary["goals_sent"]
    # safety: nothing detonated, nobody entered a hazard's keep-out disk (truth)
    assert not report.events
    assert summary["closest_static_m"] >= 2.5 + 0.75
    assert summary["closest_hostile_m"] >= 5.0 + 0.75


def test_run_command_reports_a_bad_config_file(tmp_path, capsys) -> None:
    bad = tmp_path / "run.yaml"
    bad.write_text("duration_s: soon\n")
    assert main(["run", "--config", str(bad), "--quiet"]) == 2
    assert "duration_s: expected float, got str" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "problem"),
    [
        (["--world", "nosuch"], "nosuch: no such file, nor a world config under"),
        (["--world", "/tmp/no/such/world.yaml"], "(shipped: magic_phase, "),
        (["--duration", "-5"], "duration_s must be > 0 mission-seconds, got -5.0"),
        (["--duration", "nan"], "duration_s must be > 0 mission-seconds, got nan"),
        (["--workers", "0"], "workers must be >= 1 processes, got 0"),
        (["--remote-robots", "2-1", "--mission", "m"], "--remote-robots: robot ids '2-1':"),
        (["--remote-robots", "3"], "--remote-robots 3: give --mission NAME too"),
        (
            ["--remote-robots", "9", "--mission", "m"],
            "remote robots [9]: world world/small.yaml has robots 0-3 only",
        ),
        (["--listen", "tcp/0.0.0.0:0"], "--listen tcp/0.0.0.0:0: the robot workers connect"),
        (["--workers", "2", "--realtime"], "realtime and robot_processes cannot be combined"),
        (["--link-config", "/no/such.yaml"], "/no/such.yaml"),
    ],
)
def test_run_command_refuses_bad_arguments_before_running(argv, problem, capsys) -> None:
    assert main(["run", *argv, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert problem in err.replace("\n", " ") and "Traceback" not in err


def test_run_command_reports_a_bad_world_file(tmp_path, capsys) -> None:
    bad = tmp_path / "world.yaml"
    bad.write_text("sizee: [10, 10]\n")
    assert main(["run", "--world", str(bad), "--duration", "1", "--quiet"]) == 2
    assert f"{bad}: sizee: unknown key" in capsys.readouterr().err.replace("\n", "")


def _short(seed: int = 0) -> RunConfig:
    return RunConfig(duration_s=12.0, seed=seed)


def test_same_seed_gives_the_same_mission_bit_for_bit_even_under_load() -> None:
    """DESIGN section 4: a run is fixed by its world, team, seed, duration and configuration,
    whatever the load; another seed is another mission."""
    first = run_mission(_short()).fields()
    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        again = run_mission(_short()).fields()
    finally:
        busy.kill()
        busy.wait()
    assert len(first) > 60  # team figures, every robot's progress and final pose
    assert fields_differing(first, again) == []
    other = run_mission(_short(seed=1)).fields()
    differing = fields_differing(first, other)
    assert any(name.endswith(".final_x_m") for name in differing), differing


def test_robots_in_their_own_processes_give_the_same_mission() -> None:
    """``magic run --robot-processes --workers 2 --listen E --mission M``: the robot nodes in
    two ``magic robot --lockstep`` worker processes, the same figures bit for bit as in one
    process (node counters and uplink bytes included)."""
    from protocol.link import LinkConfig
    from protocol.loopback import free_loopback_port, unique_mission

    config = RunConfig(duration_s=8.0, seed=2)
    in_process = run_mission(config).fields()
    report = run_mission(
        msgspec.structs.replace(config, robot_processes=True, workers=2),
        link=LinkConfig(listen=(f"tcp/127.0.0.1:{free_loopback_port()}",)),
        mission_name=unique_mission("run-workers"),
    )
    spread = report.fields()
    assert fields_differing(in_process, spread) == []
    assert report.processes == "robot nodes in 2 worker processes (0,1; 2,3)"
    assert spread["robot0.pose_nodes"] > 0 and spread["robot0.uplink_bytes"] > 0


def test_fields_differing_compares_floats_bit_for_bit() -> None:
    assert fields_differing({"a": 0.1 + 0.2}, {"a": 0.3}) == ["a"]
    assert fields_differing({"a": 0.0}, {"a": -0.0}) == ["a"]
    assert fields_differing({"a": float("nan"), "b": "x"}, {"a": float("nan"), "b": "x"}) == []
    assert fields_differing({"a": 1.0}, {"b": 1.0}) == ["a", "b"]


@pytest.mark.parametrize(
    ("sig", "status", "name"),
    [(signal.SIGINT, 130, "SIGINT"), (signal.SIGTERM, 143, "SIGTERM")],
)
def test_a_signal_mid_run_ends_it_with_the_summary_so_far(sig, status, name, tmp_path) -> None:
    run_dir = tmp_path / "run"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mission.cli", "run", "--duration", "600", "--out", str(run_dir)],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    watchdog = threading.Timer(180.0, proc.kill)  # a hung run fails the test, not the suite
    watchdog.start()
    try:
        assert proc.stderr is not None
        seen = []
        for line in proc.stderr:  # progress lines (stderr is a pipe)
            seen.append(line)
            if "mission-s" in line:
                break
        assert any("mission-s" in line for line in seen), seen
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=120)
    finally:
        watchdog.cancel()
        proc.kill()
    err = "".join(seen) + err
    assert proc.returncode == status, err
    assert "Traceback" not in err
    assert f"magic run: stopped by {name} at " in err
    lines = out.splitlines()
    assert any("tasks ok/sent" in line for line in lines)  # the table of the run so far
    # a pipe: every summary line whole, none wrapped mid-phrase
    assert any(line.startswith("teammate deadlocks broken: ") for line in lines), out
    assert any(line.startswith("mode: deterministic lockstep") for line in lines), out
    # the report is written from what ran
    assert (run_dir / "report.json").is_file() and (run_dir / "report.md").is_file()
    # the library's log went to the run directory, counted in the summary
    assert (run_dir / "run.log").is_file()
    assert any(line.startswith("log: ") and "run.log" in line for line in lines), out
    assert any(line.startswith("report: explored ") for line in lines), out


def test_library_logging_goes_to_the_run_log_not_to_stderr(tmp_path, capsys) -> None:
    """During a run a library warning (the GCS refusing a detection, say) is written to the
    run directory's log and counted; nothing reaches stderr, where the progress is."""
    import logging

    from mission.run import _library_logging

    path = tmp_path / "run.log"
    with _library_logging(path) as counter:
        logging.getLogger("gcs.ground_station").warning("rejected robot 2 Detection 17")
        logging.getLogger("robot.node").info("robot 1: deadlock")
    logging.getLogger("gcs.ground_station").warning("after the run")  # not in the file
    assert counter.warnings == 1
    text = path.read_text()
    assert "rejected robot 2 Detection 17" in text and "robot 1: deadlock" in text
    assert "after the run" not in text
    assert "rejected robot 2" not in capsys.readouterr().err


def test_run_help_gives_defaults_units_outputs_and_terms(capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["run", "--help"])
    assert exit_.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    for needle in (
        "mission-seconds to run (default: 180)",
        "(default: 0)",
        "(default: small)",
        "what a run produces: a run directory (--out; default runs/",
        "--scripted",
        "events (rule events): the simulator's rule events",
        "130 after ^C and 143 after SIGTERM",
        "--realtime",
        "NOT repeatable",
    ):
        assert needle in text, needle


def test_run_command_refuses_a_run_directory_that_holds_a_run(capsys, tmp_path) -> None:
    (tmp_path / "record").mkdir()
    assert main(["run", "--out", str(tmp_path), "--duration", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "already holds a run (record/, journal.sqlite)" in err and err.count("\n") == 1


def test_run_command_refuses_a_negative_seed_in_one_line(capsys) -> None:
    assert main(["run", "--seed", "-1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == "magic run: seed must be >= 0, got -1"


def test_realtime_says_it_is_not_repeatable(capsys, tmp_path) -> None:
    out = ["--out", str(tmp_path / "run")]
    assert main(["run", "--realtime", "--duration", "2", "--quiet", *out]) == 0
    captured = capsys.readouterr()
    assert "--realtime: radio delivery on wall-clock threads; this run is not repeatable" in (
        " ".join(captured.err.split())
    )
    assert "mode: --realtime, wall-clock delivery (not repeatable)" in captured.out


def test_tasks_ok_over_sent_count_the_same_tasks_planners_and_operators_alike() -> None:
    """The progress table's tasks ok/sent: of the tasks sent to a robot (the planners' and an
    operator's), those that ended well; a task's end heard twice (a resumed GCS) counts once,
    and a status for a task this run never sent counts nowhere."""
    from mission.run import RobotProgress, _ProgressTap
    from protocol.messages import TaskState, TaskStatus

    progress = {0: RobotProgress(0), 1: RobotProgress(1)}
    tap = _ProgressTap(progress)
    for rid, tid, state in [
        (0, 1, TaskState.SUCCEEDED),
        (0, 1, TaskState.SUCCEEDED),  # heard again
        (0, 70001, TaskState.SUCCEEDED),  # an operator's task
        (0, 2, TaskState.ACTIVE),
        (1, 3, TaskState.FAILED),
        (1, 99, TaskState.SUCCEEDED),  # never sent by this run
    ]:
        tap(rid, TaskStatus(tid, state, 1.0), True)
    tap.settle({0: {1, 2, 70001}, 1: {3, 4}})
    assert (progress[0].goals_succeeded, progress[0].goals_sent) == (2, 3)
    assert (progress[1].goals_succeeded, progress[1].goals_failed, progress[1].goals_sent) == (
        0,
        1,
        2,
    )


def test_the_gcs_in_its_own_process_gives_the_same_mission() -> None:
    """``magic run --gcs-process``: the GCS in a process of its own (and the robots in a
    worker) over the zenoh link, the same figures bit for bit as all in one process."""
    from protocol.link import LinkConfig
    from protocol.loopback import free_loopback_port, unique_mission

    config = RunConfig(duration_s=6.0, seed=2)
    in_process = run_mission(config).fields()
    report = run_mission(
        msgspec.structs.replace(config, robot_processes=True, workers=1, gcs_process=True),
        link=LinkConfig(listen=(f"tcp/127.0.0.1:{free_loopback_port()}",)),
        mission_name=unique_mission("run-gcs"),
    )
    apart = report.fields()
    assert fields_differing(in_process, apart) == []
    assert "the GCS in its own (pid " in report.processes
    assert apart["gcs_pose_nodes"] > 0 and apart["tasks_sent"] > 0


def test_a_gcs_process_killed_with_sigkill_is_restarted_and_loses_nothing(
    tmp_path: Path,
) -> None:
    """kill -9 of the GCS process mid-turn: the run notices, a standby rebuilds the station
    and the radio's state from the journal, the mission goes on; at the end every message
    the robots' links accepted on a reliable stream is journaled or still on its way, and
    the journal replays to the station it rebuilds."""
    from gcs.journal import GcsJournal, rebuild_station
    from mission.bench.chaos import _floor_loss, _reliable_lost
    from mission.lockstep import TeamOverProcesses
    from mission.mission_replay import compare_replay
    from protocol.loopback import unique_mission
    from tests.mission.test_lockstep_gcs import gcs_process_team

    journal = tmp_path / "journal.sqlite"
    with gcs_process_team(journal, seed=5, mission=unique_mission("gcs-kill")) as asm:
        _floor_loss(asm.sim, 0.3)  # messages held behind gaps when it dies
        remote, team = asm.remote_gcs, asm.team
        assert isinstance(team, TeamOverProcesses)
        first_pid = remote.pid
        steps = int(round(12.0 / asm.sim.config.step_s))
        for k in range(steps):
            if k == steps // 2:
                at_kill = remote.figures["gcs"]["gcs_pose_nodes"]
                team.step(remote.kill)  # SIGKILL during its turn
            else:
                team.report_link = k == steps - 1
                asm.step()
        assert remote.restarts == 1 and remote.pid != first_pid
        assert remote.restart_s[0] < 10.0  # 0.3-0.5 s warm (magic bench chaos); loaded CI
        lost, in_flight, first = _reliable_lost(team.robot_done(), remote.figures["recv"])
        assert lost == 0, first
        nodes = remote.figures["gcs"]["gcs_pose_nodes"]
    reader = GcsJournal.open(journal)
    station, _ = rebuild_station(reader)
    reader.close()
    assert station.stats.pose_nodes >= nodes > at_kill  # the mission went on after the kill
    diff = compare_replay(journal, station)
    assert diff.nodes_equal and diff.edges_equal and diff.pose_diff_max_m <= 1e-9


def test_a_cold_kernel_cache_is_told_before_the_first_run(tmp_path, monkeypatch) -> None:
    from mission.run import _kernels_cold

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert _kernels_cold()  # nothing compiled yet: the run says it compiles first
    (tmp_path / "robot" / "terrain").mkdir(parents=True)
    (tmp_path / "robot" / "terrain" / "free_space._ray_floor-32.py311.nbi").write_bytes(b"x")
    assert not _kernels_cold()


def test_print_config_lists_every_key_and_reads_back(capsys) -> None:
    from protocol.config import load_config_text

    assert main(["run", "--print-config", "--duration", "42", "--seed", "3"]) == 0
    text = capsys.readouterr().out
    config = load_config_text(text, RunConfig, source="printed")
    assert config == msgspec.structs.replace(RunConfig(), duration_s=42.0, seed=3)
