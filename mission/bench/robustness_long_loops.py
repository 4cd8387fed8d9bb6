"""Part of ``magic bench robustness``: long loops (issue 19 item 5).

Every shipped CARMEN log with reference poses (Intel, ACES, Freiburg 079) is replayed through
:func:`mission.replay.run_replay` as the replay part does (seeded odometry noise,
:data:`mission.bench.robustness.NOISE_SCALE` times the pose-node model), whole and with a
data gap (``data_gap``: a tenth of the scans, laser and odometry, dropped from the middle: no
closure can span the gap unless something finds the place again without the graph's help).
The GCS runs its default configuration: what is measured is what ships.

Evaluation only (the GCS never reads the reference poses): a node *revisits after a long loop*
when it lies within :data:`REVISIT_M` of a node that the robot left at least :data:`LOOP_M`
of travel before (travel and distances on the reference poses); it is *closed* when it is an
end of an accepted automatic closure whose other end lies at least :data:`LOOP_M` of travel
away. Metrics:

- ``long_loop_revisits_closed_frac_{log}`` (and ``_{log}_data_gap``): closed over revisiting nodes;
- ``long_loop_revisits_{log}``: how many nodes revisit (the denominator);
- ``long_loop_ate_m_{log}``: the run's ATE against the reference poses;
- ``long_loop_false_closures``: accepted closures off the reference by more than 0.5 m or
  5 deg, summed over these runs; target 0.

``--quick`` scores ACES only, without the gap, on the replay part's quick run of it
(:func:`mission.bench.robustness.replay_run`, one run for both parts): its quick prefix (316
of 440 scans) ends after 30 scans came back to a place left 50 m before, and holds 30 of the
whole log's 51 long-loop revisits (its first long loop comes after 250 scans). Without
``--quick`` all three logs, each whole and with the data gap (the replay part's
clean and ``data_gap`` runs again).
The Duke DP-SLAM log has no reference poses and is skipped with that reason.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from mission.bench import BenchError
from mission.bench.robustness import (
    LASER,
    LOGS,
    quick_scans,
    replay_run,
)
from mission.replay import ReplayResult

__all__ = ["LOOP_M", "QUICK_LOGS", "REVISIT_M", "long_loop_revisits", "run"]

#: A loop this long (metres of travel) or longer is a long loop.
LOOP_M = 100.0
#: A node this close (metres) to an earlier one revisits it.
REVISIT_M = 2.0
QUICK_LOGS: tuple[str, ...] = ("aces",)


def long_loop_revisits(
    reference: NDArray[np.float64],
    closure_nodes: NDArray[np.int64],
    *,
    loop_m: float = LOOP_M,
    revisit_m: float = REVISIT_M,
) -> tuple[int, int]:
    """``(revisiting nodes, of them closed)`` (module docstring): ``reference`` ``(N, 3)`` the
    nodes' reference poses in travel order, ``closure_nodes`` ``(K, 2)`` the node indices of
    the accepted automatic closures."""
    ref = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    travel = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(ref[:, :2], axis=0).T))])
    revisit = np.zeros(len(ref), dtype=bool)
    for i in range(len(ref)):
        earlier = travel <= travel[i] - loop_m
        if earlier.any():
            d = np.hypot(*(ref[earlier, :2] - ref[i, :2]).T)
            revisit[i] = bool((d <= revisit_m).any())
    closed = np.zeros(len(ref), dtype=bool)
    for a, b in np.asarray(closure_nodes, dtype=np.int64).reshape(-1, 2):
        if abs(travel[a] - travel[b]) >= loop_m:
            closed[a] = closed[b] = True
    return int(revisit.sum()), int((revisit & closed).sum())


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    """Replays and metrics (module docstring)."""
    names = QUICK_LOGS if quick else tuple(n for n in LOGS if n != "dpslam_loop5")
    progress("long loops: dpslam_loop5 skipped: no reference poses (raw odometry only)")
    metrics: dict[str, float] = {}
    false_closures = 0
    for name in names:
        path = LASER / LOGS[name]
        if not path.is_file():
            raise BenchError(f"dataset {path} not found (long loops need ../shared/datasets)")
        runs: list[tuple[str, Callable[[], ReplayResult]]] = [
            (
                name,
                functools.partial(replay_run, name, quick_scans(name) if quick else None, "clean"),
            )
        ]
        if not quick:
            runs.append((f"{name}_data_gap", functools.partial(replay_run, name, None, "data_gap")))
        for label, replay in runs:
            t0 = time.perf_counter()
            result = replay()
            if result.reference is None or result.ate is None:
                raise BenchError(f"long loops: {label}: no reference poses to evaluate against")
            revisits, closed = long_loop_revisits(result.reference, result.closure_nodes)
            frac = closed / revisits if revisits else 1.0
            metrics[f"long_loop_revisits_closed_frac_{label}"] = frac
            metrics[f"long_loop_revisits_{label}"] = float(revisits)
            metrics[f"long_loop_ate_m_{label}"] = result.ate.rmse_m
            false_closures += result.false_closures or 0
            odometry = result.ate_odometry.rmse_m if result.ate_odometry else float("nan")
            progress(
                f"long loops {label}: {closed}/{revisits} revisiting nodes closed, "
                f"{result.loop_closures} closures ({result.false_closures} false), ATE "
                f"{result.ate.rmse_m:.3f} m (odometry {odometry:.3f} m), "
                f"{time.perf_counter() - t0:.1f} s"
            )
    metrics["long_loop_false_closures"] = float(false_closures)
    return metrics
