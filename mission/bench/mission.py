"""``magic bench mission``: the autonomous mission, scored against the truth (issue 14).

Each run is ``magic run`` itself (:func:`mission.run.run_mission` in a ``magic run`` process):
the simulator, every robot node and the GCS with its planners over the radio in deterministic
lockstep, recorded and scored by :mod:`mission.report` in a run directory under
:func:`~mission.bench.output_dir` (``mission/seed-N``).

- ``--quick``: the small world, its 4 robots (3 sensor robots, 1 disruptor), 300 mission-s,
  seeds 0 (used in development) and 7 (never used in development), the two runs side by side
  in two processes (the machine has two cores);
- full: ``magic_phase``, 14 robots (10 sensor robots, 4 disruptors), 30 mission-min, seed 0.

Metrics (the issue's names): the worst over the seeds, each also per seed (``name.seedN``):
``explored_frac``, ``static_ooi_detected_frac``, ``static_ooi_neutralized_frac``,
``hostiles_neutralized_frac``, ``occupancy_f1`` (lowest; also ``occupancy_f1_aligned``, the
map scored after the ATE's rigid alignment, a diagnostic); ``robots_lost``,
``civilians_harmed``, ``false_closures``, ``ate_rmse_m``, ``radio_use_frac`` (highest);
``rtf``: whole-system mission-s per wall second (lowest; setup excluded); ``wall_s``: the
bench's own wall time; ``tasks_sent``, ``closures`` (sum over the seeds). A metric the report
could not score (no OOI in the world, say) is left out rather than made up.
"""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

from mission.bench import BenchError, output_dir

__all__ = ["QUICK_SEEDS", "run"]

#: Seed 0 was used in development; seed 7 never was.
QUICK_SEEDS = (0, 7)

_LOWEST = (
    "explored_frac",
    "static_ooi_detected_frac",
    "static_ooi_neutralized_frac",
    "hostiles_neutralized_frac",
    "occupancy_f1",
    "occupancy_f1_aligned",
    "rtf",
)
_HIGHEST = (
    "robots_lost",
    "civilians_harmed",
    "false_closures",
    "ate_rmse_m",
    "radio_use_frac",
)
_SUMMED = ("closures",)


def _launch(world: str, duration_s: float, seed: int, run_dir: Path) -> subprocess.Popen[bytes]:
    if run_dir.exists():
        shutil.rmtree(run_dir)
    argv = [sys.executable, "-m", "mission.cli", "run", "--world", world]
    argv += ["--duration", f"{duration_s:g}", "--seed", str(seed), "--out", str(run_dir)]
    argv += ["--quiet"]
    return subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE)


def _metrics(run_dir: Path, proc: subprocess.Popen[bytes], seed: int) -> dict[str, float]:
    out, err = proc.communicate()
    if proc.returncode != 0:
        tail = err.decode(errors="replace").strip().splitlines()[-3:]
        raise BenchError(f"mission seed {seed} failed (status {proc.returncode}): {tail}")
    path = run_dir / "report.json"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise BenchError(f"mission seed {seed}: no report at {path}: {e}") from None
    metrics = {k: float(v) for k, v in doc["metrics"].items() if isinstance(v, int | float)}
    tasks = [line for line in out.decode(errors="replace").splitlines() if "tasks sent" in line]
    if tasks:  # "gcs: ... N tasks sent" from the summary
        words = tasks[-1].split()
        i = words.index("tasks")
        metrics["tasks_sent"] = float(words[i - 1])
    return metrics


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    world, duration_s, seeds = (
        ("small", 300.0, QUICK_SEEDS) if quick else ("magic_phase", 1800.0, (0,))
    )
    root = output_dir("mission")
    t0 = time.perf_counter()
    procs = {s: _launch(world, duration_s, s, root / f"seed-{s}") for s in seeds}
    per_seed: dict[int, dict[str, float]] = {}
    try:
        for s, proc in procs.items():
            per_seed[s] = _metrics(root / f"seed-{s}", proc, s)
            m = per_seed[s]
            progress(
                f"{world} seed {s}: explored {m.get('explored_frac', math.nan):.2f}, "
                f"F1 {m.get('occupancy_f1', math.nan):.2f}, ATE {m.get('ate_rmse_m', math.nan):.3f}"
                f" m, rtf {m.get('rtf', math.nan):.2f} ({root / f'seed-{s}'})"
            )
    finally:
        for proc in procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    out: dict[str, float] = {"wall_s": time.perf_counter() - t0, "seeds": float(len(seeds))}
    for names, pick in ((_LOWEST, min), (_HIGHEST, max), (_SUMMED + ("tasks_sent",), sum)):
        for name in names:
            values = [m[name] for m in per_seed.values() if math.isfinite(m.get(name, math.nan))]
            if values:
                out[name] = float(pick(values))
            for s, m in per_seed.items():
                v = m.get(name, math.nan)
                if math.isfinite(v):
                    out[f"{name}.seed{s}"] = v
    return out
