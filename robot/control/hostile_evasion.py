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
  one walking past does not), or where it may be ``react_s`` from now walking straight at
  the robot at ``walker_speed_m_s`` (a tracked walker's velocity is poor: from a LIDAR
  segment's centre it swings by 1 m/s sweep to sweep, and a walker turns at its route's
  corners: small world seed 11 at 66f8349, a robot's track said "walking away" while the
  walker came at it from 7 m; at 144 s seed 11 robot 0 began backing away 5.1 m off, the
  velocity-only rule); a threat when below ``blast_radius_m + margin_m``. The evasion
  lasts until every hostile is beyond that plus ``release_m`` (no dithering at the edge).
* :func:`suspect_tracks`: a person the LIDAR tracks but the camera has not coloured is the
  hostile when it is where a hostile can be: within ``suspect_reach_m`` plus
  ``walker_speed_m_s`` times the age (at most ``suspect_reach_max_m``) of a hostile sighting
  of the last ``suspect_memory_s``: this robot's own, or one of the GCS's hostile hazards,
  as old as the time since the robot first heard of it there; and only a person
  :func:`walking`: its measurements of the last ``suspect_window_s`` moved at least
  ``suspect_travel_m`` at ``suspect_speed_m_s`` or more (the LIDAR's person tracks are mostly
  clutter: posts, a wall's corner, a fence end; small world 66f8349 seed 3, 1433 samples of
  still unlabelled tracks near robots against 7 of the walker; taken for suspects, they held
  robot 2 of seed 7 evading phantoms for 192 of 300 s).
  The camera colours a walker seldom (small world 66f8349, seeds 3 and 11: the hostile's
  track unlabelled in 38 of 54 and 15 of 31 samples near a robot) and a dropped track comes
  back unlabelled: seeds 3, 7, 11 at 66f8349, robots drove head-on at an unlabelled walker
  from 10 m to 4.8 m, 3.4 m and 2.9 m (the trigger is 2.5 m).
* :func:`evasion_goal`: the reachable drivable cell, nearest by path (plus
  ``turn_cost_m_per_rad`` for each radian the robot must turn to head there: a robot turned
  in place for 4 s, the long way round, while a walker closed from 4.6 m to 2.9 m, seed 11)
  from the robot, that is
  ``blast_radius_m + clear_m`` from every hostile's way over the next ``predict_s`` (the
  segment from where it is along its velocity: a walker keeps walking, and a goal a few
  metres ahead of it on its way only puts off the next evasion, as the first version did:
  robot lost); none such in the map: the reachable cell farthest from those ways.

* :func:`keep_in_view_goal`: a robot with no task (a watcher at the view position the GCS
  sent it to) keeps its own nearest hostile in view: a walker going beyond ``keep_far_m``
  (within ``keep_within_m``) is followed back to ``keep_m``, on the line to the robot; the
  robot node holds it so (watching; also near a GCS sighting heard within ``keep_heard_s``:
  at its view the walker may be on the far side of its loop) rather than going back to its
  last point of radio contact, for at most ``keep_silent_s`` of silence (the rules' lock
  needs two robots to see the walker for 30 s, not the radio; the walker's loop lies in a
  radio shadow of the small world).

Pure functions over numpy arrays in the robot's ``odom`` frame, metres and seconds; hostiles
are rows ``(x_m, y_m, vx_m_s, vy_m_s)`` (zero velocity when unknown: the GCS's hazards).

Measured (small world, ``magic run --duration 300``, seeds 0/7/3/11, traced every 0.5 s; load
2-14): at 66f8349 no robot was lost but robots came within 2.75/3.35/4.84/2.94 m of the walker
(the trigger is 2.5 m), 8.5/25.5/2.0/19.5 robot-seconds inside its blast radius, explored
0.962/0.860/0.960/0.944 (median 0.952). With suspects, the closing speed, the turn cost, no
yield while backing away, the flee with no path (robot node) and the GCS's view ring from
7.5 m (66f8349 with this module, robot/node.py and the hostile planner of dd73057): 0 lost,
closest 4.90/5.86/4.83/3.23 m, 2.0/0/2.5/8.5 robot-s within 5 m,
explored 0.952/0.939/0.930/0.972 (median 0.946), hostiles locked 0 before and after. Before
the GCS's sightings were kept as suspects' seeds past ``suspect_memory_s``, seed 3 lost robot
0 at 231 s: it drove at an uncoloured walker 2 m from a sighting it had heard of 90 s before.
Left: a walker turning at its route's corner is "not walking" for a moment and its
velocity points the old way (seed 11, 3.23 m).
"""

from __future__ import annotations

import math

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from robot.planning.config_space import configuration_space
from robot.planning.dijkstra import dijkstra_grid
from robot.terrain.grid import DRIVABLE, OBSTACLE, GridGeometry

__all__ = [
    "EvasionConfig",
    "evasion_goal",
    "hostile_threat",
    "keep_in_view_goal",
    "line_of_sight",
    "sight_point",
    "suspect_tracks",
    "walk_velocity",
    "walking",
    "way_clearance_m",
]


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
    than this far off its heading (the LIDAR's 270 deg: a walker behind it is lost);
    ``walker_speed_m_s``/``react_s``: a hostile may close at this speed, whatever its track
    says, over this long (the robot's reaction: start, turn, drive); ``suspect_*``: see
    :func:`suspect_tracks`; ``turn_cost_m_per_rad``: see :func:`evasion_goal`;
    ``flee_clear_m``/``flee_speed_m_s``: a robot backing away that has no path to its goal
    drives straight away from the nearest hostile at this speed while the terrain is clear
    this far ahead (the robot node)."""

    enabled: bool = True
    blast_radius_m: float = 5.0
    margin_m: float = 0.75
    lookahead_s: float = 4.0
    release_m: float = 1.5
    clear_m: float = 4.0
    predict_s: float = 20.0
    unknown_cost: float = 2.0
    memory_s: float = 8.0
    return_tolerance_m: float = 0.5
    return_timeout_s: float = 90.0
    face_within_m: float = 12.0
    face_rad: float = 1.6
    face_turn_rate_rad_s: float = 1.0
    walker_speed_m_s: float = 0.8
    react_s: float = 1.5
    suspect_memory_s: float = 60.0
    suspect_reach_m: float = 2.0
    suspect_reach_max_m: float = 12.0
    suspect_window_s: float = 3.0
    suspect_travel_m: float = 0.8
    suspect_speed_m_s: float = 0.3
    turn_cost_m_per_rad: float = 1.0
    flee_clear_m: float = 1.0
    flee_speed_m_s: float = 0.8
    # keeping a hostile in view (:func:`keep_in_view_goal`): a robot with no task follows its
    # own hostile beyond keep_far_m (within keep_within_m) back to keep_m, and with the link
    # silent watches so at most keep_silent_s before it goes back to contact (robot node).
    # Off by default: measured on (with the allocator's view_shadow_retry_s 0) on the quick
    # mission at ec6bf10, seeds 0/7/3/11 (load ~10): hostiles locked 0/0/0/0, two sensor
    # robots within 12 m of the walker 12/46/31/0 s (38fac2c: 8/6/0/0), but explored
    # 0.944/0.932/0.847/0.948 (median 0.938 against 0.941), ATE median 0.253 against 0.223 m,
    # F1 0.816 against 0.840: robots held in the walker's radio shadow, written off by the
    # GCS (robot_lost 60 s silent), their maps late; the lock still never held 30 s.
    # Session 15, at 8183549 + the disruptor's ooi_blob_m, with view_shadow_retry_s 0, the
    # allocator's watch_on_return and predict_s 8 / clear_m 2.5 here (the default 20 s / 4 m
    # sent a backing-away watcher 9 m off the walker's next 12 m, beyond the 12 m lock
    # range), seeds 0/7/3/11 (load 8-16, /tmp/team/tasks15/runs/B_s*): hostile locked on
    # seed 0 only (212 s, robots 0 and 2 after 52 s of two in view); two sensor robots
    # within 12 m 89/48/10/48 s (longest 52/14/10/28 s; base 31/69/53/36 s, longest
    # 17/26/25/22); explored 0.923/0.909/0.914/0.903 (median 0.911 against 0.923 without),
    # ATE 0.324/0.443/0.181/0.095 (median 0.253 against 0.155 m), F1 0.657/0.847/0.834/0.895
    # (0.840 against 0.786), false closures 1/1/0/0, 0 lost, 0 civilians, but a watcher held
    # 3.0 m from the live walker on seed 3 (its trigger is 2.5 m: the walker came at it
    # from 8 m while it stood) where the base kept 5.6 m. With the hostile planner's
    # self_watch_m 16 (also on its way) and keep_m 8 / keep_far_m 9.5 (runs E_s*): seed 0
    # locked again, 7, 3 and 11 not (seed 11: two within 12 m for 53 s at a stretch, a
    # building cut one's line of sight, 26 s in view: the follow point is on the line to the
    # robot, not chosen for line of sight), explored 0.921/0.912/0.918/0.879 (median
    # 0.915), ATE median 0.235 m, F1 0.776, 0 lost, seed 3's 3.0 m again. Stays off: 1 lock
    # in 4 seeds (the target was 2), a closer approach and the maps' cost. Session 16 (at
    # 1d6eb73 + the node's movers-only yield, without yield_cleared; load 10-20; two sensor
    # robots within 12 m of the walker from the truth at 0.2 s): with the E settings above
    # the line point locked seed 7 only (63 s of two within 12 m at a stretch) and came 2.59 m
    # from the walker there (the trigger is 2.5 m), explored 0.933/0.915/0.885/0.906 on seeds
    # 0/7/3/11 (median 0.911); the follow point in view over the robot's map (keep_sight)
    # locked none (longest 20/41/13/24 s), explored 0.921/0.899/0.860/0.906 (median 0.903),
    # closest 3.67 m; keep_view off: no lock, longest 3/17/14/19 s, explored median 0.917.
    # 0 lost, 0 civilians in all. Stays off.
    keep_view: bool = False
    keep_silent_s: float = 90.0
    keep_heard_s: float = 60.0
    keep_far_m: float = 10.0
    keep_m: float = 8.5
    keep_within_m: float = 16.0
    keep_arrive_m: float = 0.5
    # with the robot's map (keep_sight): the follow point is a reachable point keep_m (or
    # keep_m - keep_sight_band_m) from where the walker will be in keep_predict_s with a
    # clear line over the map's obstacles to it, nearest the robot; a robot holding within
    # keep_far_m whose line to the walker a wall cuts moves to such a point
    keep_sight: bool = True
    keep_predict_s: float = 3.0
    keep_sight_band_m: float = 2.0
    keep_sight_angles: int = 48

    def __post_init__(self) -> None:
        names = (
            "blast_radius_m",
            "margin_m",
            "lookahead_s",
            "release_m",
            "clear_m",
            "memory_s",
            "walker_speed_m_s",
            "react_s",
            "suspect_memory_s",
            "suspect_reach_m",
            "suspect_reach_max_m",
            "suspect_window_s",
            "suspect_travel_m",
            "suspect_speed_m_s",
            "turn_cost_m_per_rad",
            "flee_clear_m",
            "flee_speed_m_s",
            "keep_far_m",
            "keep_m",
            "keep_within_m",
            "keep_arrive_m",
            "keep_silent_s",
            "keep_heard_s",
            "keep_predict_s",
            "keep_sight_band_m",
        )
        for name in names:
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"evasion.{name} must be finite and >= 0, got {v}")
        if not (math.isfinite(self.predict_s) and self.predict_s >= 0):
            raise ValueError(f"evasion.predict_s must be finite and >= 0, got {self.predict_s}")
        if self.keep_sight_angles < 4:
            raise ValueError(
                f"evasion.keep_sight_angles must be >= 4, got {self.keep_sight_angles}"
            )
        if not (math.isfinite(self.unknown_cost) and self.unknown_cost >= 1):
            raise ValueError(f"evasion.unknown_cost must be >= 1, got {self.unknown_cost}")
        if not (
            self.blast_radius_m + self.margin_m + self.release_m
            < self.keep_m + self.keep_arrive_m
            < self.keep_far_m
            <= self.keep_within_m
        ):
            raise ValueError(
                "evasion: expected blast_radius_m + margin_m + release_m < keep_m + "
                "keep_arrive_m < keep_far_m <= keep_within_m, got "
                f"{self.blast_radius_m + self.margin_m + self.release_m:g}, "
                f"{self.keep_m + self.keep_arrive_m:g}, {self.keep_far_m:g}, "
                f"{self.keep_within_m:g}"
            )


def keep_in_view_goal(
    position: NDArray[np.float64],
    hostiles: NDArray[np.float64],
    config: EvasionConfig,
    *,
    following: bool,
    sight: NDArray[np.bool_] | None = None,
    blocked: NDArray[np.bool_] | None = None,
    geometry: GridGeometry | None = None,
    robot_radius_m: float = 0.3,
    previous: NDArray[np.float64] | None = None,
) -> NDArray[np.float64] | None:
    """Where an idle robot drives to keep its nearest hostile in view, or None (stay).

    The rules' lock (paper 2) needs two sensor robots to see a walker for 30 s without a
    break, within the lock range (12 m in :mod:`sim.rules`); a walker patrolling its route at
    0.6 m/s leaves a robot holding at a view position within 15 to 20 s (small world at
    38fac2c: no cell within 12 m with line of sight of more than 29 s of its 59 s loop, and
    robots held 13 to 17 m from it for minutes, the GCS's view goals placed off stale
    sightings). Nearest hostile ``hostiles`` ``(N, 4)`` row (x, y, vx, vy) beyond
    ``keep_far_m`` (``keep_m + keep_arrive_m`` while ``following``) and within
    ``keep_within_m`` of ``position``: the point ``keep_m`` from it on the line to the
    robot (the way it came into view). Nearer than that it stays (a walker coming on is the
    evasion's: :func:`hostile_threat`).

    With the robot's map (``config.keep_sight`` and ``sight``, ``blocked``, ``geometry``,
    all in ``odom``): the line to the robot may cross a building (small world seed 11: a
    building cut one watcher's view, 26 s in view of the 30 needed). The follow point is
    then :func:`sight_point`: in view of where the walker will be in ``keep_predict_s``
    over ``sight`` (cells that block the view) and reachable over ``blocked`` (cells the
    robot may not enter); ``previous`` (the follow point held) is kept while it still
    serves. A robot within range whose line to the walker is cut moves too; one with a
    clear line stays. No such point in the map: the line point (or stay, within range)."""
    if not config.keep_view:
        return None
    h = _rows(hostiles)
    if not len(h):
        return None
    p = np.asarray(position, dtype=np.float64).reshape(2)
    d = np.hypot(h[:, 0] - p[0], h[:, 1] - p[1])
    k = int(np.argmin(d))
    near = config.keep_m + config.keep_arrive_m if following else config.keep_far_m
    if not d[k] <= config.keep_within_m:
        return None
    use_map = config.keep_sight and sight is not None and geometry is not None
    if d[k] <= near and not use_map:
        return None
    if d[k] <= config.blast_radius_m + config.margin_m + config.release_m:
        return None  # the evasion's
    line = None
    if d[k] > near:
        u = (p - h[k, :2]) / d[k]
        line = h[k, :2] + config.keep_m * u
    if not use_map:
        return line
    assert sight is not None and geometry is not None
    target = h[k, :2] + config.keep_predict_s * h[k, 2:]
    if d[k] <= near and line_of_sight(p, target, sight, geometry):
        return None  # in range and in view: hold
    best = sight_point(
        p,
        target,
        h,
        config,
        sight=sight,
        blocked=sight if blocked is None else blocked,
        geometry=geometry,
        robot_radius_m=robot_radius_m,
        previous=previous,
    )
    return line if best is None else best


def line_of_sight(
    a: NDArray[np.float64],
    b: NDArray[np.float64],
    sight: NDArray[np.bool_],
    geometry: GridGeometry,
    *,
    skip_end_m: float = 1.0,
) -> bool:
    """Whether the segment ``a -> b`` (``odom``) crosses no ``sight`` cell, but for its last
    ``skip_end_m`` (the walker's own marks in the map). Cells off the map do not block."""
    a = np.asarray(a, dtype=np.float64).reshape(2)
    b = np.asarray(b, dtype=np.float64).reshape(2)
    length = float(np.hypot(*(b - a)))
    end = length - skip_end_m
    if end <= 0:
        return True
    s = np.arange(0.0, end, 0.5 * geometry.resolution_m)
    pts = a + (s / max(length, 1e-9))[:, None] * (b - a)
    rc = geometry.cell_of(pts)
    ok = (rc[:, 0] >= 0) & (rc[:, 0] < geometry.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < geometry.cols)
    rc = rc[ok]
    return not bool(sight[rc[:, 0], rc[:, 1]].any())


def sight_point(
    position: NDArray[np.float64],
    target: NDArray[np.float64],
    hostiles: NDArray[np.float64],
    config: EvasionConfig,
    *,
    sight: NDArray[np.bool_],
    blocked: NDArray[np.bool_],
    geometry: GridGeometry,
    robot_radius_m: float,
    previous: NDArray[np.float64] | None = None,
) -> NDArray[np.float64] | None:
    """The point nearest ``position`` among those ``keep_m`` or ``keep_m -
    keep_sight_band_m`` from ``target`` (``keep_sight_angles`` round it) that lie on the map,
    reachable from ``position`` over ``blocked`` in the configuration space, in view of
    ``target`` (:func:`line_of_sight` over ``sight``) and ``blast_radius_m + margin_m`` clear
    of every hostile's way (:func:`way_clearance_m`); ``previous`` when it still is all that
    within ``keep_sight_band_m`` of the ring. None: no such point."""
    p = np.asarray(position, dtype=np.float64).reshape(2)
    t = np.asarray(target, dtype=np.float64).reshape(2)
    res = geometry.resolution_m
    free = ~configuration_space(blocked, robot_radius_m=robot_radius_m, resolution_m=res)
    _, labels = cv2.connectedComponents(free.astype(np.uint8), connectivity=8)
    r, c = (int(v) for v in geometry.cell_of(p))
    inside = 0 <= r < geometry.rows and 0 <= c < geometry.cols
    own = int(labels[r, c]) if inside else 0
    safe = config.blast_radius_m + config.margin_m

    def serves(q: NDArray[np.float64]) -> bool:
        qr, qc = (int(v) for v in geometry.cell_of(q))
        if not (0 <= qr < geometry.rows and 0 <= qc < geometry.cols) or not free[qr, qc]:
            return False
        if own and labels[qr, qc] != own:
            return False
        if way_clearance_m(q.reshape(1, 2), hostiles, config)[0] < safe:
            return False
        return line_of_sight(q, t, sight, geometry)

    if previous is not None:
        q = np.asarray(previous, dtype=np.float64).reshape(2)
        dq = float(np.hypot(*(q - t)))
        if config.keep_m - config.keep_sight_band_m - 0.5 <= dq <= config.keep_m + 0.5 and serves(
            q
        ):
            return q
    n = config.keep_sight_angles
    ang = np.arange(n) * (2.0 * math.pi / n)
    ring = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    radii = [config.keep_m, max(safe + 0.5, config.keep_m - config.keep_sight_band_m)]
    cands = np.vstack([t + rad * ring for rad in radii])
    order = np.argsort(np.hypot(cands[:, 0] - p[0], cands[:, 1] - p[1]))
    for i in order:
        if serves(cands[i]):
            return np.asarray(cands[i], dtype=np.float64)
    return None


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
    """The distance (m) from ``robot_xy`` to the nearest hostile: ``lookahead_s`` ahead
    along its velocity, or ``react_s`` ahead walking straight at the robot at
    ``walker_speed_m_s``, whichever is nearer (``inf``
    without hostiles). Compare with ``blast_radius_m + margin_m`` (start) and that plus
    ``release_m`` (end)."""
    h = _rows(hostiles)
    if not len(h):
        return math.inf
    p = np.asarray(robot_xy, dtype=np.float64).reshape(2)
    now = np.hypot(h[:, 0] - p[0], h[:, 1] - p[1])
    # a tracked walker's speed is no better than its velocity (a still post's track says 1.5
    # m/s at times): the closing speed is the walker's
    closing = np.maximum(now - config.walker_speed_m_s * config.react_s, 0.0)
    ahead = h[:, :2] + config.lookahead_s * h[:, 2:]
    soon = np.hypot(ahead[:, 0] - p[0], ahead[:, 1] - p[1])
    return float(np.minimum(closing, soon).min())


def suspect_tracks(
    tracks_xy: NDArray[np.float64],
    sightings: NDArray[np.float64],
    now_s: float,
    config: EvasionConfig,
) -> NDArray[np.bool_]:
    """Which of the unlabelled person tracks ``tracks_xy`` ``(N, 2)`` are taken for a
    hostile (see the module docstring): near where the hostile of one of the ``sightings``
    ``(M, 3)``, rows ``(x_m, y_m, seen_s)``, may have walked since. One frame (``odom``)."""
    pts = np.asarray(tracks_xy, dtype=np.float64).reshape(-1, 2)
    out = np.zeros(len(pts), dtype=bool)
    if not len(pts):
        return out
    sig = np.asarray(sightings, dtype=np.float64).reshape(-1, 3)
    sig = sig[np.isfinite(sig).all(axis=1)]
    age = now_s - sig[:, 2]
    recent = (age >= 0) & (age <= config.suspect_memory_s)
    sig, age = sig[recent], age[recent]
    for (x, y, _), a in zip(sig, age, strict=True):
        reach = min(
            config.suspect_reach_m + config.walker_speed_m_s * float(a), config.suspect_reach_max_m
        )
        out |= np.hypot(pts[:, 0] - x, pts[:, 1] - y) <= reach
    return out


def walking(history: NDArray[np.float64], now_s: float, config: EvasionConfig) -> bool:
    """Whether a person track's measurements ``(K, 3)`` rows ``(time_s, x_m, y_m)`` show it
    walking (see :func:`suspect_tracks`): those of the last ``suspect_window_s`` before
    ``now_s`` span a second or more, and moved ``suspect_travel_m`` or more end to end, at
    ``suspect_speed_m_s`` or more."""
    return walk_velocity(history, now_s, config) is not None


def walk_velocity(
    history: NDArray[np.float64], now_s: float, config: EvasionConfig
) -> NDArray[np.float64] | None:
    """The velocity (m/s) end to end over a walking track's measurements of the last
    ``suspect_window_s`` (:func:`walking`), None when it is not walking. Steadier than the
    tracker's filter for a walker (small world 66f8349 seed 11: an uncoloured walker's
    filter velocity said 1.34 m/s north while it walked 0.6 m/s east, and the robot, its
    suspect placed 2 m off by it, drove on to 2.9 m of the walker)."""
    h = np.asarray(history, dtype=np.float64).reshape(-1, 3)
    h = h[np.isfinite(h).all(axis=1) & (h[:, 0] >= now_s - config.suspect_window_s)]
    if len(h) < 2:
        return None
    span = float(h[-1, 0] - h[0, 0])
    if span < 1.0:
        return None
    d = h[-1, 1:] - h[0, 1:]
    travel = math.hypot(float(d[0]), float(d[1]))
    if travel < config.suspect_travel_m or travel / span < config.suspect_speed_m_s:
        return None
    return np.asarray(d / span, dtype=np.float64)


def evasion_goal(
    classes: NDArray[np.uint8],
    geometry: GridGeometry,
    robot_xy: NDArray[np.float64],
    hostiles: NDArray[np.float64],
    config: EvasionConfig,
    *,
    robot_radius_m: float,
    heading_rad: float | None = None,
) -> NDArray[np.float64] | None:
    """Where to go (odom, metres): see the module docstring. ``classes``: the terrain map
    around the robot (``UNKNOWN``/``DRIVABLE``/``OBSTACLE``; keep-out disks already drawn in
    as obstacles, shrunk to let a robot inside one out, never deeper); ``heading_rad``: the
    robot's heading, for the turn cost (None: no turn cost). None when the robot's
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
    if heading_rad is not None and config.turn_cost_m_per_rad > 0:
        bearing = np.arctan2(centres[:, 1] - p[1], centres[:, 0] - p[0])
        turn = np.abs((bearing - heading_rad + np.pi) % (2 * np.pi) - np.pi)
        travel = travel + config.turn_cost_m_per_rad * turn
    d = way_clearance_m(centres, h, config)
    safe = (d >= config.blast_radius_m + config.clear_m) & (classes[rows, cols] == DRIVABLE)
    if safe.any():
        i = int(np.flatnonzero(safe)[np.argmin(travel[safe])])
    else:
        # nowhere far enough in the map: the farthest reachable cell (the shorter way on ties)
        i = int(np.lexsort((travel, -np.round(d, 1)))[0])
    return np.asarray(centres[i], dtype=np.float64)
