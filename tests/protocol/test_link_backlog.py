"""A robot's uplink backlog through its endpoint, over real zenoh: what a robot back in
contact waits for before it drives on (robot.comms_watchdog's drain hold)."""

from __future__ import annotations

from protocol.loopback import LockstepPair
from protocol.messages import TaskState, TaskStatus
from protocol.radio import RadioGrant


def test_the_backlog_builds_while_dead_and_is_gone_soon_after_the_grant_returns() -> None:
    dead = RadioGrant(uplink_bps=0.0, downlink_bps=0.0, loss=0.3)
    lossy = RadioGrant(uplink_bps=9600.0, downlink_bps=9600.0, loss=0.3)
    with LockstepPair.open(robot_id=5, seed=3) as pair:
        pair.robot.set_grant(dead)
        pair.gcs.set_grant(5, dead)
        for i in range(40):
            pair.robot.send(TaskStatus(i, TaskState.ACTIVE, float(i)))
            pair.step(0.05)
        queued = pair.robot.backlog_bytes()
        assert queued == pair.robot.channel.backlog_bytes() > 40 * 10
        pair.robot.set_grant(lossy)
        pair.gcs.set_grant(5, lossy)
        steps = 0
        while pair.robot.backlog_bytes() and steps < 200:
            pair.step(0.05)
            steps += 1
        # ~1 kB at 9600 bps: under a second of mission time, lost ones resent or not
        assert pair.robot.backlog_bytes() == 0 and steps * 0.05 <= 2.0, steps
