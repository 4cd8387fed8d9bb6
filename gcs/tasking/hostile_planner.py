"""Mobile OOI (hostile) lock and blast-radius keep-out (MAGIC rules; paper 2 and 5.1.3).

A mobile OOI is neutralized when two sensor robots keep it in view for ``lock_s`` (30 s)
without a break, while no robot enters its blast radius (5 m). The paper's operators
coordinated this by hand (5.1.3); here it is a planner:

* :func:`view_positions`: for the ``viewers`` robots nearest the OOI, traversable cells in the
  ring ``[blast_radius_m + margin_m, view_range_m]`` around it with line of sight, the first
  robot's cheapest (travel plus ``range_weight`` per metre off ``view_pref_m``), each
  following one at least ``min_bearing_sep_rad`` around the OOI from those taken (two views
  from one side are one view if it turns a corner). Watchers that see the walker now stay
  where they are (``fixed_in_map``): the robot keeps a walker in view itself
  (:func:`robot.control.hostile_evasion.keep_in_view_goal`), and one still on its way is
  placed around them. Why (small world, quick mission at 38fac2c, seeds 0/7, traced every
  step against the rules' own view test): the nearest cell of the ring lay on its 12 m
  edge, and with radio contact first on the edge towards the GCS: watchers held 13 to 17 m
  from the walker's loop for minutes (the lock range is 12 m), two robots saw the walker
  together for at most 8.2 s, and no cell within 12 m with line of sight sees more than 29 s
  of its 59 s loop. A watcher that fell silent at its view watches on (the lock needs no
  radio); only one silent on its way is kept off that hostile (``view_shadow_retry_s``).
  Measured (quick mission at ec6bf10 with this, seeds 0/7/3/11, load ~10): two sensor robots
  within 12 m of the walker 8/25/30/36 s of the run (longest 8/11/17/22 s) against 8/6/0/0
  at 38fac2c; locked 0 before and after (the lock needs 30 s); explored
  0.955/0.913/0.955/0.889 (median 0.934 against 0.941), ATE median 0.166 against 0.223 m,
  F1 0.888 against 0.840, false closures 0/2/0/0 (1/0/0/0), 0 robots lost, closest
  approach 4.70/6.44/5.25/5.89 m (4.90/5.50/5.22/4.33). Left: watchers reach their views
  one at a time and through the walker's radio shadow; the GCS hears a walker seldom (seed
  7 at ec6bf10: both watchers back in contact 10 m from it were sent to explore; why is
  not known yet).
* :class:`HostileLock`: bookkeeping of the lock: who saw the OOI when (the GCS's detections),
  since when two robots have kept it in view with no gap above ``view_gap_s``, and whether the
  lock has held ``lock_s``.
* :func:`evasion_goal`: a robot inside a keep-out disc drives to the nearest traversable cell
  it can see (the planning grid already excludes the discs), apart from the cells other
  robots are evading to.
* :func:`watch_slots`: how many hostiles are watched at once. The paper is silent on hostiles
  (its operators handled them, 5.1.3); a commander keeps exploration the standing task and
  puts at most ``max_watch_frac`` of the sensor robots on watch (full mission at 66b4360:
  9 of 10 sensor robots on watch duty at 600 s, for 14 sightings of 2 walkers, and the
  explored area flat from 900 s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgspec
import numpy as np
from numpy.typing import ArrayLike

from gcs.tasking.planning_grid import PlanningGrid, line_of_sight

__all__ = [
    "HostileConfig",
    "HostileLock",
    "LockState",
    "evasion_goal",
    "view_positions",
    "watch_slots",
]


class HostileConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Metres, seconds, radians; see the module docstring."""

    blast_radius_m: float = 5.0
    # the view ring's inner edge is blast_radius_m + margin_m from the sighting: a robot backs
    # away on its own from a walker that may reach its blast radius plus 0.75 m within 1.5 s
    # at 0.8 m/s (robot.control.hostile_evasion: 6.95 m off), so a watcher placed nearer (at
    # 1.0: 6 m) backs away as soon as it sees the walker, and a sighting is seconds old
    margin_m: float = 2.5
    # the ring's outer edge: the rules' lock range is 12 m (sim.rules), and a walker walks on
    view_range_m: float = 11.0
    # within the ring, a view this far off the sighting is preferred: each metre off it costs
    # range_weight metres of travel (view_positions)
    view_pref_m: float = 9.0
    range_weight: float = 3.0
    # a view where the GCS has not heard robots costs this many metres more (view_positions)
    unheard_cost_m: float = 4.0
    lock_s: float = 30.0
    view_gap_s: float = 1.5
    viewers: int = 2
    min_bearing_sep_rad: float = 0.6
    replan_move_m: float = 2.0
    # a watcher at its view within self_watch_m of the hostile's sighting is not re-placed
    # when the sighting moves (nor sent to another sighting of the same walker: it watches
    # that one); it keeps the walker in view itself (robot.control.hostile_evasion
    # .keep_in_view_goal, whose keep_within_m matches 16 m); 0: off (re-placed as before).
    # Off by default with keep_view (without it a watcher does not follow). Quick mission
    # at 8183549 + ooi_blob_m with keep_view and the allocator's watch_on_return, seeds
    # 0/7/3: 16 m (at its view only) changed nothing (the same runs, to 0.0004 explored);
    # 16 m at its view or on its way, with keep_m 8 / keep_far_m 9.5: see keep_view's
    # docstring (robot.control.hostile_evasion)
    self_watch_m: float = 0.0
    # a watch that has not started the lock (two robots seeing the hostile) within
    # watch_budget_s is paused for watch_pause_s: its robots explore meanwhile (small world
    # seed 7: every sensor robot chased one hostile in and out of radio shadows from 166 s
    # to the end, no lock, and exploration stood still at 0.85)
    watch_budget_s: float = 75.0
    watch_pause_s: float = 120.0
    # hostile sightings this close are one hostile (it walks: its hazards spread), watched once
    same_hostile_m: float = 8.0
    # at most this share of the sensor robots heard is on watch duty (at least ``viewers``):
    # exploration stays the standing task (see the module docstring)
    max_watch_frac: float = 0.4
    # only robots this close (straight line) to a hostile are sent to watch it: a watcher
    # 100 m off arrives minutes later, through radio shadows, to where the walker was (full
    # mission: robots sent 110 m across the site to a hostile, silent on the way for good)
    watch_reach_m: float = 40.0
    # a sighting no robot has seen for this long is not watched: the walker is elsewhere,
    # and a lock needs it in view now (full mission: 14 sightings of 2 walkers, each asking
    # for two viewers)
    watch_fresh_s: float = 60.0
    # a robot inside a hostile's blast radius is sent out of it only while the sighting is
    # this fresh (allocator._evade)
    evade_fresh_s: float = 30.0
    # each further pause of the same hostile (sightings within same_hostile_m of a paused
    # one) lasts this many times longer: a hostile that never lets itself be locked stops
    # costing the team its explorers
    pause_growth: float = 2.0

    def __post_init__(self) -> None:
        for name in (
            "blast_radius_m",
            "view_range_m",
            "view_pref_m",
            "lock_s",
            "view_gap_s",
            "watch_budget_s",
            "watch_pause_s",
            "same_hostile_m",
            "watch_reach_m",
            "watch_fresh_s",
            "evade_fresh_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"hostile {name} must be finite and > 0, got {v}")
        if not self.view_range_m > self.blast_radius_m + self.margin_m:
            raise ValueError(
                f"hostile view_range_m {self.view_range_m} must exceed blast_radius_m + margin_m"
            )
        for name in ("range_weight", "unheard_cost_m", "self_watch_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"hostile {name} must be finite and >= 0, got {v}")
        if self.viewers < 1:
            raise ValueError(f"hostile viewers must be >= 1, got {self.viewers}")
        if not (math.isfinite(self.max_watch_frac) and 0 <= self.max_watch_frac <= 1):
            raise ValueError(f"hostile max_watch_frac must be in [0, 1], got {self.max_watch_frac}")
        if not (math.isfinite(self.pause_growth) and self.pause_growth >= 1):
            raise ValueError(f"hostile pause_growth must be >= 1, got {self.pause_growth}")


def watch_slots(sensor_robots: int, config: HostileConfig) -> int:
    """How many hostiles may be watched at once by ``sensor_robots`` robots in contact: the
    watchers allowed, ``max(viewers, floor(max_watch_frac * sensor_robots))`` (0 with fewer
    robots than ``viewers``), over ``viewers`` a hostile. 10 sensor robots: 2 hostiles (4
    robots), 6 others explore; 3 (the small world's): 1 hostile, as before the cap."""
    if sensor_robots < config.viewers:
        return 0
    allowed = max(config.viewers, int(math.floor(config.max_watch_frac * sensor_robots + 1e-9)))
    return allowed // config.viewers


def view_positions(
    grid: PlanningGrid,
    hostile_in_map: ArrayLike,
    robots_in_map: dict[int, tuple[float, float]],
    config: HostileConfig,
    *,
    contact_in_map: ArrayLike | None = None,
    contact_radius_m: float = 2.0,
    fixed_in_map: dict[int, tuple[float, float]] | None = None,
) -> dict[int, tuple[float, float]]:
    """``robot_id -> view position`` for up to ``viewers`` of ``robots_in_map`` (the nearest
    first); robots with no admissible cell are left out. Of the admissible cells a robot
    takes the one with the least straight-line distance from it plus ``range_weight`` times
    the cell's distance from ``view_pref_m`` off the hostile (the nearest cell alone lies on
    the ring's outer edge, out of view a few seconds after the walker walks on). With
    ``contact_in_map`` ``(C, 2)`` (where the GCS heard robots at once), a cell farther than
    ``contact_radius_m`` from all of them costs ``unheard_cost_m`` more: the GCS's own lock
    bookkeeping hears only watchers in contact, but the rules' lock does not need the radio
    (:mod:`sim.rules`), and contact first put every view on the ring's edge nearest the GCS
    (small world at 38fac2c: views 10 to 17 m off the walker's loop, on its side towards the
    GCS). ``fixed_in_map``: watchers that stay where they are (they
    see the hostile now): they count among the ``viewers``, their bearings are taken, and
    they are returned as they are."""
    h = np.asarray(hostile_in_map, dtype=np.float64).reshape(2)
    if not robots_in_map:
        return {}
    res = grid.resolution_m
    (r, c) = grid.cells_of(h)[0]
    k = int(math.ceil(config.view_range_m / res))
    rows, cols = grid.shape
    r0, r1 = max(0, r - k), min(rows, r + k + 1)
    c0, c1 = max(0, c - k), min(cols, c + k + 1)
    if r0 >= r1 or c0 >= c1:
        return {}
    rr, cc = np.nonzero(grid.traversable[r0:r1, c0:c1])
    cells = np.stack([rr + r0, cc + c0], axis=1)
    pts = grid.centers_of(cells)
    d = np.hypot(*(pts - h).T)
    ok = (d >= config.blast_radius_m + config.margin_m) & (d <= config.view_range_m)
    pts = pts[ok]
    if len(pts) == 0:
        return {}
    heard = np.zeros(len(pts), dtype=bool)
    contact = np.zeros((0, 2)) if contact_in_map is None else np.asarray(contact_in_map)
    contact = contact.astype(np.float64).reshape(-1, 2)
    if len(contact):
        near = np.abs(contact - h).max(axis=1) <= config.view_range_m + contact_radius_m
        for c in contact[near]:
            heard |= np.hypot(*(pts - c).T) <= contact_radius_m
    out: dict[int, tuple[float, float]] = {}
    bearings: list[float] = []
    for rid, q in (fixed_in_map or {}).items():
        if len(out) >= config.viewers:
            break
        out[rid] = (float(q[0]), float(q[1]))
        bearings.append(math.atan2(q[1] - h[1], q[0] - h[0]))
    order = sorted(
        (rid for rid in robots_in_map if rid not in out),
        key=lambda rid: math.dist(robots_in_map[rid], h),
    )
    off_pref = config.range_weight * np.abs(d[ok] - config.view_pref_m)
    for rid in order:
        if len(out) >= config.viewers:
            break
        p = np.asarray(robots_in_map[rid], dtype=np.float64)
        dist = np.hypot(*(pts - p).T) + off_pref
        bearing = np.arctan2(pts[:, 1] - h[1], pts[:, 0] - h[0])
        for b in bearings:
            sep = np.abs((bearing - b + np.pi) % (2 * np.pi) - np.pi)
            dist = np.where(sep >= config.min_bearing_sep_rad, dist, np.inf)
        dist = dist + np.where(heard, 0.0, config.unheard_cost_m)
        for j in np.argsort(dist, kind="stable"):
            if not np.isfinite(dist[j]):
                continue
            if line_of_sight(grid, pts[j], h):
                out[rid] = (float(pts[j, 0]), float(pts[j, 1]))
                bearings.append(float(bearing[j]))
                break
    return out


def evasion_goal(
    grid: PlanningGrid,
    position_in_map: ArrayLike,
    search_m: float,
    *,
    taken_in_map: ArrayLike | None = None,
    separation_m: float = 1.0,
) -> tuple[float, float] | None:
    """A traversable cell centre within ``search_m`` to leave a keep-out by (None if none):
    the nearest in line of sight of the robot (no wall between: the nearest cell may be in
    the room behind a wall) at least ``separation_m`` from every point of ``taken_in_map``
    ``(K, 2)`` (where other robots are evading to: three robots sent to one cell in a 1 m
    corridor jammed there, each evasion timing out, for 600 s of the full mission); else the
    nearest in line of sight; else the nearest."""
    p = np.asarray(position_in_map, dtype=np.float64).reshape(2)
    near = grid.traversable_near(p, search_m)
    if near is None:
        return None
    _, rr, cc = near
    pts = grid.centers_of(np.stack([rr, cc], axis=1))
    d = np.hypot(*(pts - p).T)
    keep = d <= search_m + 1e-9
    pts, d = pts[keep], d[keep]
    if len(pts) == 0:
        return None
    taken = np.zeros((0, 2)) if taken_in_map is None else np.asarray(taken_in_map)
    taken = taken.astype(np.float64).reshape(-1, 2)
    apart = np.ones(len(pts), dtype=bool)
    for t in taken:
        apart &= np.hypot(*(pts - t).T) >= separation_m
    order = np.argsort(d, kind="stable")
    fallback: int | None = None
    for j in order[:2000]:  # the nearest cells first: a visible one is near
        if not line_of_sight(grid, p, pts[j]):
            continue
        if apart[j]:
            return (float(pts[j, 0]), float(pts[j, 1]))
        if fallback is None:
            fallback = int(j)
    j = fallback if fallback is not None else int(order[0])
    return (float(pts[j, 0]), float(pts[j, 1]))


@dataclass
class LockState:
    """``since_s``: start of the current unbroken two-robot view (None: not in view);
    ``locked``: the lock held ``lock_s``; ``locked_at_s`` when."""

    since_s: float | None = None
    locked: bool = False
    locked_at_s: float | None = None
    breaks: int = 0


@dataclass
class HostileLock:
    """Lock bookkeeping per hostile (state across planning steps; see the module docstring)."""

    config: HostileConfig = field(default_factory=HostileConfig)
    states: dict[int, LockState] = field(default_factory=dict)

    def update(self, hazard_id: int, last_seen_s: dict[int, float], now_s: float) -> LockState:
        """Fold in ``robot_id -> last time it saw the hostile``; returns the hostile's state."""
        st = self.states.setdefault(hazard_id, LockState())
        if st.locked:
            return st
        seeing = [t for t in last_seen_s.values() if now_s - t <= self.config.view_gap_s]
        need = min(2, self.config.viewers)
        if len(seeing) >= need:
            if st.since_s is None:
                # the view began when the last of the two robots started seeing it: now
                st.since_s = now_s
            if now_s - st.since_s >= self.config.lock_s:
                st.locked = True
                st.locked_at_s = now_s
        elif st.since_s is not None:
            st.since_s = None
            st.breaks += 1
        return st
