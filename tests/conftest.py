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
