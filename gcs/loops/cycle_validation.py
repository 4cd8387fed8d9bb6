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

Hypotheses older than ``expiry_s`` (mission time) without a confirming cycle are dropped (they
cost search time and, the older, the likelier an erroneous cycle, paper 4.5), as are the
oldest beyond ``max_hypotheses``.

Graph access is through two callables (so the module is pure and testable without a graph):
``links(key) -> {other_key: (key_from_other, covariance)}`` for tight paths from ``key``, and
``path(key_a, key_b) -> (a_from_b, covariance) | None`` for the graph's best path between two
nodes (None when they are not connected). Covariances are body-frame (right perturbation,
GTSAM's ``BetweenFactorPose2`` convention).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

from gcs.graph import se2

__all__ = [
    "CycleCheck",
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
    only while at most ``deep_search_max_pending`` hypotheses wait, and at most
    ``max_hypotheses`` wait at all (the oldest expire first).

    ``floor_sigma_xy_m`` / ``floor_sigma_yaw_rad`` floor every hypothesis's covariance in the
    test (a matcher's response surface can be overconfident).
    """

    chi2_threshold: float = 11.34
    min_cycle_hypotheses: int = 2
    max_cycle_hypotheses: int = 3
    expiry_s: float = 60.0
    max_hypotheses: int = 120
    deep_search_max_pending: int = 60
    floor_sigma_xy_m: float = 0.05
    floor_sigma_yaw_rad: float = math.radians(1.0)

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
        if self.deep_search_max_pending < 0:
            raise ValueError(
                f"deep_search_max_pending: expected >= 0, got {self.deep_search_max_pending}"
            )
        if not (self.floor_sigma_xy_m >= 0 and self.floor_sigma_yaw_rad >= 0):
            raise ValueError("covariance floors must be >= 0")


@dataclass(frozen=True)
class Hypothesis:
    """A match waiting for confirmation: ``a_from_b`` between ``key_a`` and ``key_b``, its
    body-frame covariance, the matcher's normalized score and when it was made."""

    hyp_id: int
    key_a: int
    key_b: int
    a_from_b: FloatArray
    covariance: FloatArray
    score: float
    time_s: float


@dataclass(frozen=True)
class CycleCheck:
    """One cycle that was tested: its hypotheses (in order), its chi-square and verdict."""

    hyp_ids: tuple[int, ...]
    chi2: float
    consistent: bool


@dataclass
class ValidationResult:
    """What one :meth:`CycleValidator.validate` call decided."""

    accepted: list[Hypothesis] = field(default_factory=list)
    rejected: list[Hypothesis] = field(default_factory=list)  # contradicted by the graph
    expired: list[Hypothesis] = field(default_factory=list)
    cycles: list[CycleCheck] = field(default_factory=list)


def compose_with_covariance(steps: Iterable[Link]) -> Link:
    """Compose ``(pose, body covariance)`` steps left to right (independent errors):
    ``x_{k+1} = x_k * step``, ``cov_{k+1} = Ad(step^-1) cov_k Ad(step^-1)' + cov_step``."""
    acc: Link = (np.zeros(3), np.zeros((3, 3)))
    for step in steps:
        acc = _compose2(acc, step)
    return acc


def _inverse(link: Link) -> Link:
    z, c = link
    ad = se2.adjoint(z)
    return se2.inverse(z), ad @ c @ ad.T


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
        self, *, now_s: float, links: LinksFn, path: PathFn, revision: int = 0
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
            ok = chi2 <= cfg.chi2_threshold
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
        for ids, pose, cov in self._search(links):
            chi2 = _chi2(pose, cov)
            check = CycleCheck(ids, chi2, chi2 <= cfg.chi2_threshold)
            out.cycles.append(check)
            searched.append(check)
        # a failing cycle blocks all its members: which one is wrong is unknown
        blocked: set[int] = set()
        for c in searched:
            if not c.consistent:
                blocked.update(c.hyp_ids)
        promoted: set[int] = set()
        for c in searched:
            if not c.consistent or len(c.hyp_ids) < cfg.min_cycle_hypotheses:
                continue
            if blocked.intersection(c.hyp_ids):
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

    def _pop(self, hyp_id: int) -> Hypothesis:
        self._checked.pop(hyp_id, None)
        return self._pending.pop(hyp_id)

    def _search(self, links: LinksFn) -> list[tuple[tuple[int, ...], FloatArray, FloatArray]]:
        """Depth-limited search for cycles ``h, link, h, link, ...`` of 2 or more hypotheses.

        A cycle is searched from its lowest-id hypothesis, traversed from ``key_a`` to
        ``key_b``, and reported once per distinct cyclic sequence of hypotheses (the first
        link found closes it). The composition is carried along the search (one step per
        edge). Returns ``(hyp_ids, composed pose, covariance)``.
        """
        cfg = self.config
        hyps = self.pending
        by_node: dict[int, list[tuple[Hypothesis, Link, int]]] = {}
        for h in hyps:
            fwd = self._floored(h)
            by_node.setdefault(h.key_a, []).append((h, fwd, h.key_b))
            by_node.setdefault(h.key_b, []).append((h, _inverse(fwd), h.key_a))
        link_cache: dict[int, dict[int, Link]] = {}
        zero = (np.zeros(3), np.zeros((3, 3)))

        def links_of(key: int) -> dict[int, Link]:
            if key not in link_cache:
                found = dict(links(key))
                found.setdefault(key, zero)  # a node links itself
                link_cache[key] = found
            return link_cache[key]

        found: dict[tuple[int, ...], tuple[FloatArray, FloatArray]] = {}
        max_h = cfg.max_cycle_hypotheses
        if len(hyps) > cfg.deep_search_max_pending:
            max_h = min(max_h, 2)

        def extend(start_key: int, at_key: int, used: tuple[int, ...], acc: Link) -> None:
            reach = links_of(at_key)
            if len(used) >= 2 and start_key in reach:  # close the cycle back to the start
                rev = used[::-1]
                canon = min(
                    min(used[i:] + used[:i] for i in range(len(used))),
                    min(rev[i:] + rev[:i] for i in range(len(rev))),
                )
                if canon not in found:
                    found[canon] = _compose2(acc, reach[start_key])
            if len(used) >= max_h:
                return
            if len(reach) <= len(by_node):
                near = [(node, reach[node]) for node in reach if node in by_node]
            else:
                near = [(node, reach[node]) for node in by_node if node in reach]
            for node, link in near:
                via = None
                for h, step, nxt in by_node[node]:
                    if h.hyp_id in used or h.hyp_id < used[0]:
                        continue
                    if via is None:
                        via = _compose2(acc, link)
                    extend(start_key, nxt, (*used, h.hyp_id), _compose2(via, step))

        for h in hyps:
            # start at key_a, traverse h first; only cycles whose lowest id is h are searched
            fwd = self._floored(h)
            extend(h.key_a, h.key_b, (h.hyp_id,), fwd)
        return [(ids, pose, cov) for ids, (pose, cov) in found.items()]


def _compose2(first: Link, step: Link) -> Link:
    """``first * step`` with ``cov = Ad(step^-1) cov_first Ad(step^-1)' + cov_step``
    (scalar SE(2) arithmetic: the search calls it many times)."""
    (p, pc), (z, zc) = first, step
    c, s = math.cos(z[2]), math.sin(z[2])
    ix = -c * z[0] - s * z[1]
    iy = s * z[0] - c * z[1]
    ad = np.array([[c, s, iy], [-s, c, -ix], [0.0, 0.0, 1.0]])
    cov = ad @ pc @ ad.T + zc
    cp, sp = math.cos(p[2]), math.sin(p[2])
    th = (p[2] + z[2] + math.pi) % (2.0 * math.pi) - math.pi
    pose = np.array([p[0] + cp * z[0] - sp * z[1], p[1] + sp * z[0] + cp * z[1], th])
    return pose, cov
