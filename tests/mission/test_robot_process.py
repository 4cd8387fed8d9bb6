"""A robot node as its own process's worth of wiring: simulator server, robot node and ground
side on three separate zenoh sessions over loopback, the simulator in lockstep."""

from __future__ import annotations

import threading

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
