"""``magic bench robot``: on-robot autonomy (issue 4; paper 5.3, 5.4).

One small function per metric group; :func:`run` merges them. Times are medians of repeats,
wall clock, after warm-up (numba kernels are compiled and cached before anything is timed).

Terrain classification (:func:`terrain_speed`, :func:`terrain_quality`):

- ``terrain_ms_400x400``: :func:`robot.terrain.classifier.classify_sweep` of one synthetic
  sweep of about 50k points (the MAGIC sensor's density) into a 400 x 400 grid at 5 cm
  (the paper's 400 m^2 map: about 300 ms in-system). Target <= 30 ms.
- ``terrain_layers_ms_400x400``: the same with the fusion's evidence layers, i.e. also
  tracing every beam through the grid for free space (:mod:`robot.terrain.free_space`), as
  the node does.
- ``terrain_fuse_ms_12``: fusing the last 12 sweeps into a 400 x 400 map.
- ``vertical_grid_ms_400x400``: the 10 cm vertical-surface grid (40 x 40 m) of the same sweep.
- ``terrain_obstacle_recall`` (>= 0.99) and ``terrain_false_obstacle_frac`` (<= 0.01): pooled
  over generated scenes (:mod:`robot.terrain.synthetic_scene`, boxes, walls, curbs, 5-15 deg
  ramps, trees with overhanging canopy), one sweep each, against their known truth
  (:func:`robot.terrain.synthetic_scene.truth_grids`): the fraction of cells with a LIDAR hit
  on the face of an obstacle whose rim rises >= 9 cm (10 cm less range noise) above a ground
  hit within 15 cm that have an obstacle within one cell, and the fraction of drivable-ground
  cells (ground, ramp or under-canopy hits away from faces) marked obstacle.
  ``..._recall_exact``: the same in the exact cell (the up-detector marks the higher cell,
  often the curb top next to the face cell).

Odometry and the node, against the simulator (:func:`odometry`, :func:`node`; trials in
:mod:`mission.evaluation`):

- ``odom_drift_frac`` (<= 0.02): final position error over distance after a scripted
  ~200 m zigzag drive with stops (UMBmark-like) in an open world, default simulator noise,
  median over seeds (``..._worst``: the worst seed); ``odom_heading_drift_deg_per_min``
  (<= 1); ``odom_bias_error_rad_s`` after the first stop. The zigzag goes back and forth, so
  a distance scale error largely cancels: ``odom_drift_frac_one_way`` is the same drive as a
  serpentine that keeps going away (half the distance ends up as displacement), and
  ``odom_distance_scale_error`` the odometry's distance over the true one, minus 1 (the
  calibrated wheel slip, paper 4.3.1).
- ``node_cpu_ms_per_sweep``: the whole node pipeline (odometry, control, terrain
  classification and fusion, pose node, vertical grid and its compression, planning) between
  consecutive sweeps, thread CPU time, median, in the small world.
- ``uplink_bps_per_robot``: what that node put on the air (metered frames plus framing) per
  mission second, with the default codec.

Path planning (:func:`plan_speed`):

- ``plan_ms_400x400``: :meth:`robot.planning.planner.PathPlanner.plan` (configuration space,
  Dijkstra with the exact octile A* ordering, relaxation, smoothing) on a fused 400 x 400 map
  of a generated scene, to random goals 6-9 m away that have a path (goals inside obstacles,
  answered in well under a millisecond, are not timed; ``plan_found_frac`` is the fraction
  of random goals with a path). Target <= 20 ms.
- ``plan_ms_400x400_unknown_cost``: the same with ``unknown="cost"`` (unknown cells cost 1.5x):
  the octile heuristic is weaker there, so more cells are expanded.
- ``dijkstra_ms_400x400_full``: plain Dijkstra (no heuristic) over the same maps, to the
  farthest reachable cell, i.e. nearly the whole grid: the worst case without A*.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from functools import partial

import numpy as np

from mission.bench import median_time_s
from robot.planning.config_space import configuration_space
from robot.planning.dijkstra import dijkstra_grid
from robot.planning.planner import PathPlanner, PlannerConfig
from robot.terrain.classifier import TerrainConfig, classify_sweep, classify_sweep_layers
from robot.terrain.grid import OBSTACLE
from robot.terrain.map_fusion import TerrainMapFusion
from robot.terrain.synthetic_scene import (
    cast_sweep,
    issue_scene,
    random_scene,
    score_classification,
    truth_grids,
)
from robot.terrain.vertical_surface_grid import VerticalSurfaceConfig, vertical_surface_grid

__all__ = ["node", "odometry", "plan_speed", "run", "terrain_quality", "terrain_speed"]

#: Nodding-LIDAR pattern giving about 50k points per sweep (paper 3.1).
DENSE = {"beams": 1081, "lines": 80}


def terrain_speed(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    progress("terrain: classification speed")
    cfg = TerrainConfig()
    rng = np.random.default_rng(11)
    hits = cast_sweep(issue_scene(), (0.2, -0.1, 0.3), rng=rng, **DENSE)
    pts, pose, line = hits.points_in_base, hits.odom_from_base, hits.line_index
    classify_ms = 1e3 * median_time_s(
        lambda: classify_sweep(pts, pose, config=cfg), repeats=10 if quick else 40, warmup=2
    )
    layers_ms = 1e3 * median_time_s(
        lambda: classify_sweep_layers(pts, pose, config=cfg),
        repeats=10 if quick else 40,
        warmup=2,
    )
    fusion = TerrainMapFusion(
        memory_sweeps=cfg.memory_sweeps, clear_after_sweeps=cfg.clear_after_sweeps
    )
    geo = None
    for k in range(cfg.memory_sweeps):
        layers = classify_sweep_layers(pts, pose + np.array([0.1 * k, 0.03 * k, 0.0]), config=cfg)
        geo = layers.geometry
        fusion.add(
            layers.classes,
            geo,
            obstacle_height_m=layers.obstacle_height_m,
            free_height_m=layers.free_height_m,
        )
    assert geo is not None
    fuse_ms = 1e3 * median_time_s(lambda: fusion.fused(geo), repeats=10 if quick else 40)
    vcfg = VerticalSurfaceConfig()
    vertical_ms = 1e3 * median_time_s(
        lambda: vertical_surface_grid(pts, config=vcfg, point_time_s=line),
        repeats=10 if quick else 40,
    )
    return {
        "terrain_ms_400x400": classify_ms,
        "terrain_layers_ms_400x400": layers_ms,
        "terrain_fuse_ms_12": fuse_ms,
        "terrain_points_per_sweep": float(len(pts)),
        "vertical_grid_ms_400x400": vertical_ms,
    }


def terrain_quality(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    cfg = TerrainConfig()
    found = found_exact = total = false = drivable_total = 0.0
    scenes = 16 if quick else 60
    for seed in range(scenes):
        progress(f"terrain: quality scene {seed + 1}/{scenes}")
        rng = np.random.default_rng(1000 + seed)
        scene = issue_scene() if seed == 0 else random_scene(rng)
        pose = (
            float(rng.uniform(-0.5, 0.5)),
            float(rng.uniform(-0.5, 0.5)),
            float(rng.uniform(-np.pi, np.pi)),
        )
        hits = cast_sweep(scene, pose, rng=rng)
        classes, geo = classify_sweep(hits.points_in_base, hits.odom_from_base, config=cfg)
        must_obstacle, must_drivable = truth_grids(
            hits,
            geo,
            scene,
            overhead_clearance_m=cfg.overhead_clearance_m,
            margin_cells=cfg.iterations + 1,
        )
        recall, exact, false_frac = score_classification(
            classes == OBSTACLE, must_obstacle, must_drivable
        )
        n_obs, n_drv = float(must_obstacle.sum()), float(must_drivable.sum())
        found += recall * n_obs
        found_exact += exact * n_obs
        total += n_obs
        false += false_frac * n_drv
        drivable_total += n_drv
    return {
        "terrain_obstacle_recall": found / total,
        "terrain_obstacle_recall_exact": found_exact / total,
        "terrain_false_obstacle_frac": false / drivable_total,
        "terrain_truth_obstacle_cells": total,
        "terrain_truth_drivable_cells": drivable_total,
    }


def _fused_map(seed: int, cfg: TerrainConfig):  # type: ignore[no-untyped-def]
    """A 400 x 400 fused map of 12 sweeps along a short drive through a random scene."""
    rng = np.random.default_rng(seed)
    scene = random_scene(rng)
    fusion = TerrainMapFusion(
        memory_sweeps=cfg.memory_sweeps, clear_after_sweeps=cfg.clear_after_sweeps
    )
    for k in range(cfg.memory_sweeps):
        hits = cast_sweep(scene, (0.05 * k, 0.02 * k, 0.3 * k), rng=rng)
        classes, _ = classify_sweep(hits.points_in_base, hits.odom_from_base, config=cfg)
        fusion.add(classes, cfg.geometry_around((0.0, 0.0)))
    geo = cfg.geometry_around((0.0, 0.0))
    return fusion.fused(geo), geo


def plan_speed(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    tcfg = TerrainConfig()
    pcfg = PlannerConfig()
    planner = PathPlanner(pcfg)
    cost_planner = PathPlanner(PlannerConfig(unknown="cost"))
    cost_samples: list[float] = []
    samples: list[float] = []
    full: list[float] = []
    ok = tried = 0
    maps = 3 if quick else 8
    for m in range(maps):
        progress(f"planning: map {m + 1}/{maps}")
        classes, geo = _fused_map(500 + m, tcfg)
        rng = np.random.default_rng(m)
        timed = 0
        while timed < (4 if quick else 10) and tried < 200:
            ang, dist = rng.uniform(-np.pi, np.pi), rng.uniform(6.0, 9.0)
            goal = (dist * np.cos(ang), dist * np.sin(ang))
            result = planner.plan(classes, geo, (0.0, 0.0), goal)
            tried += 1
            if not result.ok:  # a goal inside an obstacle: quick to reject, not timed
                continue
            ok += 1
            timed += 1

            plan_once = partial(planner.plan, classes, geo, (0.0, 0.0), goal)
            samples.append(median_time_s(plan_once, repeats=3 if quick else 7, warmup=0))
            plan_cost = partial(cost_planner.plan, classes, geo, (0.0, 0.0), goal)
            cost_samples.append(median_time_s(plan_cost, repeats=1 if quick else 3, warmup=0))
        blocked = configuration_space(
            classes == OBSTACLE, robot_radius_m=pcfg.robot_radius_m, resolution_m=geo.resolution_m
        )
        cost = np.where(blocked, np.inf, 1.0)
        start = geo.cell_index((0.0, 0.0))
        far = dijkstra_grid(cost, start, None, resolution_m=geo.resolution_m)
        reach = np.where(np.isfinite(far.distance_m), far.distance_m, -1.0)
        r, c = np.unravel_index(np.argmax(reach), reach.shape)
        goal_rc = (int(r), int(c))
        t0 = time.perf_counter()
        for _ in range(3):
            dijkstra_grid(cost, start, goal_rc, resolution_m=geo.resolution_m)
        full.append((time.perf_counter() - t0) / 3)
    return {
        "plan_ms_400x400": 1e3 * statistics.median(samples),
        "plan_ms_400x400_max": 1e3 * max(samples),
        "plan_found_frac": ok / tried,
        "plan_ms_400x400_unknown_cost": 1e3 * statistics.median(cost_samples),
        "dijkstra_ms_400x400_full": 1e3 * statistics.median(full),
    }


def odometry(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    from mission.evaluation import odometry_drive

    seeds = range(5, 8) if quick else range(5, 12)
    progress(f"odometry: scripted 200 m drives in the simulator, {len(seeds)} seeds")
    trials = [odometry_drive(seed=s) for s in seeds]
    progress("odometry: the same drives going one way")
    one_way = [odometry_drive(seed=s, out_and_back=False) for s in seeds]
    return {
        "odom_drift_frac_one_way": statistics.median(t.drift_frac for t in one_way),
        "odom_distance_scale_error": statistics.median(
            abs(t.distance_scale_error) for t in trials + one_way
        ),
        "odom_drift_frac": statistics.median(t.drift_frac for t in trials),
        "odom_drift_frac_worst": max(t.drift_frac for t in trials),
        "odom_heading_drift_deg_per_min": statistics.median(
            t.heading_drift_deg_per_min for t in trials
        ),
        "odom_heading_drift_deg_per_min_worst": max(t.heading_drift_deg_per_min for t in trials),
        "odom_bias_error_rad_s": statistics.median(abs(t.bias_error_rad_s) for t in trials),
        "odom_drive_m": statistics.median(t.distance_m for t in trials),
    }


def node(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    from mission.evaluation import node_pipeline

    progress("robot node in the small world")
    trial = node_pipeline(duration_s=30.0 if quick else 90.0)
    return {
        "node_cpu_ms_per_sweep": statistics.median(trial.cpu_ms_per_sweep),
        "uplink_bps_per_robot": trial.uplink_bps,
    }


def _warm_up() -> None:
    """Compile (or load from cache) every numba kernel once, untimed."""
    cfg = TerrainConfig(size_cells=40)
    pts = np.array([[1.0, 0.0, 0.0], [1.0, 0.2, 0.3]], dtype=np.float32)
    classes, geo = classify_sweep(pts, np.zeros(3), config=cfg)
    classify_sweep_layers(pts, np.zeros(3), config=cfg)
    PathPlanner().plan(classes, geo, (0.0, 0.0), (0.5, 0.5))
    dijkstra_grid(np.ones((3, 3)), (0, 0), (2, 2), astar=True)
    dijkstra_grid(np.ones((3, 3)), (0, 0), (2, 2), astar=False)


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    progress("warm-up: compiling kernels")
    _warm_up()
    metrics: dict[str, float] = {}
    for group in (terrain_speed, terrain_quality, plan_speed, odometry, node):
        metrics.update(group(quick=quick, progress=progress))
    return metrics
