"""Loop-closure candidate generation (paper 4.3.3, 4.6: Dijkstra projection sizes the search).

For a new pose node ``n``, every other node ``m`` that has a scan, of any robot, is a
candidate when the graph already relates the two (same connected component) and:

* their expected relative pose ``n_from_m`` (the Dijkstra projection: composition of the
  measurements along the minimum-uncertainty path) puts ``m`` within ``max_distance_m`` of
  ``n`` (so the two grids overlap), or its ``k_sigma`` uncertainty region comes that close;
* the uncertainty of that relative pose (the projection's covariance, an upper bound) still
  leaves something to correct: its translation standard deviation is at least
  ``min_sigma_xy_m`` (nodes already tightly related, e.g. consecutive nodes of one robot,
  are skipped; so are the same robot's nodes fewer than ``min_index_gap`` apart, unless
  the odometry between them is uncertain by ``gap_sigma_xy_m`` or more: lost scans widened
  the step across a gap, and the nodes either side of it are the only pairs that can tie
  the nodes after it to the map before it while they see the same place (such a pair is
  kept up to the coarse gate, ``max_distance_m + wide_xy_m`` apart, not ``max_distance_m``:
  Intel with 12 scans dropped, the nodes either side of the gap lay 8.1 m apart);
* the ``k_sigma`` region of the uncertainty fits a search window: the standard matcher's
  window (``window_xy_m``, ``window_yaw_rad``) or, for poorly related nodes (a robot linked
  only by a loose operator hint, a long loop), a bounded *wide* window: ``wide_xy_m`` in
  translation when the standard one is too small, and a yaw window as wide as needed, in
  steps of ``yaw_class_rad``, up to ``wide_yaw_rad``. Beyond even that the candidate is
  dropped: the search would be too expensive and too prone to aliasing.

Each candidate carries the window it needs and its priority: the expected correction, the
translation standard deviation (largest first, paper: "large expected correction first"),
discounted by a Gaussian factor when the expected position lies beyond ``max_distance_m``
(the grids may not overlap), so that a budget of matches per second goes where matching
helps most. Ties (to the centimetre) go to the nearer node. At most ``max_per_node``
candidates are kept per new node (highest priority first).

Overlap (``overlap_m``, off by default). After a long stretch without closures every candidate
of a new node shares that node's large uncertainty, so the expected correction no longer tells
them apart: whole Intel (noise seed 1, clock jump, 38fac2c), node 840 had 200 candidates with
sigmas of 1.3-2.0 m within 6 m, and sigma alone kept the eight 4.4-4.6 m away whose paths were
2-5 % looser; the pairs 3.1 m away (nodes 488, 489), which match at 0.68 and 0.61 within 0.07 m
and 1.4 deg of the truth, were never tried and the late loop stayed open (ATE 0.416 m against
the clean run's 0.071: the clean run had drawn those pairs). With ``overlap_m`` the priority is
also discounted by ``exp(-d^2 / (2 overlap_m^2))`` for the expected distance ``d``, so that
among candidates of like uncertainty the budget goes to the grids that overlap. Measured on the
robustness bench's replays (``magic bench robustness``, noise seed 1, 5 m for every replay,
load 10-13; /tmp/team/robust19/full_ovl.log, session 14): whole Intel clean 0.071 -> 0.068 m
(closures 470 -> 911), clock jump 0.416 -> 0.068 m (5.85 -> 1.00 x clean), turns x1.08 1.76 ->
1.18 x clean, odometry gap 0.199 -> 0.191 m, false closures 1 -> 0 over its runs; whole
Freiburg 079 clean 0.160 -> 0.128 m and false closures 4 -> 0, but turns x0.92 2 -> 11 false (a
look-alike, scans 1515-1524 against 1190-1195, 1.3 m off, now matched from six neighbouring
nodes that agree), frozen clock 1 -> 18 false (1063 closures against 165); quick bench
``perturbed_ate_ratio_max`` 1.149 -> 1.21 (ACES odometry gap 0.140 m against a clean 0.115);
the full run's ``perturbed_ate_ratio_max`` 5.85 -> 2.79 (Intel's odometry gap),
``false_closures`` 27 -> 58. At 6 m whole Freiburg 079 clean took 6 false closures (0.340 m),
at 8 m 11 (0.172 m; Intel clean 0.090 m). The quick mission with 5 m (seeds 0 / 7) gave ATE
0.242 / 0.473 m and F1 0.784 / 0.634 against 0.205 / 0.619 and 0.817 / 0.799. Nearer pairs are
tried more often, and where a place has a look-alike a metre off, the look-alike is tried from
more nodes and its matches agree: the closer's cycles cannot tell them from a true group, so
this waits for a look-alike test that can.

Robots in different components (not yet linked by a fiducial, an operator hint or an accepted
closure) are never candidates: there is no bounded window to search (a robot with no seed
stays unlinked). The module is pure: it works on a projection result and node arrays.

Covariances: the projection's covariance of ``m`` is in ``m``'s body frame (right
perturbation, GTSAM's convention); the matcher's window is over ``(x, y)`` in ``n``'s frame
and the yaw, so it is rotated into those components first.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "Candidate",
    "CandidateSearchConfig",
    "body_to_vector_covariance",
    "search_candidates",
]

FloatArray = NDArray[Any]
IntArray = NDArray[np.int64]


class CandidateSearchConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Gates of candidate generation (metres, radians); see the module docstring.

    ``overlap_m``: the expected distance at which the priority is discounted by ``exp(-1/2)``
    (module docstring, "Overlap"; inf, the default: not at all).
    """

    max_distance_m: float = 5.0
    min_sigma_xy_m: float = 0.05
    min_index_gap: int = 5
    gap_sigma_xy_m: float = 0.25
    k_sigma: float = 3.0
    window_xy_m: float = 3.0
    window_yaw_rad: float = math.radians(30.0)
    wide_xy_m: float = 8.0
    wide_yaw_rad: float = math.pi
    yaw_class_rad: float = math.radians(15.0)
    max_per_node: int = 8
    overlap_m: float = math.inf

    def __post_init__(self) -> None:
        for name in (
            "max_distance_m",
            "k_sigma",
            "window_xy_m",
            "window_yaw_rad",
            "wide_xy_m",
            "yaw_class_rad",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v}")
        if not self.overlap_m > 0:  # inf: distance within max_distance_m does not matter
            raise ValueError(f"overlap_m: expected > 0, got {self.overlap_m}")
        if not self.gap_sigma_xy_m > 0:  # inf: never
            raise ValueError(f"gap_sigma_xy_m: expected > 0, got {self.gap_sigma_xy_m}")
        if not (math.isfinite(self.min_sigma_xy_m) and self.min_sigma_xy_m >= 0):
            raise ValueError(f"min_sigma_xy_m: expected >= 0, got {self.min_sigma_xy_m}")
        if not 0 < self.wide_yaw_rad <= math.pi:
            raise ValueError(f"wide_yaw_rad: expected in (0, pi], got {self.wide_yaw_rad}")
        if self.wide_xy_m < self.window_xy_m or self.wide_yaw_rad < self.window_yaw_rad:
            raise ValueError("the wide window must contain the standard window")
        if self.min_index_gap < 0 or self.max_per_node < 1:
            raise ValueError("need min_index_gap >= 0 and max_per_node >= 1")


@dataclass(frozen=True)
class Candidate:
    """A pair to match: ``reference_key`` (the new node, whose table is built) and
    ``query_key``; the projection's ``reference_from_query`` and its covariance in vector
    components ``(x, y, yaw)`` of the reference frame; the window the match needs and its
    priority (translation standard deviation, metres)."""

    reference_key: int
    query_key: int
    reference_from_query: FloatArray
    covariance_xyt: FloatArray
    window_xy_m: float
    window_yaw_rad: float
    wide: bool
    priority: float


def body_to_vector_covariance(pose: FloatArray, cov_body: FloatArray) -> FloatArray:
    """Covariance of ``(x, y, theta)`` of ``pose`` from its body-frame (right-perturbation)
    covariance: ``d(x, y) = R(theta) v``, ``d theta = omega``. Works on ``(N, 3)`` /
    ``(N, 3, 3)`` batches."""
    p = np.asarray(pose, dtype=np.float64)
    c = np.asarray(cov_body, dtype=np.float64)
    th = p[..., 2]
    k = np.zeros(c.shape)
    k[..., 0, 0] = np.cos(th)
    k[..., 0, 1] = -np.sin(th)
    k[..., 1, 0] = np.sin(th)
    k[..., 1, 1] = np.cos(th)
    k[..., 2, 2] = 1.0
    return k @ c @ np.swapaxes(k, -1, -2)  # type: ignore[no-any-return]


def search_candidates(
    reference_key: int,
    *,
    keys: IntArray,
    robot_ids: IntArray,
    indices: IntArray,
    has_scan: NDArray[np.bool_],
    poses: FloatArray,
    covariances: FloatArray,
    config: CandidateSearchConfig,
) -> list[Candidate]:
    """Candidates of ``reference_key`` among the nodes ``keys`` (see the module docstring).

    ``poses`` ``(N, 3)`` and ``covariances`` ``(N, 3, 3)`` are the Dijkstra projection from
    the reference node (``reference_from_node`` and its body-frame covariance; NaN / inf where
    unreached), ``robot_ids`` / ``indices`` each node's robot and pose index, ``has_scan``
    whether a scan is stored for it. Returns at most ``max_per_node``, highest priority first.
    """
    keys = np.asarray(keys, dtype=np.int64)
    n = len(keys)
    for name, arr, shape in (
        ("robot_ids", robot_ids, (n,)),
        ("indices", indices, (n,)),
        ("has_scan", has_scan, (n,)),
        ("poses", poses, (n, 3)),
        ("covariances", covariances, (n, 3, 3)),
    ):
        if np.shape(arr) != shape:
            raise ValueError(f"search_candidates: {name} has shape {np.shape(arr)}, need {shape}")
    where = np.nonzero(keys == reference_key)[0]
    if len(where) != 1:
        raise ValueError(f"search_candidates: reference key {reference_key} not among the keys")
    r = int(where[0])
    cfg = config
    poses = np.asarray(poses, dtype=np.float64)
    reached = np.isfinite(poses[:, 0]) & np.all(np.isfinite(covariances), axis=(1, 2))
    ok = reached & np.asarray(has_scan, dtype=bool)
    ok[r] = False
    same_robot = robot_ids == robot_ids[r]
    near = same_robot & (np.abs(indices - indices[r]) < cfg.min_index_gap)
    dist = np.hypot(poses[:, 0], poses[:, 1])
    ok &= dist <= cfg.max_distance_m + cfg.wide_xy_m  # a coarse gate before the exact one
    idx = np.nonzero(ok)[0]
    if len(idx) == 0:
        return []
    cov = body_to_vector_covariance(poses[idx], np.asarray(covariances)[idx])
    sigma_xy = np.sqrt(np.maximum(np.linalg.eigvalsh(cov[:, :2, :2])[:, 1], 0.0))
    sigma_yaw = np.sqrt(np.maximum(cov[:, 2, 2], 0.0))
    need_xy = cfg.k_sigma * sigma_xy
    need_yaw = cfg.k_sigma * sigma_yaw
    d = dist[idx]
    keep = (sigma_xy >= cfg.min_sigma_xy_m) & (need_xy <= cfg.wide_xy_m)
    keep &= ~near[idx] | (sigma_xy >= cfg.gap_sigma_xy_m)  # near: only across a gap
    keep &= need_yaw <= cfg.wide_yaw_rad
    # the uncertainty region comes close enough (across a gap: the coarse gate, above)
    keep &= (d - need_xy <= cfg.max_distance_m) | (near[idx] & (sigma_xy >= cfg.gap_sigma_xy_m))
    # expected correction, discounted by the chance that the grids overlap at all
    # and, with overlap_m, by how much two grids that far apart are expected to share
    priority = sigma_xy * np.exp(
        -0.5 * (np.maximum(d - cfg.max_distance_m, 0.0) / np.maximum(sigma_xy, 1e-9)) ** 2
        - 0.5 * (d / cfg.overlap_m) ** 2
    )
    out: list[Candidate] = []
    for k in np.nonzero(keep)[0]:
        wide_xy = bool(need_xy[k] > cfg.window_xy_m)
        # the yaw window only as wide as needed (in steps of yaw_class_rad): cost is linear in it
        yaw = cfg.window_yaw_rad
        if need_yaw[k] > yaw:
            yaw = min(
                cfg.wide_yaw_rad, math.ceil(need_yaw[k] / cfg.yaw_class_rad) * cfg.yaw_class_rad
            )
        i = int(idx[k])
        out.append(
            Candidate(
                reference_key=int(reference_key),
                query_key=int(keys[i]),
                reference_from_query=poses[i].copy(),
                covariance_xyt=cov[k],
                window_xy_m=cfg.wide_xy_m if wide_xy else cfg.window_xy_m,
                window_yaw_rad=yaw,
                wide=wide_xy or yaw > cfg.window_yaw_rad,
                priority=float(priority[k]),
            )
        )
    out.sort(key=lambda c: (-round(c.priority, 2), float(np.hypot(*c.reference_from_query[:2]))))
    return out[: cfg.max_per_node]
