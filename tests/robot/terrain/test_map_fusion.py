"""Pessimistic fusion of the last sweeps in odom (paper 5.3, stage 3)."""

from __future__ import annotations

import numpy as np
import pytest

from robot.terrain.grid import DRIVABLE, OBSTACLE, UNKNOWN, GridGeometry
from robot.terrain.map_fusion import TerrainMapFusion


def _geo(cx: float, cy: float, n: int = 20) -> GridGeometry:
    return GridGeometry.centered([cx, cy], resolution_m=0.1, rows=n, cols=n)


def _brute_fuse(maps, out_geo):  # type: ignore[no-untyped-def]
    """Per output cell, look up every map by world coordinates of the cell center."""
    out = np.full(out_geo.shape, UNKNOWN, dtype=np.uint8)
    for r in range(out_geo.rows):
        for c in range(out_geo.cols):
            xy = out_geo.center_of((r, c))
            seen = []
            for classes, geo in maps:
                mr, mc = geo.cell_of(xy)
                if 0 <= mr < geo.rows and 0 <= mc < geo.cols:
                    seen.append(classes[mr, mc])
            if OBSTACLE in seen:
                out[r, c] = OBSTACLE
            elif DRIVABLE in seen:
                out[r, c] = DRIVABLE
    return out


def test_fusion_matches_brute_force_and_forgets_old_sweeps() -> None:
    rng = np.random.default_rng(0)
    fusion = TerrainMapFusion(memory_sweeps=3)
    maps = []
    for k in range(5):
        geo = _geo(0.37 * k, -0.21 * k)
        classes = rng.integers(0, 3, geo.shape).astype(np.uint8)
        fusion.add(classes, geo)
        maps.append((classes, geo))
    assert len(fusion) == 3
    out_geo = _geo(0.9, -0.5, n=30)
    np.testing.assert_array_equal(fusion.fused(out_geo), _brute_fuse(maps[-3:], out_geo))


def test_one_obstacle_anywhere_wins() -> None:
    geo = _geo(0.0, 0.0)
    fusion = TerrainMapFusion()
    drivable = np.full(geo.shape, DRIVABLE, dtype=np.uint8)
    one = drivable.copy()
    one[5, 7] = OBSTACLE
    for classes in (drivable, one, drivable):
        fusion.add(classes, geo)
    out = fusion.fused(geo)
    assert out[5, 7] == OBSTACLE
    assert (out == DRIVABLE).sum() == out.size - 1
    for _ in range(12):  # after 12 newer sweeps the obstacle is forgotten
        fusion.add(drivable, geo)
    assert (fusion.fused(geo) == DRIVABLE).all()


def test_tall_marks_obstacles_at_least_that_high_and_those_of_unknown_height() -> None:
    """A 10 cm curb does not cut the neutralization laser's beam; a 0.5 m box and an
    obstacle whose height no sweep measured do (robot/node.py's line of sight)."""
    geo = _geo(0.0, 0.0)
    shifted = _geo(0.3, 0.0)  # a second sweep on the same lattice, 3 cells east
    fusion = TerrainMapFusion()
    classes = np.full(geo.shape, DRIVABLE, dtype=np.uint8)
    classes[5, 5] = classes[5, 6] = OBSTACLE
    heights = np.zeros(geo.shape)
    heights[5, 5], heights[5, 6] = 0.10, 0.50
    fusion.add(classes, geo, obstacle_height_m=heights)
    unknown_height = np.full(shifted.shape, DRIVABLE, dtype=np.uint8)
    unknown_height[8, 2] = OBSTACLE  # cell (8, 5) of geo
    fusion.add(unknown_height, shifted)
    tall = fusion.tall(geo, 0.25)
    assert tall.sum() == 2 and tall[5, 6] and tall[8, 5] and not tall[5, 5]
    assert fusion.tall(geo, 0.05)[5, 5]


def test_later_drivable_sweeps_clear_a_moving_obstacles_trail() -> None:
    geo = _geo(0.0, 0.0)
    drivable = np.full(geo.shape, DRIVABLE, dtype=np.uint8)
    trail = []
    for k in range(5):  # a teammate crossing the grid, one cell per sweep, seen where it is
        classes = drivable.copy()
        classes[10, 5 + k] = OBSTACLE
        trail.append(classes)
    wall = drivable.copy()
    wall[3, :] = OBSTACLE  # a static obstacle that every sweep sees
    for k, pessimistic in ((0, True), (2, False)):
        fusion = TerrainMapFusion(clear_after_sweeps=k)
        for classes in trail:
            fusion.add(np.maximum(classes, wall), geo)
        out = fusion.fused(geo)
        assert (out[3, :] == OBSTACLE).all()  # the wall stays
        assert out[10, 9] == OBSTACLE  # where it is now
        assert out[10, 8] == OBSTACLE  # seen free only once since
        assert (out[10, 5:8] == OBSTACLE).all() == pessimistic  # seen free twice since
    # a cell that is marked only now and then (a thin pole) is kept while marks keep coming
    fusion = TerrainMapFusion(clear_after_sweeps=2)
    pole = drivable.copy()
    pole[15, 15] = OBSTACLE
    for classes in (pole, drivable, pole, drivable):
        fusion.add(classes, geo)
    assert fusion.fused(geo)[15, 15] == OBSTACLE
    with pytest.raises(ValueError, match="clear_after_sweeps"):
        TerrainMapFusion(clear_after_sweeps=-1)


def test_beams_below_a_marks_top_clear_it_and_beams_above_do_not() -> None:
    geo = _geo(0.0, 0.0)
    unknown = np.full(geo.shape, UNKNOWN, dtype=np.uint8)
    marked = unknown.copy()
    marked[4, 4] = marked[6, 6] = OBSTACLE  # a teammate's body (0.4 m) and a curb (0.1 m)
    height = np.zeros(geo.shape)
    height[4, 4], height[6, 6] = 0.4, 0.1
    no_beams = np.full(geo.shape, np.inf)
    beams = no_beams.copy()
    beams[4, 4] = 0.2  # later beams pass through where the teammate was, at 0.2 m
    beams[6, 6] = 0.2  # and over the curb, above its top
    fusion = TerrainMapFusion(clear_after_sweeps=2)
    fusion.add(marked, geo, obstacle_height_m=height, free_height_m=no_beams)
    fusion.add(unknown, geo, obstacle_height_m=np.zeros(geo.shape), free_height_m=beams)
    assert fusion.fused(geo)[4, 4] == OBSTACLE  # one look is not enough
    fusion.add(unknown, geo, obstacle_height_m=np.zeros(geo.shape), free_height_m=beams)
    out = fusion.fused(geo)
    assert out[4, 4] == UNKNOWN  # gone: twice a beam crossed below its top
    assert out[6, 6] == OBSTACLE  # a curb is not cleared by beams that pass over it
    # without heights, a mark is taken as tall: only drivable observations clear it
    fusion = TerrainMapFusion(clear_after_sweeps=1)
    fusion.add(marked, geo)
    fusion.add(unknown, geo, free_height_m=beams)
    assert fusion.fused(geo)[4, 4] == OBSTACLE
    fusion.forget_older(keep=1)
    assert len(fusion) == 1 and fusion.fused(geo)[4, 4] == UNKNOWN


def test_bad_input_names_the_problem() -> None:
    fusion = TerrainMapFusion()
    geo = _geo(0.0, 0.0)
    with pytest.raises(ValueError, match="shape"):
        fusion.add(np.zeros((3, 3), np.uint8), geo)
    with pytest.raises(ValueError, match="dtype"):
        fusion.add(np.zeros(geo.shape, np.int32), geo)
    with pytest.raises(ValueError, match="values"):
        fusion.add(np.full(geo.shape, 7, np.uint8), geo)
    with pytest.raises(ValueError, match="lattice"):
        fusion.fused(GridGeometry((0.05, 0.0), 0.1, 4, 4))
    fusion.add(np.zeros(geo.shape, np.uint8), geo)
    with pytest.raises(ValueError, match="resolution_m"):
        fusion.fused(GridGeometry((0.0, 0.0), 0.2, 4, 4))
    with pytest.raises(ValueError, match="memory_sweeps"):
        TerrainMapFusion(memory_sweeps=0)
    with pytest.raises(ValueError, match="free_height_m"):
        fusion.add(np.zeros(geo.shape, np.uint8), geo, free_height_m=np.zeros((2, 2)))


def _random_layers(rng, geo):  # type: ignore[no-untyped-def]
    u = rng.random(geo.shape)
    classes = np.where(u < 0.05, OBSTACLE, np.where(u < 0.5, DRIVABLE, UNKNOWN)).astype(np.uint8)
    obstacle_h = np.where(rng.random(geo.shape) < 0.2, np.inf, rng.uniform(0.0, 2.0, geo.shape))
    free_h = np.where(rng.random(geo.shape) < 0.5, rng.uniform(0.0, 2.0, geo.shape), np.inf)
    return classes, obstacle_h, free_h


def test_answers_kept_between_sweeps_equal_a_fresh_fusion_of_the_same_memory() -> None:
    # fused() and tall() remember their last answer until the memory changes: after every
    # add, forget and clear, and when asked twice, they equal a fusion built from scratch
    rng = np.random.default_rng(5)
    kept = TerrainMapFusion(memory_sweeps=4, clear_after_sweeps=2)
    history: list = []
    ask = [_geo(0.0, 0.0, 30), _geo(0.3, -0.2, 30), _geo(0.0, 0.0, 30)]
    for step in range(14):
        if step == 9:
            kept.forget_older(keep=1)
            history = history[-1:]
        elif step == 11:
            kept.clear()
            history = []
        else:
            geo = _geo(rng.uniform(-1, 1), rng.uniform(-1, 1), 30)
            layers = _random_layers(rng, geo)
            kept.add(layers[0], geo, obstacle_height_m=layers[1], free_height_m=layers[2])
            history = (history + [(geo, layers)])[-4:]
        fresh = TerrainMapFusion(memory_sweeps=4, clear_after_sweeps=2)
        for geo, (cls, oh, fh) in history:
            fresh.add(cls, geo, obstacle_height_m=oh, free_height_m=fh)
        for geo in ask:
            for _ in range(2):
                got = kept.fused(geo)
                np.testing.assert_array_equal(got, fresh.fused(geo))
                got[:] = OBSTACLE  # the caller's copy: the remembered answer is untouched
                tall = kept.tall(geo, 0.5)
                np.testing.assert_array_equal(tall, fresh.tall(geo, 0.5))
                tall[:] = True
            np.testing.assert_array_equal(kept.tall(geo, 1.0), fresh.tall(geo, 1.0))


def test_a_grid_asked_again_elsewhere_before_the_next_sweep_equals_a_fresh_fusion() -> None:
    # between sweeps the last answer's lattice window serves the cells a moved grid shares
    # with it (the rest computed): any shift, size or no overlap gives a fresh fusion's answer
    rng = np.random.default_rng(11)
    kept = TerrainMapFusion(memory_sweeps=5, clear_after_sweeps=2)
    fresh_maps = []
    for _ in range(5):
        geo = _geo(rng.uniform(-1, 1), rng.uniform(-1, 1), 25)
        layers = _random_layers(rng, geo)
        kept.add(layers[0], geo, obstacle_height_m=layers[1], free_height_m=layers[2])
        fresh_maps.append((geo, layers))
    for _ in range(25):
        n = int(rng.integers(5, 40))
        geo = GridGeometry.centered(
            rng.uniform(-3, 3, 2), resolution_m=0.1, rows=n, cols=int(rng.integers(5, 40))
        )
        fresh = TerrainMapFusion(memory_sweeps=5, clear_after_sweeps=2)
        for g, (cls, oh, fh) in fresh_maps:
            fresh.add(cls, g, obstacle_height_m=oh, free_height_m=fh)
        np.testing.assert_array_equal(kept.fused(geo), fresh.fused(geo))
