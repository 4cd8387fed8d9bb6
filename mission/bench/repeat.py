"""``magic bench repeat``: same seed, same mission (issue 20; DESIGN section 4).

The small world's default mission (:class:`mission.run.RunConfig`: 4 robots, the GCS and its
planners in the loop), run in deterministic lockstep (:mod:`mission.lockstep`):

1. seed 0;
2. seed 0 again, with a CPU-bound process beside it (the machine loaded);
3. seed 0 again, each robot node in its own process (``magic run --robot-processes``);
4. seed 1;
5. seed 0 with ``realtime`` (wall-clock delivery), for the speed comparison only.

Metrics:

- ``fields_compared``: figures of a run compared (:meth:`mission.run.RunReport.fields`: team
  summary, every robot's progress, node counters, uplink bytes and final pose from ground
  truth, every rule event);
- ``same_seed_fields_differing``: of those, how many differ between run 1 and runs 2 and 3
  (the largest count), floats compared bit for bit (must be 0);
- ``loaded_fields_differing``, ``processes_fields_differing``: the same, each on its own;
- ``other_seed_fields_differing``: how many differ between runs 1 and 4 (must be > 0: the
  seed matters);
- ``lockstep_rtf``, ``realtime_rtf``: real-time factors (mission-s per wall second, setup
  excluded) of runs 1 and 5; ``lockstep_rtf_over_free``: their ratio (the cost of
  determinism; >= 0.8 expected); ``loaded_rtf``, ``processes_rtf``: runs 2 and 3.

``--quick``: 20 mission-seconds per run (about 60 s in all); full: 90 mission-seconds.
Longer runs hold too: the quick mission's seed 7 over 300 mission-s, run twice in separate
``magic run`` processes (once beside seed 0, once at load ~9), gave reports equal in every
field but the wall time (session 13, 66f8349). Figures differ between installs with other
library versions (numpy, OpenCV, ...): the same seed is the same run on one install.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable

from mission.run import RunConfig, RunReport, fields_differing, run_mission

__all__ = ["run"]

_BUSY = "import time\nend = time.monotonic() + 600\nwhile time.monotonic() < end:\n    pass\n"


def _busy_process() -> subprocess.Popen[bytes]:
    """A CPU-bound process (bounded to 10 minutes should its parent die)."""
    return subprocess.Popen([sys.executable, "-c", _BUSY])


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    duration_s = 20.0 if quick else 90.0
    base = RunConfig(duration_s=duration_s, seed=0)

    def one(label: str, config: RunConfig) -> RunReport:
        report = run_mission(config)
        progress(f"{label}: {report.mission_s:g} mission-s at x{report.rtf:.2f} real time")
        return report

    first = one("seed 0", base)
    busy = _busy_process()
    try:
        loaded = one("seed 0, a CPU-bound process beside", base)
    finally:
        busy.kill()
        busy.wait()
    spread = one(
        "seed 0, robots in their own processes",
        RunConfig(duration_s=duration_s, seed=0, robot_processes=True),
    )
    other = one("seed 1", RunConfig(duration_s=duration_s, seed=1))
    free = one("seed 0, --realtime", RunConfig(duration_s=duration_s, seed=0, realtime=True))
    fields = first.fields()
    by_load = fields_differing(fields, loaded.fields())
    by_processes = fields_differing(fields, spread.fields())
    for what, names in (("beside a busy process", by_load), ("in processes", by_processes)):
        if names:
            progress(f"same seed {what}, differing: {', '.join(names[:8])}")
    return {
        "fields_compared": float(len(fields)),
        "same_seed_fields_differing": float(max(len(by_load), len(by_processes))),
        "loaded_fields_differing": float(len(by_load)),
        "processes_fields_differing": float(len(by_processes)),
        "other_seed_fields_differing": float(len(fields_differing(fields, other.fields()))),
        "lockstep_rtf": first.rtf,
        "loaded_rtf": loaded.rtf,
        "processes_rtf": spread.rtf,
        "realtime_rtf": free.rtf,
        "lockstep_rtf_over_free": first.rtf / free.rtf,
    }
