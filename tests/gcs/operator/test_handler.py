"""The operator command handler on a real GroundStation: tasks in each robot's private frame,
who controls which robot, approvals, reclassification, graph commands, subsets, suggestions."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.graph.pose_graph import PoseGraphConfig
from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.operator.grammar import CommandError, RobotFacts, parse_line, parse_subset
from gcs.operator.handler import CommandHandler, OperatorContext, RobotReport
from protocol.messages import (
    AutonomyMode,
    Detection,
    GoToTask,
    IdleTask,
    NeutralizeTask,
    ObjectKind,
    ParameterUpdate,
    PauseTask,
    RelayTask,
    ResumeTask,
    TaskState,
    TaskStatus,
    Telemetry,
)
from protocol.operator import OPERATOR_TASK_IDS_FROM
from protocol.se2 import transform_points
from tests.gcs.test_ground_station import nodes_along, straight

MAP_FROM_ODOM0 = (10.0, 5.0, math.pi / 2)


def _station() -> GroundStation:
    gs = GroundStation(GroundStationConfig(graph=PoseGraphConfig(map_from_odom=MAP_FROM_ODOM0)))
    for msg in nodes_along(straight(6)):
        gs.handle(0, msg, now_s=1.0)
    for msg in nodes_along(straight(4, heading=0.3)):
        gs.handle(1, msg, now_s=1.0)  # not linked to map
    gs.handle(
        0,
        Detection(1, 5, 5.0, ObjectKind.STATIC_OOI, (3.0, 0.0), (0.01, 0.0, 0.01), 0.3, 1.0, 0.9),
        now_s=5.0,
    )
    gs.step(now_s=6.0)
    return gs


def _ctx(gs: GroundStation, **kw: object) -> OperatorContext:
    tele = Telemetry(6.0, (2.5, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.8, AutonomyMode.AUTONOMOUS, 7)
    reports = {0: RobotReport(tele, None, 6.0), 1: RobotReport(None, None, 6.0)}
    return OperatorContext(station=gs, now_s=6.0, reports=reports, **kw)  # type: ignore[arg-type]


def test_goto_goes_out_in_the_robots_private_frame_and_holds_the_robot() -> None:
    gs = _station()
    h = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 100)
    out = h.handle(parse_line("goto 0 12 -3"), _ctx(gs))
    assert out.status == "ok" and out.interaction, out.text
    ((rid, task),) = out.downlink
    assert rid == 0 and isinstance(task, GoToTask) and task.task_id == OPERATOR_TASK_IDS_FROM + 100
    mfo = np.asarray(gs.graph.map_from_odom(0))
    back = transform_points(mfo, np.asarray([task.waypoints_in_odom[0]]))[0]
    np.testing.assert_allclose(back, (12.0, -3.0), atol=1e-3)
    assert h.held_robots() == {0} and h.control_of(0) == "operator"
    # robot 1 has no map_from_odom yet: failed, says why, not an interaction
    out = h.handle(parse_line("goto 1 0 0"), _ctx(gs))
    assert out.status == "failed" and "not linked" in out.text and not out.interaction
    assert len(h.interactions) == 1


def test_pause_resume_auto_and_who_controls() -> None:
    gs = _station()
    h = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 1)
    out = h.handle(parse_line("pause all"), _ctx(gs))
    assert [type(m) for _, m in out.downlink] == [PauseTask, PauseTask]
    assert "robot(s) 1 had no task" in out.text
    assert h.held_robots() == {0, 1} and h.control_of(1) == "paused"
    out = h.handle(parse_line("resume 0-1"), _ctx(gs))
    assert [type(m) for _, m in out.downlink] == [ResumeTask, ResumeTask]
    assert h.held_robots() == set()  # back to the planners: nobody had taken them before
    h.handle(parse_line("goto 0 1 1"), _ctx(gs))
    h.handle(parse_line("pause 0"), _ctx(gs))
    h.handle(parse_line("resume 0"), _ctx(gs))
    assert h.control_of(0) == "operator"  # still the operator's after its pause
    assignments = {0: "explore"}

    class Alloc:
        pass

    alloc = Alloc()
    alloc.assignments = assignments  # type: ignore[attr-defined]
    out = h.handle(parse_line("auto 0"), _ctx(gs, allocator=alloc))
    assert out.status == "ok" and h.held_robots() == set() and assignments == {}
    # robot 0 was on the operator's goal: it drops it now (autonomous again at once), rather
    # than driving on semi-autonomous until the planners' next task
    assert [(r, type(m)) for r, m in out.downlink] == [(0, IdleTask)]
    assert "operator goal dropped by robot(s) 0" in out.text
    again = h.handle(parse_line("auto 0"), _ctx(gs, allocator=alloc))
    assert again.downlink == []  # nothing of the operator's left to drop


def test_neutralize_needs_a_disruptor_and_a_static_ooi_then_approves() -> None:
    gs = _station()
    (hz,) = gs.hazards
    h = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 1)
    roles = {0: "disruptor", 1: "sensor"}
    out = h.handle(parse_line(f"neutralize {hz.hazard_id} 1"), _ctx(gs, roles=roles))
    assert out.status == "invalid" and "not a disruptor" in out.text and "disruptors: 0" in out.text
    out = h.handle(parse_line(f"neutralize {hz.hazard_id} 0"), _ctx(gs, roles=roles))
    assert out.status == "ok", out.text
    ((rid, task),) = out.downlink
    assert isinstance(task, NeutralizeTask) and task.approved and task.standoff_m >= 2.5
    mfo = np.asarray(gs.graph.map_from_odom(0))
    back = transform_points(mfo, np.asarray([task.target_in_odom]))
    np.testing.assert_allclose(back[0], hz.position_in_map, atol=1e-3)
    assert hz.hazard_id in h.approved_hazard_ids
    out = h.handle(parse_line("approve 99"), _ctx(gs))
    assert out.status == "invalid" and "unknown OOI id '99'" in out.text


def test_reclassify_relay_set_and_graph_commands() -> None:
    gs = _station()
    (hz,) = gs.hazards
    h = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 1)
    out = h.handle(parse_line(f"reclassify {hz.hazard_id} civilian"), _ctx(gs))
    assert out.status == "ok" and gs.hazards[0].kind == ObjectKind.CIVILIAN
    assert gs.hazards[0].radius_m == 0.0
    out = h.handle(parse_line("relay 0 20 4"), _ctx(gs))
    assert isinstance(out.downlink[0][1], RelayTask) and h.control_of(0) == "operator"
    out = h.handle(parse_line("set telemetry_period_s 0.5 0"), _ctx(gs))
    assert out.downlink == [(0, ParameterUpdate("link.telemetry_period_s", 0.5))]
    out = h.handle(parse_line("set codec nonsense 0"), _ctx(gs))
    assert out.status == "invalid" and "unknown codec 'nonsense'" in out.text
    assert not out.downlink and not out.interaction
    out = h.handle(parse_line("set codec magic4 0"), _ctx(gs))
    assert out.downlink == [(0, ParameterUpdate("codec", "magic4"))]
    out = h.handle(parse_line("set status_period_s 2"), _ctx(gs))
    assert out.status == "failed"  # no GCS-side setter given
    out = h.handle(parse_line("rewind -100"), _ctx(gs))
    assert out.status == "ok" and "removed 0" in out.text
    assert h.handle(parse_line("restart-loops"), _ctx(gs)).status == "ok"
    out = h.handle(parse_line("closure 0:1 0:4"), _ctx(gs))
    assert out.status == "failed" and "terrain grid" in out.text
    out = h.handle(parse_line("closure 7:1 0:4"), _ctx(gs))
    assert out.status == "invalid" and "robot id" in out.text
    before = len(gs.graph.edges())
    out = h.handle(parse_line("simplify"), _ctx(gs))
    assert out.status == "ok" and len(gs.graph.edges()) <= before
    status = h.handle(parse_line("status"), _ctx(gs))
    assert status.status == "ok" and not status.interaction
    assert "robot  0" in status.text and "OOI" in status.text


def test_subsets_and_suggestions() -> None:
    facts = {
        r: RobotFacts(r, "disruptor" if r >= 4 else "sensor", idle=r in (1, 5)) for r in range(6)
    }
    assert parse_subset("3", facts) == [3]
    assert parse_subset("2-4", facts) == [2, 3, 4]
    assert parse_subset("sensors", facts) == [0, 1, 2, 3]
    assert parse_subset("disruptors", facts) == [4, 5]
    assert parse_subset("idle", facts) == [1, 5]
    assert parse_subset("all", facts) == list(range(6))
    assert parse_subset("0,4-5, idle", facts) == [0, 1, 4, 5]
    with pytest.raises(CommandError, match="robot id '9'"):
        parse_subset("9", facts)
    with pytest.raises(CommandError, match="did you mean 'sensors'"):
        parse_subset("sensrs", facts)
    with pytest.raises(CommandError, match="backwards"):
        parse_subset("5-2", facts)
    with pytest.raises(CommandError, match="did you mean 'pause'"):
        parse_line("paus all")
    with pytest.raises(CommandError, match="missing X_M Y_M"):
        parse_line("goto 3")
    with pytest.raises(CommandError, match="expected a number"):
        parse_line("goto 3 a b")
    with pytest.raises(CommandError, match="did you mean 'civilian'"):
        parse_line("reclassify 2 civilan")


def test_goto_several_robots_spreads_them_around_the_point() -> None:
    gs = GroundStation(GroundStationConfig())
    gs.add_start_hint(1, map_from_odom=(0.0, 5.0, 0.5), sigma_xy_m=0.1, sigma_yaw_rad=0.01)
    for rid in (0, 1):
        for msg in nodes_along(straight(4)):
            gs.handle(rid, msg, now_s=1.0)
    gs.step(now_s=2.0)
    h = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 1)
    out = h.handle(parse_line("goto 0,1 10 10"), _ctx(gs))
    assert out.status == "ok" and "spread 1.5 m" in out.text, out.text
    goals = []
    for rid, task in out.downlink:
        mfo = np.asarray(gs.graph.map_from_odom(rid))
        goals.append(transform_points(mfo, np.asarray([task.waypoints_in_odom[0]]))[0])
    for g in goals:
        assert math.dist(g, (10.0, 10.0)) == pytest.approx(1.5, abs=1e-3)
    assert math.dist(goals[0], goals[1]) == pytest.approx(3.0, abs=1e-3)


def test_status_says_how_the_operators_task_stands() -> None:
    """The robot's report on the operator's task is in the status (not just "goto 12,-3")."""
    gs = _station()
    h = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 5)
    ctx = _ctx(gs)
    assert h.handle(parse_line("goto 0 12 -3"), ctx).status == "ok"
    assert "goto 12,-3 " in h.handle(parse_line("status 0"), ctx).text
    ctx.reports[0].status = TaskStatus(OPERATOR_TASK_IDS_FROM + 5, TaskState.SUCCEEDED, 9.0, "")
    assert "goto 12,-3: succeeded" in h.handle(parse_line("status 0"), ctx).text
    ctx.reports[0].status = TaskStatus(
        OPERATOR_TASK_IDS_FROM + 5, TaskState.FAILED, 9.0, "no path to the next waypoint"
    )
    text = h.task_text(0, ctx.reports[0], None)
    assert text == "goto 12,-3: failed (no path to the next waypoint)"
    assert h.handle(parse_line("auto 0"), ctx).status == "ok"
    assert h.task_text(0, ctx.reports[0], None) == "task 7"  # its telemetry's task


def test_a_handlers_decisions_survive_a_state_round_trip() -> None:
    """``state()`` -> JSON -> ``restore()`` (a GCS resumed from its journal): the same held,
    paused and operator-controlled robots, operator tasks, approvals, reclassifications,
    interactions and counts; task ids go on past the saved ones; a damaged state is refused
    naming what is wrong and changes nothing."""
    import json

    gs = _station()
    (hz,) = gs.hazards
    h = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 1)
    roles = {0: "disruptor", 1: "sensor"}
    for line in ("goto 0 12 -3", "pause 0-1", f"approve {hz.hazard_id}"):
        assert h.handle(parse_line(line), _ctx(gs, roles=roles)).status == "ok", line
    assert h.handle(parse_line(f"reclassify {hz.hazard_id} hostile"), _ctx(gs)).status == "ok"
    saved = json.loads(json.dumps(h.state()))
    again = CommandHandler(first_task_id=OPERATOR_TASK_IDS_FROM + 1)
    again.restore(saved)
    for name in ("operator_controlled", "paused", "approved_hazard_ids", "reclassified"):
        assert getattr(again, name) == getattr(h, name), name
    assert again.operator_tasks == h.operator_tasks and again.counts == h.counts
    assert again.interactions == h.interactions and len(again.interactions) == 4
    assert again.held_robots() == {0, 1} and again.control_of(0) == "paused"
    # resumed, robot 0 goes back to the operator's control (it had a goto before its pause)
    out = again.handle(parse_line("resume 0"), _ctx(gs))
    assert again.control_of(0) == "operator" and again.control_of(1) == "paused"
    assert out.task_ids[0] == h._next_id  # no task id of the killed GCS's used twice
    bad = dict(saved, paused=[1, 2])
    with pytest.raises(ValueError, match="operator handler state"):
        CommandHandler().restore(bad)
    fresh = CommandHandler()
    with pytest.raises(ValueError, match="next_task_id 5 is no operator id"):
        fresh.restore(dict(saved, next_task_id=5))
    assert fresh.paused == {} and fresh.interactions == []
