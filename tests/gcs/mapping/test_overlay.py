"""The near map laid over the far one: known near cells win, the rest is the far map's."""

from __future__ import annotations

import numpy as np
import pytest

from compression import encode_grid
from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.mapping.overlay import overlay
from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from protocol.messages import PoseNode, TerrainGrid, covariance_to_upper
from protocol.se2 import relative


def test_known_top_cells_win_and_the_result_covers_both() -> None:
    bottom = OccupancyMap(np.full((3, 4), FREE, dtype=np.int8), (0.0, 0.0), 0.5)
    top_values = np.array([[UNKNOWN, OCCUPIED], [FREE, UNKNOWN]], dtype=np.int8)
    top = OccupancyMap(top_values, (1.0, -0.5), 0.5)  # cell (0, 0) at col 2, row -1
    out = overlay(top, bottom)
    assert out.origin_in_map == (0.0, -0.5) and out.values.shape == (4, 4)
    expected = np.full((4, 4), UNKNOWN, dtype=np.int8)
    expected[1:, :] = FREE
    expected[0, 3] = OCCUPIED  # top only
    expected[1, 2] = FREE  # top's free over bottom's free
    np.testing.assert_array_equal(out.values, expected)
    # a top that knows nothing changes nothing; an empty bottom gives the top
    assert overlay(OccupancyMap(np.zeros((0, 0), np.int8), (0.0, 0.0), 0.5), bottom) is bottom
    assert overlay(top, OccupancyMap(np.zeros((0, 0), np.int8), (0.0, 0.0), 0.5)) is top


def test_maps_on_different_lattices_are_refused() -> None:
    a = OccupancyMap(np.zeros((2, 2), np.int8), (0.0, 0.0), 0.5)
    with pytest.raises(ValueError, match="resolutions"):
        overlay(OccupancyMap(np.zeros((2, 2), np.int8), (0.0, 0.0), 0.1), a)
    with pytest.raises(ValueError, match="lattice"):
        overlay(OccupancyMap(np.zeros((2, 2), np.int8), (0.25, 0.0), 0.5), a)


def _wall_then_far_view(near: bool) -> OccupancyMap:
    """Node 0 sees a wall 1.5 m ahead; node 1, later, 6.5 m from it and facing it, has no
    return from it (sparse at range): its far free rays run through the wall."""
    cfg = GroundStationConfig() if near else GroundStationConfig(near_raster=None)
    gs = GroundStation(cfg)
    path = np.array([[0.0, 0.0, 0.0], [-5.0, 0.0, 0.0]])
    cov = covariance_to_upper(np.diag([0.01**2, 0.01**2, 0.002**2]))
    wall = np.zeros((60, 60), dtype=bool)
    wall[10:50, 45] = True  # x = -3 + 45.5 * 0.1 = 1.55 m ahead of node 0, 4 m wide
    for i, grid in enumerate((wall, np.zeros((60, 60), dtype=bool))):
        delta = (0.0, 0.0, 0.0) if i == 0 else tuple(relative(path[0], path[1]))
        node = PoseNode(i, float(i), tuple(path[i]), delta, (0.0,) * 6 if i == 0 else cov)  # type: ignore[arg-type]
        assert gs.handle(0, node, now_s=float(i))
        msg = TerrainGrid(i, 0.1, encode_grid(grid, origin_cells=(-30, -30)))
        assert gs.handle(0, msg, now_s=float(i))
    gs.step(now_s=2.0)
    return gs.rasterize()


def test_a_wall_seen_from_close_by_survives_a_later_far_view() -> None:
    far_only, layered = _wall_then_far_view(False), _wall_then_far_view(True)
    wall_pts = np.array([[1.55, y] for y in np.arange(-1.5, 1.51, 0.1)])
    for m, kept in ((far_only, False), (layered, True)):
        rc = m.cells_of(wall_pts)
        values = m.values[rc[:, 0], rc[:, 1]]
        assert np.all(values == OCCUPIED) if kept else np.all(values == FREE)
    # the far view's free space beyond the near range is still known
    assert layered.values.shape == far_only.values.shape
    np.testing.assert_array_equal(layered.values != UNKNOWN, far_only.values != UNKNOWN)
