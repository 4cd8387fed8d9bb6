"""SIGTERM and ^C stop every ``magic`` process the same way (protocol.process_cli)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import pytest

from protocol.process_cli import (
    Terminated,
    check_input_file,
    check_output_dir,
    check_output_file,
    exit_code_for,
    install_sigterm_handler,
    install_stop_handlers,
    one_line,
    raise_on_sigterm,
    signal_name_for,
    signals_received,
    spin_until,
    stop_cause,
    stop_exception,
    stop_on_interrupt,
    stopped_line,
)


def test_terminated_is_a_keyboard_interrupt_carrying_its_signal() -> None:
    exc = Terminated()
    assert isinstance(exc, KeyboardInterrupt)
    assert exc.signum == signal.SIGTERM
    assert exit_code_for(exc) == 143
    assert exit_code_for(KeyboardInterrupt()) == 130
    assert exit_code_for(Terminated(signal.SIGHUP)) == 129
    # raised from signal handlers, so it never fails to construct (mission/run.py passes a name)
    assert Terminated("SIGTERM").signum == signal.SIGTERM
    assert Terminated("SIGHUP").signum == signal.SIGHUP
    assert Terminated("no such signal").signum == signal.SIGTERM
    assert signal_name_for(exc) == "SIGTERM"
    assert signal_name_for(KeyboardInterrupt()) == "SIGINT"
    assert stopped_line("bench", KeyboardInterrupt(), "suite loops") == (
        "magic bench: stopped by SIGINT (suite loops)"
    )


def test_sigterm_raises_terminated_within_the_block_only() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Terminated) as caught, raise_on_sigterm():
        os.kill(os.getpid(), signal.SIGTERM)
        threading.Event().wait(5.0)
    assert caught.value.signum == signal.SIGTERM
    assert signal.getsignal(signal.SIGTERM) is before


def test_stop_on_interrupt_takes_sigint_and_sigterm() -> None:
    stops: list[int] = []
    with raise_on_sigterm():  # the handler cli.main installs: stop_on_interrupt takes over
        with stop_on_interrupt(lambda: stops.append(1)) as received:
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(100):
                if len(received) == 2:
                    break
                threading.Event().wait(0.01)
        assert sorted(received) == sorted([signal.SIGTERM, signal.SIGINT])
        assert stops == [1, 1]
        with pytest.raises(Terminated):  # and gives SIGTERM back after
            os.kill(os.getpid(), signal.SIGTERM)
            threading.Event().wait(5.0)


def test_stop_on_interrupt_leaves_a_callers_own_sigterm_handler() -> None:
    mine: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, _f: mine.append(signum))
    try:
        with stop_on_interrupt(lambda: None) as received:
            os.kill(os.getpid(), signal.SIGTERM)
            for _ in range(100):
                if mine:
                    break
                threading.Event().wait(0.01)
        assert mine == [signal.SIGTERM]
        assert received == []
    finally:
        signal.signal(signal.SIGTERM, previous)


def test_off_the_main_thread_nothing_changes() -> None:
    results: list[object] = []
    t = threading.Thread(target=lambda: results.append(install_sigterm_handler()))
    t.start()
    t.join()
    assert results == [None]


def test_a_process_stopped_by_sigterm_exits_143_without_a_traceback() -> None:
    code = textwrap.dedent(
        """
        import sys, threading
        from protocol.process_cli import exit_code_for, install_sigterm_handler, stopped_line
        install_sigterm_handler()
        try:
            print("ready", flush=True)
            threading.Event().wait(30)
        except KeyboardInterrupt as exc:
            print(stopped_line("test", exc), file=sys.stderr)
            sys.exit(exit_code_for(exc))
        """
    )
    for signum, status, name in ((signal.SIGTERM, 143, "SIGTERM"), (signal.SIGINT, 130, "SIGINT")):
        proc = subprocess.Popen(
            [sys.executable, "-c", code],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))),
        )
        try:
            assert proc.stdout is not None
            assert proc.stdout.readline().strip() == "ready"
            proc.send_signal(signum)
            _, err = proc.communicate(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert proc.returncode == status
        assert err.strip() == f"magic test: stopped by {name}"


def test_one_line_keeps_both_ends_under_the_limit() -> None:
    assert one_line("a\n  b\tc") == "a b c"
    long = "magic bench: " + "/x" * 200 + " is not a directory"
    short = one_line(long)
    assert len(short) == 199
    assert short.startswith("magic bench: /x") and short.endswith("is not a directory")


def test_path_checks_name_the_directory_at_fault(tmp_path: Path) -> None:
    assert check_output_file(tmp_path / "a.json", "--json") == tmp_path / "a.json"
    with pytest.raises(ValueError, match="directory /nonexistent/dir does not exist"):
        check_output_file("/nonexistent/dir/x.json", "--json")
    with pytest.raises(ValueError, match="is a directory"):
        check_output_file(tmp_path, "--json")
    assert check_output_dir(tmp_path / "new" / "deeper", "--out") == tmp_path / "new" / "deeper"
    assert not (tmp_path / "new").exists()  # nothing created
    (tmp_path / "f").write_text("x")
    with pytest.raises(ValueError, match=f"{tmp_path / 'f'} is not a directory"):
        check_output_dir(tmp_path / "f" / "sub", "--out")
    with pytest.raises(ValueError, match="--corpus .*: not found"):
        check_input_file(tmp_path / "none.npz", "--corpus")
    assert check_input_file(tmp_path / "f", "--corpus") == tmp_path / "f"
    assert list(tmp_path.iterdir()) == [tmp_path / "f"]  # the write probe left nothing


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")
def test_a_stop_swallowed_by_c_code_is_still_on_record() -> None:
    """CPython drops an exception raised in a ctypes callback (numba compiling calls back
    like this): the raise is lost, the record of the signal is not."""
    import ctypes

    def callback() -> None:
        os.kill(os.getpid(), signal.SIGTERM)
        for _ in range(1000):  # the handler runs between these bytecodes, inside C's call
            pass

    c_callback = ctypes.CFUNCTYPE(None)(callback)
    previous = install_stop_handlers()
    try:
        before = len(signals_received())
        c_callback()  # the Terminated raised inside is printed and ignored, not propagated
        assert signals_received()[before:] == (signal.SIGTERM,)
        assert isinstance(stop_exception(signal.SIGTERM), Terminated)
        assert type(stop_exception(signal.SIGINT)) is KeyboardInterrupt
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def test_install_stop_handlers_keeps_an_ignored_signal_ignored() -> None:
    previous_int = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        previous = install_stop_handlers()
        assert set(previous) == {signal.SIGTERM}
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        signal.signal(signal.SIGTERM, previous[signal.SIGTERM])
    finally:
        signal.signal(signal.SIGINT, previous_int)


def test_stop_cause_finds_a_stop_wrapped_by_c_code() -> None:
    def wrapped() -> None:
        try:
            raise Terminated()
        except KeyboardInterrupt as exc:  # what numba's dispatcher does with it
            raise SystemError("dispatcher returned a result with an exception set") from exc

    with pytest.raises(SystemError) as caught:
        wrapped()
    stop = stop_cause(caught.value)
    assert isinstance(stop, Terminated) and exit_code_for(stop) == 143
    assert stop_cause(ValueError("plain")) is None
    assert type(stop_cause(KeyboardInterrupt())) is KeyboardInterrupt


def test_a_still_mission_clock_is_reported_once_not_repeated() -> None:
    clock = {"t": 0.0}
    spins = {"n": 0}
    lines: list[str] = []
    stop = threading.Event()

    def spin_once() -> None:
        spins["n"] += 1
        if spins["n"] <= 3:
            clock["t"] += 1.0  # the simulator runs 3 s, then ends: the clock stands at 3.0
        if spins["n"] >= 12:
            stop.set()

    spin_until(
        spin_once,
        now=lambda: clock["t"],
        stop=stop,
        progress=lines.append,
        status=lambda: f"t={clock['t']:.1f}",
        progress_period_s=0.0,
    )
    assert lines[:3] == ["t=1.0", "t=2.0", "t=3.0"]
    assert len(lines) == 4 and "stands at t=3.0 s" in lines[3]  # once, then quiet
