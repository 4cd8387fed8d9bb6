"""Automatic loop closing at the GCS: candidates, matching on a budget, cycle validation
(paper 4.3.3, 4.5, 6.1).

:class:`LoopCloser` composes the pure pieces around the shared
:class:`~gcs.graph.pose_graph.PoseGraph`:

1. :meth:`LoopCloser.add_scan` stores a node's vertical-surface points (in its ``base``).
2. :meth:`LoopCloser.step`:

   * **candidates** (:mod:`gcs.loops.candidate_search`) for every new scanned node, from the
     Dijkstra projection over the graph's relative edges (bounded by the wide window's
     uncertainty, so its cost stays local). When components merge (a fiducial, an operator
     hint or an accepted closure links robots), the scanned nodes of the merged component
     become sources again, every ``resweep_stride``-th, so that cross-robot pairs are
     generated once robots are linked. Candidates wait in a priority queue (largest expected
     correction first) and a pair is matched at most once until :meth:`LoopCloser.restart`;
   * **matching** (:mod:`gcs.loops.correlative_matcher`) within the call's wall-time budget
     and a token bucket of ``matches_per_s`` on the *progress clock* (below): the new node's
     grid is the reference (its table is cached, LRU), the candidate's points the query, the
     guess the current estimate of ``reference_from_query``. Poorly related pairs get the
     bounded wide window: each costs ``wide_match_cost`` tokens, at most
     ``max_wide_per_step`` per call, and must reach a higher ``wide_min_score``. A match
     reaching ``min_score`` becomes a hypothesis;
   * **validation** (:mod:`gcs.loops.cycle_validation`): hypotheses are promoted only by a
     consistent cycle and never against one; promoted ones become ``LOOP_AUTO`` edges.

   It does not optimize: the caller optimizes after the step.

   **Progress clock.** Message timestamps are not trusted to meter the work: a frozen, coarse,
   jumping or backwards clock would otherwise stop matching after the first burst, or age
   every candidate out at once. The match rate, candidate ageing and hypothesis expiry all run
   on a clock that cannot freeze: ``nominal_s_per_node`` nominal seconds per pose node added
   to the graph (any robot; nodes are made every so many metres or degrees, so this is
   distance travelled). ``now_s`` only stamps the edges (for :meth:`LoopCloser.rewind`).
   **Odometry self-calibration** (in the spirit of the paper's online gyro calibration, 4.2).
   A robot whose odometry misreads its turns (a gyro scale or wheel-base error) makes a graph
   whose odometry is confidently wrong: true closures then fail the graph check and look-alikes
   that agree with the odometry pass. So every same-robot match (before validation) is a
   sample of the robot's turn scale ``s`` (:mod:`gcs.loops.odometry_bias`: the matched heading
   change against the odometry's turning ``T``), counted only when its search window could hold
   the truth; the graph check allows the scale's uncertainty ``(σ_s T)²`` along the chain. A
   fit that differs significantly from the scale in use is fed back into the graph
   (:meth:`PoseGraph.set_odometry_correction`: every odometry edge of the robot re-expressed
   from what it reported, later ones as they come); then the graph is re-solved in batch, the
   closures that contradict the corrected odometry (or the re-solved estimate) are removed
   (``prune_chi2``) and every pair is matched again (:meth:`LoopCloser.restart`).
   **Bent grids.** A node's grid that joins several scans (``grid_window_m``) was joined by
   the reported odometry, so a turn-scale error ``s - 1`` bends it by up to ``(s - 1) W``
   (``W`` the turning within the window: a robot spinning in place). Matches between bent
   grids agree with one another and with the biased odometry, so cycles cannot catch them;
   they are held back until the turn-scale fit bounds the bend below
   ``max_grid_distortion_rad`` (never, for a biased robot's spins; soon, for a true one's).
3. Operator primitives (paper 6.1): :meth:`LoopCloser.suggest` (run the matcher between two
   poses, return pose and score), :meth:`LoopCloser.rewind` (remove automatic closures since
   a time), :meth:`LoopCloser.restart` (forget hypotheses and candidates).

Frames: points in each node's ``base``; ``a_from_b`` between nodes; covariances of edges and
hypotheses in the body frame of ``b`` (GTSAM ``BetweenFactorPose2``); the matcher works in
vector components ``(x, y, yaw)`` of ``a`` and its covariance is rotated accordingly.
"""

from __future__ import annotations

import dataclasses
import functools
import heapq
import math
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

from gcs.graph import se2
from gcs.graph.dijkstra_projection import ProjectionResult, dijkstra_projection
from gcs.graph.graph_mirror import GraphMirror
from gcs.graph.keys import split_key
from gcs.graph.pose_graph import PoseGraph, Provenance
from gcs.loops.candidate_search import (
    Candidate,
    CandidateSearchConfig,
    body_to_vector_covariance,
    search_candidates,
)
from gcs.loops.correlative_matcher import (
    CorrelativeMatcher,
    MatcherConfig,
    MatchResult,
    ReferenceTable,
    points_grid,
)
from gcs.loops.cycle_validation import (
    CycleValidationConfig,
    CycleValidator,
    Hypothesis,
    ValidationResult,
)
from gcs.loops.long_loop_search import LongLoopConfig, LongLoopSearch
from gcs.loops.odometry_bias import (
    OdometryBiasConfig,
    TurnScale,
    debias_odometry,
    estimate_turn_scale,
)

__all__ = [
    "LoopCloser",
    "LoopCloserConfig",
    "LoopCloserStats",
    "LoopClosingReport",
    "vector_to_body_covariance",
]

FloatArray = NDArray[Any]


class LoopCloserConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Everything loop closing runs with (metres, radians, seconds).

    ``matcher`` is the standard window (it must equal ``candidates.window_*``); the wide
    matcher is the same with ``candidates.wide_*``. ``link_sigma_*`` bound the graph paths
    that join hypotheses into cycles; ``path_sigma_xy_m`` bounds the search for the graph's
    own path between a hypothesis's nodes. ``edge_floor_sigma_*`` are added to a promoted
    edge's covariance (a response surface can be overconfident). A match whose translation
    standard deviation exceeds ``max_match_sigma_xy_m`` (an ambiguous, corridor-like view;
    the matcher's outer response surface measures it), or whose heading standard deviation
    exceeds ``max_match_sigma_yaw_rad`` (2.5 deg: a view whose overlap fixes its heading
    loosely; Freiburg 079's matches between nodes 241 and 247 came out 5.1 deg off at a
    sigma of 3 deg), constrains too little to be a closure and is dropped. Nearly every false
    closure of session 15's quick and full journals stated 0.18-0.25 m; 0.2 m measured in
    :class:`~gcs.loops.cycle_validation.CycleValidationConfig` (``graph_offset_m``): fewer
    false closures, fewer closures, seed 7's F1 lower; 0.25 kept.

    ``odometry_bias`` configures the odometry self-calibration (module docstring): after a
    correction, automatic closures whose heading contradicts the corrected odometry
    (``prune_heading_chi2``, 1 dof) or whose residual at the re-solved estimate exceeds
    ``prune_chi2`` (3 dof) are removed, and the latest
    ``max_rejected_kept`` hypotheses the graph check rejected are checked again.

    ``grid_window_m``: how much of the robot's travel each node's grid spans (0: one sweep, as
    the project's robots send; a logger with a 180-degree laser joins its last metres of scans,
    e.g. the replay's 2 m), and ``grid_window_rad`` how much turning at most (the scans go back
    no further than the odometry turned this much; inf: unbounded). Those scans were joined by
    the odometry the robot reported, so a turn-scale error bends the grid; a match whose grids'
    bend exceeds ``max_grid_distortion_rad`` (5 deg: a closure off by more is false) waits for a
    tighter turn-scale fit (at most ``max_deferred_kept``), and an admitted one carries the bend
    in its heading variance (:meth:`LoopCloser._grid_distortion_rad`).

    Look-alikes. With ``matcher.runner_up_radius_m`` > 0, a match whose window holds another
    place that the query fits nearly as well (:attr:`MatchResult.runner_up_score`: at least
    ``matcher.runner_up_ratio`` of the best score, that far or farther from it) is no closure
    (counted in ``look_alikes``). Off by default: measured at 1 m / 0.85 it rejected the true
    matches of corridors, whose look-alikes lie a door further on. Every window: Freiburg 079
    quick clean 63 -> 31 closures, ATE 0.110 -> 0.278 m; whole, noise seed 1, false closures
    clean 4 -> 6, gap 5 -> 7 (ATE 0.160 -> 0.211, 0.330 -> 0.373 m); seed 2 gap 6 -> 1 (0.338
    -> 0.305 m). Wide windows only (where little is known: across a gap, a loose hint): the
    same Freiburg 079 quick clean, 44 closures, ATE 0.278 m (the wide match that closes its
    loop has a look-alike). The look-alike it was meant for still came in: scans 1519-1526
    against 1189-1195, 1.3 m off, opposite-facing 180-degree views whose true alignment scores
    0.22-0.33 on the raw scans and a place 1.3 m on 0.5-0.69.
    ``look_alike_radius_m`` > 0 narrows the rule to look-alikes the graph cannot rule out
    (Olson 2009's ambiguity test against the prior, paper 4.3.3): the runner-up search (that
    radius, ``matcher.runner_up_ratio``) runs only when the candidate's prior (its Dijkstra
    projection) is loose enough to hold a place that far within ``look_alike_chi2`` (3 dof),
    and a runner-up counts only within ``look_alike_chi2`` of the guess. Off by default:
    at 1 m, on the full mission's journal (magic_phase, first 720 s, fiducial heading bound
    on) false closures 6 -> 4 but ATE 0.41 -> 0.50 m (true closures 1566 -> 1493); small
    world journals, seed 7: false 3 -> 1, ATE 0.430 -> 0.424 m; seed 0: unchanged.
    ``look_alike_cycle_radius_m`` > 0 keeps the look-alike instead of refusing the match: the
    runner-up search runs on every match (that radius, ``matcher.runner_up_ratio``) and a
    runner-up found goes with the hypothesis (:attr:`Hypothesis.look_alike`, counted in
    ``look_alikes``), for its cycles to tell which of the two places they agree with
    (:mod:`gcs.loops.cycle_validation`, "Look-alikes"). It excludes the two rules above. Off by
    default. Measured at 0.5 m (session 16, replaying the GCS journals of HEAD 1d6eb73's quick
    missions, seeds 0/1/2/3/7/11 and 4/5/6): false closures 5 -> 2 (seed 11 3 -> 1, seeds 4 and
    6 1 -> 0, seed 7 0 -> 1: a corridor pair 0.506 m off), ATE 0.459/0.119/0.091/0.113/0.184/
    0.222/0.067/0.200/0.280 -> 0.455/0.118/0.089/0.123/0.207/0.221/0.108/0.179/0.275 m (median
    0.184 -> 0.179), F1 lower on seeds 7/11/4/6 by 0.02-0.05 (the aligned F1 within +-0.03).
    But the full mission's journal (magic_phase, 600 s, seed 0, /tmp/team/relay16/full_head):
    false closures 5 -> 6, ATE 2.02 -> 8.94 m: held-back closures let three long-loop matches
    between robots 8 and 9 in at 537 s, turned by 180 deg and 68-70 m off, that agreed with
    one another (the same with ``validation.look_alike_margin`` 0.5 and with 0.6 m).

    ``wide_min_points`` (0: off): a wide candidate whose scans hold fewer points than that (either
    one) is not matched (counted in ``wide_too_few_points``): a few points fit somewhere in a
    wide window, at a high score. The full mission's journal at 1d6eb73 (magic_phase, 600 s)
    took two closures 2.5 m and 21-23 deg off from robot 10's node 225 (41 points, wide,
    scores 0.93-0.95) to robot 0's nodes 30 and 31, confirmed by their one cycle with each
    other (chi-square 1.0). 50 since session 16 (true wide closures with fewer: 1 of 116 in
    that journal, 2 of 101 in seed 7's, none in seven other quick journals). That journal
    replayed: those two gone, false closures 5 -> 5 (three new, 0.50-0.77 m off, one of them
    42 points in the standard window), ATE 2.02 -> 1.23 m, F1 0.392 -> 0.454 (aligned 0.394
    -> 0.510). Nine quick journals replayed: only seed 7's changed (ATE 0.184 -> 0.167 m, F1
    0.739 -> 0.872). Live quick missions against 1d6eb73, seeds 0/7/3/11: false closures
    0/0/0/3 -> 0/0/0/0, ATE 0.459/0.184/0.113/0.222 -> 0.387/0.161/0.094/0.185 m (median
    0.203 -> 0.173), F1 0.697/0.739/0.924/0.828 -> 0.716/0.876/0.943/0.833 (median 0.783 ->
    0.854; aligned 0.903 -> 0.904), explored median 0.933 -> 0.928, and seed 0 lost robot 2 to
    a hostile's blast at 224 s. Seeds 1/2 (whose journals replay identically with it): ATE
    0.119/0.091 -> 0.145/0.192 m, F1 0.835/0.945 -> 0.942/0.721, explored 0.897/0.868 ->
    0.885/0.928: the missions took other paths. Over the six, medians: ATE 0.151 -> 0.173 m,
    F1 0.832 -> 0.854 (aligned 0.934 -> 0.930), explored 0.909 -> 0.925, false closures 3 -> 0.
    ``magic bench robustness --quick``: every run as before (no wide candidate of the logs has
    so few points). The whole-log bench (``magic bench robustness``, 1d6eb73 -> 0ed3d89):
    every run as before but whole Freiburg 079 clean, 885 -> 864 closures, false 8 -> 15, ATE
    0.118 -> 0.132 m (its perturbed runs unchanged, so ``false_closures`` 47 -> 54 and
    ``long_loop_false_closures`` 14 -> 21, both counting that run; ``perturbed_ate_ratio_max``
    5.85 either way).

    ``matches_per_s``, ``candidate_max_age_s`` and ``validation.expiry_s`` are in nominal
    seconds of the progress clock: ``nominal_s_per_node`` per pose node added (module
    docstring), never message time.
    """

    resolution_m: float = 0.1
    matcher: MatcherConfig = msgspec.field(
        default_factory=lambda: MatcherConfig(response_outer_radius=10)
    )
    candidates: CandidateSearchConfig = msgspec.field(default_factory=CandidateSearchConfig)
    validation: CycleValidationConfig = msgspec.field(default_factory=CycleValidationConfig)
    odometry_bias: OdometryBiasConfig = msgspec.field(default_factory=OdometryBiasConfig)
    prune_chi2: float = 16.27
    prune_heading_chi2: float = 6.63
    max_rejected_kept: int = 200
    max_deferred_kept: int = 400
    min_score: float = 0.5
    max_match_sigma_xy_m: float = 0.25
    max_match_sigma_yaw_rad: float = math.radians(2.5)
    wide_min_score: float = 0.6
    matches_per_s: float = 500.0
    max_burst_matches: int = 200
    max_wide_per_step: int = 20
    wide_match_cost: float = 4.0
    max_queue: int = 5000
    candidate_max_age_s: float = 30.0
    nominal_s_per_node: float = 1.0
    resweep_stride: int = 3
    table_cache: int = 48
    wide_table_cache: int = 8
    link_sigma_xy_m: float = 0.5
    link_sigma_yaw_rad: float = 0.1
    path_sigma_xy_m: float = 10.0
    edge_floor_sigma_xy_m: float = 0.02
    edge_floor_sigma_yaw_rad: float = math.radians(0.5)
    min_scan_points: int = 20
    wide_min_points: int = 50
    grid_window_m: float = 0.0
    grid_window_rad: float = math.inf
    max_turn_scale_yaw_rad: float = math.radians(20.0)
    max_grid_distortion_rad: float = math.radians(5.0)
    look_alike_radius_m: float = 0.0
    look_alike_chi2: float = 11.34
    look_alike_cycle_radius_m: float = 0.0
    # long-loop candidate source (gcs.loops.long_loop_search, issue 19 item 5)
    long_loops: LongLoopConfig = msgspec.field(default_factory=LongLoopConfig)

    def __post_init__(self) -> None:
        if self.long_loops.enabled and self.validation.min_cycle_hypotheses < 2:
            raise ValueError("long_loops needs validation.min_cycle_hypotheses >= 2")
        m, c = self.matcher, self.candidates
        if not math.isclose(m.search_xy_m, c.window_xy_m) or not math.isclose(
            m.search_yaw_rad, c.window_yaw_rad
        ):
            raise ValueError(
                "matcher.search_xy_m / search_yaw_rad must equal candidates.window_xy_m / "
                f"window_yaw_rad, got ({m.search_xy_m}, {m.search_yaw_rad}) and "
                f"({c.window_xy_m}, {c.window_yaw_rad})"
            )
        if not (0 < self.resolution_m <= 1 and math.isfinite(self.resolution_m)):
            raise ValueError(f"resolution_m: expected in (0, 1], got {self.resolution_m}")
        for name in ("min_score", "wide_min_score"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name}: expected in [0, 1], got {getattr(self, name)}")
        for name in (
            "matches_per_s",
            "candidate_max_age_s",
            "nominal_s_per_node",
            "link_sigma_xy_m",
            "link_sigma_yaw_rad",
            "path_sigma_xy_m",
            "max_match_sigma_xy_m",
            "max_match_sigma_yaw_rad",
            "prune_chi2",
            "prune_heading_chi2",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v}")
        if not (math.isfinite(self.wide_match_cost) and self.wide_match_cost >= 1):
            raise ValueError(f"wide_match_cost: expected >= 1, got {self.wide_match_cost}")
        for name in (
            "max_burst_matches",
            "max_queue",
            "resweep_stride",
            "table_cache",
            "wide_table_cache",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if not (math.isfinite(self.grid_window_m) and self.grid_window_m >= 0):
            raise ValueError(f"grid_window_m: expected >= 0, got {self.grid_window_m}")
        if not (math.isfinite(self.max_turn_scale_yaw_rad) and self.max_turn_scale_yaw_rad >= 0):
            raise ValueError(
                f"max_turn_scale_yaw_rad: expected >= 0, got {self.max_turn_scale_yaw_rad}"
            )
        if not self.grid_window_rad > 0:  # inf: the grids' turning is not bounded
            raise ValueError(f"grid_window_rad: expected > 0, got {self.grid_window_rad}")
        if not (math.isfinite(self.max_grid_distortion_rad) and self.max_grid_distortion_rad > 0):
            raise ValueError(
                f"max_grid_distortion_rad: expected > 0, got {self.max_grid_distortion_rad}"
            )
        if self.max_rejected_kept < 0 or self.max_deferred_kept < 0:
            raise ValueError("max_rejected_kept and max_deferred_kept must be >= 0")
        if self.wide_min_points < 0:
            raise ValueError(f"wide_min_points: expected >= 0, got {self.wide_min_points}")
        if self.max_wide_per_step < 0 or self.min_scan_points < 1:
            raise ValueError("need max_wide_per_step >= 0 and min_scan_points >= 1")
        if not (math.isfinite(self.look_alike_radius_m) and self.look_alike_radius_m >= 0):
            raise ValueError(f"look_alike_radius_m: expected >= 0, got {self.look_alike_radius_m}")
        if not (
            math.isfinite(self.look_alike_cycle_radius_m) and self.look_alike_cycle_radius_m >= 0
        ):
            raise ValueError(
                f"look_alike_cycle_radius_m: expected >= 0, got {self.look_alike_cycle_radius_m}"
            )
        if self.look_alike_cycle_radius_m > 0 and (
            self.look_alike_radius_m > 0 or self.matcher.runner_up_radius_m > 0
        ):
            raise ValueError(
                "look_alike_cycle_radius_m excludes look_alike_radius_m and "
                "matcher.runner_up_radius_m (a look-alike is either refused or kept for the "
                "cycles to judge)"
            )
        if not (math.isfinite(self.look_alike_chi2) and self.look_alike_chi2 > 0):
            raise ValueError(f"look_alike_chi2: expected > 0, got {self.look_alike_chi2}")
        if not (self.edge_floor_sigma_xy_m >= 0 and self.edge_floor_sigma_yaw_rad >= 0):
            raise ValueError("edge covariance floors must be >= 0")


@dataclass
class LoopCloserStats:
    """Counters since construction (never reset, not even by :meth:`LoopCloser.restart`)."""

    scans: int = 0
    scans_too_small: int = 0
    candidates: int = 0
    matches: int = 0
    wide_matches: int = 0
    below_min_score: int = 0
    ambiguous: int = 0
    hypotheses: int = 0
    accepted: int = 0
    rejected_by_cycle: int = 0
    expired: int = 0
    stale_candidates: int = 0
    dropped_candidates: int = 0
    odometry_recalibrations: int = 0
    closures_pruned: int = 0
    distorted: int = 0
    look_alikes: int = 0
    wide_too_few_points: int = 0


@dataclass
class LoopClosingReport:
    """What one :meth:`LoopCloser.step` did: matches run, hypotheses made, edge ids added,
    hypotheses rejected by a cycle or expired, candidates still queued, time spent and whether
    the budget (time or matches) ran out before the queue did."""

    matches: int = 0
    hypotheses: int = 0
    accepted_edge_ids: list[int] = field(default_factory=list)
    rejected: int = 0
    expired: int = 0
    queued: int = 0
    elapsed_s: float = 0.0
    budget_exhausted: bool = False
    validation: ValidationResult | None = None
    recalibrated_robots: list[int] = field(default_factory=list)
    pruned_edge_ids: list[int] = field(default_factory=list)


def vector_to_body_covariance(pose: FloatArray, cov_xyt: FloatArray) -> FloatArray:
    """Inverse of :func:`~gcs.loops.candidate_search.body_to_vector_covariance`."""
    p = np.asarray(pose, dtype=np.float64).copy()
    p[..., 2] = -p[..., 2]
    return body_to_vector_covariance(p, cov_xyt)


class LoopCloser:
    """Automatic loop closing over a shared pose graph (module docstring)."""

    def __init__(self, graph: PoseGraph, config: LoopCloserConfig | None = None) -> None:
        self.graph = graph
        self.config = config or LoopCloserConfig()
        cfg = self.config
        self._matcher = CorrelativeMatcher(cfg.matcher)
        self._matchers: dict[tuple[bool, float], CorrelativeMatcher] = {}
        self._wide = self._matcher_for(True, cfg.candidates.wide_yaw_rad)
        self._validator = CycleValidator(cfg.validation)
        self.stats = LoopCloserStats()
        self._scans: dict[int, FloatArray] = {}
        self._tables: OrderedDict[tuple[int, bool], ReferenceTable] = OrderedDict()
        self._sources: list[int] = []  # nodes whose candidates are to be generated
        self._queue: list[tuple[float, int, float, Candidate]] = []
        self._seq = 0
        self._tried: set[tuple[int, int]] = set()
        self._next_hyp = 0
        self._tokens = float(cfg.max_burst_matches)
        self._progress_s = 0.0  # the progress clock (module docstring)
        self._nodes_seen = 0
        # the graph's poses and relative edges as arrays, extended by what each step added
        # (gcs.graph.graph_mirror, issue 16); stale after this closer changed the graph
        # itself, until the next step syncs it (as a rebuilt copy was before)
        self._mirror = GraphMirror()
        self._stale = True
        self._groups: frozenset[frozenset[int]] | None = None
        self._links: dict[int, dict[int, tuple[FloatArray, FloatArray]]] = {}
        self._has_scan_cache: tuple[tuple[int, int], NDArray[np.bool_]] | None = None
        # odometry self-calibration (module docstring): per robot, same-robot matches
        # {(key_a, key_b): (yaw of a_from_b, its variance)}, the last fit and the one in use
        self._bias_samples: dict[int, dict[tuple[int, int], tuple[float, ...]]] = {}
        self._bias_fitted_at: dict[int, int] = {}
        self._bias_applied_at: dict[int, int] = {}
        self._turn_scales: dict[int, TurnScale] = {}
        self._applied_scales: dict[int, TurnScale] = {}
        self._chains: dict[
            int, tuple[int, tuple[int, FloatArray, FloatArray, FloatArray] | None]
        ] = {}
        self._rejected: dict[int, Hypothesis] = {}  # by the graph check, latest last
        self._restarted_at: dict[int, TurnScale] = {}  # per robot: the scale of the last restart
        self._deferred: dict[int, Hypothesis] = {}  # matches on grids bent too far (_admit)
        self._bend_var: dict[int, float] = {}  # hypothesis -> bend variance added (_admit)
        self._closure_bend_var: dict[int, float] = {}  # closure edge -> the same
        self.long_loops = (
            LongLoopSearch(cfg.long_loops, matcher=cfg.matcher, resolution_m=cfg.resolution_m)
            if cfg.long_loops.enabled
            else None
        )

    # ---- input -----------------------------------------------------------------------------

    def add_scan(self, key: int, points_in_base: FloatArray) -> None:
        """Store node ``key``'s vertical-surface points ``(N, 2)`` (metres, its ``base``).

        The node must already be in the graph. A scan with fewer than ``min_scan_points`` is
        counted and ignored (nothing to match); a second scan of a node replaces the first.
        Raises ``ValueError`` naming the node for an unknown key or malformed points.
        """
        try:
            robot, index = split_key(key)
        except ValueError as exc:
            raise ValueError(f"add_scan: {exc}") from None
        try:
            self.graph.pose(key)
        except ValueError:
            raise ValueError(f"add_scan: robot {robot} pose {index} is not in the graph") from None
        pts = np.asarray(points_in_base, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(
                f"add_scan: robot {robot} pose {index}: points must be (N, 2), got {pts.shape}"
            )
        if not np.all(np.isfinite(pts)):
            raise ValueError(f"add_scan: robot {robot} pose {index}: non-finite points")
        if len(pts) < self.config.min_scan_points:
            self.stats.scans_too_small += 1
            return
        self.stats.scans += 1
        self._scans[int(key)] = np.ascontiguousarray(pts)
        for wide in (False, True):
            self._tables.pop((int(key), wide), None)
        self._sources.append(int(key))

    @property
    def scanned_keys(self) -> list[int]:
        """Keys of the nodes with a stored scan."""
        return sorted(self._scans)

    @property
    def pending_hypotheses(self) -> list[Hypothesis]:
        """Hypotheses waiting for a cycle."""
        return self._validator.pending

    @property
    def queued_candidates(self) -> int:
        return len(self._queue)

    @property
    def turn_scales(self) -> dict[int, TurnScale]:
        """Per robot, the latest odometry turn-scale fit (:mod:`gcs.loops.odometry_bias`)."""
        return dict(self._turn_scales)

    @property
    def applied_turn_scales(self) -> dict[int, TurnScale]:
        """Per robot, the turn-scale estimate the graph's odometry edges use now."""
        return dict(self._applied_scales)

    @property
    def progress_s(self) -> float:
        """The progress clock (nominal seconds: ``nominal_s_per_node`` per node added)."""
        return self._progress_s

    # ---- the step --------------------------------------------------------------------------

    def step(self, *, now_s: float, budget_s: float) -> LoopClosingReport:
        """Candidates, matching within ``budget_s`` (wall seconds) and the match rate,
        cycle validation; promoted hypotheses are added to the graph (``LOOP_AUTO``, stamped
        ``now_s``). Does not optimize.

        ``now_s`` only stamps edges: how many matches run, which candidates age out and which
        hypotheses expire depend on the progress clock (nodes added), so a frozen, coarse,
        jumping or backwards ``now_s`` changes none of it. The budget bounds candidate
        generation and matching (checked between items, so one match may overrun it);
        validation runs every call, its cost bounded by its own caps
        (:class:`~gcs.loops.cycle_validation.CycleValidationConfig`)."""
        if not math.isfinite(now_s):
            raise ValueError(f"step: now_s must be finite, got {now_s}")
        if not budget_s >= 0:
            raise ValueError(f"step: budget_s must be >= 0, got {budget_s}")
        cfg = self.config
        t0 = time.perf_counter()
        deadline = t0 + budget_s
        report = LoopClosingReport()
        mirror = self._sync()
        progress_s = self._advance(len(mirror.keys))
        self._resweep_on_merge()
        # candidate generation (cheap: bounded projections) for the waiting sources
        while self._sources and time.perf_counter() < deadline:
            self._generate(self._sources.pop(0), mirror, progress_s)
        report.budget_exhausted = bool(self._sources)
        # matching, highest priority first
        wide_left = cfg.max_wide_per_step
        deferred: list[tuple[float, int, float, Candidate]] = []
        while self._queue:
            if time.perf_counter() >= deadline or self._tokens < 1.0:
                report.budget_exhausted = True
                break
            item = heapq.heappop(self._queue)
            _, _, created_s, cand = item
            if progress_s - created_s > cfg.candidate_max_age_s:
                self.stats.stale_candidates += 1
                continue
            cost = cfg.wide_match_cost if cand.wide else 1.0
            if cand.wide and (wide_left <= 0 or self._tokens < cost):
                deferred.append(item)
                continue
            wide_left -= cand.wide
            self._tokens -= cost
            hyp = self._match(cand, progress_s)
            report.matches += 1
            if hyp is not None:
                self._validator.add(hyp)
                report.hypotheses += 1
        for item in deferred:
            heapq.heappush(self._queue, item)
        # validation and promotion
        result = self._validator.validate(
            now_s=progress_s, links=self._links_of, path=self._path, revision=mirror.version
        )
        report.validation = result
        for h in result.rejected:  # kept a while: a recalibration may vindicate them
            self._rejected[h.hyp_id] = h
        while len(self._rejected) > self.config.max_rejected_kept:
            self._rejected.pop(next(iter(self._rejected)))
        for h in result.accepted:
            eid = self.graph.add_edge(
                h.key_a,
                h.key_b,
                a_from_b=h.a_from_b,
                covariance=h.covariance,
                provenance=Provenance.LOOP_AUTO,
                time_s=now_s,
            )
            bend_var = self._bend_var.pop(h.hyp_id, 0.0)
            if bend_var > 0.0:
                self._closure_bend_var[eid] = bend_var
            report.accepted_edge_ids.append(eid)
        report.rejected = len(result.rejected)
        report.expired = len(result.expired)
        self.stats.accepted += len(result.accepted)
        self.stats.rejected_by_cycle += len(result.rejected)
        self.stats.expired += len(result.expired)
        self._calibrate_odometry(report)
        report.queued = len(self._queue)
        report.elapsed_s = time.perf_counter() - t0
        return report

    # ---- operator primitives (paper 6.1) ---------------------------------------------------

    def suggest(
        self,
        key_a: int,
        key_b: int,
        b_in_a_guess: FloatArray | None = None,
        *,
        wide: bool | None = None,
    ) -> MatchResult:
        """Run the matcher between two poses and return ``a_from_b``, covariance and score
        (does not add an edge). The guess defaults to the current estimates when both poses
        are in one component (else a guess is required); ``wide`` (default: when the poses
        are in different components or a guess is given) searches the wide window."""
        for k in (key_a, key_b):
            if k not in self._scans:
                r, i = split_key(k)
                raise ValueError(f"suggest: robot {r} pose {i} has no scan to match")
        comps = self.graph.components()
        if b_in_a_guess is None:
            if comps[key_a] != comps[key_b]:
                raise ValueError(
                    "suggest: the two poses are in different components; give b_in_a_guess"
                )
            guess = se2.between(self.graph.pose(key_a), self.graph.pose(key_b))
        else:
            guess = np.asarray(b_in_a_guess, dtype=np.float64)
            if guess.shape != (3,) or not np.all(np.isfinite(guess)):
                raise ValueError(f"suggest: b_in_a_guess must be a finite pose (3,), got {guess}")
        use_wide = (
            (b_in_a_guess is not None or comps[key_a] != comps[key_b]) if wide is None else wide
        )
        matcher = self._wide if use_wide else self._matcher
        table = self._table(key_a, use_wide)
        result = matcher.match(table, self._scans[key_b], guess)
        assert result is not None  # min_score 0: the best transform always exists
        return result

    def operator_edge(self, key_a: int, key_b: int, result: MatchResult, *, time_s: float) -> int:
        """Add a suggested match the operator accepted as a ``LOOP_OPERATOR`` edge."""
        cov = self._edge_covariance(result)
        return self.graph.add_edge(
            key_a,
            key_b,
            a_from_b=result.a_from_b,
            covariance=cov,
            provenance=Provenance.LOOP_OPERATOR,
            time_s=time_s,
        )

    def propose(self, key_a: int, key_b: int, result: MatchResult, *, time_s: float) -> int:
        """Add a match (e.g. an operator's :meth:`suggest`) as a hypothesis: it becomes an
        edge only through cycle validation, like the automatic ones. Returns its id.
        ``time_s`` is kept for the caller's records; the hypothesis ages on the progress
        clock like the automatic ones."""
        for k in (key_a, key_b):
            self.graph.pose(k)  # raises naming an unknown pose
        self._advance(len(self.graph.nodes()))
        self._next_hyp += 1
        self._validator.add(
            Hypothesis(
                hyp_id=self._next_hyp,
                key_a=int(key_a),
                key_b=int(key_b),
                a_from_b=np.asarray(result.a_from_b, dtype=np.float64),
                covariance=self._edge_covariance(result),
                score=result.normalized_score,
                time_s=self._progress_s,
            )
        )
        del time_s
        self.stats.hypotheses += 1
        return self._next_hyp

    def rewind(self, since_s: float) -> int:
        """Remove the automatic closures added after ``since_s`` and drop every hypothesis;
        returns how many edges were removed. Optimize next."""
        removed = self.graph.rewind(since_s)
        self._validator.clear()
        self._stale = True
        self._links.clear()
        return len(removed)

    def graph_simplified(self) -> None:
        """The graph was simplified (Algorithm 1, paper 4.7): its kept closures were
        re-expressed at the estimate and parallel ones merged, so the per-closure grid-bend
        variances no longer describe them (a later turn-scale fit leaves them as they are:
        re-bending a merged closure could drive its heading variance below zero) and cached
        graph paths may run over edges merged away."""
        self._closure_bend_var.clear()
        self._stale = True
        self._links.clear()

    def restart(self) -> None:
        """Forget hypotheses, queued candidates and the pairs already tried (so every pair may
        be matched again, against the new prior); accepted edges stay."""
        self._validator.clear()
        self._deferred.clear()
        self._queue.clear()
        self._tried.clear()
        self._sources = sorted(self._scans)
        self._stale = True
        self._links.clear()
        self._groups = None

    # ---- internals -------------------------------------------------------------------------

    def _advance(self, n_nodes: int) -> float:
        """Move the progress clock to ``n_nodes`` nodes (never back) and refill the tokens."""
        cfg = self.config
        added = n_nodes - self._nodes_seen
        if added > 0:  # nodes are never removed; a smaller count adds nothing
            self._nodes_seen = n_nodes
            elapsed = added * cfg.nominal_s_per_node
            self._progress_s += elapsed
            self._tokens = min(
                float(cfg.max_burst_matches), self._tokens + cfg.matches_per_s * elapsed
            )
        return self._progress_s

    def _sync(self) -> GraphMirror:
        """The graph's relative edges as arrays: extended by what was added since the last
        step, rebuilt whole only after another change (:class:`GraphMirror`); the cached
        links are dropped whenever anything changed."""
        if self._mirror.update(self.graph) or self._stale:
            self._links.clear()
        self._stale = False
        return self._mirror

    def _resweep_on_merge(self) -> None:
        """When robots' components merged, regenerate candidates from the merged robots'
        scanned nodes (every ``resweep_stride``-th) so pairs across them appear."""
        comps = self.graph.components()
        by_label: dict[int, set[int]] = {}
        for robot in self.graph.robots:
            by_label.setdefault(comps[self.graph.last_key(robot)], set()).add(robot)
        groups = frozenset(frozenset(g) for g in by_label.values())
        previous = self._groups
        self._groups = groups
        if previous is None:
            return
        merged: set[int] = set()
        for g in groups:
            if not any(g <= old for old in previous) and len(g) > 1:
                merged |= g
        if not merged:
            return
        per_robot: dict[int, int] = {}
        queued = set(self._sources)
        for key in sorted(self._scans):
            robot = split_key(key)[0]
            if robot not in merged:
                continue
            k = per_robot.get(robot, 0)
            per_robot[robot] = k + 1
            if k % self.config.resweep_stride == 0 and key not in queued:
                self._sources.append(key)

    def _projection(
        self, key: int, *, max_trace: float, target: int | None = None
    ) -> ProjectionResult:
        m = self._mirror
        return dijkstra_projection(
            m.adjacency,
            m.index[key],
            target=None if target is None else m.index[target],
            max_trace=max_trace,
        )

    def _generate(self, key: int, mirror: GraphMirror, progress_s: float) -> None:
        if key not in self._scans or key not in mirror.index:
            return
        c = self.config.candidates
        sxy = c.wide_xy_m / c.k_sigma
        syaw = c.wide_yaw_rad / c.k_sigma
        proj = self._projection(key, max_trace=2 * sxy**2 + syaw**2)
        has_scan = self._has_scan(mirror)
        found = search_candidates(
            key,
            keys=mirror.keys,
            robot_ids=mirror.robot_ids,
            indices=mirror.indices,
            has_scan=has_scan,
            poses=proj.poses,
            covariances=self._with_turn_scale_error(key, mirror, proj.covariances),
            config=c,
        )
        for cand in found:
            pair = (
                min(cand.reference_key, cand.query_key),
                max(cand.reference_key, cand.query_key),
            )
            if pair in self._tried:
                continue
            self._tried.add(pair)
            self.stats.candidates += 1
            self._seq += 1
            heapq.heappush(self._queue, (-cand.priority, self._seq, progress_s, cand))
        while len(self._queue) > self.config.max_queue:
            # drop the lowest priority (largest key): rebuild without it
            worst = max(self._queue)
            self._queue.remove(worst)
            heapq.heapify(self._queue)
            self.stats.dropped_candidates += 1
        # ---- long-loop candidate source (gcs.loops.long_loop_search, issue 19 item 5) ----
        if self.long_loops is not None:
            self._propose_long_loops(key, mirror, progress_s)

    def _with_turn_scale_error(
        self, key: int, mirror: GraphMirror, covariances: FloatArray
    ) -> FloatArray:
        """The projection's covariances with the robot's turn-scale error along its own chain
        added to the yaw of its nodes: ``(e T)^2`` for the odometry's turning ``T`` from
        ``key``, ``e`` what is known of the scale error (:meth:`_turn_scale_error`). The
        odometry's stated sigmas do not hold a scale error, so without it a biased robot's
        windows miss the truth after long turns: its matches return look-alikes near the
        guess, and the fit that would remove the bias starves (Intel with turns scaled by
        1.08: 4 closures and no fit). At most ``max_turn_scale_yaw_rad`` (a yaw sigma of 20
        deg, windows of 60 deg): wider windows over a symmetric hall took its look-alikes,
        turned by 90 or 180 deg, and fitted a scale of 1.30 to an unbiased robot."""
        robot = split_key(key)[0]
        chain = self._chain(robot)
        if chain is None:
            return covariances
        first, turn, _var, _dist = chain
        i = key - first
        if not 0 <= i < len(turn):
            return covariances
        rows = mirror.keys - first
        ok = (mirror.robot_ids == robot) & (rows >= 0) & (rows < len(turn))
        ok &= np.isfinite(covariances[:, 2, 2])
        if not ok.any():
            return covariances
        err = self._turn_scale_error(robot)
        out = np.array(covariances, copy=True)
        sd = np.minimum(err * np.abs(turn[rows[ok]] - turn[i]), self.config.max_turn_scale_yaw_rad)
        out[ok, 2, 2] += sd**2
        return out

    def _turn_scale_error(self, robot: int) -> float:
        """How far the robot's turn scale may be from the one its graph odometry uses: before
        any fit the prior's ``prior_sigma``; after one, the fit's distance from the scale in
        use (1 until a correction is applied) with its statistical standard deviation (as
        :meth:`_grid_distortion_rad`: the single-closure floor widened the synthetic city's
        windows by 3 x 1.5 % of two laps' turning, and look-alike streets came in)."""
        fit = self._turn_scales.get(robot)
        applied = self._applied_scales.get(robot)
        if fit is None:
            return applied.sigma if applied is not None else self.config.odometry_bias.prior_sigma
        ref = applied.scale if applied is not None else 1.0
        spread = fit.sigma if fit.statistical_sigma is None else fit.statistical_sigma
        return math.hypot(fit.scale - ref, spread)

    def _propose_long_loops(self, key: int, mirror: GraphMirror, progress_s: float) -> None:
        """Place-recognition matches of ``key`` become hypotheses like any other: they reach
        the graph only through a consistent cycle (min_cycle_hypotheses >= 2)."""
        assert self.long_loops is not None
        c = self.config.candidates
        found = self.long_loops.propose(
            key,
            scans=self._scans,
            keys=mirror.keys,
            index_of=mirror.index,
            robot_ids=mirror.robot_ids,
            indices=mirror.indices,
            project=lambda: self._projection(key, max_trace=math.inf),
            path=self._path,
            regular_xy_m=c.wide_xy_m,
            regular_yaw_rad=c.wide_yaw_rad,
            regular_k_sigma=c.k_sigma,
            progress_s=progress_s,
        )
        for m in found:
            if m.result.runner_up_score > 0.0:
                self.stats.look_alikes += 1
                continue
            cov = self._edge_covariance(m.result)
            if self._ambiguous(cov):
                self.stats.ambiguous += 1
                continue
            self._next_hyp += 1
            self.stats.hypotheses += 1
            admitted = self._admit(  # its grids' bend, as in _match
                Hypothesis(
                    hyp_id=self._next_hyp,
                    key_a=m.key_a,
                    key_b=m.key_b,
                    a_from_b=m.result.a_from_b,
                    covariance=cov,
                    score=m.result.normalized_score,
                    time_s=progress_s,
                )
            )
            if admitted is not None:
                self._validator.add(admitted)
        # ---- end of the long-loop candidate source ----

    def _matcher_for(self, wide_xy: bool, yaw_rad: float) -> CorrelativeMatcher:
        """The matcher of a window: standard or wide translation (each with its own tables),
        and any yaw window (tables do not depend on it)."""
        k = (wide_xy, round(yaw_rad, 9))
        if k not in self._matchers:
            cfg = self.config
            xy = cfg.candidates.wide_xy_m if wide_xy else cfg.matcher.search_xy_m
            self._matchers[k] = CorrelativeMatcher(
                msgspec.structs.replace(cfg.matcher, search_xy_m=xy, search_yaw_rad=yaw_rad)
            )
        return self._matchers[k]

    def _has_scan(self, mirror: GraphMirror) -> NDArray[np.bool_]:
        stamp = (mirror.version, len(self._scans))
        if self._has_scan_cache is None or self._has_scan_cache[0] != stamp:
            flags = np.array([int(k) in self._scans for k in mirror.keys], dtype=bool)
            self._has_scan_cache = (stamp, flags)
        return self._has_scan_cache[1]

    def _table(self, key: int, wide: bool) -> ReferenceTable:
        k = (key, wide)
        table = self._tables.get(k)
        if table is not None:
            self._tables.move_to_end(k)
            return table
        grid, origin = points_grid(self._scans[key], resolution_m=self.config.resolution_m)
        matcher = self._wide if wide else self._matcher
        table = matcher.reference_table(
            grid, origin_m=origin, resolution_m=self.config.resolution_m
        )
        self._tables[k] = table
        cap = {False: self.config.table_cache, True: self.config.wide_table_cache}
        kinds = [kk for kk in self._tables if kk[1] == wide]
        for kk in kinds[: max(0, len(kinds) - cap[wide])]:  # least recently used first
            del self._tables[kk]
        return table

    def _edge_covariance(self, result: MatchResult) -> FloatArray:
        cfg = self.config
        cov = vector_to_body_covariance(result.a_from_b, result.covariance)
        cov = 0.5 * (cov + cov.T)
        floor = np.diag(
            [
                cfg.edge_floor_sigma_xy_m**2,
                cfg.edge_floor_sigma_xy_m**2,
                cfg.edge_floor_sigma_yaw_rad**2,
            ]
        )
        return cov + floor  # type: ignore[no-any-return]

    def _look_alike_radius_m(self, prior_xyt: FloatArray) -> float | None:
        """This match's runner-up exclusion radius (config ``look_alike_radius_m``; None:
        the matcher's own ``runner_up_radius_m``): 0, no runner-up search, when the candidate's
        prior (``prior_xyt``, the Dijkstra projection's covariance, vector components) is so
        tight that nothing that far from the guess lies within ``look_alike_chi2`` of it."""
        cfg = self.config
        r = cfg.look_alike_radius_m
        if r <= 0.0:
            return None
        lam = float(np.linalg.eigvalsh(np.asarray(prior_xyt, dtype=np.float64)[:2, :2])[-1])
        floor = cfg.validation.floor_sigma_xy_m**2
        return r if (lam + floor) * cfg.look_alike_chi2 >= r * r else 0.0

    def _plausible_look_alike(
        self, result: MatchResult, guess: FloatArray, prior_xyt: FloatArray
    ) -> bool:
        """Whether a match's runner-up is a place the graph cannot rule out: with
        ``look_alike_radius_m`` > 0, within ``look_alike_chi2`` (3 dof) of the guess under the
        candidate's prior (floored like hypotheses); without, any runner-up in the window."""
        cfg = self.config
        if cfg.look_alike_radius_m <= 0.0 or result.runner_up_a_from_b is None:
            return True
        d = np.asarray(result.runner_up_a_from_b, dtype=np.float64) - np.asarray(guess, float)
        d[2] = se2.wrap_angle(d[2])
        v = cfg.validation
        cov = np.asarray(prior_xyt, dtype=np.float64) + np.diag(
            [v.floor_sigma_xy_m**2, v.floor_sigma_xy_m**2, v.floor_sigma_yaw_rad**2]
        )
        return bool(d @ np.linalg.solve(cov, d) <= cfg.look_alike_chi2)

    def _ambiguous(self, cov: FloatArray) -> bool:
        """Whether a match (its edge covariance ``cov``, body frame) constrains too little to
        be a closure: a translation standard deviation beyond ``max_match_sigma_xy_m`` or a
        heading one beyond ``max_match_sigma_yaw_rad`` (each half of what makes a closure
        false, 0.5 m and 5 deg: a match twice its sigma off is still a true closure)."""
        cfg = self.config
        return bool(
            np.linalg.eigvalsh(cov[:2, :2])[-1] > cfg.max_match_sigma_xy_m**2
            or cov[2, 2] > cfg.max_match_sigma_yaw_rad**2
        )

    def _match(self, cand: Candidate, progress_s: float) -> Hypothesis | None:
        cfg = self.config
        a, b = cand.reference_key, cand.query_key
        if a not in self._scans or b not in self._scans:
            return None
        guess = se2.between(self.graph.pose(a), self.graph.pose(b))
        wide_xy = cand.window_xy_m > cfg.matcher.search_xy_m
        if cand.wide and min(len(self._scans[a]), len(self._scans[b])) < cfg.wide_min_points:
            self.stats.wide_too_few_points += 1  # a few points fit somewhere in a wide window
            return None
        matcher = self._matcher_for(wide_xy, cand.window_yaw_rad)
        table = self._table(a, wide_xy)
        min_score = cfg.wide_min_score if cand.wide else cfg.min_score
        self.stats.matches += 1
        self.stats.wide_matches += cand.wide
        radius = self._look_alike_radius_m(cand.covariance_xyt)
        cycle_radius = cfg.look_alike_cycle_radius_m
        result = matcher.match(
            table,
            self._scans[b],
            guess,
            min_score=min_score,
            runner_up_radius_m=cycle_radius if cycle_radius > 0.0 else radius,
        )
        if result is None:
            self.stats.below_min_score += 1
            return None
        look_alike = None
        if cycle_radius > 0.0:
            # kept with the hypothesis: a cycle must tell the two places apart (validation)
            if result.runner_up_a_from_b is not None:
                look_alike = np.asarray(result.runner_up_a_from_b, dtype=np.float64)
                self.stats.look_alikes += 1
        elif result.runner_up_score > 0.0 and self._plausible_look_alike(
            result, guess, cand.covariance_xyt
        ):  # another place the graph cannot rule out fits nearly as well
            self.stats.look_alikes += 1
            return None
        cov = self._edge_covariance(result)
        if self._ambiguous(cov):
            self.stats.ambiguous += 1
            return None
        # a sample of the turn scale whatever its grids' bend: the bend bound comes from the
        # fit, so widening the samples by it would keep the fit as uncertain as its prior
        self._record_bias_sample(a, b, result.a_from_b, cov, guess, cand.window_yaw_rad)
        self.stats.hypotheses += 1
        self._next_hyp += 1
        return self._admit(
            Hypothesis(
                hyp_id=self._next_hyp,
                key_a=a,
                key_b=b,
                a_from_b=result.a_from_b,
                covariance=cov,
                score=result.normalized_score,
                time_s=progress_s,
                look_alike=look_alike,
            )
        )

    def _admit(self, h: Hypothesis) -> Hypothesis | None:
        """``h`` with its heading variance widened by its grids' bend
        (:meth:`_grid_distortion_rad`), or None when the bend exceeds
        ``max_grid_distortion_rad``: such a match is no closure under what is known of the
        turn scale now, so it waits (at most ``max_deferred_kept``, the oldest dropped) for the
        next fit, which may bound the scale tighter (:meth:`_release_deferred`)."""
        bend = self._grid_distortion_rad(h.key_a, h.key_b)
        if bend > self.config.max_grid_distortion_rad:
            self.stats.distorted += 1
            self._deferred[h.hyp_id] = h
            while len(self._deferred) > self.config.max_deferred_kept:
                self._deferred.pop(next(iter(self._deferred)))
            return None
        cov = np.array(h.covariance, dtype=np.float64, copy=True)
        cov[2, 2] += bend**2
        if bend > 0.0:
            self._bend_var[h.hyp_id] = bend**2
            if len(self._bend_var) > 4 * (self.config.validation.max_hypotheses + 100):
                pending = {p.hyp_id for p in self._validator.pending}
                self._bend_var = {k: v for k, v in self._bend_var.items() if k in pending}
        return dataclasses.replace(h, covariance=cov)

    def _rebend_closures(self) -> list[int]:
        """After a new turn-scale fit: each automatic closure's heading variance carries its
        grids' bend under the new fit (it was admitted under an older one, or the prior);
        a closure whose bend now exceeds ``max_grid_distortion_rad`` is removed, as it would
        not be admitted now. Returns the removed edge ids."""
        gate = self.config.max_grid_distortion_rad
        updates: dict[int, tuple[FloatArray, FloatArray]] = {}
        bad: list[int] = []
        for e in self.graph.edges(Provenance.LOOP_AUTO):
            old = self._closure_bend_var.get(e.edge_id)
            if old is None:
                continue
            assert e.key_b is not None
            bend = self._grid_distortion_rad(e.key_a, e.key_b)
            if bend > gate:
                bad.append(e.edge_id)
                continue
            new = bend**2
            base = float(e.covariance[2, 2]) - old
            if abs(new - old) <= 0.1 * (base + old):
                continue  # a small change is not worth re-seeding the incremental solver
            cov = np.array(e.covariance, dtype=np.float64, copy=True)
            cov[2, 2] = base + new
            updates[e.edge_id] = (np.asarray(e.z), cov)
            self._closure_bend_var[e.edge_id] = new
        if updates:
            self.graph.update_edges(updates)
            self._stale = True
        if bad:
            self.graph.remove_edges(bad)
            self.stats.closures_pruned += len(bad)
            self._stale = True
            for eid in bad:
                self._closure_bend_var.pop(eid, None)
        return bad

    def _release_deferred(self) -> None:
        """After a new turn-scale fit: the deferred matches whose bend is now within bounds
        join the validation (stamped now: they wait for their cycles from here)."""
        for hyp_id, h in list(self._deferred.items()):
            if self._grid_distortion_rad(h.key_a, h.key_b) > self.config.max_grid_distortion_rad:
                continue
            del self._deferred[hyp_id]
            admitted = self._admit(dataclasses.replace(h, time_s=self._progress_s))
            assert admitted is not None
            self._validator.add(admitted)

    # ---- odometry self-calibration (paper 4.2 in spirit; module docstring) -----------------

    def _record_bias_sample(
        self,
        key_a: int,
        key_b: int,
        a_from_b: FloatArray,
        cov: FloatArray,
        guess: FloatArray,
        window_yaw_rad: float,
    ) -> None:
        """Keep a same-robot match for the robot's turn-scale fit: every match that reached
        ``min_score``, before validation (validating against biased odometry would select
        the matches that agree with it), with the guess and yaw window it was searched in (a
        match whose window could not hold the truth is not evidence, see
        :meth:`_fit_turn_scale`)."""
        ra, rb = split_key(key_a)[0], split_key(key_b)[0]
        if ra != rb:
            return
        self._bias_samples.setdefault(ra, {})[(key_a, key_b)] = (
            float(a_from_b[2]),
            float(cov[2, 2]),
            float(guess[2]),
            float(window_yaw_rad),
        )

    def _calibrate_odometry(self, report: LoopClosingReport) -> None:
        """Fit each robot's turn scale on its matches; feed a significant change back into the
        graph's odometry (:meth:`PoseGraph.set_odometry_correction`), re-solve in batch, drop
        the closures the corrected graph contradicts and match every pair again."""
        cfg = self.config.odometry_bias
        if not cfg.enabled:
            return
        changed: list[int] = []
        refitted = False
        for robot, samples in self._bias_samples.items():
            n = len(samples)
            last = self._bias_fitted_at.get(robot, 0)
            if n < cfg.min_used or n < last + max(4, last // 10):
                continue  # refit when the samples grew by 10 % (at least 4)
            if n < self._bias_applied_at.get(robot, 0) * cfg.refit_growth:
                continue  # after a correction, wait for that much more evidence
            self._bias_fitted_at[robot] = n
            est = self._fit_turn_scale(robot, samples)
            if est is None:
                continue
            self._turn_scales[robot] = est
            refitted = True
            in_use = self._applied_scales.get(robot)
            # is there a bias at all (apply_sigma from 1, not below half the floored sigma:
            # one stretch's shared noise must not start a correction), then: is the better
            # estimate (refitted only on refit_growth times the evidence) different
            # (reapply_sigma of its statistical sigma from the one in use)
            stat = est.sigma if est.statistical_sigma is None else est.statistical_sigma
            if in_use is None:
                differs = abs(est.scale - 1.0) > cfg.apply_sigma * max(stat, 0.5 * est.sigma)
            else:
                differs = abs(est.scale - in_use.scale) > cfg.reapply_sigma * stat
            if est.used < cfg.min_used or not differs:
                continue
            self.graph.set_odometry_correction(
                robot, functools.partial(debias_odometry, estimate=est)
            )
            self._applied_scales[robot] = est
            self._bias_applied_at[robot] = n
            changed.append(robot)
        if refitted and self.config.grid_window_m > 0.0:
            report.pruned_edge_ids += self._rebend_closures()
            self._release_deferred()
        if not changed:
            return
        self.stats.odometry_recalibrations += len(changed)
        report.recalibrated_robots = changed
        pruned = self._prune_against_odometry()
        self.graph.optimize()
        more = self._prune_contradicted()
        if more:
            self.graph.optimize()
        report.pruned_edge_ids += pruned + more
        # Hypotheses rejected against the biased odometry may hold now: after a large change
        # every pair is matched again (windows and guesses were wrong too), after a small one
        # the rejected hypotheses are checked again and the nodes searched for new pairs.
        restart = False
        for robot in changed:
            before = self._restarted_at.get(robot, TurnScale(scale=1.0))
            if abs(self._applied_scales[robot].scale - before.scale) > cfg.restart_change:
                self._restarted_at[robot] = self._applied_scales[robot]
                restart = True
        if restart:
            self.restart()
            # pairs already joined by a closure need no second one
            for e in self.graph.edges((Provenance.LOOP_AUTO, Provenance.LOOP_OPERATOR)):
                if e.key_b is not None:
                    self._tried.add((min(e.key_a, e.key_b), max(e.key_a, e.key_b)))
        else:
            pending = {h.hyp_id for h in self._validator.pending}
            for h in self._rejected.values():
                if h.hyp_id not in pending:
                    self._validator.add(dataclasses.replace(h, time_s=self._progress_s))
            self._sources = sorted(set(self._sources) | set(self._scans))
            self._stale = True
            self._links.clear()
        self._rejected.clear()

    def _fit_turn_scale(
        self, robot: int, samples: dict[tuple[int, int], tuple[float, ...]]
    ) -> TurnScale | None:
        """The robot's turn scale from its matches (:func:`estimate_turn_scale`).

        A match is evidence only if its yaw window could hold the true heading change: the
        matcher returns the best peak *inside* the window, so when the truth lies outside
        (odometry biased beyond the window) it returns a look-alike near the guess, and such
        matches would pull the fit towards the biased odometry. So a match is used when
        ``s T ± window_k_sigma σ |T|`` (the turning ``T`` scaled by the current estimate
        and its uncertainty) lies inside its window; starting from the prior (1 ± σ0) the fit
        admits the short turns, its estimate then admits longer ones, and so on a few times.
        When the prior admits fewer than ``min_used`` (a robot that only revisited places
        after long turns) the first fit takes every match and relies on its gate.
        """
        chain = self._chain(robot)
        if chain is None:
            return None
        first, turn, var, _dist = chain
        n = len(turn)
        rows = []
        for (a, b), (yaw, yaw_var, guess_yaw, window) in samples.items():
            ia, ib = a - first, b - first
            if 0 <= ia < n and 0 <= ib < n:
                wa, ma = self._window_turns_rad(a)
                wb, mb = self._window_turns_rad(b)
                rows.append(
                    (
                        turn[ib] - turn[ia],
                        yaw,
                        yaw_var + abs(var[ib] - var[ia]),
                        guess_yaw,
                        window,
                        math.hypot(wa, wb),
                        ma - mb,
                    )
                )
        if not rows:
            return None
        t, d, v, g, w, bw, off = np.array(rows).T
        cfg = self.config.odometry_bias
        center, sigma = 1.0, cfg.prior_sigma
        est: TurnScale | None = None
        for it in range(cfg.iterations):
            need = cfg.window_k_sigma * (sigma * np.abs(t) + np.sqrt(v))
            inside = np.abs(se2.wrap_angle(center * t - g)) + need <= w
            fit = estimate_turn_scale(
                t[inside],
                d[inside],
                v[inside],
                cfg,
                bend_turn_rad=bw[inside],
                bend_offset_rad=off[inside],
            )
            if it == 0 and fit.used < cfg.min_used:
                # the prior admits too few (only long turns were revisited): start from all
                # matches, the fit's own gate against the outliers
                fit = estimate_turn_scale(t, d, v, cfg, bend_turn_rad=bw, bend_offset_rad=off)
            if fit.used < cfg.min_used:
                break
            est = fit
            if abs(fit.scale - center) < 0.1 * fit.sigma and fit.sigma >= sigma:
                break
            center, sigma = fit.scale, fit.sigma
        return est

    def _prune_against_odometry(self) -> list[int]:
        """Remove the automatic closures of one robot whose heading change contradicts the
        robot's corrected odometry: ``wrap(yaw - s T)`` beyond ``prune_heading_chi2`` (1 dof,
        99 %: a true closure lost now and then costs little, a false one stays; the closure's
        and the chain's variances and the scale's ``(sigma_s T)^2``). Closures accepted
        against the biased odometry lean to it; the corrected chain says which."""
        vcfg = self.config.validation
        bad = []
        for e in self.graph.edges(Provenance.LOOP_AUTO):
            assert e.key_b is not None
            got = self._chain_turn(e.key_a, e.key_b)
            est = self._applied_scales.get(split_key(e.key_a)[0])
            if got is None or est is None:
                continue
            turn, chain_var = got
            r = float(se2.wrap_angle(float(e.z[2]) - est.scale * turn))
            var = (
                float(e.covariance[2, 2])
                + vcfg.floor_sigma_yaw_rad**2
                + chain_var
                + (est.sigma * turn) ** 2
            )
            if r * r > self.config.prune_heading_chi2 * var:
                bad.append(e.edge_id)
        if bad:
            self.graph.remove_edges(bad)
            self.stats.closures_pruned += len(bad)
            self._stale = True
        return bad

    def _prune_contradicted(self) -> list[int]:
        """Remove the automatic closures whose residual at the current estimate exceeds
        ``prune_chi2`` (3 degrees of freedom, their covariance floored as in validation)."""
        vcfg = self.config.validation
        floor = np.diag(
            [vcfg.floor_sigma_xy_m**2, vcfg.floor_sigma_xy_m**2, vcfg.floor_sigma_yaw_rad**2]
        )
        bad = []
        for e in self.graph.edges(Provenance.LOOP_AUTO):
            assert e.key_b is not None
            pred = se2.between(self.graph.pose(e.key_a), self.graph.pose(e.key_b))
            err = se2.between(np.asarray(e.z), pred)
            r = np.array([err[0], err[1], float(se2.wrap_angle(err[2]))])
            if float(r @ np.linalg.solve(e.covariance + floor, r)) > self.config.prune_chi2:
                bad.append(e.edge_id)
        if bad:
            self.graph.remove_edges(bad)
            self.stats.closures_pruned += len(bad)
            self._stale = True
        return bad

    def _links_of(self, key: int) -> dict[int, tuple[FloatArray, FloatArray]]:
        """Tight graph paths from ``key``: ``{other: (key_from_other, covariance)}``."""
        if key in self._links:
            return self._links[key]
        m = self._mirror
        out: dict[int, tuple[FloatArray, FloatArray]] = {}
        if not self._stale and key in m.index:
            cfg = self.config
            limit = 2 * cfg.link_sigma_xy_m**2 + cfg.link_sigma_yaw_rad**2
            proj = self._projection(key, max_trace=limit)
            for i in np.nonzero(proj.reached)[0]:
                cov = proj.covariances[i]
                if (
                    max(cov[0, 0], cov[1, 1]) <= cfg.link_sigma_xy_m**2
                    and cov[2, 2] <= cfg.link_sigma_yaw_rad**2
                ):
                    out[int(m.keys[i])] = (proj.poses[i], cov)
        self._links[key] = out
        return out

    def _path(self, key_a: int, key_b: int) -> tuple[FloatArray, FloatArray] | None:
        """The graph's minimum-uncertainty path ``a_from_b`` (None if not connected within
        ``path_sigma_xy_m``)."""
        m = self._mirror
        if self._stale or key_a not in m.index or key_b not in m.index:
            return None
        s = self.config.path_sigma_xy_m
        proj = self._projection(key_a, max_trace=2 * s**2 + math.pi**2, target=key_b)
        i = m.index[key_b]
        if not proj.reached[i]:
            return None
        cov = proj.covariances[i].copy()
        # the odometry's turn scale is uncertain (the prior, or the estimate in use): along
        # one robot's chain that error is common to every turn, (sigma_s * turning)^2
        cov[2, 2] += self._turn_scale_variance(key_a, key_b)
        return proj.poses[i], cov

    def _chain(self, robot: int) -> tuple[int, FloatArray, FloatArray, FloatArray] | None:
        """A robot's reported odometry as prefix sums: ``(first key, turning (n,), yaw
        variance (n,), distance travelled (n,))`` (node ``first + i`` at row ``i``); cached
        until a node is added."""
        n_nodes = self._nodes_seen
        hit = self._chains.get(robot)
        if hit is not None and hit[0] == n_nodes:
            return hit[1]
        _ids, keys_b, z, cov = self.graph.odometry_reported(robot)
        out: tuple[int, FloatArray, FloatArray, FloatArray] | None = None
        if len(keys_b):
            turn = np.concatenate([[0.0], np.cumsum(se2.wrap_angle(z[:, 2]))])
            var = np.concatenate([[0.0], np.cumsum(cov[:, 2, 2])])
            dist = np.concatenate([[0.0], np.cumsum(np.hypot(z[:, 0], z[:, 1]))])
            out = (int(keys_b[0]) - 1, turn, var, dist)  # keys are consecutive along a chain
        self._chains[robot] = (n_nodes, out)
        return out

    def _chain_turn(self, key_a: int, key_b: int) -> tuple[float, float] | None:
        """Odometry turning from ``key_a`` to ``key_b`` of one robot and its yaw variance
        (None: different robots or unknown nodes)."""
        ra, rb = split_key(key_a)[0], split_key(key_b)[0]
        if ra != rb:
            return None
        chain = self._chain(ra)
        if chain is None:
            return None
        first, turn, var, _dist = chain
        ia, ib = key_a - first, key_b - first
        if not (0 <= ia < len(turn) and 0 <= ib < len(turn)):
            return None
        return float(turn[ib] - turn[ia]), float(abs(var[ib] - var[ia]))

    def _turn_scale_variance(self, key_a: int, key_b: int) -> float:
        got = self._chain_turn(key_a, key_b)
        if got is None:
            return 0.0
        est = self._applied_scales.get(split_key(key_a)[0])
        sigma = est.sigma if est is not None else self.config.odometry_bias.prior_sigma
        return (sigma * got[0]) ** 2

    def _window_turn_rad(self, key: int) -> float:
        """The largest heading change within node ``key``'s grid (:meth:`_window_turns_rad`)."""
        return self._window_turns_rad(key)[0]

    def _window_turns_rad(self, key: int) -> tuple[float, float]:
        """Heading changes, by the robot's reported odometry, from node ``key`` back to the
        nodes of the last ``grid_window_m`` of travel before it (one node more: the scans
        between two nodes belong to the window too): the largest in magnitude, and the mean
        (signed; the grid's content is turned by ``(1 - s)`` times it on average). 0, 0 for
        an unknown node or one-sweep grids. A grid bounded in turning (``grid_window_rad``)
        stops at the first node back that turned beyond it."""
        if self.config.grid_window_m <= 0.0:
            return 0.0, 0.0  # one sweep per grid: nothing joined by odometry
        robot = split_key(key)[0]
        chain = self._chain(robot)
        if chain is None:
            return 0.0, 0.0
        first, turn, _var, dist = chain
        i = key - first
        if not 0 <= i < len(turn):
            return 0.0, 0.0
        j = int(np.searchsorted(dist, dist[i] - self.config.grid_window_m, side="left"))
        j = max(0, min(j, i) - 1)
        back = turn[j : i + 1] - turn[i]
        cap = self.config.grid_window_rad
        beyond = np.flatnonzero(np.abs(back) > cap)
        if len(beyond):
            # the scans stop where the turning reached the cap: the node beyond it bounds
            # the last stretch, clipped to the cap
            back = np.clip(back[beyond[-1] :], -cap, cap)
        return float(np.max(np.abs(back))), float(np.mean(back))

    def _grid_distortion_rad(self, key_a: int, key_b: int) -> float:
        """How far the two nodes' grids may be bent by their robots' turn-scale error: a grid
        holds the scans of its last ``grid_window_m`` brought into the node's frame by the
        odometry the robot *reported* (the robot built it on board, before any correction),
        so a scan taken ``W`` radians of turning before the node lies ``(s - 1) W`` off, for a
        true turn scale ``s``. The scale error is the robot's latest fit's,
        ``sqrt((s_fit - 1)^2 + sigma^2)`` (``sigma`` from the closures' scatter: the
        single-closure floor, which guards the correction against one stretch's shared noise,
        would refuse a true robot's spins for long; the prior ``prior_sigma`` before a fit); the two
        grids' bends add in quadrature. Matches on biased grids came out off by 0.7 to 0.9
        times this (Intel, Freiburg 079 with turns scaled by 0.92 and 1.08)."""
        prior = self.config.odometry_bias.prior_sigma
        out = 0.0
        for key in (key_a, key_b):
            w = self._window_turn_rad(key)
            if w == 0.0:
                continue
            fit = self._turn_scales.get(split_key(key)[0])
            if fit is None:
                bound = prior
            else:
                spread = fit.sigma if fit.statistical_sigma is None else fit.statistical_sigma
                bound = math.hypot(fit.scale - 1.0, spread)
            out = math.hypot(out, bound * w)
        return out
