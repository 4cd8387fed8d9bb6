"""The covering: exact footprints, the redundancy sweep and the footprint pool (paper 4.8)."""

from __future__ import annotations

import numpy as np

from gcs.mapping.covering import (
    BLOCK_CELLS,
    FootprintPool,
    compact_footprint,
    cover_sweep,
    footprint,
)
from gcs.mapping.rasterization import RasterConfig, Rasterizer
from tests.gcs.mapping.rasterworlds import box_world, drive, grid_at


def cells_of(rows: np.ndarray) -> set[tuple[int, int]]:
    """Map cells ``(row, col)`` a footprint marks."""
    out = set()
    for bi, bj, *words in rows.tolist():
        for w, word in enumerate(words):
            for b in range(64):
                if (word >> b) & 1:
                    bit = 64 * w + b
                    out.add((bi * BLOCK_CELLS + bit // 16, bj * BLOCK_CELLS + bit % 16))
    return out


def test_footprint_marks_exactly_the_observed_cells_including_negative_blocks() -> None:
    rng = np.random.default_rng(3)
    patch = (rng.random((37, 29)) < 0.3).astype(np.int8)
    row0, col0 = -21, 5
    rows = footprint(patch, row0, col0)
    expected = {(row0 + r, col0 + c) for r, c in np.argwhere(patch)}
    assert cells_of(rows) == expected
    assert len({(r[0], r[1]) for r in rows.tolist()}) == len(rows)  # one row per block


def test_compact_footprint_of_dense_masks_equals_footprint() -> None:
    patch = np.zeros((20, 40), dtype=np.int8)
    patch[3, 7] = patch[19, 39] = patch[0, 16] = 1
    row0, col0 = 32, -16  # block-aligned: patch block (0, 0) is map block (2, -1)
    masks = np.zeros((2, 3, 4), dtype=np.int64)
    for r, c in np.argwhere(patch):
        bit = ((row0 + r) % 16) * 16 + (col0 + c) % 16
        masks[r // 16, c // 16, bit // 64] |= np.int64(1) << np.int64(bit % 64)
    assert np.array_equal(compact_footprint(masks, 2, -1), footprint(patch, row0, col0))


def _foot(cells: list[tuple[int, int]]) -> np.ndarray:
    patch = np.zeros((40, 40), dtype=np.int8)
    for r, c in cells:
        patch[r, c] = 1
    return footprint(patch, 0, 0)


def test_sweep_drops_a_node_only_when_later_nodes_observe_all_its_cells() -> None:
    pool = FootprintPool()
    feet = [
        _foot([(1, 1), (20, 30)]),  # 0: earliest, both cells seen later -> redundant
        _foot([(20, 30), (5, 5)]),  # 1: (5, 5) only here -> kept
        _foot([(1, 1), (20, 30), (39, 0)]),  # 2: latest -> kept
        _foot([(1, 1)]),  # 3: earliest of all, but no pose -> out
    ]
    for f in feet:
        pool.add_node()
        pool.set(len(pool) - 1, f)
    kept = cover_sweep(np.array([2, 1, 0]), pool, (0, 3, 0, 3))
    assert kept.tolist() == [False, True, True, False]
    # the latest node observes nothing: it cannot cover anyone
    pool.set(2, np.zeros((0, 6), dtype=np.int64))
    kept = cover_sweep(np.array([2, 1, 0]), pool, (0, 3, 0, 3))
    assert kept.tolist() == [True, True, False, False]


def test_pool_keeps_every_footprint_through_replacements_and_compaction() -> None:
    rng = np.random.default_rng(1)
    pool = FootprintPool()
    current: dict[int, np.ndarray] = {}
    for step in range(400):
        if step < 50 or rng.random() < 0.2:
            pool.add_node()
            n = len(pool) - 1
        else:
            n = int(rng.integers(len(pool)))
        k = int(rng.integers(0, 30))
        rows = rng.integers(-1000, 1000, size=(k, 6)).astype(np.int64)
        pool.set(n, rows)
        current[n] = rows
    for n, rows in current.items():
        got = pool.rows[pool.offset[n] : pool.offset[n] + pool.count[n]]
        assert np.array_equal(got, rows), n


def test_covering_keeps_exactly_the_latest_observers() -> None:
    size = (40.0, 30.0)
    walls = box_world(size, seed=4)
    rng = np.random.default_rng(4)
    raster = Rasterizer(RasterConfig(submap_nodes=6))
    poses: dict[int, np.ndarray] = {}
    t = 0.0
    for robot in range(3):
        for k, pose in enumerate(drive(rng, size, 25, stop_every=5)):
            key = (robot << 32) | k
            grid, origin = grid_at(walls, pose)
            raster.add_node(key, t + rng.uniform(0, 3), grid, origin, 0.1)
            poses[key] = pose
            t += 1.0
    raster.rasterize(poses)
    owners = raster.latest_observers(poses)
    assert raster.stats.kept == len(owners) < raster.stats.nodes


def test_rasterizer_footprints_are_the_cells_each_node_draws() -> None:
    """The footprints the rasterizer packs while sampling equal :func:`footprint` of the
    node's own drawing (its naive map alone), for nodes at arbitrary poses."""
    walls = box_world((40.0, 30.0), seed=8)
    rng = np.random.default_rng(8)
    raster = Rasterizer()
    route = drive(rng, (40.0, 30.0), 12)
    for k, pose in enumerate(route):
        grid, origin = grid_at(walls, pose)
        raster.add_node(k, float(k), grid, origin, 0.1)
    for k, pose in enumerate(route):
        moved = pose + rng.normal(0, [3.0, 3.0, 2.0])
        raster.rasterize({k: moved})
        alone = raster.rasterize_naive({k: moved})
        row0 = round(alone.origin_in_map[1] / 0.1)
        col0 = round(alone.origin_in_map[0] / 0.1)
        expected = footprint((alone.values != -1).astype(np.int8), row0, col0)
        feet = raster._feet
        got = feet.rows[feet.offset[k] : feet.offset[k] + feet.count[k]]
        assert np.array_equal(got, expected), k
