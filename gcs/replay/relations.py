"""The relations error metric of Kuemmerle et al. (2009) for SLAM results on real logs.

Kuemmerle, Steder, Dornhege, Ruhnke, Grisetti, Stachniss, Kleiner: *On measuring the accuracy
of SLAM algorithms* (Autonomous Robots 27(4), 2009). Instead of comparing a trajectory with a
global ground truth, which rarely exists, a set of *relations* -- relative poses
``δ*_ij = x_i⁻¹ ⊕ x_j`` between pairs of scan timestamps, established by hand-checked scan
alignment -- is compared with the same relative poses of the estimate:

    e_ij = δ*_ij⁻¹ ⊕ δ_ij,   trans_ij = ‖(e_x, e_y)‖,   rot_ij = |e_θ|,

and the metric is the mean (and spread) of ``trans_ij`` and ``rot_ij`` over the relations;
``ε = 1/N Σ trans² + rot²`` as in the paper is reported too. Relations files are text lines
``t1 t2 x y z roll pitch yaw`` (seconds, metres, radians; 3-D fields that a planar log keeps at
0), ``(x, y, yaw)`` being the pose at ``t2`` in the frame of the pose at ``t1``.

Logs and relations files do not always share a clock: a "corrected" CARMEN log may store time
since the start while its relations carry the original absolute stamps.
:func:`estimate_time_offset_s` finds the constant offset by voting over all pairwise
differences; that needs stamps that are the same numbers on both sides (the Intel log). The
Freiburg 079 corrected log was re-stamped: its stamps are time since its start, none of them
equals a relation stamp minus any one offset (at most 3 of 989 agree to the microsecond) and
the relations refer to scans of the raw log between the corrected log's scans. Then
:func:`align_relations` falls back to geometry: an offset is right when the relations whose
stamps land near a scan (within half the median scan period) agree with the log's own
relative poses (its odometry, or its corrected poses); the offset with the most agreeing
relations wins when it beats every offset more than a few scan periods away by a wide margin
(fr079: 1234 of 1685 relations agree at 1211.42 s, at most 100 anywhere else).
:func:`match_relations` then keeps the relations whose *both* timestamps fall on a pose (within
``tolerance_s``, unambiguously: exactly one relation timestamp within the tolerance of that
pose) and says how many did.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from protocol.se2 import relative

__all__ = [
    "MatchedRelations",
    "RelationsAlignment",
    "align_relations",
    "Relations",
    "RelationsError",
    "RelationsFileError",
    "estimate_time_offset_s",
    "match_relations",
    "parse_relations",
    "read_relations",
    "relations_error",
]

FloatArray = NDArray[np.float64]
_CHANCE_BINS = 100  # bins either side of the winner that estimate the chance level
IntArray = NDArray[np.int64]


class RelationsFileError(ValueError):
    """A relations file could not be read; the message names the file and line."""


@dataclass(frozen=True)
class Relations:
    """``M`` relations: timestamps ``t1_s``, ``t2_s`` ``(M,)`` and ``t1_from_t2`` ``(M, 3)``."""

    t1_s: FloatArray
    t2_s: FloatArray
    t1_from_t2: FloatArray
    path: str = "<string>"

    def __len__(self) -> int:
        return int(self.t1_s.shape[0])


@dataclass(frozen=True)
class MatchedRelations:
    """The relations that fall on poses: pose indices ``i``, ``j`` and the reference
    ``i_from_j``, with ``relation_index`` into the file's relations; ``total`` relations in all."""

    i: IntArray
    j: IntArray
    i_from_j: FloatArray
    relation_index: IntArray
    total: int

    def __len__(self) -> int:
        return int(self.i.shape[0])


@dataclass(frozen=True)
class RelationsError:
    """Per-relation errors ``trans_m`` and ``rot_rad`` ``(K,)`` and their summaries."""

    trans_m: FloatArray
    rot_rad: FloatArray

    @property
    def count(self) -> int:
        return int(self.trans_m.shape[0])

    @property
    def trans_mean_m(self) -> float:
        return float(np.mean(self.trans_m))

    @property
    def trans_std_m(self) -> float:
        return float(np.std(self.trans_m))

    @property
    def rot_mean_rad(self) -> float:
        return float(np.mean(self.rot_rad))

    @property
    def rot_std_rad(self) -> float:
        return float(np.std(self.rot_rad))

    @property
    def rot_mean_deg(self) -> float:
        return math.degrees(self.rot_mean_rad)

    @property
    def epsilon(self) -> float:
        """Kuemmerle et al.'s ``ε = 1/N Σ trans² + rot²`` (m² and rad² summed, as published)."""
        return float(np.mean(self.trans_m**2 + self.rot_rad**2))


def parse_relations(text: str, *, path: str = "<string>") -> Relations:
    """Parse relations lines ``t1 t2 x y z roll pitch yaw``; ``#`` starts a comment."""
    rows: list[list[float]] = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        tok = line.split()
        if len(tok) != 8:
            raise RelationsFileError(
                f"{path}:{lineno}: expected 8 fields 't1 t2 x y z roll pitch yaw', got {len(tok)}"
            )
        try:
            values = [float(t) for t in tok]
        except ValueError as exc:
            raise RelationsFileError(f"{path}:{lineno}: {exc}") from None
        if not all(math.isfinite(v) for v in values):
            raise RelationsFileError(f"{path}:{lineno}: non-finite value")
        rows.append(values)
    if not rows:
        raise RelationsFileError(f"{path}: no relations")
    a = np.asarray(rows, dtype=np.float64)
    return Relations(t1_s=a[:, 0], t2_s=a[:, 1], t1_from_t2=a[:, [2, 3, 7]].copy(), path=path)


def read_relations(path: str | Path) -> Relations:
    """Read a relations file; errors name the file."""
    p = Path(path)
    try:
        text = p.read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise RelationsFileError(f"{p}: cannot read: {exc}") from None
    return parse_relations(text, path=str(p))


def _times(values: ArrayLike, name: str) -> FloatArray:
    t = np.asarray(values, dtype=np.float64)
    if t.ndim != 1 or len(t) == 0:
        raise ValueError(f"{name}: expected a non-empty 1-D array of times, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError(f"{name}: times must be finite (a log without timestamps has none)")
    return t


def estimate_time_offset_s(
    relations: Relations,
    times_s: ArrayLike,
    *,
    bin_s: float = 0.01,
    min_votes: int = 3,
    significance: float = 5.0,
) -> float:
    """The offset ``d`` with ``times_s + d`` on the relations' clock.

    Every (relation timestamp, pose time) pair votes for its difference in bins of ``bin_s``;
    the winning bin (with its neighbours) is refined to the median of its differences. Raises
    ValueError when fewer than ``min_votes`` timestamps agree, or fewer than ``significance``
    times the votes a bin pair gets by chance (the mean of the 200 bins around it): the clocks
    are unrelated.
    ``O(U·N)`` for ``U`` distinct relation timestamps and ``N`` poses.
    """
    t = _times(times_s, "times_s")
    ref = np.unique(np.concatenate([relations.t1_s, relations.t2_s]))
    diffs = (ref[:, None] - t[None, :]).ravel()
    bins = np.round(diffs / bin_s).astype(np.int64)
    values, counts = np.unique(bins, return_counts=True)
    # A true offset split across two bins by rounding still wins with its neighbours.
    pair = counts + np.r_[counts[1:] * (np.diff(values) == 1), 0]
    best = int(np.argmax(pair))
    near = diffs[(bins == values[best]) | (bins == values[best] + 1)]
    # Unrelated clocks still give every bin pair some votes by chance: demand many more than
    # the bins around the winner get (the density of differences is local, not uniform).
    around = np.abs(bins - values[best]) <= _CHANCE_BINS
    chance = max(int(np.count_nonzero(around)) - len(near), 1) / (2 * _CHANCE_BINS - 1) * 2
    need = max(min_votes, math.ceil(significance * chance))
    if len(near) < need:
        raise ValueError(
            f"{relations.path}: only {len(near)} timestamps agree on a clock offset (need "
            f"{need}; {chance:.1f} by chance): the relations do not belong to these poses"
        )
    return float(np.median(near))


@dataclass(frozen=True)
class RelationsAlignment:
    """How a relations file's clock maps onto a log's: ``times_s + offset_s`` are relation
    times, a stamp falls on a scan within ``tolerance_s``; ``method`` ``"stamps"`` (identical
    stamps voted) or ``"geometry"`` (relations agreeing with the log's own poses voted);
    ``votes`` for the winner and ``runner_up`` for the best offset elsewhere."""

    offset_s: float
    tolerance_s: float
    method: str
    votes: int
    runner_up: float


def _nearest(ts: FloatArray, order: IntArray, x: FloatArray) -> tuple[IntArray, FloatArray]:
    """Index (into the unsorted times) of the time nearest each ``x`` and its distance."""
    if len(ts) == 1:
        return np.zeros(len(x), dtype=np.int64), np.abs(ts[0] - x)
    k = np.clip(np.searchsorted(ts, x), 1, len(ts) - 1)
    left = k - 1
    pick = np.where(np.abs(ts[left] - x) <= np.abs(ts[k] - x), left, k)
    return order[pick].astype(np.int64), np.abs(ts[pick] - x)


def _agreeing(
    rel: Relations,
    rows: IntArray,
    ts: FloatArray,
    order: IntArray,
    poses: FloatArray,
    offsets: FloatArray,
    tolerance_s: float,
    gate_m: float,
    gate_frac: float,
    gate_rad: float,
) -> NDArray[np.int64]:
    """For each offset, how many relations ``rows`` land on scans and agree with ``poses``."""
    z = rel.t1_from_t2[rows]
    dist = np.hypot(z[:, 0], z[:, 1])
    out = np.zeros(len(offsets), dtype=np.int64)
    for n, d in enumerate(offsets.tolist()):
        i, da = _nearest(ts, order, rel.t1_s[rows] - d)
        j, db = _nearest(ts, order, rel.t2_s[rows] - d)
        ok = (da <= tolerance_s) & (db <= tolerance_s) & (i != j)
        if not ok.any():
            continue
        e = relative(z[ok], relative(poses[i[ok]], poses[j[ok]]))
        good = (np.hypot(e[:, 0], e[:, 1]) <= gate_m + gate_frac * dist[ok]) & (
            np.abs(e[:, 2]) <= gate_rad
        )
        out[n] = int(np.count_nonzero(good))
    return out


def _poses_of(poses: ArrayLike, n: int) -> FloatArray:
    p = np.asarray(poses, dtype=np.float64)
    if p.shape != (n, 3):
        raise ValueError(f"poses: expected ({n}, 3), got shape {p.shape}")
    return p


def _median_step(ts: FloatArray, path: str) -> float:
    steps = np.diff(ts)
    steps = steps[steps > 0]
    if len(steps) == 0:
        raise ValueError(f"{path}: the log's stamps do not advance: no clock to align")
    return float(np.median(steps))


def align_relations(
    relations: Relations,
    times_s: ArrayLike,
    poses: ArrayLike | None = None,
    *,
    stamp_tolerance_s: float = 0.006,
    gate_m: float = 0.05,
    gate_frac: float = 0.05,
    gate_rad: float = math.radians(2.0),
    min_votes: int = 10,
    margin: float = 3.0,
    max_candidates: int = 20000,
) -> RelationsAlignment:
    """The clock offset and matching tolerance between a relations file and a log's scans.

    ``times_s`` ``(N,)`` the scans' stamps; ``poses`` ``(N, 3)`` the log's own poses at them
    (its odometry: relative poses over a relation's span are good to a few centimetres). First
    the stamp vote of :func:`estimate_time_offset_s`; when that finds no offset and ``poses``
    are given, the geometric vote (module docstring): candidate offsets one tolerance apart
    over the range that puts at least half the relation stamps within the log's span, scored
    on up to 400 relations, the best refined on all of them in tenths of the tolerance. A
    relation agrees when its error is within ``gate_m + gate_frac·distance`` and ``gate_rad``.
    Raises ValueError (one line, naming the file) when no offset wins with at least
    ``min_votes`` and ``margin`` times the runner-up's votes.
    """
    t = _times(times_s, "times_s")
    try:
        offset = estimate_time_offset_s(relations, t)
    except ValueError as exc:
        if poses is None:
            raise
        # "only K timestamps agree ...": keep the numbers for the one-line error.
        words = str(exc).split("only ", 1)[-1].split()
        stamp_votes = f"{words[0]} agree, need {words[8].rstrip(';')}" if len(words) > 8 else "?"

    else:
        if poses is None:
            return RelationsAlignment(offset, stamp_tolerance_s, "stamps", 0, 0.0)
        # A regular clock votes almost as much for the offsets a few scan periods away: the
        # one whose relations agree with the poses wins.
        p = _poses_of(poses, len(t))
        order = np.argsort(t, kind="stable")
        ts = t[order]
        period = _median_step(ts, relations.path)
        near = offset + period * np.arange(-5, 6, dtype=np.float64)
        args0 = (gate_m, gate_frac, gate_rad)
        rows_all = np.arange(len(relations), dtype=np.int64)
        score0 = _agreeing(relations, rows_all, ts, order, p, near, stamp_tolerance_s, *args0)
        k0 = int(np.argmax(score0))
        if score0[k0] <= score0[5]:
            k0 = 5
        if score0[k0] >= min_votes:
            return RelationsAlignment(
                float(near[k0]),
                stamp_tolerance_s,
                "stamps",
                int(score0[k0]),
                float(np.delete(score0, k0).max()),
            )
        # A few stamps agreeing by chance (the first 300 scans of the re-stamped Freiburg 079
        # log: 7, 23 s off) is no alignment unless the poses agree too: try geometry.
        stamp_votes = f"{int(score0[k0])} agree with the poses, need {min_votes}"
    p = _poses_of(poses, len(t))
    order = np.argsort(t, kind="stable")
    ts = t[order]
    tol = 0.5 * _median_step(ts, relations.path)
    stamps = np.concatenate([relations.t1_s, relations.t2_s])
    # Every offset that lets some relation fall within the log's span: a log that is a part
    # of the relations' run (a replay of its first scans) overlaps only a few of them.
    lo = float(stamps.min()) - float(ts[-1])
    hi = float(stamps.max()) - float(ts[0])
    count = int(min(max_candidates, math.ceil((hi - lo) / tol) + 1))
    coarse = np.linspace(lo, hi, count)
    rng = np.random.default_rng(0)
    rows_all = np.arange(len(relations), dtype=np.int64)
    rows = np.sort(rng.choice(rows_all, 400, replace=False)) if len(rows_all) > 400 else rows_all
    args = (gate_m, gate_frac, gate_rad)
    score = _agreeing(relations, rows, ts, order, p, coarse, tol, *args)
    best = coarse[int(np.argmax(score))]
    step = (hi - lo) / max(count - 1, 1)
    fine = best + np.linspace(-step, step, 21)
    fine_score = _agreeing(relations, rows_all, ts, order, p, fine, tol, *args)
    k = int(np.argmax(fine_score))
    offset, votes = float(fine[k]), int(fine_score[k])
    # The runner-up: the best offset more than a few scan periods away, on the same rows.
    far = np.abs(coarse - offset) > 8.0 * tol
    runner = float(score[far].max()) * len(rows_all) / len(rows) if far.any() else 0.0
    if votes < min_votes or votes < margin * runner:
        raise ValueError(
            f"{relations.path}: no clock offset fits the log (stamps: {stamp_votes}; "
            f"geometry: {votes} agree, {runner:.0f} elsewhere)"
        )
    return RelationsAlignment(offset, tol, "geometry", votes, runner)


def match_relations(
    relations: Relations,
    times_s: ArrayLike,
    *,
    time_offset_s: float = 0.0,
    tolerance_s: float = 0.006,
) -> MatchedRelations:
    """Relations whose two timestamps each fall on a pose of ``times_s`` (+ ``time_offset_s``).

    A relation timestamp falls on pose ``k`` when it is within ``tolerance_s`` of it and no other
    relation timestamp is (ambiguous poses are dropped). Relations on one pose twice are dropped.
    """
    if not (math.isfinite(tolerance_s) and tolerance_s > 0):
        raise ValueError(f"tolerance_s must be > 0, got {tolerance_s}")
    t = _times(times_s, "times_s") + time_offset_s
    order = np.argsort(t, kind="stable")
    ts = t[order]
    stamps = np.unique(np.concatenate([relations.t1_s, relations.t2_s]))

    def nearest_pose(x: FloatArray) -> tuple[IntArray, FloatArray]:
        k = (
            np.clip(np.searchsorted(ts, x), 1, len(ts) - 1)
            if len(ts) > 1
            else np.zeros(len(x), dtype=np.int64)
        )
        left = np.maximum(k - 1, 0)
        pick = np.where(np.abs(ts[left] - x) <= np.abs(ts[k] - x), left, k)
        return order[pick].astype(np.int64), np.abs(ts[pick] - x)

    pose_of, dist = nearest_pose(stamps)
    within = dist <= tolerance_s
    # How many stamps fall on each pose: keep only poses with exactly one.
    hits = np.bincount(pose_of[within], minlength=len(t))
    ok = within & (hits[pose_of] == 1)
    lookup = dict(zip(stamps[ok].tolist(), pose_of[ok].tolist(), strict=True))
    i_list: list[int] = []
    j_list: list[int] = []
    idx: list[int] = []
    for r, (a, b) in enumerate(zip(relations.t1_s.tolist(), relations.t2_s.tolist(), strict=True)):
        pa, pb = lookup.get(a), lookup.get(b)
        if pa is None or pb is None or pa == pb:
            continue
        i_list.append(pa)
        j_list.append(pb)
        idx.append(r)
    index = np.asarray(idx, dtype=np.int64)
    return MatchedRelations(
        i=np.asarray(i_list, dtype=np.int64),
        j=np.asarray(j_list, dtype=np.int64),
        i_from_j=relations.t1_from_t2[index].reshape(-1, 3),
        relation_index=index,
        total=len(relations),
    )


def relations_error(poses: ArrayLike, matched: MatchedRelations) -> RelationsError:
    """Errors of the relative poses of ``poses`` ``(N, 3)`` against the matched relations.

    ``poses`` are in any common frame (the metric is invariant to it). Raises ValueError when no
    relation matched or an index is out of range.
    """
    p = np.asarray(poses, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"poses: expected (N, 3), got shape {p.shape}")
    if len(matched) == 0:
        raise ValueError("no relation falls on these poses: nothing to evaluate")
    top = int(max(matched.i.max(), matched.j.max()))
    if top >= len(p):
        raise ValueError(f"matched relations use pose {top}, but only {len(p)} poses were given")
    estimate = relative(p[matched.i], p[matched.j])
    err = relative(matched.i_from_j, estimate)
    return RelationsError(trans_m=np.hypot(err[:, 0], err[:, 1]), rot_rad=np.abs(err[:, 2]))
