"""``magic bench perception``: the robots' own perception against the simulator (issue 13;
paper 5.2, 5.2.1, 4.3.2).

Worlds (:func:`bench_world`) are drawn from seeds never used in training (the shape and
colour recorders use seeds below 300; these start at :data:`FIRST_SEED`): a sensor robot
drives a straight route, its full :class:`robot.node.RobotNode` (perception wired in, as in a
mission) and the simulator in lockstep, past static OOIs and toxic vats (3.6-6 m either side:
beyond the own keep-out), distractors (tree trunks of OOI radius and thinner, posts, a car,
a fence, a standing civilian), a hostile patrolling parallel to the route, and two teammates
the simulator in lockstep, past static OOIs and toxic vats (3.6-6 m either side:
Ground truth is read only here, to score:

- ``static_ooi_recall``, ``toxic_vat_recall``: objects that came within 8 m of the robot with
  line of sight (LIDAR height to the object's mid-height) and were reported (a Detection of
  their kind within 1 m, placed through the truth pose of the detection's pose node) within
  5 s of first being in range;
- ``detection_precision``: reported objects (each detection id's last report, and each
  hostile report) with a true object of that kind within 1 m; ``class_confusion``: static
  detections whose nearest true thing within 1 m is of another class (OOI, vat, other);
- ``detection_pos_err_p95_m``: every static report's error against its object;
- ``hostile_track_recall``: hostiles that came within 10 m with line of sight and were
  reported as hostile within 1 m; ``hostile_velocity_err_p50_m_s``: their reported velocity
  (rotated to the world by the truth) against the patrol's;
- ``fiducial_pose_err_p95_m`` / ``_deg``: FiducialObservations of teammates within 3 m
  against the truth relative pose (observer at its pose node's time, teammate at the image's);
  ``..._deg_2face``: those whose heading two tags pinned (a single frontal tag's heading is
  loose, and its covariance says so: sigma >= 0.3 rad);
- ``perception_ms_per_sweep_p95`` (LIDAR shape detector and tracking, thread CPU time),
  ``colour_ms_per_candidate_p95`` (one cylinder candidate's colour test, thread CPU time),
  ``person_colour_ms_p95`` (a person's test, up to five placements);
- ``thumbnail_bytes_p50``: the answer to a ThumbnailRequest for every object reported;
  ``uplink_detection_bytes_per_object``: encoded Detection frames per object reported;
- ``images_per_min``: images the node asked the simulator for (its rendering cost);
  ``perception_cpu_frac``: the node's thread CPU time in perception (everything: sweeps,
  images, colour, tags, thumbnails) per second of mission: its share of one core.

Quick: one world, a 24 m route, 10 s at the rendezvous. Full: four worlds, 34 m routes, 14 s.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.messages import (
    Detection,
    DetectionImage,
    FiducialObservation,
    GoToTask,
    ObjectKind,
    PoseNode,
    TaskState,
    TaskStatus,
    ThumbnailRequest,
    encode_frame,
)
from protocol.se2 import compose, relative, wrap_angle
from robot.node import RobotNode
from sim.simulator import Simulator
from sim.world_generator import (
    Human,
    Ooi,
    RobotsConfig,
    RobotStart,
    Solid,
    World,
    WorldConfig,
)

__all__ = ["FIRST_SEED", "bench_world", "run", "run_world"]

FIRST_SEED = 501
OOI_RGBA = (1.0, 0.3, 0.0, 1.0)
VAT_RGBA = (0.95, 0.85, 0.0, 1.0)
CIVILIAN_RGBA = (0.1, 0.2, 0.9, 1.0)
HOSTILE_RGBA = (0.9, 0.05, 0.05, 1.0)
ROUTE_Y_M = 12.0
LIDAR_Z_M = 0.52
OBJECT_RANGE_M = 8.0
HOSTILE_RANGE_M = 10.0
REPORT_WITHIN_S = 5.0
MATCH_M = 1.0
FIDUCIAL_RANGE_M = 3.0


def _cylinder(kind: str, x: float, y: float, r: float, h: float, rgba: Any) -> Solid:
    return Solid(kind, "cylinder", "obstacle", (x, y, h / 2), (r, r, h / 2), 0.0, rgba)


def bench_world(seed: int, *, length_m: float = 34.0) -> World:
    """A straight route along ``y = 12`` from ``x = 3`` to ``x = length_m + 1`` with objects,
    distractors, a hostile and two standing teammates placed from ``seed``."""
    rng = np.random.default_rng(seed)
    size = (length_m + 6.0, 2 * ROUTE_Y_M)
    taken: list[tuple[float, float]] = []

    def spot(lateral: tuple[float, float], x_range: tuple[float, float]) -> tuple[float, float]:
        for _ in range(500):
            x = float(rng.uniform(*x_range))
            y = ROUTE_Y_M + float(rng.choice([-1.0, 1.0]) * rng.uniform(*lateral))
            if all(math.hypot(x - a, y - b) > 2.5 for a, b in taken):
                taken.append((x, y))
                return x, y
        raise RuntimeError(f"bench world {seed}: no room left")

    x_objects = (8.0, length_m - 1.0)
    oois: list[Ooi] = []
    n_each = max(1, int(length_m // 12))
    for k in range(2 * n_each):
        x, y = spot((3.6, 6.0), x_objects)
        if k % 2 == 0:
            oois.append(Ooi(k + 1, "static_ooi", (x, y), float(rng.uniform(0.22, 0.28)),
                            float(rng.uniform(0.7, 0.9)), OOI_RGBA))  # fmt: skip
        else:
            oois.append(Ooi(k + 1, "toxic_vat", (x, y), float(rng.uniform(0.27, 0.33)),
                            float(rng.uniform(0.8, 1.0)), VAT_RGBA))  # fmt: skip
    solids: list[Solid] = []
    bark = (0.4, 0.3, 0.2, 1.0)
    for r in (0.25, float(rng.uniform(0.1, 0.2))):  # one trunk of OOI radius, one thinner
        x, y = spot((3.6, 7.0), x_objects)
        solids.append(_cylinder("trunk", x, y, r, 3.0, bark))
    x, y = spot((3.6, 7.0), x_objects)
    solids.append(_cylinder("post", x, y, 0.06, 1.2, (0.5, 0.5, 0.5, 1.0)))
    x, y = spot((4.5, 7.0), x_objects)
    solids.append(
        Solid("car", "box", "obstacle", (x, y, 0.75), (2.2, 0.9, 0.75), 0.0, (0.2, 0.3, 0.6, 1))
    )
    x, y = spot((5.0, 7.5), x_objects)
    solids.append(
        Solid("fence", "box", "obstacle", (x, y, 0.6), (1.5, 0.03, 0.6), 0.0, (0.6, 0.6, 0.5, 1))
    )
    humans: list[Human] = []
    x, y = spot((3.6, 6.0), x_objects)
    humans.append(Human(1, "civilian", ((x, y),), 0.0, 0.25, 1.7, CIVILIAN_RGBA))
    hx = float(rng.uniform(10.0, max(10.5, length_m - 10.0)))
    side = float(rng.choice([-1.0, 1.0]))
    hy = ROUTE_Y_M + side * 7.5  # beyond the hostile keep-out (5.75 m) of a robot on the route
    humans.append(Human(2, "hostile", ((hx, hy), (hx + 8.0, hy)), 0.5, 0.25, 1.7, HOSTILE_RGBA))
    robots = [RobotStart(0, "sensor", (3.0, ROUTE_Y_M, 0.0))]
    goal_x = length_m + 1.0
    for k, (dx, dy) in enumerate(((1.5, 0.9), (-0.4, -1.7))):  # waiting at the rendezvous
        yaw = float(rng.uniform(-math.pi, math.pi))
        robots.append(RobotStart(k + 1, "sensor", (goal_x + dx, ROUTE_Y_M + dy, yaw)))
    cfg = WorldConfig(size_m=size, seed=seed, robots=RobotsConfig(sensors=3, disruptors=0))
    return World(
        config=cfg,
        size_m=size,
        solids=tuple(solids),
        oois=tuple(oois),
        humans=tuple(humans),
        robots=tuple(robots),
        start_zone_m=(2.4, ROUTE_Y_M - 0.6, 3.6, ROUTE_Y_M + 0.6),
        gcs_antenna_m=(1.0, ROUTE_Y_M, 3.0),
    )


@dataclass
class WorldResult:
    """Per-world samples, pooled by :func:`run`."""

    ooi_in_range: int = 0
    ooi_found: int = 0
    vat_in_range: int = 0
    vat_found: int = 0
    static_ids: int = 0
    static_true: int = 0
    confused: int = 0
    matched: int = 0
    hostile_reports: int = 0
    hostile_true: int = 0
    hostiles_in_range: int = 0
    hostiles_found: int = 0
    pos_err_m: list[float] = field(default_factory=list)
    vel_err_m_s: list[float] = field(default_factory=list)
    fid_err_m: list[float] = field(default_factory=list)
    fid_err_deg: list[float] = field(default_factory=list)
    fid_err_deg_2face: list[float] = field(default_factory=list)  # two tags of it seen
    sweep_ms: list[float] = field(default_factory=list)
    colour_ms: list[float] = field(default_factory=list)
    person_colour_ms: list[float] = field(default_factory=list)
    thumb_bytes: list[int] = field(default_factory=list)
    detection_bytes: int = 0
    objects_reported: int = 0
    images: int = 0
    sim_s: float = 0.0
    robot_lost: bool = False
    perception_cpu_s: float = 0.0
    hostile_ids_found: set[int] = field(default_factory=set)


def _light(sim: Simulator, rng: np.random.Generator) -> None:
    az, el = rng.uniform(0, 2 * math.pi), rng.uniform(0.3, 1.4)
    scene = sim.scene
    scene.light_direction = [math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)]
    scene.light_ambient = float(rng.uniform(0.45, 0.8))
    scene.light_diffuse = float(rng.uniform(0.2, 0.6))


def run_world(
    seed: int,
    *,
    length_m: float,
    max_s: float,
    hold_s: float = 10.0,
    progress: Callable[[str], None] = lambda _: None,
) -> WorldResult:
    """Drive the route of :func:`bench_world` ``seed`` and score what the node sent."""
    world = bench_world(seed, length_m=length_m)
    res = WorldResult()
    sent: list[tuple[float, Any]] = []
    oois = world.oois
    ooi_xy = np.array([o.xy_m for o in oois]).reshape(-1, 2)
    hostiles = [k for k, h in enumerate(world.humans) if h.kind == "hostile"]
    first_in_range = np.full(len(oois), math.inf)
    hostile_seen = np.zeros(len(world.humans), dtype=bool)
    times: list[float] = []
    poses: list[np.ndarray] = []
    with Simulator(world) as sim:
        _light(sim, np.random.default_rng(seed + 7))
        clock = [0.0]
        node = RobotNode(0, send=lambda m: sent.append((clock[0], m)))
        driver = sim.driver(0)
        goal = relative(np.array(world.robots[0].pose_m), np.array([length_m + 1.0, ROUTE_Y_M, 0]))
        node.handle_downlink(GoToTask(1, 0.0, [(float(goal[0]), float(goal[1]))]))
        step = 0
        arrived_s = math.inf
        while sim.time_s < max_s and sim.time_s < arrived_s + hold_s:
            sim.step()
            clock[0] = sim.time_s
            if not bool(sim.alive()[0]):
                res.robot_lost = True
                break
            for command in node.process(driver.poll(0.0)):
                driver.send(command)
            pose = sim.robot_poses()[0].copy()
            times.append(sim.time_s)
            poses.append(pose)
            if step % 5 == 0:
                _visibility(sim, world, pose, ooi_xy, first_in_range, hostiles, hostile_seen)
            step += 1
            if not math.isfinite(arrived_s) and any(
                isinstance(m, TaskStatus) and m.task_id == 1 and m.state is TaskState.SUCCEEDED
                for _, m in sent[-5:]
            ):
                arrived_s = sim.time_s  # the teammates wait here: a pan cycle to see them
        res.sim_s = sim.time_s
        truth_t = np.array(times)
        truth_pose = np.array(poses)
        p = node.perception
        assert p is not None
        res.sweep_ms = list(p.stats.sweep_cpu_ms)
        res.colour_ms = list(p.stats.colour_cpu_ms)
        res.person_colour_ms = list(p.stats.person_colour_cpu_ms)
        res.images = p.stats.images_requested
        res.perception_cpu_s = node.stats.perception_cpu_s
        # thumbnails: the operator asks for each object reported
        ids = sorted({m.detection_id for _, m in sent if isinstance(m, Detection)})
        for k, did in enumerate(ids):
            node.handle_downlink(ThumbnailRequest(k + 1, did, 0))
        node._apply_downlink()  # noqa: SLF001 - the bench plays the downlink's next frame
        routes = sim.routes

        def truth_at(t: float) -> np.ndarray:
            i = int(np.clip(np.searchsorted(truth_t, t), 0, len(truth_t) - 1))
            return np.asarray(truth_pose[i])

        def human_xy(t: float) -> np.ndarray:
            return np.asarray(routes.positions(t))

        _score(world, sent, truth_at, human_xy, first_in_range, hostile_seen, res)
    progress(
        f"world {seed}: {res.sim_s:.0f} s, OOIs {res.ooi_found}/{res.ooi_in_range}, "
        f"vats {res.vat_found}/{res.vat_in_range}, hostiles {res.hostiles_found}/"
        f"{res.hostiles_in_range}, fiducials {len(res.fid_err_m)}, images {res.images}"
    )
    return res


def _visibility(
    sim: Simulator,
    world: World,
    pose: np.ndarray,
    ooi_xy: np.ndarray,
    first_in_range: np.ndarray,
    hostiles: list[int],
    hostile_seen: np.ndarray,
) -> None:
    """Objects within range with line of sight from the LIDAR's height (truth, scoring only)."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    src = np.array([pose[0] + 0.2 * c, pose[1] + 0.2 * s, LIDAR_Z_M])
    scene = sim.scene
    if len(ooi_xy):
        d = np.hypot(*(ooi_xy - src[:2]).T)
        near = np.flatnonzero((d <= OBJECT_RANGE_M) & ~np.isfinite(first_in_range))
        if len(near):
            dst = np.array([[*ooi_xy[i], 0.5 * world.oois[i].height_m] for i in near])
            _, body = scene.ray_cast(np.repeat(src[None], len(near), 0), dst)
            for i, b in zip(near, body, strict=True):
                if b >= 0 and scene.body_kind.get(int(b)) == ("ooi", world.oois[i].ooi_id):
                    first_in_range[i] = sim.time_s
    if hostiles:
        hxy = np.asarray(sim.routes.positions(sim.time_s))
        for k in hostiles:
            if hostile_seen[k] or math.hypot(*(hxy[k] - src[:2])) > HOSTILE_RANGE_M:
                continue
            _, body = scene.ray_cast(src[None], np.array([[*hxy[k], 0.85]]))
            kind = scene.body_kind.get(int(body[0])) if body[0] >= 0 else None
            if kind is not None and kind[0] == "human":
                hostile_seen[k] = True


def _score(
    world: World,
    sent: list[tuple[float, Any]],
    truth_at: Callable[[float], np.ndarray],
    human_xy: Callable[[float], np.ndarray],
    first_in_range: np.ndarray,
    hostile_seen: np.ndarray,
    res: WorldResult,
) -> None:
    nodes = {m.node_index: m for _, m in sent if isinstance(m, PoseNode)}
    kind_of = {"static_ooi": ObjectKind.STATIC_OOI, "toxic_vat": ObjectKind.TOXIC_VAT}
    things: list[tuple[str, np.ndarray]] = [(o.kind, np.array(o.xy_m)) for o in world.oois]
    things += [("other", np.array(s.center_m[:2])) for s in world.solids]
    things += [("other", np.array(r.pose_m[:2])) for r in world.robots[1:]]
    humans0 = human_xy(0.0)

    def in_world(m: Detection) -> np.ndarray:
        node = nodes[m.node_index]
        return compose(truth_at(node.time_s), np.array([*m.position_in_base, 0.0]))[:2]

    static_last: dict[int, tuple[float, Detection]] = {}
    found_at = np.full(len(world.oois), math.inf)
    for t, m in sent:
        if isinstance(m, Detection):
            res.detection_bytes += len(encode_frame(1, m))
        if not isinstance(m, Detection) or m.node_index not in nodes:
            continue
        xy = in_world(m)
        if m.kind in (ObjectKind.STATIC_OOI, ObjectKind.TOXIC_VAT):
            static_last[m.detection_id] = (t, m)
            for i, o in enumerate(world.oois):
                if kind_of[o.kind] == m.kind and math.dist(o.xy_m, xy) <= MATCH_M:
                    res.pos_err_m.append(math.dist(o.xy_m, xy))
                    found_at[i] = min(found_at[i], t)
        elif m.kind == ObjectKind.HOSTILE:
            res.hostile_reports += 1
            hxy = human_xy(m.time_s)
            for k, h in enumerate(world.humans):
                if h.kind != "hostile" or math.dist(hxy[k], xy) > MATCH_M:
                    continue
                res.hostile_true += 1
                if hostile_seen[k]:
                    res.hostile_ids_found.add(k)
                v_true = (human_xy(m.time_s + 0.25)[k] - human_xy(m.time_s - 0.25)[k]) / 0.5
                yaw = truth_at(nodes[m.node_index].time_s)[2]
                c, s = math.cos(yaw), math.sin(yaw)
                vx, vy = m.velocity_in_base
                v = np.array([c * vx - s * vy, s * vx + c * vy])
                res.vel_err_m_s.append(float(np.hypot(*(v - v_true))))
                break
    for i, o in enumerate(world.oois):
        if not math.isfinite(first_in_range[i]):
            continue
        ok = found_at[i] <= first_in_range[i] + REPORT_WITHIN_S
        if o.kind == "static_ooi":
            res.ooi_in_range += 1
            res.ooi_found += int(ok)
        else:
            res.vat_in_range += 1
            res.vat_found += int(ok)
    for _, m in static_last.values():
        xy = in_world(m)
        res.static_ids += 1
        if any(kind_of.get(k) == m.kind and math.dist(p, xy) <= MATCH_M for k, p in things):
            res.static_true += 1
        near = [(float(math.dist(p, xy)), k) for k, p in things if math.dist(p, xy) <= MATCH_M]
        near += [
            (float(math.dist(humans0[j], xy)), "other")
            for j in range(len(world.humans))
            if math.dist(humans0[j], xy) <= MATCH_M
        ]
        if near:
            res.matched += 1
            res.confused += int(kind_of.get(min(near)[1]) != m.kind)
    res.hostiles_in_range = int(hostile_seen.sum())
    res.hostiles_found = len(res.hostile_ids_found)
    res.objects_reported = len(static_last) + len(
        {
            m.detection_id
            for _, m in sent
            if isinstance(m, Detection) and m.kind == ObjectKind.HOSTILE
        }
    )
    res.thumb_bytes = [len(m.data) for _, m in sent if isinstance(m, DetectionImage)]
    for _, m in sent:
        if not isinstance(m, FiducialObservation) or m.node_index not in nodes:
            continue
        observer_at_image = truth_at(m.time_s)
        other = world.robots[m.observed_robot_id].pose_m  # the teammates stand still
        if math.dist(observer_at_image[:2], other[:2]) > FIDUCIAL_RANGE_M:
            continue
        truth_rel = relative(truth_at(nodes[m.node_index].time_s), np.array(other))
        res.fid_err_m.append(
            float(
                math.hypot(
                    m.observed_in_base[0] - truth_rel[0], m.observed_in_base[1] - truth_rel[1]
                )
            )
        )
        yaw_err = abs(math.degrees(float(wrap_angle(m.observed_in_base[2] - truth_rel[2]))))
        res.fid_err_deg.append(yaw_err)
        # two faces pin the heading; one frontal tag leaves it loose (its covariance says so)
        yaw_sigma = math.sqrt(max(m.covariance[5], 0.0))
        if yaw_sigma < 0.25:
            res.fid_err_deg_2face.append(yaw_err)


def _ratio(a: int, b: int) -> float:
    return a / b if b else 1.0


def _pct(values: list[float] | list[int], q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else math.nan


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    """The suite (see the module docstring)."""
    # hold: the robot waits with its teammates; a full pan cycle (13 s) shows every bearing
    n_worlds, length_m, max_s, hold_s = (1, 24.0, 60.0, 10.0) if quick else (4, 34.0, 100.0, 14.0)
    t0 = time.perf_counter()
    results = [
        run_world(FIRST_SEED + k, length_m=length_m, max_s=max_s, hold_s=hold_s, progress=progress)
        for k in range(n_worlds)
    ]

    def tot(name: str) -> int:
        return int(sum(getattr(r, name) for r in results))

    def pool(name: str) -> list[float]:
        return [v for r in results for v in getattr(r, name)]

    reports = tot("static_ids") + tot("hostile_reports")
    sim_s = sum(r.sim_s for r in results)
    metrics = {
        "static_ooi_recall": _ratio(tot("ooi_found"), tot("ooi_in_range")),
        "toxic_vat_recall": _ratio(tot("vat_found"), tot("vat_in_range")),
        "detection_precision": _ratio(tot("static_true") + tot("hostile_true"), reports),
        "class_confusion": tot("confused") / max(1, tot("matched")),
        "detection_pos_err_p95_m": _pct(pool("pos_err_m"), 95),
        "hostile_track_recall": _ratio(tot("hostiles_found"), tot("hostiles_in_range")),
        "hostile_velocity_err_p50_m_s": _pct(pool("vel_err_m_s"), 50),
        "fiducial_pose_err_p95_m": _pct(pool("fid_err_m"), 95),
        "fiducial_pose_err_p95_deg": _pct(pool("fid_err_deg"), 95),
        "fiducial_pose_err_p95_deg_2face": _pct(pool("fid_err_deg_2face"), 95),
        "fiducial_sightings": float(len(pool("fid_err_m"))),
        "perception_ms_per_sweep_p95": _pct(pool("sweep_ms"), 95),
        "colour_ms_per_candidate_p95": _pct(pool("colour_ms"), 95),
        "person_colour_ms_p95": _pct(pool("person_colour_ms"), 95),
        "thumbnail_bytes_p50": _pct(pool("thumb_bytes"), 50),
        "uplink_detection_bytes_per_object": tot("detection_bytes")
        / max(1, tot("objects_reported")),
        "images_per_min": 60.0 * tot("images") / max(sim_s, 1e-9),
        "perception_cpu_frac": sum(r.perception_cpu_s for r in results) / max(sim_s, 1e-9),
        "objects_in_range": float(tot("ooi_in_range") + tot("vat_in_range")),
        "robots_lost": float(sum(r.robot_lost for r in results)),
        "wall_s": time.perf_counter() - t0,
    }
    # a metric with no sample (nothing in range) is reported as a bad value, never hidden:
    # every one that can lack samples is an error, a time or a size (lower is better)
    for k, v in metrics.items():
        if not math.isfinite(v):
            metrics[k] = 999.0
    return metrics
