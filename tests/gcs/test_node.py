"""The GCS node over real zenoh: robots' uplink in, frames out, bad input counted not fatal."""

from __future__ import annotations

import threading

import numpy as np

from compression import encode_grid
from gcs.ground_station import GroundStationConfig
from gcs.node import GcsProcess, main
from protocol.clock import ManualClock
from protocol.loopback import open_pair
from protocol.messages import HazardUpdate, PoseNode, TerrainGrid, covariance_to_upper

COV = covariance_to_upper(np.diag([1e-4, 1e-4, 4e-6]))


def test_gcs_node_takes_uplink_and_sends_frames_over_zenoh() -> None:
    clock = ManualClock()
    gcs_link, robot_link = open_pair(clock=clock)
    proc = GcsProcess(gcs_link, clock, GroundStationConfig(robots=(0,)), step_period_s=0.5)
    got = threading.Event()
    updates: list[HazardUpdate] = []

    def on_down(msg: object) -> None:
        if isinstance(msg, HazardUpdate) and msg.frames:
            updates.append(msg)
            got.set()

    robot0 = robot_link.robot_endpoint(0, on_message=on_down)
    stranger = robot_link.robot_endpoint(9)
    try:
        assert proc.radio.wait_for_robot(0, 10.0)
        grid = np.zeros((20, 30), dtype=bool)
        grid[5, :] = True
        for i in range(4):
            pose = (0.5 * i, 0.0, 0.0)
            robot0.send(PoseNode(i, float(i), pose, (0.5, 0.0, 0.0) if i else (0.0,) * 3,
                                 COV if i else (0.0,) * 6))  # fmt: skip
            robot0.send(TerrainGrid(i, 0.1, encode_grid(grid, origin_cells=(-15, -10))))
        robot0.send(TerrainGrid(4, 0.1, b"\xfe\x00garbage"))
        stranger.send(PoseNode(0, 0.0, (0.0, 0.0, 0.0), (0.0,) * 3, (0.0,) * 6))
        deadline = 200
        s = proc.station.stats
        while deadline and not (s.terrain_grids == 4 and s.rejected_total == 2 and got.is_set()):
            clock.set(clock.now() + 0.25)
            robot_link.pump()
            gcs_link.pump()
            proc.spin_once(timeout_s=0.05)
            deadline -= 1
        assert s.pose_nodes == 4 and s.terrain_grids == 4
        assert s.rejected["bad_grid"] == 1 and s.rejected["unknown_robot"] == 1
        assert got.is_set()
        assert updates[-1].frames[0].robot_id == 0
        assert "nodes 4 grids 4" in proc.status_line()
    finally:
        proc.close()
        robot_link.close()
        gcs_link.close()


def test_magic_gcs_rejects_a_bad_config(tmp_path, capsys) -> None:  # type: ignore[no-untyped-def]
    bad = tmp_path / "gcs.yaml"
    bad.write_text("frames_period_s: fast\n")
    assert main(["--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "gcs.yaml" in err and "frames_period_s" in err
