"""``magic run`` end to end: simulator, robot nodes and the ground side over real zenoh."""

from __future__ import annotations

import pytest

from mission.cli import main
from mission.run import RunConfig, run_mission

pytestmark = pytest.mark.slow


def test_team_drives_scripted_goals_over_the_radio_link() -> None:
    """The README's main job as configured by default (4 robots, 4 goals each, 180 s)."""
    config = RunConfig()
    report = run_mission(config)
    assert report.mission_s == pytest.approx(config.duration_s)
    assert len(report.robots) == 4
    summary = report.summary()
    print("magic run:", summary)  # the numbers, for the record (pytest -s)
    for p in report.robots.values():
        assert p.alive
        assert p.goals_succeeded >= 2  # every robot makes real progress on its own
        assert p.distance_m > 10.0
        assert p.pose_nodes >= 3 and p.terrain_grids == p.pose_nodes  # arrived over the link
        assert p.uplink_bytes > 0
    # most goals are reached (measured: all 16 of 16 for seeds 0-5)
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
        (["--world", "/tmp/no/such/world.yaml"], "(shipped: magic_phase, small)"),
        (["--duration", "-5"], "duration_s must be > 0 mission-seconds, got -5.0"),
        (["--duration", "nan"], "duration_s must be > 0 mission-seconds, got nan"),
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
