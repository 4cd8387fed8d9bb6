"""The ``magic`` command: bad input is one line on stderr and status 2; bench checks suites
and paths before it runs; SIGINT/SIGTERM end any command in one line with 130/143; the help
states defaults and what each command produces."""

from __future__ import annotations

import json
import os
import re
import selectors
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import IO

import pytest

from mission.bench import SUITES, bench_root, output_dir
from mission.cli import main

COMMANDS = ["bench", "run", "sim", "robot", "gcs", "replay", "console", "perception", "codec"]
COMMANDS += ["report"]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["report", "run.json"], "magic report: run.json: not a directory"),
        (["report", "/nonexistent/run"], "magic report: /nonexistent/run: not a directory"),
    ],
)
def test_bad_input_is_one_line_and_status_2(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(message) and err.count("\n") == 1


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
    # one line naming the problem and where help is, not argparse's usage block
    assert err.startswith("magic") and err.count("\n") == 1 and "--help says" in err


def test_help_lists_every_subcommand(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["--help"])
    assert info.value.code == 0
    out = " ".join(capsys.readouterr().out.split())  # argparse wraps to the terminal width
    for command in COMMANDS:
        assert f" {command} " in out
    assert "not built yet" not in out


def test_console_script() -> None:
    script = Path(sys.executable).parent / "magic"
    assert script.exists(), f"console script not installed at {script}"
    proc = subprocess.run(
        [str(script), "report", "no-such-run"], capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 2
    assert proc.stdout == ""
    assert proc.stderr == "magic report: no-such-run: not a directory\n"


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


# ------------------------------------------------------------------ stops, checks, help (issue 20)

MAGIC = str(Path(sys.executable).parent / "magic")
REPO = Path(__file__).resolve().parents[2]


def _start(argv: list[str], env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [MAGIC, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=REPO,
        env=env,
    )


def _wait_for_line(stream: IO[str], wanted: str, timeout_s: float) -> list[str]:
    """Lines read from ``stream`` up to the first containing ``wanted`` (AssertionError
    with what was read if it does not come within ``timeout_s``)."""
    deadline = time.monotonic() + timeout_s
    seen: list[str] = []
    with selectors.DefaultSelector() as sel:
        sel.register(stream, selectors.EVENT_READ)
        while time.monotonic() < deadline:
            if not sel.select(timeout=max(deadline - time.monotonic(), 0.0)):
                break
            line = stream.readline()
            if not line:
                break
            seen.append(line)
            if wanted in line:
                return seen
    raise AssertionError(f"no line with {wanted!r} within {timeout_s} s; read: {seen}")


def _stop(proc: subprocess.Popen[str], signum: int) -> tuple[str, str]:
    try:
        proc.send_signal(signum)
        return proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.parametrize(
    ("json_arg", "named"),
    [
        ("/nonexistent/dir/x.json", "directory /nonexistent/dir does not exist"),
        ("{tmp}", "is a directory"),
    ],
)
def test_bench_json_path_is_checked_before_the_suite(
    json_arg: str, named: str, tmp_path: Path
) -> None:
    """The whole graph suite would run for a minute first: it fails at once, in one line."""
    json_arg = json_arg.replace("{tmp}", str(tmp_path))
    t0 = time.monotonic()
    proc = subprocess.run(
        [MAGIC, "bench", "graph", "--quick", "--json", json_arg],
        capture_output=True,
        text=True,
        timeout=30,
        cwd=REPO,
    )
    assert proc.returncode == 2
    assert time.monotonic() - t0 < 15  # interpreter start and imports only
    assert proc.stdout == ""
    assert proc.stderr.count("\n") == 1 and len(proc.stderr) < 200
    assert proc.stderr.startswith(f"magic bench: --json {json_arg}: ") and named in proc.stderr


def test_bench_refuses_an_unwritable_bench_dir(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    env = dict(os.environ, MAGIC_BENCH_DIR=str(blocker / "sub"))
    proc = subprocess.run(
        [MAGIC, "bench", "graph", "--quick"],
        capture_output=True,
        text=True,
        timeout=30,
        cwd=REPO,
        env=env,
    )
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and len(proc.stderr.strip()) < 200
    assert proc.stderr.startswith("magic bench: $MAGIC_BENCH_DIR ")
    assert proc.stderr.strip().endswith("/file is not a directory")  # long paths lose a middle


@pytest.mark.parametrize(("signum", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_a_signal_stops_a_bench_suite_in_one_line(signum: int, status: int) -> None:
    proc = _start(["bench", "loops", "--quick"])
    assert proc.stderr is not None
    _wait_for_line(proc.stderr, "loops matcher", timeout_s=60)
    out, err = _stop(proc, signum)
    name = signal.Signals(signum).name
    assert proc.returncode == status, err
    assert "Traceback" not in err and "Error" not in err
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"magic bench: stopped by {name} (suite loops stopped after ")
    assert len(last) < 200
    assert out == ""  # no table of metrics that were not measured


def test_sigterm_escaping_a_command_ends_in_one_line_not_a_traceback(tmp_path: Path) -> None:
    """``magic codec record`` has no stop handling of its own: main's last line of defence
    ends it (status 143) and nothing is half-written."""
    out_file = tmp_path / "corpus.npz"
    proc = _start(["codec", "record", "--split", "test", "--out", str(out_file)])
    assert proc.stderr is not None
    _wait_for_line(proc.stderr, "recording ", timeout_s=60)
    _, err = _stop(proc, signal.SIGTERM)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1] == "magic codec: stopped by SIGTERM"
    assert not out_file.exists()


def _option_helps(help_text: str) -> dict[str, str]:
    """Option -> its help text (argparse's layout: an option line, continuation lines)."""
    helps: dict[str, str] = {}
    current = None
    for line in help_text.splitlines():
        m = re.match(r"^  (-[-\w]+(?:, --[-\w]+)?)(?: [A-Z_{}\[\],|.]+)?(?:\s{2,}(.*))?$", line)
        if m:
            current = m.group(1)
            helps[current] = m.group(2) or ""
        elif current and line.startswith("    "):
            helps[current] += " " + line.strip()
        else:
            current = None
    return helps


@pytest.mark.parametrize(
    "argv", [["bench", "--help"], ["codec", "record", "--help"], ["codec", "train", "--help"]]
)
def test_help_states_every_default_and_what_is_produced(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        main(argv)
    assert info.value.code == 0
    text = capsys.readouterr().out
    helps = _option_helps(text)
    options = [o for o in helps if o != "-h, --help"]
    assert options, text
    for option in options:
        assert "default" in helps[option], f"{argv}: {option} states no default: {helps[option]}"
    flat = " ".join(text.split())
    if argv[0] == "bench":
        assert "under 60 s" in flat and "MAGIC_BENCH_DIR" in flat and "stdout" in flat
        assert "130" in flat and "143" in flat
    else:
        assert ".npz" in flat and "stderr" in flat


def test_top_level_help_says_what_each_command_produces(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit):
        main(["--help"])
    flat = " ".join(capsys.readouterr().out.split())
    for words in ("table on stdout", "summary line", ".npz", "--out", "143 stopped by SIGTERM"):
        assert words in flat


def test_a_bench_run_writes_nothing_to_the_system_temp_dir(tmp_path: Path) -> None:
    """With MAGIC_BENCH_DIR set, a suite's plot goes there; a private TMPDIR stays empty."""
    system_tmp = tmp_path / "system-tmp"
    bench_dir = tmp_path / "bench"
    system_tmp.mkdir()
    env = dict(os.environ, MAGIC_BENCH_DIR=str(bench_dir), TMPDIR=str(system_tmp))
    proc = subprocess.run(
        [MAGIC, "bench", "compression", "--quick", "--json", str(tmp_path / "m.json")],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=REPO,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (bench_dir / "compression" / "fig10_bytes_per_grid.png").stat().st_size > 1000
    assert json.loads((tmp_path / "m.json").read_text())["suite"] == "compression"
    assert sorted(p.name for p in system_tmp.rglob("*")) == []


def test_bench_output_dir_follows_the_environment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("MAGIC_BENCH_DIR", str(tmp_path / "b"))
    assert output_dir("loops_replay") == tmp_path / "b" / "loops_replay"
    assert (tmp_path / "b" / "loops_replay").is_dir()
    monkeypatch.delenv("MAGIC_BENCH_DIR")
    assert bench_root() == Path(tempfile.gettempdir()) / "magic-bench"


def test_sigterm_stops_a_suites_child_processes_too(tmp_path: Path) -> None:
    """``magic bench sim`` runs its 64-robot part in a child: SIGTERM (which reaches the
    parent only) ends both, in one line with status 143, and neither leaves its scene's
    temporary files behind (a private TMPDIR stays empty)."""
    system_tmp = tmp_path / "system-tmp"
    system_tmp.mkdir()
    proc = _start(["bench", "sim", "--quick"], env=dict(os.environ, TMPDIR=str(system_tmp)))
    assert proc.stderr is not None
    _wait_for_line(proc.stderr, "in a child process", timeout_s=120)
    children: list[str] = []
    deadline = time.monotonic() + 30
    while not children and time.monotonic() < deadline:  # the child is being spawned
        listing = subprocess.run(
            ["pgrep", "-P", str(proc.pid)], capture_output=True, text=True, timeout=10
        )
        children = listing.stdout.split()
        if not children:
            time.sleep(0.1)
    assert children, "the 64-robot child never started"
    while not any(system_tmp.iterdir()) and time.monotonic() < deadline:
        time.sleep(0.1)  # the child builds its scene (files under TMPDIR)
    assert any(system_tmp.iterdir()), "the child wrote no scene files"
    _, err = _stop(proc, signal.SIGTERM)
    assert proc.returncode == 143, err
    assert "Traceback" not in err
    assert err.strip().splitlines()[-1].startswith("magic bench: stopped by SIGTERM (suite sim")
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline and any(Path(f"/proc/{c}").exists() for c in children):
        time.sleep(0.1)
    assert not [c for c in children if Path(f"/proc/{c}").exists()]
    assert sorted(p.name for p in system_tmp.iterdir()) == []


def test_every_registered_suite_has_its_module() -> None:
    import importlib.util

    missing = [m for m in SUITES.values() if importlib.util.find_spec(m) is None]
    assert missing == []


_HEAVY = ("gtsam", "pybullet", "numba", "scipy", "cv2")


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "--help"],
        ["gcs", "--help"],
        ["robot", "--help"],
        ["replay", "--help"],
        ["sim", "--help"],
        ["robot", "--id", "0", "--duration", "soon"],
        ["run", "--workers", "two"],
        ["replay"],
    ],
)
def test_help_and_argument_errors_load_none_of_the_work(argv: list[str]) -> None:
    """``magic X --help`` and a bad argument answer from the command's light parser: none of
    gtsam, PyBullet, numba, scipy, cv2 is imported (they made help take seconds); the help
    ends with the exit statuses, an argument error is status 2."""
    code = (
        "import sys\nfrom mission.cli import main\ntry:\n    status = main(sys.argv[1:])\n"
        "except SystemExit as e:\n    status = e.code\n"
        f"print('loaded', [m for m in {_HEAVY!r} if m in sys.modules], 'status', status)"
    )
    done = subprocess.run(
        [sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=120
    )
    last = done.stdout.strip().splitlines()[-1]
    want = 0 if "--help" in argv else 2
    assert last == f"loaded [] status {want}", (last, done.stderr[-300:])
    if want == 0:
        flat = " ".join(done.stdout.split())
        assert "exit status: 0 done, 1 the work failed, 2 bad input" in flat
        assert "143 stopped by SIGTERM" in flat
