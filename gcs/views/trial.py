"""Try the views on a replay: a team of replayed robots feeds a GroundStation, the views
publish to a recording, and their cost is measured (issue 15: ``views_cpu_frac``,
``rrd_bytes_per_robot_hour``).

Each of ``robots`` robots replays the first ``max_nodes`` pose nodes and grids of one CARMEN
log (:func:`mission.replay.iter_replay_messages`, read-only use) with its own odometry noise
seed, starting ``stagger_s`` after the previous one, and sends what a robot node would add:
telemetry at every node, a task status, a detection now and then (static OOI, civilian,
toxic vat, in front of the robot) with a camera image of some, and one robot falls silent
halfway (a link outage, then a lost robot). The GCS loop is the node's: handle every message,
``GroundStation.step`` every ``step_period_s`` of mission time, and a picture when the views
say one is due.

Measured in one run (process CPU, every thread): the GCS loop takes the messages batch by
batch (``batch_s`` of mission time, as the node's loop does) and the station's thread CPU is
read once per batch; ``views_cpu_frac`` = (process - station) / process: picture building,
drawing, rerun's own threads and the views' rasterization; ``views_cpu_frac_given_map`` the
same when the GCS hands the views the map it rasterized anyway (for its planners), so
rasterization is not the views' cost; ``views_cpu_frac_python`` / ``views_cpu_frac_no_raster``
count only the views' Python work (thread CPU of building and drawing).

Run: ``python -m gcs.views.trial LOG [--robots 14] [--max-nodes 120] [--rrd FILE] [--png F]``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gcs.ground_station import GroundStation
from gcs.views.operator_picture import PictureBuilder, PlannerView, ViewsConfig
from gcs.views.render import render_region
from gcs.views.rerun_views import RerunViews
from protocol.messages import (
    AutonomyMode,
    Detection,
    DetectionImage,
    ObjectKind,
    TaskState,
    TaskStatus,
    Telemetry,
    encode_frame,
)

__all__ = ["TrialResult", "feed_events", "run_trial"]


@dataclass
class TrialResult:
    robots: int
    nodes: int
    mission_s: float
    pictures: int
    station_cpu_s: float
    build_cpu_s: float
    rasterize_cpu_s: float
    draw_cpu_s: float
    process_cpu_s: float
    rrd_bytes: int
    views_cpu_frac: float
    views_cpu_frac_python: float
    views_cpu_frac_no_raster: float
    views_cpu_frac_given_map: float
    rrd_bytes_per_robot_hour: float
    dropped: int
    sink_failures: dict[str, int]
    layer_cpu_s: dict[str, float]
    alerts: int
    events: int

    def metrics(self) -> dict[str, float]:
        return {
            "views_cpu_frac": self.views_cpu_frac,
            "views_cpu_frac_python": self.views_cpu_frac_python,
            "views_cpu_frac_no_raster": self.views_cpu_frac_no_raster,
            "views_cpu_frac_given_map": self.views_cpu_frac_given_map,
            "rrd_bytes_per_robot_hour": self.rrd_bytes_per_robot_hour,
        }


def _image(kind: ObjectKind, rng: np.random.Generator) -> bytes:
    img = np.full((120, 160, 3), 90, np.uint8)
    img += rng.integers(0, 30, img.shape, dtype=np.uint8)
    bgr = {ObjectKind.STATIC_OOI: (40, 40, 220), ObjectKind.CIVILIAN: (220, 80, 30)}.get(
        kind, (40, 160, 160)
    )
    cv2.circle(img, (80, 60), 30, bgr, -1)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def feed_events(
    log_path: str | Path,
    *,
    robots: int = 14,
    max_nodes: int = 120,
    stagger_s: float = 5.0,
    noise_scale: float = 1.0,
    seed: int = 0,
    detection_every: int = 25,
    silent_robot: int | None = 1,
) -> list[tuple[float, int, Any, int]]:
    """``(mission time s, robot id, message, radio bytes)`` of the whole team, in time order."""
    from gcs.replay.carmen_log import read_carmen_log
    from mission.replay import OdometryNoiseConfig, ReplayConfig, iter_replay_messages

    log = read_carmen_log(str(log_path))
    rng = np.random.default_rng(seed)
    kinds = [ObjectKind.STATIC_OOI, ObjectKind.CIVILIAN, ObjectKind.TOXIC_VAT]
    events: list[tuple[float, int, Any, int]] = []
    for r in range(robots):
        cfg = ReplayConfig(noise=OdometryNoiseConfig(scale=noise_scale, seed=seed + r))
        t0: float | None = None
        for n, rn in enumerate(iter_replay_messages(log, cfg)):
            if n >= max_nodes:
                break
            if silent_robot == r and n >= max_nodes // 2:
                break
            t0 = rn.pose_node.time_s if t0 is None else t0
            now = rn.pose_node.time_s - t0 + r * stagger_s
            node = rn.pose_node
            battery = max(0.05, 1.0 - 0.002 * n - 0.03 * r)
            tele = Telemetry(
                node.time_s,
                node.pose_in_odom,
                (0.5, 0.0),
                (0.0, 0.0),
                battery,
                AutonomyMode.AUTONOMOUS,
                1,
            )
            msgs: list[Any] = [node, rn.terrain_grid, tele]
            if n == 0:
                msgs.append(TaskStatus(1, TaskState.ACTIVE, node.time_s))
            if n > 0 and n % detection_every == 0:
                kind = kinds[(n // detection_every + r) % len(kinds)]
                det_id = 1000 * r + n
                msgs.append(
                    Detection(
                        det_id,
                        node.node_index,
                        node.time_s,
                        kind,
                        (2.0, 0.5),
                        (0.04, 0.0, 0.04),
                        0.3,
                        1.0,
                        0.8,
                    )
                )
                if kind != ObjectKind.TOXIC_VAT:
                    data = _image(kind, rng)
                    msgs.append(
                        DetectionImage(det_id, det_id, node.time_s, 0.0, "jpeg", 160, 120, data)
                    )
            for k, m in enumerate(msgs):
                events.append((now + 1e-3 * k, r, m, len(encode_frame(0, m))))
    events.sort(key=lambda e: (e[0], e[1]))
    return events


def _batches(
    events: list[tuple[float, int, Any, int]], batch_s: float
) -> list[list[tuple[float, int, Any, int]]]:
    """Consecutive events within one ``batch_s`` slot of mission time: what one turn of the
    GCS node's loop takes from its inbox."""
    out: list[list[tuple[float, int, Any, int]]] = []
    slot = None
    for e in events:
        k = math.floor(e[0] / batch_s)
        if k != slot:
            out.append([])
            slot = k
        out[-1].append(e)
    return out


def _run_gcs(
    events: list[tuple[float, int, Any, int]],
    step_period_s: float,
    builder: PictureBuilder,
    views: RerunViews,
    batch_s: float = 0.1,
) -> tuple[float, float, GroundStation, Any, int]:
    """The GCS node's loop over ``events``, batch by batch (:func:`_batches`): the station
    takes a batch and steps when due, then the views observe it and publish when due.
    Returns (process CPU s: every thread, the views closed and their thread joined first;
    the station's thread CPU s, read once per batch, not per message; the station; the
    last picture; pictures published)."""
    station = GroundStation(_station_config())
    last_step = -math.inf
    pictures = 0
    picture = None
    station_cpu = 0.0
    p0 = time.process_time()
    for batch in _batches(events, batch_s):
        now = batch[-1][0]
        c0 = time.thread_time()
        for t, rid, msg, _ in batch:
            station.handle(rid, msg, now_s=t)
        if now - last_step >= step_period_s:
            last_step = now
            station.step(now_s=now)
        station_cpu += time.thread_time() - c0
        for t, rid, msg, nbytes in batch:
            builder.observe(rid, msg, now_s=t, nbytes=nbytes, station=station)
        if builder.due(now):
            picture = builder.build(station, now, planner=_planner(station))
            views.publish(picture, now)
            pictures += 1
    end = (events[-1][0] if events else 0.0) + step_period_s
    c0 = time.thread_time()
    station.step(now_s=end)
    station_cpu += time.thread_time() - c0
    picture = builder.build(station, end, force_layers=True)
    views.publish(picture, end)
    pictures += 1
    views.close()
    return time.process_time() - p0, station_cpu, station, picture, pictures


def run_trial(
    log_path: str | Path,
    *,
    robots: int = 14,
    max_nodes: int = 120,
    rrd_path: str | Path | None = None,
    png_path: str | Path | None = None,
    step_period_s: float = 1.0,
    threaded: bool = False,
    views_config: ViewsConfig | None = None,
    seed: int = 0,
) -> TrialResult:
    """Feed the team's replay through a GroundStation with the views on (module docstring).

    The views' share: everything the process spent (every thread, rerun's included) beyond
    the station's own thread CPU, ``(process - station) / process``; the station is timed once
    per batch of messages, as the GCS node takes them (a clock read per message would cost
    more than the views' work on it)."""
    events = feed_events(log_path, robots=robots, max_nodes=max_nodes, seed=seed)
    _warm_up(events)
    builder = PictureBuilder(views_config)
    sink = f"save {rrd_path}" if rrd_path is not None else "memory"
    views = RerunViews(sink, threaded=threaded)
    process_cpu, base_cpu, station, picture, pictures = _run_gcs(
        events, step_period_s, builder, views
    )
    end = events[-1][0] if events else 0.0
    data_len = 0
    if rrd_path is not None:
        data_len = os.path.getsize(rrd_path)
    else:
        data_len = len(views.memory_bytes())
    if png_path is not None and picture is not None and picture.map is not None:
        m = picture.map
        cx = m.origin_in_map[0] + m.shape[1] * m.resolution_m / 2
        cy = m.origin_in_map[1] + m.shape[0] * m.resolution_m / 2
        half = max(m.shape) * m.resolution_m / 2
        img = render_region(picture, m, (cx, cy), half, px=800)
        cv2.imwrite(str(png_path), img[:, :, ::-1])
    views_py = builder.cpu_s + views.stats.draw_cpu_s
    views_cpu = max(process_cpu - base_cpu, 0.0)
    raster = builder.rasterize_cpu_s
    hours = max(end, 1e-9) / 3600.0
    return TrialResult(
        robots=robots,
        nodes=station.stats.pose_nodes,
        mission_s=end,
        pictures=pictures,
        station_cpu_s=base_cpu,
        build_cpu_s=builder.cpu_s,
        rasterize_cpu_s=raster,
        draw_cpu_s=views.stats.draw_cpu_s,
        process_cpu_s=process_cpu,
        rrd_bytes=data_len,
        views_cpu_frac=views_cpu / process_cpu if process_cpu > 0 else math.nan,
        views_cpu_frac_python=views_py / (views_py + base_cpu),
        views_cpu_frac_given_map=max(views_cpu - raster, 0.0) / (process_cpu - raster),
        views_cpu_frac_no_raster=(views_py - raster) / (views_py - raster + base_cpu),
        rrd_bytes_per_robot_hour=data_len / (robots * hours),
        dropped=views.stats.dropped,
        sink_failures=dict(views.stats.sink_failures),
        layer_cpu_s={k: round(v, 4) for k, v in views.stats.layer_cpu_s.items()},
        alerts=len(builder.alert_log.lines),
        events=len(builder.narrator.events),
    )


def _warm_up(events: list[tuple[float, int, Any, int]]) -> None:
    """Compile the numba kernels (rasterization, matching) before anything is timed."""
    station = GroundStation(_station_config())
    for now, rid, msg, _ in events[:40]:
        if rid == events[0][1]:
            station.handle(rid, msg, now_s=now)
    station.step(now_s=events[39][0] if len(events) > 39 else 0.0)
    station.rasterize()


def _station_config() -> Any:
    from mission.replay import ReplayConfig

    return ReplayConfig().station


def _planner(station: GroundStation) -> PlannerView:
    """A stand-in for gcs/tasking's state: each robot's goal 3 m ahead, robot 2 neutralizing."""
    goals = {}
    tasks = {}
    for r in station.graph.robots:
        x, y, t = station.graph.pose(station.graph.last_key(r))
        goals[r] = np.array([x + 3.0 * math.cos(t), y + 3.0 * math.sin(t)])
        tasks[r] = "neutralize 1" if r == 2 and len(station.hazards) else "explore"
    return PlannerView(goals_in_map=goals, tasks=tasks)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gcs.views.trial", description=__doc__)
    ap.add_argument("log")
    ap.add_argument("--robots", type=int, default=14)
    ap.add_argument("--max-nodes", type=int, default=120)
    ap.add_argument("--rrd", default=None)
    ap.add_argument("--png", default=None)
    ap.add_argument("--threaded", action="store_true")
    args = ap.parse_args(argv)
    res = run_trial(
        args.log,
        robots=args.robots,
        max_nodes=args.max_nodes,
        rrd_path=args.rrd,
        png_path=args.png,
        threaded=args.threaded,
    )
    print(json.dumps(res.__dict__, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
