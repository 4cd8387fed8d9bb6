"""``magic replay --carmen FILE``: a real 2-D laser log through the GCS pipeline (issue 7 item 7).

A CARMEN log (:mod:`gcs.replay.carmen_log`) becomes exactly what a robot sends (paper 4.2,
4.3.3, 4.3.4): a :class:`~protocol.messages.PoseNode` per scan after which the robot moved or
turned enough (:class:`robot.odometry.pose_node_maker.PoseNodeMaker`, the robot's own rule and
covariance model), with its odometry constraint, and a :class:`~protocol.messages.TerrainGrid`
whose 10 cm binary grid holds scan endpoints in the node's ``base`` frame (a 2-D laser sees
only vertical surfaces), compressed by the robot's codec. One 180-degree scan sees much less
than the robot's 360-degree 3-D sweep, so a node's grid holds the scans of the last
``grid.aggregate_m`` metres of travel, brought into the node's frame by the odometry the robot
reports (measured with this issue's loop closer: on the Duke loop 0 closures from single
scans, 64 from the last 2 m; on the noisy Intel log a relations error of 0.21 m from single
scans, 0.045 m from the last 2 m). The messages go through the
same :class:`gcs.ground_station.GroundStation` the GCS node runs (loop closing, incremental
optimization); the result is evaluated against

* the log's reference poses, when it has some (a *corrected* log whose odometry was made noisy
  here, or a log whose laser poses differ from its odometry): the ATE after alignment
  (:mod:`gcs.replay.trajectory_error`), for the GCS estimate and for odometry alone;
* a relations file (Kuemmerle et al. 2009, :mod:`gcs.replay.relations`): the mean translation
  and rotation error of the relations whose two timestamps fall on scans, and how many did.
  The relations' clock is mapped onto the log's by
  :func:`~gcs.replay.relations.align_relations` (identical stamps, or failing that the
  relations that agree with the log's own odometry: the re-stamped Freiburg 079 log); a
  scan's pose is its node's estimate carried on by the odometry reported since that node.

Odometry. A raw log's odometry (the Duke DP-SLAM log) is used as is; its robot's odometry
may be worse than ours, so ``odometry_sigma_scale`` multiplies the pose-node model's sigmas
(the covariances the nodes report). A corrected log has no raw odometry (its odometry fields
repeat the corrected poses), so ``noise.scale`` adds seeded noise to each scan-to-scan
increment ``(ds, dyaw, dt)`` drawn from that covariance model itself,
``σ_ds² = slip²|ds|``, ``σ_dyaw² = turn²|dyaw| + gyro²·dt``, with every σ multiplied by
``scale``; the nodes' covariances then use the same scaled model, so they state the noise that
was really added.

Odometry dropouts. A log whose wheel odometry dropped out while the laser kept coming carries
the last odometry pose the base reported in every laser record (the odometry *froze*).
:func:`odometry_dropouts` finds such stretches from the data alone (bitwise-repeated poses
while the laser's ranges change: a robot at rest repeats its pose too, but not its ranges
changing), and the robot's chain is carried across them by the laser on a constant-velocity
prior (:func:`robot_odometry`, :mod:`robot.odometry.scan_odometry`); the nodes over the stretch
state the bridged steps' covariance (:data:`BRIDGE_SIGMA_M_PER_SQRT_M`), and any step the laser
could not bridge is widened by what the robot can have done meanwhile. One line in the
summary's ``gaps`` says what was found and done.

Clocks. Every time the replay uses (node times, the gyro term ``gyro²·dt`` of the node
covariances and of the added noise, the node maker's interval rule) comes from
:func:`log_clock`, the log's stamps checked and repaired by :mod:`gcs.replay.log_clock`: a
frozen, coarse, jumping or backwards clock never reaches the GCS, and never inflates a
covariance; each anomaly is one line in the summary (``clock``).

Results first. The map, the poses and the summary are written to ``out_dir`` *before* any
evaluation, and written again with the evaluation added; an evaluation that cannot be done (a
relations file on another clock, a log without timestamps) is one line under ``evaluation``
in the summary and leaves the rest of the result intact. An interrupted replay (^C,
``KeyboardInterrupt``) stops feeding scans, and the result holds the nodes that ran.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

from compression import encode_grid, origin_cells_of
from gcs.graph.pose_graph import Provenance
from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.mapping.map_export import write_pgm_yaml, write_png
from gcs.mapping.rasterization import RasterConfig
from gcs.replay.carmen_log import CarmenLog
from gcs.replay.log_clock import ClockCheck, check_clock
from gcs.replay.relations import (
    MatchedRelations,
    Relations,
    RelationsAlignment,
    RelationsError,
    align_relations,
    match_relations,
    relations_error,
)
from gcs.replay.trajectory_error import TrajectoryError, trajectory_error
from mission.replay_args import replay_parser
from protocol.messages import (
    PoseNode,
    TerrainGrid,
    covariance_from_upper,
    covariance_to_upper,
)
from protocol.se2 import compose, relative, transform_points, wrap_angle
from robot.odometry.inertial_odometry import OdometryIncrement
from robot.odometry.pose_node_maker import PoseNodeConfig, PoseNodeMaker
from robot.odometry.scan_odometry import ScanOdometryConfig, ScanOdometryStats, refine_odometry

__all__ = [
    "FALSE_CLOSURE_M",
    "FALSE_CLOSURE_RAD",
    "OdometryDropouts",
    "OdometryGaps",
    "OdometryNoiseConfig",
    "ReplayConfig",
    "ReplayNode",
    "ReplayResult",
    "ScanGridConfig",
    "iter_replay_messages",
    "log_clock",
    "odometry_dropouts",
    "odometry_gaps",
    "replay_messages",
    "replay_odometry",
    "robot_odometry",
    "run_replay",
    "scan_grid",
]

FloatArray = NDArray[np.float64]


class OdometryNoiseConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Noise added to the log's odometry: ``scale`` times the pose-node model's sigmas (0: the
    log's odometry as is), drawn with ``numpy.random.default_rng(seed)``."""

    scale: float = 0.0
    seed: int = 0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scale) and self.scale >= 0):
            raise ValueError(f"noise.scale: expected a finite number >= 0, got {self.scale}")


class ScanGridConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """A node's binary grid: cell size, the longest range kept, how much of the recent past it
    holds (the scans of the last ``aggregate_m`` metres of odometry, at most
    ``aggregate_max_scans``, and back only as far as the odometry turned ``aggregate_max_turn_rad``
    from the node; 0 m: the node's own scan only), and the codec that carries it.

    Why the turning bound: the scans join the node's frame by the odometry the robot reports, so
    a turn-scale error ``s - 1`` bends the grid by ``(s - 1) W`` for ``W`` radians turned within
    it (:mod:`gcs.loops.loop_closer`, "Bent grids"). Unbounded, a robot that turns on the spot
    joins half a revolution into one grid (ACES: median 160 deg per pair of matched grids), and
    a 8 % error bends it by 13 deg: such matches can never be closures. At 40 deg two grids
    bent by a scale error within 8.8 % stay within the closer's 5 deg gate
    (``max_grid_distortion_rad``), so once a fit bounds the error the matches are admitted.
    Quick bench, noise seeds 1 / 2, ACES turns x0.92: ATE 3.41 m unbounded -> 0.26 / 0.25 m;
    perturbed-over-clean ATE, worst of every log, 1.99 / 1.58 (35 deg: 3.32 / 1.60, Freiburg
    079 clean 0.237 m with half its closures; 45 deg: 12.7, ACES x0.92's matches waited;
    25 deg: Intel x0.92 starved of matches, 1.25 m).

    ``complete_after_gap``: a node just after lost scans (:func:`odometry_gaps`) has no past
    within reach to join (its window stops at the gap: the first node after it holds one
    scan), so its window is completed forward, with the scans that follow it up to the same
    travel, turning and count (as a robot would send that grid once it had driven them). A
    one-scan grid of a 180-degree laser matches loosely: Freiburg 079 with the gap (quick,
    seed 1) closed the first node after it to a later pass 0.39 m and 3.7 deg off, the next
    (five scans) 0.12 m and 1.6 deg off, and the map bent there."""

    resolution_m: float = 0.10
    max_range_m: float = 10.0
    aggregate_m: float = 2.0
    aggregate_max_scans: int = 50
    aggregate_max_turn_rad: float = math.radians(40.0)
    codec: str = "ctx4a"  # the robot node's default
    complete_after_gap: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution_m) and 0.01 <= self.resolution_m <= 1.0):
            raise ValueError(f"grid.resolution_m: expected 0.01..1 m, got {self.resolution_m}")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > 0):
            raise ValueError(f"grid.max_range_m: expected > 0, got {self.max_range_m}")
        if not (math.isfinite(self.aggregate_m) and self.aggregate_m >= 0):
            raise ValueError(f"grid.aggregate_m: expected >= 0, got {self.aggregate_m}")
        if self.aggregate_max_scans < 1:
            raise ValueError(
                f"grid.aggregate_max_scans: expected >= 1, got {self.aggregate_max_scans}"
            )
        if not (self.aggregate_max_turn_rad > 0):  # inf: no bound
            raise ValueError(
                f"grid.aggregate_max_turn_rad: expected > 0, got {self.aggregate_max_turn_rad}"
            )
        if 2 * self.max_range_m / self.resolution_m > 1000:
            raise ValueError(
                f"grid: {self.max_range_m} m at {self.resolution_m} m exceeds 1000 cells a side"
            )


def _replay_station_config() -> GroundStationConfig:
    # The rasterizer's visibility sweep casts free space all around a node, as the robot's
    # 360-degree sweeps allow; a 180-degree laser saw nothing behind it, so the replay maps
    # only what was seen: occupied cells. No near map laid over it (the station's default
    # since 56b746e): its free rays are the same all-round assumption.
    return GroundStationConfig(raster=RasterConfig(free_range_m=0.0), near_raster=None)


def _replay_node_config() -> PoseNodeConfig:
    # Half the robot's node spacing: the logs' scans are sparse already (Intel: ~1 m apart).
    return PoseNodeConfig(min_distance_m=0.5)


class ReplayConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Everything a replay runs with.

    ``robot_id`` the log's robot (the map robot by default, so the map is its first node);
    ``period_s`` the scan period assumed for logs without timestamps; ``step_every_nodes``
    how many pose nodes between two calls of ``GroundStation.step`` and ``step_budget_s`` the
    budget each call gets (None: unbounded); ``reference`` whether to evaluate against the log's
    poses (None: when they can be a reference, see :func:`run_replay`);
    ``relations_tolerance_s`` how close a relation timestamp must fall to a scan's (None: as
    :func:`~gcs.replay.relations.align_relations` finds, identical stamps 6 ms, else half the
    median scan period); ``station``
    the GCS (its rasterizer maps occupied cells only by default: a 180-degree laser saw
    nothing behind it, while the visibility sweep assumes the robot's all-round view);
    ``odometry_sigma_scale`` multiplies the sigmas of ``nodes`` (module docstring);
    ``scan_odometry`` (None: off) refines the odometry by matching each scan against the last
    few (:func:`robot_odometry`), for the nodes and their grids alike. On by default: ``magic
    bench robustness --quick``, off -> on: clean ATE Intel / ACES / Freiburg 079 0.063 / 0.178 /
    0.138 -> 0.058 / 0.146 / 0.112 m, turns x0.92 0.079 / 0.256 / 0.127 -> 0.053 / 0.153 /
    0.117, x1.08 0.068 / 0.246 / 0.273 -> 0.056 / 0.139 / 0.110, false closures 2 -> 0,
    perturbed_ate_ratio_max 1.99 -> 1.41 (Freiburg 079's gap 0.122 -> 0.157 m), bench CPU 45 ->
    72 s (~5 ms per scan).
    """

    robot_id: int = 0
    nodes: PoseNodeConfig = msgspec.field(default_factory=_replay_node_config)
    grid: ScanGridConfig = msgspec.field(default_factory=ScanGridConfig)
    noise: OdometryNoiseConfig = msgspec.field(default_factory=OdometryNoiseConfig)
    station: GroundStationConfig = msgspec.field(default_factory=_replay_station_config)
    period_s: float = 0.5
    step_every_nodes: int = 1
    step_budget_s: float | None = None
    reference: bool | None = None
    relations_tolerance_s: float | None = None
    odometry_sigma_scale: float = 1.0
    scan_odometry: ScanOdometryConfig | None = msgspec.field(default_factory=ScanOdometryConfig)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.odometry_sigma_scale) and self.odometry_sigma_scale > 0):
            raise ValueError(f"odometry_sigma_scale: expected > 0, got {self.odometry_sigma_scale}")
        if not (math.isfinite(self.period_s) and self.period_s > 0):
            raise ValueError(f"period_s: expected > 0, got {self.period_s}")
        if self.step_every_nodes < 1:
            raise ValueError(f"step_every_nodes: expected >= 1, got {self.step_every_nodes}")
        if self.step_budget_s is not None and not self.step_budget_s > 0:
            raise ValueError(f"step_budget_s: expected > 0 or None, got {self.step_budget_s}")
        tol = self.relations_tolerance_s
        if tol is not None and not (math.isfinite(tol) and tol > 0):
            raise ValueError(f"relations_tolerance_s: expected > 0 or None, got {tol}")


def scan_grid(
    points_in_base: FloatArray, *, resolution_m: float
) -> tuple[NDArray[np.bool_], tuple[float, float]]:
    """The binary grid of a scan's endpoints ``(K, 2)`` in ``base``: ``(grid, origin_in_base)``.

    A cell is occupied when an endpoint falls into it; the grid is cropped to the occupied
    cells' bounding box on the lattice anchored at the ``base`` origin (cell ``(r, c)`` covers
    ``origin_in_base + (c, r) * resolution_m``, the ``TerrainGrid`` convention). No points:
    an empty ``0 x 0`` grid at the origin.
    """
    pts = np.asarray(points_in_base, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros((0, 0), dtype=bool), (0.0, 0.0)
    cells = np.floor(pts / resolution_m).astype(np.int64)
    c0, r0 = cells.min(axis=0)
    c1, r1 = cells.max(axis=0)
    grid = np.zeros((int(r1 - r0 + 1), int(c1 - c0 + 1)), dtype=bool)
    grid[cells[:, 1] - r0, cells[:, 0] - c0] = True
    return grid, (float(c0 * resolution_m), float(r0 * resolution_m))


def log_clock(log: CarmenLog, period_s: float = 0.5) -> ClockCheck:
    """The log's clock, checked and repaired (:func:`gcs.replay.log_clock.check_clock`, with
    the log's odometry for plausibility and ``period_s`` for a log without a usable clock)."""
    return check_clock(log.time_s, odometry=log.odometry_in_log, default_period_s=period_s)


def _scan_times(log: CarmenLog, period_s: float) -> FloatArray:
    """Mission time of each scan from 0, on the repaired clock (:func:`log_clock`)."""
    t = log_clock(log, period_s).time_s
    return t - t[0] if len(t) else t  # type: ignore[no-any-return]


def _scaled_model(cfg: PoseNodeConfig, scale: float) -> PoseNodeConfig:
    return msgspec.structs.replace(
        cfg,
        slip_std_m_per_sqrt_m=cfg.slip_std_m_per_sqrt_m * scale,
        turn_std_rad_per_sqrt_rad=cfg.turn_std_rad_per_sqrt_rad * scale,
        gyro_noise_rad_per_sqrt_s=cfg.gyro_noise_rad_per_sqrt_s * scale,
    )


def replay_odometry(
    log: CarmenLog, config: ReplayConfig
) -> tuple[FloatArray, list[OdometryIncrement], PoseNodeConfig]:
    """The odometry the replay reports: ``(odometry (N, 3), increments, node model)``.

    ``increments[k]`` is the motion from scan ``k`` to ``k + 1`` for the covariance model;
    the node model is ``config.nodes`` with its sigmas scaled by ``odometry_sigma_scale`` and,
    when noise is added, by ``noise.scale``.
    """
    odom = log.odometry_in_log
    times = _scan_times(log, config.period_s)
    steps = relative(odom[:-1], odom[1:]).reshape(-1, 3)
    ds = np.hypot(steps[:, 0], steps[:, 1]) * np.where(steps[:, 0] < 0, -1.0, 1.0)
    # The repaired clock's steps: never negative, never a clock jump (module docstring).
    dt = np.maximum(np.diff(times), 0.0)
    increments = [
        OdometryIncrement(distance_m=float(a), dyaw_rad=float(b), dt_s=float(c))
        for a, b, c in zip(ds, steps[:, 2], dt, strict=True)
    ]
    scale = config.noise.scale
    base = config.nodes
    if config.odometry_sigma_scale != 1.0:
        base = _scaled_model(base, config.odometry_sigma_scale)
    if scale == 0.0:
        return odom.copy(), increments, base
    model = _scaled_model(base, scale)
    rng = np.random.default_rng(config.noise.seed)
    sd_ds = model.slip_std_m_per_sqrt_m * np.sqrt(np.abs(ds))
    sd_yaw = np.sqrt(
        model.turn_std_rad_per_sqrt_rad**2 * np.abs(steps[:, 2])
        + model.gyro_noise_rad_per_sqrt_s**2 * dt
    )
    e_ds = rng.normal(size=len(steps)) * sd_ds
    e_yaw = rng.normal(size=len(steps)) * sd_yaw
    # Lengthen or shorten each step along its own direction by e_ds; turn it by e_yaw.
    stretch = np.where(np.abs(ds) > 1e-12, 1.0 + e_ds / np.maximum(np.abs(ds), 1e-12), 1.0)
    noisy = np.column_stack([steps[:, 0] * stretch, steps[:, 1] * stretch, steps[:, 2] + e_yaw])
    out = np.empty_like(odom)
    out[0] = odom[0]
    for k, step in enumerate(noisy):
        out[k + 1] = compose(out[k], step)
    return out, increments, model


@dataclass(frozen=True)
class OdometryGaps:
    """Steps of a log across which scans are missing (:func:`odometry_gaps`): ``steps``
    (index ``k``: scan ``k`` to ``k + 1``), ``widen`` the zero-mean increments added before
    each such step's own, ``xy_var`` the position variance (m², each axis) added to the node
    that ends the step, and ``lines`` one line saying what was found and done."""

    steps: NDArray[np.int64]
    widen: dict[int, list[OdometryIncrement]]
    lines: list[str]
    xy_var: dict[int, float] = field(default_factory=dict)


def _node_model(config: ReplayConfig) -> PoseNodeConfig:
    """The pose-node model the replay's nodes state (:func:`replay_odometry`'s third value)."""
    model = config.nodes
    if config.odometry_sigma_scale != 1.0:
        model = _scaled_model(model, config.odometry_sigma_scale)
    if config.noise.scale > 0.0:
        model = _scaled_model(model, config.noise.scale)
    return model


def _window_quantile(cum_x: FloatArray, cum_y: FloatArray, span: float, q: float) -> float:
    """The ``q`` quantile of ``y`` gathered over the log's stretches at least ``span`` long in
    ``x`` (``cum_x``, ``cum_y``: running sums from 0 over consecutive steps). A span longer
    than the whole log: the log's total rate times ``span``."""
    total_x = float(cum_x[-1])
    if total_x <= 0.0 or span <= 0.0:
        return 0.0
    if span >= total_x:
        return float(cum_y[-1]) * span / total_x
    # Stretches start on every step boundary that leaves room for ``span`` and end on the first
    # boundary at or past ``span``: each covers at least ``span`` (an honest over-cover).
    last = int(np.searchsorted(cum_x, total_x - span, side="right"))
    starts = np.arange(last)
    ends = np.minimum(np.searchsorted(cum_x, cum_x[starts] + span, side="left"), len(cum_x) - 1)
    return float(np.quantile(cum_y[ends] - cum_y[starts], q))


def odometry_gaps(
    log: CarmenLog,
    config: ReplayConfig,
    *,
    factor: float = 8.0,
    quantile: float = 0.9,
    time_gaps: bool = True,
) -> OdometryGaps:
    """Find gaps in a log and widen the covariance of the steps across them.

    A step is a gap when it is more than ``factor`` times the median step in distance or
    (``time_gaps``, on a clock :func:`log_clock` did not have to repair there) in duration:
    scans were lost, and the one increment that spans them states only the net motion, while
    odometry's error grew with the path driven and the turning done in between, which nobody
    saw. Steps long in time alone are gaps too by default: the ACES log's 13 (up to 38 s,
    turning about 30 degrees each) hid turning its covariance did not state. Measured, one
    run each, whole logs, with / without them: ACES ATE 0.188 / 0.246 m (long-loop revisits
    closed 30 / 29 of 51), ACES with a tenth of its scans dropped 0.776 / 5.09 m (5 / 0 of
    36), Freiburg 079 with the gap 0.167 / 0.291 m, but Freiburg 079 whole 1.415 / 0.619 m
    (its one such step, 2.25 s over 1.6 cm at scan 1301, widened by 1.3 deg; the loop closer
    on it is chaotic). What the robot can have done across a gap is taken from the log itself:
    among the log's own stretches (gaps left out) as long as the gap in distance, and as long
    in duration (on a clock that needed no repair there), the ``quantile`` (0.9) of the turning
    and of the path they hold. The turning ``u`` beyond the step's own ``|dyaw|`` is added to the
    node covariance as zero-mean increments (turning ``+u/2`` then ``-u/2`` on the spot), so the
    step's mean is unchanged and its yaw variance grows by ``σ_u² = turn²·u``, as if the robot
    had been seen turning; that heading spreads sideways through the step itself. The path
    ``p`` beyond the straight line was driven with that unknown heading, in directions nobody
    saw: each axis of the position gets ``slip²·p + σ_u²·(p² + ds²)/3`` (a heading error
    ``σ_u`` over a path turning every way), which also keeps the covariance well conditioned
    (a large yaw variance over a tiny along-track one is near singular: the ground station
    rejects it). Bounded: the added yaw variance is at most pi²/3, the variance of a heading
    that could be anything (uniform on a circle); a longer gap says nothing more about it, and
    the path is the log's own (its stretches, or its rate times the duration).
    """
    odom = log.odometry_in_log
    n = len(log)
    empty = OdometryGaps(np.zeros(0, dtype=np.int64), {}, [])
    if n < 3:
        return empty
    steps = relative(odom[:-1], odom[1:]).reshape(-1, 3)
    ds = np.hypot(steps[:, 0], steps[:, 1])
    dyaw = np.abs(steps[:, 2])
    clock = log_clock(log, config.period_s)
    dt = np.maximum(clock.dt_s, 0.0)
    timed = ~clock.repaired  # a replaced step's duration is no evidence
    moving = ds > 1e-6
    if not moving.any():
        return empty
    med_ds = float(np.median(ds[moving]))
    gap = ds > factor * med_ds
    positive = timed & (dt > 0)
    med_dt = float(np.median(dt[positive])) if positive.any() else math.inf
    if time_gaps:
        gap |= positive & (dt > factor * med_dt)
    if not gap.any():
        return empty
    # the log's own stretches: neither gaps nor steps whose odometry froze (no motion seen)
    ok = ~gap & ~odometry_dropouts(log).absent[1:]
    cum_path, cum_turn, cum_time = _cumulative_motion(ds, dyaw, np.where(timed, dt, 0.0), ok)
    model = _node_model(config)
    turn_var = model.turn_std_rad_per_sqrt_rad**2
    max_turn = math.pi**2 / 3.0 / turn_var if turn_var > 0 else math.inf
    widen: dict[int, list[OdometryIncrement]] = {}
    xy_var: dict[int, float] = {}
    most_turn = most_path = 0.0
    for k in np.flatnonzero(gap).tolist():
        turn = _window_quantile(cum_path, cum_turn, float(ds[k]), quantile)
        path = float(ds[k])
        if timed[k]:
            turn = max(turn, _window_quantile(cum_time, cum_turn, float(dt[k]), quantile))
            path = max(path, _window_quantile(cum_time, cum_path, float(dt[k]), quantile))
        u = min(max(0.0, turn - float(dyaw[k])), max_turn)
        p = max(0.0, path - float(ds[k]))
        if u > 0:
            widen[k] = [OdometryIncrement(0.0, u / 2, 0.0), OdometryIncrement(0.0, -u / 2, 0.0)]
        var_u = turn_var * u
        xy_var[k] = model.slip_std_m_per_sqrt_m**2 * p + var_u * (p**2 + float(ds[k]) ** 2) / 3
        most_turn, most_path = max(most_turn, u), max(most_path, p)
    idx = np.flatnonzero(gap).astype(np.int64)
    line = (
        f"odometry gap: {len(idx)} step(s) from scan {int(idx[0]) + 1} (largest "
        f"{float(ds[gap].max()):.3g} m, {float(dt[gap].max()):.3g} s; median step {med_ds:.3g} m, "
        f"{med_dt:.3g} s); covariance widened by the log's own stretches that long (q "
        f"{quantile:g}): up to {most_turn:.3g} rad turned, {most_path:.3g} m driven unseen"
    )
    return OdometryGaps(idx, widen, [line], xy_var)


def _cumulative_motion(
    ds: FloatArray, dyaw: FloatArray, dt: FloatArray, ok: NDArray[np.bool_]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Cumulative path, turning and time over the log's own steps ``ok`` (leading 0): what
    :func:`_window_quantile` reads the log's stretches from (:func:`odometry_gaps`,
    :func:`_prior_widening`)."""
    return (
        np.r_[0.0, np.cumsum(ds[ok])],
        np.r_[0.0, np.cumsum(dyaw[ok])],
        np.r_[0.0, np.cumsum(dt[ok])],
    )


@dataclass(frozen=True)
class OdometryDropouts:
    """Stretches of a log whose odometry is absent (:func:`odometry_dropouts`): ``absent``
    ``(N,)``, ``absent[k]`` the odometry's step from scan ``k - 1`` to ``k`` is missing;
    ``runs`` ``(first scan, scans)`` of each stretch, ``range_change_m`` the median change of
    the laser's ranges across each, and ``standstills`` frozen stretches the laser says the
    robot stood through (not absent: a robot at rest reports the same pose)."""

    absent: NDArray[np.bool_]
    runs: list[tuple[int, int]]
    range_change_m: list[float]
    standstills: int = 0


def odometry_dropouts(
    log: CarmenLog, *, min_scans: int = 3, min_range_change_m: float = 0.05
) -> OdometryDropouts:
    """Find where the wheel odometry dropped out while the laser kept coming.

    A CARMEN log whose base stopped reporting carries the last odometry pose in every laser
    record (:func:`mission.bench.perturbations.freeze_odometry`): at least ``min_scans``
    consecutive steps of *exactly* zero motion (bitwise the same pose; real encoders on a
    moving robot never repeat a pose, and the replay's added noise is drawn before). A robot
    standing still shows the same; the laser tells them apart: across the stretch (its first
    scan to its last) the median change of the ranges of beams with a return in both is the
    sensor's noise at rest (SICK: 1 cm) and grows with any motion (Freiburg 079: 0.1 m per
    scan of 0.1 m). A stretch is a dropout when that median exceeds ``min_range_change_m``
    (0.05 m), or when fewer than 10 beams have a return in both (the laser cannot vouch for a
    rest). Only the log's own data is used (never its reference poses)."""
    odom = log.odometry_in_log
    n = len(log)
    absent = np.zeros(n, dtype=bool)
    if n < 2:
        return OdometryDropouts(absent, [], [])
    same = np.all(odom[1:] == odom[:-1], axis=1)  # step k-1 -> k, as scan k
    edges = np.diff(np.r_[0, same.astype(np.int8), 0])
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    valid = log.valid_mask()
    runs: list[tuple[int, int]] = []
    changes: list[float] = []
    standstills = 0
    for a, b in zip(starts.tolist(), stops.tolist(), strict=True):
        if b - a < min_scans:
            continue
        first, last = a, b  # scans a .. b share one pose (steps a -> b)
        both = valid[first] & valid[last]
        change = (
            float(np.median(np.abs(log.ranges_m[last, both] - log.ranges_m[first, both])))
            if np.count_nonzero(both) >= 10
            else math.inf
        )
        if change <= min_range_change_m:
            standstills += 1
            continue
        absent[a + 1 : b + 1] = True
        runs.append((a + 1, b - a))
        changes.append(change)
    return OdometryDropouts(absent, runs, changes, standstills)


@dataclass(frozen=True)
class _RobotOdometry:
    odom: FloatArray
    increments: list[OdometryIncrement]
    model: PoseNodeConfig
    widen: dict[int, list[OdometryIncrement]]
    xy_var: dict[int, float]
    lines: list[str]


#: A step the laser bridged without odometry (:func:`robot_odometry`): the position variance
#: (m² per metre of the step, each axis) added to it, beyond the node model's own for a step
#: of that size. Measured (quick prefixes, noise seed 1, a tenth of the odometry frozen from
#: the middle) against the reference: the bridged steps' errors, median / largest, 0.033 /
#: 0.100 m (Intel, 0.67 m steps), 0.018 / 0.061 m (Freiburg 079, 0.1 m steps), 0.042 / 0.117 m
#: (ACES, 1 m steps), but not additive (each scan is matched against the last few, so a
#: step's error is mostly undone by the next): over 20 steps 0.040 m (Freiburg 079, 2 m) and
#: 0.34 m (ACES, 20 m); the whole stretch 0.25 m over 8 m of path (Intel), 0.32 m over 10 m
#: (Freiburg 079), 0.37 m over 31 m (ACES). Whole Intel's stretch (91 scans, 61 m of path)
#: ends 1.31 m off, beyond what 0.05 states (0.39 m each axis; odometry with the laser was
#: 0.70 m off there). Larger values loosen the nodes, and the closer then accepts fewer
#: closures over them: quick Freiburg 079 with 0.08, 2.6 x clean (0.05: 1.09; 0.05 m a step
#: rather than per square root of a metre, 2.7).
BRIDGE_SIGMA_M_PER_SQRT_M = 0.05


def _robot_odometry(log: CarmenLog, config: ReplayConfig) -> _RobotOdometry:
    """:func:`robot_odometry` with what the node covariances need across absent odometry."""
    odom, increments, model = replay_odometry(log, config)
    drop = odometry_dropouts(log)
    st = ScanOdometryStats()
    times = _scan_times(log, config.period_s)
    if config.scan_odometry is not None and len(odom):
        scans = [
            log.points_in_base(k, max_range_m=config.grid.max_range_m) for k in range(len(log))
        ]
        absent = drop.absent if drop.runs else None
        odom = refine_odometry(odom, scans, config.scan_odometry, st, absent=absent, time_s=times)
        on_prior = set(st.prior_steps)
    else:
        on_prior = set(np.flatnonzero(drop.absent).tolist())
    widen: dict[int, list[OdometryIncrement]] = {}
    xy_var: dict[int, float] = {}
    lines: list[str] = []
    if not drop.runs:
        return _RobotOdometry(odom, increments, model, widen, xy_var, lines)
    increments = list(increments)
    # The steps the robot has instead of its odometry's: the laser's (or the prior's), each
    # stated like an odometry step of that size, plus BRIDGE_SIGMA_M_PER_SQRT_M of position.
    for k in np.flatnonzero(drop.absent).tolist():
        step = relative(odom[k - 1], odom[k])
        ds = math.hypot(step[0], step[1]) * (-1.0 if step[0] < 0 else 1.0)
        increments[k - 1] = OdometryIncrement(
            distance_m=float(ds), dyaw_rad=float(step[2]), dt_s=increments[k - 1].dt_s
        )
        if k not in on_prior:
            xy_var[k - 1] = BRIDGE_SIGMA_M_PER_SQRT_M**2 * abs(ds)
    # Steps left on the motion prior: what the robot can have done meanwhile, from the log's
    # own stretches that long (odometry_gaps' widening), per run of consecutive such steps.
    if on_prior:
        prior_gaps = _prior_widening(log, config, drop, sorted(on_prior), times)
        widen.update(prior_gaps[0])
        for k, v in prior_gaps[1].items():
            xy_var[k] = xy_var.get(k, 0.0) + v
    scans_absent = int(np.count_nonzero(drop.absent))
    first = drop.runs[0][0]
    lines.append(
        f"odometry absent: {scans_absent} scan(s) in {len(drop.runs)} stretch(es) from scan "
        f"{first} (the odometry froze while the laser's ranges changed by a median "
        f"{max(drop.range_change_m):.2g} m); bridged by the laser: {st.bridged} step(s) "
        f"matched ({len(st.ambiguous_steps)} with a runner-up), {len(on_prior)} on the motion "
        "prior (covariance widened)"
    )
    return _RobotOdometry(odom, increments, model, widen, xy_var, lines)


def _prior_widening(
    log: CarmenLog,
    config: ReplayConfig,
    drop: OdometryDropouts,
    steps: list[int],
    times: FloatArray,
    quantile: float = 0.9,
) -> tuple[dict[int, list[OdometryIncrement]], dict[int, float]]:
    """The widening of runs of consecutive scans ``steps`` left on the motion prior (no
    odometry, no laser match): unlike a gap's step (:func:`odometry_gaps`), whose mean is the
    odometry's net motion and only the unseen turning's noise is added, the prior's step may
    miss the whole motion. From the log's present steps, ``u`` and ``p`` the ``quantile`` of
    turning and path over stretches as long in time as the run: the heading gets a variance of
    ``u²`` (at most pi²/3, a heading that could be anything), the position ``p²/3`` each axis
    (plus the slip of ``p``), at the run's first step."""
    odom = log.odometry_in_log
    rel = relative(odom[:-1], odom[1:]).reshape(-1, 3)
    ds, dyaw = np.hypot(rel[:, 0], rel[:, 1]), np.abs(rel[:, 2])
    dt = np.maximum(np.diff(times), 0.0)
    cum_path, cum_turn, cum_time = _cumulative_motion(ds, dyaw, dt, ~drop.absent[1:])
    model = _node_model(config)
    turn_var = model.turn_std_rad_per_sqrt_rad**2
    widen: dict[int, list[OdometryIncrement]] = {}
    xy_var: dict[int, float] = {}
    groups: list[list[int]] = []
    for k in steps:
        if groups and groups[-1][-1] == k - 1:
            groups[-1].append(k)
        else:
            groups.append([k])
    for group in groups:
        span = float(np.sum(dt[[k - 1 for k in group]]))
        u = _window_quantile(cum_time, cum_turn, span, quantile)
        p = _window_quantile(cum_time, cum_path, span, quantile)
        first = group[0] - 1
        var_yaw = min(u**2, math.pi**2 / 3.0)
        if var_yaw > 0 and turn_var > 0:
            # zero-mean turns whose model variance (turn² |dyaw| each) adds up to var_yaw
            a = var_yaw / (2.0 * turn_var)
            widen[first] = [OdometryIncrement(0.0, a, 0.0), OdometryIncrement(0.0, -a, 0.0)]
        xy_var[first] = model.slip_std_m_per_sqrt_m**2 * p + p**2 / 3.0
    return widen, xy_var


def robot_odometry(
    log: CarmenLog, config: ReplayConfig
) -> tuple[FloatArray, list[OdometryIncrement], PoseNodeConfig]:
    """:func:`replay_odometry`, then, with ``config.scan_odometry``, laser-aided (paper 4.1:
    :func:`robot.odometry.scan_odometry.refine_odometry` over the log's scans): the chain the
    robot's nodes and grids use. The increments (the node covariance model's input) stay the
    reported odometry's, except where the odometry was absent (:func:`odometry_dropouts`):
    there the laser bridged the steps on a constant-velocity prior, and the increments are the
    bridged chain's (the nodes state them like odometry steps of that size, plus
    :data:`BRIDGE_SIGMA_M_PER_SQRT_M` of position; a step the laser could not bridge is widened
    by what the robot can have done in that time, as :func:`odometry_gaps` does). Without
    ``scan_odometry`` an absent stretch stays frozen (a zero-velocity prior), all of it
    widened."""
    out = _robot_odometry(log, config)
    return out.odom, out.increments, out.model


@dataclass(frozen=True)
class ReplayNode:
    """One pose node of the replay: the scan it was made at and the two messages it sends."""

    scan: int
    pose_node: PoseNode
    terrain_grid: TerrainGrid


def replay_messages(log: CarmenLog, config: ReplayConfig | None = None) -> list[ReplayNode]:
    """Pose nodes and terrain grids of a log, in order (see the module docstring)."""
    return list(iter_replay_messages(log, config))


def iter_replay_messages(
    log: CarmenLog, config: ReplayConfig | None = None, notes: list[str] | None = None
) -> Iterator[ReplayNode]:
    """:func:`replay_messages` one node at a time (a replay can stop between two). ``notes``
    (optional) gets one line per stretch of absent odometry and what was done about it."""
    cfg = config or ReplayConfig()
    robot = _robot_odometry(log, cfg)
    odom, increments, model = robot.odom, robot.increments, robot.model
    if notes is not None:
        notes.extend(robot.lines)
    times = _scan_times(log, cfg.period_s)
    gaps = odometry_gaps(log, cfg)
    maker = PoseNodeMaker(model)
    xy_var = 0.0  # the gaps' position variance since the last node (odometry_gaps)
    gcfg = cfg.grid
    res = gcfg.resolution_m
    travelled = np.concatenate([[0.0], np.cumsum(np.abs([i.distance_m for i in increments]))])
    # the reported odometry's unwrapped heading: how far it turned between any two scans
    turned = np.concatenate([[0.0], np.cumsum(wrap_angle(np.diff(odom[:, 2])))])
    points_of: dict[int, FloatArray] = {}  # a scan joins several nodes' grids: convert once
    gap_steps = set(gaps.steps.tolist())
    for k in range(len(log)):
        if k > 0:
            for extra in (*gaps.widen.get(k - 1, ()), *robot.widen.get(k - 1, ())):
                maker.add_increment(extra)
            maker.add_increment(increments[k - 1])
            xy_var += gaps.xy_var.get(k - 1, 0.0) + robot.xy_var.get(k - 1, 0.0)
        if not maker.due(odom[k], float(times[k])):
            continue
        node = maker.make(odom[k], float(times[k]))
        if xy_var > 0.0:
            cov = covariance_from_upper(node.odom_covariance) + np.diag([xy_var, xy_var, 0.0])
            node = msgspec.structs.replace(node, odom_covariance=covariance_to_upper(cov))
            xy_var = 0.0
        first = max(0, k - gcfg.aggregate_max_scans + 1)
        recent = np.flatnonzero(travelled[first : k + 1] >= travelled[k] - gcfg.aggregate_m) + first
        # back only as far as the odometry turned aggregate_max_turn_rad (ScanGridConfig)
        too_far = np.flatnonzero(np.abs(turned[recent] - turned[k]) > gcfg.aggregate_max_turn_rad)
        if len(too_far):
            recent = recent[too_far[-1] + 1 :]
        if gcfg.complete_after_gap and int(recent[0]) - 1 in gap_steps:
            # cut by lost scans: completed forward (ScanGridConfig.complete_after_gap)
            start, ahead = int(recent[0]), k + 1
            while (
                ahead < len(log)
                and ahead - 1 not in gap_steps
                and travelled[ahead] - travelled[start] <= gcfg.aggregate_m
                and ahead - start < gcfg.aggregate_max_scans
                and abs(turned[ahead] - turned[k]) <= gcfg.aggregate_max_turn_rad
            ):
                ahead += 1
            recent = np.r_[recent, np.arange(k + 1, ahead, dtype=recent.dtype)]
        # Older scans join the node's frame by the odometry the robot reported, as on board.
        node_from_scan = relative(odom[k], odom[recent]).reshape(-1, 3)
        for j in recent.tolist():
            if j not in points_of:
                points_of[j] = log.points_in_base(j, max_range_m=gcfg.max_range_m)
        for j in [j for j in points_of if j < recent[0]]:
            del points_of[j]
        points = np.concatenate(
            [
                transform_points(pose, points_of[j])
                for pose, j in zip(node_from_scan, recent.tolist(), strict=True)
            ]
        )
        grid, origin = scan_grid(points, resolution_m=res)
        data = encode_grid(grid, cfg.grid.codec, origin_cells=origin_cells_of(origin, res))
        msg = TerrainGrid(node.node_index, res, data)
        yield ReplayNode(scan=k, pose_node=node, terrain_grid=msg)


@dataclass
class ReplayResult:
    """What a replay produced and how good it is.

    Per node ``(M,)``: ``scans`` (index into the log), ``time_s`` (the log's own clock, NaN
    without timestamps), ``odometry`` and ``estimate`` ``(M, 3)`` (``odom`` and ``map``),
    ``reference`` ``(M, 3)`` in the log's frame or None. ``ate``/``ate_odometry`` against the
    reference; ``relations``/``relations_odometry`` with ``relations_matched`` (None without a
    relations file); ``loop_closures`` automatic loop-closure edges in the final graph, with
    ``closure_nodes`` ``(K, 2)`` (indices into the per-node arrays) and ``closure_a_from_b``
    ``(K, 3)``; against the reference, ``closure_err_m`` / ``closure_err_rad`` ``(K,)`` and
    ``false_closures``, those off by more than ``FALSE_CLOSURE_M`` or ``FALSE_CLOSURE_RAD``.
    ``clock`` the clock anomalies found and what was done (one line each, empty: a good clock);
    ``gaps`` the same for steps across lost scans (:func:`odometry_gaps`);
    ``evaluation_errors`` one line per evaluation that could not be done; ``relations_alignment``
    how the relations' clock was mapped; ``interrupted`` the signal's name when the replay was
    stopped early (``scans_done`` scans were fed).
    """

    log_path: str
    scans_total: int
    scans: NDArray[np.int64]
    time_s: FloatArray
    odometry: FloatArray
    estimate: FloatArray
    reference: FloatArray | None
    loop_closures: int
    closure_nodes: NDArray[np.int64]
    closure_a_from_b: FloatArray
    station_stats: dict[str, Any]
    wall_s: float
    closure_err_m: FloatArray | None = None
    closure_err_rad: FloatArray | None = None
    ate: TrajectoryError | None = None
    ate_odometry: TrajectoryError | None = None
    relations_matched: MatchedRelations | None = None
    relations: RelationsError | None = None
    relations_odometry: RelationsError | None = None
    files: dict[str, str] = field(default_factory=dict)
    clock: list[str] = field(default_factory=list)
    gaps: list[str] = field(default_factory=list)
    evaluation_errors: list[str] = field(default_factory=list)
    relations_alignment: RelationsAlignment | None = None
    interrupted: str | None = None
    scans_done: int = 0

    @property
    def false_closures(self) -> int | None:
        if self.closure_err_m is None or self.closure_err_rad is None:
            return None
        bad = (self.closure_err_m > FALSE_CLOSURE_M) | (self.closure_err_rad > FALSE_CLOSURE_RAD)
        return int(np.count_nonzero(bad))

    def summary(self) -> dict[str, Any]:
        """The numbers, JSON-ready."""
        out: dict[str, Any] = {
            "log": self.log_path,
            "scans": self.scans_total,
            "nodes": int(len(self.scans)),
            "loop_closures": self.loop_closures,
            "wall_s": round(self.wall_s, 3),
            "station": self.station_stats,
            "clock": list(self.clock),
            "gaps": list(self.gaps),
        }
        if self.interrupted is not None:
            out["interrupted"] = self.interrupted
            out["scans_done"] = self.scans_done
        out["evaluation"] = list(self.evaluation_errors) or "ok"
        for name, ate in (("ate", self.ate), ("ate_odometry", self.ate_odometry)):
            if ate is not None:
                out[f"{name}_rmse_m"] = ate.rmse_m
                out[f"{name}_max_m"] = ate.max_m
                out[f"{name}_yaw_rmse_deg"] = ate.yaw_rmse_deg
        if self.closure_err_m is not None and self.closure_err_rad is not None:
            out["false_closures"] = self.false_closures
            if len(self.closure_err_m):
                out["closure_err_p95_m"] = float(np.percentile(self.closure_err_m, 95))
                out["closure_err_p95_deg"] = math.degrees(
                    float(np.percentile(self.closure_err_rad, 95))
                )
        if self.relations_matched is not None:
            out["relations_matched"] = len(self.relations_matched)
            out["relations_total"] = self.relations_matched.total
        if self.relations_alignment is not None:
            out["relations_offset_s"] = self.relations_alignment.offset_s
            out["relations_tolerance_s"] = self.relations_alignment.tolerance_s
            out["relations_alignment"] = self.relations_alignment.method
        for name, rel in (
            ("relations", self.relations),
            ("relations_odometry", self.relations_odometry),
        ):
            if rel is not None:
                out[f"{name}_trans_err_m"] = rel.trans_mean_m
                out[f"{name}_trans_std_m"] = rel.trans_std_m
                out[f"{name}_rot_err_deg"] = rel.rot_mean_deg
                out[f"{name}_rot_std_deg"] = math.degrees(rel.rot_std_rad)
        out["files"] = dict(self.files)
        return out


ProgressFn = Callable[[int, int, str], None]

#: A closure off the reference by more than this is false (the sim4 metric's thresholds).
FALSE_CLOSURE_M = 0.5
FALSE_CLOSURE_RAD = math.radians(5.0)


def _has_reference(log: CarmenLog, config: ReplayConfig) -> bool:
    if config.reference is not None:
        return config.reference
    # The log's poses are a reference when noise was added to them, or when they are not
    # simply the odometry (a corrected log that kept its raw odometry).
    differs = not np.allclose(log.odometry_in_log, log.laser_in_log, atol=1e-6)
    return config.noise.scale > 0 or differs


def run_replay(
    log: CarmenLog,
    *,
    config: ReplayConfig | None = None,
    relations: Relations | None = None,
    out_dir: str | Path | None = None,
    progress: ProgressFn | None = None,
) -> ReplayResult:
    """Replay ``log`` through a :class:`GroundStation` and evaluate (module docstring).

    ``progress(scans_done, scans_total, text)`` is called after every ``GroundStation.step``.
    With ``out_dir``, writes there ``map.png`` and ``map.pgm`` + ``map.yaml`` (the station's
    global map at the final posterior), ``summary.json``, ``poses.txt`` and ``closures.txt``,
    first before the evaluation and again with it. An evaluation that cannot be done (relations
    on another clock, or for a log without timestamps) does not raise: it is one line in
    ``evaluation_errors``. A ``KeyboardInterrupt`` while scans are fed ends the feeding: the
    result (and the files) hold what ran, with ``interrupted`` set to the exception's name.
    """
    cfg = config or ReplayConfig()
    t_start = time.perf_counter()
    clock = log_clock(log, cfg.period_s)
    station_cfg = cfg.station
    if station_cfg.loops.grid_window_m == 0.0 and cfg.grid.aggregate_m > 0.0:
        # the closer bounds how far odometry's turn error bends a grid by the travel and the
        # turning it spans (gcs.loops.loop_closer, "Bent grids"): here, the scans of
        # aggregate_m, back at most aggregate_max_turn_rad
        loops = msgspec.structs.replace(
            station_cfg.loops,
            grid_window_m=cfg.grid.aggregate_m,
            grid_window_rad=min(station_cfg.loops.grid_window_rad, cfg.grid.aggregate_max_turn_rad),
        )
        station_cfg = msgspec.structs.replace(station_cfg, loops=loops)
    station = GroundStation(station_cfg)
    rid = cfg.robot_id
    nodes: list[ReplayNode] = []
    interrupted: str | None = None
    dropout_lines: list[str] = []
    try:
        for rn in iter_replay_messages(log, cfg, dropout_lines):
            nodes.append(rn)
            n = len(nodes)
            now = rn.pose_node.time_s
            station.handle(rid, rn.pose_node, now_s=now)
            station.handle(rid, rn.terrain_grid, now_s=now)
            if n % cfg.step_every_nodes == 0:
                station.step(now_s=now, budget_s=cfg.step_budget_s)
                if progress is not None:
                    accepted = len(station.graph.edges(Provenance.LOOP_AUTO))
                    progress(rn.scan + 1, len(log), f"{n} nodes, {accepted} loop closures")
    except KeyboardInterrupt as exc:
        interrupted = "SIGTERM" if isinstance(exc, ReplayTerminated) else "SIGINT"
    if nodes and len(nodes) % cfg.step_every_nodes != 0:
        now = nodes[-1].pose_node.time_s
        station.step(now_s=now, budget_s=cfg.step_budget_s)
        if progress is not None:
            accepted = len(station.graph.edges(Provenance.LOOP_AUTO))
            progress(nodes[-1].scan + 1, len(log), f"{len(nodes)} nodes, {accepted} loop closures")
    scans = np.array([rn.scan for rn in nodes], dtype=np.int64)
    odometry = np.array([rn.pose_node.pose_in_odom for rn in nodes], dtype=np.float64)
    odometry = odometry.reshape(-1, 3)
    keys = [station.key_of(rid, rn.pose_node.node_index) for rn in nodes]
    missing = [rn.pose_node.node_index for rn, k in zip(nodes, keys, strict=True) if k is None]
    if missing:
        raise RuntimeError(f"the ground station dropped pose nodes {missing[:10]}: {station.stats}")
    estimate = np.array([station.graph.pose(k) for k in keys if k is not None]).reshape(-1, 3)
    stats = station.stats
    node_of = {k: i for i, k in enumerate(keys)}
    closures = station.graph.edges(Provenance.LOOP_AUTO)
    closure_nodes = np.array(
        [(node_of[e.key_a], node_of[e.key_b]) for e in closures], dtype=np.int64
    ).reshape(-1, 2)
    result = ReplayResult(
        log_path=log.path,
        scans_total=len(log),
        scans=scans,
        time_s=log.time_s[scans],
        odometry=odometry,
        estimate=estimate,
        reference=None,
        loop_closures=len(closures),
        closure_nodes=closure_nodes,
        closure_a_from_b=np.array([e.z for e in closures], dtype=np.float64).reshape(-1, 3),
        station_stats={
            "pose_nodes": stats.pose_nodes,
            "terrain_grids": stats.terrain_grids,
            "optimizations": stats.optimizations,
            "rejected": dict(stats.rejected),
            "solver_faults": stats.solver_faults,
            "solver_recoveries": stats.solver_recoveries,
            "clock_anomalies": dict(stats.clock_anomalies),
        },
        wall_s=time.perf_counter() - t_start,
        clock=clock.lines(),
        gaps=[*odometry_gaps(log, cfg).lines, *dropout_lines],
        interrupted=interrupted,
        scans_done=int(scans[-1]) + 1 if len(scans) else 0,
    )
    out = Path(out_dir) if out_dir is not None else None
    if out is not None:  # the result is saved before anything can fail in its evaluation
        _write_outputs(result, station, out)
    _evaluate(result, log, cfg, clock, relations)
    result.wall_s = time.perf_counter() - t_start
    if out is not None:
        _write_outputs(result, station, out, with_map=False)
    return result


def _evaluate(
    result: ReplayResult,
    log: CarmenLog,
    cfg: ReplayConfig,
    clock: ClockCheck,
    relations: Relations | None,
) -> None:
    """Fill in the reference and relations evaluations; failures become one line each."""
    scans, estimate, odometry = result.scans, result.estimate, result.odometry
    if _has_reference(log, cfg) and len(scans):
        result.reference = log.base_in_log[scans]
        result.ate = trajectory_error(estimate, result.reference)
        result.ate_odometry = trajectory_error(odometry, result.reference)
        cn = result.closure_nodes
        truth = relative(result.reference[cn[:, 0]], result.reference[cn[:, 1]]).reshape(-1, 3)
        err = relative(truth, result.closure_a_from_b).reshape(-1, 3)
        result.closure_err_m = np.hypot(err[:, 0], err[:, 1])
        result.closure_err_rad = np.abs(err[:, 2])
    if relations is None:
        return
    try:
        _evaluate_relations(result, log, cfg, clock, relations)
    except ValueError as exc:
        result.evaluation_errors.append(_one_line(f"relations not evaluated: {exc}"))


def _evaluate_relations(
    result: ReplayResult,
    log: CarmenLog,
    cfg: ReplayConfig,
    clock: ClockCheck,
    relations: Relations,
) -> None:
    if not log.has_timestamps:
        raise ValueError(f"{log.path} has no timestamps to match {relations.path} with")
    if len(result.scans) == 0:
        raise ValueError("no pose node ran")
    # The relations are on the log's own clock; only a clock that had to be rewritten as a
    # whole (frozen, coarse, jumping) is replaced by the repaired one.
    times = clock.time_s if clock.rewritten else log.time_s
    last = int(result.scans[-1]) + 1
    align = align_relations(relations, times[:last], log.odometry_in_log[:last])
    tol = cfg.relations_tolerance_s if cfg.relations_tolerance_s is not None else align.tolerance_s
    result.relations_alignment = RelationsAlignment(
        align.offset_s, tol, align.method, align.votes, align.runner_up
    )
    # Relations fall on scans (not only nodes): a scan's pose is its node's estimate carried
    # on by the odometry the robot reported since that node.
    odom_all, _increments, _model = robot_odometry(log.subset(slice(0, last)), cfg)
    node_at = np.searchsorted(result.scans, np.arange(last), side="right") - 1
    node_at = np.maximum(node_at, 0)
    per_scan = compose(
        result.estimate[node_at],
        relative(odom_all[result.scans[node_at]], odom_all[:last]).reshape(-1, 3),
    )
    per_scan_odom = compose(
        result.odometry[node_at],
        relative(odom_all[result.scans[node_at]], odom_all[:last]).reshape(-1, 3),
    )
    matched = match_relations(
        relations, times[:last], time_offset_s=align.offset_s, tolerance_s=tol
    )
    result.relations_matched = matched
    if len(matched) == 0:
        raise ValueError(f"{relations.path}: clock aligned, but no relation falls on two scans")
    result.relations = relations_error(per_scan, matched)
    result.relations_odometry = relations_error(per_scan_odom, matched)


def _one_line(text: str, limit: int = 199) -> str:
    line = " ".join(text.split())
    return line if len(line) <= limit else line[: limit - 3] + "..."


def _write_outputs(
    result: ReplayResult, station: GroundStation, out: Path, *, with_map: bool = True
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    occupancy = station.rasterize() if with_map else None
    if occupancy is not None and occupancy.values.size:
        result.files["map"] = str(write_png(occupancy, out / "map.png"))
        pgm, yml = write_pgm_yaml(occupancy, out / "map")
        result.files["map_pgm"] = str(pgm)
        result.files["map_yaml"] = str(yml)
    poses = out / "poses.txt"
    ref = (
        result.reference if result.reference is not None else np.full_like(result.estimate, np.nan)
    )
    table = np.column_stack([result.scans, result.time_s, result.estimate, result.odometry, ref])
    np.savetxt(
        poses,
        table,
        fmt=["%d", "%.6f"] + ["%.6f"] * 9,
        header="scan time_s map_x map_y map_yaw odom_x odom_y odom_yaw ref_x ref_y ref_yaw",
    )
    result.files["poses"] = str(poses)
    closures = out / "closures.txt"
    k = len(result.closure_nodes)
    err_m = result.closure_err_m if result.closure_err_m is not None else np.full(k, np.nan)
    err_rad = result.closure_err_rad if result.closure_err_rad is not None else np.full(k, np.nan)
    np.savetxt(
        closures,
        np.column_stack(
            [
                result.scans[result.closure_nodes].reshape(-1, 2),
                result.closure_a_from_b,
                err_m,
                np.degrees(err_rad),
            ]
        ),
        fmt=["%d", "%d"] + ["%.6f"] * 5,
        header="scan_a scan_b a_from_b_x a_from_b_y a_from_b_yaw err_m err_deg (vs log poses)",
    )
    result.files["closures"] = str(closures)
    summary = out / "summary.json"
    result.files["summary"] = str(summary)
    summary.write_text(json.dumps(result.summary(), indent=2) + "\n", encoding="utf-8")


# ---------------------------------------------------------------- the command


def _format_summary(summary: dict[str, Any]) -> list[str]:
    lines = [
        f"log {summary['log']}: {summary['scans']} scans -> {summary['nodes']} pose nodes, "
        f"{summary['loop_closures']} loop closures accepted, {summary['wall_s']:.1f} s"
    ]
    if "ate_rmse_m" in summary:
        lines.append(
            f"ATE vs the log's poses: {summary['ate_rmse_m']:.3f} m RMS "
            f"(max {summary['ate_max_m']:.3f} m, yaw {summary['ate_yaw_rmse_deg']:.2f} deg); "
            f"odometry alone {summary['ate_odometry_rmse_m']:.3f} m"
        )
        if "false_closures" in summary:
            lines.append(
                f"loop closures off the log's poses by > {FALSE_CLOSURE_M} m or "
                f"> {math.degrees(FALSE_CLOSURE_RAD):.0f} deg: {summary['false_closures']}"
            )
    else:
        lines.append("ATE: no reference poses in this log (raw odometry only)")
    if "relations_matched" in summary:
        lines.append(
            f"relations: {summary['relations_matched']} of {summary['relations_total']} fall on "
            "scans of this replay"
        )
        if "relations_trans_err_m" in summary:
            lines.append(
                f"relations error: {summary['relations_trans_err_m']:.3f} m, "
                f"{summary['relations_rot_err_deg']:.2f} deg (odometry alone "
                f"{summary['relations_odometry_trans_err_m']:.3f} m, "
                f"{summary['relations_odometry_rot_err_deg']:.2f} deg)"
            )
    station = summary.get("station", {})
    if station.get("solver_faults"):
        lines.append(
            f"solver faults: {station['solver_faults']}, recovered "
            f"{station['solver_recoveries']} (batch re-solve, fresh iSAM2)"
        )
    for line in summary.get("gaps", []):
        lines.append(line)
    for line in summary.get("clock", []):
        lines.append(f"clock of the log: {line.removeprefix('clock ')}")
    if summary.get("evaluation", "ok") != "ok":
        lines.append(f"evaluation missing: {len(summary['evaluation'])} part(s), see above")
    if "interrupted" in summary:
        lines.append(f"interrupted by {summary['interrupted']} after {summary['scans_done']} scans")
    for name, path in summary.get("files", {}).items():
        lines.append(f"wrote {name}: {path}")
    return lines


class ReplayTerminated(KeyboardInterrupt):
    """SIGTERM during a replay: ends it as ^C does (what ran is saved), exit 143."""


def main(argv: list[str] | None = None) -> int:
    """``magic replay``: exit 0 with the result saved (an evaluation that could not be done is
    listed, not fatal), 2 on bad input (one line on stderr naming the file and the problem),
    130 on ^C, 143 on SIGTERM (both after saving and summarising what ran)."""
    import signal
    import sys
    import threading

    from gcs.replay.carmen_log import CarmenLogError, read_carmen_log
    from gcs.replay.relations import RelationsFileError, read_relations
    from mission.config import ConfigError, load_config

    if argv and not argv[0].startswith("-"):  # magic replay RUN_DIR: a mission's GCS journal
        from mission.mission_replay import main as replay_run_dir

        return replay_run_dir(argv)
    args = replay_parser().parse_args(argv)
    err = sys.stderr
    try:
        config = load_config(args.config, ReplayConfig) if args.config else ReplayConfig()
        noise = config.noise
        if args.odom_noise is not None:
            noise = msgspec.structs.replace(noise, scale=args.odom_noise)
        if args.seed is not None:
            noise = msgspec.structs.replace(noise, seed=args.seed)
        config = msgspec.structs.replace(config, noise=noise)
        if args.odom_sigma_scale is not None:
            config = msgspec.structs.replace(config, odometry_sigma_scale=args.odom_sigma_scale)
        if args.no_scan_odometry:
            config = msgspec.structs.replace(config, scan_odometry=None)
        if args.progress_every < 1:
            raise ValueError(f"--progress-every must be >= 1, got {args.progress_every}")
        if args.scans is not None and args.scans < 1:
            raise ValueError(f"--scans must be >= 1, got {args.scans}")
        log = read_carmen_log(args.carmen)
        if args.scans is not None:
            log = log.subset(slice(0, args.scans))
        relations = read_relations(args.relations) if args.relations else None
    except (ConfigError, CarmenLogError, RelationsFileError, ValueError) as exc:
        print(_one_line(f"magic replay: {exc}"), file=err)
        return 2
    except KeyboardInterrupt:
        print("magic replay: interrupted while reading the input; nothing ran", file=err)
        return 130
    for line in log_clock(log, config.period_s).lines():
        print(_one_line(f"magic replay: {log.path}: {line}"), file=err)
    t0 = time.perf_counter()
    last = [-args.progress_every]

    def progress(done: int, total: int, text: str) -> None:
        if args.quiet or (done - last[0] < args.progress_every and done < total):
            return
        last[0] = done
        width = 30
        bar = "#" * round(width * done / total)
        elapsed = time.perf_counter() - t0
        print(f"replay [{bar:<{width}}] {done}/{total} scans, {text}, {elapsed:.1f} s", file=err)

    def on_term(_signum: int, _frame: object) -> None:
        raise ReplayTerminated

    on_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, on_term) if on_main else None
    try:
        result = run_replay(
            log, config=config, relations=relations, out_dir=args.out, progress=progress
        )
    except KeyboardInterrupt as exc:  # outside the feeding loop: run_replay could not save
        print(
            f"magic replay: stopped by {_signal_name(exc)} outside the scan loop (building the "
            "station, evaluating or saving): the outputs may be incomplete",
            file=err,
        )
        return 143 if isinstance(exc, ReplayTerminated) else 130
    finally:
        if on_main:
            signal.signal(signal.SIGTERM, previous)
    for line in result.evaluation_errors:
        print(_one_line(f"magic replay: {line}"), file=err)
    print("\n".join(_format_summary(result.summary())))
    if result.interrupted is not None:
        print(
            f"magic replay: stopped by {result.interrupted} after {result.scans_done} of "
            f"{result.scans_total} scans; what ran is summarised above",
            file=err,
        )
        return 143 if result.interrupted == "SIGTERM" else 130
    return 0


def _signal_name(exc: BaseException) -> str:
    return "SIGTERM" if isinstance(exc, ReplayTerminated) else "SIGINT"
