"""The ``magic`` command: unbuilt subcommands say so on stderr and exit 2; bench checks suites."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from mission.bench import SUITES
from mission.cli import main

UNBUILT = ["console", "report"]


@pytest.mark.parametrize("command", UNBUILT)
def test_unbuilt_subcommands_exit_2(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main([command]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(f"magic {command}: not built yet; it arrives with ")
    assert err.endswith(".\n") and err.count("\n") == 1


@pytest.mark.parametrize(
    "argv",
    [
        ["console", "--mission", "demo"],
        ["report", "run.json"],
    ],
)
def test_unbuilt_subcommands_with_arguments(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(f"magic {argv[0]}: not built yet")


def test_unknown_suite_names_the_known_ones(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "nosuchsuite"]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    text = " ".join(err.split())  # rich may wrap long lines
    assert "magic bench: unknown benchmark suite 'nosuchsuite'; known suites: " in text
    assert SUITES and all(name in text for name in SUITES)


@pytest.mark.parametrize(
    "argv",
    [[], ["nosuchcommand"], ["bench"], ["bench", "link", "--bogus"]],
)
def test_usage_errors_exit_2(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith("usage: magic")


def test_help_lists_unbuilt_subcommands(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps to the terminal width
    for command in [*UNBUILT, "bench"]:
        assert command in out
    assert out.count("[not built yet]") == len(UNBUILT)


def test_console_script() -> None:
    script = Path(sys.executable).parent / "magic"
    assert script.exists(), f"console script not installed at {script}"
    proc = subprocess.run(
        [str(script), "report", "--run", "x"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr.startswith("magic report: not built yet")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["robot"], "the following arguments are required: --id"),
        (["robot", "--id", "-2"], "--id must be >= 0"),
        (["sim", "--world", "configs/worlds/x.yaml"], "x.yaml: no such file"),
        (["sim", "--bogus"], "unrecognized arguments: --bogus"),
    ],
)
def test_process_commands_refuse_bad_arguments(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    assert message in capsys.readouterr().err
