"""``magic bench scale``'s parts at a small size: the synthetic team's traffic, the GCS's
node-to-frame latency measured on it, and the whole team in worker processes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mission.bench.radio_scale import simulate
from mission.bench.scale import full_team, gcs_latency, synthetic_team_traffic
from protocol.messages import PoseNode, TerrainGrid


def test_synthetic_traffic_is_repeatable_and_in_arrival_order() -> None:
    a, starts = synthetic_team_traffic(6, 12.0)
    b, _ = synthetic_team_traffic(6, 12.0)
    assert [(t, r, type(m).__name__) for t, r, m in a] == [
        (t, r, type(m).__name__) for t, r, m in b
    ]
    times = [t for t, _, _ in a]
    assert times == sorted(times)
    nodes = [(r, m) for _, r, m in a if isinstance(m, PoseNode)]
    grids = [(r, m) for _, r, m in a if isinstance(m, TerrainGrid)]
    assert len(nodes) == len(grids) > 6 * 5  # several nodes a robot, each with its grid
    for rid in range(6):
        idx = [m.node_index for r, m in nodes if r == rid]
        assert idx == list(range(len(idx)))  # no gaps
    assert set(starts) == set(range(6))
    # robots of one tile share it (within its 60 m), tiles are 200 m apart
    assert np.hypot(*(starts[0][:2] - starts[4][:2])) < 60
    assert np.hypot(*(starts[0][:2] - starts[5][:2])) > 100


@pytest.mark.slow
def test_gcs_latency_frames_every_node_it_was_fed() -> None:
    r = gcs_latency(10, 20.0, profile_steps=3)
    assert r["gcs_nodes"] > 50
    assert r["gcs_nodes_never_framed"] == 0
    # a frame goes out every FRAMES_PERIOD_S (1 s) after a step every second: a node waits
    # at least until the next step, and not forever
    assert 0.0 < r["gcs_node_to_frame_s_p50"] <= r["gcs_node_to_frame_s_p95"] < 60.0
    # a frame never comes before the optimization that includes the node
    assert 0.0 < r["gcs_node_to_estimate_s_p95"] <= r["gcs_node_to_frame_s_p95"]
    assert r["gcs_peak_rss_mb"] > 50 and "ground_station.py" in r["profile"]
    assert all(math.isfinite(v) for k, v in r.items() if k != "profile")


@pytest.mark.slow
def test_full_team_measures_rtf_and_cpu_of_its_workers() -> None:
    r = full_team(4, world="small", mission_s=0.5, warmup_s=1.0, steady_after_s=0.5, steady_s=1.25)
    assert r["workers"] >= 1 and r["rtf"] > 0
    # the workers did the robots' work: CPU was spent there (1.0-1.5 s holds the first LIDAR
    # sweep; before it a robot costs less than a 10 ms CPU tick since the group messages)
    assert r["cpu_s_per_robot_mission_s"] > 0 and r["cpu_s_sim_gcs_per_mission_s"] > 0
    # the steady window (2.0-3.25 s, the second sweep's end in it) is measured on its own
    assert r["rtf_steady"] > 0 and r["cpu_s_per_robot_mission_s_steady"] > 0
    assert r["cpu_s_sim_gcs_per_mission_s_steady"] > 0


def test_the_radio_measurement_broadcasts_frames_at_the_period_asked() -> None:
    slow = simulate(robots=8, duration_s=12.0, drain_s=2.0, frames_period_s=2.0)
    fast = simulate(robots=8, duration_s=12.0, drain_s=2.0, frames_period_s=1.0)
    # twice the broadcasts: more downlink, the same uplink per node
    assert fast["downlink_bps_per_robot_100"] > 1.3 * slow["downlink_bps_per_robot_100"]
    assert fast["uplink_bytes_per_node"] == pytest.approx(slow["uplink_bytes_per_node"], rel=0.1)
