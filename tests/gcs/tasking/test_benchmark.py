"""The benchmark's synthetic mission plans for every robot (the timing itself is a bench)."""

from __future__ import annotations

from gcs.tasking.benchmark import synthetic_state, time_planning


def test_synthetic_mission_tasks_every_robot() -> None:
    st = synthetic_state(width_m=80.0, height_m=60.0, resolution_m=0.2, walk_m=80.0, seed=3)
    r = time_planning(st, repeats=1)
    assert r["tasks"] == 14.0
    assert r["full_plan_s"] > 0.0 and r["steady_plan_s"] > 0.0
