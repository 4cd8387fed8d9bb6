"""Information gain by ray casting, against hand counts."""

from __future__ import annotations

import numpy as np
import pytest

from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from gcs.tasking.information_gain import information_gain
from gcs.tasking.planning_grid import coarsen


def _grid(values: np.ndarray):  # type: ignore[no-untyped-def]
    return coarsen(OccupancyMap(values, (0.0, 0.0), 1.0), resolution_m=1.0, robot_radius_m=0.0)


def test_open_view_counts_every_unknown_cell_in_range() -> None:
    v = np.full((41, 41), FREE, dtype=np.int8)
    v[20:23, 25:28] = UNKNOWN  # 9 cells, 5-7 m east of the goal
    v[2:4, 2:4] = UNKNOWN  # 4 cells out of range (25 m away)
    gain = information_gain(_grid(v), [[20, 20]], sensor_range_m=10.0)
    assert gain.tolist() == [pytest.approx(9.0)]


def test_occupied_cells_hide_what_is_behind() -> None:
    v = np.full((41, 41), FREE, dtype=np.int8)
    v[20:23, 25:28] = UNKNOWN
    v[10:30, 23] = OCCUPIED  # a wall between the goal and the block
    v[18:20, 14:16] = UNKNOWN  # 4 visible cells to the west
    gain = information_gain(_grid(v), [[20, 20], [20, 30]], sensor_range_m=10.0)
    # from (20, 20): only the 4 west cells; from (20, 30) east of the wall: the block of 9
    assert gain.tolist() == [pytest.approx(4.0), pytest.approx(9.0)]


def test_beyond_the_map_is_unknown() -> None:
    v = np.full((21, 21), FREE, dtype=np.int8)
    assert information_gain(_grid(v), [[10, 10]], sensor_range_m=5.0)[0] == 0.0
    assert information_gain(_grid(v), [[10, 19]], sensor_range_m=5.0)[0] > 10.0
