"""The coarse planning grid: pessimistic coarsening, clearance, keep-out, line of sight."""

from __future__ import annotations

import numpy as np
import pytest

from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from gcs.tasking.planning_grid import coarsen, line_of_sight, simplify_path


def test_coarsening_is_pessimistic_about_obstacles() -> None:
    fine = np.full((4, 4), FREE, dtype=np.int8)
    fine[0, 0] = OCCUPIED  # one occupied fine cell makes its 2x2 block occupied
    fine[2:4, 0:2] = UNKNOWN
    fine[2, 2] = UNKNOWN  # 3 of 4 free: free
    fine[0:2, 2] = UNKNOWN  # 2 of 4 free at free_fraction 0.5: free
    g = coarsen(OccupancyMap(fine, (1.0, 2.0), 0.1), resolution_m=0.2, robot_radius_m=0.0)
    assert g.resolution_m == pytest.approx(0.2)
    assert g.values.tolist() == [[OCCUPIED, FREE], [UNKNOWN, FREE]]
    assert g.origin_in_map == (1.0, 2.0)
    assert g.cells_of([[1.25, 2.35]]).tolist() == [[1, 1]]
    assert np.allclose(g.centers_of([[1, 1]]), [[1.3, 2.3]])


def test_clearance_and_keepout_remove_traversable_cells() -> None:
    fine = np.full((20, 20), FREE, dtype=np.int8)
    fine[:, 0] = OCCUPIED
    g = coarsen(OccupancyMap(fine, (0.0, 0.0), 1.0), resolution_m=1.0, robot_radius_m=1.5)
    # cells 1 m from the wall are too close for a 1.5 m radius, 2 m are fine
    assert not g.traversable[5, 1].any()
    assert g.traversable[5, 2]
    g = coarsen(
        OccupancyMap(fine, (0.0, 0.0), 1.0),
        resolution_m=1.0,
        robot_radius_m=0.0,
        keepout_in_map=[[10.5, 10.5, 3.0]],
    )
    assert not g.traversable[10, 10] and not g.traversable[13, 10]
    assert g.traversable[14, 10]


def test_line_of_sight_blocked_by_occupied_not_unknown() -> None:
    fine = np.full((10, 10), FREE, dtype=np.int8)
    fine[:, 5] = UNKNOWN
    g = coarsen(OccupancyMap(fine, (0.0, 0.0), 1.0), resolution_m=1.0, robot_radius_m=0.0)
    assert line_of_sight(g, (0.5, 4.5), (9.5, 4.5))
    fine[4, 5] = OCCUPIED
    g = coarsen(OccupancyMap(fine, (0.0, 0.0), 1.0), resolution_m=1.0, robot_radius_m=0.0)
    assert not line_of_sight(g, (0.5, 4.5), (9.5, 4.5))
    assert line_of_sight(g, (0.5, 8.5), (9.5, 8.5))


def test_simplify_path_keeps_corners() -> None:
    pts = np.array([[0, 0], [1, 0], [2, 0], [3, 0], [3, 1], [3, 2]], dtype=float)
    assert simplify_path(pts, 0.1).tolist() == [[0, 0], [3, 0], [3, 2]]
