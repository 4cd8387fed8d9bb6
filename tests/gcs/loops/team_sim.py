"""A small 2D multi-robot run for loop-closing tests: a city of blocks, scripted routes that
revisit streets, noisy odometry, ray-cast vertical-surface scans, and the truth to score it.

Robots drive waypoint routes along the streets; a pose node is made every ``node_spacing_m``
(and at every corner). Odometry composes the true relative motion with Gaussian noise
(proportional to the distance, plus a per-robot yaw bias: drift that loop closing must fix).
Scans are the cell centres of the 150 x 150 grid of a 360 deg ray cast, in the node's base.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from gcs.graph import se2
from gcs.graph.keys import pose_key
from gcs.graph.pose_graph import PoseGraph, PoseGraphConfig, Provenance
from gcs.loops.correlative_matcher import grid_points
from gcs.loops.loop_closer import LoopCloser, LoopCloserConfig
from gcs.loops.synthetic_scenes import box_segments, scan_grid, scan_points

BLOCK_PITCH_M = 14.0  # block 8..10 m + street


def city_world(rng: np.random.Generator, *, blocks: int = 3) -> np.ndarray:
    """``blocks x blocks`` buildings of varied size (with a doorway each) on a 14 m pitch,
    centred on the origin, plus cars and bins along the streets (off the centre lines)."""
    segs = []
    half = (blocks - 1) / 2
    for i in range(blocks):
        for j in range(blocks):
            cx, cy = (i - half) * BLOCK_PITCH_M, (j - half) * BLOCK_PITCH_M
            w, h = rng.uniform(7.0, 10.0, 2)
            segs.append(
                box_segments(
                    cx, cy, w, h, rng.normal(0, 0.03), door_m=1.2, door_side=int(rng.integers(4))
                )
            )
    # streets run along x = (i - half + 0.5) * pitch and y alike; objects 1.8..2.6 m off axis
    lines = [(k - half + 0.5) * BLOCK_PITCH_M for k in range(-1, blocks)]
    extent = (half + 0.5) * BLOCK_PITCH_M
    for _ in range(12 * blocks):
        along = rng.uniform(-extent, extent)
        line = lines[int(rng.integers(len(lines)))]
        off = rng.choice([-1.0, 1.0]) * rng.uniform(1.8, 2.6)
        w, h = rng.uniform(0.4, 1.8), rng.uniform(0.4, 4.0)
        if rng.random() < 0.5:
            segs.append(box_segments(along, line + off, h, w, rng.normal(0, 0.1)))
        else:
            segs.append(box_segments(line + off, along, w, h, rng.normal(0, 0.1)))
    return np.concatenate(segs)


def street(k: float, blocks: int = 3) -> float:
    """Coordinate of street ``k`` (0 .. blocks) of :func:`city_world`."""
    return (k - (blocks - 1) / 2 - 0.5) * BLOCK_PITCH_M


def route_poses(waypoints: list[tuple[float, float]], *, spacing_m: float) -> np.ndarray:
    """True node poses ``(N, 3)`` along straight legs between waypoints, heading along each
    leg, a node every ``spacing_m`` and at every waypoint (turning in place there)."""
    out = []
    for (x0, y0), (x1, y1) in zip(waypoints[:-1], waypoints[1:], strict=True):
        d = math.hypot(x1 - x0, y1 - y0)
        yaw = math.atan2(y1 - y0, x1 - x0)
        n = max(1, int(round(d / spacing_m)))
        for k in range(n):
            t = k / n
            out.append((x0 + t * (x1 - x0), y0 + t * (y1 - y0), yaw))
    x, y = waypoints[-1]
    out.append((x, y, out[-1][2]))
    return np.array(out)


@dataclass
class RobotRun:
    robot_id: int
    truth: np.ndarray  # (N, 3) map_from_base
    odom: np.ndarray  # (N, 3) odom_from_base (noisy)
    step_cov: list[np.ndarray]
    keys: list[int] = field(default_factory=list)


def noisy_odometry(
    truth: np.ndarray,
    rng: np.random.Generator,
    *,
    sigma_frac: float = 0.02,
    sigma_yaw_rad: float = math.radians(0.7),
    yaw_bias_rad_per_m: float = 0.0,
) -> tuple[np.ndarray, list[np.ndarray]]:
    """Odometry starting at the origin: true steps plus noise (and a yaw bias)."""
    odom = [np.zeros(3)]
    covs = []
    for a, b in zip(truth[:-1], truth[1:], strict=True):
        step = se2.between(a, b)
        d = max(float(np.hypot(*step[:2])), 0.05)
        sig = np.array([sigma_frac * d, sigma_frac * d, sigma_yaw_rad * math.sqrt(d) + 0.002])
        noisy = step + rng.normal(0.0, 1.0, 3) * sig + np.array([0.0, 0.0, yaw_bias_rad_per_m * d])
        odom.append(se2.compose(odom[-1], noisy))
        # the bias is unknown to the estimator: its covariance inflates to cover part of it
        cov_sig = sig + np.array([0.0, 0.0, abs(yaw_bias_rad_per_m) * d])
        covs.append(np.diag(cov_sig**2))
    return np.array(odom), covs


def scan_of(world: np.ndarray, pose: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    grid, origin = scan_grid(scan_points(world, pose, rng=rng))
    return grid_points(grid, origin_m=origin, resolution_m=0.1)


@dataclass
class TeamResult:
    graph: PoseGraph
    closer: LoopCloser
    robots: list[RobotRun]
    truth_by_key: dict[int, np.ndarray]

    def closure_errors(
        self, provenance: Provenance = Provenance.LOOP_AUTO
    ) -> list[tuple[float, float]]:
        """``(translation m, |yaw| rad)`` error of every closure of ``provenance`` vs truth."""
        out = []
        for e in self.graph.edges(provenance):
            assert e.key_b is not None
            true = se2.between(self.truth_by_key[e.key_a], self.truth_by_key[e.key_b])
            err = se2.between(true, e.z)
            out.append((float(np.hypot(*err[:2])), abs(float(se2.wrap_angle(err[2])))))
        return out

    def cross_robot_closures(self) -> int:
        return sum(
            1
            for e in self.graph.edges(Provenance.LOOP_AUTO)
            if e.key_b is not None and (e.key_a >> 32) != (e.key_b >> 32)
        )

    def ate_rmse_m(self) -> float:
        """RMSE of positions after the best rigid alignment of the estimate to the truth."""
        keys = sorted(self.truth_by_key)
        est = np.array([self.graph.pose(k)[:2] for k in keys])
        tru = np.array([self.truth_by_key[k][:2] for k in keys])
        return rigid_ate_rmse_m(est, tru)


def rigid_ate_rmse_m(est: np.ndarray, tru: np.ndarray) -> float:
    """RMSE of positions ``(N, 2)`` after the least-squares rotation and translation."""
    me, mt = est.mean(axis=0), tru.mean(axis=0)
    h = (est - me).T @ (tru - mt)
    u, _, vt = np.linalg.svd(h)
    r = vt.T @ u.T
    if np.linalg.det(r) < 0:
        vt[-1] *= -1
        r = vt.T @ u.T
    aligned = (est - me) @ r.T + mt
    return float(np.sqrt(np.mean(np.sum((aligned - tru) ** 2, axis=1))))


def run_team(
    world: np.ndarray,
    routes: list[np.ndarray],
    *,
    rng: np.random.Generator,
    config: LoopCloserConfig | None = None,
    hints: dict[int, tuple[float, float]] | None = None,
    yaw_bias_rad_per_m: float = 0.002,
    step_every: int = 1,
    budget_s: float = 1.0,
    optimize: bool = True,
) -> TeamResult:
    """Robots ``0..R-1`` drive ``routes`` (true poses) interleaved, one node each per tick.

    ``hints[r] = (sigma_xy_m, sigma_yaw_rad)``: an operator start hint for robot ``r`` (its
    true start relative to robot 0's, perturbed by those sigmas, as a loose
    ``LOOP_OPERATOR`` edge between the first poses). Robots without a hint stay unlinked.
    """
    graph = PoseGraph(PoseGraphConfig(map_robot_id=0))
    closer = LoopCloser(graph, config)
    robots = []
    for r, truth in enumerate(routes):
        bias = yaw_bias_rad_per_m * (1 if r % 2 == 0 else -1)
        odom, covs = noisy_odometry(truth, rng, yaw_bias_rad_per_m=bias)
        robots.append(RobotRun(r, truth, odom, covs))
    truth_by_key: dict[int, np.ndarray] = {}
    hints = hints or {}
    ticks = max(len(rr.truth) for rr in robots)
    now = 0.0
    for t in range(ticks):
        now = float(t)
        for rr in robots:
            if t >= len(rr.truth):
                continue
            key = graph.add_pose(
                rr.robot_id,
                odom_from_base=rr.odom[t],
                time_s=now,
                odometry_covariance=None if t == 0 else rr.step_cov[t - 1],
            )
            rr.keys.append(key)
            truth_by_key[key] = rr.truth[t]
            if t == 0 and rr.robot_id in hints:
                sxy, syaw = hints[rr.robot_id]
                true = se2.between(robots[0].truth[0], rr.truth[0])
                z = true + rng.normal(0, 1, 3) * np.array([sxy, sxy, syaw])
                graph.add_edge(
                    pose_key(0, 0),
                    key,
                    a_from_b=z,
                    covariance=np.diag([sxy**2, sxy**2, syaw**2]),
                    provenance=Provenance.LOOP_OPERATOR,
                    time_s=now,
                )
            closer.add_scan(key, scan_of(world, rr.truth[t], rng))
        if t % step_every == 0:
            report = closer.step(now_s=now, budget_s=budget_s)
            if optimize and (report.accepted_edge_ids or t % 10 == 0):
                graph.optimize_incremental()
    closer.step(now_s=now + 1.0, budget_s=budget_s)
    if optimize:
        graph.optimize()
    return TeamResult(graph, closer, robots, truth_by_key)
