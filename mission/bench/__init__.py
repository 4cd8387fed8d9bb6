"""``magic bench SUITE``: benchmark suites and their runner (DESIGN section 6).

A suite is a module ``mission.bench.<suite>`` exposing::

    def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]

It returns metrics by the names its issue gives; ``--quick`` finishes in under 60 s on the
2-core machine and still measures every metric. Ratios are measured against a baseline run in
the same process, and timings are medians of repeats. Suites never print: they report
progress through ``progress`` and return numbers; this runner prints the table and writes
``{"suite": ..., "quick": bool, "metrics": {name: number}}`` with ``--json``.

Files a suite writes besides its metrics (maps, plots) go under :func:`output_dir`:
``$MAGIC_BENCH_DIR/<suite>`` when that environment variable is set, else
``<system temp dir>/magic-bench/<suite>``.
"""

from __future__ import annotations

import importlib
import json
import math
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

__all__ = [
    "BENCH_DIR_ENV",
    "SUITES",
    "BenchError",
    "bench_root",
    "median_time_s",
    "output_dir",
    "run_suite",
    "write_json",
]

#: Environment variable naming the directory bench suites write their files under.
BENCH_DIR_ENV = "MAGIC_BENCH_DIR"

#: Suite name -> module that implements it (``radio``: the radio half of issue 16's scale
#: suite, 100 synthetic robots through the real link; ``scale``: the whole of it).
SUITES: dict[str, str] = {
    "link": "mission.bench.link",
    "graph": "mission.bench.graph",
    "sim": "mission.bench.sim",
    "robot": "mission.bench.robot",
    "loops": "mission.bench.loops",
    "compression": "mission.bench.compression",
    "robustness": "mission.bench.robustness",
    "repeat": "mission.bench.repeat",
    "mission": "mission.bench.mission",
    "perception": "mission.bench.perception",
    "operator": "mission.bench.operator",
    "radio": "mission.bench.radio_scale",
    "scale": "mission.bench.scale",
    "fuzz": "mission.bench.fuzz",
    "chaos": "mission.bench.chaos",
}


class BenchError(RuntimeError):
    """A suite is unknown or failed to produce its metrics."""


def bench_root() -> Path:
    """Where suites write their files: ``$MAGIC_BENCH_DIR`` if set, else
    ``<system temp dir>/magic-bench`` (read at each call: tests point it elsewhere)."""
    configured = os.environ.get(BENCH_DIR_ENV, "").strip()
    return Path(configured) if configured else Path(tempfile.gettempdir()) / "magic-bench"


def output_dir(suite: str) -> Path:
    """The directory suite (or suite part) ``suite`` writes its files in, created if absent;
    BenchError naming it when it cannot be."""
    path = bench_root() / suite
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise BenchError(f"cannot create bench output directory {path}: {err.strerror}") from None
    return path


class Suite(Protocol):
    def run(self, *, quick: bool, progress: Callable[[str], None]) -> dict[str, float]: ...


def median_time_s(fn: Callable[[], object], *, repeats: int, warmup: int = 1) -> float:
    """Median wall time of ``fn()`` over ``repeats`` runs after ``warmup`` untimed runs."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t0)
    return statistics.median(samples)


def run_suite(
    name: str, *, quick: bool, progress: Callable[[str], None] = lambda _msg: None
) -> dict[str, float]:
    """Import and run suite ``name``; returns its metrics (all finite numbers)."""
    if name not in SUITES:
        known = ", ".join(sorted(SUITES))
        raise BenchError(f"unknown benchmark suite {name!r}; known suites: {known}")
    module: Suite = importlib.import_module(SUITES[name])  # type: ignore[assignment]
    metrics = module.run(quick=quick, progress=progress)
    for key, value in metrics.items():
        if not isinstance(value, int | float) or not math.isfinite(value):
            raise BenchError(f"suite {name!r} metric {key!r} is not a finite number: {value!r}")
    return dict(metrics)


def write_json(path: str | Path, *, suite: str, quick: bool, metrics: dict[str, float]) -> None:
    """Write the benchmark result file in the format DESIGN section 6 fixes."""
    doc = {"suite": suite, "quick": quick, "metrics": metrics}
    Path(path).write_text(json.dumps(doc, indent=2, sort_keys=True) + "\n", encoding="utf-8")
