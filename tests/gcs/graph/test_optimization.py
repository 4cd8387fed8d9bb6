from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.g2o import chained_odometry, read_g2o, to_gtsam
from gcs.graph.optimization import (
    Isam2Config,
    Isam2Solver,
    compute_ordering,
    optimize_batch,
    optimize_pose2,
    pose2_factors,
    pose2_factors_from_g2o,
    values_from_poses,
)


def _solve(path: Path, *, use_vertices: bool, method: str, ordering: str) -> float:
    g = read_g2o(path)
    fg, values = to_gtsam(g, poses=None if use_vertices else chained_odometry(g))
    res = optimize_batch(fg, values, method=method, ordering=ordering)  # type: ignore[arg-type]
    return g.chi2(res.values)


@pytest.mark.parametrize("ordering", ["colamd", "metis", "emd"])
def test_manhattan_olson3500_optimum(posegraph_dir: Path, ordering: str) -> None:
    chi2 = _solve(
        posegraph_dir / "manhattan_olson3500.g2o",
        use_vertices=False,
        method="gn",
        ordering=ordering,
    )
    assert chi2 == pytest.approx(146.08, rel=1e-3)


@pytest.mark.parametrize("method", ["gn", "lm", "dogleg"])
def test_intel_optimum(posegraph_dir: Path, method: str) -> None:
    chi2 = _solve(posegraph_dir / "intel.g2o", use_vertices=True, method=method, ordering="emd")
    assert chi2 == pytest.approx(45.004, rel=1e-3)


def test_natural_ordering_same_optimum() -> None:
    rng = np.random.default_rng(2)
    n = 80
    truth = np.cumsum(rng.normal([0.5, 0.0, 0.2], 0.1, size=(n, 3)), axis=0)
    fg = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([0.05, 0.05, 0.02]))
    pairs = [(k, k + 1) for k in range(n - 1)] + [
        (int(a), int(b)) for a, b in rng.integers(0, n, (40, 2)) if a != b
    ]
    for i, j in pairs:
        z = se2.between(truth[i], truth[j]) + rng.normal(0, [0.05, 0.05, 0.02])
        fg.add(gtsam.BetweenFactorPose2(i, j, se2.pose2(z), noise))
    fg.add(gtsam.PriorFactorPose2(0, se2.pose2(truth[0]), noise))
    values = gtsam.Values()
    for k in range(n):
        values.insert(k, se2.pose2(truth[k]))
    chi2s = [optimize_batch(fg, values, ordering=o).chi2 for o in ("natural", "colamd", "emd")]
    assert chi2s[0] == pytest.approx(chi2s[1], rel=1e-6)
    assert chi2s[0] == pytest.approx(chi2s[2], rel=1e-6)


@pytest.mark.parametrize("ordering", ["emd", "colamd", "metis"])
def test_block_gn_from_arrays_reaches_manhattan_olson3500_optimum(
    posegraph_dir: Path, ordering: str
) -> None:
    g = read_g2o(posegraph_dir / "manhattan_olson3500.g2o")
    odo = chained_odometry(g)
    fg, values = to_gtsam(g, poses=odo)
    factors, keys = pose2_factors_from_g2o(g, odo)
    res = optimize_pose2(fg, values, factors, keys, ordering=ordering, initial_poses=odo)  # type: ignore[arg-type]
    assert g.chi2(res.values) == pytest.approx(146.08, rel=1e-3)
    assert res.chi2 + g.chi2_offset == pytest.approx(g.chi2(res.values), rel=1e-12)
    # Same optimum as GTSAM's Gauss-Newton, in as many iterations.
    ref = optimize_batch(fg, values, method="gn", ordering="colamd")
    assert res.iterations == ref.iterations
    assert res.chi2 == pytest.approx(ref.chi2, rel=1e-9)


@pytest.mark.parametrize("name", ["intel.g2o", "manhattan.g2o"])
def test_block_gn_through_optimize_batch(posegraph_dir: Path, name: str) -> None:
    g = read_g2o(posegraph_dir / name)
    fg, values = to_gtsam(g, poses=None if name == "intel.g2o" else chained_odometry(g))
    res = optimize_batch(fg, values, method="block_gn", ordering="colamd")
    expected = 45.004 if name == "intel.g2o" else 3549.04
    assert g.chi2(res.values) == pytest.approx(expected, rel=1e-3)


def test_block_gn_city10000_optimum(posegraph_dir: Path) -> None:
    g = read_g2o(posegraph_dir / "city10000.g2o")
    odo = chained_odometry(g)
    fg, values = to_gtsam(g, poses=odo)
    factors, keys = pose2_factors_from_g2o(g, odo)
    res = optimize_pose2(fg, values, factors, keys, ordering="emd", initial_poses=odo)
    assert g.chi2(res.values) == pytest.approx(511.99, rel=1e-3)


def test_pose2_factors_read_the_graph() -> None:
    fg = gtsam.NonlinearFactorGraph()
    info = np.array([[4.0, 1.0, 0.2], [1.0, 3.0, 0.1], [0.2, 0.1, 9.0]])
    fg.add(
        gtsam.BetweenFactorPose2(
            10, 30, gtsam.Pose2(1, 2, 0.3), gtsam.noiseModel.Gaussian.Information(info)
        )
    )
    fg.add(
        gtsam.PriorFactorPose2(30, gtsam.Pose2(-1, 0, 2), gtsam.noiseModel.Isotropic.Sigma(3, 0.5))
    )
    f = pose2_factors(fg, np.array([10, 20, 30]))
    assert f.n == 3
    np.testing.assert_array_equal(f.ij, [[0, 2]])
    np.testing.assert_allclose(f.z, [[1, 2, 0.3]])
    np.testing.assert_allclose(f.info[0], info)
    np.testing.assert_array_equal(f.prior_index, [2])
    np.testing.assert_allclose(f.prior_pose, [[-1, 0, 2]])
    np.testing.assert_allclose(f.prior_info[0], 4 * np.eye(3))
    with pytest.raises(ValueError, match="a between factor refers to key 10, not a variable"):
        pose2_factors(fg, np.array([20, 30]))
    robust = gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(1.0), gtsam.noiseModel.Unit.Create(3)
    )
    fg.add(gtsam.BetweenFactorPose2(10, 20, gtsam.Pose2(), robust))
    with pytest.raises(ValueError, match="factor 2 .* needs a Gaussian noise model"):
        pose2_factors(fg, np.array([10, 20, 30]))
    other = gtsam.NonlinearFactorGraph()
    other.add(gtsam.PriorFactorPoint2(10, np.zeros(2), gtsam.noiseModel.Unit.Create(2)))
    with pytest.raises(ValueError, match="factor 0 is a PriorFactorPoint2"):
        pose2_factors(other, np.array([10]))


def test_values_from_poses_round_trip() -> None:
    rng = np.random.default_rng(7)
    keys = np.array([3, 8, 100])
    template = gtsam.Values()
    for k in keys.tolist():
        template.insert(k, se2.pose2(rng.normal(0, 2, 3)))
    poses = rng.normal(0, 3, (3, 3))
    poses[:, 2] = [0.1, -3.0, 3.1]
    out = values_from_poses(template, keys, poses)
    got = np.array([se2.pose_vec(out.atPose2(k)) for k in keys.tolist()])
    np.testing.assert_allclose(got, poses, atol=1e-12)
    with pytest.raises(ValueError, match="template keys differ"):
        values_from_poses(template, np.array([3, 8, 9]), poses)


def test_manhattan_edges_only_optimum(posegraph_dir: Path) -> None:
    chi2 = _solve(posegraph_dir / "manhattan.g2o", use_vertices=False, method="gn", ordering="emd")
    assert chi2 == pytest.approx(3549.04, rel=1e-3)


@pytest.mark.slow
def test_city10000_optimum(posegraph_dir: Path) -> None:
    chi2 = _solve(posegraph_dir / "city10000.g2o", use_vertices=False, method="gn", ordering="emd")
    assert chi2 == pytest.approx(511.99, rel=1e-3)


def test_unknown_ordering_and_method() -> None:
    fg = gtsam.NonlinearFactorGraph()
    with pytest.raises(ValueError, match="unknown ordering"):
        compute_ordering(fg, "amd")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown method"):
        optimize_batch(fg, gtsam.Values(), method="sgd")  # type: ignore[arg-type]


@pytest.mark.slow
def test_isam2_incremental_reaches_batch_optimum(posegraph_dir: Path) -> None:
    g = read_g2o(posegraph_dir / "intel.g2o")
    solver = Isam2Solver(Isam2Config(relinearize_threshold=0.01, relinearize_skip=1))
    by_newest: dict[int, list[int]] = {}
    for m, (i, j) in enumerate(g.edge_ij.tolist()):
        by_newest.setdefault(max(i, j), []).append(m)
    n = len(g.node_ids)
    last = gtsam.Pose2()
    for k in range(n):
        fg = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        if k == 0:
            prior_noise = gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
            fg.add(gtsam.PriorFactorPose2(0, gtsam.Pose2(), prior_noise))
            values.insert(0, gtsam.Pose2())
        else:
            guess = None
            for m in by_newest.get(k, []):
                i, j = (int(v) for v in g.edge_ij[m])
                noise = gtsam.noiseModel.Gaussian.Information(g.edge_info[m])
                fg.add(gtsam.BetweenFactorPose2(i, j, se2.pose2(g.edge_z[m]), noise))
                if (i, j) == (k - 1, k):
                    guess = last.compose(se2.pose2(g.edge_z[m]))
            assert guess is not None
            values.insert(k, guess)
        solver.update(fg, values)
        last = solver.estimate_pose(k)
    for _ in range(3):
        solver.update(gtsam.NonlinearFactorGraph(), gtsam.Values())
    estimate = solver.estimate()
    assert g.chi2(estimate) == pytest.approx(45.004, rel=1e-2)
    fg, _ = to_gtsam(g, prior_sigma=1e-6)
    batch = optimize_batch(fg, estimate, method="gn")
    a = np.array([se2.pose_vec(estimate.atPose2(k)) for k in range(n)])
    b = np.array([se2.pose_vec(batch.values.atPose2(k)) for k in range(n)])
    assert np.abs(a[:, :2] - b[:, :2]).max() < 0.05


@pytest.mark.parametrize("method", ["block_gn", "block_lm"])
def test_pose_graph_solves_with_block_methods(method: str) -> None:
    """PoseGraph's graph (robot keys, map anchor, weak anchor of a floating robot) through
    ``block_gn`` / ``block_lm`` lands on the same estimate as GTSAM's Levenberg-Marquardt."""
    from gcs.graph.pose_graph import PoseGraph, PoseGraphConfig, Provenance

    rng = np.random.default_rng(3)
    graph = PoseGraph(PoseGraphConfig(map_from_odom=(1.0, 2.0, 0.3), relative_error_tol=1e-12))
    cov = np.diag([0.02**2, 0.02**2, 0.01**2])
    for robot in (0, 1, 2):
        pose = rng.normal(0, 3, 3)
        graph.add_pose(robot, odom_from_base=pose, time_s=0.0)
        for k in range(1, 25):
            pose = se2.compose(pose, np.array([1.0, 0.0, 0.2]) + rng.normal(0, 0.02, 3))
            graph.add_pose(robot, odom_from_base=pose, time_s=float(k), odometry_covariance=cov)
    keys0, keys1 = graph.poses(0)[0], graph.poses(1)[0]
    graph.add_edge(
        int(keys0[3]),
        int(keys1[7]),
        a_from_b=np.array([0.5, -1.0, 0.4]),
        covariance=cov * 4,
        provenance=Provenance.FIDUCIAL,
        time_s=30.0,
    )
    graph.add_edge(
        int(keys0[20]),
        int(keys0[2]),
        a_from_b=np.array([0.3, 0.2, -0.1]),
        covariance=cov * 25,
        provenance=Provenance.LOOP_AUTO,
        time_s=31.0,
    )
    reference = graph.copy()
    reference.optimize(method="lm")
    summary = graph.optimize(method=method)  # type: ignore[arg-type]
    assert summary.components == 2
    assert summary.chi2 == pytest.approx(reference.optimize(method="lm").chi2, rel=1e-6)
    for robot in (0, 1, 2):
        np.testing.assert_allclose(graph.poses(robot)[1], reference.poses(robot)[1], atol=1e-6)
