"""``magic run`` end to end: simulator, robot nodes and the ground side over real zenoh."""

from __future__ import annotations

import pytest

from mission.cli import main
from mission.run import RunConfig, run_mission

pytestmark = pytest.mark.slow


def test_team_drives_scripted_goals_over_the_radio_link() -> None:
    report = run_mission(RunConfig(duration_s=45.0, seed=1))
    assert report.mission_s == pytest.approx(45.0)
    assert len(report.robots) == 4
    for p in report.robots.values():
        assert p.goals_sent >= 1
        assert p.distance_m > 3.0  # every robot drove on its own
        assert p.pose_nodes >= 3 and p.terrain_grids == p.pose_nodes  # arrived over the link
        assert p.uplink_bytes > 0
        assert p.goals_failed == 0
    # Robots do not yet avoid moving teammates reactively (two robots that start side by
    # side can jam each other); the team as a whole makes progress.
    assert sum(p.distance_m for p in report.robots.values()) > 80.0
    assert sum(p.goals_succeeded for p in report.robots.values()) >= 4


def test_run_command_reports_a_bad_config_file(tmp_path, capsys) -> None:
    bad = tmp_path / "run.yaml"
    bad.write_text("duration_s: soon\n")
    assert main(["run", "--config", str(bad), "--quiet"]) == 2
    assert "duration_s: expected float, got str" in capsys.readouterr().err
