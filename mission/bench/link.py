"""``magic bench link``: the radio link over real zenoh sessions on loopback (issue 2).

Metrics:

* ``delivered_fraction_30pct_loss``: reliable messages (both directions) delivered exactly once
  and in order, over sent, with 30% loss each way and a 10 s disconnect (must be 1.0);
  ``duplicates_delivered`` (0); ``out_of_order_delivered`` (0).
* ``rate_error_frac``: ``|achieved - granted| / granted`` over 60 mission-seconds with a
  saturated uplink, the worse of a fine (50 ms) and a coarse (500 ms) pump step (<= 0.05).
* ``ack_overhead_frac``: ack bytes over the payload bytes they acknowledge, at 1 kbps per
  robot with MAGIC-like traffic (a pose node and a terrain grid every 1.25 s) (<= 0.05).
* ``msgs_per_s_loopback``: small reliable messages through the full stack (encode, queue,
  pump, zenoh, decode, reliability, delivery) in wall time, median of 3 runs (>= 20000).

Mission time is stepped in lockstep (:class:`~protocol.loopback.LockstepPair`) for the first
three, so they are repeatable; the last runs on the wall clock with the pump thread.
"""

from __future__ import annotations

import statistics
import threading
import time
from collections.abc import Callable
from typing import Any

from protocol.clock import WallClock
from protocol.loopback import LockstepPair, open_pair
from protocol.messages import (
    Direction,
    GoToTask,
    PoseNode,
    TaskState,
    TaskStatus,
    TerrainGrid,
)
from protocol.radio import RadioGrant

__all__ = ["run"]


def _pose_node(i: int) -> PoseNode:
    return PoseNode(
        i, 1.25 * i, (0.5 * i, 0.1 * i, 0.01 * i), (0.5, 0.0, 0.01), (1e-3, 0, 0, 1e-3, 0, 1e-4)
    )


def _grid(i: int, nbytes: int) -> TerrainGrid:
    return TerrainGrid(i, 0.1, bytes((i + k) % 251 for k in range(nbytes)))


def _drain(pair: LockstepPair, up: list[int], down: list[int]) -> None:
    while (item := pair.gcs.recv(0)) is not None:
        up.append(item[1].node_index if isinstance(item[1], PoseNode) else item[1].task_id)
    while (msg := pair.robot.recv(0)) is not None:
        down.append(msg.task_id)


def delivery_under_loss(*, n_up: int, n_down: int, seed: int) -> dict[str, float]:
    """30% loss both ways, a 10 s disconnect in the middle; count what arrives and how."""
    lossy = RadioGrant(uplink_bps=9600.0, downlink_bps=9600.0, loss=0.3)
    dead = RadioGrant(uplink_bps=0.0, downlink_bps=0.0, loss=0.3)
    up: list[int] = []
    down: list[int] = []
    with LockstepPair.open(seed=seed) as pair:
        pair.robot.set_grant(lossy)
        pair.gcs.set_grant(1, lossy)
        sent_up = sent_down = 0
        t = 0.0
        while (len(up) < n_up or len(down) < n_down) and t < 3600.0:
            # offer traffic for the first part of the run: 8 uplink and 1 downlink per second
            if sent_up < n_up and t >= sent_up / 8.0:
                pair.robot.send(TaskStatus(sent_up, TaskState.ACTIVE, t))
                sent_up += 1
            if sent_down < n_down and t >= sent_down:
                pair.gcs.send(1, GoToTask(sent_down, t, [(1.0, 2.0), (3.0, 4.0)]))
                sent_down += 1
            if abs(t - 10.0) < 1e-9:
                pair.robot.set_grant(dead)
                pair.gcs.set_grant(1, dead)
            if abs(t - 20.0) < 1e-9:
                pair.robot.set_grant(lossy)
                pair.gcs.set_grant(1, lossy)
            pair.step(0.05)
            t = round(t + 0.05, 9)
            _drain(pair, up, down)
        lost = pair.robot.channel.stats.lost_in_air + pair.gcs.channel(1).stats.lost_in_air
        transmitted = pair.robot.channel.stats.transmitted + pair.gcs.channel(1).stats.transmitted
    unique = len(set(up)) + len(set(down))
    dups = (len(up) - len(set(up))) + (len(down) - len(set(down)))
    disorder = sum(1 for a, b in zip(up, up[1:], strict=False) if b < a) + sum(
        1 for a, b in zip(down, down[1:], strict=False) if b < a
    )
    exact = unique if (dups == 0 and disorder == 0) else unique - dups - disorder
    return {
        "delivered_fraction_30pct_loss": exact / (n_up + n_down),
        "duplicates_delivered": float(dups),
        "out_of_order_delivered": float(disorder),
        "loss_run_mission_s": t,
        "loss_observed_frac": lost / max(transmitted, 1),
    }


def rate_error(*, grant_bps: float, duration_s: float, step_s: float) -> float:
    """Saturate the uplink and compare the metered on-air rate with the grant."""
    with LockstepPair.open() as pair:
        pair.robot.set_grant(RadioGrant(uplink_bps=grant_bps, downlink_bps=grant_bps))
        pair.gcs.set_grant(1, RadioGrant(uplink_bps=grant_bps, downlink_bps=grant_bps))
        i = 0
        t = 0.0
        pair.step(0.0)
        start = pair.robot_link.meter.total_bytes(direction=Direction.UP)
        while t < duration_s - 1e-9:
            while pair.robot.channel.pending() < 20:  # keep the queue backlogged
                pair.robot.send(_grid(i, 240))
                i += 1
            pair.step(step_s)
            t += step_s
            while pair.gcs.recv(0) is not None:
                pass
        sent = pair.robot_link.meter.total_bytes(direction=Direction.UP) - start
    achieved_bps = sent * 8.0 / duration_s
    return abs(achieved_bps - grant_bps) / grant_bps


def ack_overhead(*, duration_s: float) -> dict[str, float]:
    """1 kbps per robot, a pose node and a ~150-byte terrain grid every 1.25 s."""
    grant = RadioGrant(uplink_bps=1000.0, downlink_bps=1000.0)
    with LockstepPair.open() as pair:
        pair.robot.set_grant(grant)
        pair.gcs.set_grant(1, grant)
        t = 0.0
        node = 0
        delivered = 0
        while t < duration_s - 1e-9:
            if t >= node * 1.25:
                pair.robot.send(_pose_node(node))
                pair.robot.send(_grid(node, 60))
                node += 1
            pair.step(0.05)
            t += 0.05
            while pair.gcs.recv(0) is not None:
                delivered += 1
        # the GCS acknowledges on its own ack stream and in the team's coalesced broadcast ack
        ack_bytes = sum(
            pair.gcs_link.meter.total_bytes(direction=Direction.DOWN, stream=stream)
            for stream in ("ack", "ack_broadcast")
        )
        data_bytes = pair.robot_link.meter.total_bytes(direction=Direction.UP)
    return {
        "ack_overhead_frac": ack_bytes / data_bytes,
        "ack_run_uplink_bps": data_bytes * 8.0 / duration_s,
        "ack_run_delivered": float(delivered),
    }


def loopback_throughput(*, n: int) -> float:
    """Messages per wall second through two real sessions, with the pump thread running."""
    gcs_link, robot_link = open_pair(clock=WallClock())
    try:
        done = threading.Event()
        count = [0]

        def on_message(_robot_id: int, _msg: Any) -> None:
            count[0] += 1
            if count[0] >= n:
                done.set()

        gcs_link.gcs_endpoint(on_message=on_message)
        robot = robot_link.robot_endpoint(7)
        if not robot.wait_for_gcs(10.0):
            raise TimeoutError("loopback sessions did not match")
        msg = TaskStatus(1, TaskState.ACTIVE, 0.0)
        t0 = time.perf_counter()
        for _ in range(n):
            robot.send(msg)
        if not done.wait(120.0):
            raise TimeoutError(f"only {count[0]} of {n} messages arrived")
        return n / (time.perf_counter() - t0)
    finally:
        robot_link.close()
        gcs_link.close()


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    metrics: dict[str, float] = {}
    progress("reliable delivery under 30% loss and a 10 s disconnect")
    metrics.update(
        delivery_under_loss(n_up=200 if quick else 1000, n_down=20 if quick else 100, seed=1)
    )
    progress("rate limiting over 60 mission-seconds")
    metrics["rate_error_frac"] = max(
        rate_error(grant_bps=9600.0, duration_s=60.0, step_s=0.05),
        rate_error(grant_bps=9600.0, duration_s=60.0, step_s=0.5),
    )
    progress("ack overhead at 1 kbps")
    metrics.update(ack_overhead(duration_s=120.0 if quick else 600.0))
    progress("loopback throughput")
    runs = [loopback_throughput(n=20_000 if quick else 100_000) for _ in range(3)]
    metrics["msgs_per_s_loopback"] = statistics.median(runs)
    return metrics
