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


@pytest.fixture(autouse=True)
def _clean_stop_signals(request: pytest.FixtureRequest) -> Iterator[None]:
    """Every test starts with SIGINT and SIGTERM deliverable and not ignored in the worker, as
    a process started from a shell has them: a child process inherits an ignored or blocked
    signal (the signal tests' ``magic run`` and CLI children then never stop). A test that
    leaves them so is named in a warning and the worker is put right."""
    import signal
    import threading
    import warnings

    stops = {signal.SIGINT, signal.SIGTERM}
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    yield
    blocked = stops & signal.pthread_sigmask(signal.SIG_BLOCK, [])
    ignored = {s for s in stops if signal.getsignal(s) is signal.SIG_IGN}
    if blocked or ignored:
        warnings.warn(
            f"{request.node.nodeid} left signals blocked {sorted(map(int, blocked))} / "
            f"ignored {sorted(map(int, ignored))} in the test worker",
            stacklevel=1,
        )
        signal.pthread_sigmask(signal.SIG_UNBLOCK, stops)
        if signal.SIGINT in ignored:
            signal.signal(signal.SIGINT, signal.default_int_handler)
        if signal.SIGTERM in ignored:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
