"""Loop validation: hypotheses wait until a cycle of agreeing edges confirms them (paper 4.5).

A scan match is a *hypothesis* ``a_from_b`` between two pose nodes. It waits in a temporary
graph until a cycle through it composes to (approximately) the identity:

* a *link* joins two nodes the existing pose graph already relates tightly (a path whose
  Dijkstra-projected covariance is small, e.g. a few metres of one robot's odometry, or
  earlier closures), with the path's composed measurement and covariance;
* a cycle alternates hypotheses and links: ``h1, link, h2, link, ...`` back to its start,
  with at least ``min_cycle_hypotheses`` (2: "require that multiple edges agree") and at most
  ``max_cycle_hypotheses`` hypotheses (the depth of the search; 2 while more than
  ``deep_search_max_pending`` wait, which bounds its cost);
* its composed transform ``T`` is compared with the identity by a chi-square test on the
  propagated covariance ``S`` of the composition: ``r' S^-1 r <= chi2_threshold`` with
  ``r = (x, y, wrap(theta))`` of ``T`` (3 degrees of freedom; 11.34 is the 99% quantile).

Soundness. Each hypothesis is first checked against the graph alone: the graph's own path
between its two nodes (any length: its covariance says how much it knows) closes a
one-hypothesis cycle; when that cycle fails the test the hypothesis contradicts what the
graph already knows and is rejected for good (the aliasing case: two look-alike places whose
graph path says they are apart). Among pending hypotheses, a hypothesis is promoted only
with the other members of a consistent cycle, and only when none of them lies on a failing
cycle: which member of a failing cycle is wrong is unknown, so all wait (until the wrong one
expires, or an edge accepted elsewhere lets the graph check reject it). So no accepted
closure lies on a tested cycle that failed, with the graph or with other hypotheses; what
remains is the paper's caveat, errors that cancel around a cycle ("this seldom occurs").

Known paths (``graph_offset_m`` / ``graph_offset_rad``). The graph check above weighs the
difference between a match and the graph's path by both covariances, so a match that states a
loose axis (a corridor: the quick mission's false closures were nearly all translation
sigmas of 0.19-0.25 m, just inside ``LoopCloserConfig.max_match_sigma_xy_m``, 0.5-0.97 m off
along that axis) passes against a path that knows the relation to a few centimetres: its own
covariance excuses the difference. And a cycle does not catch it either, since its partners
are matched against the same grids (see "Shared data" below). So a hypothesis is also
rejected when the path places its nodes further from it than ``graph_offset_m`` (in
translation) or ``graph_offset_rad`` (in heading), and by more than the path's covariance
and the floors alone allow (the same chi-square test, without the match's covariance): the
graph then knows the relation well enough to tell the match is off by nearly a false
closure's margin (0.5 m, 5 deg), whatever the match's response surface says. A true match
is within that margin of the truth, so it is refused only where the path itself is off.

Look-alikes. A hypothesis may carry its match's *look-alike* (:attr:`Hypothesis.look_alike`:
the best other transform of the same search, at least a false closure's distance from the
match and nearly as good; :class:`~gcs.loops.loop_closer.LoopCloserConfig`
``look_alike_cycle_radius_m``). A cycle then tests not only whether the match agrees with
its partners but which of the two places they agree with: the cycle is composed again with
the match moved to its look-alike. A hypothesis whose consistent cycles fit its look-alike
at least as well as its match (the least chi-square over its cycles with the look-alike no
larger than the least with the match) is not confirmed by them, and no cycle through it
promotes anything (its partners agree with a place the matcher could not tell apart from
another). It waits, like a member of a failing cycle: a later, tighter cycle may tell. This
is Olson's ambiguity test (paper 4.3.3) judged by the cycle instead of the prior: a
look-alike the cycle's links rule out costs nothing, one they cannot rule out holds the
match back. The quick mission's false closures that passed every other test were such
matches: seed 11 at 1d6eb73, robots 3 and 2's nodes 52 and 19 (0.67 m, 4.6 deg off), its
one cycle chi-square 9.5 with the match and 0.02 with the look-alike (the true place), and
robot 1's corridor pair 182-40 (0.52 m along it), whose two cycles fitted a look-alike
better (0.95 against 0.31, 4.4 against 0.07). ``look_alike_margin`` (0) lets a look-alike hold
a hypothesis back only when it fits by that much better. Off unless the loop closer keeps
look-alikes (off by default; measured in ``LoopCloserConfig``: fewer false closures on the
quick missions' journals, the full mission's journal far worse).

Groups (issue 19 item 4). Cycles are tested one at a time, each at its own 99% quantile, so a
set of hypotheses accepted together can disagree beyond its noise while each of its cycles
passes, and one wrong member blocks its right partners until it expires. So the hypotheses
joined by the tested cycles form groups, and each group is tested as a whole: a least-squares
fit of its hypotheses (floored) and a spanning forest of the tightest links between their nodes
(links along one robot's chain share its odometry: only a forest of them is independent) has
at its optimum a chi-square on ``3 (E - V + C)`` degrees of freedom (the group's independent
cycles; ``E`` edges, ``V`` nodes, ``C`` connected parts), tested at ``group_quantile``. A group
that fails, or holds a failing cycle, loses its largest contributor to the chi-square (among
the members of failing cycles, when there are some) and is tested again, at most
``group_max_outliers`` times (1) and only while ``group_min_support`` (3) remain: removing more
is how look-alikes that agree with a biased odometry outvote the true matches (a robot whose
turns read 8 % short: greedy removal took 21 true matches out of a group of 48 and promoted
closures 1.8 m off). A group that passes promotes its members that lie on a consistent cycle
of ``min_cycle_hypotheses`` or more, and its outlier is rejected (it disagrees with a group
that agrees without it); a group that does not pass promotes nothing (its members wait, as
members of a failing cycle did). Off by default (``group_test = False``: cycles alone): on,
the loop closer's biased-robot test (turns read 8 % short, tests/gcs/loops/
test_odometry_calibration.py) accepted three closures 1.6-1.8 m off, with or without the
outlier removal: promoting less (a group with one failing cycle waits whole) held back true
closures the turn-scale fit needed, and look-alikes that agree with the biased odometry came
in instead. On the quick bench's replays it changed nothing (seed 1); on whole Freiburg 079
(seed 1, clean) it let in more: false closures 4 -> 7 (up to 15.8 deg off), ATE 0.160 -> 0.164
m, 126 CPU-s against 49.

Shared data. A cycle is evidence only when its hypotheses' errors are independent. Two matches
against the same node's grid carry that grid's error twice: a grid turned by a few degrees
(built across wheel slip, or a place whose overlap fixes its heading loosely) turns every
match against it alike, and their cycle closes however wrong they all are (the quick mission
bench, seed 7: three closures 5-6 deg off, all against robot 2's node 61; Freiburg 079 whole:
nodes 91 and 92 each matched to node 292, 5.3-5.6 deg off). With ``independent_cycles`` a
cycle promotes only when no two of its hypotheses share a node (a cycle that shares one and
fails still blocks). Off by default: measured, it made things worse. Most cycles are one new
node's matches against several old ones, so closures came later and fewer: Freiburg 079's
quick prefix with turns scaled by 0.92 ended at ATE 0.239 m against 0.117 m, with the gap
0.362 against 0.146; the whole log still took 14 false closures, now from neighbouring nodes
(grids sharing scans without sharing a node: 325-327 against 252-254, 1.3-1.5 m off), and
counting those as dependent too (windows overlapping) halved the closures on the ACES quick
prefix (ATE 0.143 -> 0.215 m).

Hypotheses older than ``expiry_s`` (on the caller's clock: the loop closer's progress clock, not
message time) without a confirming cycle are dropped (they cost search time and, the older, the
likelier an erroneous cycle, paper 4.5), as are the oldest beyond ``max_hypotheses``.

Graph access is through two callables (so the module is pure and testable without a graph):
``links(key) -> {other_key: (key_from_other, covariance)}`` for tight paths from ``key``, and
``path(key_a, key_b) -> (a_from_b, covariance) | None`` for the graph's best path between two
nodes (None when they are not connected). Covariances are body-frame (right perturbation,
GTSAM's ``BetweenFactorPose2`` convention).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np
import scipy.stats
from numpy.typing import NDArray

from gcs.graph import se2

__all__ = [
    "CycleCheck",
    "GroupCheck",
    "CycleValidationConfig",
    "CycleValidator",
    "Hypothesis",
    "ValidationResult",
    "compose_with_covariance",
]

FloatArray = NDArray[Any]
Link = tuple[FloatArray, FloatArray]
LinksFn = Callable[[int], dict[int, Link]]
PathFn = Callable[[int, int], Link | None]


class CycleValidationConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Cycle search and acceptance (see the module docstring); sigmas in metres / radians.

    The search costs about ``pending * d^(k-1)`` for ``k`` hypotheses per cycle and ``d``
    hypotheses within a link of a node, so cycles of more than two hypotheses are searched
    only while at most ``deep_search_max_pending`` hypotheses wait, at most
    ``max_hypotheses`` wait at all (the oldest expire first), and a search is capped at
    ``max_search_steps`` extensions (see :meth:`CycleValidator._search`).

    ``floor_sigma_xy_m`` / ``floor_sigma_yaw_rad`` floor every hypothesis's covariance in the
    test (a matcher's response surface can be overconfident).

    ``group_test`` tests the hypotheses a set of cycles joins as one group (module docstring,
    "Groups") at the ``group_quantile`` of chi-square, fitting it in at most
    ``group_max_iterations`` Gauss-Newton steps; at most ``group_max_outliers`` are removed
    from a group, and only while ``group_min_support`` members remain.

    ``independent_cycles``: a cycle promotes only when no two of its hypotheses share a node
    (module docstring, "Shared data"; off by default: measured worse).

    ``look_alike_margin``: a hypothesis's look-alike holds it back when the least chi-square
    of its consistent cycles with the look-alike plus this margin is no larger than the least
    with its match (module docstring, "Look-alikes").

    ``graph_offset_m`` / ``graph_offset_rad`` (0: off) reject a hypothesis the graph's own path
    places further off than that and by more than the path's covariance allows (module
    docstring, "Known paths"). On (0.4 m / 4 deg) since session 15, together with the robots'
    accelerometer slip (``robot.node.RobotNodeConfig.odometry``): both on against both off,
    quick mission at 7abe497, seeds 0/7/3/11: F1 median 0.786 -> 0.915, ATE median 0.155 ->
    0.090 m, explored median 0.923 -> 0.914, false closures 0/0/1/0 -> 0/0/1/1 (the new one
    0.52 m off). Alone it was measured worse, below. Measured at 0.4 m / 4 deg (GCS at
    2b0cbc5). Replaying 20 quick-mission journals (seeds 0/7/3/11 of session 14's variants,
    /tmp/team/closures15/res_{base,off40}.jsonl): false closures 27 -> 11 (of 11282 -> 11272
    closures), ATE median 0.143 -> 0.139 m, F1 median 0.875 -> 0.881 (mean 0.841 -> 0.837: a
    seed-7 journal 0.798 -> 0.719); the four baseline journals' ATE and F1 within 0.002, seed
    3's false closure (2:74-2:57, 0.65 m off at a sigma of 0.23 m, graph check chi-square
    7.3) gone. Live quick missions, seeds 0/7/3/11: false closures 0/0/1/0 -> 0/0/0/0, ATE
    0.166/0.188/0.080/0.122 -> 0.098/0.188/0.087/0.102 m (median 0.144 -> 0.100), but F1
    0.907/0.568/0.945/0.905 -> 0.835/0.568/0.913/0.908 (median 0.906 -> 0.871; seed 0's map
    turned about the anchor, 0.935 aligned) and explored median 0.920 -> 0.902: the missions
    took other paths (seed 0's own journal replayed with it off: ATE 0.096, F1 0.838, as with
    it), so alone it stays off. ``magic bench robustness --quick`` with it on: as without (ratio
    1.149, 0 false closures, ate_over_odometry_max 0.369). The full mission's journal
    (magic_phase, 600 s, seed 0, at 8183549; /tmp/team/lead/full15_s0) replayed: false
    closures 12 -> 9 (of 853 -> 872), ATE 1.429 -> 1.413 m, F1 0.482 -> 0.489. It does not
    catch matches that agree with a graph path as far off as they are (quick journals: 7 of
    the 11 left, 5-9 deg off at graph check chi-square 0.4-2; the full mission: robot 4's
    0.56-3.3 m / 5-24 deg, pairs of neighbouring nodes agreeing against one old node). Nearly
    every false closure left states a translation sigma of 0.18-0.25 m: with
    ``LoopCloserConfig.max_match_sigma_xy_m`` 0.2 as well, the full mission's journal takes
    1 false closure (the two robots' first nodes, 1.5 m off at 7 s; 634 closures), ATE
    1.023 m, F1 0.530 (the bound alone: 3 false, ATE 1.436 m, F1 0.518). But not on the
    small world: the bound alone on 35 quick journals took false closures 38 -> 8, but with
    18 % fewer closures their F1 mean fell 0.831 -> 0.796 (seed 7's journals 0.14-0.21
    lower); both together on 8 of them (the baseline four, res_both.jsonl) false 11 -> 2
    (the baseline four 1 -> 2, both 5-7 deg off), F1 mean 0.847 -> 0.777.
    """

    chi2_threshold: float = 11.34
    min_cycle_hypotheses: int = 2
    max_cycle_hypotheses: int = 3
    expiry_s: float = 60.0
    max_hypotheses: int = 120
    deep_search_max_pending: int = 60
    max_search_steps: int = 20_000
    floor_sigma_xy_m: float = 0.05
    floor_sigma_yaw_rad: float = math.radians(1.0)
    group_test: bool = False
    group_quantile: float = 0.99
    group_max_iterations: int = 10
    group_max_outliers: int = 1
    group_min_support: int = 3
    independent_cycles: bool = False
    graph_offset_m: float = 0.4
    graph_offset_rad: float = math.radians(4.0)
    look_alike_margin: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.chi2_threshold) and self.chi2_threshold > 0):
            raise ValueError(f"chi2_threshold: expected > 0, got {self.chi2_threshold}")
        if not 1 <= self.min_cycle_hypotheses <= self.max_cycle_hypotheses <= 6:
            raise ValueError(
                "need 1 <= min_cycle_hypotheses <= max_cycle_hypotheses <= 6, got "
                f"{self.min_cycle_hypotheses}, {self.max_cycle_hypotheses}"
            )
        if not (self.expiry_s > 0 and self.max_hypotheses >= 1):
            raise ValueError("need expiry_s > 0 and max_hypotheses >= 1")
        if self.max_search_steps < 1:
            raise ValueError(f"max_search_steps: expected >= 1, got {self.max_search_steps}")
        if self.deep_search_max_pending < 0:
            raise ValueError(
                f"deep_search_max_pending: expected >= 0, got {self.deep_search_max_pending}"
            )
        if not (self.floor_sigma_xy_m >= 0 and self.floor_sigma_yaw_rad >= 0):
            raise ValueError("covariance floors must be >= 0")
        if not 0.5 <= self.group_quantile < 1.0:
            raise ValueError(f"group_quantile: expected in [0.5, 1), got {self.group_quantile}")
        if self.group_max_outliers < 0 or self.group_min_support < 2:
            raise ValueError(
                "need group_max_outliers >= 0 and group_min_support >= 2, got "
                f"{self.group_max_outliers}, {self.group_min_support}"
            )
        if self.group_max_iterations < 1:
            raise ValueError(
                f"group_max_iterations: expected >= 1, got {self.group_max_iterations}"
            )
        for name in ("graph_offset_m", "graph_offset_rad", "look_alike_margin"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite number >= 0, got {v}")


@dataclass(frozen=True)
class Hypothesis:
    """A match waiting for confirmation: ``a_from_b`` between ``key_a`` and ``key_b``, its
    body-frame covariance, the matcher's normalized score and when it was made;
    ``look_alike`` (None: none known) another ``a_from_b`` the match fitted nearly as well
    (module docstring, "Look-alikes")."""

    hyp_id: int
    key_a: int
    key_b: int
    a_from_b: FloatArray
    covariance: FloatArray
    score: float
    time_s: float
    look_alike: FloatArray | None = None


@dataclass(frozen=True)
class CycleCheck:
    """One cycle that was tested: its hypotheses (in order), its chi-square and verdict.
    ``look_alike_chi2``: per member (in the order of ``hyp_ids``), the chi-square of the same
    cycle with that member's match moved to its look-alike (:attr:`Hypothesis.look_alike`;
    inf for a member without one; empty when no member has one)."""

    hyp_ids: tuple[int, ...]
    chi2: float
    consistent: bool
    look_alike_chi2: tuple[float, ...] = ()


@dataclass(frozen=True)
class GroupCheck:
    """One group test (module docstring, "Groups"): the hypotheses tested together, the
    chi-square of their joint fit, its degrees of freedom, the verdict and the outliers
    already removed from the group before this test."""

    hyp_ids: tuple[int, ...]
    chi2: float
    dof: int
    consistent: bool
    removed: tuple[int, ...] = ()


@dataclass
class ValidationResult:
    """What one :meth:`CycleValidator.validate` call decided."""

    accepted: list[Hypothesis] = field(default_factory=list)
    # contradicted by the graph, or the outlier of a group that agrees without it
    rejected: list[Hypothesis] = field(default_factory=list)
    expired: list[Hypothesis] = field(default_factory=list)
    cycles: list[CycleCheck] = field(default_factory=list)
    groups: list[GroupCheck] = field(default_factory=list)


@dataclass(frozen=True)
class _GroupFit:
    chi2: float
    dof: int
    contribution: dict[int, float]


def compose_with_covariance(steps: Iterable[Link]) -> Link:
    """Compose ``(pose, body covariance)`` steps left to right (independent errors):
    ``x_{k+1} = x_k * step``, ``cov_{k+1} = Ad(step^-1) cov_k Ad(step^-1)' + cov_step``."""
    acc: Link = (np.zeros(3), np.zeros((3, 3)))
    for step in steps:
        acc = _compose2(acc, step)
    return acc


def _inverse(link: Link) -> Link:
    return _from_t(_inverse_t(_to_t(*link)))


def _chi2(pose: FloatArray, cov: FloatArray) -> float:
    r = np.array([pose[0], pose[1], float(se2.wrap_angle(pose[2]))])
    try:
        return float(r @ np.linalg.solve(cov, r))
    except np.linalg.LinAlgError:
        return math.inf


class CycleValidator:
    """The temporary graph of hypotheses and its cycle search (module docstring)."""

    def __init__(self, config: CycleValidationConfig | None = None) -> None:
        self.config = config or CycleValidationConfig()
        self._pending: dict[int, Hypothesis] = {}
        self._checked: dict[int, int] = {}  # hypothesis -> graph revision it was checked at
        self._searched: tuple[int, frozenset[int]] | None = None

    @property
    def pending(self) -> list[Hypothesis]:
        """Hypotheses waiting for a cycle, oldest first."""
        return sorted(self._pending.values(), key=lambda h: (h.time_s, h.hyp_id))

    def add(self, hypothesis: Hypothesis) -> None:
        """Add a hypothesis to the temporary graph."""
        h = hypothesis
        if h.hyp_id in self._pending:
            raise ValueError(f"hypothesis {h.hyp_id} is already pending")
        if h.key_a == h.key_b:
            raise ValueError(f"hypothesis {h.hyp_id} joins a node to itself")
        z = np.asarray(h.a_from_b, dtype=np.float64)
        c = np.asarray(h.covariance, dtype=np.float64)
        if (
            z.shape != (3,)
            or c.shape != (3, 3)
            or not (np.all(np.isfinite(z)) and np.all(np.isfinite(c)))
        ):
            raise ValueError(
                f"hypothesis {h.hyp_id}: need a finite pose (3,) and covariance (3, 3)"
            )
        self._pending[h.hyp_id] = h

    def clear(self) -> list[Hypothesis]:
        """Drop every pending hypothesis; returns them."""
        out = self.pending
        self._pending.clear()
        self._checked.clear()
        self._searched = None
        return out

    def _floored(self, h: Hypothesis) -> Link:
        cfg = self.config
        floor = np.diag(
            [cfg.floor_sigma_xy_m**2, cfg.floor_sigma_xy_m**2, cfg.floor_sigma_yaw_rad**2]
        )
        return np.asarray(h.a_from_b, dtype=np.float64), np.asarray(h.covariance) + floor

    def _step(self, h: Hypothesis, from_key: int) -> tuple[Link, int]:
        """Traverse ``h`` starting at ``from_key``: the step and the node reached."""
        link = self._floored(h)
        if from_key == h.key_a:
            return link, h.key_b
        return _inverse(link), h.key_a

    def validate(
        self,
        *,
        now_s: float,
        links: LinksFn,
        path: PathFn,
        revision: int = 0,
    ) -> ValidationResult:
        """Expire, check hypotheses against the graph, search cycles, promote.

        ``revision`` identifies the state of the graph's paths (bump it when edges other than
        a new node's odometry are added or removed); a hypothesis already checked against the
        graph at the same revision is not checked again. Accepted and rejected hypotheses
        leave the temporary graph; the caller adds the accepted ones to the pose graph.
        """
        cfg = self.config
        out = ValidationResult()
        for h in self.pending:
            if now_s - h.time_s > cfg.expiry_s:
                out.expired.append(self._pop(h.hyp_id))
        excess = len(self._pending) - cfg.max_hypotheses
        if excess > 0:
            for h in self.pending[:excess]:
                out.expired.append(self._pop(h.hyp_id))
        # each hypothesis against the graph's own path between its two nodes
        for h in self.pending:
            if self._checked.get(h.hyp_id) == revision:
                continue
            self._checked[h.hyp_id] = revision
            known = path(h.key_a, h.key_b)
            if known is None:
                continue
            pose, cov = compose_with_covariance([self._floored(h), _inverse(known)])
            chi2 = _chi2(pose, cov)
            ok = chi2 <= cfg.chi2_threshold and not self._off_a_known_path(h, known, pose)
            out.cycles.append(CycleCheck((h.hyp_id,), chi2, ok))
            if not ok:
                out.rejected.append(self._pop(h.hyp_id))
        # cycles among the remaining hypotheses; nothing to redo when neither the pending set
        # nor the graph's paths changed since the last search
        state = (revision, frozenset(self._pending))
        if state == self._searched:
            return out
        self._searched = state
        searched = []
        link_cache: dict[int, dict[int, _T]] = {}
        for ids, pose, cov, walk in self._search(links, link_cache):
            chi2 = _chi2(pose, cov)
            alts: tuple[float, ...] = ()
            if any(self._pending[i].look_alike is not None for i in ids):
                alts = tuple(
                    math.inf
                    if (other := self._pending[i].look_alike) is None
                    else self._recompose(walk, link_cache, i, other)
                    for i in ids
                )
            check = CycleCheck(ids, chi2, chi2 <= cfg.chi2_threshold, alts)
            out.cycles.append(check)
            searched.append(check)
        # a failing cycle blocks all its members: which one is wrong is unknown (unless the
        # group test below finds it)
        blocked: set[int] = set()
        for c in searched:
            if not c.consistent:
                blocked.update(c.hyp_ids)

        look_alike_ok = self._look_alike_verdicts(searched)
        promoted: set[int] = set()
        if cfg.group_test:
            promoted, outliers = self._group_verdicts(searched, links, link_cache, out)
            blocked -= promoted
            for i in sorted(outliers):
                out.rejected.append(self._pop(i))
        else:
            for c in searched:
                if not c.consistent or len(c.hyp_ids) < cfg.min_cycle_hypotheses:
                    continue
                if not look_alike_ok.issuperset(c.hyp_ids):
                    continue
                if blocked.intersection(c.hyp_ids):
                    continue
                if cfg.independent_cycles and self._share_a_node(c.hyp_ids):
                    continue
                promoted.update(c.hyp_ids)
        if cfg.min_cycle_hypotheses <= 1:
            promoted.update(
                c.hyp_ids[0]
                for c in out.cycles
                if len(c.hyp_ids) == 1 and c.consistent and c.hyp_ids[0] not in blocked
            )
        for i in sorted(promoted, key=lambda i: (self._pending[i].time_s, i)):
            out.accepted.append(self._pop(i))
        return out

    def _look_alike_verdicts(self, searched: list[CycleCheck]) -> set[int]:
        """The hypotheses whose consistent cycles fit their match better than its look-alike
        (module docstring, "Look-alikes"): the least chi-square of a consistent cycle through
        ``h`` below the least with ``h`` moved to its look-alike. A hypothesis without a
        look-alike, or on no consistent cycle, is not in question: it is in the set."""
        best: dict[int, float] = {}
        best_alt: dict[int, float] = {}
        for c in searched:
            if not c.consistent or not c.look_alike_chi2:
                continue
            for i, alt in zip(c.hyp_ids, c.look_alike_chi2, strict=True):
                if math.isfinite(alt):
                    best[i] = min(best.get(i, math.inf), c.chi2)
                    best_alt[i] = min(best_alt.get(i, math.inf), alt)
        margin = self.config.look_alike_margin
        doubtful = {i for i in best if best_alt[i] + margin <= best[i]}
        return set(self._pending) - doubtful

    def _off_a_known_path(self, h: Hypothesis, known: Link, offset: FloatArray) -> bool:
        """Whether the graph's path ``known`` between ``h``'s nodes places them further from
        ``h`` (``offset``, the composed ``h * known^-1``) than ``graph_offset_m`` or
        ``graph_offset_rad``, and by more than the path's own covariance (and the floors)
        allow: the graph alone then tells that ``h`` is off by nearly a false closure's
        margin, whatever the match's own covariance would excuse (config docstring)."""
        cfg = self.config
        if cfg.graph_offset_m <= 0.0 and cfg.graph_offset_rad <= 0.0:
            return False
        far = (
            cfg.graph_offset_m > 0.0 and math.hypot(offset[0], offset[1]) > cfg.graph_offset_m
        ) or (
            cfg.graph_offset_rad > 0.0
            and abs(float(se2.wrap_angle(offset[2]))) > cfg.graph_offset_rad
        )
        if not far:
            return False
        floor = np.diag(
            [cfg.floor_sigma_xy_m**2, cfg.floor_sigma_xy_m**2, cfg.floor_sigma_yaw_rad**2]
        )
        z = np.asarray(h.a_from_b, dtype=np.float64)
        pose, cov = compose_with_covariance([(z, floor), _inverse(known)])
        return _chi2(pose, cov) > cfg.chi2_threshold

    def _share_a_node(self, hyp_ids: tuple[int, ...]) -> bool:
        """Whether two hypotheses of a cycle share a node (module docstring, "Shared
        data")."""
        ends = [k for i in hyp_ids for k in (self._pending[i].key_a, self._pending[i].key_b)]
        return len(set(ends)) < len(ends)

    def _pop(self, hyp_id: int) -> Hypothesis:
        self._checked.pop(hyp_id, None)
        return self._pending.pop(hyp_id)

    def _group_verdicts(
        self,
        searched: list[CycleCheck],
        links: LinksFn,
        link_cache: dict[int, dict[int, _T]],
        out: ValidationResult,
    ) -> tuple[set[int], set[int]]:
        """The group test (module docstring, "Groups"): ``(promoted, outliers)`` over the
        groups of hypotheses joined by the cycles in ``searched``; each group tested is
        appended to ``out.groups``."""
        cfg = self.config
        need = max(cfg.min_cycle_hypotheses, cfg.group_min_support)
        parent: dict[int, int] = {}

        def find(i: int) -> int:
            while parent.setdefault(i, i) != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for c in searched:
            if len(c.hyp_ids) >= 2:
                for i in c.hyp_ids[1:]:
                    parent[find(i)] = find(c.hyp_ids[0])
        groups: dict[int, set[int]] = {}
        for i in list(parent):
            groups.setdefault(find(i), set()).add(i)
        promoted: set[int] = set()
        outliers: set[int] = set()
        for members in sorted(groups.values(), key=min):
            members = set(members)
            removed: list[int] = []
            while True:
                inner = [c for c in searched if len(c.hyp_ids) >= 2 and members >= set(c.hyp_ids)]
                failing = [c for c in inner if not c.consistent]
                fit = self._group_fit(members, links, link_cache)
                ok = not failing and fit.chi2 <= _chi2_quantile(cfg.group_quantile, fit.dof)
                out.groups.append(
                    GroupCheck(tuple(sorted(members)), fit.chi2, fit.dof, ok, tuple(removed))
                )
                if ok:
                    break
                # one more outlier out, if few were and enough members would remain
                if len(members) - 1 < need or len(removed) >= cfg.group_max_outliers:
                    members = set()
                    break
                suspects = {i for c in failing for i in c.hyp_ids} or members
                worst = max(sorted(suspects), key=lambda i: fit.contribution.get(i, 0.0))
                members.discard(worst)
                removed.append(worst)
            confirmed = {
                i
                for c in searched
                if c.consistent
                and len(c.hyp_ids) >= cfg.min_cycle_hypotheses
                and members >= set(c.hyp_ids)
                for i in c.hyp_ids
            }
            if confirmed:
                promoted |= confirmed
                outliers.update(removed)
        return promoted, outliers

    def _group_fit(
        self, members: set[int], links: LinksFn, link_cache: dict[int, dict[int, _T]]
    ) -> _GroupFit:
        """Least squares over the group's hypotheses and the graph's links between their
        nodes (a spanning forest of the tightest links: links along one chain share its
        odometry, so only a forest of them is independent); chi-square at the optimum,
        degrees of freedom ``3 (E - V + C)`` and each hypothesis's share of the chi-square."""
        hyps = [self._pending[i] for i in sorted(members)]
        nodes = sorted({k for h in hyps for k in (h.key_a, h.key_b)})
        col = {k: i for i, k in enumerate(nodes)}
        edges: list[tuple[int, int, FloatArray, FloatArray, int]] = []
        for h in hyps:
            z, cov = self._floored(h)
            edges.append((col[h.key_a], col[h.key_b], z, cov, h.hyp_id))
        candidates: list[tuple[float, int, int, _T]] = []
        for a in nodes:
            if a not in link_cache:
                found = {k: _to_t(*v) for k, v in links(a).items()}
                found.setdefault(a, _ZERO)
                link_cache[a] = found
            for b, t in link_cache[a].items():
                if b != a and b in col and a < b:
                    candidates.append((t[3] + t[6] + t[8], a, b, t))
        parent = list(range(len(nodes)))

        def find(i: int) -> int:
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for _, a, b, t in sorted(candidates, key=lambda c: (c[0], c[1], c[2])):
            ra, rb = find(col[a]), find(col[b])
            if ra != rb:
                parent[ra] = rb
                z, cov = _from_t(t)
                edges.append((col[a], col[b], z, cov, -1))
        for i, j, *_ in edges:
            parent[find(i)] = find(j)
        roots = sorted({find(i) for i in range(len(nodes))})
        dof = 3 * (len(edges) - len(nodes) + len(roots))
        poses = _initial_poses(len(nodes), edges, roots)
        chi2, contribution = _solve_group(poses, edges, roots, self.config.group_max_iterations)
        return _GroupFit(chi2, dof, contribution)

    def _search(
        self, links: LinksFn, link_cache: dict[int, dict[int, _T]] | None = None
    ) -> list[tuple[tuple[int, ...], FloatArray, FloatArray, _Walk]]:
        """Depth-limited search for cycles ``h, link, h, link, ...`` of 2 or more hypotheses.

        A cycle is searched from its lowest-id hypothesis, traversed from ``key_a`` to
        ``key_b``, and reported once per distinct cyclic sequence of hypotheses (the first
        link found closes it). The composition is carried along the search (one step per
        edge, scalar arithmetic). When a search would take more than ``max_search_steps``
        extensions it is redone with two hypotheses per cycle; if even that is too long no
        cycle is reported (nothing is promoted this time: never an incomplete verdict).
        Returns ``(hyp_ids, composed pose, covariance, walk)``; ``walk`` is the traversal,
        ``((hyp_id, forward), ...)`` in the order composed (:meth:`_recompose`).
        """
        cfg = self.config
        depth = cfg.max_cycle_hypotheses
        if len(self._pending) > cfg.deep_search_max_pending:
            depth = min(depth, 2)
        if link_cache is None:
            link_cache = {}
        while True:
            found = self._search_depth(links, depth, link_cache)
            if found is not None:
                return [(ids, *_from_t(t), walk) for ids, (t, walk) in found.items()]
            if depth <= 2:
                return []
            depth = 2

    def _search_depth(
        self, links: LinksFn, max_h: int, link_cache: dict[int, dict[int, _T]]
    ) -> dict[tuple[int, ...], tuple[_T, _Walk]] | None:
        hyps = self.pending
        by_node: dict[int, list[tuple[int, _T, int, bool]]] = {}
        for h in hyps:
            fwd = _to_t(*self._floored(h))
            by_node.setdefault(h.key_a, []).append((h.hyp_id, fwd, h.key_b, True))
            by_node.setdefault(h.key_b, []).append((h.hyp_id, _inverse_t(fwd), h.key_a, False))

        def links_of(key: int) -> dict[int, _T]:
            if key not in link_cache:
                found = {k: _to_t(*v) for k, v in links(key).items()}
                found.setdefault(key, _ZERO)  # a node links itself
                link_cache[key] = found
            return link_cache[key]

        found: dict[tuple[int, ...], tuple[_T, _Walk]] = {}
        budget = [self.config.max_search_steps]

        def extend(
            start_key: int, at_key: int, used: tuple[int, ...], acc: _T, walk: _Walk
        ) -> bool:
            budget[0] -= 1
            if budget[0] < 0:
                return False
            reach = links_of(at_key)
            if len(used) >= 2 and start_key in reach:  # close the cycle back to the start
                rev = used[::-1]
                canon = min(
                    min(used[i:] + used[:i] for i in range(len(used))),
                    min(rev[i:] + rev[:i] for i in range(len(rev))),
                )
                if canon not in found:
                    found[canon] = (_compose_t(acc, reach[start_key]), walk)
            if len(used) >= max_h:
                return True
            if len(reach) <= len(by_node):
                near = [(node, reach[node]) for node in reach if node in by_node]
            else:
                near = [(node, reach[node]) for node in by_node if node in reach]
            for node, link in near:
                via = None
                for hid, step, nxt, forward in by_node[node]:
                    if hid in used or hid < used[0]:
                        continue
                    if via is None:
                        via = _compose_t(acc, link)
                    if not extend(
                        start_key,
                        nxt,
                        (*used, hid),
                        _compose_t(via, step),
                        (*walk, (hid, forward)),
                    ):
                        return False
            return True

        for h in hyps:
            # start at key_a, traverse h first; only cycles whose lowest id is h are searched
            start = _to_t(*self._floored(h))
            if not extend(h.key_a, h.key_b, (h.hyp_id,), start, ((h.hyp_id, True),)):
                return None
        return found

    def _recompose(
        self,
        walk: _Walk,
        link_cache: dict[int, dict[int, _T]],
        swap: int,
        alternative: FloatArray,
    ) -> float:
        """The chi-square of the cycle ``walk`` (as :meth:`_search_depth` composed it) with
        hypothesis ``swap``'s match replaced by ``alternative`` (same covariance); inf when a
        link of the walk is no longer cached."""
        acc: _T | None = None
        first = self._pending[walk[0][0]]
        start_key = first.key_a if walk[0][1] else first.key_b
        at_key = start_key
        for hid, forward in walk:
            h = self._pending[hid]
            z, cov = self._floored(h)
            step = _to_t(alternative if hid == swap else z, cov)
            if not forward:
                step = _inverse_t(step)
            begin, end = (h.key_a, h.key_b) if forward else (h.key_b, h.key_a)
            if acc is None:
                acc = step
            else:
                link = link_cache.get(at_key, {}).get(begin)
                if link is None:
                    return math.inf
                acc = _compose_t(_compose_t(acc, link), step)
            at_key = end
        assert acc is not None
        back = link_cache.get(at_key, {}).get(start_key)
        if back is None:
            return math.inf
        return _chi2(*_from_t(_compose_t(acc, back)))


# A pose with its covariance as plain floats (x, y, theta, c00, c01, c02, c11, c12, c22):
# the cycle search composes many of them, far faster than with small numpy arrays.
_T = tuple[float, float, float, float, float, float, float, float, float]
_Walk = tuple[tuple[int, bool], ...]  # a cycle's hypotheses in order, each (id, forward)
_ZERO: _T = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


def _to_t(pose: FloatArray, cov: FloatArray) -> _T:
    return (
        float(pose[0]), float(pose[1]), float(pose[2]),
        float(cov[0, 0]), float(cov[0, 1]), float(cov[0, 2]),
        float(cov[1, 1]), float(cov[1, 2]), float(cov[2, 2]),
    )  # fmt: skip


def _from_t(t: _T) -> tuple[FloatArray, FloatArray]:
    _, _, _, a, b, c, d, e, f = t
    return np.array(t[:3]), np.array([[a, b, c], [b, d, e], [c, e, f]])


def _inverse_t(t: _T) -> _T:
    """``z^-1`` with covariance ``Ad_z cov Ad_z'``."""
    x, y, th, a, b, c3, d, e, f = t
    c, s = math.cos(th), math.sin(th)
    # Ad_z = [[c, -s, y], [s, c, -x], [0, 0, 1]]
    m00, m01, m02 = c * a - s * b + y * c3, c * b - s * d + y * e, c * c3 - s * e + y * f
    m10, m11, m12 = s * a + c * b - x * c3, s * b + c * d - x * e, s * c3 + c * e - x * f
    return (
        -c * x - s * y, s * x - c * y, (math.pi - th) % (2.0 * math.pi) - math.pi,
        m00 * c - m01 * s + m02 * y, m00 * s + m01 * c - m02 * x, m02,
        m10 * s + m11 * c - m12 * x, m12, f,
    )  # fmt: skip


def _compose_t(p: _T, z: _T) -> _T:
    """``p * z`` with ``cov = Ad(z^-1) cov_p Ad(z^-1)' + cov_z``."""
    px, py, pt, a, b, c3, d, e, f = p
    zx, zy, zt = z[0], z[1], z[2]
    c, s = math.cos(zt), math.sin(zt)
    ix = -c * zx - s * zy
    iy = s * zx - c * zy
    # A = Ad(z^-1) = [[c, s, iy], [-s, c, -ix], [0, 0, 1]]; M = A P
    m00, m01, m02 = c * a + s * b + iy * c3, c * b + s * d + iy * e, c * c3 + s * e + iy * f
    m10, m11, m12 = -s * a + c * b - ix * c3, -s * b + c * d - ix * e, -s * c3 + c * e - ix * f
    cp, sp = math.cos(pt), math.sin(pt)
    th = (pt + zt + math.pi) % (2.0 * math.pi) - math.pi
    return (
        px + cp * zx - sp * zy, py + sp * zx + cp * zy, th,
        m00 * c + m01 * s + m02 * iy + z[3],
        -m00 * s + m01 * c - m02 * ix + z[4],
        m02 + z[5],
        -m10 * s + m11 * c - m12 * ix + z[6],
        m12 + z[7],
        f + z[8],
    )  # fmt: skip


def _compose2(first: Link, step: Link) -> Link:
    """``first * step`` with ``cov = Ad(step^-1) cov_first Ad(step^-1)' + cov_step``."""
    return _from_t(_compose_t(_to_t(*first), _to_t(*step)))


@functools.cache
def _chi2_quantile(q: float, dof: int) -> float:
    return float(scipy.stats.chi2.ppf(q, dof)) if dof > 0 else math.inf


_Edge = tuple[int, int, FloatArray, FloatArray, int]


def _initial_poses(n: int, edges: list[_Edge], roots: list[int]) -> FloatArray:
    """Poses of the group's nodes composed along a breadth-first tree from each component's
    root (the root at the origin: a group's fit is relative)."""
    poses = np.zeros((n, 3))
    adj: dict[int, list[tuple[int, FloatArray, bool]]] = {}
    for i, j, z, _cov, _h in edges:
        adj.setdefault(i, []).append((j, z, True))
        adj.setdefault(j, []).append((i, z, False))
    seen = [False] * n
    for r in roots:
        # the component's root: find() gave a representative; any member is as good
        queue = [r]
        seen[r] = True
        while queue:
            i = queue.pop()
            for j, z, forward in adj.get(i, []):
                if seen[j]:
                    continue
                seen[j] = True
                poses[j] = se2.compose(poses[i], z if forward else se2.inverse(z))
                queue.append(j)
    return poses


def _solve_group(
    poses: FloatArray, edges: list[_Edge], roots: list[int], iterations: int
) -> tuple[float, dict[int, float]]:
    """Gauss-Newton on the group's poses (each component's root held), error of an edge
    ``i -> j`` with measurement ``z``: ``(Rz' (Ri' (tj - ti) - tz), wrap(thj - thi - thz))``
    weighted by its covariance. Returns the chi-square at the end and each hypothesis's part
    of it (by hypothesis id; links are ``-1`` and left out)."""
    n = len(poses)
    info = [np.linalg.inv(cov) for _i, _j, _z, cov, _h in edges]
    held = np.zeros(3 * n, dtype=bool)
    for root in roots:
        held[3 * root : 3 * root + 3] = True
    free = ~held

    def residuals(x: FloatArray) -> list[FloatArray]:
        out = []
        for i, j, z, _cov, _h in edges:
            ci, si = math.cos(x[i, 2]), math.sin(x[i, 2])
            cz, sz = math.cos(z[2]), math.sin(z[2])
            dx, dy = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1]
            ux, uy = ci * dx + si * dy - z[0], -si * dx + ci * dy - z[1]
            out.append(
                np.array(
                    [
                        cz * ux + sz * uy,
                        -sz * ux + cz * uy,
                        float(se2.wrap_angle(x[j, 2] - x[i, 2] - z[2])),
                    ]
                )
            )
        return out

    def total(res: list[FloatArray]) -> float:
        return float(sum(r @ w @ r for r, w in zip(res, info, strict=True)))

    x = poses.copy()
    res = residuals(x)
    chi2 = total(res)
    for _ in range(iterations):
        h = np.zeros((3 * n, 3 * n))
        g = np.zeros(3 * n)
        for (i, j, z, _cov, _hid), r, w in zip(edges, res, info, strict=True):
            ci, si = math.cos(x[i, 2]), math.sin(x[i, 2])
            cz, sz = math.cos(z[2]), math.sin(z[2])
            rz_t = np.array([[cz, sz], [-sz, cz]])
            ri_t = np.array([[ci, si], [-si, ci]])
            dri_t = np.array([[-si, ci], [-ci, -si]])
            d = x[j, :2] - x[i, :2]
            jac_i = np.zeros((3, 3))
            jac_j = np.zeros((3, 3))
            jac_i[:2, :2] = -rz_t @ ri_t
            jac_i[:2, 2] = rz_t @ dri_t @ d
            jac_i[2, 2] = -1.0
            jac_j[:2, :2] = rz_t @ ri_t
            jac_j[2, 2] = 1.0
            blocks = ((i, jac_i), (j, jac_j))
            for a, ja in blocks:
                g[3 * a : 3 * a + 3] += ja.T @ w @ r
                for b, jb in blocks:
                    h[3 * a : 3 * a + 3, 3 * b : 3 * b + 3] += ja.T @ w @ jb
        try:
            step = np.linalg.solve(h[np.ix_(free, free)], -g[free])
        except np.linalg.LinAlgError:
            break
        trial = x.copy()
        trial.reshape(-1)[free] += step
        trial[:, 2] = se2.wrap_angle(trial[:, 2])
        trial_res = residuals(trial)
        trial_chi2 = total(trial_res)
        if trial_chi2 > chi2:  # a step that makes things worse is not taken
            break
        done = chi2 - trial_chi2 < 1e-9 * max(chi2, 1.0)
        x, res, chi2 = trial, trial_res, trial_chi2
        if done:
            break
    contribution = {
        hid: float(r @ w @ r)
        for (_i, _j, _z, _cov, hid), r, w in zip(edges, res, info, strict=True)
        if hid >= 0
    }
    return chi2, contribution
