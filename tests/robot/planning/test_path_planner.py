"""The composed on-robot planner (paper 5.4) over terrain maps in odom."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.ndimage import distance_transform_edt
from scipy.sparse.csgraph import dijkstra as scipy_dijkstra

from robot.planning.config_space import configuration_space
from robot.planning.dijkstra import grid_graph
from robot.planning.path_relaxation import clearance_field, path_clearance, segments_free
from robot.planning.planner import PathPlanner, PlannerConfig
from robot.terrain.classifier import TerrainConfig, classify_sweep
from robot.terrain.grid import DRIVABLE, OBSTACLE, UNKNOWN, GridGeometry
from robot.terrain.synthetic_scene import cast_sweep, random_scene

GEO = GridGeometry((-5.0, -5.0), 0.05, 200, 200)


def _doorway_map() -> np.ndarray:
    classes = np.full(GEO.shape, DRIVABLE, dtype=np.uint8)
    classes[99:101, :] = OBSTACLE
    classes[99:101, 90:122] = DRIVABLE  # 1.6 m doorway
    return classes


def _cells_to_xy_path(result) -> np.ndarray:  # type: ignore[no-untyped-def]
    return np.stack(
        [
            (result.path_in_odom[:, 1] - GEO.origin_m[1]) / GEO.resolution_m - 0.5,
            (result.path_in_odom[:, 0] - GEO.origin_m[0]) / GEO.resolution_m - 0.5,
        ],
        axis=1,
    )


@pytest.mark.parametrize("clearance_cost", [0.0, 2.0])
@pytest.mark.parametrize("unknown", ["free", "obstacle", "cost"])
def test_dijkstra_length_equals_scipy_and_clearance_is_kept(
    unknown: str, clearance_cost: float
) -> None:
    cfg = PlannerConfig(
        unknown=unknown,  # type: ignore[arg-type]
        robot_radius_m=0.3,
        clearance_m=0.6,
        clearance_cost=clearance_cost,
    )
    classes = _doorway_map()
    classes[150:170, 20:180] = UNKNOWN
    start, goal = np.array([-4.0, -4.0]), np.array([-3.5, 4.0])
    result = PathPlanner(cfg).plan(classes, GEO, start, goal)
    assert result.ok, result.reason

    # The oracle: the same graph built independently, solved by scipy.
    hard = classes == OBSTACLE
    if unknown == "obstacle":
        hard |= classes == UNKNOWN
    blocked = configuration_space(hard, robot_radius_m=0.3, resolution_m=0.05)
    cost = np.ones(GEO.shape)
    if unknown == "cost":
        cost[classes == UNKNOWN] = cfg.unknown_cost
    # comfort cost: 1 at 0.6 m from the nearest obstacle, 1 + clearance_cost at 0.3 m
    dist_m = distance_transform_edt(~hard) * 0.05
    cost *= 1.0 + clearance_cost * np.clip((0.6 - dist_m) / 0.3, 0.0, 1.0)
    cost[blocked] = np.inf
    s = GEO.cell_of(start)
    g = GEO.cell_of(goal)
    ref = scipy_dijkstra(grid_graph(cost, resolution_m=0.05), indices=s[0] * 200 + s[1])
    assert result.dijkstra_length_m == pytest.approx(ref[g[0] * 200 + g[1]], rel=1e-6)

    # After relaxation and smoothing: collision-free, and through the doorway with the
    # configured clearance (the doorway is wider than twice the clearance).
    cells = _cells_to_xy_path(result)
    assert segments_free(cells[1:-1], blocked)
    clearance = path_clearance(cells, clearance_field(hard, resolution_m=0.05))
    assert result.min_clearance_m >= 0.3
    crossing = np.abs(result.path_in_odom[:, 1] - 0.0) < 0.15
    assert crossing.any() and clearance[crossing].min() >= 0.6 - 0.05
    np.testing.assert_allclose(result.path_in_odom[[0, -1]], [start, goal])
    assert result.length_m >= math.dist(start, goal)


def test_cost_policy_prefers_seen_terrain() -> None:
    classes = np.full(GEO.shape, DRIVABLE, dtype=np.uint8)
    classes[60:140, 60:140] = UNKNOWN  # unseen block in the straight line
    start, goal = (-3.0, 0.0), (3.0, 0.0)
    free = PathPlanner(PlannerConfig(unknown="free")).plan(classes, GEO, start, goal)
    cost = PathPlanner(PlannerConfig(unknown="cost", unknown_cost=3.0)).plan(
        classes, GEO, start, goal
    )
    blocked = PathPlanner(PlannerConfig(unknown="obstacle")).plan(classes, GEO, start, goal)
    assert free.ok and cost.ok and blocked.ok
    through = lambda r: (np.abs(r.path_in_odom) < 1.5).all(axis=1).any()  # noqa: E731
    assert through(free) and not through(cost) and not through(blocked)


def test_no_path_is_reported() -> None:
    classes = _doorway_map()
    classes[99:101, :] = OBSTACLE  # close the door
    result = PathPlanner().plan(classes, GEO, (0.0, -3.0), (0.0, 3.0))
    assert result.status == "no_path" and not result.ok
    assert result.path_in_odom.shape == (0, 2) and math.isinf(result.dijkstra_length_m)
    assert "no path" in result.reason


def test_blocked_start_and_goal_are_reported() -> None:
    classes = _doorway_map()
    planner = PathPlanner(PlannerConfig(robot_radius_m=0.4, escape=False))
    assert planner.plan(classes, GEO, (-3.0, -0.2), (0.0, 3.0)).status == "start_blocked"
    assert planner.plan(classes, GEO, (-3.0, 3.0), (-3.0, 0.1)).status == "goal_blocked"
    # Escape cannot leave an obstacle cell itself.
    on_wall = PathPlanner(PlannerConfig(robot_radius_m=0.4)).plan(
        classes, GEO, (-3.0, 0.0), (0.0, 3.0)
    )
    assert on_wall.status == "start_blocked" and "clearance 0.000" in on_wall.reason


def test_start_inside_the_margin_escapes_without_getting_closer() -> None:
    classes = _doorway_map()
    cfg = PlannerConfig(robot_radius_m=0.4)
    start = (-3.0, -0.2)  # 0.15 m from the wall's face: inside the 0.4 m margin
    result = PathPlanner(cfg).plan(classes, GEO, start, (-3.0, -3.0))
    assert result.ok and result.escaped
    hard = classes == OBSTACLE
    clearance = clearance_field(hard, resolution_m=GEO.resolution_m)
    cells = result.dijkstra_cells
    s = GEO.cell_index(start)
    assert (clearance[cells[:, 0], cells[:, 1]] >= clearance[s] - 1e-9).all()
    blocked = configuration_space(hard, robot_radius_m=0.4, resolution_m=GEO.resolution_m)
    assert not blocked[cells[-1, 0], cells[-1, 1]]


def test_goal_tolerance_moves_a_blocked_goal_to_the_nearest_free_cell() -> None:
    classes = _doorway_map()
    cfg = PlannerConfig(robot_radius_m=0.4, goal_tolerance_m=0.5)
    result = PathPlanner(cfg).plan(classes, GEO, (-3.0, 3.0), (-3.0, 0.3))
    assert result.ok and result.goal_in_odom is not None
    gx, gy = result.goal_in_odom
    assert gx == pytest.approx(-3.0, abs=0.05) and 0.4 <= gy <= 0.5 + 1e-9
    tight = PathPlanner(PlannerConfig(robot_radius_m=0.4, goal_tolerance_m=0.05))
    assert tight.plan(classes, GEO, (-3.0, 3.0), (-3.0, 0.1)).status == "goal_blocked"


def test_unknown_cells_under_the_robot_do_not_block_it() -> None:
    classes = np.full(GEO.shape, UNKNOWN, dtype=np.uint8)
    classes[:, 120:] = DRIVABLE
    cfg = PlannerConfig(unknown="obstacle", robot_radius_m=0.3)
    result = PathPlanner(cfg).plan(classes, GEO, (1.1, 0.0), (4.0, 0.0))
    assert result.ok, result.reason


def test_plans_on_a_classified_sweep() -> None:
    rng = np.random.default_rng(3)
    hits = cast_sweep(random_scene(rng), (0.0, 0.0, 0.0), rng=rng)
    classes, geo = classify_sweep(hits.points_in_base, hits.odom_from_base, config=TerrainConfig())
    result = PathPlanner().plan(classes, geo, (0.0, 0.0), (8.0, 6.0))
    assert result.ok, result.reason
    assert result.min_clearance_m >= PlannerConfig().robot_radius_m


@pytest.mark.parametrize(
    ("classes", "start", "goal", "match"),
    [
        (np.zeros((10, 10), np.uint8), (0, 0), (1, 1), "classes: shape"),
        (np.zeros(GEO.shape, np.int64), (0, 0), (1, 1), "classes: expected dtype uint8"),
        (np.full(GEO.shape, 5, np.uint8), (0, 0), (1, 1), "classes: values"),
        (np.zeros(GEO.shape, np.uint8), (0, 0), (np.nan, 1), "goal_in_odom: expected 2 finite"),
        (np.zeros(GEO.shape, np.uint8), (0, 0), (1, 2, 3), "goal_in_odom: expected 2 finite"),
        (
            np.zeros(GEO.shape, np.uint8),
            (0, 0),
            (12.0, 1.0),
            r"goal_in_odom \(12.000, 1.000\) is "
            r"outside the map x \[-5.000, 5.000\)",
        ),
        (np.zeros(GEO.shape, np.uint8), (-9, 0), (1, 1), "start_in_odom .* outside the map"),
    ],
)
def test_bad_input_names_the_problem(classes, start, goal, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=match):
        PathPlanner().plan(classes, GEO, start, goal)


def test_config_rejects_bad_values() -> None:
    with pytest.raises(ValueError, match="unknown_cost"):
        PlannerConfig(unknown_cost=0.5)
    with pytest.raises(ValueError, match="robot_radius_m"):
        PlannerConfig(robot_radius_m=-1.0)


def test_start_equals_goal() -> None:
    classes = _doorway_map()
    result = PathPlanner().plan(classes, GEO, (-2.99, -2.99), (-2.96, -2.97))
    assert result.ok and result.length_m == 0.0 and result.dijkstra_length_m == 0.0
    np.testing.assert_allclose(result.path_in_odom, [[-2.96, -2.97]])


def test_cost_multiplier_steers_the_path_and_matches_scipy() -> None:
    classes = np.full(GEO.shape, DRIVABLE, dtype=np.uint8)
    mult = np.ones(GEO.shape)
    mult[80:120, 95:105] = 5.0  # a sandy strip across the straight line
    start, goal = (-3.0, 0.0), (3.0, 0.0)
    plain = PathPlanner().plan(classes, GEO, start, goal)
    sandy = PathPlanner().plan(classes, GEO, start, goal, cost_multiplier=mult)
    assert plain.ok and sandy.ok
    assert sandy.dijkstra_length_m > plain.dijkstra_length_m
    cells = sandy.dijkstra_cells
    assert (mult[cells[:, 0], cells[:, 1]] == 1.0).all()  # goes around the strip
    blocked = configuration_space(
        classes == OBSTACLE, robot_radius_m=PlannerConfig().robot_radius_m, resolution_m=0.05
    )
    cost = np.where(blocked, np.inf, mult)
    s, g = GEO.cell_index(start), GEO.cell_index(goal)
    ref = scipy_dijkstra(grid_graph(cost, resolution_m=0.05), indices=s[0] * 200 + s[1])
    assert sandy.dijkstra_length_m == pytest.approx(ref[g[0] * 200 + g[1]], rel=1e-12)
    with pytest.raises(ValueError, match="cost_multiplier: values"):
        PathPlanner().plan(classes, GEO, start, goal, cost_multiplier=np.zeros(GEO.shape))
    with pytest.raises(ValueError, match="cost_multiplier: shape"):
        PathPlanner().plan(classes, GEO, start, goal, cost_multiplier=np.ones((3, 3)))


def test_clearance_cost_prefers_going_around_over_squeezing_between() -> None:
    # two robot-sized boxes 1.0 m apart: the straight line squeezes between them (0.1 m to
    # spare on each side of a 0.4 m disc); a little detour around them is roomy
    classes = np.full(GEO.shape, DRIVABLE, dtype=np.uint8)
    for y0 in (0.5, -1.0):
        r0, c0 = GEO.cell_index((-0.3, y0))
        classes[r0 : r0 + 10, c0 : c0 + 12] = OBSTACLE
    start, goal = (-3.0, 0.0), (3.0, 0.0)

    def crossing_y(clearance_cost: float) -> float:
        cfg = PlannerConfig(clearance_cost=clearance_cost)
        result = PathPlanner(cfg).plan(classes, GEO, start, goal)
        assert result.ok, result.reason
        xy = result.path_in_odom
        return float(np.interp(0.0, xy[:, 0], xy[:, 1]))

    assert abs(crossing_y(0.0)) < 0.2  # minimum distance: through the gap
    assert abs(crossing_y(2.0)) > 1.0  # comfort as a cost: around the boxes
    # with no way around (a wall with a doorway 1.1 m wide) the cost still lets it through
    door = np.full(GEO.shape, DRIVABLE, dtype=np.uint8)
    door[99:101, :] = OBSTACLE
    door[99:101, 89:111] = DRIVABLE
    result = PathPlanner(PlannerConfig(clearance_cost=2.0)).plan(door, GEO, (0, -3), (0, 3))
    assert result.ok and result.min_clearance_m >= 0.4


@pytest.mark.parametrize("unknown", ["free", "obstacle"])
def test_a_planner_reusing_its_last_obstacle_fields_plans_as_a_fresh_one(unknown: str) -> None:
    # the configuration space and clearance of the last obstacle grid are kept: plans over
    # the same grid again (other start or goal), a changed grid and the first grid again
    # equal those of a planner that has planned nothing before
    rng = np.random.default_rng(3)
    geo = GridGeometry((0.0, 0.0), 0.1, 60, 60)
    maps = []
    for _ in range(3):
        cls = np.full(geo.shape, DRIVABLE, dtype=np.uint8)
        cls[rng.random(geo.shape) < 0.1] = UNKNOWN
        for _ in range(8):
            r, c = rng.integers(0, 55, 2)
            cls[r : r + int(rng.integers(1, 12)), c : c + int(rng.integers(1, 4))] = OBSTACLE
        maps.append(cls)
    config = PlannerConfig(unknown=unknown)  # type: ignore[arg-type]
    kept = PathPlanner(config)
    order = [0, 0, 1, 1, 0, 2, 2]
    for k, i in enumerate(order):
        start, goal = rng.uniform(0.5, 5.5, 2), rng.uniform(0.5, 5.5, 2)
        got = kept.plan(maps[i], geo, start, goal)
        want = PathPlanner(config).plan(maps[i], geo, start, goal)
        assert got.status == want.status and got.reason == want.reason, k
        np.testing.assert_array_equal(got.path_in_odom, want.path_in_odom)
        np.testing.assert_array_equal(got.dijkstra_cells, want.dijkstra_cells)
        assert (got.length_m, got.min_clearance_m, got.escaped, got.goal_in_odom) == (
            want.length_m,
            want.min_clearance_m,
            want.escaped,
            want.goal_in_odom,
        )
    if unknown == "free":
        assert kept.field_reuses == 3  # the repeats of the same grid


def test_clearance_costs_in_one_pass_equal_the_numpy_passes() -> None:
    """The compiled cost pass (speed) gives the costs of the numpy passes it replaced, bit for
    bit: tight cells scaled, blocked cells infinite, the rest untouched."""
    from robot.planning.planner import _clearance_costs

    rng = np.random.default_rng(11)
    cfg = PlannerConfig()
    comfort = cfg.clearance_m - cfg.robot_radius_m
    for _ in range(20):
        shape = (int(rng.integers(1, 60)), int(rng.integers(1, 60)))
        base = 1.0 + rng.random(shape) * rng.integers(0, 4)
        clearance = rng.random(shape) * 1.2
        blocked = rng.random(shape) < 0.2
        expected = base.copy()
        tight = clearance < cfg.clearance_m
        expected[tight] *= 1.0 + cfg.clearance_cost * np.minimum(
            1.0, (cfg.clearance_m - clearance[tight]) / comfort
        )
        expected[blocked] = np.inf
        got = base.copy()
        _clearance_costs(
            got, clearance, blocked, cfg.clearance_m, cfg.clearance_cost, comfort, True
        )
        assert np.array_equal(got.view(np.int64), expected.view(np.int64))
        untouched = base.copy()
        _clearance_costs(
            untouched, clearance, blocked, cfg.clearance_m, cfg.clearance_cost, comfort, False
        )
        assert np.array_equal(untouched, np.where(blocked, np.inf, base))
