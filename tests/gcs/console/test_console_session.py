"""A scripted console session against a running mission over real zenoh: the small world's
robots and the real GCS (planners on) in lockstep, the operator service on the GCS's link, a
console on its own zenoh session. `pause all` stops every robot within 2 mission-seconds, `goto`
gets there, `resume` continues; forged and replayed commands are refused and told why; the
saved recording holds the map, robots, graph and events."""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest
from rerun.chunk import RrdReader

from gcs.console.repl import Console
from mission.bench.operator import operator_team
from protocol import operator as op

pytestmark = pytest.mark.slow


def _moved_m(truth: list[tuple[float, np.ndarray]], t0: float, t1: float) -> np.ndarray:
    """Each robot's largest distance from its pose at ``t0`` during [t0, t1] (mission s)."""
    rows = [p for t, p in truth if t0 <= t <= t1]
    assert len(rows) >= 2, f"no truth between {t0} and {t1}"
    start = rows[0][:, :2]
    return np.max([np.hypot(*(p[:, :2] - start).T) for p in rows], axis=0)


def _wait(pred, timeout_s: float) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_console_session_pause_goto_resume_and_refusals(tmp_path: Path) -> None:
    rrd = tmp_path / "ops.rrd"
    lines: list[str] = []
    with operator_team(views=[f"save {rrd}"]) as team:
        client = team.client
        assert client.wait_for_gcs(120.0), "the console never heard the GCS"
        console = Console(client, out=lines.append, reply_timeout_s=60.0, wait_s=60.0)
        # the planners drive the robots out; remember where robot 0 has been (GCS estimate)
        seen0: list[tuple[float, float]] = []
        t_end = team.now_s + 30.0
        while team.now_s < t_end:
            s = client.status
            row = next((r for r in s.robots if r.robot_id == 0), None) if s else None
            if row is not None and row.pose_in_map is not None:
                seen0.append(row.pose_in_map[:2])
            assert team.wait_mission_s(min(t_end, team.now_s + 1.0), timeout_s=120.0)
        t0 = team.now_s
        moving_before = _moved_m(team.ground.truth, t0 - 10.0, t0)
        assert np.any(moving_before > 0.5), f"nothing moved before the pause: {moving_before}"

        assert console.run_line("pause all"), lines[-3:]
        assert lines[-1].startswith("ok: pause sent to robot(s) 0,1,2,3")
        t_paused = team.now_s
        assert team.wait_mission_s(t_paused + 5.0)
        # from 2 mission-s after the command on, nobody moves (slack: wheel settling)
        still = _moved_m(team.ground.truth, t_paused + 2.0, t_paused + 5.0)
        assert np.all(still < 0.05), f"robots still moving after pause all: {still}"
        held = client.status
        assert held is not None and all(r.control == "paused" for r in held.robots)

        # goto: back to a place robot 0 has been (reachable), at least 2 m from where it is
        here = client.status.robots[0].pose_in_map  # type: ignore[union-attr]
        assert here is not None
        goal = max(seen0, key=lambda p: math.dist(p, here[:2]))
        assert math.dist(goal, here[:2]) > 1.0, (seen0, here)
        assert console.run_line(f"goto 0 {goal[0]:.2f} {goal[1]:.2f}"), lines[-3:]

        def arrived() -> bool:
            s = client.status
            p = s.robots[0].pose_in_map if s else None
            return p is not None and math.dist(p[:2], goal) < 1.0

        assert _wait(arrived, 240.0), f"robot 0 never reached {goal}: {client.status}"

        assert console.run_line("resume 1-3; auto 0"), lines[-4:]
        t_resumed = team.now_s
        assert team.wait_mission_s(t_resumed + 15.0, timeout_s=180.0)
        after = _moved_m(team.ground.truth, t_resumed, t_resumed + 15.0)
        assert np.any(after[1:] > 0.3), f"nobody continued after resume: {after}"

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
        assert any("forged" in line for line in team.service.refused_log)
        # unknown command and robot: a suggestion, not a traceback
        assert not console.run_line("paus all") and "did you mean 'pause'" in lines[-1]
        assert not console.run_line("pause 9") and "unknown robot id '9'" in lines[-1]
        interactions = len(team.service.handler.interactions)
        assert interactions == 4  # pause, goto, resume, auto: status and refusals do not count
        assert team.service.ledger.time_s.get("semi_autonomous", 0.0) > 0.0
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
