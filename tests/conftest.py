"""Session-wide test settings: nothing a test runs writes outside pytest's temporary dirs.

``magic bench`` suites write their maps and plots under ``$MAGIC_BENCH_DIR``
(:func:`mission.bench.output_dir`); for the whole session that is a directory pytest made
(session scope, so module-scoped fixtures that run a suite are covered too). Subprocesses
inherit it through the environment.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

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
