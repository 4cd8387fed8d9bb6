"""Global map rasterization: covering and cached submaps equal the naive map (paper 4.8)."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from gcs.mapping.rasterization import (
    FREE,
    OCCUPIED,
    UNKNOWN,
    OccupancyMap,
    RasterConfig,
    Rasterizer,
)
from tests.gcs.mapping.rasterworlds import box_world, drive, grid_at

SIZE = (48.0, 36.0)


def assert_same(a: OccupancyMap, b: OccupancyMap) -> None:
    assert a.origin_in_map == b.origin_in_map
    assert a.resolution_m == b.resolution_m
    assert a.values.shape == b.values.shape
    diff = np.count_nonzero(a.values != b.values)
    assert diff == 0, f"{diff} cells differ"


def close_loop(poses: dict[int, np.ndarray], chain: list[int], rng: np.random.Generator) -> None:
    """Move ``chain`` by a correction ramped along it (rotation about its first node)."""
    d_yaw, d_xy = rng.normal(0, 0.02), rng.normal(0, 0.15, 2)
    pivot = poses[chain[0]][:2].copy()
    for i, key in enumerate(chain):
        w = (i + 1) / len(chain)
        c, s = math.cos(w * d_yaw), math.sin(w * d_yaw)
        rel = poses[key][:2] - pivot
        poses[key] = np.array(
            [pivot[0] + c * rel[0] - s * rel[1] + w * d_xy[0],
             pivot[1] + s * rel[0] + c * rel[1] + w * d_xy[1],
             poses[key][2] + w * d_yaw]
        )  # fmt: skip


@pytest.mark.parametrize(
    "config",
    [
        RasterConfig(),
        RasterConfig(submap_nodes=4, tile_cells=16),
        RasterConfig(cover=False),
        RasterConfig(cache=False),
    ],
    ids=["default", "small-submaps-tiles", "cache-only", "cover-only"],
)
def test_cover_and_cache_equal_the_naive_map_cell_for_cell(config: RasterConfig) -> None:
    """Four robots revisit a walled world; between rasterizations nodes are appended (one
    with an earlier time than nodes already in), loop closures move chains of nodes, a node
    loses its pose and gets it back. Every map equals the naive one, and the covering and
    the cache really skip work."""
    walls = box_world(SIZE, seed=2)
    rng = np.random.default_rng(2)
    routes = {r: drive(rng, SIZE, 40, stop_every=7) for r in range(4)}
    raster = Rasterizer(config)
    truth: dict[int, np.ndarray] = {}
    poses: dict[int, np.ndarray] = {}
    added = {r: 0 for r in routes}

    def add(robot: int, count: int, t_offset: float = 0.0) -> None:
        for _ in range(min(count, len(routes[robot]) - added[robot])):
            k = added[robot]
            key = (robot << 32) | k
            grid, origin = grid_at(walls, routes[robot][k])
            raster.add_node(key, 2.0 * k + 0.3 * robot + t_offset, grid, origin, 0.1)
            truth[key] = routes[robot][k]
            poses[key] = routes[robot][k].copy()
            added[robot] += 1

    for r in range(3):
        add(r, 25)
    skipped = reused = 0
    for step in range(8):
        if step == 2:
            add(3, 10, t_offset=-60.0)  # a robot heard late: older than most nodes in
        for r in range(4):
            if added[r]:
                add(r, 2)
        robot = step % 4
        chain = [(robot << 32) | k for k in range(added[robot])][-12:]
        if chain:
            close_loop(poses, chain, rng)
        if step == 4:
            hidden = (1 << 32) | 3
            given = {k: v for k, v in poses.items() if k != hidden}
        else:
            given = dict(poses)
        fast = raster.rasterize(given)
        stats = raster.stats
        assert_same(fast, raster.rasterize_naive(given))
        skipped += stats.nodes - stats.kept
        reused += stats.reused
    if config.cover:
        assert skipped > 0
    if config.cache:
        assert reused > 0


def test_latest_observation_wins_and_removes_trails() -> None:
    """Two nodes at one pose: the earlier saw an obstacle (a passer-by), the later saw the
    cell empty. The map shows it free; with the times swapped, occupied."""
    obstacle = np.ones((1, 1), dtype=bool)
    nothing = np.zeros((0, 0), dtype=bool)
    pose = np.array([5.0, 5.0, 0.3])
    for t_obstacle, t_empty, expected in ((0.0, 1.0, FREE), (1.0, 0.0, OCCUPIED)):
        for config in (RasterConfig(), RasterConfig(cover=False, cache=False)):
            raster = Rasterizer(config)
            raster.add_node(1, t_obstacle, obstacle, (1.0, 0.0), 0.1)
            raster.add_node(2, t_empty, nothing, (0.0, 0.0), 0.1)
            m = raster.rasterize({1: pose, 2: pose})
            c, s = math.cos(0.3), math.sin(0.3)
            point = pose[:2] + np.array([c * 1.05 - s * 0.05, s * 1.05 + c * 0.05])
            ((row, col),) = m.cells_of(point[None])
            assert m.values[row, col] == expected


def test_geometry_of_one_node() -> None:
    """A node at (10, 5) facing +y with one occupied cell 1.05 m ahead, 0.05 m left."""
    raster = Rasterizer(RasterConfig(free_range_m=2.0))
    grid = np.ones((1, 1), dtype=bool)
    raster.add_node(7, 0.0, grid, (1.0, 0.0), 0.1)
    m = raster.rasterize({7: (10.0, 5.0, math.pi / 2)})
    assert m.resolution_m == 0.1
    assert np.allclose(
        np.asarray(m.origin_in_map) / 0.1, np.round(np.asarray(m.origin_in_map) / 0.1)
    )
    ((row, col),) = m.cells_of([[10.0 - 0.05, 5.0 + 1.05]])
    assert m.values[row, col] == OCCUPIED
    assert np.count_nonzero(m.values == OCCUPIED) == 1
    ((row, col),) = m.cells_of([[10.0, 5.0]])
    assert m.values[row, col] == FREE
    ((row, col),) = m.cells_of([[10.0 - 0.05, 5.0 + 1.6]])  # behind the obstacle
    assert m.values[row, col] == UNKNOWN
    ((row, col),) = m.cells_of([[11.5, 5.0]])  # within range, in the open, to its right
    assert m.values[row, col] == FREE
    ((row, col),) = m.cells_of([[10.0, 5.0 - 1.5]])  # behind: the laser's blind side
    assert m.values[row, col] == UNKNOWN
    free = np.count_nonzero(m.values == FREE) * 0.01
    sector = RasterConfig().free_fov_rad / 2  # the area of the default 240-degree sector
    assert sector * 2.0**2 * 0.9 < free < sector * 2.1**2


def test_a_wall_behind_a_later_node_is_not_erased_by_its_blind_side() -> None:
    """Node 1 faces a wall 2 m ahead; node 2, later, stands 1 m before the wall with its back
    to it: its 270-degree laser never saw the wall, so its grid is empty there. With the
    default field of view the wall stays occupied and the far side unknown; an all-round
    sensor model (``2 pi``) would have painted both free (the leak the default prevents)."""
    wall = np.ones((40, 1), dtype=bool)  # x in [2.0, 2.1), y in [-2, 2) of node 1's base
    nothing = np.zeros((0, 0), dtype=bool)
    poses = {1: (0.0, 0.0, 0.0), 2: (1.0, 0.0, math.pi)}
    probes = np.array([[2.05, 0.05], [3.0, 0.05]])  # on the wall, behind it
    expected = {RasterConfig().free_fov_rad: (OCCUPIED, UNKNOWN), 2.0 * math.pi: (FREE, FREE)}
    for fov, (on_wall, behind) in expected.items():
        for config in (
            RasterConfig(free_fov_rad=fov),
            RasterConfig(free_fov_rad=fov, cover=False, cache=False),
        ):
            raster = Rasterizer(config)
            raster.add_node(1, 0.0, wall, (2.0, -2.0), 0.1)
            raster.add_node(2, 1.0, nothing, (0.0, 0.0), 0.1)
            m = raster.rasterize(poses)
            (a, b) = m.cells_of(probes)
            assert (m.values[a[0], a[1]], m.values[b[0], b[1]]) == (on_wall, behind), fov


def test_poses_as_dict_or_arrays_give_the_same_map_and_unknown_keys_are_counted() -> None:
    walls = box_world(SIZE, seed=5)
    rng = np.random.default_rng(5)
    raster = Rasterizer()
    route = drive(rng, SIZE, 6)
    for k, pose in enumerate(route):
        grid, origin = grid_at(walls, pose)
        raster.add_node(k, float(k), grid, origin, 0.1)
    as_dict = {k: route[k] for k in range(6)} | {99: np.zeros(3)}
    a = raster.rasterize(as_dict)
    assert raster.stats.unknown_keys == 1 and raster.stats.nodes == 6
    keys = np.array([5, 3, 1, 0, 2, 4])
    b = raster.rasterize((keys, route[keys]))
    assert raster.stats.unknown_keys == 0
    assert_same(a, b)


def test_nothing_to_draw_gives_an_empty_map() -> None:
    raster = Rasterizer()
    assert raster.rasterize({}).values.shape == (0, 0)
    raster.add_node(1, 0.0, np.ones((2, 2), dtype=bool), (0.0, 0.0), 0.1)
    assert raster.rasterize({}).values.shape == (0, 0)
    assert raster.rasterize_naive({}).values.shape == (0, 0)


def test_pose_tolerance_reuses_submaps_for_small_moves() -> None:
    walls = box_world(SIZE, seed=6)
    rng = np.random.default_rng(6)
    raster = Rasterizer(RasterConfig(pose_tolerance_m=0.01, pose_tolerance_rad=0.001))
    route = drive(rng, SIZE, 20)
    for k, pose in enumerate(route):
        grid, origin = grid_at(walls, pose)
        raster.add_node(k, float(k), grid, origin, 0.1)
    first = raster.rasterize((np.arange(20), route))
    nudged = route + np.array([0.004, -0.004, 0.0005])
    again = raster.rasterize((np.arange(20), nudged))
    assert raster.stats.rebuilt == 0 and raster.stats.reused == raster.stats.submaps
    assert raster.stats.sampled == 0
    assert_same(first, again)
    moved = route + np.array([0.05, 0.0, 0.0])
    raster.rasterize((np.arange(20), moved))
    assert raster.stats.rebuilt > 0


def test_bad_input_is_rejected_with_the_node_named() -> None:
    raster = Rasterizer(RasterConfig(max_map_cells=10_000_000))
    raster.add_node(3, 0.0, np.ones((2, 2), dtype=bool), (0.0, 0.0), 0.1)
    with pytest.raises(ValueError, match="node 3: already added"):
        raster.add_node(3, 1.0, np.ones((2, 2), dtype=bool), (0.0, 0.0), 0.1)
    with pytest.raises(ValueError, match="node 4: time_s"):
        raster.add_node(4, math.nan, np.ones((2, 2), dtype=bool), (0.0, 0.0), 0.1)
    with pytest.raises(ValueError, match="node 5: grid must be 2-D"):
        raster.add_node(5, 0.0, np.ones(4, dtype=bool), (0.0, 0.0), 0.1)
    with pytest.raises(ValueError, match="key must be an integer"):
        raster.add_node(1.5, 0.0, np.ones((2, 2), dtype=bool), (0.0, 0.0), 0.1)  # type: ignore[arg-type]
    assert len(raster) == 1 and 3 in raster and 4 not in raster
    with pytest.raises(ValueError, match="pose of node 3 is not finite"):
        raster.rasterize({3: (0.0, math.inf, 0.0)})
    with pytest.raises(ValueError, match=r"pose of node 3 must be \(x, y, theta\)"):
        raster.rasterize({3: (0.0, 0.0)})
    with pytest.raises(ValueError, match="poses must be"):
        raster.rasterize((np.array([3]), np.zeros((1, 2))))
    with pytest.raises(ValueError, match="keys must be integers"):
        raster.rasterize((np.array([3.0]), np.zeros((1, 3))))
    with pytest.raises(ValueError, match="names a node twice"):
        raster.rasterize((np.array([3, 3]), np.zeros((2, 3))))
    raster.add_node(6, 0.0, np.ones((2, 2), dtype=bool), (0.0, 0.0), 0.1)
    with pytest.raises(ValueError, match="max_map_cells"):
        raster.rasterize({3: (0.0, 0.0, 0.0), 6: (5000.0, 5000.0, 0.0)})


@pytest.mark.parametrize(
    "fields",
    [
        {"resolution_m": 0.0},
        {"free_range_m": -1.0},
        {"free_fov_rad": 7.0},
        {"submap_nodes": 0},
        {"submap_nodes": 200},
        {"tile_cells": 4},
        {"pose_tolerance_m": math.nan},
        {"max_map_cells": 0},
    ],
)
def test_bad_config_is_rejected(fields: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        RasterConfig(**fields)  # type: ignore[arg-type]


def test_config_decodes_strictly() -> None:
    assert msgspec.convert({"submap_nodes": 16}, RasterConfig).submap_nodes == 16
    with pytest.raises(msgspec.ValidationError, match="unknown"):
        msgspec.convert({"submap_size": 16}, RasterConfig)
