"""The pose graph's incremental views (issue 16: a GCS that keeps up with 100 robots):
additions since a mark, poses moved since a revision, and the estimate read back in bulk."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.keys import pose_key
from gcs.graph.pose_graph import (
    AutoSimplifyConfig,
    PoseGraph,
    PoseGraphConfig,
    PoseGraphError,
    Provenance,
)
from tests.gcs.graph.test_pose_graph import LOOP_COV, drive, trajectory


def _two_robots(rng: np.random.Generator, n: int = 30) -> tuple[PoseGraph, list[int], list[int]]:
    g = PoseGraph()
    a = drive(g, 0, trajectory(rng, n, np.zeros(3)), np.zeros(3), rng)
    b = drive(g, 1, trajectory(rng, n, np.array([3.0, 1.0, 0.5])), np.zeros(3), rng, t0=0.5)
    return g, a, b


def test_additions_since_a_mark_list_what_was_added_in_order_until_another_change() -> None:
    rng = np.random.default_rng(1)
    g, a, b = _two_robots(rng)
    mark = g.change_mark()
    assert g.additions_since(mark) is not None
    assert g.additions_since(mark).node_keys == []  # type: ignore[union-attr]
    k_new = g.add_pose(
        0, odom_from_base=(40.0, 0.0, 0.0), time_s=40.0, odometry_covariance=LOOP_COV
    )
    eid = g.add_edge(
        a[3],
        b[3],
        a_from_b=se2.between(g.pose(a[3]), g.pose(b[3])),
        covariance=LOOP_COV,
        provenance=Provenance.LOOP_AUTO,
        time_s=41.0,
    )
    added = g.additions_since(mark)
    assert added is not None
    assert added.node_keys == [k_new]
    assert [e.edge_id for e in added.edges] == [eid - 1, eid]  # the odometry edge, the loop
    assert added.edges[0].provenance is Provenance.ODOMETRY and added.edges[0].key_b == k_new
    assert g.node_count == len(g.nodes()) and g.edge_count == len(g.edges())
    # from the new mark on: nothing; a removal ends the incremental view
    later = added.mark
    assert g.additions_since(later) == type(added)([], [], later)
    g.remove_edges([eid])
    assert g.additions_since(later) is None and g.additions_since(mark) is None
    fresh = g.change_mark()
    g.update_edges({eid - 1: (added.edges[0].z, LOOP_COV)})
    assert g.additions_since(fresh) is None
    # a restore rebuilds the logs: a mark taken after it works again
    snap = g.snapshot()
    g.restore(snap)
    m2 = g.change_mark()
    k2 = g.add_pose(1, odom_from_base=(9.0, 9.0, 0.0), time_s=50.0, odometry_covariance=LOOP_COV)
    assert g.additions_since(m2).node_keys == [k2]  # type: ignore[union-attr]


def test_moved_since_lists_the_poses_a_solve_moved_and_the_estimate_matches_per_key_reads() -> None:
    rng = np.random.default_rng(2)
    g, a, b = _two_robots(rng, 40)
    g.optimize_incremental()
    rev = g.estimate_revision
    assert g.moved_since(rev).size == 0  # type: ignore[union-attr]
    # an addition at the end of robot 1's chain: iSAM2 moves (at most) what it touches
    k_new = g.add_pose(
        1, odom_from_base=(50.0, 0.0, 0.0), time_s=60.0, odometry_covariance=LOOP_COV
    )
    g.optimize_incremental()
    moved = g.moved_since(rev)
    assert moved is not None and np.all(np.diff(moved) > 0)
    # the new pose (solved from its first guess) and at most robot 1's others: robot 0 is
    # not linked to robot 1
    assert k_new in moved.tolist() and set(moved.tolist()) <= set(b) | {k_new}
    # the bulk read is the per-key read, bit for bit
    fg, values = g.factor_graph()
    isam_values = g._isam.estimate()  # type: ignore[union-attr]
    for key in a + b:
        assert np.array_equal(g.pose(key), se2.pose_vec(isam_values.atPose2(key)))
    # a loop closure between the robots merges them: robot 0's poses move (rigidly)
    rev2 = g.estimate_revision
    g.add_edge(
        a[5],
        b[5],
        a_from_b=np.array([1.0, 0.0, 0.0]),
        covariance=LOOP_COV,
        provenance=Provenance.LOOP_AUTO,
        time_s=70.0,
    )
    moved2 = g.moved_since(rev2)
    assert moved2 is not None and set(moved2.tolist()) & (set(a) | set(b))
    # a revision older than the log: unknown, None
    for k in range(70):
        g.add_pose(0, odom_from_base=(60.0 + k, 0.0, 0.0), time_s=80.0 + k,
                   odometry_covariance=LOOP_COV)  # fmt: skip
        g.initialize_from_spanning_trees()
    assert g.moved_since(rev) is None
    del fg


def test_set_estimate_names_a_missing_pose_and_refuses_non_finite_values() -> None:
    rng = np.random.default_rng(3)
    g, a, _b = _two_robots(rng, 5)
    _fg, values = g.factor_graph()
    short = gtsam.Values()
    for key in a:
        short.insert(key, values.atPose2(key))
    with pytest.raises(PoseGraphError, match=r"no value for pose \(1, 0\)"):
        g.set_estimate(short)
    before = {k: g.pose(k) for k in a}
    bad = gtsam.Values(values)
    bad.update(pose_key(0, 2), gtsam.Pose2(float("nan"), 0.0, 0.0))
    with pytest.raises(PoseGraphError, match=r"non-finite at 1 poses, e.g. \(0, 2\)"):
        g.set_estimate(bad)
    assert all(np.array_equal(g.pose(k), p) for k, p in before.items())
    # values with another type beside the poses: read one pose at a time, same numbers
    mixed = gtsam.Values(values)
    mixed.insert(gtsam.symbol("q", 1), gtsam.Point2(1.0, 2.0))
    g.set_estimate(mixed)
    assert all(np.array_equal(g.pose(k), se2.pose_vec(values.atPose2(k))) for k in a)


def test_the_graph_simplifies_itself_when_due_and_keeps_its_optimum() -> None:
    rng = np.random.default_rng(4)
    auto = AutoSimplifyConfig(min_poses=60, max_edges_per_pose=1.2, min_interval_s=100.0)
    g = PoseGraph(PoseGraphConfig(auto_simplify=auto))
    assert not g.simplify_due(1000.0)  # no poses: too small
    out = trajectory(rng, 40, np.zeros(3))
    truth = np.vstack([out, out[-2::-1]])  # out and back: 79 poses
    keys = drive(g, 0, truth, np.zeros(3), rng)
    # the way back re-observes the way out: closures, each one twice
    for k in range(0, 38, 2):
        for _ in range(2):
            g.add_edge(
                keys[k],
                keys[78 - k],
                a_from_b=rng.normal(0, [0.02, 0.02, 0.01]),
                covariance=LOOP_COV,
                provenance=Provenance.LOOP_AUTO,
                time_s=90.0,
            )
    assert g.relative_edge_count() == 78 + 38 > 1.2 * g.node_count
    g.optimize()
    before = {k: g.pose(k) for k in keys}
    mark = g.change_mark()
    assert g.simplify_due(200.0)
    removed = g.simplify_if_due(200.0)
    assert removed and g.relative_edge_count() == 78 + 38 - len(removed)
    assert all(e.provenance is Provenance.LOOP_AUTO for e in removed)  # the chain stays
    assert g.additions_since(mark) is None  # consumers rebuild their copies
    g.optimize()
    assert max(float(np.abs(g.pose(k) - p).max()) for k, p in before.items()) < 1e-4
    # not again before min_interval_s, and never without the policy
    assert g.simplify_if_due(250.0) == [] and not g.simplify_due(250.0)
    assert not PoseGraph().simplify_due(1e9)
    with pytest.raises(ValueError, match="max_edges_per_pose"):
        AutoSimplifyConfig(max_edges_per_pose=0.0)


def test_a_graph_pickled_before_the_incremental_views_loads_and_solves() -> None:
    import pickle

    rng = np.random.default_rng(5)
    g, a, b = _two_robots(rng, 10)
    g.optimize_incremental()
    state = dict(g.__dict__)
    state.pop("_isam", None)  # a GTSAM object: not what this test is about
    for name in ("_node_log", "_edge_log", "_epoch", "_estimate_revision", "_moved",
                 "_last_simplified_s", "_relative_count", "_prior_cache", "_est_cache",
                 "_isam_mark"):  # fmt: skip
        state.pop(name)
    state["_isam_edges"], state["_isam_keys"] = set(g._edges), set(g._nodes)  # the old ones
    old = PoseGraph.__new__(PoseGraph)
    old.__setstate__(pickle.loads(pickle.dumps(state)))
    assert old._isam_stale and not hasattr(old, "_isam_edges")
    mark = old.change_mark()
    k = old.add_pose(0, odom_from_base=(9.0, 0.0, 0.0), time_s=20.0, odometry_covariance=LOOP_COV)
    assert old.additions_since(mark).node_keys == [k]  # type: ignore[union-attr]
    assert old.optimize_incremental() is None
    g.add_pose(0, odom_from_base=(9.0, 0.0, 0.0), time_s=20.0, odometry_covariance=LOOP_COV)
    g.optimize()
    old.optimize()
    assert all(np.allclose(old.pose(key), g.pose(key), atol=1e-9) for key in a + b + [k])
