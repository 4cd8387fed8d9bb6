"""Backing away from a hostile that comes close, on the robot (MAGIC rules, paper 2 and 5.1.3).

A hostile (mobile OOI) detonates when a robot comes within 2.5 m of it and destroys every
robot within 5 m. The planner keeps a driving robot's paths out of the hostile's keep-out disk
(:mod:`robot.control.keepout`), but a robot that holds still (a watcher at its view position,
an idle robot, a robot waiting for a path or for its link) does not move, and a hostile
walking its route comes to it (small world seed 0: a hostile walked onto the robot watching
it, 6.5 m off 7 s before, and its blast took a second robot 4 m away). Here the robot moves
away on its own, without waiting for the GCS (whose picture of a walker is seconds old):

* :func:`hostile_threat`: the nearest distance from the robot to any hostile, each where it
  will be ``lookahead_s`` from now along its velocity (a walker coming closer counts early,
  one walking past does not); a threat when below ``blast_radius_m + margin_m``. The evasion
  lasts until every hostile is beyond that plus ``release_m`` (no dithering at the edge).
* :func:`evasion_goal`: the reachable drivable cell, nearest by path from the robot, that is
  ``blast_radius_m + clear_m`` from every hostile's way over the next ``predict_s`` (the
  segment from where it is along its velocity: a walker keeps walking, and a goal a few
  metres ahead of it on its way only puts off the next evasion, as the first version did:
  robot lost); none such in the map: the reachable cell farthest from those ways.

Pure functions over numpy arrays in the robot's ``odom`` frame, metres and seconds; hostiles
are rows ``(x_m, y_m, vx_m_s, vy_m_s)`` (zero velocity when unknown: the GCS's hazards).
"""

from __future__ import annotations

import math

import msgspec
import numpy as np
from numpy.typing import NDArray

from robot.planning.config_space import configuration_space
from robot.planning.dijkstra import dijkstra_grid
from robot.terrain.grid import DRIVABLE, OBSTACLE, GridGeometry

__all__ = ["EvasionConfig", "evasion_goal", "hostile_threat", "way_clearance_m"]


class EvasionConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """See the module docstring. ``blast_radius_m``: the rules' hostile blast (5 m; its
    trigger is 2.5 m); ``margin_m``: a threat within blast + margin (the keep-out disk's own
    margin: a watcher the GCS places 6 m off a still hostile is not one); ``release_m``: the
    evasion ends beyond blast + margin + release; ``clear_m``: the goal's distance beyond the
    blast radius; ``predict_s``: how far ahead a hostile's walk is extrapolated for the goal;
    ``unknown_cost``: per-metre cost of unknown cells on the way (drivable ones cost 1);
    ``memory_s``: a hostile track the robot lost is carried on along its velocity this long
    (the robot node's memory: behind the robot it is in the LIDAR's blind quarter);
    ``return_tolerance_m``/``return_timeout_s``: a robot that backed away from where it
    held (a relay, a stand-off, an idle watcher) drives back there after, until this close
    or this long since it left; ``face_within_m``/``face_rad``/``face_turn_rate_rad_s``: a
    holding robot turns towards its nearest own hostile within this range when it is more
    than this far off its heading (the LIDAR's 270 deg: a walker behind it is lost)."""

    enabled: bool = True
    blast_radius_m: float = 5.0
    margin_m: float = 0.75
    lookahead_s: float = 4.0
    release_m: float = 1.5
    clear_m: float = 3.0
    predict_s: float = 20.0
    unknown_cost: float = 2.0
    memory_s: float = 8.0
    return_tolerance_m: float = 0.5
    return_timeout_s: float = 90.0
    face_within_m: float = 12.0
    face_rad: float = 1.6
    face_turn_rate_rad_s: float = 1.0

    def __post_init__(self) -> None:
        names = ("blast_radius_m", "margin_m", "lookahead_s", "release_m", "clear_m", "memory_s")
        for name in names:
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"evasion.{name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.predict_s) and self.predict_s >= 0):
            raise ValueError(f"evasion.predict_s must be finite and >= 0, got {self.predict_s}")
        if not (math.isfinite(self.unknown_cost) and self.unknown_cost >= 1):
            raise ValueError(f"evasion.unknown_cost must be >= 1, got {self.unknown_cost}")


def _rows(hostiles: NDArray[np.float64]) -> NDArray[np.float64]:
    h = np.asarray(hostiles, dtype=np.float64).reshape(-1, 4)
    return h[np.isfinite(h).all(axis=1)]


def _segment_distance(
    points: NDArray[np.float64], start: tuple[float, float], step: tuple[float, float]
) -> NDArray[np.float64]:
    """Distances from ``points`` ``(N, 2)`` to the segment ``start -> start + step``."""
    rel = points - np.asarray(start)
    s = np.asarray(step, dtype=np.float64)
    n2 = float(s @ s)
    t = np.clip(rel @ s / n2, 0.0, 1.0) if n2 > 1e-12 else np.zeros(len(points))
    return np.hypot(rel[:, 0] - t * s[0], rel[:, 1] - t * s[1])


def way_clearance_m(
    points: NDArray[np.float64], hostiles: NDArray[np.float64], config: EvasionConfig
) -> NDArray[np.float64]:
    """For each of ``points`` ``(N, 2)``, the distance to the nearest hostile's way over the
    next ``predict_s`` (``inf`` without hostiles)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    d = np.full(len(pts), np.inf)
    for x, y, vx, vy in _rows(hostiles):
        step = (vx * config.predict_s, vy * config.predict_s)
        d = np.minimum(d, _segment_distance(pts, (x, y), step))
    return d


def hostile_threat(
    robot_xy: NDArray[np.float64], hostiles: NDArray[np.float64], config: EvasionConfig
) -> float:
    """The distance (m) from ``robot_xy`` to the nearest hostile, now or ``lookahead_s``
    ahead along its velocity, whichever is nearer (``inf`` without hostiles). Compare with
    ``blast_radius_m + margin_m`` (start) and that plus ``release_m`` (end)."""
    h = _rows(hostiles)
    if not len(h):
        return math.inf
    p = np.asarray(robot_xy, dtype=np.float64).reshape(2)
    now = np.hypot(h[:, 0] - p[0], h[:, 1] - p[1])
    ahead = h[:, :2] + config.lookahead_s * h[:, 2:]
    soon = np.hypot(ahead[:, 0] - p[0], ahead[:, 1] - p[1])
    return float(np.minimum(now, soon).min())


def evasion_goal(
    classes: NDArray[np.uint8],
    geometry: GridGeometry,
    robot_xy: NDArray[np.float64],
    hostiles: NDArray[np.float64],
    config: EvasionConfig,
    *,
    robot_radius_m: float,
) -> NDArray[np.float64] | None:
    """Where to go (odom, metres): see the module docstring. ``classes``: the terrain map
    around the robot (``UNKNOWN``/``DRIVABLE``/``OBSTACLE``; keep-out disks already drawn in
    as obstacles, shrunk to let a robot inside one out, never deeper). None when the robot's
    own cell is blocked or nothing is reachable. ``O(n log n)`` in the map's cells (one
    Dijkstra distance field)."""
    h = _rows(hostiles)
    p = np.asarray(robot_xy, dtype=np.float64).reshape(2)
    res = geometry.resolution_m
    blocked = configuration_space(
        classes == OBSTACLE, robot_radius_m=robot_radius_m, resolution_m=res
    )
    r, c = (int(v) for v in geometry.cell_of(p))
    if not (0 <= r < geometry.rows and 0 <= c < geometry.cols):
        return None
    # the robot's own footprint is free (the LIDAR does not see under it; a disk shrunk to
    # the robot's distance may graze it)
    k = max(1, int(math.ceil(robot_radius_m / res)))
    blocked[max(0, r - k) : r + k + 1, max(0, c - k) : c + k + 1] = False
    cost = np.where(classes == DRIVABLE, 1.0, config.unknown_cost)
    cost[blocked] = np.inf
    field = dijkstra_grid(cost, (r, c), None, resolution_m=res).distance_m
    reach = np.isfinite(field)
    reach[r, c] = False
    if not reach.any():
        return None
    rows, cols = np.nonzero(reach)
    centres = geometry.center_of(np.stack([rows, cols], axis=1))
    travel = field[rows, cols]
    d = way_clearance_m(centres, h, config)
    safe = (d >= config.blast_radius_m + config.clear_m) & (classes[rows, cols] == DRIVABLE)
    if safe.any():
        i = int(np.flatnonzero(safe)[np.argmin(travel[safe])])
    else:
        # nowhere far enough in the map: the farthest reachable cell (the shorter way on ties)
        i = int(np.lexsort((travel, -np.round(d, 1)))[0])
    return np.asarray(centres[i], dtype=np.float64)
