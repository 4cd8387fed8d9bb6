"""Vertical-surface grid for loop closing (paper 4.3.3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.terrain.synthetic_scene import FACE, cast_sweep, issue_scene
from robot.terrain.vertical_surface_grid import VerticalSurfaceConfig, vertical_surface_grid


def _cell(grid, x: float, y: float) -> tuple[int, int]:  # type: ignore[no-untyped-def]
    c = math.floor((x - grid.origin_in_base[0]) / grid.resolution_m)
    r = math.floor((y - grid.origin_in_base[1]) / grid.resolution_m)
    return r, c


def test_wall_is_occupied_ground_and_slope_are_not() -> None:
    cfg = VerticalSurfaceConfig(size_cells=100)
    z = np.linspace(0.0, 1.5, 16)
    wall = np.c_[np.full(16, 2.03), np.full(16, 1.01), z]  # vertical: one cell
    slope = np.c_[np.linspace(-3.0, -2.0, 50), np.full(50, 0.5), np.linspace(0, 0.5, 50)]  # 27 deg
    ground = np.c_[np.random.default_rng(0).uniform(-4, 4, (500, 2)), np.zeros(500)]
    grid = vertical_surface_grid(np.vstack([wall, slope, ground]).astype(np.float32), config=cfg)
    assert grid.occupied.shape == (100, 100)
    assert grid.origin_in_base == (-5.0, -5.0) and grid.resolution_m == 0.1
    assert grid.occupied[_cell(grid, 2.03, 1.01)]
    assert grid.occupied.sum() == 1


def test_grid_is_in_base_frame_and_sees_the_scene_walls() -> None:
    """The same scene from a rotated pose gives the wall in the rotated base-frame cells."""
    scene = issue_scene()
    cfg = VerticalSurfaceConfig()
    for yaw in (0.0, 0.7):
        hits = cast_sweep(scene, (0.0, 0.0, yaw), rng=np.random.default_rng(1))
        grid = vertical_surface_grid(hits.points_in_base, config=cfg)
        # Face hits taller than the band's lower edge should mostly land in occupied cells.
        sel = (hits.labels == FACE) & (hits.points_in_odom[:, 2] > 0.3)
        p = hits.points_in_base[sel]
        rc = np.floor((p[:, 1::-1] - np.array(grid.origin_in_base)[::-1]) / grid.resolution_m)
        rc = rc.astype(int)
        assert grid.occupied[rc[:, 0], rc[:, 1]].mean() > 0.8
        # The wall at y = 7 m in odom, seen from the robot at the origin with this yaw.
        c, s = math.cos(yaw), math.sin(yaw)
        x_b, y_b = c * 0.0 + s * 6.9, -s * 0.0 + c * 6.9
        r0, c0 = _cell(grid, x_b, y_b)
        assert grid.occupied[r0 - 2 : r0 + 3, c0 - 2 : c0 + 3].any()
        # Ground and canopy-free area in front of the robot stays empty.
        r1, c1 = _cell(grid, 1.0 * c, -1.0 * s)
        assert not grid.occupied[r1 - 3 : r1 + 4, c1 - 3 : c1 + 4].any()


def test_bad_input_names_the_problem() -> None:
    cfg = VerticalSurfaceConfig(size_cells=10)
    with pytest.raises(ValueError, match="points_in_base"):
        vertical_surface_grid(np.zeros((3, 4)), config=cfg)
    with pytest.raises(ValueError, match="not finite"):
        vertical_surface_grid(np.array([[np.inf, 0, 0]]), config=cfg)
    with pytest.raises(ValueError, match="base_from_point_base: expected shape"):
        vertical_surface_grid(np.zeros((3, 3)), config=cfg, base_from_point_base=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="z_min_m"):
        VerticalSurfaceConfig(z_min_m=2.0, z_max_m=1.0)


def _sparse_wall_lines(spacing_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A wall along x = 3 m seen by six scan lines (heights 0.3..1.8 m), returns every
    ``spacing_m`` along y; a 1.2 m doorway at y in (0, 1.2). One time stamp per line."""
    y = np.arange(-2.0, 3.0, spacing_m) + 0.013
    y = y[(y < 0.0) | (y > 1.2)]
    pts, times = [], []
    for k, z in enumerate(np.linspace(0.3, 1.8, 6)):
        pts.append(np.c_[np.full(len(y), 3.04), y, np.full(len(y), z)])
        times.append(np.full(len(y), 0.05 * k))
    return np.vstack(pts).astype(np.float32), np.concatenate(times).astype(np.float32)


def test_scan_line_segments_close_the_gaps_between_beams_but_not_doorways() -> None:
    cfg = VerticalSurfaceConfig(size_cells=100)
    pts, times = _sparse_wall_lines(0.25)
    column = round((3.04 + 5.0) / 0.1)
    y_cell = -5.0 + (np.arange(100) + 0.5) * 0.1  # cell centres
    rows_door = np.flatnonzero((0.0 < y_cell) & (y_cell < 1.2))
    # between the first and last returns, off the doorway and its edge cells
    rows_solid = np.flatnonzero(
        ((-1.95 <= y_cell) & (y_cell <= -0.3)) | ((1.3 <= y_cell) & (y_cell <= 2.75))
    )
    alone = vertical_surface_grid(pts, config=cfg).occupied
    joined = vertical_surface_grid(pts, config=cfg, point_time_s=times).occupied
    assert alone[rows_solid, column].mean() < 0.5  # 25 cm beams leave most 10 cm cells empty
    assert joined[rows_solid, column].all()  # the segments fill them
    assert not joined[rows_door, column].any()  # 1.2 m apart: a doorway stays open
    assert joined.sum() == joined[:, column].sum()  # nothing off the wall
    off = VerticalSurfaceConfig(size_cells=100, connect_max_gap_m=0.0)
    assert np.array_equal(
        vertical_surface_grid(pts, config=off, point_time_s=times).occupied, alone
    )
    with pytest.raises(ValueError, match="point_time_s"):
        vertical_surface_grid(pts, config=cfg, point_time_s=times[:-1])
    with pytest.raises(ValueError, match="connect_max_gap_m"):
        VerticalSurfaceConfig(connect_max_gap_m=-1.0)
