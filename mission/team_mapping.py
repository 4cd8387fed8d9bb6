"""A team maps together: robots revisit shared places, the GCS closes loops (issue 7).

The simulator, one :class:`~robot.node.RobotNode` per robot and a
:class:`~gcs.ground_station.GroundStation` run in this process in lockstep; uplink messages go
to the station directly (the radio link is exercised by ``magic run`` and the link tests; here
what matters is what the GCS makes of the data). Every robot visits the same waypoints in a
rotated order, so each place is seen by several robots at different times: cross-robot loop
closures.

Robots start in unknown relative poses. As MAGIC's operators did with robots deployed from a
staging area, the operator gives each robot's start a hint (the true start plus noise, with its
uncertainty): a loose ``LOOP_OPERATOR`` edge that the scan matches then correct.

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
posterior trajectory with the true one (ATE RMSE after a rigid alignment).
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
from protocol.config import config_path
from protocol.messages import GoToTask, PoseNode, TaskState, TaskStatus
from protocol.se2 import compose, inverse, relative, transform_points, wrap_angle
from robot.node import RobotNode, RobotNodeConfig
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
    firm_ground: bool = True  # drop the world's sand pits (see the module docstring)
    inert_hazards: bool = True  # nothing detonates (see the module docstring)
    duration_s: float = 240.0
    waypoints: int = 4
    dwell_s: float = 4.0  # still at each waypoint: the gyro recalibrates (paper 4.3.1)
    waypoint_clearance_m: float = 1.5
    ooi_clearance_m: float = 7.0
    seed: int = 0
    hint_sigma_xy_m: float = 0.3
    hint_sigma_yaw_rad: float = 0.05
    false_closure_m: float = 0.5
    false_closure_rad: float = math.radians(5.0)
    gcs_step_period_s: float = 1.0
    # wall seconds per GCS step for loop closing: generous, so that the match rate (a token
    # bucket in mission time, ``gcs.loops.matches_per_s``) binds and the result does not
    # depend on the machine's load (measured: a step takes 0.01 s median, 1.2 s at most)
    gcs_budget_s: float = 5.0
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


class _Team:
    """The robots, their goal scripts and the station, wired in one process."""

    def __init__(self, sim: Simulator, config: TeamMappingConfig) -> None:
        self.sim = sim
        self.config = config
        ids = tuple(sim.robot_ids)
        gcs_cfg = msgspec.structs.replace(config.gcs, robots=ids)
        gcs_cfg = msgspec.structs.replace(
            gcs_cfg, graph=msgspec.structs.replace(gcs_cfg.graph, map_robot_id=ids[0])
        )
        self.station = GroundStation(gcs_cfg)
        self.truth_in_world: dict[int, np.ndarray] = {}  # graph key -> world_from_base
        self._recent: collections.deque[tuple[float, np.ndarray]] = collections.deque(maxlen=100)
        self._recent.append((sim.time_s, sim.robot_poses().copy()))
        self.nodes = {
            rid: RobotNode(rid, send=self._sender(rid), config=config.robot) for rid in ids
        }
        self.drivers = {rid: sim.driver(rid) for rid in ids}
        starts = sim.robot_poses()
        self.world_from_odom = {rid: starts[k].copy() for k, rid in enumerate(ids)}
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
        rng = np.random.default_rng(config.seed)
        odom0 = self.world_from_odom[ids[0]]
        for rid in ids[1:]:
            true = relative(odom0, self.world_from_odom[rid])  # map_from_odom of rid
            noise = rng.normal(0.0, [config.hint_sigma_xy_m] * 2 + [config.hint_sigma_yaw_rad])
            self.station.add_start_hint(
                rid,
                map_from_odom=compose(true, noise),
                sigma_xy_m=config.hint_sigma_xy_m,
                sigma_yaw_rad=config.hint_sigma_yaw_rad,
            )

    def _sender(self, rid: int) -> Callable[[Any], object]:
        def send(msg: Any) -> object:
            now = self.sim.time_s
            accepted = self.station.handle(rid, msg, now_s=now)
            if isinstance(msg, PoseNode) and accepted:
                key = self.station.key_of(rid, msg.node_index)
                if key is not None:
                    k = self.sim.robot_ids.index(rid)
                    self.truth_in_world[key] = self._truth_at(k, msg.time_s)
            elif isinstance(msg, TaskStatus) and msg.task_id == self.active.get(rid):
                if msg.state in (TaskState.SUCCEEDED, TaskState.FAILED, TaskState.REJECTED):
                    del self.active[rid]
                    self.goals_reached += msg.state is TaskState.SUCCEEDED
                    self.resume_at[rid] = self.sim.time_s + self.config.dwell_s
            return None

        return send

    def _truth_at(self, k: int, time_s: float) -> np.ndarray:
        """Robot ``k``'s true pose at ``time_s`` (a node's time is its sweep's end, which may
        precede the step that delivered the sweep): interpolated between recorded steps."""
        if len(self._recent) < 2:
            return np.asarray(self._recent[-1][1][k], dtype=float).copy()
        times = np.array([t for t, _ in self._recent])
        j = int(np.clip(np.searchsorted(times, time_s), 1, len(times) - 1))
        (t0, p0), (t1, p1) = self._recent[j - 1], self._recent[j]
        w = float(np.clip((time_s - t0) / max(t1 - t0, 1e-9), 0.0, 1.0))
        a, b = p0[k], p1[k]
        return np.array([*(a[:2] + w * (b[:2] - a[:2])), a[2] + w * wrap_angle(b[2] - a[2])])

    def step(self) -> None:
        self.sim.step()
        now = self.sim.time_s
        self._recent.append((now, self.sim.robot_poses().copy()))
        for rid, node in self.nodes.items():
            for command in node.process(self.drivers[rid].poll(0.0)):
                self.drivers[rid].send(command)
            if rid not in self.active and self.goals[rid] and now >= self.resume_at[rid]:
                goal = self.goals[rid].pop(0)
                node.handle_downlink(
                    GoToTask(self.next_task, now, [(float(goal[0]), float(goal[1]))])
                )
                self.active[rid] = self.next_task
                self.next_task += 1
                self.goals_sent += 1

    def gcs_step(self) -> None:
        for rid, msg in self.station.step(now_s=self.sim.time_s, budget_s=self.config.gcs_budget_s):
            self.nodes[rid].handle_downlink(msg)

    def score(self, report: TeamMappingReport) -> None:
        st = self.station
        in_graph = {n.key for n in st.graph.nodes()}
        keys = [k for k in self.truth_in_world if k in in_graph]
        odom0 = self.world_from_odom[self.sim.robot_ids[0]]
        truth = np.array([relative(odom0, self.truth_in_world[k]) for k in keys])
        est = np.array([st.graph.pose(k) for k in keys])
        report.nodes = len(keys)
        report.grids = st.stats.terrain_grids
        report.ate_rmse_m = ate_rmse_m(est, truth) if len(keys) >= 3 else math.nan
        for e in st.graph.edges(Provenance.LOOP_AUTO):
            assert e.key_b is not None
            if e.key_a not in self.truth_in_world or e.key_b not in self.truth_in_world:
                continue
            true_rel = relative(self.truth_in_world[e.key_a], self.truth_in_world[e.key_b])
            err_m = float(np.hypot(*(e.z[:2] - true_rel[:2])))
            err_rad = abs(float(wrap_angle(e.z[2] - true_rel[2])))
            report.closures += 1
            report.cross_robot_closures += (e.key_a >> 32) != (e.key_b >> 32)
            report.closure_errors_m.append(err_m)
            if err_m > self.config.false_closure_m or err_rad > self.config.false_closure_rad:
                report.false_closures += 1
        report.goals_reached = self.goals_reached
        report.goals_sent = self.goals_sent
        report.robots = len(self.nodes)


def run_team_mapping(
    config: TeamMappingConfig | None = None,
    *,
    progress: Callable[[str], None] | None = None,
    progress_period_s: float = 5.0,
) -> tuple[TeamMappingReport, GroundStation]:
    """Run the team for ``config.duration_s`` mission-seconds; returns the scored report and
    the station (its graph, grids and maps) for further inspection."""
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
    t0 = time.perf_counter()
    with Simulator(world, config=sim_cfg) as sim:
        team = _Team(sim, config)
        last_gcs = -math.inf
        last_progress = time.perf_counter()
        n_steps = int(round(config.duration_s / sim.config.step_s))
        prior_scored = False
        for _ in range(n_steps):
            team.step()
            if sim.time_s - last_gcs >= config.gcs_step_period_s:
                team.gcs_step()
                last_gcs = sim.time_s
                if not prior_scored and team.station.graph.edges(Provenance.LOOP_AUTO):
                    before = TeamMappingReport()
                    team.score(before)
                    report.ate_rmse_prior_m = before.ate_rmse_m
                    prior_scored = True
            if progress is not None and time.perf_counter() - last_progress >= progress_period_s:
                s = team.station.stats
                closures = len(team.station.graph.edges(Provenance.LOOP_AUTO))
                progress(
                    f"team mapping t={sim.time_s:6.1f}s nodes {s.pose_nodes} grids "
                    f"{s.terrain_grids} closures {closures}"
                )
                last_progress = time.perf_counter()
        team.gcs_step()
        team.score(report)
        report.robots_lost = sum(1 for e in sim.events if e.kind == "robot_lost")
        report.mission_s = sim.time_s
    report.wall_s = time.perf_counter() - t0
    return report, team.station
