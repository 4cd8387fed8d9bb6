"""Deadlock detection and breaking between teammates (robot.control.deadlock)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.control.deadlock import DeadlockBreaker, DeadlockConfig, Phase, path_block_distance
from robot.terrain.grid import GridGeometry

GEO = GridGeometry((-10.0, -10.0), 0.05, 400, 400)


def _drive_straight(b: DeadlockBreaker, goal: tuple[float, float], x1: float, t0: float = 0.0):
    """Drive from x=0 to x=x1 along y=0 at 1 m/s, 10 Hz; returns the end time."""
    t = t0
    for x in np.arange(0.0, x1, 0.1):
        assert b.update(t, (x, 0.0), goal) is Phase.DRIVE
        t += 0.1
    return t


def _stand(b: DeadlockBreaker, xy, goal, t: float, seconds: float) -> tuple[float, Phase]:
    phase = b.phase
    for _ in range(int(round(seconds / 0.1))):
        phase = b.update(t, xy, goal)
        t += 0.1
        if phase is Phase.DEADLOCKED:
            break
    return t, phase


def test_stall_is_detected_after_the_jittered_wait_and_not_while_progressing() -> None:
    cfg = DeadlockConfig(stall_s=6.0, stall_jitter_s=4.0)
    goal = (30.0, 0.0)
    waits = []
    for seed in range(8):
        b = DeadlockBreaker(cfg, seed=seed)
        t = _drive_straight(b, goal, 10.0)  # progress all along: no detection
        t_stop = t
        t, phase = _stand(b, (10.0, 0.0), goal, t, 20.0)
        assert phase is Phase.DEADLOCKED
        waits.append(t - t_stop)
        assert b.deadlocks == 1 and b.attempts == 1
    assert all(6.0 - 0.2 <= w <= 10.0 + 0.2 for w in waits)
    assert max(waits) - min(waits) > 1.0  # robots do not all give way at the same instant


def test_livelock_back_and_forth_is_detected() -> None:
    cfg = DeadlockConfig(livelock_s=20.0, stall_s=6.0, stall_jitter_s=0.0)
    b = DeadlockBreaker(cfg, seed=1)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 5.0)
    phase = Phase.DRIVE
    for k in range(400):  # driving to and fro between x=1 and x=5, never closer to the goal
        x = 3.0 + 2.0 * math.cos(k * 0.1)
        phase = b.update(t, (x, 0.0), goal)
        t += 0.1
        if phase is Phase.DEADLOCKED:
            break
    assert phase is Phase.DEADLOCKED
    assert 20.0 <= t - 0.5 <= 26.0


def test_backoff_goes_back_along_the_trail_to_the_first_roomy_point() -> None:
    b = DeadlockBreaker(DeadlockConfig(stall_jitter_s=0.0, backoff_min_m=1.5), seed=0)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 8.0)  # from x=0 through a corridor x in [3, 7.9]
    t, phase = _stand(b, (7.9, 0.0), goal, t, 15.0)
    assert phase is Phase.DEADLOCKED
    obstacle = np.zeros(GEO.shape, dtype=bool)
    rows = GEO.cell_of(np.array([[5.0, -0.9], [5.0, 0.9]]))[:, 0]
    c0, c1 = GEO.cell_index((3.0, 0.0))[1], GEO.cell_index((7.9, 0.0))[1]
    obstacle[rows[0], c0:c1] = obstacle[rows[1], c0:c1] = True  # walls 0.9 m each side
    target = b.start_backoff(t, obstacle, GEO)
    assert b.phase is Phase.BACKOFF and target is not None
    # outside the corridor, with 1.4 m of room: at least 1.4 m back from its entrance
    assert 3.0 - 1.4 - 0.1 <= target[0] <= 3.0 - 1.4 + 0.25 and abs(target[1]) < 1e-9
    # backing off, then holding a random time, then driving again
    phase = b.update(t, (7.0, 0.0), goal)
    assert phase is Phase.BACKOFF
    phase = b.update(t + 5.0, target, goal)
    assert phase is Phase.HOLD
    t2, phase = t + 5.0, Phase.HOLD
    while phase is Phase.HOLD:
        t2 += 0.1
        phase = b.update(t2, target, goal)
    cfg = b.config
    assert cfg.hold_s <= t2 - (t + 5.0) <= cfg.hold_s + cfg.hold_spread_s + 0.2
    assert phase is Phase.DRIVE and b.backoff_target_in_odom is None


def test_refine_moves_the_target_further_back_when_a_newer_map_shows_no_room() -> None:
    b = DeadlockBreaker(DeadlockConfig(stall_jitter_s=0.0, backoff_min_m=1.0), seed=0)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 8.0)
    t, _ = _stand(b, (7.9, 0.0), goal, t, 15.0)
    empty = np.zeros(GEO.shape, dtype=bool)
    first = b.start_backoff(t, empty, GEO)  # nothing seen behind: 1 m back looks roomy
    assert first is not None and abs(first[0] - 6.9) < 0.25
    seen = empty.copy()
    r, c0 = GEO.cell_index((3.0, 0.8))
    c1 = GEO.cell_index((8.0, 0.8))[1]
    seen[r, c0:c1] = True  # now it sees a wall 0.8 m to the side from x = 3 on
    refined = b.refine_backoff(seen, GEO)
    # 1.4 m from the wall's end at (3, 0.8): x <= 3 - sqrt(1.4^2 - 0.8^2) = 1.85
    assert refined is not None and 1.6 < refined[0] < 1.9
    np.testing.assert_array_equal(b.refine_backoff(seen, GEO), refined)  # stable


def test_something_receding_restarts_the_wait() -> None:
    cfg = DeadlockConfig(stall_s=6.0, stall_jitter_s=0.0)
    b = DeadlockBreaker(cfg, seed=0)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 5.0)
    for k in range(100):  # 10 s waiting while the obstacle ahead backs away
        b.note_block_distance(t, 0.2 + 0.05 * k)
        assert b.update(t, (5.0, 0.0), goal) is Phase.DRIVE
        t += 0.1
    for _ in range(70):  # it stopped: the wait runs out
        b.note_block_distance(t, 5.15)
        phase = b.update(t, (5.0, 0.0), goal)
        t += 0.1
    assert phase is Phase.DEADLOCKED


def test_gives_up_after_max_attempts_and_a_new_goal_starts_afresh() -> None:
    cfg = DeadlockConfig(stall_s=2.0, stall_jitter_s=0.0, max_attempts=2, hold_spread_s=0.0)
    b = DeadlockBreaker(cfg, seed=0)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 3.0)
    empty = np.zeros(GEO.shape, dtype=bool)
    for _ in range(2):
        t, phase = _stand(b, (2.9, 0.0), goal, t, 10.0)
        assert phase is Phase.DEADLOCKED
        target = b.start_backoff(t, empty, GEO)
        assert target is not None
        t, phase = _stand(b, target, goal, t, 3.0)  # arrive, hold 2 s, drive again
        assert phase is Phase.DRIVE
    assert b.gave_up
    t, phase = _stand(b, (2.9, 0.0), goal, t, 20.0)
    assert phase is Phase.DRIVE  # no more interference: the task's own timeout decides
    assert b.update(t, (2.9, 0.0), (0.0, 30.0)) is Phase.DRIVE and not b.gave_up


def test_path_block_distance_matches_brute_force() -> None:
    rng = np.random.default_rng(4)
    for _ in range(20):
        obstacle = rng.random(GEO.shape) < 0.0005
        path = np.cumsum(rng.normal(0.0, 0.7, (12, 2)), axis=0)
        pos = path[0] + rng.normal(0.0, 0.1, 2)
        got = path_block_distance(path, pos, obstacle, GEO, robot_radius_m=0.4, lookahead_m=6.0)
        # brute force: walk the same stretch in 1 mm steps
        pts = np.vstack([pos, path])
        seg = np.hypot(*np.diff(pts, axis=0).T)
        along = np.concatenate([[0.0], np.cumsum(seg)])
        s = np.arange(0.0, min(6.0, along[-1]), 0.001)
        xy = np.stack([np.interp(s, along, pts[:, 0]), np.interp(s, along, pts[:, 1])], axis=1)
        centres = GEO.center_of(np.argwhere(obstacle))
        rc = GEO.cell_of(xy)
        here = GEO.center_of(rc)
        d = np.hypot(here[:, None, 0] - centres[None, :, 0], here[:, None, 1] - centres[None, :, 1])
        hit = np.flatnonzero((d <= 0.4 + 1e-9).any(axis=1))
        expected = s[hit[0]] if len(hit) else math.inf
        if math.isinf(expected):
            assert math.isinf(got)
        else:
            assert got == pytest.approx(expected, abs=0.03)


def test_bad_input_and_config_name_the_problem() -> None:
    with pytest.raises(ValueError, match="deadlock.stall_s"):
        DeadlockConfig(stall_s=0.0)
    with pytest.raises(ValueError, match="backoff_min_m"):
        DeadlockConfig(backoff_min_m=30.0, backoff_max_m=10.0)
    with pytest.raises(ValueError, match="max_attempts"):
        DeadlockConfig(max_attempts=0)
    b = DeadlockBreaker()
    with pytest.raises(ValueError, match="goal_in_odom"):
        b.update(0.0, (0.0, 0.0), (math.nan, 0.0))
    with pytest.raises(ValueError, match="no deadlock"):
        b.start_backoff(0.0, np.zeros(GEO.shape, bool), GEO)
    with pytest.raises(ValueError, match="obstacle"):
        path_block_distance(
            [(0, 0), (1, 0)],
            (0, 0),
            np.zeros((3, 3), bool),
            GEO,
            robot_radius_m=0.4,
            lookahead_m=1.0,
        )


def test_a_blocked_way_back_holds_at_once() -> None:
    b = DeadlockBreaker(DeadlockConfig(stall_s=2.0, stall_jitter_s=0.0), seed=0)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 5.0)
    t, phase = _stand(b, (4.9, 0.0), goal, t, 10.0)
    assert b.start_backoff(t, np.zeros(GEO.shape, bool), GEO) is not None
    b.abort_backoff(t)
    assert b.phase is Phase.HOLD and b.backoff_target_in_odom is None


def test_backoffs_that_cannot_move_the_robot_try_elsewhere_then_exhaust() -> None:
    # issue 14: a robot backing off again and again to one trail point without moving
    cfg = DeadlockConfig(
        stall_s=2.0, stall_jitter_s=0.0, hold_s=0.5, hold_spread_s=0.0, backoff_timeout_s=3.0
    )
    b = DeadlockBreaker(cfg, seed=0)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 6.0)
    empty = np.zeros(GEO.shape, dtype=bool)
    here = (5.9, 0.0)
    t, phase = _stand(b, here, goal, t, 10.0)
    assert phase is Phase.DEADLOCKED
    first = b.start_backoff(t, empty, GEO)
    assert first is not None
    # the way back is the trail, reversed, from the robot to the target
    path = b.trail_back_path(here)
    assert path[0][0] == pytest.approx(5.9, abs=0.11) and np.allclose(path[-1], first)
    assert np.all(np.diff(path[:, 0]) < 0)
    t, phase = _stand(b, here, goal, t, 3.2)  # the back-off times out: the robot never moved
    assert phase is Phase.HOLD and b.failed_escapes == 1 and not b.exhausted
    t, phase = _stand(b, here, goal, t, 10.0)
    assert phase is Phase.DEADLOCKED
    second = b.start_backoff(t, empty, GEO)
    assert second is not None and float(np.hypot(*(second - first))) > cfg.arrive_m
    t, phase = _stand(b, here, goal, t, 3.2)
    assert b.exhausted and "could not move" in b.exhaustion_reason
    b.reset()
    assert not b.exhausted and b.failed_escapes == 0


def test_a_backoff_that_moves_clears_the_failures_and_giving_up_then_stalling_exhausts() -> None:
    cfg = DeadlockConfig(
        stall_s=2.0, stall_jitter_s=0.0, hold_s=0.5, hold_spread_s=0.0, max_attempts=2
    )
    b = DeadlockBreaker(cfg, seed=0)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 6.0)
    empty = np.zeros(GEO.shape, dtype=bool)
    for _ in range(2):
        t, phase = _stand(b, (5.9, 0.0), goal, t, 10.0)
        assert phase is Phase.DEADLOCKED
        target = b.start_backoff(t, empty, GEO)
        assert target is not None
        t, phase = _stand(b, target, goal, t, 2.0)  # arrived: it moved
        assert b.failed_escapes == 0 and not b.exhausted
    assert b.gave_up
    t, phase = _stand(b, (5.9, 0.0), goal, t, 10.0)
    assert phase is Phase.DRIVE and b.exhausted and "no progress" in b.exhaustion_reason
    assert b.update(t, (5.9, 0.0), (0.0, 30.0)) is Phase.DRIVE and not b.exhausted


def test_trail_back_path_is_empty_unless_backing_off() -> None:
    b = DeadlockBreaker(DeadlockConfig(stall_s=2.0, stall_jitter_s=0.0), seed=0)
    _drive_straight(b, (30.0, 0.0), 3.0)
    assert b.trail_back_path((2.9, 0.0)).shape == (0, 2)
    with pytest.raises(ValueError, match="position_in_odom"):
        b.trail_back_path((math.inf, 0.0))


def test_backoff_target_is_away_from_the_robot_when_the_trail_coiled() -> None:
    b = DeadlockBreaker(DeadlockConfig(stall_s=2.0, stall_jitter_s=0.0, backoff_min_m=1.5), seed=0)
    goal = (30.0, 0.0)
    t = _drive_straight(b, goal, 4.0)  # in along y=0 to x=4, then a tight loop in a nook
    for k in range(60):
        a = k * 2 * math.pi / 30
        xy = (4.0 + 0.3 * math.sin(a), 0.3 - 0.3 * math.cos(a))
        b.update(t, xy, goal)
        t += 0.1
    t, phase = _stand(b, (4.0, 0.0), goal, t, 10.0)
    assert phase is Phase.DEADLOCKED
    target = b.start_backoff(t, np.zeros(GEO.shape, dtype=bool), GEO)
    assert target is not None and float(np.hypot(target[0] - 4.0, target[1])) >= 1.5 - 1e-6
