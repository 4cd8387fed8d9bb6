"""The sans-IO radio channel: queueing, rates, reliability and metering, without zenoh.

The "air" between the two channels is simulated here: packets from ``poll`` are handed to
the other side's ``receive``, optionally duplicated, reordered or dropped by the test.
"""

from __future__ import annotations

import math
import random

import pytest

from protocol.messages import (
    AutonomyMode,
    Direction,
    GoToTask,
    Hazard,
    HazardUpdate,
    ObjectKind,
    PoseNode,
    TaskState,
    TaskStatus,
    Telemetry,
    TerrainGrid,
    encode_frame,
)
from protocol.meter import Meter
from protocol.radio import RadioGrant
from protocol.radio_channel import LinkBackpressure, Packet, RadioChannel, ReliabilityConfig
from protocol.wire import ProtocolError


def make_pair(
    *, rate_bps: float = math.inf, loss: float = 0.0, config: ReliabilityConfig | None = None
) -> tuple[RadioChannel, RadioChannel]:
    meter = Meter()
    robot = RadioChannel(
        7, Direction.UP, meter=meter, grant_bps=rate_bps, loss=loss, seed=1, config=config
    )
    gcs = RadioChannel(
        7, Direction.DOWN, meter=meter, grant_bps=rate_bps, loss=loss, seed=2, config=config
    )
    return robot, gcs


def exchange(robot: RadioChannel, gcs: RadioChannel, now: float) -> tuple[list, list]:
    """One instant on the air: both sides transmit, the other side receives."""
    to_gcs = robot.poll(now)
    to_robot = gcs.poll(now)
    at_gcs = [m for p in to_gcs for m in gcs.receive(p.stream, p.payload, now)]
    at_robot = [m for p in to_robot for m in robot.receive(p.stream, p.payload, now)]
    return at_gcs, at_robot


def status(i: int) -> TaskStatus:
    return TaskStatus(i, TaskState.ACTIVE, float(i))


def telemetry(t: float) -> Telemetry:
    return Telemetry(t, (t, 0.0, 0.0), (0.5, 0.0), (0.0, 0.0), 0.9, AutonomyMode.AUTONOMOUS, 0)


def test_reliable_exactly_once_in_order_under_loss_and_disconnect() -> None:
    robot, gcs = make_pair(rate_bps=9600.0, loss=0.3)
    up, down = [], []
    n_up, n_down = 300, 30
    t = 0.0
    for step in range(20_000):
        t = step * 0.05
        if step < n_up:
            robot.send(status(step))
        if step < n_down:
            gcs.send(GoToTask(step, t, [(1.0, 2.0)]))
        if step == 100:  # 10 s without radio in the middle of the traffic
            robot.set_grant(0.0, 0.3)
            gcs.set_grant(0.0, 0.3)
        if step == 300:
            robot.set_grant(9600.0, 0.3)
            gcs.set_grant(9600.0, 0.3)
        a, b = exchange(robot, gcs, t)
        up += [m.task_id for m in a]
        down += [m.task_id for m in b]
        if len(up) == n_up and len(down) == n_down and step > n_up:
            break
    assert up == list(range(n_up))
    assert down == list(range(n_down))
    assert robot.stats.lost_in_air > 50  # the loss really happened
    # losses are repaired without a retransmission storm (lost_in_air includes lost acks)
    assert 0 < robot.stats.retransmitted <= 1.5 * robot.stats.lost_in_air
    for k in range(1, 400):  # let the last acknowledgements come back
        exchange(robot, gcs, t + 0.05 * k)
    assert robot.held_bytes == 0 and robot.pending() == 0
    assert gcs.pending() == 0


def test_duplicated_and_reordered_packets_deliver_once_in_order() -> None:
    robot, gcs = make_pair()
    for i in range(50):
        robot.send(status(i))
    packets = robot.poll(0.0)
    air = packets + packets[::3]  # duplicates
    random.Random(4).shuffle(air)
    got = [m.task_id for p in air for m in gcs.receive(p.stream, p.payload, 0.0)]
    assert got == list(range(50))
    assert gcs.stats.duplicates_dropped == len(packets[::3])


def test_latest_only_stream_keeps_only_newest_and_never_retransmits() -> None:
    robot, gcs = make_pair(rate_bps=0.0)
    for i in range(10):
        robot.send(telemetry(float(i)))
    assert robot.poll(1.0) == []  # disconnected: nothing goes out
    robot.set_grant(9600.0)
    packets = robot.poll(2.0)
    assert [p.stream for p in packets] == ["telemetry"]
    delivered = gcs.receive(packets[0].stream, packets[0].payload, 2.0)
    assert [m.time_s for m in delivered] == [9.0]
    assert robot.stats.superseded == 9
    # lose every telemetry message: it is never sent again
    robot.set_grant(9600.0, loss=0.99)
    robot.send(telemetry(10.0))
    for k in range(100):
        robot.poll(3.0 + k)
    assert robot.stats.transmitted == 2
    # an older message arriving late is dropped
    late = encode_frame(3, telemetry(3.0))
    assert gcs.receive("telemetry", late, 5.0) == []
    assert gcs.stats.stale_dropped == 1


def test_latest_reliable_stream_retransmits_newest_until_acked() -> None:
    gcs_side = RadioChannel(2, Direction.DOWN, grant_bps=math.inf, loss=0.0, seed=3)
    robot_side = RadioChannel(2, Direction.UP, grant_bps=math.inf)
    update = HazardUpdate(1.0, [Hazard(1, ObjectKind.STATIC_OOI, (3.0, 4.0), 2.5)], [])
    gcs_side.send(update)
    first = gcs_side.poll(0.0)
    assert [p.stream for p in first] == ["hazard_update"]
    # the first transmission is lost: it comes again after the timeout (a stream's first
    # message: the prompt one, nothing follows it to reveal its loss)
    assert gcs_side.poll(0.9 * gcs_side.config.prompt_rto_s) == []
    again = gcs_side.poll(gcs_side.config.prompt_rto_s + 0.1)
    assert [p.stream for p in again] == ["hazard_update"]
    # a newer update supersedes the old one, which is then never delivered
    newer = HazardUpdate(2.0, [], [])
    gcs_side.send(newer)
    pk = gcs_side.poll(10.0)
    assert [robot_side.receive(p.stream, p.payload, 10.0) for p in pk] == [[newer]]
    assert robot_side.receive(again[0].stream, again[0].payload, 10.1) == []
    # once acknowledged it is not retransmitted any more
    for t in (11.0, 16.0):
        for p in robot_side.poll(t):
            gcs_side.receive(p.stream, p.payload, t)
    assert gcs_side.pending() == 0
    assert gcs_side.poll(100.0) == []


@pytest.mark.parametrize("step_s", [0.01, 0.05, 0.5, 2.0])
def test_rate_holds_in_mission_time(step_s: float) -> None:
    grant = 9600.0
    robot, gcs = make_pair(rate_bps=grant)
    i = 0
    t = 0.0
    robot.poll(0.0)
    while t < 60.0 - 1e-9:
        while robot.pending() < 200:  # more than one step can drain: always backlogged
            robot.send(TerrainGrid(i, 0.1, bytes(200)))
            i += 1
        t += step_s
        exchange(robot, gcs, t)
    sent_bits = robot.meter.total_bytes(direction=Direction.UP) * 8
    assert abs(sent_bits / 60.0 - grant) / grant <= 0.05


def test_rate_zero_holds_everything_and_loses_nothing() -> None:
    robot, gcs = make_pair(rate_bps=0.0)
    for i in range(20):
        robot.send(status(i))
    for t in range(100):
        assert robot.poll(float(t)) == []
    robot.set_grant(1e6)
    got, _ = exchange(robot, gcs, 200.0)
    assert [m.task_id for m in got] == list(range(20))


def test_priority_order_when_link_opens() -> None:
    robot, _ = make_pair(rate_bps=0.0)
    robot.send(telemetry(1.0))
    robot.send(TerrainGrid(0, 0.1, b"\x00"))
    robot.send(PoseNode(0, 0.0, (0, 0, 0), (0, 0, 0), (1, 0, 0, 1, 0, 1)))
    robot.send(status(1))
    robot.set_grant(math.inf)
    assert [p.stream for p in robot.poll(1.0)] == [
        "task_status",
        "pose_node",
        "terrain_grid",
        "telemetry",
    ]


def test_backpressure_refuses_new_and_keeps_accepted() -> None:
    cfg = ReliabilityConfig(max_queue_bytes=400)
    robot, gcs = make_pair(rate_bps=0.0, config=cfg)
    accepted = 0
    with pytest.raises(LinkBackpressure, match="reliable bytes"):
        for i in range(1000):
            robot.send(status(i))
            accepted += 1
    assert 0 < accepted < 1000
    robot.set_grant(math.inf)
    got, _ = exchange(robot, gcs, 1.0)
    assert [m.task_id for m in got] == list(range(accepted))


def test_bad_bytes_and_wrong_stream_raise_protocol_error_and_count() -> None:
    _, gcs = make_pair()
    with pytest.raises(ProtocolError):
        gcs.receive("pose_node", b"\xc1garbage", 0.0)
    with pytest.raises(ProtocolError, match="arrived on the uplink stream 'pose_node'"):
        gcs.receive("pose_node", encode_frame(1, status(1)), 0.0)
    with pytest.raises(ProtocolError, match="no uplink stream named 'nope'"):
        gcs.receive("nope", encode_frame(1, status(1)), 0.0)
    assert gcs.stats.rejected == 3
    # and the channel still works
    assert [m.task_id for m in gcs.receive("task_status", encode_frame(1, status(1)), 0.0)] == [1]


def test_wrong_direction_message_is_refused_by_send() -> None:
    robot, _ = make_pair()
    with pytest.raises(ProtocolError, match="not a uplink message"):
        robot.send(GoToTask(1, 0.0, []))


def test_acks_stay_a_small_fraction_at_one_kilobit() -> None:
    robot, gcs = make_pair(rate_bps=1000.0)
    t = 0.0
    node = 0
    while t < 300.0:
        if t >= node * 1.25:
            robot.send(PoseNode(node, t, (0, 0, 0), (0.5, 0, 0), (1e-3, 0, 0, 1e-3, 0, 1e-4)))
            robot.send(TerrainGrid(node, 0.1, bytes(60)))
            node += 1
        t += 0.05
        exchange(robot, gcs, t)
    acks = robot.meter.total_bytes(direction=Direction.DOWN, stream="ack")
    data = robot.meter.total_bytes(direction=Direction.UP)
    assert acks / data <= 0.05
    assert robot.stats.retransmitted == 0  # delayed acks never trigger needless resends


def test_metering_counts_framing_retransmissions_and_losses() -> None:
    meter = Meter()
    ch = RadioChannel(3, Direction.UP, meter=meter, framing_overhead_bytes=10, loss=0.5, seed=5)
    msg = status(1)
    size = len(encode_frame(1, msg))
    ch.send(msg)
    ch.poll(0.0)
    ch.poll(ch.config.rto_initial_s + 1.0)  # unacknowledged: sent again
    counts = meter.snapshot()[(3, Direction.UP, "task_status")]
    assert counts.messages == 2
    assert counts.payload_bytes == 2 * size
    assert counts.bytes == 2 * (size + 10)
    assert counts.retransmissions == 1
    assert counts.lost == ch.stats.lost_in_air


def test_grant_validation() -> None:
    ch = RadioChannel(1, Direction.UP)
    with pytest.raises(ValueError, match="rate_bps"):
        ch.set_grant(float("nan"))
    with pytest.raises(ValueError, match="loss"):
        ch.set_grant(100.0, 1.5)
    with pytest.raises(ValueError, match="loss"):
        RadioGrant(uplink_bps=1.0, downlink_bps=1.0, loss=1.0)
    ch.apply_grant(RadioGrant(uplink_bps=1200.0, downlink_bps=50.0))
    assert ch.rate_bps == 1200.0


def test_packet_is_what_poll_returns() -> None:
    robot, _ = make_pair()
    robot.send(status(1))
    (pkt,) = robot.poll(0.0)
    assert isinstance(pkt, Packet) and pkt.stream == "task_status"


def test_a_task_lost_on_the_air_is_resent_within_a_second_and_acked_at_once() -> None:
    """Tasks and their reports (``PROMPT_STREAMS``) are acknowledged promptly and resent
    after ``prompt_rto_s`` (1 s), not after the delayed acks' 9 s: a robot waiting for a
    lost task stood idle that long."""
    from protocol.radio_channel import PROMPT_STREAMS

    assert {"task", "task_status"} <= PROMPT_STREAMS
    robot, gcs = make_pair(rate_bps=9600.0)
    gcs.send(GoToTask(5, 0.0, [(1.0, 2.0)]))
    t, lost = 0.0, []
    while not lost:  # the first transmission never reaches the robot
        t += 0.05
        lost = gcs.poll(t)
    assert [p.stream for p in lost] == ["task"]
    sent_s, got = t, []
    while not got and t < 30.0:
        t += 0.05
        got += [m for p in gcs.poll(t) for m in robot.receive(p.stream, p.payload, t)]
    assert [m.task_id for m in got] == [5]
    assert t - sent_s <= gcs.config.prompt_rto_s + 0.1  # was rto_initial_s (10 s) and more
    # the robot acknowledges it at once (ack_prompt_delay_s), and it is not resent again
    heard = t
    while gcs.held_bytes and t < heard + 2.0:
        t += 0.05
        for p in robot.poll(t):
            gcs.receive(p.stream, p.payload, t)
    assert gcs.held_bytes == 0 and t <= heard + robot.config.ack_prompt_delay_s + 0.1
    assert gcs.stats.retransmitted == 1
    with pytest.raises(ValueError, match="prompt_rto_s"):
        ReliabilityConfig(prompt_rto_s=0.05)


def test_the_public_state_accessors_restore_a_channel_as_it_was() -> None:
    """What a resumed GCS reads and restores (``gcs.node.restore_link_state``): a channel
    given another's receive state, sequence numbers and decoder reference drops what that one
    delivered, delivers the held message once its gap is filled, and numbers on."""
    robot, gcs = make_pair()
    for i in range(1, 5):
        robot.send(status(i))
    packets = robot.poll(0.0)
    for p in packets[:2] + packets[3:]:  # the third is lost: the fourth is held
        gcs.receive(p.stream, p.payload, 0.0)
    assert gcs.receive_state("task_status") == (2, [4])
    assert robot.unacked_seqs("task_status") == [1, 2, 3, 4]
    gcs.send(GoToTask(1, 0.0, []))
    assert gcs.next_seq("task") == 2
    fresh = RadioChannel(7, Direction.DOWN, seed=9)
    through, held = gcs.receive_state("task_status")
    fresh.restore_received("task_status", through, {4: status(4)})
    fresh.restore_next_seq("task", gcs.next_seq("task"))
    fresh.prime_decoder("task_status", status(2))  # no decoder on this stream: ignored
    assert fresh.receive("task_status", packets[0].payload, 1.0) == []  # delivered before
    got = fresh.receive("task_status", packets[2].payload, 1.0)
    assert [m.task_id for m in got] == [3, 4]
    assert fresh.send(GoToTask(2, 1.0, [])) == 2
    with pytest.raises(ValueError, match="next_seq"):
        fresh.restore_next_seq("task", 0)
