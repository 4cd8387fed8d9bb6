"""Odometry edges re-expressed in place (issue 19 item 4): :meth:`PoseGraph.update_edges`,
:meth:`PoseGraph.set_odometry_correction`, :meth:`PoseGraph.odometry_reported`, and iSAM2
after them."""

from __future__ import annotations

import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.pose_graph import PoseGraph, PoseGraphError, Provenance

ODO_COV = np.diag([0.02**2, 0.02**2, 0.01**2])
LOOP_COV = np.diag([0.02**2, 0.02**2, 0.005**2])


def scale_yaw(factor: float, extra_var: float = 0.0):  # type: ignore[no-untyped-def]
    def correct(z: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = z.copy()
        cov = cov.copy()
        z[:, 2] *= factor
        cov[:, 2, 2] += extra_var
        return z, cov

    return correct


def square_loop(under_read: float) -> tuple[PoseGraph, np.ndarray, list[int]]:
    """A robot driving a 4 m square twice; its odometry reads every turn ``under_read`` times
    the truth; a loop closure (exact) back to the start after each lap."""
    truth = [np.zeros(3)]
    for _lap in range(2):
        for _side in range(4):
            for _ in range(4):
                truth.append(se2.compose(truth[-1], np.array([1.0, 0.0, 0.0])))
            truth.append(se2.compose(truth[-1], np.array([0.0, 0.0, np.pi / 2])))
    truth_arr = np.array(truth)
    g = PoseGraph()
    odom = truth_arr[0].copy()
    keys = [g.add_pose(0, odom_from_base=odom, time_s=0.0)]
    for k in range(1, len(truth_arr)):
        step = se2.between(truth_arr[k - 1], truth_arr[k]).copy()
        step[2] *= under_read
        odom = se2.compose(odom, step)
        keys.append(g.add_pose(0, odom_from_base=odom, time_s=k, odometry_covariance=ODO_COV))
    for lap_end in (20, 40):
        g.add_edge(
            keys[0],
            keys[lap_end],
            a_from_b=se2.between(truth_arr[0], truth_arr[lap_end]),
            covariance=LOOP_COV,
            provenance=Provenance.LOOP_AUTO,
            time_s=float(lap_end),
        )
    return g, truth_arr, keys


def ate(g: PoseGraph, keys: list[int], truth: np.ndarray) -> float:
    est = np.array([g.pose(k) for k in keys])
    return float(np.sqrt(np.mean(np.sum((est[:, :2] - truth[:, :2]) ** 2, axis=1))))


def test_a_turn_scale_correction_rewrites_every_odometry_edge_and_later_ones() -> None:
    g, truth, keys = square_loop(0.92)
    g.optimize()
    biased = ate(g, keys, truth)
    _ids, keys_b, z_reported, cov_reported = g.odometry_reported(0)
    assert list(keys_b) == keys[1:]
    assert g.set_odometry_correction(0, scale_yaw(1 / 0.92)) == len(keys) - 1
    g.optimize()
    corrected = ate(g, keys, truth)
    assert corrected < 0.02 < biased / 5  # the corrected odometry agrees with the closures
    # what the robot reported is kept, whatever the correction
    _ids, _kb, z_again, cov_again = g.odometry_reported(0)
    np.testing.assert_allclose(z_again, z_reported)
    np.testing.assert_allclose(cov_again, cov_reported)
    odo = g.edges(Provenance.ODOMETRY)
    np.testing.assert_allclose([e.z[2] for e in odo], z_reported[:, 2] / 0.92)
    # a new pose gets the correction as it arrives
    last = g.nodes(0)[-1].odom_from_base
    key = g.add_pose(
        0,
        odom_from_base=se2.compose(last, np.array([0.0, 0.0, 0.92 * np.pi / 2])),
        time_s=99.0,
        odometry_covariance=ODO_COV,
    )
    new = g.edges(Provenance.ODOMETRY)[-1]
    assert new.key_b == key and new.z[2] == pytest.approx(np.pi / 2)
    # corrections never compound: a second one starts from the reported increments again
    g.set_odometry_correction(0, scale_yaw(1.0, extra_var=1e-4))
    odo = g.edges(Provenance.ODOMETRY)
    np.testing.assert_allclose([e.z[2] for e in odo][:-1], z_reported[:, 2])
    assert odo[0].covariance[2, 2] == pytest.approx(ODO_COV[2, 2] + 1e-4)
    g.set_odometry_correction(0, None)
    np.testing.assert_allclose(
        [e.covariance for e in g.edges(Provenance.ODOMETRY)][:-1], cov_reported
    )


def test_isam2_after_an_update_agrees_with_the_batch_solution() -> None:
    g, truth, keys = square_loop(1.08)
    assert g.optimize_incremental() is None
    g.set_odometry_correction(0, scale_yaw(1 / 1.08))
    h = g.copy()
    h.optimize()
    # iSAM2 is re-seeded with the new measurements: from the old estimate its first update
    # lands within millimetres, and from the batch solution exactly on it
    assert g.optimize_incremental() is None
    assert ate(g, keys, truth) < 0.02
    g.optimize()
    assert g.optimize_incremental() is None
    for k in keys:
        d = se2.between(h.pose(k), g.pose(k))
        np.testing.assert_allclose(d, 0.0, atol=1e-6)
    # the copy keeps the correction for later poses
    last = h.nodes(0)[-1].odom_from_base
    h.add_pose(
        0,
        odom_from_base=se2.compose(last, np.array([0.0, 0.0, 1.08])),
        time_s=99.0,
        odometry_covariance=ODO_COV,
    )
    assert h.edges(Provenance.ODOMETRY)[-1].z[2] == pytest.approx(1.0)


def test_bad_updates_are_named_and_change_nothing() -> None:
    g, _truth, _keys = square_loop(1.0)
    before = {e.edge_id: e for e in g.edges()}
    first, second = list(before)[:2]
    with pytest.raises(PoseGraphError, match="no edge with id 12345"):
        g.update_edges({first: (np.zeros(3), ODO_COV), 12345: (np.zeros(3), ODO_COV)})
    with pytest.raises(PoseGraphError, match=f"edge {second}.*non-finite"):
        g.update_edges({first: (np.zeros(3), ODO_COV), second: (np.array([np.nan, 0, 0]), ODO_COV)})
    with pytest.raises(PoseGraphError, match="not positive definite"):
        g.update_edges({second: (np.zeros(3), -ODO_COV)})
    with pytest.raises(PoseGraphError, match="expected shapes"):
        g.set_odometry_correction(0, lambda z, c: (z[:1], c[:1]))
    with pytest.raises(PoseGraphError, match="unknown robot 7"):
        g.set_odometry_correction(7, None)
    assert {e.edge_id: e for e in g.edges()} == before
    # a correction that would make a new edge non-physical is refused at add_pose, named
    g.set_odometry_correction(0, lambda z, c: (z, c * np.nan if len(z) == 1 else c))
    last = g.nodes(0)[-1].odom_from_base
    with pytest.raises(PoseGraphError, match="corrected odometry"):
        g.add_pose(0, odom_from_base=last, time_s=99.0, odometry_covariance=ODO_COV)
