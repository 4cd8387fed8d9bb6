"""Robot nodes in worker processes, a group of nodes per process (``mission.lockstep``'s
:class:`TeamOverProcesses`, ``magic robot --lockstep --id 0-3``): the same run as in one
process bit for bit, across a zenoh router on loopback too; a worker that dies, a robot id
hosted twice, a port in use and an endpoint that does not answer each named in one line."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from mission.lockstep import (
    TeamInLockstep,
    TeamOverProcesses,
    WorkerDied,
    seed_streams,
    step_wait_s,
    worker_groups,
)
from mission.lockstep_protocol import parse_robot_ids, robot_host_key
from protocol.config import load_config
from protocol.link import Link, LinkConfig
from protocol.loopback import free_loopback_port, unique_mission
from protocol.messages import GoToTask, encode_frame
from protocol.radio import RadioConfig
from sim.simulator import Simulator, load_world_config

REPO = Path(__file__).resolve().parents[2]
RADIO_PATH = str(REPO / "configs" / "radio" / "magic2010.yaml")
SEED = 5
STEPS = 60  # 6 mission-s at the simulator's 0.1 s step: pose nodes and grids flow both ways


def _sim() -> Simulator:
    world = load_world_config(REPO / "configs" / "world" / "small.yaml")
    seeds = seed_streams(SEED)
    from sim.simulator import SimulatorConfig

    return Simulator(world, config=SimulatorConfig(seed=seeds.simulator))


def _run(make_team: Any) -> tuple[np.ndarray, list[tuple[int, str, bytes]], dict[Any, int]]:
    """Drive a team ``STEPS`` steps with a goal for every robot at 1 s; returns the robots'
    true final poses, every uplink message the ground got (robot, encoded) in order, and
    the radio bytes by robot, direction and stream."""
    got: list[tuple[int, str, bytes]] = []

    def on_message(rid: int, msg: Any) -> None:
        got.append((rid, type(msg).__name__, encode_frame(0, msg)))

    with _sim() as sim, make_team(sim, on_message) as team:
        sent = False

        def on_step() -> None:
            nonlocal sent
            if not sent and sim.time_s >= 1.0:
                for k, rid in enumerate(sim.robot_ids):
                    x, y, _ = sim.robot_poses()[k]
                    team.ground.send(rid, GoToTask(1, sim.time_s, [(x + 3.0, y + 0.5)]))
                sent = True

        for _ in range(STEPS):
            team.step(on_step)
        poses = sim.robot_poses().copy()
        up = {k: v for k, v in team.link_bytes().items() if k[1] == "down"}
        up.update({(r, "up"): team.uplink_bytes(r) for r in sim.robot_ids})
        return poses, got, up


def _radio() -> RadioConfig:
    return load_config(RADIO_PATH, RadioConfig)


def _in_process(sim: Simulator, on_message: Any) -> TeamInLockstep:
    return TeamInLockstep(
        sim, radio=_radio(), seeds=seed_streams(SEED), on_ground_message=on_message
    )


def _compare(a: Any, b: Any) -> None:
    poses_a, got_a, bytes_a = a
    poses_b, got_b, bytes_b = b
    assert poses_a.tobytes() == poses_b.tobytes()  # bit for bit
    assert len(got_a) > 20 and got_a == got_b
    assert bytes_a == bytes_b


def test_worker_groups_split_ids_evenly_and_ids_parse() -> None:
    assert worker_groups([3, 0, 1, 2, 4], 2) == [[0, 1, 2], [3, 4]]
    assert worker_groups([0, 1], 8) == [[0], [1]]
    assert worker_groups(list(range(100)), 2) == [list(range(50)), list(range(50, 100))]
    assert parse_robot_ids("0,1,4-6") == [0, 1, 4, 5, 6]
    with pytest.raises(ValueError, match="robot id 5 given twice"):
        parse_robot_ids("4-6,5")
    with pytest.raises(ValueError, match="'x' is not an id"):
        parse_robot_ids("1,x")


@pytest.mark.slow
@pytest.mark.parametrize("workers", [1, 3])
def test_robot_nodes_in_worker_groups_give_the_in_process_run(workers: int) -> None:
    """One worker hosting all four nodes, and three workers (groups of 2, 1, 1): the same
    poses, uplink messages and radio bytes as one process, bit for bit."""

    def over(sim: Simulator, on_message: Any) -> TeamOverProcesses:
        team = TeamOverProcesses(
            sim,
            radio=_radio(),
            radio_path=RADIO_PATH,
            seeds=seed_streams(SEED),
            on_ground_message=on_message,
            workers=workers,
        )
        assert len(team.groups) == workers and sum(map(len, team.groups)) == 4
        return team

    _compare(_run(_in_process), _run(over))


@pytest.mark.slow
def test_two_groups_reach_each_other_only_through_a_zenoh_router(tmp_path: Path) -> None:
    """A router (a zenoh session in router mode, in this process); the simulator and the
    ground side with robots 0-1's worker on one side, robots 2-3's worker started apart (as
    on another host) on the other, every session a client of the router: the run is the one
    in one process."""
    router_ep = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("routed")
    router = Link(LinkConfig(mode="router", listen=(router_ep,)), mission=mission)
    client = LinkConfig(mode="client", connect=(router_ep,))
    remote = subprocess.Popen(
        [sys.executable, "-m", "mission.cli", "robot", "--id", "2-3", "--lockstep"]
        + ["--mission", mission, "--seed", str(SEED), "--radio", RADIO_PATH]
        + ["--mode", "client", "--connect", router_ep],
        cwd=REPO,
        stdout=subprocess.DEVNULL,
        stderr=open(tmp_path / "remote.err", "wb"),  # noqa: SIM115 - closed with the process
    )

    def over(sim: Simulator, on_message: Any) -> TeamOverProcesses:
        return TeamOverProcesses(
            sim,
            radio=_radio(),
            radio_path=RADIO_PATH,
            seeds=seed_streams(SEED),
            on_ground_message=on_message,
            workers=1,
            remote_robots=(2, 3),
            link=client,
            mission=mission,
        )

    try:
        routed = _run(over)
    finally:
        remote.terminate()
        remote.wait(timeout=30)
        router.close()
    assert "Traceback" not in (tmp_path / "remote.err").read_text()
    _compare(_run(_in_process), routed)


@pytest.mark.slow
def test_a_worker_that_dies_is_named_with_its_robots_and_status() -> None:
    with _sim() as sim:
        team = TeamOverProcesses(
            sim,
            radio=_radio(),
            radio_path=RADIO_PATH,
            seeds=seed_streams(SEED),
            on_ground_message=lambda _r, _m: None,
            workers=2,
            step_timeout_s=20.0,
        )
        with team:
            team.step()
            pid = team.worker_pids[1]
            os.kill(pid, signal.SIGKILL)
            with pytest.raises(WorkerDied) as err:
                for _ in range(20):
                    team.step()
    assert str(err.value) == f"robot worker 1 (robots 2-3, pid {pid}) exited with signal 9"


def _robot_main(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    from mission.robot_process import main

    status = main(argv)
    return status, capsys.readouterr().err.strip()


def test_a_robot_id_another_process_hosts_is_refused_in_one_line(capsys) -> None:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("twice")
    with Link(LinkConfig(listen=(endpoint,)), mission=mission) as other:
        other.declare_presence(robot_host_key(mission, 1))
        argv = ["--id", "0-1", "--mission", mission, "--connect", endpoint, "--lockstep"]
        status, err = _robot_main(argv, capsys)
    assert status == 2
    assert err == (
        f"magic robot: robot 1 of mission {mission!r} already runs in another process "
        "(a robot id given twice)"
    )
    status, err = _robot_main(["--id", "0,2,0"], capsys)
    assert (status, err) == (2, "magic robot: robot ids '0,2,0': robot id 0 given twice")


def test_a_port_in_use_and_an_endpoint_that_does_not_answer_are_named(capsys) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        status, err = _robot_main(["--id", "0", "--listen", f"tcp/127.0.0.1:{port}"], capsys)
        assert status == 2 and "\n" not in err and len(err) < 200
        assert err.startswith("magic robot: cannot open the zenoh link: ")
        assert f"tcp/127.0.0.1:{port}" in err and "in use" in err
        with _sim() as sim, pytest.raises(ValueError) as exc:
            TeamOverProcesses(
                sim,
                radio=_radio(),
                radio_path=RADIO_PATH,
                seeds=seed_streams(SEED),
                on_ground_message=lambda _r, _m: None,
                link=LinkConfig(listen=(f"tcp/127.0.0.1:{port}",)),
            )
        line = str(exc.value)
        assert line.startswith(f"cannot open the ground side's zenoh link on tcp/127.0.0.1:{port}")
        assert "in use" in line and "\n" not in line
    dead = f"tcp/127.0.0.1:{free_loopback_port()}"
    argv = ["--id", "0", "--connect", dead, "--connect-timeout", "1"]
    status, err = _robot_main(argv, capsys)
    assert (status, err) == (
        2,
        f"magic robot: cannot reach {dead} (no zenoh router or peer answered within 1 s)",
    )
    status, err = _robot_main([*argv, "--mode", "client"], capsys)
    assert status == 2 and err.startswith("magic robot: cannot open the zenoh link: ")
    assert dead in err and "\n" not in err


def test_a_link_config_file_gives_the_endpoints(tmp_path: Path) -> None:
    import argparse

    from protocol.process_cli import add_link_arguments, link_config

    path = tmp_path / "link.yaml"
    path.write_text("mode: client\nconnect: [tcp/10.0.0.9:7447]\n")
    p = argparse.ArgumentParser()
    add_link_arguments(p)
    cfg = link_config(_radio(), p.parse_args(["--link-config", str(path)]))
    assert (cfg.mode, cfg.connect) == ("client", ("tcp/10.0.0.9:7447",))
    cfg = link_config(_radio(), p.parse_args(["--link-config", str(path), "--mode", "peer"]))
    assert cfg.mode == "peer" and cfg.connect == ("tcp/10.0.0.9:7447",)
    path.write_text("mode: relay\n")
    with pytest.raises(ValueError, match="mode"):
        link_config(_radio(), p.parse_args(["--link-config", str(path)]))
    assert msgspec.structs.replace(cfg, mode="router").mode == "router"


def test_the_first_mission_seconds_wait_long_enough_for_kernels_to_compile() -> None:
    # a cold numba cache compiles at the first sweep (1.2 s): 30 s had ended first runs
    assert step_wait_s(1.2, 120.0, 900.0, 5.0) == 900.0
    assert step_wait_s(5.0, 120.0, 900.0, 5.0) == 120.0  # then a hung robot is named sooner
    assert step_wait_s(1.2, 120.0, 0.0, 5.0) == 120.0  # never shorter than the step's
