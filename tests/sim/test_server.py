"""``magic sim``: runs, shows progress, serves frames and takes commands over real zenoh,
refuses bad input without stopping, and steps in lockstep with remote robot nodes."""

from __future__ import annotations

import math
import signal
import subprocess
import sys
import threading
import time

import pytest

from protocol import keys
from protocol.clock import WallClock
from protocol.link import Link, LinkConfig
from protocol.loopback import open_pair, unique_mission
from protocol.sensors import ImuSample, LidarSweep, VelocityCommand
from sim.server import SimServer, main
from sim.simulator import Simulator
from tests.sim.simworlds import REPO, make_world

SMALL = str(REPO / "configs/world/small.yaml")


def test_main_runs_a_world_and_shows_progress(capsys) -> None:
    assert main(["--world", SMALL, "--no-zenoh", "--rtf", "0", "--duration", "1.5"]) == 0
    out = capsys.readouterr().out
    assert "world 60 x 40 m" in out and "4 robots (1 disruptors)" in out
    assert "t=    1.50 s" in out and "robots alive 4/4" in out


def test_a_port_in_use_is_one_line_before_the_world_is_built(capsys) -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        assert main(["--world", SMALL, "--listen", f"tcp/127.0.0.1:{port}"]) == 2
    out, err = capsys.readouterr()
    assert "generating" not in out
    assert err.startswith("magic sim: cannot open the zenoh link: ") and err.count("\n") == 1
    assert f"127.0.0.1:{port}" in err


def test_main_refuses_an_invalid_world_config_clearly(tmp_path, capsys) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("seed: 1\ntrees:\n  count: -3\n", encoding="utf-8")
    assert main(["--world", str(bad), "--no-zenoh", "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert f"{bad}: trees.count: must be >= 0, got -3" in err
    assert main(["--world", str(tmp_path / "missing.yaml"), "--no-zenoh"]) == 2
    assert "missing.yaml: no such file" in capsys.readouterr().err


def _serve(server: SimServer, duration_s: float | None = None) -> threading.Thread:
    t = threading.Thread(target=server.run, args=(duration_s,), daemon=True)
    t.start()
    return t


def test_frames_and_commands_over_zenoh_and_bad_commands_are_refused() -> None:
    mission = unique_mission("simtest")
    sim_link, robot_link = open_pair(mission=mission, clock=WallClock())
    sim = Simulator(make_world(robots=[(5.0, 10.0, 0.0, "sensor"), (5.0, 14.0, 0.0, "sensor")]))
    server = SimServer(sim, link=sim_link, mission=mission, rtf=4.0)
    driver = robot_link.remote_driver(0)
    thread = _serve(server)
    try:
        frames: list = []
        deadline = time.monotonic() + 20.0
        while not any(isinstance(f, LidarSweep) for f in frames) and time.monotonic() < deadline:
            frames += driver.poll(0.1)
        assert any(isinstance(f, ImuSample) for f in frames)
        assert any(isinstance(f, LidarSweep) for f in frames)
        x0 = sim.robot_poses()[0, 0]
        driver.send(VelocityCommand(time_s=0.0, linear_m_s=math.nan, angular_rad_s=0.0))
        while server.rejected_commands == 0 and time.monotonic() < deadline:
            driver.poll(0.05)
        assert server.rejected_commands == 1
        while sim.robot_poses()[0, 0] < x0 + 0.3 and time.monotonic() < deadline:
            driver.send(VelocityCommand(time_s=sim.time_s, linear_m_s=1.0, angular_rad_s=0.0))
            driver.poll(0.1)
        assert sim.robot_poses()[0, 0] >= x0 + 0.3  # still running, and driving
        assert thread.is_alive()
    finally:
        server.stop()
        thread.join(10.0)
        server.close()
        driver.close()
        robot_link.close()
        sim_link.close()
        sim.close()


def test_lockstep_over_zenoh_waits_for_the_remote_node() -> None:
    mission = unique_mission("lockstep")
    sim_link, robot_link = open_pair(mission=mission, clock=WallClock())
    sim = Simulator(make_world())
    server = SimServer(sim, link=sim_link, mission=mission, rtf=0.0, lockstep=True)
    driver = robot_link.remote_driver(0)
    thread = _serve(server)
    try:
        acked = 0
        deadline = time.monotonic() + 30.0
        while acked < 3 and time.monotonic() < deadline:
            for f in driver.poll(0.1):
                if isinstance(f, LidarSweep):
                    # the sim cannot be more than one sweep ahead of this node
                    assert sim.time_s <= f.time_s + f.duration_s + 1.25 + 1e-6
                    driver.send(VelocityCommand(time_s=f.time_s, linear_m_s=0.2, angular_rad_s=0.0))
                    acked += 1
        assert acked == 3
        # stop acknowledging: the world stops once the next sweep is out
        unacked = None
        while unacked is None and time.monotonic() < deadline:
            unacked = next((f for f in driver.poll(0.1) if isinstance(f, LidarSweep)), None)
        assert unacked is not None and unacked.sweep_index == 3
        assert not sim.ready()
        stalled_at = sim.time_s
        driver.poll(0.3)
        assert sim.time_s == stalled_at and thread.is_alive()
    finally:
        server.stop()
        thread.join(10.0)
        server.close()
        driver.close()
        robot_link.close()
        sim_link.close()
        sim.close()


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_stops_the_server_cleanly(sig, status) -> None:
    """No traceback: the server stops, prints its last status and the events, 130 / 143."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "mission.cli", "sim", "--world", SMALL, "--no-zenoh"]
        + ["--rtf", "1", "--progress-s", "0.5"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    watchdog = threading.Timer(120.0, proc.kill)
    watchdog.start()
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if "robots alive" in line:
                break
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=60)
    finally:
        watchdog.cancel()
        proc.kill()
    assert proc.returncode == status, err
    assert "Traceback" not in err
    assert f"magic sim: stopped by {signal.Signals(sig).name} at t=" in out


def test_the_server_declares_the_robots_it_simulates() -> None:
    mission = unique_mission("team")
    sim_link, robot_link = open_pair(mission=mission, clock=WallClock())
    sim = Simulator(make_world())
    server = SimServer(sim, link=sim_link, mission=mission, rtf=0.0)
    try:
        deadline = time.monotonic() + 10.0
        present: list[str] = []
        while not present and time.monotonic() < deadline:  # declarations propagate
            present = robot_link.present(keys.sim_radio(mission, None), timeout_s=1.0)
        assert [int(k.rsplit("/", 1)[1]) for k in present] == sim.robot_ids
    finally:
        server.close()
        robot_link.close()
        sim_link.close()
        sim.close()
    # gone with the server's session
    with Link(LinkConfig(), mission=mission) as alone:
        assert alone.present(keys.sim_radio(mission, None), timeout_s=0.5) == []
