"""Long-loop candidates: place recognition where the Dijkstra projection cannot bound a search.

The loop closer's candidates (:mod:`gcs.loops.candidate_search`, paper 4.3.3) come from the
Dijkstra projection: a pair is searched in a window that holds the ``k_sigma`` region of the
graph's relative-pose uncertainty, at most the bounded *wide* window. After a loop of 100 m
and more, or across lost scans (a gap widens the yaw covariance to the log's turning), that
region is larger than any window: such a revisit gets no candidate at all and the loop stays
open. :class:`LongLoopSearch` is a second candidate source for exactly those pairs:

1. **Recognize**: the new node's polar descriptor (:mod:`gcs.loops.place_recognition`)
   against the stored nodes that pass step 2's gates; the ``query_k`` nearest within
   ``max_descriptor_distance``, same-robot nodes fewer than ``min_index_gap`` apart left out.
2. **Gate on the graph** (one full Dijkstra projection from the new node): a node whose
   projected uncertainty fits the closer's wide window is the regular search's (left out
   here); a node in another component is left out (no bound at all: linking robots is for
   fiducials and operators); a node whose ``k_sigma`` region does not come within
   ``max_distance_m`` is left out (the graph says it is elsewhere). When the projection's yaw
   is bounded (``k_sigma`` sigma under ``yaw_gate_max_rad``), the descriptor's yaw must fall
   in its ``k_sigma`` interval, widened by one sector. ``k_sigma`` is the regular search's
   3: the region is where the graph allows the place to be. A larger one would let in the
   places the graph rightly excludes (ACES: a corridor 25 m along matches "here" with
   score 0.7, consistently from node to node, where the graph says 20 m +- 4.2 m), at the
   price of the case where the graph is overconfident (across an odometry gap the replay's
   widened yaw sigma was 8 deg for a 28 deg error): that one is for the gap's covariance to
   state honestly, not for this gate to guess (:func:`mission.replay.odometry_gaps` now
   widens it by the log's own stretches of the gap's length and duration: ACES with a tenth
   of its scans dropped closes 5 of 36 long-loop revisits, was 0, ATE 0.78 m, was 5.07 m).
   When the yaw is bounded, a verified match must
   also agree with the projection (chi-square ``confirm_chi2`` on the sum of the two
   covariances): the region gate alone lets in a place 3.8 sigma along a corridor.
   Place recognition then ranks only the nodes that passed (Scan Context's ring key, then
   full descriptors): among a region's nodes the true place ranks near the top, among all
   nodes of a building it rarely does (ACES: top-1 13 %, top-5 44 %).
3. **Verify** the ``top_k`` best-ranked by the correlative matcher over a window around the
   descriptor's guess (translation 0: the same place; yaw: the descriptor's column shift):
   ``window_xy_m``, ``window_yaw_rad``; the match must reach ``min_score`` (the closer then
   drops ambiguous, corridor-like matches by their response surface, as for its own). A match
   costs about 10 ms (ACES, +-4 m, +-30 deg), so several per node are affordable.
4. **Unique**: a node whose matches disagree on where it is (``b1_from_b2`` they imply against
   the graph's path, chi-square ``confirm_chi2``, or no such path) sees an aliased view: none
   of its matches is kept.
5. **Confirm**: a match is released only once another match, made from a node at least
   ``confirm_min_separation_m`` away (another view, tightly linked to the first by the
   graph: ``confirm_link_sigma_xy_m``), closes a consistent cycle with it through the graph's
   path between the two stored nodes (chi-square ``confirm_chi2``); matches wait
   ``confirm_window_s``. 1.5 m, not more: a revisit can be brief (ACES crosses its start
   while turning: its 12 true matches came from nodes within 4 m of each other). Two
   matches of one view agree by construction, even when aliased;
   separated views still agree on a consistent shift along a corridor (ACES above), which
   only step 2 excludes.

What comes out is a match, not a closure: the loop closer turns it into a hypothesis that must
still close a consistent cycle with another hypothesis (:mod:`gcs.loops.cycle_validation`,
``min_cycle_hypotheses`` >= 2, checked by the closer's config) before it enters the graph; a
long loop is never closed on one match. Matching is rationed on the caller's progress clock
(``matches_per_s`` with a burst of ``max_burst_matches``): a node that finds no token is not
retried, the next nodes of the revisit are. A pair is matched at most once.

Cost per new node: one full Dijkstra projection and the gates over every node (measured 4 ms
at 1,000 nodes, 33 ms at 10,000 on the loaded 2-core machine), a descriptor query, and at
most ``top_k`` matches when tokens allow; a node is searched once per scan (a restart or a
component merge makes every node a source of the regular search again, not of this one).

Frames: points in each node's ``base``; ``a_from_b`` from the new node (reference, its table
built) to the stored one (query). Units: metres, radians, progress seconds.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

from gcs.graph import se2
from gcs.graph.dijkstra_projection import ProjectionResult
from gcs.loops.candidate_search import body_to_vector_covariance
from gcs.loops.correlative_matcher import (
    CorrelativeMatcher,
    MatcherConfig,
    MatchResult,
    ReferenceTable,
    points_grid,
)
from gcs.loops.cycle_validation import compose_with_covariance
from gcs.loops.place_recognition import PlaceDescriptorConfig, PlaceIndex, PlaceMatch

__all__ = ["LongLoopConfig", "LongLoopMatch", "LongLoopSearch", "LongLoopStats"]

FloatArray = NDArray[Any]


class LongLoopConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The long-loop candidate source (module docstring); metres, radians, progress seconds."""

    enabled: bool = True
    descriptor: PlaceDescriptorConfig = msgspec.field(default_factory=PlaceDescriptorConfig)
    max_descriptor_distance: float = 0.7
    query_k: int = 12
    prefilter: int = 30
    top_k: int = 4
    min_index_gap: int = 40
    k_sigma: float = 3.0
    max_distance_m: float = 5.0
    yaw_gate_max_rad: float = math.pi / 2
    window_xy_m: float = 4.0
    window_yaw_rad: float = math.radians(30.0)
    min_score: float = 0.65
    matches_per_s: float = 2.0
    max_burst_matches: float = 8.0
    table_cache: int = 4
    confirm_min_separation_m: float = 1.5
    confirm_link_sigma_xy_m: float = 0.5
    confirm_chi2: float = 11.34
    confirm_window_s: float = 60.0
    max_pending: int = 64
    confirm_floor_sigma_xy_m: float = 0.05
    confirm_floor_sigma_yaw_rad: float = math.radians(1.0)

    def __post_init__(self) -> None:
        if not 0 < self.max_descriptor_distance <= 1:
            raise ValueError(
                f"max_descriptor_distance: expected in (0, 1], got {self.max_descriptor_distance}"
            )
        for name in ("query_k", "prefilter", "top_k", "table_cache", "max_pending"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if self.min_index_gap < 1:
            raise ValueError(f"min_index_gap: expected >= 1, got {self.min_index_gap}")
        for name in (
            "k_sigma",
            "max_distance_m",
            "yaw_gate_max_rad",
            "window_xy_m",
            "window_yaw_rad",
            "matches_per_s",
            "max_burst_matches",
            "confirm_min_separation_m",
            "confirm_link_sigma_xy_m",
            "confirm_chi2",
            "confirm_window_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v}")
        if self.window_yaw_rad > math.pi or self.window_xy_m > 20:
            raise ValueError("need window_yaw_rad <= pi and window_xy_m <= 20")
        if not 0 <= self.min_score <= 1:
            raise ValueError(f"min_score: expected in [0, 1], got {self.min_score}")
        if self.max_burst_matches < 1:
            raise ValueError(f"max_burst_matches: expected >= 1, got {self.max_burst_matches}")


@dataclass
class LongLoopStats:
    """Counters since construction."""

    described: int = 0
    recognized: int = 0  # descriptor matches within max_descriptor_distance
    queries: int = 0  # new nodes with stored nodes beyond the regular search, in the region
    gated_yaw: int = 0
    no_token: int = 0
    matches: int = 0
    below_min_score: int = 0
    found: int = 0
    disagree_graph: int = 0  # matches outside the projection's chi-square region
    ambiguous_place: int = 0  # matches of a node whose matches disagreed (aliasing)
    confirmed: int = 0  # pairs of matches from separated nodes that agreed


@dataclass(frozen=True)
class LongLoopMatch:
    """A verified match: ``a_from_b`` (``key_a`` the new node) with the matcher's result."""

    key_a: int
    key_b: int
    result: MatchResult
    descriptor_distance: float


class LongLoopSearch:
    """Place-recognition candidates verified by the correlative matcher (module docstring)."""

    def __init__(self, config: LongLoopConfig, *, matcher: MatcherConfig, resolution_m: float):
        self.config = config
        self.resolution_m = resolution_m
        self._index = PlaceIndex(config.descriptor)
        self._matcher = CorrelativeMatcher(
            msgspec.structs.replace(
                matcher, search_xy_m=config.window_xy_m, search_yaw_rad=config.window_yaw_rad
            )
        )
        self._tables: OrderedDict[int, ReferenceTable] = OrderedDict()
        self._tried: set[tuple[int, int]] = set()
        self._done: dict[int, FloatArray] = {}  # node -> the scan it was searched with
        # matches waiting for a second, agreeing one: (match, made at, released)
        self._pending: list[tuple[LongLoopMatch, float, bool]] = []
        self._tokens = float(config.max_burst_matches)
        self._clock_s: float | None = None
        self.stats = LongLoopStats()

    def add_scan(self, key: int, points_in_base: FloatArray) -> None:
        """Describe ``key``'s scan (a second scan replaces the first)."""
        self._index.add(int(key), self._index.describe(points_in_base))
        self._tables.pop(int(key), None)
        self.stats.described += 1

    def propose(
        self,
        key: int,
        *,
        scans: Mapping[int, FloatArray],
        keys: NDArray[np.int64],
        index_of: Mapping[int, int],
        robot_ids: NDArray[np.int64],
        indices: NDArray[np.int64],
        project: Callable[[], ProjectionResult],
        path: Callable[[int, int], tuple[FloatArray, FloatArray] | None],
        regular_xy_m: float,
        regular_yaw_rad: float,
        regular_k_sigma: float,
        progress_s: float,
    ) -> list[LongLoopMatch]:
        """Verified matches of the new node ``key`` against earlier places (module docstring).

        ``keys``/``robot_ids``/``indices`` describe the graph's nodes (``index_of`` maps a key
        to its row), ``project()`` runs the full Dijkstra projection from ``key`` (rows as
        ``keys``; called only when a place was recognized), ``regular_*`` is the regular
        search's wide window and ``k_sigma`` (pairs it covers are left to it), ``progress_s``
        the caller's progress clock (refills the match tokens; never goes back).
        """
        cfg = self.config
        self._refill(progress_s)
        if key not in index_of or key not in scans:
            return []
        if self._done.get(key) is scans[key]:
            # once per scan: a restart or a merge makes every node a source again, and the
            # regular search needs that step's budget (this source's pairs were tried)
            return []
        self._done[key] = scans[key]
        self.add_scan(key, scans[key])  # (re)described: a second scan of a node replaces it
        row = index_of[key]
        if len(self._index) < 2:
            return []
        proj = project()
        ok = proj.reached & ~(
            (robot_ids == robot_ids[row]) & (np.abs(indices - indices[row]) < cfg.min_index_gap)
        )
        ok[row] = False
        rows = np.nonzero(ok)[0]
        if len(rows) == 0:
            return []
        poses = np.asarray(proj.poses)[rows]
        cov = body_to_vector_covariance(poses, np.asarray(proj.covariances)[rows])
        # the larger eigenvalue of each 2x2 translation block, in closed form (every node)
        half_tr = 0.5 * (cov[:, 0, 0] + cov[:, 1, 1])
        half_df = 0.5 * (cov[:, 0, 0] - cov[:, 1, 1])
        sxy = np.sqrt(np.maximum(half_tr + np.hypot(half_df, cov[:, 0, 1]), 0.0))
        syaw = np.sqrt(np.maximum(cov[:, 2, 2], 0.0))
        regular = (regular_k_sigma * sxy <= regular_xy_m) & (
            regular_k_sigma * syaw <= regular_yaw_rad
        )
        region = np.hypot(poses[:, 0], poses[:, 1]) - cfg.k_sigma * sxy <= cfg.max_distance_m
        keep = ~regular & region
        if not keep.any():
            return []
        self.stats.queries += 1
        where = {int(keys[r]): i for i, r in enumerate(rows) if keep[i]}
        found = self._index.query(
            self._index.descriptor(key),
            allowed=np.fromiter(where, dtype=np.int64, count=len(where)),
            k=cfg.query_k,
            prefilter=cfg.prefilter,
            max_distance=cfg.max_descriptor_distance,
        )
        found = [
            m
            for m in found
            if (min(key, m.key), max(key, m.key)) not in self._tried and m.key in scans
        ]
        self.stats.recognized += len(found)
        sector = 2.0 * math.pi / cfg.descriptor.sectors
        gated: list[tuple[PlaceMatch, FloatArray, FloatArray, bool]] = []
        for m in found:
            i = where[m.key]
            pose, yaw_sigma = poses[i], float(syaw[i])
            yaw_bounded = cfg.k_sigma * yaw_sigma < cfg.yaw_gate_max_rad
            if yaw_bounded and abs(_wrap(m.yaw_rad - float(pose[2]))) > (
                cfg.k_sigma * yaw_sigma + sector
            ):
                self.stats.gated_yaw += 1
                continue
            gated.append((m, pose, cov[i], yaw_bounded))
        out: list[LongLoopMatch] = []
        for m, pose, pose_cov, yaw_bounded in gated[: cfg.top_k]:
            if self._tokens < 1.0:
                self.stats.no_token += 1
                break
            self._tokens -= 1.0
            self._tried.add((min(key, m.key), max(key, m.key)))
            self.stats.matches += 1
            guess = np.array([0.0, 0.0, m.yaw_rad])
            result = self._matcher.match(
                self._table(key, scans[key]), scans[m.key], guess, min_score=cfg.min_score
            )
            if result is None:
                self.stats.below_min_score += 1
                continue
            if yaw_bounded and not self._agrees(result, pose, pose_cov):
                self.stats.disagree_graph += 1
                continue
            out.append(LongLoopMatch(int(key), int(m.key), result, m.distance))
        if not self._unique(out, path):
            self.stats.ambiguous_place += len(out)
            return self._confirm(key, [], proj, index_of, path, progress_s)
        self.stats.found += len(out)
        return self._confirm(key, out, proj, index_of, path, progress_s)

    def _agrees(self, result: MatchResult, pose: FloatArray, cov_xyt: FloatArray) -> bool:
        """The match against the projection ``a_from_b`` (vector components): chi-square of
        their difference on the sum of both covariances, at most ``confirm_chi2``."""
        r = np.asarray(result.a_from_b, dtype=np.float64) - np.asarray(pose, dtype=np.float64)
        r[2] = _wrap(float(r[2]))
        s = np.asarray(cov_xyt, dtype=np.float64) + np.asarray(result.covariance)
        try:
            return float(r @ np.linalg.solve(s, r)) <= self.config.confirm_chi2
        except np.linalg.LinAlgError:
            return False

    def _unique(
        self,
        matches: list[LongLoopMatch],
        path: Callable[[int, int], tuple[FloatArray, FloatArray] | None],
    ) -> bool:
        """Whether one node's matches agree on where it is: for every two of them, ``b1_from_b2``
        implied by the matches against the graph's path between ``b1`` and ``b2`` (chi-square,
        ``confirm_chi2``). A view that matches two places the graph holds apart is aliased
        (a corridor, a repeated facade): none of its matches is kept."""
        for i, m1 in enumerate(matches):
            for m2 in matches[i + 1 :]:
                if m1.key_b == m2.key_b:
                    continue
                known = path(m1.key_b, m2.key_b)
                if known is None:  # the graph holds them far apart: two places
                    return False
                cycle = compose_with_covariance(
                    [_inverse_link(self._link(m1)), self._link(m2), _inverse_link(known)]
                )
                if _chi2(*cycle) > self.config.confirm_chi2:
                    return False
        return True

    def _confirm(
        self,
        key: int,
        new: list[LongLoopMatch],
        proj: ProjectionResult,
        index_of: Mapping[int, int],
        path: Callable[[int, int], tuple[FloatArray, FloatArray] | None],
        progress_s: float,
    ) -> list[LongLoopMatch]:
        """Release matches that another match, made from a node at least
        ``confirm_min_separation_m`` away, agrees with (module docstring, step 4)."""
        cfg = self.config
        self._pending = [p for p in self._pending if progress_s - p[1] <= cfg.confirm_window_s][
            -cfg.max_pending :
        ]
        released: list[LongLoopMatch] = []
        for m in new:
            for i, (other, _t, done) in enumerate(self._pending):
                j = index_of.get(other.key_a)
                if j is None or not proj.reached[j]:
                    continue
                a_from_a2 = np.asarray(proj.poses[j], dtype=np.float64)
                link_cov = np.asarray(proj.covariances[j], dtype=np.float64)
                sep = math.hypot(a_from_a2[0], a_from_a2[1])
                if sep < cfg.confirm_min_separation_m or (
                    max(link_cov[0, 0], link_cov[1, 1]) > cfg.confirm_link_sigma_xy_m**2
                ):
                    continue
                b_path = path(m.key_b, other.key_b)
                if b_path is None:
                    continue
                cycle = compose_with_covariance(
                    [
                        self._link(m),
                        b_path,
                        _inverse_link(self._link(other)),
                        _inverse_link((a_from_a2, link_cov)),
                    ]
                )
                if _chi2(*cycle) > cfg.confirm_chi2:
                    continue
                self.stats.confirmed += 1
                if not done:
                    released.append(other)
                    self._pending[i] = (other, _t, True)
                if m not in released:
                    released.append(m)
            self._pending.append((m, progress_s, m in released))
        return released

    def _link(self, m: LongLoopMatch) -> tuple[FloatArray, FloatArray]:
        """A match as ``(a_from_b, body-frame covariance)`` with the validator's floor."""
        z = np.asarray(m.result.a_from_b, dtype=np.float64)
        flip = z.copy()
        flip[2] = -flip[2]
        cov = body_to_vector_covariance(flip, np.asarray(m.result.covariance, dtype=np.float64))
        sxy, syaw = self.config.confirm_floor_sigma_xy_m, self.config.confirm_floor_sigma_yaw_rad
        floor = np.diag([sxy**2, sxy**2, syaw**2])
        return z, 0.5 * (cov + cov.T) + floor

    def _refill(self, progress_s: float) -> None:
        if self._clock_s is None:
            self._clock_s = progress_s
            return
        elapsed = progress_s - self._clock_s
        if elapsed > 0:
            self._clock_s = progress_s
            self._tokens = min(
                self.config.max_burst_matches, self._tokens + self.config.matches_per_s * elapsed
            )

    def _table(self, key: int, points: FloatArray) -> ReferenceTable:
        table = self._tables.get(key)
        if table is not None:
            self._tables.move_to_end(key)
            return table
        grid, origin = points_grid(points, resolution_m=self.resolution_m)
        table = self._matcher.reference_table(grid, origin_m=origin, resolution_m=self.resolution_m)
        self._tables[key] = table
        while len(self._tables) > self.config.table_cache:
            self._tables.popitem(last=False)
        return table


def _inverse_link(link: tuple[FloatArray, FloatArray]) -> tuple[FloatArray, FloatArray]:
    """``z^-1`` with covariance ``Ad_z cov Ad_z'`` (body frames)."""
    z, cov = link
    ad = se2.adjoint(z)
    return np.asarray(se2.inverse(z), dtype=np.float64), ad @ cov @ ad.T


def _chi2(pose: FloatArray, cov: FloatArray) -> float:
    r = np.array([pose[0], pose[1], _wrap(float(pose[2]))])
    try:
        return float(r @ np.linalg.solve(cov, r))
    except np.linalg.LinAlgError:
        return math.inf


def _wrap(a: float) -> float:
    return float(se2.wrap_angle(a))
