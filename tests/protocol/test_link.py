"""The link over real zenoh sessions on loopback (two sessions, TCP on 127.0.0.1)."""

from __future__ import annotations

import threading
import time

import pytest

from protocol import keys
from protocol.clock import ManualClock, WallClock
from protocol.link import Link, LinkConfig
from protocol.loopback import LockstepPair, open_pair, unique_mission
from protocol.messages import (
    AutonomyMode,
    Direction,
    GoToTask,
    IdleTask,
    TaskState,
    TaskStatus,
    Telemetry,
    TerrainGrid,
    encode_frame,
)
from protocol.radio import RadioGrant


def status(i: int) -> TaskStatus:
    return TaskStatus(i, TaskState.ACTIVE, float(i))


def drain_up(pair: LockstepPair) -> list:
    out = []
    while (item := pair.gcs.recv(0)) is not None:
        out.append(item)
    return out


def test_reliable_stream_exactly_once_in_order_under_loss_and_disconnect() -> None:
    lossy = RadioGrant(uplink_bps=9600.0, downlink_bps=9600.0, loss=0.3)
    dead = RadioGrant(uplink_bps=0.0, downlink_bps=0.0, loss=0.3)
    n_up, n_down = 150, 15
    up: list[int] = []
    down: list[int] = []
    with LockstepPair.open(robot_id=4, seed=11) as pair:
        pair.robot.set_grant(lossy)
        pair.gcs.set_grant(4, lossy)
        for step in range(10_000):
            t = step * 0.05
            if step < n_up:
                pair.robot.send(status(step))
            if step < n_down:
                pair.gcs.send(4, GoToTask(step, t, [(0.0, 1.0)]))
            if step == 60:
                pair.robot.set_grant(dead)
                pair.gcs.set_grant(4, dead)
            if step == 260:  # 10 mission-seconds later
                pair.robot.set_grant(lossy)
                pair.gcs.set_grant(4, lossy)
            pair.step(0.05)
            for robot_id, msg in drain_up(pair):
                assert robot_id == 4
                up.append(msg.task_id)
            while (msg := pair.robot.recv(0)) is not None:
                down.append(msg.task_id)
            if len(up) >= n_up and len(down) >= n_down and step > 300:
                break
        assert pair.robot.channel.stats.lost_in_air > 20
        assert pair.gcs.channel(4).stats.lost_in_air > 5
    assert up == list(range(n_up))
    assert down == list(range(n_down))


def test_latest_only_stream_delivers_only_newest_after_outage() -> None:
    with LockstepPair.open(robot_id=2) as pair:
        pair.robot.set_grant(RadioGrant(uplink_bps=0.0, downlink_bps=0.0))
        for i in range(5):
            pair.robot.send(
                Telemetry(float(i), (0, 0, 0), (0, 0), (0, 0), 1.0, AutonomyMode.IDLE, 0)
            )
        pair.step(1.0)
        assert drain_up(pair) == []
        pair.robot.set_grant(RadioGrant(uplink_bps=9600.0, downlink_bps=9600.0))
        pair.step(1.0)
        got = drain_up(pair)
    assert [(rid, m.time_s) for rid, m in got] == [(2, 4.0)]


def test_rate_limit_holds_in_mission_time_over_zenoh() -> None:
    grant = 4800.0
    with LockstepPair.open(robot_id=1) as pair:
        pair.robot.set_grant(RadioGrant(uplink_bps=grant, downlink_bps=grant))
        pair.gcs.set_grant(1, RadioGrant(uplink_bps=grant, downlink_bps=grant))
        pair.step(0.0)
        i = 0
        for _ in range(240):  # 60 mission-seconds in 0.25 s steps
            while pair.robot.channel.pending() < 10:
                pair.robot.send(TerrainGrid(i, 0.1, bytes(150)))
                i += 1
            pair.step(0.25)
            drain_up(pair)
        on_air = pair.robot_link.meter.total_bytes(direction=Direction.UP)
    assert abs(on_air * 8 / 60.0 - grant) / grant <= 0.05


def test_bad_bytes_are_counted_and_the_link_keeps_working() -> None:
    with LockstepPair.open(robot_id=3) as pair:
        key = keys.radio(pair.robot_link.mission, 3, Direction.UP, "task_status")
        pair.robot_link.publish(key, b"\x93\x01\x01\xff garbage")
        pair.robot_link.publish(key, encode_frame(1, IdleTask(1, 0.0)))  # downlink type on uplink
        assert pair.gcs.wait_packets_in(2, 5.0)
        assert pair.gcs.channel(3).stats.rejected == 2
        pair.robot.send(status(1))
        pair.robot_link.pump()
        assert pair.gcs.wait_packets_in(3, 5.0)
        assert [(r, m.task_id) for r, m in drain_up(pair)] == [(3, 1)]


def test_callback_errors_do_not_stop_delivery() -> None:
    seen: list[int] = []
    done = threading.Event()

    def on_message(robot_id: int, msg: TaskStatus) -> None:
        seen.append(msg.task_id)
        if msg.task_id == 0:
            raise RuntimeError("consumer bug")
        if msg.task_id == 2:
            done.set()

    gcs_link, robot_link = open_pair(clock=WallClock())
    try:
        gcs = gcs_link.gcs_endpoint(on_message=on_message)
        robot = robot_link.robot_endpoint(9)
        assert robot.wait_for_gcs(10.0)
        for i in range(3):
            robot.send(status(i))
        assert done.wait(10.0)
        assert seen == [0, 1, 2]
        assert gcs.callback_errors == 1
    finally:
        robot_link.close()
        gcs_link.close()


def test_radio_grants_follow_the_simulator() -> None:
    gcs_link, robot_link = open_pair(clock=WallClock())
    try:
        gcs = gcs_link.gcs_endpoint(follow_radio=True)
        robot = robot_link.robot_endpoint(5, follow_radio=True)
        gcs.channel(5)  # the GCS knows robot 5 already
        grant = RadioGrant(uplink_bps=2400.0, downlink_bps=1200.0, loss=0.1)
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline and not (
            robot.channel.rate_bps == 2400.0 and gcs.channel(5).rate_bps == 1200.0
        ):
            gcs_link.publish_grant(5, grant)  # repeated until both subscriptions are live
            robot.wait_packets_in(1, 0.05)  # a bounded pause between attempts
        assert robot.channel.rate_bps == 2400.0
        assert gcs.channel(5).rate_bps == 1200.0
    finally:
        robot_link.close()
        gcs_link.close()


def test_downlink_task_reaches_robot_with_pump_thread() -> None:
    gcs_link, robot_link = open_pair(clock=WallClock())
    try:
        gcs = gcs_link.gcs_endpoint()
        robot = robot_link.robot_endpoint(6)
        assert gcs.wait_for_robot(6, 10.0)
        gcs.send(6, IdleTask(42, 1.0))
        assert robot.recv(10.0) == IdleTask(42, 1.0)
    finally:
        robot_link.close()
        gcs_link.close()


def test_link_config_and_mission_validation() -> None:
    with pytest.raises(ValueError, match="mission"):
        Link(LinkConfig(listen=()), mission="bad/name")
    with pytest.raises(ValueError, match="pump_period_s"):
        LinkConfig(pump_period_s=-1.0)


def test_manual_clock_never_goes_back() -> None:
    clock = ManualClock(5.0)
    with pytest.raises(ValueError, match="cannot go back"):
        clock.set(4.0)
    assert clock.advance(1.5) == 6.5


def test_remote_driver_carries_sensor_frames_and_commands() -> None:
    import numpy as np

    from protocol.sensors import LidarSweep, VelocityCommand

    commands: list[VelocityCommand] = []
    got_command = threading.Event()

    def on_command(cmd: VelocityCommand) -> None:
        commands.append(cmd)
        got_command.set()

    mission = unique_mission("driver")
    sim_link, robot_link = open_pair(mission=mission, clock=WallClock())
    try:
        port = sim_link.driver_port(2, on_command)
        driver = robot_link.remote_driver(2)
        sweep = LidarSweep(
            0, 1.0, 1.25, np.arange(12, dtype=np.float32).reshape(4, 3), np.zeros(4, np.float32)
        )
        frames: list = []
        deadline = time.monotonic() + 10.0
        while not frames and time.monotonic() < deadline:  # until the subscription is live
            port.publish(sweep)
            frames = driver.poll(0.05)
        assert frames, "no sensor frame arrived"
        assert np.array_equal(frames[0].points_in_base, sweep.points_in_base)
        sim_link.publish(keys.sim_sensors(mission, 2), b"not a frame")
        cmd = VelocityCommand(1.0, 0.5, -0.1)
        while not got_command.is_set() and time.monotonic() < deadline:
            driver.send(cmd)
            got_command.wait(0.05)
        assert commands[0] == cmd
        while driver.rejected == 0 and time.monotonic() < deadline:
            driver.poll(0.05)
        assert driver.rejected == 1
    finally:
        robot_link.close()
        sim_link.close()


def test_a_script_that_never_closes_its_links_still_exits() -> None:
    # the README's link example: zenoh's callback threads must not keep the process alive
    import subprocess
    import sys
    import textwrap

    from protocol.loopback import free_loopback_port

    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    script = textwrap.dedent(f"""
        from protocol.link import Link, LinkConfig
        from protocol.messages import PoseNode

        gcs = Link(LinkConfig(listen=("{endpoint}",)), mission="exit").gcs_endpoint()
        robot = Link(LinkConfig(connect=("{endpoint}",)), mission="exit").robot_endpoint(3)
        robot.send(PoseNode(0, 0.0, (0, 0, 0), (0, 0, 0), (1e-4, 0, 0, 1e-4, 0, 1e-5)))
        print(gcs.recv(timeout_s=5.0)[0])
    """)
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=False
    )
    assert (done.returncode, done.stdout) == (0, "3\n"), done.stderr


def telemetry(time_s: float, task_id: int) -> Telemetry:
    return Telemetry(
        time_s, (0.0, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 1.0, AutonomyMode.AUTONOMOUS, task_id
    )


def test_lockstep_radio_delivers_on_the_stepping_thread_in_canonical_order() -> None:
    """Several robots' packets, whatever order zenoh's threads see them in, reach the ground
    side inside ``exchange`` on the caller's thread, by robot then stream then sequence; what
    is held is counted as arrived but not delivered before ``exchange``."""
    from protocol.loopback import LockstepRadio

    clock = ManualClock()
    cfg = LinkConfig(pump_period_s=0.0)
    ground_link, robot_link = open_pair(config=cfg, clock=clock)
    got: list[tuple[int, str, int, int]] = []
    down: dict[int, list[int]] = {7: [], 2: []}
    caller = threading.get_ident()

    def on_up(robot_id: int, msg: object) -> None:
        assert threading.get_ident() == caller
        kind = type(msg).__name__
        got.append((robot_id, kind, getattr(msg, "task_id", -1), threading.get_ident()))

    try:
        ground = ground_link.gcs_endpoint(on_message=on_up)
        robots = {
            rid: robot_link.robot_endpoint(
                rid, on_message=lambda m, r=rid: down[r].append(m.task_id)
            )
            for rid in (7, 2)
        }
        radio = LockstepRadio(ground_link, ground, [robot_link], robots)
        radio.wait_connected(10.0)
        for step in range(3):
            clock.advance(0.05)
            for rid in (7, 2):  # robot 7 sends first
                robots[rid].send(status(10 * rid + step))
                robots[rid].send(telemetry(clock.now(), 10 * rid + step))
                ground.send(rid, GoToTask(100 * rid + step, clock.now(), [(1.0, 0.0)]))
            robot_link.pump()
            sent = sum(ep.packets_out for ep in robots.values())
            assert ground.wait_packets_in(sent, 10.0)  # arrived, held
            assert got == []  # nothing delivered before the exchange
            radio.exchange()
            assert [t for r, k, t, _ in got if k == "TaskStatus"] == [20 + step, 70 + step]
            assert [(r, k) for r, k, _, _ in got] == [  # robot, then stream id
                (2, "TaskStatus"),
                (2, "Telemetry"),
                (7, "TaskStatus"),
                (7, "Telemetry"),
            ]
            got.clear()
        assert down == {7: [700, 701, 702], 2: [200, 201, 202]}
    finally:
        robot_link.close()
        ground_link.close()


def test_lockstep_radio_refuses_links_with_a_pump_thread() -> None:
    from protocol.loopback import LockstepRadio

    with Link(LinkConfig(listen=(), pump_period_s=0.01), mission=unique_mission("t")) as link:
        with pytest.raises(ValueError, match="pump_period_s 0"):
            LockstepRadio(link, link.gcs_endpoint(), [], {})
