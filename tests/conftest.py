"""Session-wide test settings: nothing a test runs writes outside pytest's temporary dirs.

``magic bench`` suites write their maps and plots under ``$MAGIC_BENCH_DIR``
(:func:`mission.bench.output_dir`); for the whole session that is a directory pytest made
(session scope, so module-scoped fixtures that run a suite are covered too). Subprocesses
inherit it through the environment.

Hypothesis keeps its example database and constants cache in ``./.hypothesis`` (the
checkout) unless told otherwise: for the session it is a pytest temporary directory too.
"""

from __future__ import annotations

import os
import signal
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis.configuration import set_hypothesis_home_dir

from mission.bench import BENCH_DIR_ENV


@pytest.fixture(scope="session", autouse=True)
def bench_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """``$MAGIC_BENCH_DIR`` for the session: a pytest temporary directory."""
    path = tmp_path_factory.mktemp("magic-bench")
    previous = os.environ.get(BENCH_DIR_ENV)
    os.environ[BENCH_DIR_ENV] = str(path)
    try:
        yield path
    finally:
        if previous is None:
            os.environ.pop(BENCH_DIR_ENV, None)
        else:
            os.environ[BENCH_DIR_ENV] = previous


@pytest.fixture(scope="session", autouse=True)
def hypothesis_dir(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Hypothesis's storage (example database, constants cache) for the session: a pytest
    temporary directory, not ``.hypothesis/`` in the checkout."""
    path = tmp_path_factory.mktemp("hypothesis")
    set_hypothesis_home_dir(path)
    try:
        yield path
    finally:
        set_hypothesis_home_dir(None)


_STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def _stop_signals_off() -> tuple[set[signal.Signals], set[signal.Signals]]:
    """SIGINT / SIGTERM blocked in this thread, and ignored in this process."""
    mask = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    blocked = {s for s in _STOP_SIGNALS if s in mask}
    ignored = {s for s in _STOP_SIGNALS if signal.getsignal(s) is signal.SIG_IGN}
    return blocked, ignored


def _deliver_stop_signals() -> tuple[set[signal.Signals], set[signal.Signals]]:
    """Unblock SIGINT / SIGTERM and give them their default handlers where ignored, as a
    process started from an interactive shell has them; returns what was off (blocked,
    ignored). Main thread only (signal handlers can be set nowhere else)."""
    blocked, ignored = _stop_signals_off()
    if blocked:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, blocked)
    if signal.SIGINT in ignored:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    if signal.SIGTERM in ignored:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
    return blocked, ignored


# as this process was started (the conftest is imported before pytest_configure runs)
_STARTED_WITH = _stop_signals_off()


def _runs_tests(config: pytest.Config) -> bool:
    """False for pytest-xdist's controller (its workers run the tests), True for a worker or
    a run without workers."""
    return hasattr(config, "workerinput") or not config.getoption("numprocesses", None)


def _describe(blocked: set[signal.Signals], ignored: set[signal.Signals]) -> str:
    return f"blocked {sorted(map(int, blocked))} / ignored {sorted(map(int, ignored))}"


def pytest_report_header(config: pytest.Config) -> str | None:
    """Say so when pytest itself was started with SIGINT / SIGTERM off: a background job of a
    non-interactive shell (``.ci/run > log &`` from a script), ``nohup`` or a CI runner
    starts it with SIGINT ignored, and every worker inherits that."""
    blocked, ignored = _STARTED_WITH
    if not (blocked or ignored):
        return None
    return (
        f"stop signals: pytest was started with SIGINT / SIGTERM {_describe(blocked, ignored)}"
        " (a background job of a non-interactive shell ignores SIGINT); every process that"
        " runs tests restores them before collecting"
    )


def pytest_configure(config: pytest.Config) -> None:
    """In each process that runs tests (an xdist worker, or pytest itself without workers):
    SIGINT / SIGTERM deliverable before any test module is imported or fixture runs, so the
    children tests and module fixtures start (``magic run``, CLI processes) can be stopped
    with them. A worker inherits the state its launcher had: a background job of a
    non-interactive shell (POSIX) has SIGINT ignored; the controller is left as started."""
    if _runs_tests(config) and threading.current_thread() is threading.main_thread():
        _deliver_stop_signals()


@pytest.fixture(autouse=True)
def _clean_stop_signals(request: pytest.FixtureRequest) -> Iterator[None]:
    """Every test starts with SIGINT and SIGTERM deliverable and not ignored in the worker, as
    a process started from an interactive shell has them: a child process inherits an ignored
    or blocked signal (the signal tests' ``magic run`` and CLI children then never stop). A
    test that leaves them so is named in a warning; a fixture or teardown between tests that
    does is reported against the test it precedes; either way the worker is put right."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    blocked, ignored = _deliver_stop_signals()
    if blocked or ignored:
        warnings.warn(
            f"{_describe(blocked, ignored)} at the start of {request.node.nodeid} (set by a"
            " fixture, or an earlier test's teardown, in the test worker)",
            stacklevel=1,
        )
    yield
    blocked, ignored = _deliver_stop_signals()
    if blocked or ignored:
        warnings.warn(
            f"{request.node.nodeid} left signals {_describe(blocked, ignored)} in the test worker",
            stacklevel=1,
        )
