"""Record labelled LIDAR sweeps in simulated worlds, learn the shape thresholds, evaluate them.

Paper 5.2.1: the thresholds on the shape features were "learned from a training dataset".
Here the dataset comes from seeded simulated worlds (:mod:`sim.world_generator`):

* ``record``: for each world seed, sensor robots are placed standing still at random poses
  1.5-8 m from every object of interest and person, and at random drivable places (trees,
  cars, fences, walls and other robots are the distractors); the simulator runs until each
  robot delivered ``sweeps_per_pose`` sweeps. Each sweep is stored in the world frame (the
  robots stand still, so ``odom`` = world) with the ground truth needed for LABELS only:
  objects' and people's positions, and which objects were in line of sight within 8 m.
* ``train``: segments every stored sweep of the training worlds with the robot's own code
  (:class:`robot.perception.lidar_detector.LidarDetector`), labels each segment from the
  truth (``cylinder``: a static OOI or toxic vat; ``person``; else a distractor) and learns
  each class's box (:func:`robot.perception.shape_classifier.learn_box`), written to the
  versioned thresholds file.
* ``evaluate``: runs the detector with a thresholds file on the held-out worlds and prints
  recall, precision, position error and CPU time per sweep.

``main(argv)`` is the CLI (``magic perception record|train|evaluate``)."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robot.perception.lidar_detector import LidarDetector
from robot.perception.shape_classifier import (
    DEFAULT_THRESHOLDS_PATH,
    ShapeThresholds,
    learn_box,
    load_thresholds,
    save_thresholds,
)
from robot.perception.shape_features import FEATURE_NAMES
from robot.terrain.classifier import points_in_odom

__all__ = ["evaluate", "label_segments", "main", "record", "train"]

LIDAR_IN_BASE_M = (0.2, 0.0, 0.52)
VISIBLE_RANGE_M = 8.0
MATCH_M = 0.5


def _sensor_xy(pose: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    x, y = LIDAR_IN_BASE_M[0], LIDAR_IN_BASE_M[1]
    return np.array([pose[0] + c * x - s * y, pose[1] + s * x + c * y])


def _poses_for(world: Any, truth: Any, rng: np.random.Generator, per_object: int) -> list[Any]:
    """Robot poses 1.5-8 m from each OOI/person and at random drivable places."""
    targets = [np.asarray(o.xy_m) for o in world.oois]
    targets += [np.asarray(h.route_m[0]) for h in world.humans]
    w, h = world.size_m
    poses: list[tuple[float, float, float]] = []

    def free(x: float, y: float) -> bool:
        if not (1.0 < x < w - 1.0 and 1.0 < y < h - 1.0):
            return False
        i, j = truth.cells(np.array([x, y]))
        r = int(math.ceil(0.6 / truth.resolution_m))
        win = truth.drivable[max(i - r, 0) : i + r + 1, max(j - r, 0) : j + r + 1]
        if not bool(win.all()):
            return False
        return all(math.hypot(x - p[0], y - p[1]) > 1.2 for p in poses)

    for t in targets:
        got = 0
        for _ in range(200):
            if got >= per_object:
                break
            d = rng.uniform(1.5, VISIBLE_RANGE_M)
            a = rng.uniform(-math.pi, math.pi)
            x, y = t[0] + d * math.cos(a), t[1] + d * math.sin(a)
            if free(x, y):
                yaw = math.atan2(t[1] - y, t[0] - x) + rng.uniform(-1.0, 1.0)
                poses.append((x, y, yaw))
                got += 1
    for _ in range(400):
        if len(poses) >= per_object * (len(targets) + 4):
            break
        x, y = rng.uniform(1, w - 1), rng.uniform(1, h - 1)
        if free(x, y):
            poses.append((x, y, rng.uniform(-math.pi, math.pi)))
    return poses


def record(
    seeds: list[int], out_dir: Path, *, per_object: int = 3, sweeps_per_pose: int = 2
) -> Path:
    """Record sweeps of worlds ``seeds`` into ``out_dir/world_<seed>.npz``; returns out_dir."""
    from protocol.sensors import LidarSweep
    from sim.ground_truth import rasterize
    from sim.simulator import Simulator
    from sim.world_generator import RobotStart, WorldConfig, generate_world

    out_dir.mkdir(parents=True, exist_ok=True)
    for seed in seeds:
        rng = np.random.default_rng(1000 + seed)
        world = generate_world(WorldConfig(seed=seed))
        truth = rasterize(world)
        poses = _poses_for(world, truth, rng, per_object)
        robots = tuple(RobotStart(k, "sensor", p) for k, p in enumerate(poses))
        world = dataclasses.replace(world, robots=robots)
        pts_all: list[NDArray[np.float32]] = []
        meta: list[tuple[int, float, float, float, float]] = []
        ooi_xy = np.array([o.xy_m for o in world.oois]).reshape(-1, 2)
        ooi_info = np.array(
            [[o.radius_m, o.height_m, 1 if o.kind == "static_ooi" else 2] for o in world.oois]
        ).reshape(-1, 3)
        human_xy: list[NDArray[np.float64]] = []
        visible: list[NDArray[np.bool_]] = []
        t0 = time.perf_counter()
        with Simulator(world) as sim:
            counts = np.zeros(len(robots), dtype=int)
            drivers = [sim.driver(r.robot_id) for r in robots]
            while counts.min() < sweeps_per_pose and sim.time_s < 3.0 + 1.3 * sweeps_per_pose:
                sim.step()
                for k, d in enumerate(drivers):
                    for fr in d.poll(0.0):
                        if not isinstance(fr, LidarSweep) or counts[k] >= sweeps_per_pose:
                            continue
                        counts[k] += 1
                        pose = sim.robot_poses()[k]
                        pts = points_in_odom(fr.points_in_base, pose)
                        sensor = _sensor_xy(pose)
                        mid = fr.time_s + fr.duration_s / 2
                        hxy = sim.routes.positions(mid) if world.humans else np.zeros((0, 2))
                        # line of sight to each OOI's mid-height (labels only)
                        vis = np.zeros(len(world.oois), dtype=bool)
                        if len(world.oois):
                            src = np.array(
                                [[sensor[0], sensor[1], LIDAR_IN_BASE_M[2]]] * len(ooi_xy)
                            )
                            dst = np.column_stack([ooi_xy, ooi_info[:, 1] * 0.5])
                            _, body = sim.scene.ray_cast(src, dst)
                            for i, b in enumerate(body):
                                kind = sim.scene.body_kind.get(int(b)) if b >= 0 else None
                                near = math.hypot(*(ooi_xy[i] - sensor)) <= VISIBLE_RANGE_M
                                vis[i] = near and kind == ("ooi", world.oois[i].ooi_id)
                        pts_all.append(pts.astype(np.float32))
                        meta.append((k, fr.time_s, sensor[0], sensor[1], pose[2]))
                        human_xy.append(hxy)
                        visible.append(vis)
        n = np.array([len(p) for p in pts_all])
        np.savez_compressed(
            out_dir / f"world_{seed}.npz",
            points=np.concatenate(pts_all) if pts_all else np.zeros((0, 3), np.float32),
            counts=n,
            meta=np.array(meta).reshape(-1, 5),
            ooi_xy=ooi_xy,
            ooi_info=ooi_info,
            human_xy=np.array(human_xy).reshape(len(meta), -1, 2),
            visible=np.array(visible).reshape(len(meta), -1),
        )
        print(
            f"world {seed}: {len(robots)} robots, {len(meta)} sweeps, "
            f"{len(world.oois)} OOIs, {len(world.humans)} people, {time.perf_counter() - t0:.1f} s",
            flush=True,
        )
    return out_dir


def _load(path: Path) -> dict[str, Any]:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


def _sweeps(d: dict[str, Any]) -> list[tuple[NDArray[np.float64], int]]:
    ends = np.cumsum(d["counts"])
    starts = ends - d["counts"]
    return [
        (d["points"][s:e].astype(np.float64), i)
        for i, (s, e) in enumerate(zip(starts, ends, strict=True))
    ]


def label_segments(
    xyzs: list[NDArray[np.float64]], d: dict[str, Any], sweep: int
) -> NDArray[np.int64]:
    """0: distractor, 1: cylinder (OOI or vat), 2: person; from ground truth (labels only)."""
    lab = np.zeros(len(xyzs), dtype=np.int64)
    for k, xyz in enumerate(xyzs):
        c = xyz[:, :2].mean(axis=0)
        if len(d["ooi_xy"]):
            dist = np.hypot(*(d["ooi_xy"] - c).T)
            i = int(np.argmin(dist))
            if dist[i] <= d["ooi_info"][i, 0] + 0.25:
                lab[k] = 1
                continue
        h = d["human_xy"][sweep]
        if len(h) and np.hypot(*(h - c).T).min() <= 0.6:
            lab[k] = 2
    return lab


def _features(
    files: list[Path], det: LidarDetector
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    fs, ls = [], []
    for p in files:
        d = _load(p)
        for pts, i in _sweeps(d):
            xyzs, f, _, _ = det.features(pts, d["meta"][i, 2:4])
            fs.append(f)
            ls.append(label_segments(xyzs, d, i))
    return np.concatenate(fs), np.concatenate(ls)


def _bootstrap() -> ShapeThresholds:
    """Accept-everything thresholds, to extract features before any file exists."""
    from robot.perception.shape_classifier import ClassBox

    big = np.full(len(FEATURE_NAMES), 1e9)
    return ShapeThresholds(FEATURE_NAMES, {"cylinder": ClassBox(-big, big)})


def train(files: list[Path], out: Path) -> dict[str, Any]:
    """Learn the ``cylinder`` and ``person`` boxes from ``files``; write ``out``."""
    det = LidarDetector(thresholds=_bootstrap())
    f, lab = _features(files, det)
    boxes = {}
    scores: dict[str, Any] = {}
    # a little room beyond what the training worlds showed (paper: "manually enlarged")
    margin = np.array([0.05, 0.05, 0.05, 0.05, 0.05, 0.0])
    for name, cls in (("cylinder", 1), ("person", 2)):
        box, sc = learn_box(f[lab == cls], f[lab != cls], min_margin=margin)
        boxes[name] = box
        scores[name] = {
            **sc,
            "positives": int((lab == cls).sum()),
            "negatives": int((lab != cls).sum()),
        }
    prov = {
        "trained_on": [p.name for p in files],
        "train_scores": scores,
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    save_thresholds(out, ShapeThresholds(FEATURE_NAMES, boxes, prov))
    return prov


def evaluate(files: list[Path], thresholds: Path) -> dict[str, float]:
    """Detector on held-out recordings: per-sweep and per-pose recall of visible OOIs within
    8 m, precision against any cylinder object, position error p95, CPU ms per sweep p95."""
    det = LidarDetector(thresholds=thresholds)
    seen = hit = 0
    pose_seen: dict[tuple[str, int, int], bool] = {}
    cands = good = 0
    errs: list[float] = []
    cpu_ms: list[float] = []
    for p in files:
        d = _load(p)
        for pts, i in _sweeps(d):
            det.tracker.tracks.clear()
            det.tracker.time_s = None
            t0 = time.process_time()
            out = det.process(pts, d["meta"][i, 2:4], float(d["meta"][i, 1]))
            cpu_ms.append((time.process_time() - t0) * 1e3)
            cxy = np.array([c.position_in_odom for c in out.cylinders]).reshape(-1, 2)
            for j in np.flatnonzero(d["visible"][i]):
                dist = np.hypot(*(cxy - d["ooi_xy"][j]).T) if len(cxy) else np.array([np.inf])
                ok = bool(dist.min() <= MATCH_M)
                seen += 1
                hit += ok
                key = (p.name, int(d["meta"][i, 0]), int(j))
                pose_seen[key] = pose_seen.get(key, False) or ok
            for c in cxy:
                cands += 1
                dist = np.hypot(*(d["ooi_xy"] - c).T) if len(d["ooi_xy"]) else np.array([np.inf])
                if dist.min() <= MATCH_M:
                    good += 1
                    errs.append(float(dist.min()))
    return {
        "sweeps": float(len(cpu_ms)),
        "visible_ooi_sweeps": float(seen),
        "ooi_recall_per_sweep": hit / max(seen, 1),
        "ooi_recall_per_pose": sum(pose_seen.values()) / max(len(pose_seen), 1),
        "cylinder_candidates": float(cands),
        "shape_precision": good / max(cands, 1),
        "pos_err_p95_m": float(np.percentile(errs, 95)) if errs else math.nan,
        "ms_per_sweep_p50": float(np.median(cpu_ms)) if cpu_ms else math.nan,
        "ms_per_sweep_p95": float(np.percentile(cpu_ms, 95)) if cpu_ms else math.nan,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="magic perception", description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record", help="record labelled sweeps in seeded simulated worlds")
    r.add_argument("--seeds", type=int, nargs="+", required=True)
    r.add_argument("--out", type=Path, required=True, help="directory for world_<seed>.npz")
    r.add_argument("--per-object", type=int, default=3)
    r.add_argument("--sweeps-per-pose", type=int, default=2)
    t = sub.add_parser("train", help="learn the shape thresholds from recorded worlds")
    t.add_argument("files", type=Path, nargs="+")
    t.add_argument("--out", type=Path, default=DEFAULT_THRESHOLDS_PATH)
    e = sub.add_parser("evaluate", help="score a thresholds file on held-out recorded worlds")
    e.add_argument("files", type=Path, nargs="+")
    e.add_argument("--thresholds", type=Path, default=DEFAULT_THRESHOLDS_PATH)
    a = ap.parse_args(argv)
    if a.cmd == "record":
        record(a.seeds, a.out, per_object=a.per_object, sweeps_per_pose=a.sweeps_per_pose)
    elif a.cmd == "train":
        print(json.dumps(train(a.files, a.out), indent=1))
    else:
        load_thresholds(a.thresholds)  # a bad file: a clear error before any work
        print(json.dumps(evaluate(a.files, a.thresholds), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
