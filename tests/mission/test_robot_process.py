"""A robot node as its own process's worth of wiring: simulator server, robot node and ground
side on three separate zenoh sessions over loopback, the simulator in lockstep."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from mission.robot_process import RobotProcess
from protocol.clock import ManualClock
from protocol.link import Link, LinkConfig
from protocol.loopback import free_loopback_port, unique_mission
from protocol.messages import GoToTask, PoseNode, TaskState, TaskStatus
from robot.node import RobotNodeConfig
from sim.server import SimServer
from sim.simulator import Simulator, load_world_config

pytestmark = pytest.mark.slow


def test_remote_robot_reaches_a_goal_sent_over_the_radio() -> None:
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("remote")
    sim = Simulator(load_world_config("configs/world/small.yaml"))
    sim_link = Link(LinkConfig(listen=(endpoint,)), mission=mission, clock=sim.clock)
    robot_clock = ManualClock()
    # every peer listens (on an ephemeral loopback port): peers do not route for each other,
    # they find each other through the simulator's session and connect directly
    robot_link = Link(LinkConfig(connect=(endpoint,)), mission=mission, clock=robot_clock)
    ground_link = Link(LinkConfig(connect=(endpoint,)), mission=mission)
    rid = sim.robot_ids[0]
    done = threading.Event()
    reports: list = []

    def on_message(robot_id: int, msg: object) -> None:
        reports.append(msg)
        if isinstance(msg, TaskStatus) and msg.state is TaskState.SUCCEEDED:
            done.set()

    ground = ground_link.gcs_endpoint(on_message=on_message)
    # lockstep waits for every robot's node: run one per robot, as a deployment would
    procs = [RobotProcess(robot_link, r, robot_clock, RobotNodeConfig()) for r in sim.robot_ids]
    server = SimServer(sim, link=sim_link, mission=mission, rtf=0.0, lockstep=True)
    threads = [threading.Thread(target=server.run, kwargs={"duration_s": 60.0}, daemon=True)]
    threads += [
        threading.Thread(target=p.run, kwargs={"duration_s": 60.0}, daemon=True) for p in procs
    ]
    try:
        assert ground.wait_for_robot(rid, 10.0)
        for t in threads:
            t.start()
        ground.send(rid, GoToTask(1, 0.0, [(4.0, 0.0)]))
        assert done.wait(120.0), f"no success; reports: {reports[-5:]}"
        assert robot_clock.now() > 3.0  # mission time came from the simulator's clock ticks
        assert any(isinstance(m, PoseNode) for m in reports)
    finally:
        server.stop()
        for p in procs:
            p.stop()
        for t in threads:
            if t.is_alive():
                t.join(timeout=10.0)
        for p in procs:
            p.close()
        for link in (ground_link, robot_link, sim_link):
            link.close()
        server.close()
        sim.close()


def test_a_robot_id_the_simulator_does_not_have_gets_one_line_and_status_2(capsys) -> None:
    """``magic robot --id 99`` against a four-robot simulator: no quiet run with no sweeps."""
    from mission.robot_process import main

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("ids")
    sim = Simulator(load_world_config("configs/world/small.yaml"))
    sim_link = Link(LinkConfig(listen=(endpoint,)), mission=mission, clock=sim.clock)
    server = SimServer(sim, link=sim_link, mission=mission, rtf=0.0)
    try:
        argv = ["--mission", mission, "--connect", endpoint, "--listen", "tcp/127.0.0.1:0"]
        assert main(["--id", "99", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert err == (
            f"magic robot: the simulator of mission {mission!r} has no robot 99; its robots "
            "are 0, 1, 2, 3"
        )
        assert len(err) < 200 and "\n" not in err
    finally:
        server.close()
        sim_link.close()
        sim.close()


@pytest.mark.parametrize(("sig", "status"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_stops_a_robot_process_cleanly(sig, status) -> None:
    repo = Path(__file__).resolve().parents[2]
    proc = subprocess.Popen(
        [sys.executable, "-m", "mission.cli", "robot", "--id", "0"]
        + ["--mission", unique_mission("stop"), "--listen", "tcp/127.0.0.1:0"],
        cwd=repo,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    watchdog = threading.Timer(60.0, proc.kill)
    watchdog.start()
    try:
        assert proc.stdout is not None
        assert "waiting for sensor frames" in proc.stdout.readline()
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=30)
    finally:
        watchdog.cancel()
        proc.kill()
    assert proc.returncode == status, err
    assert "Traceback" not in err
    assert f"magic robot: stopped by {signal.Signals(sig).name}" in out
    assert "robot 0 t=" in out  # its last status line


@pytest.mark.parametrize("duration", ["-5", "0", "nan", "inf"])
def test_a_non_positive_duration_is_refused_in_one_line(duration, capsys) -> None:
    """``magic robot --duration -5``: status 2 and one line, as ``magic run`` does, before any
    link opens."""
    from mission.robot_process import main

    assert main(["--id", "0", "--duration", duration]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "--duration must be > 0 mission-seconds, got" in err and "Traceback" not in err


@pytest.mark.slow
def test_robots_started_on_another_host_join_a_run_and_leave_when_it_ends() -> None:
    """``magic run --workers 1 --remote-robots 2-3 --mission M --listen E`` with robots 2 and 3
    in a ``magic robot --lockstep --id 2-3 --mission M --connect E`` started apart (another
    host's worker): the same run bit for bit as in one process, and that worker, which the
    run does not own, ends by itself (status 0) once the run's simulator is gone."""
    import msgspec

    from mission.run import RunConfig, fields_differing, run_mission

    repo = Path(__file__).resolve().parents[2]
    config = RunConfig(duration_s=3.0, seed=1)
    in_process = run_mission(config).fields()
    mission = unique_mission("remote")
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    worker = subprocess.Popen(
        [sys.executable, "-m", "mission.cli", "robot", "--lockstep", "--id", "2-3"]
        + ["--mission", mission, "--seed", "1", "--connect", endpoint, "--progress-s", "1e9"]
        + ["--connect-timeout", "60"],
        cwd=repo,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    watchdog = threading.Timer(180.0, worker.kill)
    watchdog.start()
    try:
        report = run_mission(
            msgspec.structs.replace(config, robot_processes=True, workers=1, remote_robots=(2, 3)),
            link=LinkConfig(listen=(endpoint,)),
            mission_name=mission,
        )
        spread = report.fields()
        out, err = worker.communicate(timeout=60)
    finally:
        watchdog.cancel()
        worker.kill()
    assert fields_differing(in_process, spread) == []
    assert report.processes == "robot nodes in 1 worker process (0,1), robots 2,3 on other hosts"
    assert worker.returncode == 0, err
    assert f"the simulator of mission {mission!r} is gone: done" in out


def test_a_lockstep_group_answers_each_step_in_one_message_and_skips_a_bad_frame() -> None:
    """``magic robot --lockstep --id 3,4``'s group: hellos (a GroupDone of time 0 naming its
    robots) until the first step, then one GroupDone per GroupGo carrying both robots' dones
    and commands; a frame that does not decode is counted and skipped, the step answered."""
    import msgspec

    from mission.lockstep_protocol import (
        GroupDone,
        GroupGo,
        RobotGo,
        group_done_key,
        group_go_key,
        seed_streams,
    )
    from mission.robot_process import LockstepGroup
    from protocol.radio import RadioGrant
    from protocol.sensors import ImuSample, WheelTicks, encode_sensor_frame

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    mission = unique_mission("group")
    ground = Link(LinkConfig(listen=(endpoint,)), mission=mission)
    clock = ManualClock()
    robots = Link(LinkConfig(connect=(endpoint,), pump_period_s=0.0), mission=mission, clock=clock)
    answers: list[GroupDone] = []
    got = threading.Condition()
    decoder = msgspec.msgpack.Decoder(GroupDone)

    def on_done(_key: str, payload: bytes) -> None:
        with got:
            answers.append(decoder.decode(payload))
            got.notify_all()

    ground.subscribe(group_done_key(mission), on_done)
    group = LockstepGroup(robots, [4, 3], clock, RobotNodeConfig(), seed_streams(1).robot)
    try:
        for _ in range(50):  # no step yet: the group says hello meanwhile
            assert not group.step_once(0.2)
            with got:
                if answers:
                    break
        hello = answers[0]
        assert (hello.time_s, hello.group, hello.robot_ids) == (0.0, 3, [3, 4])
        grant = RadioGrant(uplink_bps=1000.0, downlink_bps=1000.0)
        frames = [
            encode_sensor_frame(ImuSample(0.1, (0.0, 0.0, 0.0), (0.0, 0.0, 9.81))),
            encode_sensor_frame(WheelTicks(0.1, 0, 0)),
        ]
        go = GroupGo(
            0.1,
            [RobotGo(3, 0, grant, frames), RobotGo(4, 0, grant, [b"not a frame", *frames])],
        )
        ground.publish(group_go_key(mission, 3), msgspec.msgpack.encode(go))
        for _ in range(100):
            if group.step_once(0.1):
                break
        else:
            raise AssertionError("the group never answered its step")
        with got:
            assert got.wait_for(lambda: answers[-1].time_s == 0.1, 10.0)
        done = answers[-1]
        assert done.robot_ids == [3, 4] and [d.time_s for d in done.done] == [0.1, 0.1]
        assert len(done.commands) == 2
        assert [d.commands for d in done.done] == [len(c) for c in done.commands]
        assert [r.rejected_frames for r in group.robots] == [0, 1]
        assert [r.frames_seen for r in group.robots] == [2, 2]
    finally:
        group.close()
        robots.close()
        ground.close()
