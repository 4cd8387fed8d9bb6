"""The robot's own hostile rules on constructed situations with known answers (issue 14:
robots drove at walkers their camera had not coloured, and trusted a walker's tracked
velocity that pointed the wrong way)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.control.hostile_evasion import (
    EvasionConfig,
    evasion_goal,
    hostile_threat,
    suspect_tracks,
    walk_velocity,
    walking,
)
from robot.terrain.grid import DRIVABLE, GridGeometry

CFG = EvasionConfig()
START_M = CFG.blast_radius_m + CFG.margin_m  # an evasion starts below this


def test_a_walker_whose_track_says_it_walks_away_is_a_threat_when_it_could_reach_the_robot() -> (
    None
):
    # 6.5 m off, its track says 0.6 m/s away from the robot (a walker that turned at its
    # route's corner: the velocity from the last sweeps is the old leg's)
    away = np.array([[6.5, 0.0, 0.6, 0.0]])
    assert hostile_threat(np.zeros(2), away, CFG) < START_M
    # the same walker 9 m off is not (it cannot close to the blast radius in react_s)
    far = np.array([[9.0, 0.0, 0.6, 0.0]])
    assert hostile_threat(np.zeros(2), far, CFG) >= START_M + CFG.release_m


def test_a_walker_coming_head_on_is_a_threat_early_and_one_walking_past_far_off_is_not() -> None:
    head_on = np.array([[8.0, 0.0, -0.6, 0.0]])  # 4 s ahead: 5.6 m
    assert hostile_threat(np.zeros(2), head_on, CFG) == pytest.approx(5.6)
    past = np.array([[0.0, 9.0, 0.6, 0.0]])  # walks by 9 m off, across
    assert hostile_threat(np.zeros(2), past, CFG) > START_M
    assert hostile_threat(np.zeros(2), np.zeros((0, 4)), CFG) == math.inf


def test_an_uncoloured_person_where_a_hostile_may_have_walked_is_taken_for_it() -> None:
    now = 100.0
    # a hostile seen at (0, 0) 10 s ago: it may be 2 + 0.8 * 10 = 10 m from there now
    sightings = np.array([[0.0, 0.0, now - 10.0]])
    tracks = np.array([[9.5, 0.0], [0.0, -10.5], [20.0, 0.0]])
    assert suspect_tracks(tracks, sightings, now, CFG).tolist() == [True, False, False]
    # the reach stops growing at suspect_reach_max_m
    old = np.array([[0.0, 0.0, now - 50.0]])
    assert suspect_tracks(tracks, old, now, CFG).tolist() == [True, True, False]
    # a sighting older than suspect_memory_s says nothing
    stale = np.array([[0.0, 0.0, now - CFG.suspect_memory_s - 1.0]])
    assert not suspect_tracks(tracks, stale, now, CFG).any()
    # nothing seen: nobody is a suspect
    assert not suspect_tracks(tracks, np.zeros((0, 3)), now, CFG).any()


def test_the_evasion_goal_is_the_safe_cell_the_robot_faces_not_the_one_behind_it() -> None:
    # an open 30 x 10 m strip; a still hostile due north of the robot: the safe cells east
    # and west are as far by path, the robot faces east
    geometry = GridGeometry(origin_m=(-15.0, -5.0), resolution_m=0.2, rows=50, cols=150)
    classes = np.full(geometry.shape, DRIVABLE, dtype=np.uint8)
    hostile = np.array([[0.0, 3.0, 0.0, 0.0]])
    cfg = EvasionConfig(predict_s=0.0)
    east = evasion_goal(
        classes, geometry, np.zeros(2), hostile, cfg, robot_radius_m=0.3, heading_rad=0.0
    )
    west = evasion_goal(
        classes, geometry, np.zeros(2), hostile, cfg, robot_radius_m=0.3, heading_rad=math.pi
    )
    assert east is not None and west is not None
    for goal in (east, west):
        assert math.dist(goal, (0.0, 3.0)) >= cfg.blast_radius_m + cfg.clear_m - 0.2
    assert east[0] > 0 > west[0]


def test_a_walker_is_walking_and_a_post_whose_segment_jitters_is_not() -> None:
    now = 50.0
    t = np.arange(now - 2.9, now + 1e-9, 0.1)
    walker = np.column_stack([t, 0.6 * (t - t[0]), np.zeros_like(t)])  # 0.6 m/s for 2.9 s
    assert walking(walker, now, CFG)
    v = walk_velocity(walker, now, CFG)
    assert v is not None and np.allclose(v, (0.6, 0.0))
    rng = np.random.default_rng(3)
    post = np.column_stack([t, rng.normal(0.0, 0.15, len(t)), rng.normal(0.0, 0.15, len(t))])
    assert not walking(post, now, CFG)
    # a walker seen for half a second says nothing yet; measurements before the window
    # do not count
    assert not walking(walker[-5:], now, CFG)
    assert not walking(walker, now + 10.0, CFG)


def test_an_idle_robot_follows_a_walker_leaving_its_view_and_stays_when_it_is_near() -> None:
    from robot.control.hostile_evasion import keep_in_view_goal

    cfg = EvasionConfig(keep_view=True)  # off by default (its docstring's measurement)
    p = np.array([0.0, 0.0])
    walker = np.array([[12.0, 0.0, 0.6, 0.0]])  # walking away, 12 m off
    goal = keep_in_view_goal(p, walker, cfg, following=False)
    assert goal is not None and np.allclose(goal, [12.0 - cfg.keep_m, 0.0])
    # within keep_far_m it stays; once following, it goes on to keep_m + keep_arrive_m
    mid = np.array([[9.5, 0.0, 0.0, 0.0]])
    assert keep_in_view_goal(p, mid, cfg, following=False) is None
    assert keep_in_view_goal(p, mid, cfg, following=True) is not None
    # too far to be its watch (beyond keep_within_m), or none: it stays
    assert keep_in_view_goal(p, np.array([[30.0, 0.0, 0.0, 0.0]]), cfg, following=True) is None
    assert keep_in_view_goal(p, np.zeros((0, 4)), cfg, following=True) is None
    # the goal is outside the distance at which it would back away from a still walker
    assert hostile_threat(goal, np.array([[12.0, 0.0, 0.0, 0.0]]), cfg) >= (
        cfg.blast_radius_m + cfg.margin_m
    )
    assert keep_in_view_goal(p, walker, EvasionConfig(keep_view=False), following=False) is None


def _walled_map() -> tuple[np.ndarray, GridGeometry]:
    """A 30 m map with a building (x 8-9 m, y -3-3 m) standing across the line from the
    origin to a walker at x 13-15 m."""
    geometry = GridGeometry((-10.0, -10.0), 0.1, 300, 300)
    wall = np.zeros(geometry.shape, dtype=bool)
    rows, cols = geometry.cell_of(
        np.array([[x, y] for x in np.arange(8.0, 9.01, 0.05) for y in np.arange(-3.0, 3.01, 0.05)])
    ).T
    wall[rows, cols] = True
    return wall, geometry


def test_the_follow_point_sees_the_walker_past_a_building() -> None:
    """Issue 14, small world seed 11: the follow point on the line to the robot stood behind
    a building; with its map the robot picks a reachable point in view of the walker."""
    from robot.control.hostile_evasion import keep_in_view_goal, line_of_sight

    cfg = EvasionConfig(keep_view=True)
    wall, geometry = _walled_map()
    p = np.array([0.0, 0.0])
    walker = np.array([[13.0, 0.0, 0.6, 0.0]])
    target = walker[0, :2] + cfg.keep_predict_s * walker[0, 2:]
    line = keep_in_view_goal(p, walker, cfg, following=False)  # no map: on the line
    assert line is not None and not line_of_sight(line, target, wall, geometry)
    goal = keep_in_view_goal(
        p, walker, cfg, following=False, sight=wall, blocked=wall, geometry=geometry
    )
    assert goal is not None
    assert line_of_sight(goal, target, wall, geometry)
    rng = float(np.hypot(*(goal - target)))
    assert cfg.keep_m - cfg.keep_sight_band_m - 1e-6 <= rng <= cfg.keep_m + 1e-6
    assert abs(goal[1]) > 3.0  # past the building's end
    # the point it holds is kept while it serves
    again = keep_in_view_goal(
        p, walker, cfg, following=True, sight=wall, blocked=wall, geometry=geometry, previous=goal
    )
    assert again is not None and np.allclose(again, goal)
    # without keep_sight the map is not used
    off = EvasionConfig(keep_view=True, keep_sight=False)
    plain = keep_in_view_goal(
        p, walker, off, following=False, sight=wall, blocked=wall, geometry=geometry
    )
    assert plain is not None and np.allclose(plain, line)


def test_a_watcher_in_range_moves_only_when_a_building_cuts_its_view() -> None:
    from robot.control.hostile_evasion import keep_in_view_goal, line_of_sight

    cfg = EvasionConfig(keep_view=True)
    wall, geometry = _walled_map()
    p = np.array([5.0, 0.0])
    walker = np.array([[13.5, 0.0, 0.0, 0.0]])  # 8.5 m off, within keep_far_m: it would hold
    assert keep_in_view_goal(p, walker, cfg, following=False) is None
    goal = keep_in_view_goal(
        p, walker, cfg, following=False, sight=wall, blocked=wall, geometry=geometry
    )
    assert goal is not None and line_of_sight(goal, walker[0, :2], wall, geometry)
    clear = np.zeros_like(wall)
    assert (
        keep_in_view_goal(
            p, walker, cfg, following=False, sight=clear, blocked=clear, geometry=geometry
        )
        is None
    )


def test_the_follow_point_is_reachable() -> None:
    """A point in view but walled off from the robot is not chosen."""
    from robot.control.hostile_evasion import sight_point

    cfg = EvasionConfig(keep_view=True)
    geometry = GridGeometry((-10.0, -10.0), 0.1, 300, 300)
    # the robot shut in a box of walls (x -2-2, y -2-2) with the walker outside
    box = np.zeros(geometry.shape, dtype=bool)
    for x in np.arange(-2.0, 2.01, 0.05):
        for y in (-2.0, 2.0):
            box[tuple(geometry.cell_of(np.array([[x, y]]))[0])] = True
            box[tuple(geometry.cell_of(np.array([[y, x]]))[0])] = True
    sight = np.zeros_like(box)  # the view over the box is clear (a low wall)
    walker = np.array([[14.0, 0.0, 0.0, 0.0]])  # its ring lies wholly outside the box
    got = sight_point(
        np.zeros(2),
        walker[0, :2],
        walker,
        cfg,
        sight=sight,
        blocked=box,
        geometry=geometry,
        robot_radius_m=0.3,
    )
    assert got is None
    inside = sight_point(
        np.zeros(2),
        walker[0, :2],
        walker,
        cfg,
        sight=sight,
        blocked=np.zeros_like(box),
        geometry=geometry,
        robot_radius_m=0.3,
    )
    assert inside is not None  # without the box the nearest ring point serves
