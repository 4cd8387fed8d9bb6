"""``magic replay RUN_DIR``: a whole mission's GCS replayed from its journal (issue 17 item 3).

The run directory's ``journal.sqlite`` (:mod:`gcs.journal`) holds every uplink message the GCS
took, every station step and the operator primitives, in order. :func:`replay_run` feeds them
through a fresh :class:`~gcs.ground_station.GroundStation` and :func:`compare_stations` checks
it against another station: the same nodes and the same edges, poses within ``tol_m``.
``magic replay RUN_DIR`` replays the journal twice, independently, and compares the two (a
journal that does not replay deterministically, e.g. a loop closer bounded by wall time,
shows here), and prints ``replay_pose_diff_max_m``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from gcs.ground_station import GroundStation
from gcs.journal import GcsJournal, JournalError, ReplaySummary, replay_journal
from protocol.cli_parser import CommandParser

__all__ = ["ReplayDiff", "compare_replay", "compare_stations", "main", "replay_run"]

JOURNAL_NAME = "journal.sqlite"


@dataclass(frozen=True)
class ReplayDiff:
    """How two stations differ: node keys equal, edges equal (ends, kind, measurement to
    1e-9), the largest pose difference (m, over common keys; 0 when neither has a pose, inf
    when only one has)."""

    nodes_equal: bool
    edges_equal: bool
    pose_diff_max_m: float
    nodes: int
    edges: int

    def ok(self, tol_m: float = 1e-3) -> bool:
        return self.nodes_equal and self.edges_equal and self.pose_diff_max_m <= tol_m


def _journal_path(run: str | Path) -> Path:
    p = Path(run)
    return p / JOURNAL_NAME if p.is_dir() else p


def replay_run(run: str | Path) -> tuple[GroundStation, ReplaySummary]:
    """A fresh station fed the journal of run directory (or journal file) ``run``."""
    journal = GcsJournal.open(_journal_path(run))
    try:
        station = GroundStation(journal.station_config())
        summary = replay_journal(journal, station)
    finally:
        journal.close()
    return station, summary


def _edges(station: GroundStation) -> list[tuple[int, int | None, str, tuple[float, ...]]]:
    return sorted(
        (
            (e.key_a, e.key_b, e.provenance.name, tuple(np.round(np.asarray(e.z, float), 9)))
            for e in station.graph.edges()
        ),
        key=repr,
    )


def compare_stations(a: GroundStation, b: GroundStation) -> ReplayDiff:
    keys_a, poses_a = a.poses_in_map()
    keys_b, poses_b = b.poses_in_map()
    nodes_equal = bool(np.array_equal(np.sort(keys_a), np.sort(keys_b)))
    edges_a, edges_b = _edges(a), _edges(b)
    common, ia, ib = np.intersect1d(keys_a, keys_b, return_indices=True)
    if len(common):
        diff = float(np.max(np.hypot(*(poses_a[ia, :2] - poses_b[ib, :2]).T)))
    else:  # no pose in common: equal only when both have none
        diff = 0.0 if len(keys_a) == len(keys_b) == 0 else float("inf")
    return ReplayDiff(nodes_equal, edges_a == edges_b, diff, len(keys_a), len(edges_a))


def compare_replay(run: str | Path, live: GroundStation) -> ReplayDiff:
    """The journal of ``run`` replayed through a fresh station, against ``live``."""
    station, _ = replay_run(run)
    return compare_stations(live, station)


def main(argv: list[str]) -> int:
    """``magic replay RUN_DIR [--tol-m M]``: 0 when two replays agree (nodes, edges, poses
    within the tolerance), 1 when they do not, 2 on a missing or damaged journal."""

    p = CommandParser(
        prog="magic replay RUN_DIR",
        description="Replay a mission's GCS journal (RUN_DIR/journal.sqlite) through a fresh "
        "GCS: prints the graph it rebuilds and replay_pose_diff_max_m between two independent "
        "replays (same nodes and edges, poses within --tol-m).",
    )
    p.add_argument("run_dir", metavar="RUN_DIR", help="a run directory (or a journal file)")
    p.add_argument("--tol-m", type=float, default=1e-3, help="pose tolerance (default 0.001 m)")
    args = p.parse_args(argv)
    path = _journal_path(args.run_dir)
    try:
        t0 = time.perf_counter()
        first, summary = replay_run(path)
        wall = time.perf_counter() - t0
        second, _ = replay_run(path)
    except JournalError as err:
        print(f"magic replay: {err}", file=sys.stderr)
        return 2
    diff = compare_stations(first, second)
    counts = ", ".join(f"{k} {v}" for k, v in sorted(summary.records.items()))
    print(
        f"magic replay: {path}: {counts}; up to t={summary.last_time_s:.1f} s in {wall:.2f} s "
        f"wall: nodes {diff.nodes}, edges {diff.edges}, rejected "
        f"{first.stats.rejected_total}, duplicates {first.stats.duplicates}"
    )
    print(f"replay_pose_diff_max_m {diff.pose_diff_max_m:.3g}")
    print(f"replay_nodes_equal {int(diff.nodes_equal)} replay_edges_equal {int(diff.edges_equal)}")
    return 0 if diff.ok(args.tol_m) else 1
