"""On-robot path planner (paper 5.4): the composition of configuration space, Dijkstra,
relaxation and smoothing over the fused terrain map.

Plan in two stages, as the paper argues (potential fields fail with a 15 s map memory):
first the minimum-*distance* path (:mod:`robot.planning.dijkstra`) through the configuration
space (:mod:`robot.planning.config_space`), then optimize it for clearance
(:mod:`robot.planning.path_relaxation`) and smoothness (:mod:`robot.planning.path_smoothing`).

Clearance as a cost, not a wall (``PlannerConfig.clearance_cost``): the configuration space
uses the robot's real radius, so a doorway barely wider than the robot stays open, and cells
closer to an obstacle than the comfort distance ``clearance_m`` cost more per metre, rising
linearly from 1 at ``clearance_m`` to ``1 + clearance_cost`` at ``robot_radius_m``. The first
stage then finds the path of least *cost*: of two ways around, it takes the roomy one unless
the tight one is clearly shorter (e.g. around a teammate rather than through the gap between
two of them), while a doorway with no alternative costs only its few extra metres. This is a
bounded, local term (it reaches ``clearance_m`` from obstacles only), not the potential field
the paper warns about: unknown cells never feel it, and relaxation then centres the path
where it is still tight. ``clearance_cost = 0`` gives the paper's pure minimum distance.

Unknown cells follow ``PlannerConfig.unknown``: ``"free"`` (drive through unseen terrain),
``"obstacle"`` (never), or ``"cost"`` (allowed, each metre costing ``unknown_cost`` metres, so
the path prefers seen terrain). The default is ``"free"``: a single sweep leaves most far
cells unknown between scan lines, so a cost makes paths weave along the observed rings, and
the robot re-plans with every sweep as it sees what it drives into. Unknown cells under the
robot itself (within ``robot_radius_m`` of the start, which the LIDAR cannot see) are always
free.

When no path exists the result says so (``status`` and ``reason``) with an empty path: the
robot node stops, waits for the map to change (the memory forgets old sweeps) and reports it.
Everything is in the terrain map's frame (``odom``), metres.

Cost (issue 14, session 13, thread CPU at load ~20): a plan over a 400 x 400 map about 6 ms,
of which the clearance field (a distance transform) 1.3 (plus as much on OpenCV's second
thread), Dijkstra with A* 2.4, configuration space 0.3, smoothing 0.6. The configuration
space and clearance field of the last obstacle grid are kept (:attr:`PathPlanner.field_reuses`
counts the reuses): a plan over the same obstacles reuses them, exactly (they are pure
functions of the grid). In the small world's first 60 s about one plan in ten was such a
repeat (the second plan to the nearest reachable cell, a robot that has not moved a cell).
In the 14-robot ``magic_phase`` (first 60 mission-s, seed 0, mean of two runs at load ~20,
reports identical) planning cost 3.9 -> 3.4 CPU-ms per robot-mission-s. Session 14 (issue 14):
the step costs are one compiled pass (clearance scaling and blocked cells, the same operations
in the same order as the numpy passes), the unknown-cell masks are built only for the
``obstacle`` and ``cost`` policies that read them: a plan over a 400 x 400 map with long paths
13.4 -> 10.8 ms; in the quick mission (small world, 300 mission-s, at 38fac2c, seeds 0 / 7,
one run each at load ~12, thread CPU, reports identical) planning took 6.78 / 5.64 -> 6.10 /
5.20 CPU-s (3436 / 1885 plans).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import msgspec
import numba as nb
import numpy as np
from numpy.typing import ArrayLike, NDArray

from robot.planning.config_space import configuration_space
from robot.planning.dijkstra import dijkstra_grid
from robot.planning.path_relaxation import clearance_field, path_clearance, relax_path
from robot.planning.path_smoothing import smooth_path
from robot.terrain.grid import OBSTACLE, UNKNOWN, GridGeometry

__all__ = ["PlanResult", "PlanStatus", "PathPlanner", "PlannerConfig"]

PlanStatus = Literal["ok", "no_path", "start_blocked", "goal_blocked"]


class PlannerConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``robot_radius_m``: disc enclosing the footprint (configuration space).
    ``clearance_m``: the clearance relaxation aims for (bounded: not more), and below which
    ``clearance_cost`` applies (see the module doc; 0: minimum distance).
    ``unknown``: policy for unknown cells; ``unknown_cost``: per-metre cost factor for
    ``"cost"``. ``relax_step_m``/``relax_iterations``/``max_offset_m``: relaxation;
    ``smooth_weight``/``smooth_iterations``: smoothing. ``astar``: order Dijkstra's heap with
    the octile distance to the goal (same path length, fewer cells expanded). ``escape``: a
    start inside the configuration-space margin (but not on an obstacle) may leave it, see
    :meth:`PathPlanner.plan`. ``goal_tolerance_m``: a goal inside the margin is replaced by the
    nearest free cell within this distance (0: report ``goal_blocked``)."""

    robot_radius_m: float = 0.4
    clearance_m: float = 0.7
    clearance_cost: float = 2.0
    unknown: Literal["free", "obstacle", "cost"] = "free"
    unknown_cost: float = 1.5
    relax_step_m: float = 0.025
    relax_iterations: int = 40
    max_offset_m: float = 0.6
    smooth_weight: float = 0.5
    smooth_iterations: int = 60
    astar: bool = True
    escape: bool = True
    goal_tolerance_m: float = 0.0

    def __post_init__(self) -> None:
        for name in (
            "robot_radius_m",
            "clearance_m",
            "clearance_cost",
            "max_offset_m",
            "goal_tolerance_m",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.unknown_cost) and self.unknown_cost >= 1):
            raise ValueError(f"unknown_cost must be >= 1, got {self.unknown_cost}")
        if not (math.isfinite(self.relax_step_m) and self.relax_step_m > 0):
            raise ValueError(f"relax_step_m must be > 0, got {self.relax_step_m}")
        if not 0 < self.smooth_weight <= 1:
            raise ValueError(f"smooth_weight must be in (0, 1], got {self.smooth_weight}")
        if self.relax_iterations < 0 or self.smooth_iterations < 0:
            raise ValueError("relax_iterations and smooth_iterations must be >= 0")


@dataclass(frozen=True)
class PlanResult:
    """``path_in_odom`` ``(K, 2)`` metres from start to goal (empty unless ``status == "ok"``);
    ``dijkstra_cells`` the minimum-distance path ``(row, col)`` before relaxation;
    ``dijkstra_length_m`` its cost-weighted length (``inf`` without a path); ``length_m`` the
    final polyline's length; ``min_clearance_m`` the smallest vertex clearance; ``reason``
    says why there is no path. ``escaped``: the start was inside the configuration-space
    margin and the path first leaves it; ``goal_in_odom``: the goal planned to (moved when
    ``goal_tolerance_m`` applied)."""

    status: PlanStatus
    path_in_odom: NDArray[np.float64]
    dijkstra_cells: NDArray[np.int64]
    dijkstra_length_m: float
    length_m: float
    min_clearance_m: float
    reason: str = ""
    escaped: bool = False
    goal_in_odom: tuple[float, float] | None = None

    @property
    def ok(self) -> bool:
        return self.status == "ok"


@nb.njit(cache=True, nogil=True)
def _finite_at_least_one(m: NDArray[np.float64]) -> bool:  # pragma: no cover - compiled
    """Whether every value of ``m`` is finite and ``>= 1`` (NaN is not)."""
    for v in m.ravel():
        if not (v >= 1.0 and v < np.inf):
            return False
    return True


@nb.njit(cache=True, nogil=True)
def _clearance_costs(
    cost: NDArray[np.float64],
    clearance: NDArray[np.float64],
    blocked: NDArray[np.bool_],
    clearance_m: float,
    clearance_cost: float,
    comfort_m: float,
    tight_on: bool,
) -> None:  # pragma: no cover - compiled (tested against the numpy passes it replaced)
    """In place, one pass: blocked cells ``inf``; with ``tight_on``, the others closer than
    ``clearance_m`` to an obstacle multiplied by ``1 + clearance_cost * min(1, (clearance_m -
    clearance) / comfort_m)``, the same operations in the same order as the numpy passes
    (``cost[tight] *= ...; cost[blocked] = inf``) they replace (no fused multiply-adds:
    numba's default): the same costs, bit for bit."""
    rows, cols = cost.shape
    for i in range(rows):
        for j in range(cols):
            if blocked[i, j]:
                cost[i, j] = np.inf
            elif tight_on and clearance[i, j] < clearance_m:
                t = (clearance_m - clearance[i, j]) / comfort_m
                cost[i, j] = cost[i, j] * (1.0 + clearance_cost * min(1.0, t))


def _xy(name: str, v: ArrayLike) -> NDArray[np.float64]:
    a = np.asarray(v, dtype=np.float64)
    if a.shape != (2,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected 2 finite numbers (x, y) in odom, got {v!r}")
    return a


class PathPlanner:
    """Plans over fused terrain maps (:class:`robot.terrain.map_fusion.TerrainMapFusion`)."""

    def __init__(self, config: PlannerConfig | None = None) -> None:
        self.config = config or PlannerConfig()
        # the last obstacle grid's configuration space and clearance field (both pure
        # functions of it): a replan over the same obstacles (the second plan to the nearest
        # reachable cell, a robot that has not moved a cell since the last sweep) reuses them
        self._fields: (
            tuple[NDArray[np.bool_], float, NDArray[np.bool_], NDArray[np.float64]] | None
        ) = None
        self.field_reuses = 0

    def _obstacle_fields(
        self, hard: NDArray[np.bool_], resolution_m: float
    ) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
        """``(configuration space, clearance field)`` of ``hard``, kept for the next call
        (the answers are never written to: only read by the plan, relaxation and smoothing)."""
        if self._fields is not None:
            last, last_res, blocked, clearance = self._fields
            if last_res == resolution_m and np.array_equal(last, hard):
                self.field_reuses += 1
                return blocked, clearance
        cfg = self.config
        blocked = configuration_space(
            hard, robot_radius_m=cfg.robot_radius_m, resolution_m=resolution_m
        )
        clearance = clearance_field(hard, resolution_m=resolution_m)
        self._fields = (hard.copy(), resolution_m, blocked, clearance)
        return blocked, clearance

    def plan(
        self,
        classes: NDArray[np.uint8],
        geometry: GridGeometry,
        start_in_odom: ArrayLike,
        goal_in_odom: ArrayLike,
        *,
        cost_multiplier: NDArray[np.floating] | None = None,
    ) -> PlanResult:
        """Plan from ``start_in_odom`` to ``goal_in_odom`` (``(x, y)`` m) over ``classes``
        (``uint8`` UNKNOWN/DRIVABLE/OBSTACLE laid out by ``geometry``).

        ``cost_multiplier``: optional per-cell step-cost factors ``>= 1`` on the same grid (e.g.
        AOJRF traversability learned from measured vs requested speed,
        ``robot.control.traversability``), multiplied into the unknown-cell cost. The first
        stage then finds the minimum-*cost* path; relaxation and smoothing are unchanged.

        Raises ValueError for bad input: wrong map shape or dtype, class values out of range,
        non-finite or off-map start/goal (the caller clips far goals to the map).

        Escape (``config.escape``): odometry drift or a newly seen obstacle can put the robot
        within ``robot_radius_m`` of an obstacle, i.e. inside the configuration-space margin
        where no path starts. Rather than wait for the map memory to forget (which never
        happens for a real doorway jamb), the cells of the margin within ``robot_radius_m`` of
        the start whose clearance is at least the start's become passable: the robot may
        leave the margin but never gets closer to an obstacle than it already is. A start on
        an obstacle cell (clearance 0) is ``start_blocked``.
        """
        cfg = self.config
        cls = np.asarray(classes)
        if cls.shape != geometry.shape:
            raise ValueError(f"classes: shape {cls.shape} does not match geometry {geometry.shape}")
        if cls.dtype != np.uint8:
            raise ValueError(f"classes: expected dtype uint8, got {cls.dtype}")
        if cls.size and int(cls.max()) > OBSTACLE:
            raise ValueError(f"classes: values must be 0, 1 or 2, got {int(cls.max())}")
        start = _xy("start_in_odom", start_in_odom)
        goal = _xy("goal_in_odom", goal_in_odom)
        x0, y0 = geometry.origin_m
        x1 = x0 + geometry.cols * geometry.resolution_m
        y1 = y0 + geometry.rows * geometry.resolution_m
        for name, p in (("start_in_odom", start), ("goal_in_odom", goal)):
            if not geometry.contains(p):
                raise ValueError(
                    f"{name} ({p[0]:.3f}, {p[1]:.3f}) is outside the map "
                    f"x [{x0:.3f}, {x1:.3f}) y [{y0:.3f}, {y1:.3f})"
                )
        s_rc = geometry.cell_index(start)
        g_rc = geometry.cell_index(goal)
        res = geometry.resolution_m

        reach2 = (cfg.robot_radius_m / res) ** 2 + 1e-9  # the same disc as the C-space kernel
        # the disc is tested only in its bounding window (the rest of the map is outside it)
        k = int(math.floor(math.sqrt(reach2))) + 1
        r_lo, r_hi = max(0, s_rc[0] - k), min(geometry.rows, s_rc[0] + k + 1)
        c_lo, c_hi = max(0, s_rc[1] - k), min(geometry.cols, s_rc[1] + k + 1)

        def under_robot() -> NDArray[np.bool_]:
            rr, cc = np.ogrid[r_lo:r_hi, c_lo:c_hi]
            out = np.zeros(geometry.shape, dtype=bool)
            out[r_lo:r_hi, c_lo:c_hi] = (rr - s_rc[0]) ** 2 + (cc - s_rc[1]) ** 2 <= reach2
            return out

        # unknown cells count only under the "obstacle" and "cost" policies ("free": as drivable)
        unknown = (cls == UNKNOWN) & ~under_robot() if cfg.unknown != "free" else None
        obstacle = cls == OBSTACLE
        hard = obstacle | unknown if unknown is not None and cfg.unknown == "obstacle" else obstacle
        blocked, clearance = self._obstacle_fields(hard, res)
        if cost_multiplier is not None:
            m = np.asarray(cost_multiplier, dtype=np.float64)
            if m.shape != geometry.shape:
                raise ValueError(
                    f"cost_multiplier: shape {m.shape} does not match geometry {geometry.shape}"
                )
            if not _finite_at_least_one(m):
                raise ValueError("cost_multiplier: values must be finite and >= 1")
            cost = m.copy()  # 1 * m, without the pass
        else:
            cost = np.ones(geometry.shape)
        if unknown is not None and cfg.unknown == "cost":
            cost[unknown] *= cfg.unknown_cost
        comfort = cfg.clearance_m - cfg.robot_radius_m
        _clearance_costs(
            cost,
            clearance,
            blocked,
            cfg.clearance_m,
            cfg.clearance_cost,
            comfort,
            cfg.clearance_cost > 0 and comfort > 0,
        )

        def fail(status: PlanStatus, reason: str) -> PlanResult:
            empty = np.empty((0, 2))
            return PlanResult(
                status, empty, empty.astype(np.int64), math.inf, math.inf, 0.0, reason
            )

        escaped = False
        if blocked[s_rc]:
            start_clearance = float(clearance[s_rc])
            if not (cfg.escape and start_clearance > 0.0):
                return fail(
                    "start_blocked",
                    f"start cell {s_rc} is within robot_radius_m ({cfg.robot_radius_m} m) of an "
                    f"obstacle (clearance {start_clearance:.3f} m)",
                )
            exit_cells = blocked & under_robot() & (clearance >= start_clearance - 1e-9)
            cost[exit_cells] = 1.0 if cost_multiplier is None else cost_multiplier[exit_cells]
            escaped = True
        if blocked[g_rc]:
            snapped = self._snap_goal(blocked, g_rc, cfg.goal_tolerance_m / res)
            if snapped is None:
                return fail(
                    "goal_blocked",
                    f"goal cell {g_rc} is within robot_radius_m ({cfg.robot_radius_m} m) of an "
                    f"obstacle and no free cell is within goal_tolerance_m "
                    f"({cfg.goal_tolerance_m} m)",
                )
            g_rc = snapped
            goal = geometry.center_of(g_rc)
        found = dijkstra_grid(cost, s_rc, g_rc, resolution_m=res, astar=cfg.astar)
        if not found.found:
            return fail("no_path", "no path from start to goal through configuration space")

        path = found.path_cells.astype(np.float64)
        path = relax_path(
            path,
            clearance,
            blocked,
            resolution_m=res,
            target_clearance_m=cfg.clearance_m,
            step_m=cfg.relax_step_m,
            max_offset_m=cfg.max_offset_m,
            iterations=cfg.relax_iterations,
        )
        path = smooth_path(
            path,
            clearance,
            blocked,
            target_clearance_m=cfg.clearance_m,
            weight=cfg.smooth_weight,
            iterations=cfg.smooth_iterations,
        )
        xy = geometry.center_of(path)
        xy[0], xy[-1] = start, goal
        length = float(np.sum(np.hypot(*np.diff(xy, axis=0).T))) if len(xy) > 1 else 0.0
        return PlanResult(
            "ok",
            xy,
            found.path_cells,
            found.length_m,
            length,
            float(path_clearance(path, clearance).min()),
            "",
            escaped,
            (float(goal[0]), float(goal[1])),
        )

    @staticmethod
    def _snap_goal(
        blocked: NDArray[np.bool_], goal: tuple[int, int], radius_cells: float
    ) -> tuple[int, int] | None:
        """The free cell nearest to ``goal`` within ``radius_cells``, or None."""
        k = int(math.floor(radius_cells))
        if k < 1:
            return None
        r0, c0 = max(0, goal[0] - k), max(0, goal[1] - k)
        window = blocked[r0 : goal[0] + k + 1, c0 : goal[1] + k + 1]
        rr, cc = np.nonzero(~window)
        if len(rr) == 0:
            return None
        d2 = (rr + r0 - goal[0]) ** 2 + (cc + c0 - goal[1]) ** 2
        best = int(np.argmin(d2))
        if d2[best] > radius_cells**2 + 1e-9:
            return None
        return int(rr[best] + r0), int(cc[best] + c0)
