"""A team maps together: robots revisit shared places, the GCS closes loops (issue 7).

The team is built by :func:`mission.assembly.assemble`, as ``magic run`` builds it: the
simulator, one :class:`~robot.node.RobotNode` per robot and the real GCS
(:class:`~gcs.mission_control.MissionControl` with its planners off, ``enabled: false``:
estimation only) talking over the radio in deterministic lockstep. A script rides beside the
GCS on the ground side and sends the shared waypoints as ``GoToTask`` downlink: every robot
visits the same waypoints in a rotated order, so each place is seen by several robots at
different times: cross-robot loop closures.

Robots start in unknown relative poses. As MAGIC's operators did with robots deployed from a
staging area, the GCS gets each robot's planned start as a hint (the deployment plan plus a
seeded placement error of ``hint_sigma_*``): a loose ``LOOP_OPERATOR`` edge that the scan
matches then correct (:func:`mission.assembly.give_start_hints`).

Sand makes the wheels slip: the simulated robots' wheel odometry then overestimates the
distance by about a third, far outside the odometry covariance, and no loop closer can fix
that (the paper's section 6 says as much of its own robots; operators fixed such errors). The
trial therefore runs on firm ground by default (``firm_ground``: the world's sand pits
removed); it measures loop closing, not slip. For the same reason the world's dangerous objects
are inert by default (``inert_hazards``: the rules' trigger radius shrunk to a millimetre, which
no robot body reaches): scripted routes do not avoid static OOIs or the mobile hostile, and a
blast (10 m) ends the mapping of every robot near it, half the team within the first minutes.
Losses are still counted (``robots_lost``).

Ground truth (this composition root may read it, DESIGN section 2) scores the result: every
accepted automatic closure is compared with the true relative pose of its two nodes (a
*false closure* is off by more than ``false_closure_m`` or ``false_closure_rad``) and the
posterior trajectory with the true one (ATE RMSE after a rigid alignment). A pose node's true
pose is the simulator's at the node's time, interpolated over the steps recorded while it was
on its way over the radio.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import cv2
import msgspec
import numpy as np

from gcs.graph.pose_graph import Provenance
from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.mission_control import MissionControlConfig
from mission.assembly import Assembly, assemble, staging_plan
from mission.lockstep import seed_streams
from protocol.config import config_path
from protocol.messages import GoToTask, PoseNode, TaskState, TaskStatus
from protocol.radio import RadioConfig
from protocol.se2 import inverse, relative, transform_points, wrap_angle
from robot.node import RobotNodeConfig
from sim.simulator import Simulator, SimulatorConfig, load_world_config

__all__ = [
    "TeamMappingConfig",
    "TeamMappingReport",
    "ate_rmse_m",
    "run_team_mapping",
    "shared_waypoints",
]


#: Trigger radius of inert hazards: far inside any object's or robot's body (``inert_hazards``).
_INERT_TRIGGER_M = 1e-3


class TeamMappingConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Which world, how long, the shared waypoints, the hints and the scoring tolerances."""

    world: str = "world/small.yaml"  # relative to configs/ unless absolute
    # an ideal radio (capacity, range and walls never bind, nothing lost): the trial
    # measures loop closing, not the radio (magic run's radio/magic2010.yaml does that)
    radio: RadioConfig = RadioConfig(
        shared_capacity_bps=10e6, range_m=1e4, wall_loss_db=0.0, max_loss=0.0
    )
    firm_ground: bool = True  # drop the world's sand pits (see the module docstring)
    inert_hazards: bool = True  # nothing detonates (see the module docstring)
    duration_s: float = 240.0
    waypoints: int = 4
    dwell_s: float = 4.0  # still at each waypoint: the gyro recalibrates (paper 4.3.1)
    waypoint_clearance_m: float = 1.5
    ooi_clearance_m: float = 7.0
    seed: int = 0  # every random stream of the run derives from it (mission.lockstep)
    hint_sigma_xy_m: float = 0.3
    hint_sigma_yaw_rad: float = 0.05
    false_closure_m: float = 0.5
    false_closure_rad: float = math.radians(5.0)
    gcs_step_period_s: float = 1.0
    simulator: SimulatorConfig = SimulatorConfig()
    robot: RobotNodeConfig = RobotNodeConfig()
    gcs: GroundStationConfig = GroundStationConfig()


@dataclass
class TeamMappingReport:
    """What the run produced, scored against the truth."""

    mission_s: float = 0.0
    wall_s: float = 0.0
    robots: int = 0
    nodes: int = 0
    grids: int = 0
    goals_reached: int = 0
    goals_sent: int = 0
    robots_lost: int = 0
    closures: int = 0
    cross_robot_closures: int = 0
    false_closures: int = 0
    closure_errors_m: list[float] = field(default_factory=list)
    ate_rmse_m: float = math.nan
    ate_rmse_prior_m: float = math.nan  # odometry + hints only, before any loop closure
    # the same nodes with the loop closures taken out and the graph re-solved: what the
    # closures bought, on the nodes ate_rmse_m scores (path noise moves both together)
    ate_rmse_without_closures_m: float = math.nan


def shared_waypoints(
    sim: Simulator, count: int, *, clearance_m: float, ooi_clearance_m: float
) -> np.ndarray:
    """``(count, 2)`` reachable places in the world frame, spread by farthest-point sampling
    from the robots' staging area, clear of structures and objects of interest."""
    truth = sim.truth
    res = truth.resolution_m
    free = truth.reachable.astype(np.uint8)
    clearance = cv2.distanceTransform(free, cv2.DIST_L2, 5) * res
    rows, cols = np.nonzero(clearance >= clearance_m)
    cells = np.stack([(cols + 0.5) * res, (rows + 0.5) * res], axis=1)
    for ooi in truth.oois:
        cells = cells[np.hypot(*(cells - np.asarray(ooi.xy_m)).T) >= ooi_clearance_m]
    if len(cells) == 0:
        raise ValueError("no reachable waypoint cells clear of structures and OOIs")
    chosen = [sim.robot_poses()[:, :2].mean(axis=0)]
    dist = np.hypot(*(cells - chosen[0]).T)
    for _ in range(count):
        pick = cells[int(np.argmax(dist))]
        chosen.append(pick)
        dist = np.minimum(dist, np.hypot(*(cells - pick).T))
    return np.array(chosen[1:])


def ate_rmse_m(estimate: np.ndarray, truth: np.ndarray) -> float:
    """RMSE of positions after the rigid 2D alignment (Umeyama without scale) of ``estimate``
    ``(N, 3)`` onto ``truth`` ``(N, 3)``."""
    a = estimate[:, :2] - estimate[:, :2].mean(axis=0)
    b = truth[:, :2] - truth[:, :2].mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(u @ vt))
    r = (u @ np.diag([1.0, d]) @ vt).T
    err = b - a @ r.T
    return float(np.sqrt(np.mean(np.sum(err**2, axis=1))))


class _Waypoints:
    """The ground-side script beside the GCS: each robot's rotated route of the shared
    waypoints as ``GoToTask`` downlink, the next goal ``dwell_s`` after the last one ended
    (reported over the radio)."""

    def __init__(self, sim: Simulator, config: TeamMappingConfig) -> None:
        self.dwell_s = config.dwell_s
        ids = list(sim.robot_ids)
        starts = sim.robot_poses()  # each robot's odom starts at its start pose
        places = shared_waypoints(
            sim,
            config.waypoints,
            clearance_m=config.waypoint_clearance_m,
            ooi_clearance_m=config.ooi_clearance_m,
        )
        self.goals: dict[int, list[np.ndarray]] = {}
        for k, rid in enumerate(ids):
            order = np.roll(places, -k, axis=0)
            route = np.vstack([order, starts[k][None, :2]])
            self.goals[rid] = list(transform_points(inverse(starts[k]), route))
        self.active: dict[int, int] = {}
        self.resume_at = dict.fromkeys(ids, 0.0)
        self.next_task = 1
        self.goals_sent = 0
        self.goals_reached = 0
        self.now_s = 0.0

    def on_message(self, robot_id: int, msg: Any) -> None:
        if isinstance(msg, TaskStatus) and msg.task_id == self.active.get(robot_id):
            if msg.state in (TaskState.SUCCEEDED, TaskState.FAILED, TaskState.REJECTED):
                del self.active[robot_id]
                self.goals_reached += msg.state is TaskState.SUCCEEDED
                self.resume_at[robot_id] = self.now_s + self.dwell_s

    def turn(self, now_s: float) -> list[tuple[int, Any]]:
        self.now_s = now_s
        out: list[tuple[int, Any]] = []
        for rid, goals in self.goals.items():
            if rid not in self.active and goals and now_s >= self.resume_at[rid]:
                goal = goals.pop(0)
                out.append(
                    (rid, GoToTask(self.next_task, now_s, [(float(goal[0]), float(goal[1]))]))
                )
                self.active[rid] = self.next_task
                self.next_task += 1
                self.goals_sent += 1
        return out


class _TruthTap:
    """Told of every uplink message the GCS took: the true ``world_from_base`` of each
    accepted pose node, by graph key, at the node's time (interpolated between the steps
    recorded by :meth:`record`)."""

    def __init__(self, history_steps: int) -> None:
        self.asm: Assembly | None = None
        self.truth_in_world: dict[int, np.ndarray] = {}  # graph key -> world_from_base
        self._recent: collections.deque[tuple[float, np.ndarray]] = collections.deque(
            maxlen=history_steps
        )

    def record(self, time_s: float, poses: np.ndarray) -> None:
        self._recent.append((time_s, poses.copy()))

    def __call__(self, robot_id: int, msg: Any, accepted: bool) -> None:
        if not (accepted and isinstance(msg, PoseNode)) or self.asm is None:
            return
        assert self.asm.gcs is not None
        key = self.asm.gcs.station.key_of(robot_id, msg.node_index)
        if key is not None:
            k = self.asm.sim.robot_ids.index(robot_id)
            self.truth_in_world[key] = self._truth_at(k, msg.time_s)

    def _truth_at(self, k: int, time_s: float) -> np.ndarray:
        """Robot ``k``'s true pose at ``time_s`` (a node's time is its sweep's end, which
        precedes the step that delivered it to the GCS): interpolated between recorded
        steps, clamped to the oldest recorded."""
        if len(self._recent) < 2:
            return np.asarray(self._recent[-1][1][k], dtype=float).copy()
        times = np.array([t for t, _ in self._recent])
        j = int(np.clip(np.searchsorted(times, time_s), 1, len(times) - 1))
        (t0, p0), (t1, p1) = self._recent[j - 1], self._recent[j]
        w = float(np.clip((time_s - t0) / max(t1 - t0, 1e-9), 0.0, 1.0))
        a, b = p0[k], p1[k]
        return np.array([*(a[:2] + w * (b[:2] - a[:2])), a[2] + w * wrap_angle(b[2] - a[2])])


def _score(
    report: TeamMappingReport,
    station: GroundStation,
    truth: _TruthTap,
    odom0_in_world: np.ndarray,
    config: TeamMappingConfig,
) -> None:
    """Closures and ATE of ``station``'s graph against the truth (module docstring)."""
    in_graph = {n.key for n in station.graph.nodes()}
    keys = [k for k in truth.truth_in_world if k in in_graph]
    true_in_map = np.array([relative(odom0_in_world, truth.truth_in_world[k]) for k in keys])
    est = np.array([station.graph.pose(k) for k in keys])
    report.nodes = len(keys)
    report.grids = station.stats.terrain_grids
    report.ate_rmse_m = ate_rmse_m(est, true_in_map) if len(keys) >= 3 else math.nan
    closures = station.graph.edges(Provenance.LOOP_AUTO)
    if closures and len(keys) >= 3:
        bare = station.graph.copy()
        bare.remove_edges([e.edge_id for e in closures])
        bare.optimize()
        bare_est = np.array([bare.pose(k) for k in keys])
        report.ate_rmse_without_closures_m = ate_rmse_m(bare_est, true_in_map)
    report.closures = report.cross_robot_closures = report.false_closures = 0
    report.closure_errors_m = []
    for e in station.graph.edges(Provenance.LOOP_AUTO):
        assert e.key_b is not None
        if e.key_a not in truth.truth_in_world or e.key_b not in truth.truth_in_world:
            continue
        true_rel = relative(truth.truth_in_world[e.key_a], truth.truth_in_world[e.key_b])
        err_m = float(np.hypot(*(e.z[:2] - true_rel[:2])))
        err_rad = abs(float(wrap_angle(e.z[2] - true_rel[2])))
        report.closures += 1
        report.cross_robot_closures += (e.key_a >> 32) != (e.key_b >> 32)
        report.closure_errors_m.append(err_m)
        if err_m > config.false_closure_m or err_rad > config.false_closure_rad:
            report.false_closures += 1


def run_team_mapping(
    config: TeamMappingConfig | None = None,
    *,
    progress: Callable[[str], None] | None = None,
    progress_period_s: float = 5.0,
) -> tuple[TeamMappingReport, GroundStation]:
    """Run the team for ``config.duration_s`` mission-seconds; returns the scored report and
    the station (its graph, grids and maps) for further inspection. Deterministic: the same
    config gives the same run (:mod:`mission.lockstep`)."""
    config = config or TeamMappingConfig()
    world = load_world_config(config_path(config.world, "world"))
    if config.firm_ground:
        world = msgspec.structs.replace(world, sand=msgspec.structs.replace(world.sand, count=0))
    sim_cfg = config.simulator
    if config.inert_hazards:
        sim_cfg = msgspec.structs.replace(
            sim_cfg, rules=msgspec.structs.replace(sim_cfg.rules, trigger_radius_m=_INERT_TRIGGER_M)
        )
    report = TeamMappingReport()
    # the truth of a node is looked up when it reaches the GCS: keep the last 30 s of steps
    truth = _TruthTap(history_steps=max(2, int(30.0 / sim_cfg.step_s)))
    script: list[_Waypoints] = []

    def scripts(sim: Simulator) -> list[Any]:
        script.append(_Waypoints(sim, config))
        return list(script)

    t0 = time.perf_counter()
    with assemble(
        world,
        seeds=seed_streams(config.seed, simulator_seed=sim_cfg.seed),
        radio=config.radio,
        simulator=sim_cfg,
        robot=config.robot,
        gcs=config.gcs,
        mission=MissionControlConfig(enabled=False),  # estimation only: the script drives
        scripts=scripts,
        taps=[truth],
        gcs_step_period_s=config.gcs_step_period_s,
        hint_sigma_xy_m=config.hint_sigma_xy_m,
        hint_sigma_yaw_rad=config.hint_sigma_yaw_rad,
    ) as asm:
        assert asm.gcs is not None
        truth.asm = asm
        sim, station = asm.sim, asm.gcs.station
        odom0 = staging_plan(sim.world)[sim.robot_ids[0]]  # map = robot 0's private frame
        truth.record(sim.time_s, sim.robot_poses())
        last_check_s = -math.inf
        last_progress = time.perf_counter()
        n_steps = int(round(config.duration_s / sim.config.step_s))
        prior_scored = False
        for _ in range(n_steps):
            asm.step()
            truth.record(sim.time_s, sim.robot_poses())
            if not prior_scored and sim.time_s - last_check_s >= config.gcs_step_period_s:
                last_check_s = sim.time_s
                if station.graph.edges(Provenance.LOOP_AUTO):
                    before = TeamMappingReport()
                    _score(before, station, truth, odom0, config)
                    report.ate_rmse_prior_m = before.ate_rmse_m
                    prior_scored = True
            if progress is not None and time.perf_counter() - last_progress >= progress_period_s:
                s = station.stats
                closures = len(station.graph.edges(Provenance.LOOP_AUTO))
                progress(
                    f"team mapping t={sim.time_s:6.1f}s nodes {s.pose_nodes} grids "
                    f"{s.terrain_grids} closures {closures}"
                )
                last_progress = time.perf_counter()
        # what is still queued, and a last optimization over it (its downlink is not sent)
        asm.gcs.drain(sim.time_s)
        asm.gcs.control.step(now_s=sim.time_s, budget_s=math.inf)
        _score(report, station, truth, odom0, config)
        report.goals_reached = script[0].goals_reached
        report.goals_sent = script[0].goals_sent
        report.robots = len(sim.robot_ids)
        report.robots_lost = sum(1 for e in sim.events if e.kind == "robot_lost")
        report.mission_s = sim.time_s
    report.wall_s = time.perf_counter() - t0
    return report, station
