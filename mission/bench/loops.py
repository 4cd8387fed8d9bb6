"""``magic bench loops``: loop closing and the global map (issue 7; paper 4.3.3, 4.5, 4.8).

The suite is composed of parts, each a module ``mission.bench.<part>`` with the same
``run(*, quick, progress) -> dict[str, float]`` signature as a suite, owned with the code it
measures: the matcher and candidate search, rasterization, log replay, and the 4-robot
simulated run. The metrics of all parts are merged; a name reported by two parts is an error.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from mission.bench import BenchError

#: Part modules, in the order they run.
PARTS: tuple[str, ...] = ("loops_matcher", "loops_replay", "loops_raster", "loops_sim4")


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    metrics: dict[str, float] = {}
    for part in PARTS:
        module = importlib.import_module(f"mission.bench.{part}")
        for name, value in module.run(quick=quick, progress=progress).items():
            if name in metrics:
                raise BenchError(f"bench loops: metric {name!r} reported by two parts")
            metrics[name] = value
    return metrics
