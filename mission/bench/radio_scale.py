"""``magic bench radio``: a hundred robots on one shared 115.2 kbps radio (issue 16 item 1;
the radio half of ``magic bench scale``).

Synthetic robot traffic at realistic rates goes through the real link code (two zenoh
sessions on loopback, :class:`~protocol.loopback.LockstepRadio`, every channel's queues,
reliability, codings and metering) in lockstep mission time, so the numbers are repeatable:

* each robot drives (0.4-1.2 m/s, stopping a third of the time, turning now and then) and
  sends a :class:`PoseNode` every metre or 15 degrees (at least every 30 s) with a covariance
  growing like the odometry's, a :class:`TerrainGrid` per node (compressed stream of 24 bytes
  on average: the compression bench's inter-frame codec), telemetry every second (the GCS
  sets ``link.telemetry_period_s`` to 10 s), a detection now and then, task statuses;
* the GCS broadcasts a :class:`HazardUpdate` (every robot's ``map_from_odom`` and the known
  hazards) every 2 s, sends each robot a goal every 30-90 s, coalesces its acks into one
  broadcast, and grants uplink air time by demand (:class:`~protocol.airtime.AirtimeScheduler`)
  within the shared capacity less the downlink's reserve; links lose 0-10% of messages;
* one robot gets a 30 kB backlog of grids at 2 minutes (a robot coming back into range).

Metrics:

* ``radio_use_frac_100``: every byte on the air (both directions, framing, retransmissions,
  broadcasts once) over 10 mission-minutes, over 115.2 kbps x 600 s (<= 0.8);
* ``uplink_bytes_per_node``: pose node + grid bytes plus their share of the GCS's acks, per
  node; ``uplink_bytes_per_node_all``: every uplink byte (telemetry, detections, acks) per
  node; ``pose_node_bytes`` (a coded pose node on the air, framing, retransmissions and the
  acks riding in it included) against ``pose_node_bytes_plain`` (the same nodes as plain
  frames, once each: the baseline);
* ``downlink_bps_per_robot_100`` (<= 100), ``uplink_bps_per_robot_100``; the baseline
  ``downlink_bps_per_robot_unicast_hazards``: the same hazard updates sent to each robot
  (what the downlink needed before the broadcast, growing with the square of the team);
* ``delivered_fraction``: reliable uplink messages delivered exactly once and in order, over
  sent (1.0), and ``hazard_heard_fraction``: robots holding the last broadcast's update;
* ``backlog_grant_ratio``: the backlogged robot's grant over the median robot's while it
  drains (> 1: shares follow need), ``backlog_drain_s``.

``--quick`` runs the same 100 robots for 3 mission-minutes (rates are per second, the
fractions comparable); the full run is 10 minutes.
"""

from __future__ import annotations

import functools
import math
import statistics
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from protocol.airtime import AirtimeScheduler
from protocol.clock import ManualClock
from protocol.link import GcsEndpoint, Link, LinkConfig, RobotEndpoint
from protocol.loopback import LockstepRadio, free_loopback_port, unique_mission
from protocol.messages import (
    AutonomyMode,
    Detection,
    GoToTask,
    Hazard,
    HazardUpdate,
    ObjectKind,
    ParameterUpdate,
    PoseNode,
    RobotFrame,
    TaskState,
    TaskStatus,
    Telemetry,
    TerrainGrid,
    encode_frame,
)
from protocol.radio import RadioConfig, RadioGrant
from protocol.radio_channel import LinkBackpressure

__all__ = ["run", "simulate"]

CAPACITY_BPS = RadioConfig().shared_capacity_bps
FRAMING_BYTES = RadioConfig().framing_overhead_bytes
STEP_S = 0.25


@dataclass
class _Robot:
    rid: int
    rng: np.random.Generator
    pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    last_node_pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    last_node_s: float = 0.0
    node_index: int = 0
    speed: float = 0.8
    turn: float = 0.0
    moving: bool = True
    next_change_s: float = 0.0
    next_telemetry_s: float = 0.0
    next_detection_s: float = 60.0
    detection_id: int = 0
    sent_nodes: list[int] = field(default_factory=list)
    sent_grids: list[int] = field(default_factory=list)
    tasks: list[int] = field(default_factory=list)
    plain_node_bytes: int = 0  # what the same nodes took before coding (frame + framing)


def _covariance(dist_m: float, turn_rad: float, dt_s: float) -> tuple[float, ...]:
    sxy = max(0.005, 0.03 * math.sqrt(dist_m))
    st = max(0.001, 0.02 * math.sqrt(turn_rad) + 0.002 * math.sqrt(dt_s))
    return (sxy * sxy, 0.1 * sxy * sxy, 0.0, 0.25 * sxy * sxy, 0.05 * sxy * st, st * st)


def _robot_step(r: _Robot, t: float, send: Callable[[Any], object]) -> int:
    """Drive ``r`` one step and send what a robot node would; returns nodes made."""
    rng = r.rng
    if t >= r.next_change_s:
        r.moving = rng.random() > 0.33
        r.speed = float(rng.uniform(0.4, 1.2))
        r.turn = float(rng.normal(0.0, 0.15)) if rng.random() < 0.5 else 0.0
        r.next_change_s = t + float(rng.uniform(5.0, 30.0))
    if r.moving:
        x, y, th = r.pose
        th = th + r.turn * STEP_S
        d = r.speed * STEP_S
        r.pose = np.array(
            [x + d * math.cos(th), y + d * math.sin(th), math.remainder(th, math.tau)]
        )
    made = 0
    moved = float(np.hypot(*(r.pose[:2] - r.last_node_pose[:2])))
    turned = abs(math.remainder(r.pose[2] - r.last_node_pose[2], math.tau))
    if r.node_index == 0 or moved >= 1.0 or turned >= 0.26 or t - r.last_node_s >= 30.0:
        c, s = math.cos(r.last_node_pose[2]), math.sin(r.last_node_pose[2])
        dx, dy = r.pose[:2] - r.last_node_pose[:2]
        delta = (
            c * dx + s * dy,
            -s * dx + c * dy,
            math.remainder(r.pose[2] - r.last_node_pose[2], math.tau),
        )
        if r.node_index == 0:
            delta = (0.0, 0.0, 0.0)
        cov = _covariance(moved, turned, t - r.last_node_s)
        node = PoseNode(r.node_index, t, tuple(r.pose), delta, cov)  # type: ignore[arg-type]
        seq = send(node)
        if isinstance(seq, int):
            r.sent_nodes.append(r.node_index)
            r.plain_node_bytes += len(encode_frame(seq, node)) + FRAMING_BYTES
        n_bytes = int(np.clip(rng.lognormal(math.log(22.0), 0.45), 6, 120))
        grid = TerrainGrid(
            r.node_index, 0.1, rng.integers(0, 256, n_bytes, dtype=np.uint8).tobytes()
        )
        if send(grid) is not None:
            r.sent_grids.append(r.node_index)
        r.node_index += 1
        r.last_node_pose = r.pose.copy()
        r.last_node_s = t
        made = 1
    if t >= r.next_telemetry_s:
        send(
            Telemetry(
                t,
                tuple(r.pose),  # type: ignore[arg-type]
                (r.speed if r.moving else 0.0, r.turn),
                (0.01, -0.02),
                0.8,
                AutonomyMode.AUTONOMOUS,
                r.tasks[-1] if r.tasks else 0,
            )
        )
        r.next_telemetry_s = t + 1.0
    if t >= r.next_detection_s:
        r.detection_id += 1
        send(
            Detection(
                r.detection_id,
                max(r.node_index - 1, 0),
                t,
                ObjectKind.STATIC_OOI,
                (3.0, 1.0),
                (0.04, 0.0, 0.04),
                0.3,
                0.5,
                0.8,
            )
        )
        r.next_detection_s = t + float(rng.exponential(120.0))
    return made


def simulate(
    *,
    robots: int = 100,
    duration_s: float = 600.0,
    seed: int = 7,
    drain_s: float = 30.0,
    frames_period_s: float = 2.0,
) -> dict[str, float]:
    """Run the synthetic team (module docstring) and return the metrics. ``frames_period_s``:
    how often the GCS broadcasts hazards and every robot's frame (a multiple of the link
    step, 0.25 s)."""
    frames_every = max(1, int(round(frames_period_s / STEP_S)))
    rng = np.random.default_rng(seed)
    clock = ManualClock(0.0)
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("radio-scale")
    ground_link = Link(
        LinkConfig(listen=(endpoint,), pump_period_s=0.0), mission=mission, clock=clock, seed=seed
    )
    robot_link = Link(
        LinkConfig(listen=(), connect=(endpoint,), pump_period_s=0.0),
        mission=mission,
        clock=clock,
        seed=seed + 1,
    )
    received: dict[int, dict[str, list[int]]] = {}
    hazards_seen: dict[int, float] = {}

    def on_ground(rid: int, msg: Any) -> None:
        per = received.setdefault(rid, {"node": [], "grid": [], "status": []})
        if isinstance(msg, PoseNode):
            per["node"].append(msg.node_index)
        elif isinstance(msg, TerrainGrid):
            per["grid"].append(msg.node_index)
        elif isinstance(msg, TaskStatus):
            per["status"].append(msg.task_id)

    team = [_Robot(rid, np.random.default_rng([seed, rid])) for rid in range(robots)]
    radios: dict[int, RobotEndpoint] = {}

    def on_robot(rid: int) -> Callable[[Any], None]:
        def handle(msg: Any) -> None:
            if isinstance(msg, HazardUpdate):
                hazards_seen[rid] = msg.time_s
            elif isinstance(msg, GoToTask):
                team[rid].tasks.append(msg.task_id)
                _send(rid, TaskStatus(msg.task_id, TaskState.ACCEPTED, clock.now()))

        return handle

    def _send(rid: int, msg: Any) -> object:
        try:
            return radios[rid].send(msg)
        except LinkBackpressure:
            return None

    try:
        ground: GcsEndpoint = ground_link.gcs_endpoint(on_message=on_ground)
        for r in team:
            radios[r.rid] = robot_link.robot_endpoint(r.rid, on_message=on_robot(r.rid))
        radio = LockstepRadio(ground_link, ground, [robot_link], radios)
        radio.wait_connected(20.0)
        loss = {r.rid: float(rng.uniform(0.0, 0.1)) for r in team}
        down_per_robot_bps = 30.0
        broadcast_bps = 9000.0
        uplink_capacity = 0.8 * CAPACITY_BPS - broadcast_bps - robots * down_per_robot_bps
        scheduler = AirtimeScheduler()
        up_grant = {r.rid: uplink_capacity / robots for r in team}

        def apply_grants() -> None:
            for rid, bps in up_grant.items():
                g = RadioGrant(bps, down_per_robot_bps, loss[rid])
                radios[rid].set_grant(g)
                ground.set_grant(rid, g)
            ground.set_broadcast_grant(broadcast_bps)

        apply_grants()
        for r in team:
            ground.send(r.rid, ParameterUpdate("link.telemetry_period_s", 10.0))
        frames_map = {r.rid: rng.normal(0.0, 50.0, 3) for r in team}
        hazard_list = [
            Hazard(k, ObjectKind.STATIC_OOI, tuple(rng.uniform(-200, 200, 2)), 10.0)  # type: ignore[arg-type]
            for k in range(10)
        ]
        next_goal = {r.rid: float(rng.uniform(5.0, 60.0)) for r in team}
        task_id = 0
        unicast_hazard_bytes = 0
        nodes = 0
        backlog_robot = 0
        backlog_at_s = min(120.0, duration_s / 3)
        backlog_ratio: list[float] = []
        backlog_done_s = math.nan
        backlog_grids: list[int] = []
        steps = int(round(duration_s / STEP_S))
        drain_steps = int(round(drain_s / STEP_S))
        for k in range(steps + drain_steps):
            t = (k + 1) * STEP_S
            clock.set(t)
            live = k < steps
            if live:
                for r in team:
                    nodes += _robot_step(r, t, functools.partial(_send, r.rid))
                if k == int(round(backlog_at_s / STEP_S)):
                    br = team[backlog_robot]
                    for _ in range(600):  # 600 grids of ~50 B: a robot back in range
                        grid = TerrainGrid(br.node_index, 0.1, bytes(48))
                        if _send(backlog_robot, grid) is not None:
                            br.sent_grids.append(br.node_index)
                            backlog_grids.append(br.node_index)
                        br.node_index += 1  # nodes it had kept to itself
            if (k + 1) % frames_every == 0 and live:  # the GCS's frames period
                for rid in frames_map:
                    frames_map[rid] = frames_map[rid] + rng.normal(0.0, 0.01, 3)
                frames = [RobotFrame(rid, tuple(v)) for rid, v in sorted(frames_map.items())]  # type: ignore[arg-type]
                update = HazardUpdate(t, hazard_list, frames)
                ground.broadcast(update)
                # the baseline: the same update sent to each robot (plain, framed)
                unicast_hazard_bytes += robots * (len(encode_frame(1, update)) + FRAMING_BYTES)
            if live:
                for r in team:
                    if t >= next_goal[r.rid]:
                        task_id += 1
                        wp = [tuple(r.pose[:2] + rng.uniform(-20, 20, 2))]
                        ground.send(r.rid, GoToTask(task_id, t, wp))  # type: ignore[arg-type]
                        next_goal[r.rid] = t + float(rng.uniform(30.0, 90.0))
            if abs(t - round(t)) < 1e-9:  # the GCS re-allocates air time every second
                got = {rid: ground.channel(rid).stats.bytes_received for rid in radios}
                backlog = {rid: ground.demand(rid) for rid in radios}
                up_grant = scheduler.update(
                    t, bytes_received=got, backlog_bytes=backlog, capacity_bps=uplink_capacity
                )
                apply_grants()
                if t > backlog_at_s and math.isnan(backlog_done_s):
                    recv_b = received.get(backlog_robot, {}).get("grid", [])
                    if backlog_grids and backlog_grids[-1] in set(recv_b[-50:]):
                        backlog_done_s = t - backlog_at_s
                    else:
                        others = statistics.median(
                            up_grant[r] for r in up_grant if r != backlog_robot
                        )
                        backlog_ratio.append(up_grant[backlog_robot] / others)
            radio.exchange(30.0)
        # metrics
        up = robot_link.meter.snapshot()
        down = ground_link.meter.snapshot()
        bytes_live = 0
        all_counts = list(up.values()) + list(down.values())
        bytes_live = sum(c.bytes for c in all_counts)
        span = steps * STEP_S + drain_steps * STEP_S
        use = bytes_live * 8.0 / (span * CAPACITY_BPS)
        up_by_stream: dict[str, int] = {}
        for (rid, _d, stream), c in up.items():
            if rid != backlog_robot:  # its backlog is not per-node traffic
                up_by_stream[stream] = up_by_stream.get(stream, 0) + c.bytes
        down_by_stream: dict[str, int] = {}
        for (_rid, _d, stream), c in down.items():
            down_by_stream[stream] = down_by_stream.get(stream, 0) + c.bytes
        up_total = sum(up_by_stream.values())
        down_total = sum(down_by_stream.values())
        node_bytes = up_by_stream.get("pose_node", 0) + up_by_stream.get("terrain_grid", 0)
        reliable_up = sum(v for s, v in up_by_stream.items() if s not in ("ack", "telemetry"))
        gcs_acks = down_by_stream.get("ack", 0) + down_by_stream.get("ack_broadcast", 0)
        ack_share = gcs_acks * node_bytes / max(reliable_up, 1)
        all_nodes = sum(len(r.sent_nodes) for r in team if r.rid != backlog_robot)
        pose_msgs = sum(
            c.messages
            for (rid, _d, s), c in up.items()
            if s == "pose_node" and rid != backlog_robot
        )
        ok = 0
        sent = 0
        for r in team:
            got_r = received.get(r.rid, {"node": [], "grid": []})
            sent += len(r.sent_nodes) + len(r.sent_grids)
            ok += (got_r["node"] == r.sent_nodes) * len(r.sent_nodes)
            ok += (got_r["grid"] == r.sent_grids) * len(r.sent_grids)
        last_broadcast = max(hazards_seen.values()) if hazards_seen else -1.0
        heard = sum(1 for v in hazards_seen.values() if v == last_broadcast)
        return {
            "radio_use_frac_100": use,
            "uplink_bytes_per_node": (node_bytes + ack_share) / max(all_nodes, 1),
            "uplink_bytes_per_node_all": up_total / max(all_nodes, 1),
            "pose_node_bytes": up_by_stream.get("pose_node", 0) / max(pose_msgs, 1),
            "pose_node_bytes_plain": sum(r.plain_node_bytes for r in team if r.rid != backlog_robot)
            / max(all_nodes, 1),
            "downlink_bps_per_robot_unicast_hazards": unicast_hazard_bytes * 8.0 / span / robots,
            "downlink_bps_per_robot_100": down_total * 8.0 / span / robots,
            "uplink_bps_per_robot_100": up_total * 8.0 / span / (robots - 1),
            "broadcast_bps": sum(c.bytes for (rid, _d, _s), c in down.items() if rid < 0)
            * 8.0
            / span,
            "gcs_ack_bytes_per_node": ack_share / max(all_nodes, 1),
            "delivered_fraction": ok / max(sent, 1),
            "hazard_heard_fraction": heard / robots,
            "backlog_grant_ratio": statistics.median(backlog_ratio) if backlog_ratio else 0.0,
            "backlog_drain_s": backlog_done_s if math.isfinite(backlog_done_s) else -1.0,
            "nodes_per_robot_min": all_nodes / robots / (duration_s / 60.0),
        }
    finally:
        robot_link.close()
        ground_link.close()


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    duration = 180.0 if quick else 600.0
    progress(f"100 robots, {duration:.0f} mission-s through the real link in lockstep")
    return simulate(robots=100, duration_s=duration)
