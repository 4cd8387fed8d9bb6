"""Map scores on constructed grids with known answers: exploration counts, occupancy F1 of an
exact, a shifted and a noisy map, frames related by a rotation and a translation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap
from mission.report.map_scoring import (
    cell_centres,
    explored_frac,
    lookup,
    map_in_world,
    occupancy_scores,
    surface_cells,
    world_from_map,
)

RES = 0.1


def _room() -> np.ndarray:
    """A 10 x 8 m world (100 x 80 cells... as rows x cols: 80 x 100) with a 0.2 m thick
    perimeter wall and one inner wall."""
    occ = np.zeros((80, 100), dtype=bool)
    occ[:2, :] = occ[-2:, :] = True
    occ[:, :2] = occ[:, -2:] = True
    occ[20:60, 50:52] = True
    return occ


def _map_of(
    truth: np.ndarray, wfm: np.ndarray, *, shift_m: tuple[float, float] = (0, 0)
) -> OccupancyMap:
    """The truth drawn into a map frame ``wfm`` away (everything known: free or occupied),
    optionally displaced by ``shift_m`` in the world."""
    rows, cols = 140, 140
    origin = (-7.0, -7.0)
    r, c = np.indices((rows, cols))
    centres_map = np.stack(
        [origin[0] + (c.ravel() + 0.5) * RES, origin[1] + (r.ravel() + 0.5) * RES], axis=1
    )
    cw, sw = math.cos(wfm[2]), math.sin(wfm[2])
    world = np.stack(
        [wfm[0] + cw * centres_map[:, 0] - sw * centres_map[:, 1],
         wfm[1] + sw * centres_map[:, 0] + cw * centres_map[:, 1]], axis=1,
    ) - np.asarray(shift_m)  # fmt: skip
    occ = lookup(truth, (0.0, 0.0), RES, world, outside=False)
    inside = (world[:, 0] >= 0) & (world[:, 0] < 10) & (world[:, 1] >= 0) & (world[:, 1] < 8)
    values = np.full(rows * cols, UNKNOWN, dtype=np.int8)
    values[inside] = FREE
    values[inside & occ] = OCCUPIED
    return OccupancyMap(values.reshape(rows, cols), origin, RES)


def test_world_from_map_composes_start_and_anchor() -> None:
    start = np.array([3.0, 4.0, 0.5])
    assert np.allclose(world_from_map(start), start)
    anchor = np.array([1.0, -2.0, 0.3])
    wfm = world_from_map(start, anchor)
    # map_from_odom = anchor: the odom origin (the start) sits at ``anchor`` in map
    assert np.allclose(wfm[:2] + _rot(wfm[2]) @ anchor[:2], start[:2])


def _rot(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])


@pytest.mark.parametrize("wfm", [np.array([5.0, 4.0, 0.0]), np.array([4.2, 3.1, 0.7])])
def test_exact_map_scores_one_in_any_frame(wfm: np.ndarray) -> None:
    truth = _room()
    occupancy = _map_of(truth, wfm)
    s = occupancy_scores(occupancy, truth, RES, wfm, tolerance_m=0.2)
    assert s.precision == pytest.approx(1.0)
    assert s.recall > 0.99
    assert s.f1 > 0.99


def test_shifted_map_loses_precision_and_recall() -> None:
    truth = _room()
    wfm = np.array([5.0, 4.0, 0.0])
    exact = occupancy_scores(_map_of(truth, wfm), truth, RES, wfm, tolerance_m=0.2)
    off = occupancy_scores(_map_of(truth, wfm, shift_m=(0.6, 0.0)), truth, RES, wfm)
    # the horizontal walls still match; the vertical ones are 0.6 m off, beyond tolerance
    assert off.f1 < exact.f1 - 0.2
    assert 0.3 < off.precision < 0.9
    # the same shift within a wider tolerance matches again
    wide = occupancy_scores(
        _map_of(truth, wfm, shift_m=(0.6, 0.0)), truth, RES, wfm, tolerance_m=0.7
    )
    assert wide.f1 > 0.97


def test_spurious_cells_count_against_precision_only() -> None:
    truth = _room()
    wfm = np.array([5.0, 4.0, 0.0])
    occupancy = _map_of(truth, wfm)
    values = occupancy.values.copy()
    exact = occupancy_scores(occupancy, truth, RES, wfm)
    free_rc = np.argwhere(values == FREE)
    rng = np.random.default_rng(0)
    picks = free_rc[rng.choice(len(free_rc), 200, replace=False)]
    # spurious cells far from every wall (> 0.5 m): each one is a false positive
    centres = np.stack(
        [occupancy.origin_in_map[0] + (picks[:, 1] + 0.5) * RES,
         occupancy.origin_in_map[1] + (picks[:, 0] + 0.5) * RES], axis=1,
    ) + wfm[:2]  # fmt: skip
    d_wall = lookup(_dist(truth), (0.0, 0.0), RES, centres, outside=np.inf)
    picks = picks[d_wall > 0.5]
    values[picks[:, 0], picks[:, 1]] = OCCUPIED
    noisy = occupancy_scores(OccupancyMap(values, occupancy.origin_in_map, RES), truth, RES, wfm)
    assert noisy.map_occupied == exact.map_occupied + len(picks)
    assert noisy.map_occupied_true == exact.map_occupied_true
    assert noisy.truth_surface_recalled == exact.truth_surface_recalled


def _dist(occ: np.ndarray) -> np.ndarray:
    from scipy.ndimage import distance_transform_edt

    return distance_transform_edt(~occ) * RES  # type: ignore[no-any-return]


def test_recall_counts_only_observed_surfaces() -> None:
    truth = _room()
    wfm = np.array([5.0, 4.0, 0.0])
    occupancy = _map_of(truth, wfm)
    values = occupancy.values.copy()
    # the map knows only the left half of the room (x < 4 m in the world)
    cols_world = occupancy.origin_in_map[0] + (np.arange(values.shape[1]) + 0.5) * RES + wfm[0]
    values[:, cols_world >= 4.0] = UNKNOWN
    half = occupancy_scores(OccupancyMap(values, occupancy.origin_in_map, RES), truth, RES, wfm)
    assert half.recall > 0.99  # what was observed was mapped
    full = occupancy_scores(occupancy, truth, RES, wfm)
    assert half.truth_surface_observed < 0.6 * full.truth_surface_observed


def test_explored_frac_counts_known_reachable_cells() -> None:
    reachable = np.zeros((80, 100), dtype=bool)
    reachable[10:70, 10:90] = True  # 60 x 80 cells
    wfm = np.array([5.0, 4.0, 0.0])
    values = np.full((140, 140), UNKNOWN, dtype=np.int8)
    occupancy = OccupancyMap(values, (-7.0, -7.0), RES)
    pts = cell_centres(reachable, RES) - wfm[:2]
    assert explored_frac(occupancy, pts) == (0.0, 0)
    # know world x in [1, 5) m: 40 of the 80 reachable columns (x from 1.0 to 9.0 m)
    cols_world = -7.0 + (np.arange(140) + 0.5) * RES + wfm[0]
    values[:, (cols_world >= 1.0) & (cols_world < 5.0)] = FREE
    frac, known = explored_frac(OccupancyMap(values, (-7.0, -7.0), RES), pts)
    assert known == 60 * 40
    assert frac == pytest.approx(0.5)
    assert math.isnan(explored_frac(occupancy, np.zeros((0, 2)))[0])


def test_surface_cells_are_the_faces_of_structures() -> None:
    occ = np.zeros((10, 10), dtype=bool)
    occ[2:8, 2:8] = True
    surface = surface_cells(occ)
    assert surface.sum() == 6 * 6 - 4 * 4
    assert not surface[4, 4]


def test_map_in_world_round_trips_a_rotated_map() -> None:
    truth = _room()
    wfm = np.array([4.2, 3.1, 0.7])
    est = map_in_world(_map_of(truth, wfm), wfm, truth.shape, RES)
    agree = (est == OCCUPIED) == truth
    assert agree.mean() > 0.99
