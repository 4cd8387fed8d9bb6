"""Broadcast downlink over real zenoh sessions in lockstep: one HazardUpdate heard by every
robot in range, metered once, resent until each robot in range acknowledged it; coalesced GCS
acks keep the uplink exactly-once under loss; the GCS sets the telemetry rate."""

from __future__ import annotations

from typing import Any

from protocol.clock import ManualClock
from protocol.link import Link, LinkConfig, RobotEndpoint
from protocol.loopback import LockstepRadio, free_loopback_port, unique_mission
from protocol.messages import (
    BROADCAST_ROBOT_ID,
    AutonomyMode,
    Direction,
    HazardUpdate,
    ParameterUpdate,
    PoseNode,
    RobotFrame,
    Telemetry,
    TerrainGrid,
)
from protocol.radio import RadioGrant


class _Team:
    def __init__(self, robots: list[int], seed: int = 3) -> None:
        self.clock = ManualClock(0.0)
        endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
        mission = unique_mission("bcast")
        self.ground_link = Link(
            LinkConfig(listen=(endpoint,), pump_period_s=0.0),
            mission=mission,
            clock=self.clock,
            seed=seed,
        )
        self.robot_link = Link(
            LinkConfig(listen=(), connect=(endpoint,), pump_period_s=0.0),
            mission=mission,
            clock=self.clock,
            seed=seed + 1,
        )
        self.up: dict[int, list[Any]] = {r: [] for r in robots}
        self.down: dict[int, list[Any]] = {r: [] for r in robots}
        self.ground = self.ground_link.gcs_endpoint(
            on_message=lambda rid, msg: self.up[rid].append(msg)
        )
        self.radios: dict[int, RobotEndpoint] = {
            r: self.robot_link.robot_endpoint(r, on_message=self.down[r].append) for r in robots
        }
        self.radio = LockstepRadio(self.ground_link, self.ground, [self.robot_link], self.radios)
        self.radio.wait_connected(10.0)

    def grant(self, rid: int, grant: RadioGrant) -> None:
        self.radios[rid].set_grant(grant)
        self.ground.set_grant(rid, grant)

    def step(self, dt_s: float = 0.1) -> None:
        self.clock.advance(dt_s)
        self.radio.exchange(10.0)

    def close(self) -> None:
        self.robot_link.close()
        self.ground_link.close()


def _update(t: float, robots: list[int]) -> HazardUpdate:
    return HazardUpdate(t, [], [RobotFrame(r, (r + 0.5, -1.0, 0.25)) for r in robots])


def test_one_broadcast_reaches_every_robot_in_range_and_is_metered_once() -> None:
    robots = [1, 2, 3, 4]
    team = _Team(robots)
    try:
        for r in robots:
            team.grant(r, RadioGrant(2000.0, 2000.0 if r != 4 else 0.0, 0.0))  # 4: out of range
        team.ground.broadcast(_update(0.0, robots))
        for _ in range(20):
            team.step()
        for r in (1, 2, 3):
            (got,) = [m for m in team.down[r] if isinstance(m, HazardUpdate)]
            assert [f.robot_id for f in got.frames] == robots
            assert got.frames[r - 1].map_from_odom == (r + 0.5, -1.0, 0.25)
        assert not any(isinstance(m, HazardUpdate) for m in team.down[4])
        snap = team.ground_link.meter.snapshot()
        sent = [(k, c) for k, c in snap.items() if k[2] == "hazard_broadcast"]
        assert [k for k, _ in sent] == [(BROADCAST_ROBOT_ID, Direction.DOWN, "hazard_broadcast")]
        assert sent[0][1].messages == 1
        assert not any(k[2] == "hazard_update" for k in snap)
        # the robots in range acknowledge the broadcast's sequence number
        for _ in range(100):
            team.step()
        assert team.ground.broadcast_channel.acknowledged_by("hazard_broadcast", 1) == [1, 2, 3]
        assert team.ground.broadcast_channel.stats.retransmitted == 0  # robot 4 is out of range
    finally:
        team.close()


def test_a_lost_broadcast_is_resent_until_every_robot_in_range_has_it() -> None:
    robots = [1, 2, 3, 4, 5, 6, 7, 8]
    team = _Team(robots, seed=11)
    try:
        for r in robots:
            team.grant(r, RadioGrant(4000.0, 2000.0, 0.6))
        team.ground.broadcast(_update(0.0, robots))
        for _ in range(1200):
            team.step()
            if all(any(isinstance(m, HazardUpdate) for m in team.down[r]) for r in robots):
                break
        for r in robots:
            assert sum(isinstance(m, HazardUpdate) for m in team.down[r]) == 1  # exactly once
        assert team.ground.broadcast_channel.stats.retransmitted >= 1
    finally:
        team.close()


def test_uplink_is_exactly_once_under_loss_with_coalesced_acks() -> None:
    robots = [0, 1, 2]
    team = _Team(robots, seed=5)
    try:
        for r in robots:
            team.grant(r, RadioGrant(3000.0, 600.0, 0.25))
        sent = {r: 0 for r in robots}
        t = 0.0
        for step in range(4000):
            t = team.clock.now()
            if step < 1500 and step % 12 == 0:
                for r in robots:
                    i = sent[r]
                    team.radios[r].send(
                        PoseNode(i, t, (i, 0, 0), (1, 0, 0), (1e-3, 0, 0, 1e-3, 0, 1e-4))
                    )
                    team.radios[r].send(TerrainGrid(i, 0.1, bytes([i % 251]) * 25))
                    sent[r] += 1
            if step % 20 == 0:
                team.ground.broadcast(_update(t, robots))
            team.step()
            if step > 1500 and all(
                sum(isinstance(m, PoseNode | TerrainGrid) for m in team.up[r]) == 2 * sent[r]
                for r in robots
            ):
                break
        for r in robots:
            nodes = [m.node_index for m in team.up[r] if isinstance(m, PoseNode)]
            grids = [m.node_index for m in team.up[r] if isinstance(m, TerrainGrid)]
            assert nodes == list(range(sent[r])) and grids == nodes
        snap = team.ground_link.meter.snapshot()
        assert any(k[2] == "ack_broadcast" for k in snap)
        assert not any(k[2] == "ack" and k[0] >= 0 for k in snap)  # no per-robot GCS acks
        up = team.robot_link.meter.snapshot()
        standalone = sum(c.messages for k, c in up.items() if k[2] == "ack")
        data = sum(c.messages for k, c in up.items() if k[2] != "ack")
        assert standalone < 0.1 * data  # robots' acks of broadcasts ride in their data
    finally:
        team.close()


def test_the_gcs_sets_the_telemetry_rate_and_the_node_never_sees_the_parameter() -> None:
    team = _Team([7])
    try:
        team.grant(7, RadioGrant(5000.0, 1000.0, 0.0))
        team.ground.send(7, ParameterUpdate("link.telemetry_period_s", 5.0))
        for step in range(300):  # 30 s, telemetry offered every second
            t = team.clock.now()
            if step % 10 == 0:
                team.radios[7].send(
                    Telemetry(t, (0, 0, 0), (0, 0), (0, 0), 1.0, AutonomyMode.IDLE, 0)
                )
            team.step()
        telemetry = [m for m in team.up[7] if isinstance(m, Telemetry)]
        assert 5 <= len(telemetry) <= 8, len(telemetry)
        assert not any(isinstance(m, ParameterUpdate) for m in team.down[7])
    finally:
        team.close()
