"""A short real team run for the report tests: the simulator (small world), one robot node per
robot and the GroundStation in one process, wired through real :class:`RadioChannel` pairs
(metered, rates from the simulator's radio model), robots driving scripted goals
(:func:`mission.run.scripted_goals`), recorded by :class:`MissionRecorder`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from gcs.ground_station import GroundStation, GroundStationConfig
from mission.config import CONFIGS_DIR
from mission.report.recorder import MissionRecorder, ReportConfig, link_bytes_from_meters
from mission.run import RunConfig, scripted_goals
from protocol.messages import Direction, GoToTask, TaskState, TaskStatus, Telemetry
from protocol.meter import Meter
from protocol.radio_channel import RadioChannel
from protocol.se2 import inverse, relative, transform_points
from robot.node import RobotNode
from sim.simulator import Simulator, load_world_config


def run_small_team(
    run_dir: Path,
    *,
    duration_s: float = 30.0,
    sample_period_s: float = 5.0,
    gcs_period_s: float = 1.0,
    seed: int = 0,
    track_every_step: bool = True,
    finish: bool = True,
    interactions_at_s: tuple[float, ...] = (),
    config: ReportConfig | None = None,
) -> tuple[dict[str, float] | None, MissionRecorder]:
    """Run the small world's team for ``duration_s`` mission-s, recording into ``run_dir``;
    returns ``finish``'s metrics (None when ``finish`` is False) and the recorder."""
    world = load_world_config(CONFIGS_DIR / "world" / "small.yaml")
    with Simulator(world) as sim:
        ids = list(sim.robot_ids)
        roles = dict(zip(ids, sim.roles, strict=True))
        gcs_cfg = GroundStationConfig(robots=tuple(ids))
        gcs_cfg = msgspec.structs.replace(
            gcs_cfg, graph=msgspec.structs.replace(gcs_cfg.graph, map_robot_id=ids[0])
        )
        station = GroundStation(gcs_cfg)
        starts = sim.robot_poses()
        for k, rid in enumerate(ids[1:], 1):  # the operator's start hints (team_mapping)
            station.add_start_hint(
                rid,
                map_from_odom=relative(starts[0], starts[k]),
                sigma_xy_m=0.3,
                sigma_yaw_rad=0.05,
            )
        robot_meter, ground_meter = Meter(), Meter()
        up = {r: RadioChannel(r, Direction.UP, meter=robot_meter) for r in ids}
        down = {r: RadioChannel(r, Direction.DOWN, meter=ground_meter) for r in ids}
        nodes = {r: RobotNode(r, send=up[r].send) for r in ids}
        drivers = {r: sim.driver(r) for r in ids}
        rng = np.random.default_rng(seed)
        run_cfg = RunConfig(goals_per_robot=6)
        goals: dict[int, list[np.ndarray]] = {}
        chosen: list[np.ndarray] = []
        for k, r in enumerate(ids):
            g = scripted_goals(sim, k, run_cfg, rng, avoid=chosen)
            chosen.append(g)
            goals[r] = list(transform_points(inverse(starts[k]), g))
        active: dict[int, int] = {}
        modes: dict[int, Any] = {}
        next_task = [1]
        rec = MissionRecorder(
            run_dir, world_name="small", seed=seed, duration_s=duration_s, roles=roles,
            config=config,
        )  # fmt: skip

        def on_uplink(rid: int, msg: Any, now: float) -> None:
            station.handle(rid, msg, now_s=now)
            if isinstance(msg, Telemetry):
                modes[rid] = msg.mode
            elif isinstance(msg, TaskStatus) and msg.task_id == active.get(rid):
                if msg.state in (TaskState.SUCCEEDED, TaskState.FAILED, TaskState.REJECTED):
                    del active[rid]

        next_sample, next_gcs = 0.0, 0.0
        pending_interactions = sorted(interactions_at_s)
        for _ in range(int(round(duration_s / sim.config.step_s))):
            sim.step()
            now = sim.time_s
            grants = sim.radio_grants()
            for r in ids:
                up[r].apply_grant(grants[r])
                down[r].apply_grant(grants[r])
                for cmd in nodes[r].process(drivers[r].poll(0.0)):
                    drivers[r].send(cmd)
                for pkt in up[r].poll(now):
                    for msg in down[r].receive(pkt.stream, pkt.payload, now):
                        on_uplink(r, msg, now)
                for pkt in down[r].poll(now):
                    for msg in up[r].receive(pkt.stream, pkt.payload, now):
                        nodes[r].handle_downlink(msg)
                if r not in active and goals[r]:
                    g = goals[r].pop(0)
                    down[r].send(GoToTask(next_task[0], now, [(float(g[0]), float(g[1]))]))
                    active[r] = next_task[0]
                    next_task[0] += 1
            if now >= next_gcs:
                for r, msg in station.step(now_s=now, budget_s=1.0):
                    down[r].send(msg)
                next_gcs = now + gcs_period_s
            while pending_interactions and now >= pending_interactions[0]:
                rec.event(now, "interaction", command="pause", robot_id=ids[0])
                pending_interactions.pop(0)
            if track_every_step:
                rec.track(now, sim=sim)
            if now >= next_sample - 1e-9:
                rec.sample(
                    now, sim=sim, station=station,
                    link_bytes=link_bytes_from_meters(robot_meter, ground_meter), modes=modes,
                )  # fmt: skip
                next_sample = now + sample_period_s
        station.step(now_s=sim.time_s, budget_s=1.0)
        rec.sample(
            sim.time_s, sim=sim, station=station,
            link_bytes=link_bytes_from_meters(robot_meter, ground_meter), modes=modes,
        )  # fmt: skip
        # a detection event as the mission would log one: the GCS's first hazard, if any
        for h in station.hazards[:1]:
            rec.event(
                sim.time_s, "detection", object_kind=h.kind, position_in_map=h.position_in_map
            )
        if not finish:
            rec.close()
            return None, rec
        return rec.finish(sim=sim, station=station), rec
