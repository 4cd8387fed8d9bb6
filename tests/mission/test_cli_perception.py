"""``magic perception``: the shape and colour trainers behind one command; bad paths and
threshold files are one line and status 2 before any work."""

from __future__ import annotations

from pathlib import Path

import pytest

from mission.cli import main


def test_perception_names_its_actions(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["perception", "--help"]) == 0
    out = capsys.readouterr().out
    for action in ("record", "train", "evaluate", "colour"):
        assert action in out
    assert main(["perception"]) == 2  # no action: the usage on stderr
    assert "magic perception" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main(["perception", "train", "--help"])
    assert stop.value.code == 0
    assert "magic perception train" in capsys.readouterr().out


def test_colour_refuses_bad_paths_before_rendering(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["perception", "colour", "--out", str(tmp_path / "no" / "t.json")]) == 2
    assert "no such directory" in capsys.readouterr().err
    bad = tmp_path / "t.json"
    bad.write_text("{")
    assert main(["perception", "colour", "--thresholds", str(bad)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "not valid JSON" in err and len(err.strip().splitlines()) == 1
