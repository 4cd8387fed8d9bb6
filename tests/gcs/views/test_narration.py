"""SAGE narration rules (paper 6.4.2) on constructed states."""

from __future__ import annotations

import numpy as np

from gcs.views.narration import EventKind, NarrationConfig, Narrator
from gcs.views.operator_picture import ObjectSighting, RobotStatus


def obj(oid: int, kind: str, xy: tuple[float, float]) -> ObjectSighting:
    return ObjectSighting(oid, kind, xy, 0.0, 0.0, 1, 3, 0.9)


def row(
    rid: int, *, task: str = "explore", age: float = 0.0, xy: tuple[float, float] = (0.0, 0.0)
) -> RobotStatus:
    return RobotStatus(
        robot_id=rid,
        pose_in_map=np.array([xy[0], xy[1], 0.0]),
        linked=True,
        mode="autonomous",
        task=task,
        task_kind=task.split()[0],
        battery_frac=1.0,
        last_message_s=0.0,
        last_message_age_s=age,
        active_s=100.0,
        uplink_bps=500.0,
        nodes=1,
        stuck=False,
        deadlock=False,
        trail_in_map=np.zeros((0, 2)),
        goal_in_map=np.array([xy[0] + 4.0, xy[1]]),
    )


def test_new_objects_once_dangerous_first_and_merged_when_close() -> None:
    n = Narrator()
    ev = n.update([], [obj(1, "toxic_vat", (0, 0)), obj(2, "static_ooi", (100, 0))], 1.0)
    assert [(e.kind, e.severity) for e in ev] == [
        (EventKind.NEW_OBJECT, 1),
        (EventKind.NEW_OBJECT, 3),
    ]
    assert n.update([], [obj(1, "toxic_vat", (0, 0)), obj(2, "static_ooi", (100, 0))], 2.0) == []
    # a third object 5 m from the first merges into its event; the zoom box covers both
    ev = n.update([], [obj(3, "toxic_vat", (5, 0))], 3.0)
    assert len(n.events) == 2 and ev[0].count == 2
    assert ev[0].zoom_center_in_map == (2.5, 0.0) and ev[0].zoom_half_m >= 5.5
    assert n.top(3.0)[0].subject == "object 2"  # dangerous ranks first


def test_neutralization_started_and_finished() -> None:
    n = Narrator()
    assert n.update([row(1)], [], 0.0) == []
    ev = n.update([row(1, task="neutralize 2", xy=(3, 4))], [], 1.0)
    assert [e.kind for e in ev] == [EventKind.NEUTRALIZATION_STARTED]
    assert ev[0].robot_id == 1 and ev[0].zoom_center_in_map == (5.0, 4.0)
    ev = n.update([row(1, task="explore")], [], 2.0)
    assert [e.kind for e in ev] == [EventKind.NEUTRALIZATION_FINISHED]


def test_civilian_inside_blast_ring_only() -> None:
    n = Narrator()
    objs = [
        obj(1, "static_ooi", (0, 0)),
        obj(2, "hostile", (100, 0)),
        obj(3, "civilian", (9, 0)),
        obj(4, "civilian", (106, 0)),
    ]
    ev = n.update([], objs, 0.0)
    near = [e for e in ev if e.kind is EventKind.CIVILIAN_NEAR_DANGER]
    assert [e.subject for e in near] == ["object 1/3"]  # 9 m < 10 m; 6 m > 5 m (hostile)
    assert near[0].severity == 3
    assert not [e for e in n.update([], objs, 1.0) if e.kind is EventKind.CIVILIAN_NEAR_DANGER]


def test_outage_then_lost_once_per_episode() -> None:
    n = Narrator(NarrationConfig(outage_s=10.0, lost_s=60.0, merge_window_s=1.0))
    assert [e.kind for e in n.update([row(1, age=11.0)], [], 11.0)] == [EventKind.LINK_OUTAGE]
    assert n.update([row(1, age=30.0)], [], 30.0) == []
    assert [e.kind for e in n.update([row(1, age=61.0)], [], 61.0)] == [EventKind.ROBOT_LOST]
    assert n.update([row(1, age=0.0)], [], 62.0) == []
    assert [e.kind for e in n.update([row(1, age=12.0)], [], 80.0)] == [EventKind.LINK_OUTAGE]


def test_top_four_by_aged_priority_and_expiry() -> None:
    n = Narrator(NarrationConfig(merge_m=1.0))
    objs = [obj(i, "toxic_vat", (50.0 * i, 0)) for i in range(1, 6)]
    n.update([], objs, 0.0)
    n.update([], [*objs, obj(9, "static_ooi", (0, 500))], 30.0)
    top = n.top(30.0)
    assert len(top) == 4 and top[0].subject == "object 9"
    # the others are equal in severity and age: the oldest ids lose the tie-break last
    assert [e.subject for e in top[1:]] == ["object 1", "object 2", "object 3"]
    n.update([], [], 1000.0)  # 3 x ttl (60 s) later every event is gone
    assert n.events == [] and n.top(1000.0) == []
