"""Free space from a node's binary grid by the polar visibility sweep (paper 4.8)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.mapping.visibility import FREE, OCCUPIED, UNKNOWN, LocalRaster, local_raster

RES = 0.1


def value_at(r: LocalRaster, x: float, y: float) -> int:
    """Cell value at base point ``(x, y)`` (UNKNOWN outside the raster)."""
    c = math.floor((x - r.origin_in_base[0]) / r.resolution_m)
    row = math.floor((y - r.origin_in_base[1]) / r.resolution_m)
    if 0 <= row < r.cells.shape[0] and 0 <= c < r.cells.shape[1]:
        return int(r.cells[row, c])
    return UNKNOWN


def centres(r: LocalRaster) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = r.cells.shape
    x = r.origin_in_base[0] + (np.arange(cols) + 0.5) * r.resolution_m
    y = r.origin_in_base[1] + (np.arange(rows) + 0.5) * r.resolution_m
    return np.meshgrid(x, y)


def test_empty_grid_sees_a_free_disc() -> None:
    r = local_raster(np.zeros((0, 0), dtype=bool), (0.0, 0.0), RES, free_range_m=3.0)
    x, y = centres(r)
    d = np.hypot(x, y)
    assert np.all(r.cells[d < 3.0 - RES] == FREE)
    assert np.all(r.cells[d > 3.0 + 2 * RES] == UNKNOWN)
    assert not np.any(r.cells == OCCUPIED)
    # cropped to what is observed: about the disc's bounding box
    assert max(r.cells.shape) <= 2 * 3.0 / RES + 4


def test_wall_casts_a_shadow_and_stays_occupied() -> None:
    # grid in base: a 1-cell wall at x in [2.0, 2.1), y in [-3, 3)
    origin = (2.0, -3.0)
    grid = np.ones((60, 1), dtype=bool)
    r = local_raster(grid, origin, RES, free_range_m=6.0)
    assert value_at(r, 1.95 - 0.1, 0.05) == FREE
    assert value_at(r, 2.05, 0.05) == OCCUPIED
    assert value_at(r, 2.05, 2.95) == OCCUPIED
    for x in (2.25, 3.0, 5.0):
        for y in (-1.0, 0.0, 1.0):
            assert value_at(r, x, y) == UNKNOWN, (x, y)
    # beside the wall's end the rays pass
    assert value_at(r, 2.5, 4.5) == FREE  # crosses x = 2 at y = 3.6, past the wall


def test_diagonal_wall_blocks_rays() -> None:
    # an 8-connected diagonal line of cells from (1, -2) to (5, 2): no 4-connected gap
    grid = np.eye(40, dtype=bool)
    r = local_raster(grid, (1.0, -2.0), RES, free_range_m=7.0)
    # points beyond the diagonal as seen from the origin (below-right of the line y = x - 3)
    for x, y in ((4.5, 0.2), (4.0, -0.5), (3.5, -1.2)):
        assert y < x - 3.0
        assert value_at(r, x, y) == UNKNOWN, (x, y)
    assert value_at(r, 1.0, 1.0) == FREE


def _segment_clear(occ: np.ndarray, origin: tuple[float, float], px: float, py: float) -> bool:
    """Dense sampling of the segment from the sensor to ``(px, py)`` (base) against ``occ``."""
    n = int(math.hypot(px, py) / (RES / 20)) + 2
    t = np.linspace(0.0, 1.0, n)
    c = np.floor((t * px - origin[0]) / RES).astype(int)
    r = np.floor((t * py - origin[1]) / RES).astype(int)
    inside = (r >= 0) & (c >= 0) & (r < occ.shape[0]) & (c < occ.shape[1])
    return not np.any(occ[r[inside], c[inside]])


@pytest.mark.parametrize("seed", range(4))
def test_clearly_visible_cells_are_free_against_a_brute_force_oracle(seed: int) -> None:
    rng = np.random.default_rng(seed)
    origin = (-2.0, -2.0)
    occ = rng.random((40, 40)) < 0.04
    occ[19:21, 19:21] = False  # the sensor's own cell is clear
    r = local_raster(occ, origin, RES, free_range_m=1.9)
    checked = 0
    for row in range(40):
        for col in range(40):
            x0, y0 = origin[0] + col * RES, origin[1] + row * RES
            corners = [
                (x0 + a * RES, y0 + b * RES) for a in (0.02, 0.5, 0.98) for b in (0.02, 0.5, 0.98)
            ]
            if max(math.hypot(px, py) for px, py in corners) > 1.85:
                continue
            if occ[row, col]:
                assert value_at(r, x0 + 0.05, y0 + 0.05) == OCCUPIED
            elif all(_segment_clear(occ, origin, px, py) for px, py in corners):
                assert value_at(r, x0 + 0.05, y0 + 0.05) == FREE, (row, col)
                checked += 1
    assert checked > 200


def test_occupied_cells_keep_the_lattice_convention() -> None:
    # cell (row, col) covers origin + (col, row) * res: put one at base (1.25, -0.75)
    grid = np.zeros((5, 8), dtype=bool)
    grid[2, 5] = True
    origin = (0.75, -0.95)
    r = local_raster(grid, origin, RES, free_range_m=0.5)
    occ = np.argwhere(r.cells == OCCUPIED)
    assert len(occ) == 1
    cx = r.origin_in_base[0] + (occ[0, 1] + 0.5) * RES
    cy = r.origin_in_base[1] + (occ[0, 0] + 0.5) * RES
    assert cx == pytest.approx(0.75 + 5.5 * RES)
    assert cy == pytest.approx(-0.95 + 2.5 * RES)


@pytest.mark.parametrize(
    ("grid", "origin", "res", "match"),
    [
        (np.zeros((2, 2, 2), dtype=bool), (0.0, 0.0), RES, "2-D"),
        (np.zeros((2, 2)), (0.0, 0.0), RES, "dtype"),
        (np.full((2, 2), 2, dtype=np.uint8), (0.0, 0.0), RES, "0 and 1"),
        (np.zeros((2, 2), dtype=bool), (math.nan, 0.0), RES, "finite"),
        (np.zeros((2, 2), dtype=bool), (0.0,), RES, "origin"),
        (np.zeros((2, 2), dtype=bool), (0.0, 0.0), 0.0, "resolution"),
        (np.zeros((9000, 1), dtype=bool), (0.0, 0.0), RES, "exceeds"),
    ],
)
def test_bad_grids_are_rejected_naming_the_node(grid, origin, res, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ValueError, match=match) as err:
        local_raster(grid, origin, res, free_range_m=1.0, where="node 7")
    assert "node 7" in str(err.value)


def test_integer_grids_are_accepted() -> None:
    a = local_raster(np.eye(5, dtype=np.uint8), (0.5, 0.5), RES, free_range_m=1.0)
    b = local_raster(np.eye(5, dtype=bool), (0.5, 0.5), RES, free_range_m=1.0)
    assert np.array_equal(a.cells, b.cells) and a.origin_in_base == b.origin_in_base


def test_a_forward_laser_sees_nothing_behind() -> None:
    """A 180-degree field of view around +x: free ahead and to the sides, unknown behind."""
    empty = np.zeros((0, 0), dtype=bool)
    r = local_raster(empty, (0.0, 0.0), RES, free_range_m=3.0, free_fov_rad=math.pi)
    assert value_at(r, 2.0, 0.05) == FREE
    assert value_at(r, 0.05, 2.0) == FREE and value_at(r, 0.05, -2.0) == FREE
    for x, y in ((-1.0, 0.0), (-2.0, 1.5), (-0.5, -2.5)):
        assert value_at(r, x, y) == UNKNOWN, (x, y)
    with pytest.raises(ValueError, match="free_fov_rad"):
        local_raster(empty, (0.0, 0.0), RES, free_range_m=3.0, free_fov_rad=7.0)


def _wall_with_holes(holes: list[tuple[int, int]]) -> np.ndarray:
    """A 1-cell wall at x in [2.0, 2.1), y in [-3, 3) (60 cells) with holes ``[r0, r1)``."""
    grid = np.ones((60, 1), dtype=bool)
    for r0, r1 in holes:
        grid[r0:r1, 0] = False
    return grid


def test_narrow_holes_in_a_wall_stop_rays_but_doorways_do_not() -> None:
    # holes of 2 and 4 cells (0.2, 0.4 m) and a 0.9 m doorway, at y = -2.0, -0.5 and 1.0
    grid = _wall_with_holes([(10, 12), (25, 29), (40, 49)])
    origin = (2.0, -3.0)
    leaky = local_raster(grid, origin, RES, free_range_m=6.0)
    closed = local_raster(grid, origin, RES, free_range_m=6.0, wall_gap_m=0.4)
    # straight through each narrow hole: free without closing, unknown with it
    for y in (-1.85, -0.25):
        assert value_at(leaky, 2.05, y) == FREE
        assert value_at(leaky, 4.0, 2 * y) == FREE
        assert value_at(closed, 2.05, y) == UNKNOWN  # the hole stops rays, stays unknown
        assert value_at(closed, 4.0, 2 * y) == UNKNOWN
    # the doorway still lets the robot see through
    assert value_at(closed, 2.05, 1.45) == FREE
    assert value_at(closed, 4.0, 2.9) == FREE
    # walls are not thickened: the cells in front of the wall stay free, the wall occupied
    for y in (-2.45, -1.05, 0.35):
        assert value_at(closed, 1.95, y) == FREE
        assert value_at(closed, 2.05, y) == OCCUPIED
    assert np.count_nonzero(closed.cells == OCCUPIED) == np.count_nonzero(grid)


def test_a_robot_inside_closed_gaps_still_sees() -> None:
    # four posts 0.5 m apart around the robot (a table): the closing joins them into a square
    # 0.2 m from the robot, yet rays leave the robot's own neighbourhood
    grid = np.zeros((6, 6), dtype=bool)  # x, y in [-0.3, 0.3)
    grid[0, 0] = grid[0, 5] = grid[5, 0] = grid[5, 5] = True
    r = local_raster(grid, (-0.3, -0.3), RES, free_range_m=2.0, wall_gap_m=0.4)
    assert value_at(r, 0.05, 0.05) == FREE
    for x, y in ((0.05, 1.5), (0.05, -1.5), (1.5, 0.05), (-1.5, 0.05)):
        assert value_at(r, x, y) == FREE, (x, y)
    assert value_at(r, -0.25, -0.25) == OCCUPIED


def test_bad_wall_gap_is_rejected() -> None:
    for gap in (-0.1, math.nan, 11.0):
        with pytest.raises(ValueError, match="wall_gap_m"):
            local_raster(np.ones((2, 2), bool), (0.0, 0.0), RES, free_range_m=1.0, wall_gap_m=gap)
