"""The ground-control station's estimation core, sans-IO (paper 4.1, 4.2, 4.5, 4.8).

:class:`GroundStation` takes the robots' uplink messages and owns the only global estimate:

* ``PoseNode`` -> a pose of that robot in the :class:`~gcs.graph.pose_graph.PoseGraph`, chained
  to the previous one by its odometry constraint. A robot's first node starts a new component
  (its pose in ``map`` unknown until a constraint links it; paper 4.2 and the UvA manifolds).
* ``TerrainGrid`` -> decoded by its header (``compression.decode_grid``), its vertical-surface
  cells handed to the loop closer (4.3.3) and the rasterizer (4.8). A grid that arrives before
  its pose node waits for it.
* ``FiducialObservation`` -> a ``FIDUCIAL`` edge between the observer's node and the observed
  robot's node nearest in time (4.3.2).
* ``Detection`` of a dangerous object -> a hazard in ``map`` (merged with hazards nearby).

:meth:`GroundStation.step` runs loop closing within a time budget, optimizes incrementally
(iSAM2) and returns the downlink messages: a :class:`~protocol.messages.HazardUpdate` per robot
with every robot's ``map_from_odom`` (paper 4.1: robots never receive the map).

Bad input never raises: it is rejected with a reason naming the robot, message and field,
counted in :attr:`GroundStation.stats` and logged. Nothing accepted is lost: pose nodes that
arrive out of order wait for the missing ones; a gap that does not fill within
``max_pending_nodes`` is bridged from the reported ``pose_in_odom`` values with the covariance
of the node after the gap, inflated by ``gap_covariance_scale`` (and kept within the physical
bounds below). A node rejected at the door leaves a gap that is bridged as soon as the next node
is here.

Physical covariances. A covariance (``PoseNode.odom_covariance``, ``FiducialObservation.
covariance``, ``Detection.position_covariance``) is rejected as ``non_physical_covariance`` when
it has a non-finite entry, is not positive definite, is near singular (condition number above
``max_covariance_condition``, default 1e6: the robots' odometry covariances stay below 150 on
the real logs, and iSAM2 raises on a joining edge of condition 1e8), or states a standard
deviation
above ``max_sigma_xy_m`` (default 1 km: no odometry, tag or detection is that uncertain and
still informative) or ``max_sigma_yaw_rad`` (default 2 pi: a heading variance beyond (2 pi)^2
rad^2 says nothing about the heading and only hurts the solver's conditioning; a robot clock
jump once turned into 1.7e4 rad^2 here).

Clocks. Each robot's node times are checked in chain order: a step of 0 (``frozen``), below 0
(``backwards``), above ``max_node_interval_s`` (``jump``) or a non-finite time
(``non_finite``) is reported once per robot and kind (a log line, ``stats.clock_anomalies``),
and the node is still accepted with a monotone substitute time: the previous node's time plus
the median of the robot's recent plausible steps (``clock_fallback_step_s`` before there are
any). Everything at the GCS that uses node time (graph records, edge times for rewinding,
grid and fiducial matching) sees the substitute; no covariance depends on time here. The
station's own ``now_s`` gets the same treatment (except that a repeated time is normal).

Solver faults. :meth:`GroundStation.step` never raises: an iSAM2 failure is recovered by the
graph (:meth:`gcs.graph.pose_graph.PoseGraph.optimize_incremental`: batch re-solve, fresh
iSAM2) and counted in ``stats.solver_faults`` / ``stats.solver_recoveries``; an unrecovered one
keeps the last good estimate and is retried at the next step.

Scan-checked odometry. A robot's odometry is only as good as its wheels' grip: in sand (the
simulated MAGIC site has a pit with 25% slip) the encoders report up to a third more travel
than the body made, with the usual small covariance, and the map bends there for good unless
a loop closes over it (small world, 300 s: one robot's trajectory 1-2 m off after 8 m of
sand). So every odometry edge whose two grids have arrived is checked against the correlative
match of those grids (standard window, around the odometry): a confident match whose
translation contradicts the edge (:class:`OdometryCheckConfig`, :func:`odometry_contradicted`)
replaces the edge's translation and its covariance, keeping the gyro's heading (a match's
heading in sparse sand was once 4 deg off) (``stats.odometry_replaced``; the robot's report stays in
:meth:`PoseGraph.odometry_reported`, and the replacement is put back after an odometry
recalibration). The check runs at the next :meth:`GroundStation.step`, before loop closing.

Fiducials. A tag sighting relates the observer's node to where the teammate was at the
sighting's time, which lies on the teammate's motion between two of the times its odometry
is known here (its pose nodes and telemetry poses; robots start, stop and turn in place
between nodes): the edge goes to the earlier node with the teammate half way along that step
and the step's uncertainty (:meth:`GroundStation._teammate_node`). Fiducials also tie
robots already linked (``fiducials_link_only`` False): the start hints' errors (0.3 m, 3 deg)
otherwise stay in the map wherever robots share no scan, and in the mission they rarely do
(2-8 cross-robot closures in 300 s). ``magic run`` small world 300 s, seeds 0 / 7, without
them: ATE 0.885 / 0.484 m, F1 0.43 / 0.33 (one robot 1.6 m off, rotated by its hint); with
them: 0.503 / 0.378 m, F1 0.64 / 0.84. Replayed journals, same code,
without / with: ATE 0.435 / 0.470, 0.348 / 0.290, 1.177 / 0.669 m. The team-mapping trial
(100 s, this tree): 0.202 m without, 0.218 m with.

The GCS node (:mod:`gcs.node`) is the thin zenoh shell around this class; the CARMEN replay
(:mod:`mission.replay`) drives it directly.
"""

from __future__ import annotations

import bisect
import collections
import logging
import math
import statistics
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from compression import CodecError, GridReference, decode_grid, read_header
from gcs.graph.keys import pose_key, robot_of, split_key
from gcs.graph.pose_graph import (
    MAX_COVARIANCE_CONDITION,
    AutoSimplifyConfig,
    EdgeRecord,
    PoseGraph,
    PoseGraphConfig,
    PoseGraphError,
    Provenance,
)
from gcs.loops.correlative_matcher import MatchResult, grid_points
from gcs.loops.loop_closer import (
    LoopCloser,
    LoopCloserConfig,
    LoopClosingReport,
    vector_to_body_covariance,
)
from gcs.mapping.overlay import overlay
from gcs.mapping.rasterization import OccupancyMap, RasterConfig, Rasterizer
from protocol.messages import (
    Detection,
    DetectionImage,
    FiducialObservation,
    Hazard,
    HazardUpdate,
    ObjectKind,
    PoseNode,
    RobotFrame,
    TaskStatus,
    Telemetry,
    TerrainGrid,
    covariance_from_upper,
)
from protocol.se2 import compose, inverse, relative, transform_points, wrap_angle

__all__ = [
    "GridRecord",
    "GroundStation",
    "GroundStationConfig",
    "GroundStationStats",
    "OdometryCheckConfig",
    "odometry_contradicted",
]

log = logging.getLogger("magic.gcs")

#: Decoded grids kept per robot as possible references of inter-frame grids.
_REFERENCE_MEMORY = 8

#: Telemetry poses kept per robot (about a minute at the default 1 s period): a fiducial
#: waits at most ``fiducial_wait_s`` for the teammate, so older ones are never needed.
_TELEMETRY_MEMORY = 64

#: Dangerous objects and the keep-out radius robots must respect (paper section 2: trigger
#: radius 2.5 m for static OOIs and hostiles, plus a margin the robot adds itself).
HAZARD_KINDS = {ObjectKind.STATIC_OOI: 2.5, ObjectKind.HOSTILE: 5.0, ObjectKind.MOBILE_OOI: 5.0}

#: Sightings of a static hazard kept to place it under the current estimate (the latest).
MAX_HAZARD_ANCHORS = 64

#: Hazards that move: their position is the latest sighting, not the mean of the sightings.
MOVING_KINDS = (ObjectKind.HOSTILE, ObjectKind.MOBILE_OOI)


class OdometryCheckConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The scan check of each odometry edge (:func:`odometry_contradicted`; module docstring,
    "Scan-checked odometry").

    A match of two consecutive grids counts only when it is confident: normalized score at
    least ``min_score`` and translation standard deviation at most ``max_sigma_xy_m``. It
    replaces the odometry edge when it contradicts it: Mahalanobis ``chi2`` (3 dof, odometry
    and match covariances added) above ``chi2`` and a difference of at least ``min_diff_m``
    in translation or ``min_diff_rad`` in heading (well-measured steps are left alone).
    ``keep_heading``: the replacement keeps the odometry's heading and its variance (the
    gyro's; slip corrupts the wheels' translation) and takes only the match's translation.
    ``max_slip_frac`` / ``slip_floor_m``: a match is slip only while its translation differs
    from the odometry's by at most ``max_slip_frac`` of the step the wheels reported plus
    ``slip_floor_m`` (wheels spinning in place lose the whole step; a robot does not go
    backwards or twice as far as its wheels turned): further, it is a look-alike within the
    standard window (3 m) and is not taken. Small world, seed 7 at 66f8349: robot 1's step of
    1.22 m forward was replaced by a match 1.71 m backwards (score and sigma confident, a
    corridor's repeat), its last 11 nodes 2.75 m off, the run's ATE 0.578 m.
    """

    enabled: bool = True
    keep_heading: bool = True
    min_score: float = 0.5
    max_sigma_xy_m: float = 0.1
    chi2: float = 4.0
    min_diff_m: float = 0.08
    min_diff_rad: float = math.radians(3.0)
    max_slip_frac: float = 1.0
    slip_floor_m: float = 0.2

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_score <= 1.0:
            raise ValueError(f"min_score: expected in [0, 1], got {self.min_score}")
        for name in (
            "max_sigma_xy_m",
            "chi2",
            "min_diff_m",
            "min_diff_rad",
            "max_slip_frac",
            "slip_floor_m",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v}")


def odometry_contradicted(
    odometry: np.ndarray,
    odometry_covariance: np.ndarray,
    match: np.ndarray,
    match_covariance: np.ndarray,
    *,
    chi2: float,
    min_diff_m: float,
    min_diff_rad: float,
) -> tuple[bool, float]:
    """``(contradicted, chi2 value)``: whether the scan match ``match`` (``a_from_b``) of two
    consecutive poses contradicts their odometry edge ``odometry`` (``a_from_b``). Both
    covariances are 3x3 in the body frame of ``b``; the difference is taken in that frame
    (``between(odometry, match)``). Contradicted: Mahalanobis value above ``chi2`` and a
    difference of at least ``min_diff_m`` (m) or ``min_diff_rad`` (rad)."""
    z0 = np.asarray(odometry, dtype=float)
    z1 = np.asarray(match, dtype=float)
    c, s = math.cos(z0[2]), math.sin(z0[2])
    dx, dy = z1[0] - z0[0], z1[1] - z0[1]
    d = np.array([c * dx + s * dy, -s * dx + c * dy, float(wrap_angle(z1[2] - z0[2]))])
    cov = np.asarray(odometry_covariance, dtype=float) + np.asarray(match_covariance, dtype=float)
    value = float(d @ np.linalg.solve(cov, d))
    big = math.hypot(d[0], d[1]) >= min_diff_m or abs(d[2]) >= min_diff_rad
    return bool(big and value > chi2), value


class GroundStationConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Configuration of :class:`GroundStation`.

    ``robots``: the team roster; messages from other ids are rejected (empty: accept any id).
    ``frames_period_s``: mission seconds between hazard/frame updates to each robot.
    ``max_pending_nodes``: out-of-order pose nodes held per robot before a gap is bridged.
    ``max_pending_grids``: grids held per robot while their pose node has not arrived.
    ``max_pending_sightings``: detections and fiducials held per robot while their pose node
    has not arrived (a radio backlog drains the detection stream before the pose nodes).
    ``fiducial_wait_s``: station mission-seconds a fiducial waits for the teammate's pose node
    of its time (the robots' streams race); then the teammate's latest node stands in (it
    has not moved far enough for a new node).
    ``fiducials_link_only``: a fiducial becomes an edge only when it joins two robots' graphs
    not yet connected (paper 4.3.2's purpose: robots that never share a scan); between robots
    already linked it is then counted (``fiducials_redundant``) and left out (module
    docstring, "Fiducials"). When the teammate's nearest node stood in for it (up to half a
    node spacing and its turn away, with the tag's covariance) 14 fiducial edges took the
    team-mapping trial's ATE from 0.09 m to 0.53 m; carried along its step with the step's
    uncertainty they help the mission (module docstring), hence the default False.
    ``max_grid_resolution_m`` / ``min_grid_resolution_m``: accepted grid cell sizes.
    ``gap_covariance_scale``: inflation of the odometry covariance across a bridged gap.
    ``hazard_merge_m``: detections of one kind closer than this are the same hazard.
    ``hostile_merge_m``: a sighting of a moving kind (hostile, mobile OOI) this close to the
    latest position of one already known is the same object (it walks between sightings).
    ``max_sigma_xy_m`` / ``max_sigma_yaw_rad``: largest standard deviation (m, rad) an input
    covariance may state (module docstring, "Physical covariances").
    ``max_covariance_condition``: largest condition number of an input covariance.
    ``max_node_interval_s``: largest plausible step (s) between a robot's consecutive node
    times; ``clock_fallback_step_s``: the substitute step (s) before a robot has plausible ones.
    ``fiducial_standin_sigma_*``: added to a fiducial's covariance when the teammate's latest
    node stands in for where it was (:meth:`GroundStation._teammate_node`), each growing with
    the time since the teammate's last known pose at the team's top speed and turn rate
    (``fiducial_standin_speed_m_s``, ``fiducial_standin_turn_rate_rad_s``): a teammate silent
    for 25 s may be 25 m away from its last node.
    ``fiducial_gate_*``: a fiducial between robots whose relative pose the map already holds
    (one component, or both anchored) is refused (``fiducial_inconsistent``) when it is
    further from the estimate than its covariance plus ``fiducial_gate_sigma_*`` allow
    (Mahalanobis above ``fiducial_gate_chi2``, 3 dof; 0: no gate). The sigmas are wide, so the
    drift a sighting is there to correct passes; what is refused is a sighting the map
    contradicts beyond any drift (a tag read off the wrong face, a teammate mistaken).
    ``fiducial_max_sigma_yaw_rad``: a sighting whose heading (the tag's, with the teammate's
    motion and stand-in added) is known only this loosely makes no edge; it is counted
    (``fiducials_loose_heading``) and left out, as a scan match whose heading sigma exceeds
    ``loops.max_match_sigma_yaw_rad`` is no closure: an edge whose heading sigma exceeds the
    5 deg that makes an edge false cannot be counted on to be true. A tag seen on one face
    only fixes its heading to the robot detector's 17 deg (``single_face_sigma_yaw_rad``).
    The full mission (magic_phase, 14 robots, at 66b4360), its journal's first 720 s replayed:
    19 of its 20 false fiducial edges were such (heading sigma 6-22 deg, 5-25 deg off, within
    1.9 sigma, positions within 0.5 m): right for their covariance and still false edges, and
    they tore the map. With this bound at 5 deg: false fiducials 20 -> 1, false closures
    13 -> 6 (the gross ones, 2.8-4.2 m and 18-29 deg off between robot 11 and robots 2 and
    4, gone), ATE 1.56 -> 0.47 m (at 2.5 deg, the closures' bound: 0.41 m, but on the small
    world's journals, seed 3, two true tags of 3.9-4.4 deg were lost and two false closures
    came in; at 5 deg seeds 0 / 7 / 3 / 11: ATE 0.118 / 0.431 / 0.085 / 0.145 ->
    0.136 / 0.430 / 0.085 / 0.139 m, false closures 0 / 2 / 0 / 0 -> 0 / 3 / 0 / 0, false
    fiducials 0 / 1 / 0 / 0 -> 0); the whole journal: ATE 5.55 -> 1.21 m, false fiducials
    28 -> 1, false closures 21 -> 22. Off by default (0: no bound): at 5 deg the four-robot
    team-mapping trial (tests/mission/test_team_mapping.py, ideal radio) kept 2 of its 10 tag
    edges and took a false closure (0.58 m); at 10 deg the trial's ATE was 0.38 m and the full
    mission's 720 s 2.16 m (8 false fiducials kept); at 15 deg the trial passed (ATE 0.21 m).
    A bound that holds for both is not found yet.
    ``fiducial_max_sigma_xy_m``: a sighting whose teammate's pose at that time is known only
    this loosely (a stand-in silent for long) is refused as ``fiducial_stale``: it says
    nothing (the quick mission bench's seed 7 took one with sigmas 70.6 m and pi rad, which
    the report then scored a false edge, 1.5 m and 176 deg off).
    ``odometry_check``: the scan check of odometry edges (:class:`OdometryCheckConfig`).
    ``raster`` / ``near_raster``: the global map is the near map laid over the far one
    (:mod:`gcs.mapping.overlay`; ``near_raster`` None: the far one alone).
    """

    robots: tuple[int, ...] = ()
    # Algorithm 1 by itself once the graph is large (10,000 poses: a big team's mission; a
    # small one never gets there), after a successful solve with no closure awaiting validation
    graph: PoseGraphConfig = msgspec.field(
        default_factory=lambda: PoseGraphConfig(auto_simplify=AutoSimplifyConfig())
    )
    loops: LoopCloserConfig = msgspec.field(default_factory=LoopCloserConfig)
    # iSAM2 nudges every pose a little on each update: a small tolerance lets the rasterizer
    # reuse submaps (the map is then exact to within it)
    raster: RasterConfig = msgspec.field(
        default_factory=lambda: RasterConfig(pose_tolerance_m=0.005, pose_tolerance_rad=0.001)
    )
    # the near map laid over it (gcs.mapping.overlay): walls erased only by free space seen
    # from close by; None: the one map
    near_raster: RasterConfig | None = msgspec.field(
        default_factory=lambda: RasterConfig(
            pose_tolerance_m=0.005, pose_tolerance_rad=0.001, free_range_m=4.0, wall_gap_m=0.8
        )
    )
    loop_budget_s: float = 0.2
    frames_period_s: float = 2.0
    max_pending_nodes: int = 32
    max_pending_grids: int = 64
    max_pending_sightings: int = 512
    fiducial_wait_s: float = 5.0
    fiducials_link_only: bool = False
    fiducial_standin_sigma_xy_m: float = 0.5
    fiducial_standin_sigma_yaw_rad: float = 0.2
    fiducial_standin_speed_m_s: float = 1.0
    fiducial_standin_turn_rate_rad_s: float = 1.2
    fiducial_gate_sigma_xy_m: float = 2.0
    fiducial_gate_sigma_yaw_rad: float = 0.5
    fiducial_gate_chi2: float = 16.27  # chi-square 0.999, 3 dof
    fiducial_max_sigma_xy_m: float = 5.0
    fiducial_max_sigma_yaw_rad: float = 0.0
    min_grid_resolution_m: float = 0.02
    max_grid_resolution_m: float = 1.0
    gap_covariance_scale: float = 4.0
    hazard_merge_m: float = 1.5
    hostile_merge_m: float = 4.0
    error_log_size: int = 100
    max_sigma_xy_m: float = 1000.0
    max_sigma_yaw_rad: float = 2.0 * math.pi
    max_covariance_condition: float = 1e6
    max_node_interval_s: float = 3600.0
    clock_fallback_step_s: float = 1.0
    odometry_check: OdometryCheckConfig = msgspec.field(default_factory=OdometryCheckConfig)

    def __post_init__(self) -> None:
        for name in (
            "frames_period_s",
            "gap_covariance_scale",
            "hazard_merge_m",
            "hostile_merge_m",
            "loop_budget_s",
            "max_sigma_xy_m",
            "max_sigma_yaw_rad",
            "max_covariance_condition",
            "max_node_interval_s",
            "clock_fallback_step_s",
            "fiducial_standin_sigma_xy_m",
            "fiducial_standin_sigma_yaw_rad",
            "fiducial_standin_speed_m_s",
            "fiducial_standin_turn_rate_rad_s",
            "fiducial_gate_sigma_xy_m",
            "fiducial_gate_sigma_yaw_rad",
            "fiducial_max_sigma_xy_m",
            "fiducial_max_sigma_yaw_rad",
        ):
            v = getattr(self, name)
            if name == "fiducial_max_sigma_yaw_rad" and v == 0.0:
                continue  # 0: no bound
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v}")
        if not (math.isfinite(self.fiducial_gate_chi2) and self.fiducial_gate_chi2 >= 0):
            raise ValueError(f"fiducial_gate_chi2: expected >= 0, got {self.fiducial_gate_chi2}")
        for name in (
            "max_pending_nodes",
            "max_pending_grids",
            "max_pending_sightings",
            "error_log_size",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name}: expected >= 1, got {getattr(self, name)}")
        if any(r < 0 for r in self.robots):
            raise ValueError(f"robots: ids must be >= 0, got {self.robots}")


@dataclass
class GroundStationStats:
    """Counters of what the station accepted and rejected (rejections by reason).

    ``solver_faults``: incremental solves that failed; ``solver_recoveries``: those answered by
    a batch re-solve (the others kept the last good estimate and were retried).
    ``clock_anomalies``: clock faults detected, by kind (``frozen``, ``backwards``, ``jump``,
    ``non_finite``), each counted once per robot (``gcs`` for the station's own clock);
    ``clock_substitutions``: node times replaced by a monotone substitute.
    ``loop_closer_faults`` / ``internal_errors``: exceptions the station caught in the loop
    closer and elsewhere (a bug, logged with its traceback; the station went on).
    ``sightings_held``: detections and fiducials that arrived before their pose node and
    waited for it. ``odometry_checks`` / ``odometry_replaced``: odometry edges matched against
    their two grids / replaced by the match (module docstring, "Scan-checked odometry");
    ``odometry_implausible``: contradicting matches left out as farther from the odometry
    than slip can take a robot (``OdometryCheckConfig.max_slip_frac``).
    ``simplifications`` / ``edges_simplified_away``: Algorithm 1 runs (automatic or the
    operator's) and the edges they merged away.
    """

    pose_nodes: int = 0
    terrain_grids: int = 0
    fiducials: int = 0
    detections: int = 0
    fiducials_redundant: int = 0
    fiducials_loose_heading: int = 0
    sightings_held: int = 0
    duplicates: int = 0
    gaps_bridged: int = 0
    optimizations: int = 0
    solver_faults: int = 0
    solver_recoveries: int = 0
    clock_substitutions: int = 0
    loop_closer_faults: int = 0
    internal_errors: int = 0
    odometry_checks: int = 0
    odometry_replaced: int = 0
    odometry_implausible: int = 0
    simplifications: int = 0
    edges_simplified_away: int = 0
    clock_anomalies: collections.Counter[str] = field(default_factory=collections.Counter)
    rejected: collections.Counter[str] = field(default_factory=collections.Counter)
    errors: collections.deque[str] = field(default_factory=lambda: collections.deque(maxlen=100))

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())


@dataclass(frozen=True)
class GridRecord:
    """A decoded vertical-surface grid of pose ``key`` (cells in the node's ``base`` frame)."""

    key: int
    time_s: float
    grid: np.ndarray  # bool (height, width)
    origin_in_base: tuple[float, float]
    resolution_m: float


@dataclass
class _ClockCheck:
    """Monotone substitute of a clock that may freeze, run backwards or jump (module doc)."""

    allow_repeat: bool = False
    last_raw_s: float | None = None
    last_s: float | None = None
    steps_s: collections.deque[float] = field(default_factory=lambda: collections.deque(maxlen=15))
    reported: set[str] = field(default_factory=set)

    def check(self, raw_s: float, max_step_s: float, fallback_s: float) -> tuple[float, str | None]:
        """``(substitute time, anomaly kind or None)`` of the next reading ``raw_s``."""
        if self.last_s is None or self.last_raw_s is None:
            if not math.isfinite(raw_s):
                self.last_s = 0.0
                return 0.0, "non_finite"
            self.last_raw_s = self.last_s = raw_s
            return raw_s, None
        kind: str | None = None
        if not math.isfinite(raw_s):
            kind = "non_finite"
        else:
            dt = raw_s - self.last_raw_s
            if dt == 0.0 and not self.allow_repeat:
                kind = "frozen"
            elif dt < 0.0:
                kind = "backwards"
            elif dt > max_step_s:
                kind = "jump"
            self.last_raw_s = raw_s
            if kind is None:
                self.steps_s.append(dt)
                self.last_s += dt
                return self.last_s, None
        step = (
            0.0
            if self.allow_repeat
            else (statistics.median(self.steps_s) if self.steps_s else fallback_s)
        )
        self.last_s += step
        if kind == "non_finite":
            self.last_raw_s += step  # the missing reading, assumed one step on
        return self.last_s, kind


@dataclass
class _Track:
    """What the station knows of one robot's stream of pose nodes."""

    next_index: int = 0
    keys: dict[int, int] = field(default_factory=dict)  # node_index -> graph key
    times: list[float] = field(default_factory=list)  # node times (substitutes), graph order
    raw_times: dict[int, tuple[float, float]] = field(default_factory=dict)  # index -> raw, used
    clock: _ClockCheck = field(default_factory=_ClockCheck)
    lost: set[int] = field(default_factory=set)  # indices rejected at the door: bridge them
    graph_keys: list[int] = field(default_factory=list)
    pending_nodes: dict[int, PoseNode] = field(default_factory=dict)
    pending_grids: dict[int, TerrainGrid] = field(default_factory=dict)
    # detections and fiducials that came before their pose node, in arrival order
    pending_sightings: list[tuple[Detection | FiducialObservation, float]] = field(
        default_factory=list
    )  # (message, station time it was held)
    deltas: dict[int, Any] = field(default_factory=dict)  # node_index -> odom_delta
    # recent decoded grids (references of inter-frame grids): index -> grid, origin cells, res
    decoded: dict[int, tuple[np.ndarray, tuple[int, int], float]] = field(default_factory=dict)
    decoded_floor: int = 0  # grids below this index are no longer kept as references
    undecodable: set[int] = field(default_factory=set)
    telemetry: Telemetry | None = None
    last_status: TaskStatus | None = None
    last_heard_s: float | None = None  # station time of the latest message, accepted or not
    last_pose_in_odom: np.ndarray | None = None  # of the latest node added to the graph
    poses_in_odom: list[np.ndarray] = field(default_factory=list)  # reported, graph order
    # recent telemetry poses (robot time, pose_in_odom), increasing time: where it was between
    # its nodes when a teammate saw it
    telemetry_times: collections.deque[float] = field(
        default_factory=lambda: collections.deque(maxlen=_TELEMETRY_MEMORY)
    )
    telemetry_poses: collections.deque[np.ndarray] = field(
        default_factory=lambda: collections.deque(maxlen=_TELEMETRY_MEMORY)
    )


class _Rejected(Exception):
    """Internal: a message is refused; ``reason`` is the counter name, the text says why."""

    def __init__(self, reason: str, text: str) -> None:
        super().__init__(text)
        self.reason = reason


def _finite(values: Any, what: str) -> np.ndarray:
    a = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(a)):
        raise _Rejected("non_finite", f"{what}: non-finite value in {tuple(a.ravel())}")
    return a


def _physical_covariance(
    cov: np.ndarray,
    what: str,
    *,
    max_sigma_xy_m: float,
    max_sigma_yaw_rad: float | None,
    max_condition: float,
) -> np.ndarray:
    """``cov`` (3x3 x, y, yaw or 2x2 x, y) if it is a physical covariance (module docstring),
    else :class:`_Rejected` with reason ``non_physical_covariance`` saying what is wrong."""

    def bad(text: str) -> _Rejected:
        return _Rejected("non_physical_covariance", f"{what}: {text}")

    if not np.all(np.isfinite(cov)):
        upper = tuple(float(v) for v in cov[np.triu_indices(len(cov))])
        raise bad(f"non-finite entry in {upper}")
    eig = np.linalg.eigvalsh(cov)
    if not eig[0] > 0:
        raise bad(f"not positive definite (eigenvalues {tuple(float(f'{e:.3g}') for e in eig)})")
    sigma_xy = math.sqrt(float(np.linalg.eigvalsh(cov[:2, :2])[-1]))
    if sigma_xy > max_sigma_xy_m:
        raise bad(f"xy sigma {sigma_xy:.4g} m above the {max_sigma_xy_m:g} m bound")
    if max_sigma_yaw_rad is not None and cov[2, 2] > max_sigma_yaw_rad**2:
        raise bad(
            f"yaw variance {cov[2, 2]:.4g} rad^2 above the {max_sigma_yaw_rad**2:.4g} rad^2 bound"
        )
    if eig[-1] > max_condition * eig[0]:
        cond = eig[-1] / eig[0]
        raise bad(f"near singular (condition number {cond:.3g} above {max_condition:g})")
    return cov


class GroundStation:
    """Sans-IO core of the GCS: uplink messages in, graph and maps inside, downlink out."""

    def __init__(self, config: GroundStationConfig | None = None) -> None:
        self.config = config or GroundStationConfig()
        self.graph = PoseGraph(self.config.graph)
        self.stats = GroundStationStats(errors=collections.deque(maxlen=self.config.error_log_size))
        self.grids: dict[int, GridRecord] = {}
        self.rasterizer = Rasterizer(self.config.raster)
        near = self.config.near_raster
        self.near_rasterizer = None if near is None else Rasterizer(near)
        self.loop_closer = LoopCloser(self.graph, self.config.loops)
        self.last_loop_report: LoopClosingReport | None = None
        self.hazards: list[Hazard] = []
        self._sightings: list[int] = []  # per hazard, detections merged into it
        # per hazard, the (pose key, position in that pose's base) of its latest sightings of
        # a static kind: its position follows the estimate (:meth:`_reexpress_hazards`)
        self._anchors: list[list[tuple[int, np.ndarray]]] = []
        # moving hazards: hazard id -> robot id -> mission time of that robot's latest sighting
        self._hostile_seen: dict[int, dict[int, float]] = {}
        self._handle_now_s = 0.0
        self._waited = False  # draining sightings that waited their time (fiducial_wait_s)
        self._tracks: dict[int, _Track] = {}
        self._dirty = False
        self._last_frames_s: dict[int, float] = {}
        self._key_time: dict[int, float] = {}
        self._hints: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._clock = _ClockCheck(allow_repeat=True)  # the station's own now_s
        # scan-checked odometry: pairs (a, b) of consecutive keys with both grids, to check
        self._odometry_due: list[tuple[int, int]] = []
        self._odometry_edge: dict[int, int] = {}  # key_b -> odometry edge id (filled lazily)
        # key_b -> the odometry edge into it as reported (a_from_b, covariance), until checked
        self._odometry_in: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._odometry_replaced: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._recalibrations_seen = 0

    # ---- input -----------------------------------------------------------------------------

    def handle(self, robot_id: int, msg: object, *, now_s: float) -> bool:
        """Take one uplink message of ``robot_id``; returns whether it was accepted.

        Never raises on bad input: a refused message is counted by reason in
        :attr:`stats` and its explanation kept in ``stats.errors`` and logged.
        """
        try:
            if self.config.robots and robot_id not in self.config.robots:
                raise _Rejected("unknown_robot", f"robot {robot_id} is not on the roster")
            track = self._tracks.setdefault(robot_id, _Track())
            if math.isfinite(now_s):
                heard = track.last_heard_s
                track.last_heard_s = now_s if heard is None else max(heard, float(now_s))
                self._handle_now_s = float(now_s)
            if isinstance(msg, PoseNode):
                self._on_pose_node(robot_id, track, msg)
            elif isinstance(msg, TerrainGrid):
                self._on_grid(robot_id, track, msg)
            elif isinstance(msg, FiducialObservation):
                self._on_fiducial(robot_id, track, msg)
            elif isinstance(msg, Detection):
                self._on_detection(robot_id, track, msg)
            elif isinstance(msg, Telemetry):
                track.telemetry = msg
                self._keep_telemetry_pose(track, msg)
            elif isinstance(msg, TaskStatus):
                track.last_status = msg
            elif isinstance(msg, DetectionImage):
                pass  # images are for operators' views
            else:
                raise _Rejected("unknown_message", f"unexpected message {type(msg).__name__}")
        except _Rejected as err:
            self._reject(robot_id, msg, err.reason, str(err))
            return False
        except (PoseGraphError, ValueError) as err:  # the graph refused it: same treatment
            self._reject(robot_id, msg, "graph_refused", str(err))
            return False
        except Exception as err:  # a bug: the station keeps running, the message is refused
            self.stats.internal_errors += 1
            log.exception("internal error on robot %s %s", robot_id, type(msg).__name__)
            self._reject(robot_id, msg, "internal_error", f"{type(err).__name__}: {err}")
            return False
        return True

    def _reject(self, robot_id: int, msg: object, reason: str, text: str) -> None:
        line = f"robot {robot_id} {type(msg).__name__}: {text}"
        self.stats.rejected[reason] += 1
        self.stats.errors.append(line)
        log.warning("rejected %s", line)

    def _on_pose_node(self, robot_id: int, track: _Track, msg: PoseNode) -> None:
        what = f"node {msg.node_index}"
        if msg.node_index < track.next_index or msg.node_index in track.pending_nodes:
            self.stats.duplicates += 1
            return
        try:
            _finite(msg.pose_in_odom, f"{what} pose_in_odom")
            if msg.node_index > 0:  # a robot's first node carries no constraint
                self._check_covariance(
                    covariance_from_upper(msg.odom_covariance), f"{what} odom_covariance"
                )
        except _Rejected:
            # the chain goes on without it: the next node is bridged to the previous one
            track.lost.add(msg.node_index)
            self._drain_nodes(robot_id, track)
            raise
        track.lost.discard(msg.node_index)
        track.pending_nodes[msg.node_index] = msg
        self._drain_nodes(robot_id, track)
        if len(track.pending_nodes) > self.config.max_pending_nodes:
            # The missing nodes are lost for good (a robot restart, a dropped queue): bridge.
            track.next_index = min(track.pending_nodes)
            track.lost = {i for i in track.lost if i > track.next_index}
            self._drain_nodes(robot_id, track, bridging=True)

    def _check_covariance(self, cov: np.ndarray, what: str) -> np.ndarray:
        cfg = self.config
        return _physical_covariance(
            cov,
            what,
            max_sigma_xy_m=cfg.max_sigma_xy_m,
            max_sigma_yaw_rad=cfg.max_sigma_yaw_rad if cov.shape == (3, 3) else None,
            max_condition=min(cfg.max_covariance_condition, MAX_COVARIANCE_CONDITION),
        )

    def _bounded(self, cov: np.ndarray) -> np.ndarray:
        """``cov`` scaled down (per axis, so it stays positive definite) to the physical bounds."""
        cfg = self.config
        bound = np.array([cfg.max_sigma_xy_m**2, cfg.max_sigma_xy_m**2, cfg.max_sigma_yaw_rad**2])
        d = np.sqrt(np.minimum(1.0, bound / np.diag(cov)))
        return cov * d[:, None] * d[None, :]

    def _node_time(self, robot_id: int, track: _Track, msg: PoseNode) -> float:
        """The node's time on the robot's monotone substitute clock (module docstring)."""
        cfg = self.config
        previous_s = track.clock.last_raw_s
        time_s, kind = track.clock.check(
            float(msg.time_s), cfg.max_node_interval_s, cfg.clock_fallback_step_s
        )
        track.raw_times[msg.node_index] = (float(msg.time_s), time_s)
        if kind is not None:
            self.stats.clock_substitutions += 1
            where = f"robot {robot_id} node {msg.node_index}"
            self._clock_anomaly(where, track.clock, kind, msg.time_s, previous_s, time_s)
        return time_s

    def _clock_anomaly(
        self,
        where: str,
        clock: _ClockCheck,
        kind: str,
        raw_s: float,
        previous_s: float | None,
        substitute_s: float,
    ) -> None:
        if kind in clock.reported:
            return
        clock.reported.add(kind)
        self.stats.clock_anomalies[kind] += 1
        line = (
            f"{where}: {kind} clock (time {raw_s!r} s after {previous_s!r} s); accepted with "
            f"monotone substitute time {substitute_s:.3f} s (reported once per kind)"
        )
        self.stats.errors.append(line)
        log.warning("clock anomaly: %s", line)

    def _drain_nodes(self, robot_id: int, track: _Track, *, bridging: bool = False) -> None:
        while True:
            if track.next_index in track.pending_nodes:
                msg = track.pending_nodes.pop(track.next_index)
            elif track.next_index in track.lost and any(
                i > track.next_index for i in track.pending_nodes
            ):
                # rejected at the door and a later node is here: bridge over it now
                track.lost.discard(track.next_index)
                track.next_index += 1
                bridging = True
                continue
            else:
                break
            cov = None
            if track.graph_keys:
                cov = covariance_from_upper(msg.odom_covariance)
                if bridging:
                    self.stats.gaps_bridged += 1
                    cov = self._bounded(cov * self.config.gap_covariance_scale)
            bridging = False
            key = self.graph.add_pose(
                robot_id,
                odom_from_base=np.asarray(msg.pose_in_odom, dtype=float),
                time_s=self._node_time(robot_id, track, msg),
                odometry_covariance=cov,
            )
            time_s = track.raw_times[msg.node_index][1]
            pose_in_odom = np.asarray(msg.pose_in_odom, dtype=float)
            if track.last_pose_in_odom is not None and cov is not None:
                if self.config.odometry_check.enabled:
                    z_odo = np.asarray(relative(track.last_pose_in_odom, pose_in_odom))
                    self._odometry_in[key] = (z_odo, cov)
            track.last_pose_in_odom = pose_in_odom
            track.keys[msg.node_index] = key
            track.graph_keys.append(key)
            track.times.append(time_s)
            track.poses_in_odom.append(pose_in_odom)
            self._key_time[key] = time_s
            track.next_index = msg.node_index + 1
            self.stats.pose_nodes += 1
            self._dirty = True
            track.deltas[msg.node_index] = msg.odom_delta
            if len(track.graph_keys) == 1:
                self._apply_hints()
        self._drain_grids(robot_id, track)
        self._drain_sightings()

    def add_start_hint(
        self,
        robot_id: int,
        *,
        map_from_odom: Any,
        sigma_xy_m: float,
        sigma_yaw_rad: float,
    ) -> None:
        """Operator hint (paper 6.1): where ``robot_id``'s private frame starts in ``map``.

        Becomes a loose ``LOOP_OPERATOR`` edge from the map robot's first pose to this robot's
        first pose (applied once both exist), so the robot's trajectory is linked to ``map``
        with that uncertainty and the loop closer searches it against the others.
        """
        z = np.asarray(map_from_odom, dtype=float)
        if z.shape != (3,) or not np.all(np.isfinite(z)):
            raise ValueError(f"start hint of robot {robot_id}: bad map_from_odom {z}")
        if not (sigma_xy_m > 0 and sigma_yaw_rad > 0):
            raise ValueError(f"start hint of robot {robot_id}: sigmas must be > 0")
        if robot_id == self.config.graph.map_robot_id:
            raise ValueError(f"robot {robot_id} defines map; it takes no start hint")
        cov = np.diag([sigma_xy_m**2, sigma_xy_m**2, sigma_yaw_rad**2])
        self._hints[robot_id] = (z, cov)
        self._apply_hints()

    def _apply_hints(self) -> None:
        anchor = self._tracks.get(self.config.graph.map_robot_id)
        if anchor is None or not anchor.graph_keys:
            return
        key0 = anchor.graph_keys[0]
        map_from_base0 = compose(
            np.asarray(self.config.graph.map_from_odom, dtype=float),
            self.graph.nodes(self.config.graph.map_robot_id)[0].odom_from_base,
        )
        for robot_id, (map_from_odom, cov) in list(self._hints.items()):
            track = self._tracks.get(robot_id)
            if track is None or not track.graph_keys:
                continue
            key = track.graph_keys[0]
            odom_from_base = self.graph.nodes(robot_id)[0].odom_from_base
            z = relative(map_from_base0, compose(map_from_odom, odom_from_base))
            self.graph.add_edge(
                key0,
                key,
                a_from_b=z,
                covariance=cov,
                provenance=Provenance.LOOP_OPERATOR,
                time_s=self._key_time[key],
            )
            del self._hints[robot_id]
            self._dirty = True

    def _on_grid(self, robot_id: int, track: _Track, msg: TerrainGrid) -> None:
        try:
            self._take_grid(robot_id, track, msg)
        except _Rejected:
            # a lost grid also loses the inter-frame grid coded against it
            if msg.node_index not in track.decoded:
                track.undecodable.add(msg.node_index)
                self._drain_grids(robot_id, track)
            raise

    def _take_grid(self, robot_id: int, track: _Track, msg: TerrainGrid) -> None:
        what = f"grid of node {msg.node_index}"
        res = msg.resolution_m
        if not (self.config.min_grid_resolution_m <= res <= self.config.max_grid_resolution_m):
            raise _Rejected("bad_grid", f"{what}: resolution_m {res} outside accepted range")
        try:
            read_header(msg.data)
        except CodecError as err:
            raise _Rejected("bad_grid", f"{what}: {err}") from None
        key = track.keys.get(msg.node_index)
        if (
            msg.node_index in track.decoded
            or msg.node_index in track.pending_grids
            or (key is not None and key in self.grids)
        ):
            self.stats.duplicates += 1
            return
        if msg.node_index < track.next_index and msg.node_index not in track.keys:
            raise _Rejected("orphan_grid", f"{what}: its pose node was never received")
        if len(track.pending_grids) >= self.config.max_pending_grids:
            raise _Rejected("orphan_grid", f"{what}: too many grids wait for pose nodes")
        track.pending_grids[msg.node_index] = msg
        self._drain_grids(robot_id, track, current=msg.node_index)

    def _drain_grids(self, robot_id: int, track: _Track, *, current: int | None = None) -> None:
        """Decode the waiting grids whose pose node (and, for an inter-frame grid, whose
        reference grid) is here; a grid that can never be decoded is rejected (raised if it
        is the ``current`` message's, counted here otherwise)."""
        progress = True
        while progress and track.pending_grids:
            progress = False
            for index in sorted(track.pending_grids):
                msg = track.pending_grids[index]
                key = track.keys.get(index)
                if key is None:
                    continue
                try:
                    grid = self._decode(track, msg)
                except _Rejected as err:
                    del track.pending_grids[index]
                    track.undecodable.add(index)
                    if index == current:
                        raise
                    self._reject(robot_id, msg, err.reason, str(err))
                    continue
                if grid is None:
                    continue  # its reference grid has not arrived yet
                del track.pending_grids[index]
                self._attach_grid(track, key, msg, grid)
                progress = True

    def _decode(self, track: _Track, msg: TerrainGrid) -> np.ndarray | None:
        """The grid, or None while its reference is missing (compression's inter-frame codec
        references the previous node's grid, warped by this node's ``odom_delta``)."""
        what = f"grid of node {msg.node_index}"
        header = read_header(msg.data)
        reference = None
        if header.reference_node is not None:
            previous = msg.node_index - 1
            if (previous & 0xFF) != header.reference_node:
                raise _Rejected(
                    "bad_grid",
                    f"{what}: coded against node {header.reference_node} (mod 256), "
                    f"not the previous node {previous}",
                )
            if previous in track.undecodable or previous < track.decoded_floor:
                raise _Rejected("missing_reference", f"{what}: grid of node {previous} is lost")
            ref = track.decoded.get(previous)
            if ref is None:
                return None
            grid_prev, origin_prev, res_prev = ref
            delta = tuple(float(v) for v in track.deltas[msg.node_index])
            reference = GridReference(previous, grid_prev, origin_prev, delta, res_prev)  # type: ignore[arg-type]
        try:
            return decode_grid(msg.data, reference=reference)
        except CodecError as err:
            raise _Rejected("bad_grid", f"{what}: {err}") from None

    def _attach_grid(self, track: _Track, key: int, msg: TerrainGrid, grid: np.ndarray) -> None:
        time_s = self._key_time[key]
        header = read_header(msg.data)
        res = float(msg.resolution_m)
        origin = (header.origin_cells[0] * res, header.origin_cells[1] * res)
        record = GridRecord(key, time_s, grid, origin, res)
        self.rasterizer.add_node(key, time_s, grid, record.origin_in_base, record.resolution_m)
        if self.near_rasterizer is not None:
            self.near_rasterizer.add_node(
                key, time_s, grid, record.origin_in_base, record.resolution_m
            )
        points = grid_points(grid, origin_m=record.origin_in_base, resolution_m=record.resolution_m)
        self.loop_closer.add_scan(key, points)
        self.grids[key] = record
        if self.config.odometry_check.enabled:
            robot, index = split_key(key)
            for a in (index - 1, index):
                if a < 0:
                    continue
                ka, kb = pose_key(robot, a), pose_key(robot, a + 1)
                if ka in self.grids and kb in self.grids:
                    self._odometry_due.append((ka, kb))
        self.stats.terrain_grids += 1
        track.decoded[msg.node_index] = (grid, header.origin_cells, record.resolution_m)
        track.undecodable.discard(msg.node_index)
        for old in [i for i in track.decoded if i < msg.node_index - _REFERENCE_MEMORY]:
            del track.decoded[old]
            track.decoded_floor = max(track.decoded_floor, old + 1)

    def _on_fiducial(self, robot_id: int, track: _Track, msg: FiducialObservation) -> None:
        what = f"fiducial of node {msg.node_index}"
        z = _finite(msg.observed_in_base, f"{what} observed_in_base")
        cov = self._check_covariance(covariance_from_upper(msg.covariance), f"{what} covariance")
        key_a = track.keys.get(msg.node_index)
        if key_a is None:
            self._hold_sighting(track, msg, "orphan_fiducial", f"{what}: pose node not received")
            return
        other = self._tracks.get(msg.observed_robot_id)
        roster = self.config.robots
        if msg.observed_robot_id == robot_id or (roster and msg.observed_robot_id not in roster):
            raise _Rejected("unknown_robot", f"{what}: observed robot {msg.observed_robot_id}")
        if other is None or not other.graph_keys:
            why = f"{what}: observed robot {msg.observed_robot_id} has no pose nodes here"
            self._hold_sighting(track, msg, "unknown_robot", why, own_node=False)
            return
        seen_s = self._seen_s(track, msg)
        if other.times[-1] < seen_s and not self._waited:
            # the teammate's pose node of that time is still on its way: wait for it
            why = f"{what}: robot {msg.observed_robot_id}'s pose node of t={seen_s:.1f} s not here"
            self._hold_sighting(track, msg, "unknown_robot", why, own_node=False)
            return
        i, z_i, cov_i = self._teammate_node(other, seen_s, z, cov)
        sigma_xy = math.sqrt(max(cov_i[0, 0], cov_i[1, 1]))
        if not (sigma_xy <= self.config.fiducial_max_sigma_xy_m):
            raise _Rejected(
                "fiducial_stale",
                f"{what}: robot {msg.observed_robot_id}'s pose at t={seen_s:.1f} s known only to "
                f"{sigma_xy:.1f} m (its last pose is stale); the sighting says nothing",
            )
        self._gate_fiducial(key_a, other.graph_keys[i], z_i, cov_i, what)
        bound = self.config.fiducial_max_sigma_yaw_rad
        if bound > 0.0 and not cov_i[2, 2] <= bound**2:
            # its heading is too loose to be a true edge (config docstring): no edge, not an
            # error (the robot measured what it could)
            self.stats.fiducials_loose_heading += 1
            return
        if self.config.fiducials_link_only:
            comp = self.graph.components()
            if comp[key_a] == comp[other.graph_keys[i]]:
                self.stats.fiducials_redundant += 1
                return
        self.graph.add_edge(
            key_a,
            other.graph_keys[i],
            a_from_b=z_i,
            covariance=cov_i,
            provenance=Provenance.FIDUCIAL,
            time_s=seen_s,
        )
        self.stats.fiducials += 1
        self._dirty = True

    def _gate_fiducial(
        self, key_a: int, key_b: int, z: np.ndarray, cov: np.ndarray, what: str
    ) -> None:
        """Raise ``fiducial_inconsistent`` when the map already relates ``key_a`` and
        ``key_b`` and ``z`` (``a_from_b``) is beyond the gate (config ``fiducial_gate_*``)."""
        cfg = self.config
        if not (cfg.fiducial_gate_chi2 > 0):
            return
        comp = self.graph.components()
        ca, cb = comp[key_a], comp[key_b]
        if ca != cb:
            anchored = self.graph.anchored_components()
            if ca not in anchored or cb not in anchored:
                return  # nothing to compare with: the sighting is what links them
        predicted = relative(self.graph.pose(key_a), self.graph.pose(key_b))
        err = np.asarray(relative(predicted, z), dtype=float)
        err[2] = float(wrap_angle(err[2]))
        sxy, syaw = cfg.fiducial_gate_sigma_xy_m, cfg.fiducial_gate_sigma_yaw_rad
        gate = cov + np.diag([sxy**2, sxy**2, syaw**2])
        value = float(err @ np.linalg.solve(gate, err))
        if not (value <= cfg.fiducial_gate_chi2):
            raise _Rejected(
                "fiducial_inconsistent",
                f"{what}: {math.hypot(err[0], err[1]):.2f} m and "
                f"{math.degrees(err[2]):.0f} deg from where the map has that teammate "
                f"(chi2 {value:.1f} > {cfg.fiducial_gate_chi2})",
            )

    def _keep_telemetry_pose(self, track: _Track, msg: Telemetry) -> None:
        t = float(msg.time_s)
        pose = np.asarray(msg.pose_in_odom, dtype=float)
        if not (math.isfinite(t) and np.all(np.isfinite(pose))):
            return
        if track.telemetry_times and t <= track.telemetry_times[-1]:
            return  # latest-only stream: an older one adds nothing
        track.telemetry_times.append(t)
        track.telemetry_poses.append(pose)

    def _teammate_node(
        self, other: _Track, seen_s: float, z: np.ndarray, cov: np.ndarray
    ) -> tuple[int, np.ndarray, np.ndarray]:
        """``(graph index i, a_from_node_i, covariance)`` of a fiducial ``z`` (the teammate's
        ``base`` at ``seen_s`` in the observer node's ``base``; module docstring, "Fiducials").

        The teammate's odometry is known at its pose nodes and at its telemetry times: it was
        somewhere on its motion between the last of those not after ``seen_s`` and the first
        not before it. Robots start, stop and turn in place between them, so time says little
        about where: the edge to node ``i`` (the last node not after ``seen_s``) puts the
        teammate half way along that step, with the variance of a uniform position along it
        (``d d^T / 12``) added to the covariance (exact when the two agree: a teammate
        standing still). With nothing after ``seen_s`` the teammate's latest known pose (its
        latest node, or a later telemetry pose composed onto it) stands in, and the covariance
        grows by ``fiducial_standin_sigma_*`` plus what the teammate could have driven and
        turned since that pose (a stale stand-in with a fixed 0.5 m sigma once tied two robots
        19 m and 41 deg apart)."""
        times = other.times
        poses = other.poses_in_odom
        j = bisect.bisect_right(times, seen_s)
        cfg = self.config

        def standin(since_s: float) -> np.ndarray:
            stale_s = abs(seen_s - since_s)
            xy = cfg.fiducial_standin_sigma_xy_m + cfg.fiducial_standin_speed_m_s * stale_s
            turn_rad = cfg.fiducial_standin_turn_rate_rad_s * stale_s
            yaw = cfg.fiducial_standin_sigma_yaw_rad + turn_rad
            return np.diag([xy**2, xy**2, min(yaw, math.pi) ** 2])

        if j == 0:
            return 0, z, cov + standin(times[0])
        node = poses[j - 1]
        if seen_s <= times[j - 1]:  # seen at the node's own time
            return j - 1, z, cov
        t0, p0 = times[j - 1], node
        t1, p1 = (times[j], poses[j]) if j < len(times) else (math.inf, None)
        tt = other.telemetry_times
        k = bisect.bisect_right(tt, seen_s)
        if k > 0 and tt[k - 1] > t0:
            t0, p0 = tt[k - 1], other.telemetry_poses[k - 1]
        if k < len(tt) and tt[k] < t1:
            t1, p1 = tt[k], other.telemetry_poses[k]
        if p1 is None:  # nothing after seen_s: the latest known pose stands in
            node_from_p0 = np.asarray(relative(node, p0), dtype=float)
            a_from_node = np.asarray(compose(z, inverse(node_from_p0)), dtype=float)
            return j - 1, a_from_node, cov + standin(t0)
        if seen_s <= t0:
            d = np.zeros(3)
        else:
            d = np.asarray(relative(p0, p1), dtype=float)
            d[2] = float(wrap_angle(d[2]))
        node_from_p0 = np.asarray(relative(node, p0), dtype=float)
        node_from_seen = compose(node_from_p0, 0.5 * d)  # half way along the step
        c, s_ = math.cos(node_from_p0[2]), math.sin(node_from_p0[2])
        v = np.array([c * d[0] - s_ * d[1], s_ * d[0] + c * d[1], d[2]])  # the step, node axes
        a_from_node = np.asarray(compose(z, inverse(node_from_seen)), dtype=float)
        return j - 1, a_from_node, cov + np.outer(v, v) / 12.0

    def _hold_sighting(
        self,
        track: _Track,
        msg: Detection | FiducialObservation,
        reason: str,
        why: str,
        *,
        own_node: bool = True,
    ) -> None:
        """Keep a sighting that came too early: its own pose node is still to come (its index
        is ahead of the robot's stream) or, ``own_node=False``, the teammate a fiducial saw has
        no pose node here yet (the robots' streams race). One whose node was lost or passed is
        refused with ``reason``."""
        if own_node and msg.node_index < track.next_index:
            raise _Rejected(reason, why)
        if len(track.pending_sightings) >= self.config.max_pending_sightings:
            raise _Rejected(reason, f"{why}; too many sightings wait for pose nodes")
        track.pending_sightings.append((msg, self._handle_now_s))
        self.stats.sightings_held += 1

    def _sighting_ready(
        self, track: _Track, msg: Detection | FiducialObservation, held_s: float
    ) -> bool:
        if msg.node_index >= track.next_index:
            return False
        if isinstance(msg, FiducialObservation):
            other = self._tracks.get(msg.observed_robot_id)
            if other is None or not other.graph_keys:
                return False
            if msg.node_index in track.keys and other.times[-1] < self._seen_s(track, msg):
                return self._handle_now_s - held_s >= self.config.fiducial_wait_s
        return True

    def _seen_s(self, track: _Track, msg: FiducialObservation) -> float:
        """A fiducial's time on the observer's substitute clock (its node's, if the stamp is
        implausibly far from the node's own)."""
        raw_node_s, node_s = track.raw_times[msg.node_index]
        offset_s = float(msg.time_s) - raw_node_s
        return node_s + offset_s if abs(offset_s) <= self.config.max_node_interval_s else node_s

    def _drain_sightings(self) -> None:
        """Sightings held until now whose pose nodes have arrived (every robot's: a fiducial
        waits for its teammate too); one whose own node was passed for good is refused."""
        for robot_id, track in list(self._tracks.items()):
            if not track.pending_sightings:
                continue
            ready = [self._sighting_ready(track, m, t) for m, t in track.pending_sightings]
            if not any(ready):
                continue
            due = [m for (m, _), r in zip(track.pending_sightings, ready, strict=True) if r]
            track.pending_sightings = [
                item for item, r in zip(track.pending_sightings, ready, strict=True) if not r
            ]
            self._waited = True  # a fiducial that waited its time takes the latest teammate node
            try:
                for msg in due:  # arrival order: a refined detection follows its first report
                    self.handle(robot_id, msg, now_s=self._handle_now_s)
            finally:
                self._waited = False

    def _on_detection(self, robot_id: int, track: _Track, msg: Detection) -> None:
        what = f"detection {msg.detection_id}"
        p = _finite(msg.position_in_base, f"{what} position_in_base")
        xx, xy, yy = msg.position_covariance
        self._check_covariance(
            np.array([[xx, xy], [xy, yy]], dtype=float), f"{what} position_covariance"
        )
        key = track.keys.get(msg.node_index)
        if key is None:
            why = f"{what}: pose node {msg.node_index} not received"
            self._hold_sighting(track, msg, "orphan_detection", why)
            return
        self.stats.detections += 1
        radius = HAZARD_KINDS.get(msg.kind)
        if radius is None:
            return
        xy = transform_points(self.graph.pose(key), p[None, :])[0]
        if msg.kind in MOVING_KINDS:
            self._on_moving_sighting(robot_id, msg, xy, radius)
            return
        for i, h in enumerate(self.hazards):
            if h.kind == msg.kind and math.dist(h.position_in_map, xy) < self.config.hazard_merge_m:
                # the same object seen again: its position is the mean of the sightings
                n = self._sightings[i] = self._sightings[i] + 1
                mean = np.asarray(h.position_in_map) + (xy - np.asarray(h.position_in_map)) / n
                self.hazards[i] = Hazard(
                    h.hazard_id, h.kind, (float(mean[0]), float(mean[1])), h.radius_m
                )
                anchors = self._anchors[i]
                anchors.append((key, p.copy()))
                del anchors[: max(0, len(anchors) - MAX_HAZARD_ANCHORS)]
                return
        self.hazards.append(
            Hazard(len(self.hazards) + 1, msg.kind, (float(xy[0]), float(xy[1])), radius)
        )
        self._sightings.append(1)
        self._anchors.append([(key, p.copy())])

    def _on_moving_sighting(
        self, robot_id: int, msg: Detection, xy: np.ndarray, radius: float
    ) -> None:
        """A hostile or mobile OOI seen: the known one of that kind nearest to ``xy`` (within
        ``hostile_merge_m``) moves there, else a new hazard; the robot's sighting time is kept
        (the allocator's 30 s lock needs who saw what when)."""
        seen_s = float(msg.time_s) if math.isfinite(msg.time_s) else self._handle_now_s
        best, best_d = None, self.config.hostile_merge_m
        for i, h in enumerate(self.hazards):
            d = math.dist(h.position_in_map, xy)
            if h.kind == msg.kind and d < best_d:
                best, best_d = i, d
        if best is None:
            hazard = Hazard(len(self.hazards) + 1, msg.kind, (float(xy[0]), float(xy[1])), radius)
            self.hazards.append(hazard)
            self._sightings.append(1)
            self._anchors.append([])  # a walker's position is its latest sighting's
        else:
            h = self.hazards[best]
            self._sightings[best] += 1
            hazard = Hazard(h.hazard_id, h.kind, (float(xy[0]), float(xy[1])), h.radius_m)
            self.hazards[best] = hazard
        seen = self._hostile_seen.setdefault(hazard.hazard_id, {})
        seen[robot_id] = max(seen.get(robot_id, -math.inf), seen_s)

    # ---- what the task allocator reads ------------------------------------------------------

    @property
    def robot_ids(self) -> list[int]:
        """Every robot the station has heard from (sorted)."""
        return sorted(self._tracks)

    def last_status(self, robot_id: int) -> TaskStatus | None:
        """The robot's latest :class:`TaskStatus` (None before any)."""
        track = self._tracks.get(robot_id)
        return None if track is None else track.last_status

    def last_heard_s(self, robot_id: int) -> float | None:
        """Station mission time of the robot's latest message (any, accepted or refused: the
        radio reached it); None if never heard."""
        track = self._tracks.get(robot_id)
        return None if track is None else track.last_heard_s

    def telemetry(self, robot_id: int) -> Telemetry | None:
        """The robot's latest :class:`Telemetry` (None before any)."""
        track = self._tracks.get(robot_id)
        return None if track is None else track.telemetry

    def hostile_sightings(self) -> dict[int, dict[int, float]]:
        """``hazard_id -> robot_id -> mission time`` of each robot's latest sighting of each
        moving hazard (hostile, mobile OOI); its position is the latest sighting's (a copy)."""
        return {h: dict(by_robot) for h, by_robot in self._hostile_seen.items()}

    def robot_of_key(self, key: int) -> int:
        """The robot a graph key belongs to."""
        return robot_of(key)

    def linked(self, robot_id: int) -> bool:
        """Whether the robot's trajectory is linked to ``map`` (so it has a ``map_from_odom``)."""
        if robot_id not in self.graph.robots:
            return False
        comp = self.graph.components()
        return comp[self.graph.last_key(robot_id)] in self.graph.anchored_components()

    def pose_in_map(self, robot_id: int) -> tuple[float, float, float] | None:
        """The robot's latest pose ``map_from_base``: its latest telemetry pose (newer than its
        latest pose node) carried into ``map`` by its ``map_from_odom``; None unless linked."""
        if not self.linked(robot_id):
            return None
        map_from_odom = self.graph.map_from_odom(robot_id)
        track = self._tracks[robot_id]
        if track.telemetry is not None and np.all(np.isfinite(track.telemetry.pose_in_odom)):
            p = np.asarray(
                compose(map_from_odom, np.asarray(track.telemetry.pose_in_odom, dtype=float))
            )
        else:
            p = np.asarray(self.graph.pose(self.graph.last_key(robot_id)))
        return (float(p[0]), float(p[1]), float(p[2]))

    def trajectories(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(robot_ids (N,), keys (N,), xy_in_map (N, 2))`` of every pose of every robot
        linked to ``map``, at the current posterior, keys increasing along each trajectory
        (the trajectory graph's input, paper 5.1.1 Fig. 12)."""
        ids, keys, xys = [], [], []
        for r in self.graph.robots:
            if not self.linked(r):
                continue
            k, p = self.graph.poses(r)
            ids.append(np.full(len(k), r, dtype=np.int64))
            keys.append(k)
            xys.append(p[:, :2])
        if not ids:
            return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2))
        return np.concatenate(ids), np.concatenate(keys), np.concatenate(xys)

    # ---- output ----------------------------------------------------------------------------

    def key_of(self, robot_id: int, node_index: int) -> int | None:
        """Graph key of a robot's pose node, None if it has not been added."""
        track = self._tracks.get(robot_id)
        return None if track is None else track.keys.get(node_index)

    def step(self, *, now_s: float, budget_s: float | None = None) -> list[tuple[int, Any]]:
        """Close loops within ``budget_s`` wall seconds (default ``loop_budget_s``), optimize
        what changed (iSAM2) and return the ``(robot_id, message)`` downlink messages.

        Never raises: a solver failure is recovered (or the last good estimate kept and the
        solve retried next time), a loop-closer or internal failure is logged and counted, and
        the frames go out at the last good estimate either way."""
        try:
            now = self._station_now(now_s)
            if math.isfinite(now_s) and now_s > self._handle_now_s:
                self._handle_now_s = float(now_s)
            self._drain_sightings()  # fiducials whose wait for a teammate's node is over
            self._check_odometry()
            budget = self.config.loop_budget_s if budget_s is None else budget_s
            self._close_loops(now, budget)
            self._keep_odometry_replacements()
            if self._dirty:
                self._optimize()
            if not self._dirty and not self.loop_closer.pending_hypotheses:
                self._simplified(self.graph.simplify_if_due(now))
            return self._downlink(now)
        except Exception:
            self.stats.internal_errors += 1
            log.exception("internal error in GroundStation.step (the station goes on)")
            return []

    def _station_now(self, now_s: float) -> float:
        cfg = self.config
        previous_s = self._clock.last_raw_s
        now, kind = self._clock.check(float(now_s), cfg.max_node_interval_s, 0.0)
        if kind is not None:
            self._clock_anomaly("gcs station", self._clock, kind, now_s, previous_s, now)
        return now

    def _check_odometry(self) -> None:
        """Scan-checked odometry (module docstring): the odometry edges whose two grids came
        since the last step are matched; a confident match that contradicts the edge replaces
        it (measurement and covariance), so a slipping wheel does not bend the map."""
        due, self._odometry_due = self._odometry_due, []
        cfg = self.config.odometry_check
        floors = self.config.loops
        floor = np.diag(
            [floors.edge_floor_sigma_xy_m**2] * 2 + [floors.edge_floor_sigma_yaw_rad**2]
        )
        updates: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        for ka, kb in due:
            reported = self._odometry_in.pop(kb, None)
            if reported is None:
                continue  # checked already (or the robot's first node)
            z_odo, cov_odo = reported
            self.stats.odometry_checks += 1
            try:
                m = self.loop_closer.suggest(ka, kb, z_odo, wide=False)
            except ValueError:
                continue  # a grid too small to be a scan
            cov_xy = m.covariance[:2, :2]
            if m.normalized_score < cfg.min_score or not (
                float(np.linalg.eigvalsh(cov_xy)[-1]) <= cfg.max_sigma_xy_m**2
            ):
                continue
            # slip corrupts what the wheels measure, the translation; the heading is the
            # gyro's (a match's heading in sparse sand was 4 deg off where the gyro's was 0.1)
            if cfg.keep_heading:
                z_new = np.array([m.a_from_b[0], m.a_from_b[1], z_odo[2]], dtype=float)
                cov_m = vector_to_body_covariance(z_new, m.covariance)
                cov_new = np.zeros((3, 3))
                cov_new[:2, :2] = 0.5 * (cov_m[:2, :2] + cov_m[:2, :2].T) + floor[:2, :2]
                cov_new[2, 2] = cov_odo[2, 2]
            else:
                z_new = np.asarray(m.a_from_b, dtype=float).copy()
                cov_m = vector_to_body_covariance(z_new, m.covariance)
                cov_new = 0.5 * (cov_m + cov_m.T) + floor
            bad, _ = odometry_contradicted(
                z_odo,
                cov_odo,
                z_new,
                cov_new,
                chi2=cfg.chi2,
                min_diff_m=cfg.min_diff_m,
                min_diff_rad=cfg.min_diff_rad,
            )
            step_m = math.hypot(z_odo[0], z_odo[1])
            slip_m = math.hypot(z_new[0] - z_odo[0], z_new[1] - z_odo[1])
            if bad and slip_m > cfg.max_slip_frac * step_m + cfg.slip_floor_m:
                self.stats.odometry_implausible += 1
                continue
            eid = self._odometry_edge_id(kb) if bad else None
            if eid is not None and eid not in self._odometry_replaced:
                updates[eid] = (z_new, cov_new)
        if updates:
            self.graph.update_edges(updates)
            self._odometry_replaced.update(updates)
            self.stats.odometry_replaced += len(updates)
            self._dirty = True

    def _odometry_edge_id(self, key_b: int) -> int | None:
        eid = self._odometry_edge.get(key_b)
        if eid is None:
            for e in self.graph.edges(Provenance.ODOMETRY):
                if e.key_b is not None:
                    self._odometry_edge[e.key_b] = e.edge_id
            eid = self._odometry_edge.get(key_b)
        return eid

    def _keep_odometry_replacements(self) -> None:
        """An odometry recalibration (the loop closer's turn scale) re-expresses every
        odometry edge from what the robot reported: the scan-checked ones are put back."""
        n = self.loop_closer.stats.odometry_recalibrations
        if n != self._recalibrations_seen:
            self._recalibrations_seen = n
            if self._odometry_replaced:
                self.graph.update_edges(dict(self._odometry_replaced))
                self._dirty = True

    def _close_loops(self, now_s: float, budget_s: float) -> None:
        try:
            report = self.loop_closer.step(now_s=now_s, budget_s=budget_s)
        except Exception as err:
            self.stats.loop_closer_faults += 1
            self.stats.errors.append(f"loop closer failed: {type(err).__name__}: {err}")
            log.exception("loop closer failed at t=%.3f s (the station goes on)", now_s)
            return
        self.last_loop_report = report
        # closures removed or re-weighted after a new turn-scale fit change the optimum as
        # much as new ones do: re-optimize now, not at the next accepted closure
        if report.accepted_edge_ids or report.pruned_edge_ids or report.recalibrated_robots:
            self._dirty = True

    def _optimize(self) -> None:
        """iSAM2 with the graph's recovery; an unrecovered fault keeps ``_dirty`` (retry)."""
        fault = self.graph.optimize_incremental()
        self.stats.optimizations += 1
        if fault is None:
            self._dirty = False
            self._reexpress_hazards()
            return
        self.stats.solver_faults += 1
        line = f"solver fault: {fault.error}; {fault.action}"
        self.stats.errors.append(line)
        if fault.recovered:
            self.stats.solver_recoveries += 1
            self._dirty = False
            self._reexpress_hazards()

    def _reexpress_hazards(self) -> None:
        """Each static hazard where its sightings put it under the current estimate (the mean
        over its anchored sightings): a hazard placed by a robot's pose before a closure moved
        that pose follows it, as the map does, and a later sighting of the same object from
        another robot merges with it instead of making a second hazard. The kind and radius
        are kept (an operator may have relabelled it)."""
        for i, anchors in enumerate(self._anchors):
            points = []
            for key, p in anchors:
                try:
                    points.append(transform_points(self.graph.pose(key), p[None, :])[0])
                except PoseGraphError:  # a node rewound out of the graph
                    continue
            if not points:
                continue
            mean = np.mean(points, axis=0)
            h = self.hazards[i]
            self.hazards[i] = Hazard(
                h.hazard_id, h.kind, (float(mean[0]), float(mean[1])), h.radius_m
            )

    def _downlink(self, now_s: float) -> list[tuple[int, Any]]:
        out: list[tuple[int, Any]] = []
        robots = self.graph.robots
        due = [
            r
            for r in robots
            if now_s - self._last_frames_s.get(r, -math.inf) >= self.config.frames_period_s
        ]
        if due:
            frames = self.frames()
            update = HazardUpdate(now_s, list(self.hazards), frames)
            for r in due:
                out.append((r, update))
                self._last_frames_s[r] = now_s
        return out

    # ---- operator primitives (paper 6.1) ---------------------------------------------------

    def suggest_closure(
        self, key_a: int, key_b: int, b_in_a_guess: np.ndarray | None = None
    ) -> MatchResult:
        """Match pose ``key_b``'s grid against ``key_a``'s around a guess (default: the current
        posterior); returns ``a_from_b`` with its covariance and score. Adds nothing."""
        return self.loop_closer.suggest(key_a, key_b, b_in_a_guess)

    def accept_closure(self, key_a: int, key_b: int, result: MatchResult, *, now_s: float) -> int:
        """Add a suggested closure the operator accepted (``LOOP_OPERATOR``); returns its id."""
        edge_id = self.loop_closer.operator_edge(key_a, key_b, result, time_s=now_s)
        self._dirty = True
        return edge_id

    def rewind_closures(self, since_s: float) -> int:
        """Remove the automatic loop closures added after ``since_s`` (mission time) and drop
        pending hypotheses; returns how many edges went. The next :meth:`step` re-optimizes."""
        removed = self.loop_closer.rewind(since_s)
        self._dirty = True
        return removed

    def simplify_graph(self, *, alpha: float = 5.0) -> list[EdgeRecord]:
        """Algorithm 1 (paper 4.7) now, on the graph at its current estimate (the operator's
        ``simplify``; the station runs it by itself through ``graph.auto_simplify``); returns
        the edges merged away. Solve first: the kept edges are re-expressed at the estimate."""
        removed = self.graph.simplify(alpha=alpha)
        self._simplified(removed)
        return removed

    def _simplified(self, removed: list[EdgeRecord]) -> None:
        """After a simplification: count it and forget what named the edges merged away (the
        odometry edges' ids into nodes, scan-checked replacements, the closer's bookkeeping)."""
        if not removed:
            return
        self.stats.simplifications += 1
        self.stats.edges_simplified_away += len(removed)
        gone = {e.edge_id for e in removed}
        self._odometry_edge = {k: e for k, e in self._odometry_edge.items() if e not in gone}
        for eid in gone & self._odometry_replaced.keys():
            del self._odometry_replaced[eid]
        self.loop_closer.graph_simplified()

    def restart_loop_closer(self) -> None:
        """Forget hypotheses and tried pairs so every pair may be matched again (after the
        operator fixed the prior); accepted edges stay."""
        self.loop_closer.restart()

    def poses_in_map(self) -> tuple[np.ndarray, np.ndarray]:
        """``(keys (N,), map_from_base (N, 3))`` of every pose, robot by robot."""
        parts = [self.graph.poses(r) for r in self.graph.robots]
        if not parts:
            return np.zeros(0, dtype=np.int64), np.zeros((0, 3))
        return np.concatenate([k for k, _ in parts]), np.concatenate([p for _, p in parts])

    def rasterize(self) -> OccupancyMap:
        """The global occupancy map at the current posterior (paper 4.8; cover and cache): the
        near map (``near_raster``) laid over the far one (:mod:`gcs.mapping.overlay`)."""
        poses = self.poses_in_map()
        far = self.rasterizer.rasterize(poses)
        if self.near_rasterizer is None:
            return far
        return overlay(self.near_rasterizer.rasterize(poses), far)

    def frames(self) -> list[RobotFrame]:
        """``map_from_odom`` of every robot whose trajectory is linked to ``map``."""
        anchored = self.graph.anchored_components()
        comp = self.graph.components()
        out = []
        for r in self.graph.robots:
            if comp[self.graph.last_key(r)] in anchored:
                x, y, t = self.graph.map_from_odom(r)
                out.append(RobotFrame(r, (float(x), float(y), float(t))))
        return out
