"""Planning time of :class:`~gcs.tasking.allocator.TaskAllocator` on a MAGIC-sized mission.

:func:`synthetic_state` builds a partly explored 220 x 160 m site (random buildings, 14 robots
that have driven random walks from a common start, the known map the union of 7.5 m discs
around their poses), and :func:`time_planning` reports the median wall time of a full plan
(every sensor robot needs a goal: the worst case) and of a steady step (robots under way).
``python -m gcs.tasking.benchmark`` prints both for 0.1 and 0.2 m cells. A ``magic bench``
suite can call :func:`time_planning` directly.
"""

from __future__ import annotations

import math
import statistics
import time

import numpy as np
from scipy import ndimage

from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from gcs.tasking.allocator import RobotInfo, Role, TaskAllocator, TaskingConfig, TaskingState
from protocol.messages import Hazard, ObjectKind

__all__ = ["synthetic_state", "time_planning"]


def synthetic_state(
    *,
    width_m: float = 220.0,
    height_m: float = 160.0,
    resolution_m: float = 0.1,
    robots: int = 14,
    disruptors: int = 4,
    walk_m: float = 250.0,
    seed: int = 0,
) -> TaskingState:
    """A partly explored site (see the module docstring); robots ``robots - disruptors``
    onward are disruptors."""
    rng = np.random.default_rng(seed)
    rows, cols = int(height_m / resolution_m), int(width_m / resolution_m)
    building = np.zeros((rows, cols), dtype=bool)
    for _ in range(int(width_m * height_m / 600)):
        w, h = rng.uniform(4, 18, 2)
        x, y = rng.uniform(0, width_m - w), rng.uniform(0, height_m - h)
        if math.hypot(x - 20, y - 20) < 25:
            continue  # keep the start area clear
        building[
            int(y / resolution_m) : int((y + h) / resolution_m),
            int(x / resolution_m) : int((x + w) / resolution_m),
        ] = True

    def blocked(p: np.ndarray) -> bool:
        c, r = int(p[0] / resolution_m), int(p[1] / resolution_m)
        return not (0 <= r < rows and 0 <= c < cols) or bool(building[r, c])

    ids, keys, xys = [], [], []
    key = 0
    for rid in range(1, robots + 1):
        p = np.array([20.0 + rng.uniform(-3, 3), 20.0 + rng.uniform(-3, 3)])
        yaw = rng.uniform(-math.pi, math.pi)
        length = walk_m if rid <= robots - disruptors else walk_m / 5
        for _ in range(int(length)):
            yaw += rng.normal(0, 0.25)
            nxt = p + [math.cos(yaw), math.sin(yaw)]
            if blocked(nxt):
                yaw += math.pi / 2
                continue
            p = nxt
            ids.append(rid)
            keys.append(key)
            xys.append(p.copy())
            key += 1
    xy = np.asarray(xys)
    seen = np.zeros((rows, cols), dtype=bool)
    cells = (xy / resolution_m).astype(int)
    seen[cells[:, 1], cells[:, 0]] = True
    # 7.5 m sensor discs around the poses, on a 4x coarser grid to keep the setup cheap
    f = 4
    small = seen.reshape(rows // f, f, cols // f, f).any(axis=(1, 3))
    near = ndimage.distance_transform_edt(~small) * resolution_m * f <= 7.5
    known = np.repeat(np.repeat(near, f, axis=0), f, axis=1)
    values = np.full((rows, cols), UNKNOWN, dtype=np.int8)
    values[known] = FREE
    values[known & building] = OCCUPIED
    last: dict[int, np.ndarray] = {}
    for rid, p in zip(ids, xy, strict=True):
        last[rid] = p
    infos = [
        RobotInfo(
            rid,
            Role.SENSOR if rid <= robots - disruptors else Role.DISRUPTOR,
            (float(last[rid][0]), float(last[rid][1]), 0.0),
            (0.3, -0.2, 0.05),
            0.0,
        )
        for rid in sorted(last)
    ]
    oois = [xy[len(xy) // 3] + [3.0, 0.0], xy[2 * len(xy) // 3] + [0.0, 3.0]]
    hazards = [
        Hazard(i + 1, ObjectKind.STATIC_OOI, (float(o[0]), float(o[1])), 2.5)
        for i, o in enumerate(oois)
    ]
    return TaskingState(
        OccupancyMap(values, (0.0, 0.0), resolution_m),
        infos,
        hazards=hazards,
        trajectory_robot_ids=np.asarray(ids, dtype=np.int64),
        trajectory_keys=np.asarray(keys, dtype=np.int64),
        trajectory_xy_in_map=xy,
    )


def time_planning(
    state: TaskingState, *, repeats: int = 5, config: TaskingConfig | None = None
) -> dict[str, float]:
    """Median wall seconds of a full plan (fresh allocator) and of a steady step, plus the
    number of tasks the full plan issued."""
    TaskAllocator(config).plan(state, now_s=0.0)  # compile the numba kernels
    full, steady = [], []
    issued = 0
    for _ in range(repeats):
        alloc = TaskAllocator(config)
        t0 = time.perf_counter()
        out = alloc.plan(state, now_s=0.0)
        full.append(time.perf_counter() - t0)
        issued = len(out)
        t0 = time.perf_counter()
        alloc.plan(state, now_s=1.0)
        steady.append(time.perf_counter() - t0)
    return {
        "full_plan_s": statistics.median(full),
        "steady_plan_s": statistics.median(steady),
        "tasks": float(issued),
    }


if __name__ == "__main__":
    for res in (0.1, 0.2):
        st = synthetic_state(resolution_m=res)
        known = float((st.occupancy.values != UNKNOWN).mean())
        r = time_planning(st)
        print(
            f"220x160 m at {res} m cells ({known:.0%} known), 14 robots: "
            f"full plan {r['full_plan_s'] * 1e3:.0f} ms, "
            f"steady step {r['steady_plan_s'] * 1e3:.0f} ms, {r['tasks']:.0f} tasks"
        )
