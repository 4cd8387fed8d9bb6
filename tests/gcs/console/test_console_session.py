"""A scripted console session against a running mission over real zenoh: the small world's
robots and the real GCS (planners on) in lockstep, the operator service on the GCS's ground
side as in ``magic run``, a console on its own zenoh session. `pause all` stops every robot
within 2 mission-seconds, `goto` gets there (the robot reporting itself semi-autonomous on
the way), `resume` continues; forged and replayed commands are refused and told why; the
saved recording holds the map, robots, graph and events.

Every wait is on state (the GCS's status, the robots' reports, the true poses) and bounded in
mission seconds, and the mission holds while a command is on its way to the GCS
(:func:`mission.bench.operator.operator_team`): it runs as fast as the machine lets it, so a
loaded machine makes the test slower, not different. ``WALL_GUARD_S`` only stops a hung run."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from gcs.console.repl import Console
from mission.bench.operator import OperatorTeam, operator_team
from protocol import operator as op
from protocol.messages import TaskState

pytestmark = pytest.mark.slow

WALL_GUARD_S = 900.0  # a hung mission, not a slow one (a slow one is bounded in mission s)


def _moved_m(truth: list[tuple[float, np.ndarray]], t0: float, t1: float) -> np.ndarray:
    """Each robot's largest distance from its pose at ``t0`` during [t0, t1] (mission s)."""
    rows = [p for t, p in list(truth) if t0 <= t <= t1]
    assert len(rows) >= 2, f"no truth between {t0} and {t1}"
    start = rows[0][:, :2]
    return np.max([np.hypot(*(p[:, :2] - start).T) for p in rows], axis=0)


def _until(team: OperatorTeam, pred: Callable[[], bool], *, by_mission_s: float) -> bool:
    """Wait for ``pred`` while the mission runs, until mission time ``by_mission_s``. The
    mission runs on in its own thread while the console's status comes over zenoh, so on a
    loaded machine the status can trail the mission: the verdict waits for a status stamped
    ``by_mission_s`` or later (within the wall guard), not judging one from before it."""
    deadline = time.monotonic() + WALL_GUARD_S
    while not pred():
        if team.error:
            raise RuntimeError("the mission thread failed") from team.error[0]
        status = team.client.status
        if team.now_s >= by_mission_s and status is not None and status.time_s >= by_mission_s:
            return pred()
        heard = "none" if status is None else f"{status.time_s:.1f} s"
        assert time.monotonic() < deadline, (
            f"mission at {team.now_s:.1f} s, status at {heard} (wanted {by_mission_s:.1f} s)"
        )
        time.sleep(0.02)
    return True


def _row(team: OperatorTeam, rid: int) -> op.RobotRow | None:
    s = team.client.status
    return next((r for r in s.robots if r.robot_id == rid), None) if s else None


@pytest.mark.timeout(1500)  # minutes of mission under a shared machine
def test_console_session_pause_goto_resume_and_refusals(tmp_path: Path) -> None:
    rrd = tmp_path / "ops.rrd"
    lines: list[str] = []
    with operator_team(views=[f"save {rrd}"]) as team:
        client = team.client
        service = team.service
        assert _until(team, lambda: client.connected, by_mission_s=10.0), "no GCS status"
        console = Console(client, out=lines.append, reply_timeout_s=60.0, wait_s=60.0)
        # the planners drive the robots out; where robot 0 has been (the GCS's estimate)
        seen0: list[tuple[float, float]] = []

        def note0() -> bool:
            row = _row(team, 0)
            if row is not None and row.pose_in_map is not None:
                if not seen0 or math.dist(seen0[-1], row.pose_in_map[:2]) > 0.2:
                    seen0.append(row.pose_in_map[:2])
            return False

        _until(team, note0, by_mission_s=30.0)
        t0 = team.now_s
        moving_before = _moved_m(team.ground.truth, t0 - 10.0, t0)
        assert np.any(moving_before > 0.5), f"nothing moved before the pause: {moving_before}"

        # pause all: from 2 mission-s after the command left the console, nobody moves
        t_sent = team.now_s
        assert console.run_line("pause all"), lines[-3:]
        assert lines[-1].startswith("ok: pause sent to robot(s) 0,1,2,3"), lines[-1]
        # every robot says so (one with no task to pause stands idle), within the 2 mission-s
        # and a telemetry period (1 s) to hear it
        assert _until(
            team,
            lambda: all(r.mode in ("paused", "idle") for r in client.status.robots),  # type: ignore[union-attr]
            by_mission_s=t_sent + 3.5,
        ), f"not every robot reports paused: {client.status}"
        assert team.wait_mission_s(t_sent + 5.0, timeout_s=WALL_GUARD_S)
        still = _moved_m(team.ground.truth, t_sent + 2.0, t_sent + 5.0)
        assert np.all(still < 0.05), f"robots still moving after pause all: {still}"
        assert all(r.control == "paused" for r in client.status.robots)  # type: ignore[union-attr]

        # goto: back to a place robot 0 has been (reachable), 2 m or more from where it is
        # and from every (paused) teammate, which could stand in its way
        here = _row(team, 0).pose_in_map  # type: ignore[union-attr]
        others = [r.pose_in_map[:2] for r in client.status.robots if r.robot_id != 0]  # type: ignore[union-attr,index]
        free = [p for p in seen0 if all(math.dist(p, o) > 2.0 for o in others)]
        assert here is not None and free, (seen0, others)
        goal = max(free, key=lambda p: math.dist(p, here[:2]))
        assert math.dist(goal, here[:2]) > 2.0, (seen0, here)
        assert console.run_line(f"goto 0 {goal[0]:.2f} {goal[1]:.2f}"), lines[-3:]
        t_goto = team.now_s
        task_id = service.handler.operator_tasks[0][0]
        assert _until(
            team,
            lambda: getattr(_row(team, 0), "mode", "") == "semi_autonomous",
            by_mission_s=t_goto + 5.0,
        ), f"robot 0 on the operator's goto reports {_row(team, 0)}"

        def arrived() -> bool:
            st = service.reports[0].status
            return st is not None and st.task_id == task_id and st.state is TaskState.SUCCEEDED

        assert _until(team, arrived, by_mission_s=t_goto + 120.0), (
            f"robot 0 did not reach {goal} in 120 mission-s: {service.reports[0].status}"
        )

        # the status row follows telemetry (a period behind the task's success): wait for
        # the row that shows where the robot stopped
        def near_goal() -> bool:
            row = _row(team, 0)
            pose = None if row is None else row.pose_in_map
            return pose is not None and math.dist(pose[:2], goal) < 1.5

        assert _until(team, near_goal, by_mission_s=team.now_s + 5.0), (_row(team, 0), goal)

        assert console.run_line("resume 1-3; auto 0"), lines[-4:]
        t_resumed = team.now_s

        def continued() -> bool:
            if team.now_s < t_resumed + 1.0:
                return False
            return bool(np.any(_moved_m(team.ground.truth, t_resumed, team.now_s)[1:] > 0.3))

        assert _until(team, continued, by_mission_s=t_resumed + 20.0), "nobody went on"

        # refusals over the same zenoh path, each told why
        forged = op.sign(
            bytes(32), client.mission, "bench", client.seq.next(), op.Command("pause", "all")
        )
        reply = client.send_raw(forged, timeout_s=30.0)
        assert reply is not None and (reply.status, reply.reason) == ("refused", "forged")
        genuine = client.signed(op.Command("status"))
        assert client.send_raw(genuine, timeout_s=30.0).status == "ok"  # type: ignore[union-attr]
        again = client.send_raw(genuine, timeout_s=30.0)
        assert again is not None and (again.status, again.reason) == ("refused", "replayed")
        unsigned = op.SignedCommand(1, "bench", client.seq.next(), op.Command("pause", "all"))
        reply = client.send_raw(unsigned, timeout_s=30.0)
        assert reply is not None and reply.reason == "unsigned"
        assert any("forged" in line for line in service.refused_log)
        # unknown command and robot: a suggestion, not a traceback
        assert not console.run_line("paus all") and "did you mean 'pause'" in lines[-1]
        assert not console.run_line("pause 9") and "unknown robot id '9'" in lines[-1]
        # pause, goto, resume, auto: status and refusals are no interactions
        assert len(service.handler.interactions) == 4
        assert service.ledger.time_s.get("semi_autonomous", 0.0) > 0.0
        assert service.ledger.distance_m.get("semi_autonomous", 0.0) > 1.0
    reader = RrdReader(rrd)
    entities = {c.entity_path for c in reader.stream() if c.num_rows}
    for entity in (
        "/world/map",
        "/world/robots",
        "/world/graph/odometry",
        "/sage/log",
        "/dashboard/table",
    ):
        assert entity in entities, f"{entity} missing from {sorted(entities)}"
