"""The highway: driven waypoints, merged when close, following re-optimized poses."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.sparse.csgraph import dijkstra

from gcs.tasking.trajectory_graph import TrajectoryGraphConfig, build_trajectory_graph


def _line(x0: float, x1: float, y: float, step: float = 0.5) -> np.ndarray:
    xs = np.arange(x0, x1 + 1e-9, step)
    return np.stack([xs, np.full_like(xs, y)], axis=1)


def test_driven_roads_connect_and_parallel_roads_do_not() -> None:
    a = _line(0, 20, 0.0)
    b = _line(0, 20, 10.0)
    xy = np.vstack([a, b])
    rid = np.r_[np.full(len(a), 1), np.full(len(b), 2)]
    key = np.arange(len(xy))
    hw = build_trajectory_graph(rid, key, xy)
    na, nb = hw.node_of_pose[0], hw.node_of_pose[len(a)]
    d, _ = hw.distances([na])
    assert np.isinf(d[0, nb])
    assert d[0, hw.node_of_pose[len(a) - 1]] == pytest.approx(20.0, abs=1.5)


def test_two_robots_on_one_road_share_it() -> None:
    a = _line(0, 20, 0.0)
    b = _line(10, 30, 0.4)  # a second robot 0.4 m beside the first, further on
    xy = np.vstack([a, b])
    rid = np.r_[np.full(len(a), 1), np.full(len(b), 2)]
    hw = build_trajectory_graph(rid, np.arange(len(xy)), xy)
    d, pred = hw.distances([hw.node_of_pose[0]])
    end = hw.node_of_pose[-1]
    assert d[0, end] == pytest.approx(30.0, abs=2.0)
    path = hw.path(pred[0], end)
    assert path[0] == hw.node_of_pose[0] and path[-1] == end
    assert d[0, end] == pytest.approx(dijkstra(hw.adjacency, indices=path[0])[end])


def test_a_gap_in_the_data_is_not_a_road() -> None:
    xy = np.vstack([_line(0, 10, 0.0), _line(30, 40, 0.0)])
    hw = build_trajectory_graph(np.ones(len(xy)), np.arange(len(xy)), xy)
    d, _ = hw.distances([hw.node_of_pose[0]])
    assert np.isinf(d[0, hw.node_of_pose[-1]])


def test_follows_re_optimized_poses() -> None:
    xy = _line(0, 20, 0.0)
    key = np.arange(len(xy))
    hw = build_trajectory_graph(np.ones(len(xy)), key, xy)
    bent = xy + np.stack([np.zeros(len(xy)), 0.2 * xy[:, 0]], axis=1)  # a loop closure bent it
    hw2 = build_trajectory_graph(np.ones(len(xy)), key, bent)
    assert np.allclose(hw2.nodes_in_map[hw2.node_of_pose[-1]], bent[-1], atol=1.5)
    assert not np.allclose(hw.nodes_in_map[hw.node_of_pose[-1]], bent[-1], atol=1.5)


def test_key_order_not_input_order_defines_the_road() -> None:
    xy = _line(0, 10, 0.0)
    perm = np.random.default_rng(0).permutation(len(xy))
    hw = build_trajectory_graph(np.ones(len(xy)), perm, xy[np.argsort(perm)])
    d, _ = hw.distances([hw.node_of_pose[np.argsort(perm)][0]])
    assert np.isfinite(d).all()


def test_bad_input_is_named() -> None:
    with pytest.raises(ValueError, match="robot ids"):
        build_trajectory_graph([1, 1], [1], [[0, 0], [1, 1]])
    with pytest.raises(ValueError, match="spacing_m"):
        TrajectoryGraphConfig(spacing_m=0.0)
