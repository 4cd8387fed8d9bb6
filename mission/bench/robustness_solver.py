"""Robustness of the GCS batch solver (issue 19 item 1): the part of ``magic bench robustness``
that checks that the Pose2 solver reaches the optimum from every start and never gets worse.

Cases: every shipped graph of ``../shared/datasets/posegraph`` (manhattan, manhattan_olson3500,
manhattan_M3500b, intel, city10000; a missing file is skipped, the reason goes to
``progress``) from each start it has: the file's vertices (when the file has them), chained
odometry and the spanning tree (:func:`gcs.graph.g2o.initial_poses`); and constructed cases:

- ``intel_gap``, ``m3500_gap``: intel / manhattan_olson3500 with two odometry edges removed
  (the graph stays connected through loop closures), from the file's vertices and from
  ``initial_poses(graph, "chained")``, which falls back to the spanning tree;
- ``intel_wrapped``: intel from its chained odometry turned by ``pi - 1e-3`` about the first
  vertex (headings straddle the ``+-pi`` cut; the first vertex's prior turns with it, a gauge
  change) with a random multiple of ``2 pi`` (-3..3) added to every angle;
- ``weak_loop``: a synthetic 400-pose ring with 0.1 rad odometry heading noise (about 2 rad of
  drift) closed by one weak loop edge (1 m, 0.3 rad), from chained odometry and the tree: a
  problem with many local minima (the loop's winding), so from chained odometry the solver
  needs its spanning-tree restart.

Metrics:

- ``solver_optimum_frac``: fraction of (case, start) pairs on which :func:`solve_pose2`
  (``"block_lm"``, EMD ordering, default settings: the GCS's batch path) ends within 0.1% of
  the best chi2 GTSAM's Levenberg-Marquardt (default parameters, relative tolerance 1e-6, at
  most 100 iterations) reaches from any start of that case; target 1. In ``--quick`` mode the
  GTSAM reference runs from the spanning-tree start only (the start from which GTSAM LM reaches
  the lowest chi2 on every case here; from chained odometry on manhattan_M3500b it needs ~1000
  iterations, 50 s, to stall at 8235); without ``--quick`` from every start.
- ``solver_worse_steps_accepted``: accepted steps whose chi2 exceeds the chi2 before them,
  counted from every run's own history (both runs when the solver restarts); target 0.
- ``solver_chi2_excess_max``: the largest ``chi2 / best_gtsam_lm - 1`` over the pairs.
- ``solver_restarts``: pairs on which the solver also ran from the spanning tree (its chi2
  test failed: manhattan_M3500b from the file's vertices and from chained odometry, the
  weak-loop ring from chained odometry and from the tree, whose optimum itself fails the test).
- ``{case}_{start}_chi2`` and ``{case}_chi2_gtsam_lm_best`` per case.
- ``m3500_solve_s``: manhattan_olson3500 from chained odometry to the optimum with
  :func:`optimize_pose2` (factor arrays, EMD ordering, the solve, ``gtsam.Values`` out and
  GTSAM's chi2 of them; the default ``"block_lm"``); ``m3500_solve_s_plain_gn`` the same with
  ``"block_gn"`` (plain Gauss-Newton) and ``m3500_solve_s_gtsam_gn`` GTSAM's Gauss-Newton
  (EMD ordering) from the same start; medians of interleaved repeats in the same run;
  ``m3500_solve_ratio_plain_gn`` = ``m3500_solve_s / m3500_solve_s_plain_gn`` (target <= 1.5).

``--quick`` runs every case (city10000 included) in about 10 s on the 2-core machine, the full
run in about 30 s.
"""

from __future__ import annotations

__all__ = ["run"]

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gcs.graph import se2
from gcs.graph.emd_ordering import minimum_degree_ordering
from gcs.graph.g2o import G2oError, G2oGraph, component_roots, initial_poses, read_g2o, to_gtsam
from gcs.graph.optimization import (
    BlockMethod,
    optimize_batch,
    optimize_pose2,
    pose2_factors_from_g2o,
    solve_pose2,
)

DATASETS = Path(__file__).resolve().parents[2] / ".." / "shared" / "datasets" / "posegraph"
SHIPPED = {
    "manhattan": "manhattan.g2o",
    "m3500": "manhattan_olson3500.g2o",
    "m3500b": "manhattan_M3500b.g2o",
    "intel": "intel.g2o",
    "city10k": "city10000.g2o",
}
#: Relative chi2 excess counted as reaching the optimum.
OPTIMUM_TOL = 1e-3


@dataclass(frozen=True)
class Case:
    """A graph and its named starts (poses in ``graph.node_ids`` order); ``reference`` the
    start GTSAM LM runs from in quick mode."""

    name: str
    graph: G2oGraph
    starts: dict[str, np.ndarray]
    reference: str = "tree"


def _standard_starts(g: G2oGraph) -> dict[str, np.ndarray]:
    starts = {}
    if np.array_equal(np.sort(g.vertex_ids), g.node_ids):
        starts["file"] = initial_poses(g, "file").poses
    starts["chained"] = initial_poses(g, "chained").poses
    starts["tree"] = initial_poses(g, "tree").poses
    return starts


def _with_gaps(g: G2oGraph, fractions: tuple[float, ...] = (0.37, 0.71)) -> G2oGraph:
    """``g`` without the odometry edges ``k -> k+1`` nearest ``fractions`` of the chain whose
    removal keeps the graph connected."""
    ids = g.node_ids
    keep = np.ones(len(g.edge_ij), dtype=bool)
    for frac in fractions:
        k0 = int(frac * ids.size)
        for k in range(k0, ids.size - 1):
            hit = np.flatnonzero(
                keep & (g.edge_ij.min(axis=1) == ids[k]) & (g.edge_ij.max(axis=1) == ids[k] + 1)
            )
            if hit.size == 0:
                continue
            trial = keep.copy()
            trial[hit] = False
            cut = G2oGraph(
                g.vertex_ids, g.vertex_poses, g.edge_ij[trial], g.edge_z[trial], g.edge_info[trial]
            )
            if component_roots(cut).size == 1:
                keep = trial
                break
    return G2oGraph(
        vertex_ids=g.vertex_ids,
        vertex_poses=g.vertex_poses,
        edge_ij=g.edge_ij[keep],
        edge_z=g.edge_z[keep],
        edge_info=g.edge_info[keep],
        chi2_offset=g.chi2_offset,
    )


def _wrapped(poses: np.ndarray, seed: int = 19) -> np.ndarray:
    """``poses`` turned by ``pi - 1e-3`` about the first with ``2 pi k`` added to each angle."""
    rng = np.random.default_rng(seed)
    turn = np.array([0.0, 0.0, np.pi - 1e-3])
    first_from_k = se2.between(poses[0], poses)
    out = se2.compose(se2.compose(poses[0], turn), first_from_k)
    out[:, 2] += 2.0 * np.pi * rng.integers(-3, 4, size=len(out))
    return np.asarray(out)


def weak_loop_graph(n: int = 400, seed: int = 1) -> G2oGraph:
    """A ring of ``n`` poses (radius ~ n / 2 pi m) with noisy odometry (0.05 m, 0.1 rad: about
    2 rad of heading drift) and one weak loop closure ``n-1 -> 0`` (sigma 1 m, 0.3 rad). From
    chained odometry plain Gauss-Newton stops at its start (chi2 1.1e5), GTSAM LM in a local
    minimum (5.7e4); from the spanning tree both reach 15.5."""
    rng = np.random.default_rng(seed)
    step = np.array([1.0, 0.0, 2.0 * np.pi / n])
    truth = np.zeros((n, 3))
    for k in range(1, n):
        truth[k] = se2.compose(truth[k - 1], step)
    ij = [(k, k + 1) for k in range(n - 1)] + [(n - 1, 0)]
    sig_odo = np.array([0.05, 0.05, 0.1])
    sig_loop = np.array([1.0, 1.0, 0.3])
    z, info = [], []
    for i, j in ij:
        sig = sig_loop if (i, j) == (n - 1, 0) else sig_odo
        z.append(se2.compose(se2.between(truth[i], truth[j]), rng.normal(0.0, sig)))
        info.append(np.diag(1.0 / sig**2))
    return G2oGraph(
        vertex_ids=np.arange(n, dtype=np.int64),
        vertex_poses=truth,
        edge_ij=np.array(ij, dtype=np.int64),
        edge_z=np.array(z),
        edge_info=np.array(info),
    )


def _cases(progress: Callable[[str], None]) -> list[Case]:
    cases: list[Case] = []
    loaded: dict[str, G2oGraph] = {}
    for name, file in SHIPPED.items():
        path = DATASETS / file
        if not path.is_file():
            progress(f"skipping {name}: {path} not found")
            continue
        try:
            g = read_g2o(path)
        except G2oError as err:
            progress(f"skipping {name}: {err}")
            continue
        loaded[name] = g
        cases.append(Case(name, g, _standard_starts(g)))
    for name in ("intel", "m3500"):
        if name in loaded:
            gap = _with_gaps(loaded[name])
            start = initial_poses(gap, "chained")
            progress(f"{name}_gap: {start.note}")
            cases.append(
                Case(
                    f"{name}_gap",
                    gap,
                    {"file": gap.vertex_poses, "chained": start.poses},
                    reference="chained",  # the spanning tree, by the fallback
                )
            )
    if "intel" in loaded:
        g = loaded["intel"]
        chained = initial_poses(g, "chained").poses
        tree = initial_poses(g, "tree").poses
        cases.append(Case("intel_wrapped", g, {"wrapped": _wrapped(chained), "tree": tree}))
    ring = weak_loop_graph()
    cases.append(
        Case(
            "weak_loop",
            ring,
            {
                "chained": initial_poses(ring, "chained").poses,
                "tree": initial_poses(ring, "tree").poses,
            },
        )
    )
    return cases


def _gtsam_lm_chi2(g: G2oGraph, start: np.ndarray) -> float:
    fg, values = to_gtsam(g, poses=start)
    res = optimize_batch(
        fg, values, method="lm", ordering="colamd", max_iterations=100, relative_error_tol=1e-6
    )
    return res.chi2 + g.chi2_offset


def _worse_steps(history: tuple[float, ...]) -> int:
    return int(np.count_nonzero(np.diff(np.asarray(history)) > 0.0))


def _m3500_timing(g: G2oGraph, repeats: int) -> dict[str, float]:
    start = initial_poses(g, "chained").poses
    fg, values = to_gtsam(g, poses=start)

    def ours(method: BlockMethod) -> Callable[[], float]:
        def go() -> float:
            factors, keys = pose2_factors_from_g2o(g, start)
            return optimize_pose2(
                fg,
                values,
                factors,
                keys,
                method=method,
                ordering="emd",
                initial_poses=start,
            ).chi2

        return go

    def gtsam_gn() -> float:
        return optimize_batch(fg, values, method="gn", ordering="emd").chi2

    runs = {"lm": ours("block_lm"), "plain_gn": ours("block_gn"), "gtsam_gn": gtsam_gn}
    for fn in runs.values():
        fn()  # warm-up (compiled kernels loaded, caches filled)
    samples: dict[str, list[float]] = {k: [] for k in runs}
    for _ in range(repeats):
        for key, fn in runs.items():  # interleaved: a busy spell hits all three alike
            t0 = time.perf_counter()
            fn()
            samples[key].append(time.perf_counter() - t0)
    med = {k: statistics.median(v) for k, v in samples.items()}
    return {
        "m3500_solve_s": med["lm"],
        "m3500_solve_s_plain_gn": med["plain_gn"],
        "m3500_solve_s_gtsam_gn": med["gtsam_gn"],
        "m3500_solve_ratio_plain_gn": med["lm"] / med["plain_gn"],
    }


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    """Run the solver robustness checks; see the module docstring for the metrics."""
    metrics: dict[str, float] = {}
    progress("loading graphs and building starts")
    cases = _cases(progress)
    reached = 0
    pairs = 0
    worse = 0
    restarts = 0
    excess_max = 0.0
    for case in cases:
        g = case.graph
        refs = case.starts if not quick else {case.reference: case.starts[case.reference]}
        progress(f"{case.name}: GTSAM LM from {', '.join(refs)}")
        best = min(_gtsam_lm_chi2(g, s) for s in refs.values())
        metrics[f"{case.name}_chi2_gtsam_lm_best"] = best
        factors0, _ = pose2_factors_from_g2o(g, next(iter(case.starts.values())))
        order, _ = minimum_degree_ordering(factors0.n, factors0.ij)
        progress(f"{case.name}: block_lm from {', '.join(case.starts)}")
        for start_name, start in case.starts.items():
            factors, _ = pose2_factors_from_g2o(g, start)
            sol = solve_pose2(factors, start, order=order)
            chi2 = sol.chi2 + g.chi2_offset
            metrics[f"{case.name}_{start_name}_chi2"] = chi2
            excess = chi2 / best - 1.0
            excess_max = max(excess_max, excess)
            pairs += 1
            reached += int(excess <= OPTIMUM_TOL)
            worse += sum(_worse_steps(h) for _, h in sol.runs)
            restarts += int(len(sol.runs) > 1)
            if excess > OPTIMUM_TOL:
                progress(f"{case.name} from {start_name}: chi2 {chi2:.6g} vs GTSAM LM {best:.6g}")
    metrics["solver_optimum_frac"] = reached / max(pairs, 1)
    metrics["solver_pairs"] = float(pairs)
    metrics["solver_worse_steps_accepted"] = float(worse)
    metrics["solver_chi2_excess_max"] = excess_max
    metrics["solver_restarts"] = float(restarts)
    m3500 = next((c.graph for c in cases if c.name == "m3500"), None)
    if m3500 is None:
        progress("skipping m3500 timings: manhattan_olson3500.g2o not found")
    else:
        progress("m3500 timings: block_lm, plain block_gn, GTSAM GN")
        metrics |= _m3500_timing(m3500, 7 if quick else 21)
    return {k: float(v) for k, v in metrics.items()}
