"""Levenberg-Marquardt on the block Cholesky: never worse, GTSAM's path and optimum, the batch
path's spanning-tree restart, gaps, wrapped starts and graphs in pieces (issue 19 item 1)."""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gcs.graph import se2
from gcs.graph.g2o import (
    G2oError,
    G2oGraph,
    chained_odometry,
    component_roots,
    initial_poses,
    parse_g2o,
    read_g2o,
    to_gtsam,
)
from gcs.graph.optimization import (
    METHODS,
    chi2_test_threshold,
    optimize_batch,
    pose2_factors_from_g2o,
    solve_pose2,
)
from gcs.graph.pose2_gauss_newton import Pose2Factors, gauss_newton_pose2, pose2_chi2
from gcs.graph.pose2_levenberg_marquardt import (
    LevenbergMarquardtConfig,
    levenberg_marquardt_pose2,
)


def _problem(
    seed: int, n: int = 20, loops: int = 8, angle_sigma: float = 2.5
) -> tuple[Pose2Factors, np.ndarray]:
    """A random trajectory with noisy edges and a start with heavy heading noise (GN's
    linearization is poor there)."""
    rng = np.random.default_rng(seed)
    truth = np.cumsum(rng.normal([0.5, 0.0, 0.4], 0.3, (n, 3)), axis=0)
    pairs = [(k, k + 1) for k in range(n - 1)]
    for _ in range(loops):
        a, b = (int(v) for v in rng.choice(n, 2, replace=False))
        pairs.append((a, b))
    z = np.array([se2.between(truth[i], truth[j]) for i, j in pairs])
    z = z + rng.normal(0, 0.05, z.shape)
    factors = Pose2Factors(
        n=n,
        ij=np.array(pairs),
        z=z,
        info=np.tile(np.diag([100.0, 100.0, 400.0]), (len(pairs), 1, 1)),
        prior_index=np.array([0]),
        prior_pose=truth[:1],
        prior_info=np.diag([1e4, 1e4, 1e4])[None],
    )
    start = truth + rng.normal(0, [0.5, 0.5, angle_sigma], truth.shape)
    start[0] = truth[0]
    return factors, start


def _gtsam(
    factors: Pose2Factors, poses: np.ndarray
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    fg = gtsam.NonlinearFactorGraph()
    for (i, j), z, om in zip(factors.ij.tolist(), factors.z, factors.info, strict=True):
        noise = gtsam.noiseModel.Gaussian.Information(om)
        fg.add(gtsam.BetweenFactorPose2(i, j, gtsam.Pose2(*z), noise))
    for k, p, om in zip(
        factors.prior_index.tolist(), factors.prior_pose, factors.prior_info, strict=True
    ):
        fg.add(
            gtsam.PriorFactorPose2(k, gtsam.Pose2(*p), gtsam.noiseModel.Gaussian.Information(om))
        )
    values = gtsam.Values()
    for k, p in enumerate(poses):
        values.insert(k, gtsam.Pose2(*p))
    return fg, values


def _gtsam_lm_chi2(fg: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> float:
    return optimize_batch(
        fg, values, method="lm", ordering="colamd", relative_error_tol=1e-6, max_iterations=100
    ).chi2


def test_never_worse_where_gauss_newton_overshoots() -> None:
    """Seed 6: the Gauss-Newton step from this start raises the chi2 1.6x; LM rejects such
    steps, keeps the chi2 history non-increasing and reaches GTSAM LM's optimum."""
    factors, start = _problem(6)
    gn = gauss_newton_pose2(factors, start)
    assert gn.chi2_history[1] > gn.chi2_history[0]
    # GN no longer returns the worse estimate: it keeps the one before the rising step.
    assert gn.rejected_last_step
    assert gn.chi2 == pytest.approx(pose2_chi2(factors, gn.poses))
    assert gn.chi2 <= gn.chi2_history[0]
    lm = levenberg_marquardt_pose2(factors, start)
    h = np.array(lm.chi2_history)
    assert (np.diff(h) < 0).all()
    assert lm.linear_solves > lm.iterations  # some steps were rejected and retried
    assert lm.chi2 == pytest.approx(pose2_chi2(factors, lm.poses), rel=1e-12)
    assert lm.chi2 < 1e-3 * gn.chi2
    fg, values = _gtsam(factors, start)
    assert lm.chi2 <= _gtsam_lm_chi2(fg, values) * (1 + 1e-3)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 10_000),
    angle_sigma=st.sampled_from([0.1, 1.0, 3.0]),
    lambda_initial=st.sampled_from([1e-5, 1.0]),
)
def test_chi2_history_never_increases(seed: int, angle_sigma: float, lambda_initial: float) -> None:
    factors, start = _problem(seed, angle_sigma=angle_sigma)
    cfg = LevenbergMarquardtConfig(lambda_initial=lambda_initial)
    res = levenberg_marquardt_pose2(factors, start, config=cfg)
    h = np.array(res.chi2_history)
    assert h[0] == pytest.approx(pose2_chi2(factors, start), rel=1e-12)
    assert (np.diff(h) < 0).all()
    assert res.chi2 <= h[0]
    assert len(res.lambda_history) == res.iterations == h.size - 1
    assert res.stop_reason in ("converged", "lambda_upper_bound", "max_iterations")


def test_follows_gtsam_lm_from_the_same_start() -> None:
    """Same schedule, same linear model: the same chi2 as GTSAM's LM at the end."""
    factors, start = _problem(11, n=40, loops=15, angle_sigma=1.0)
    fg, values = _gtsam(factors, start)
    ours = levenberg_marquardt_pose2(
        factors, start, config=LevenbergMarquardtConfig(relative_error_tol=1e-6)
    )
    assert ours.chi2 == pytest.approx(_gtsam_lm_chi2(fg, values), rel=1e-6)


def test_takes_the_gauss_newton_step_where_it_is_good() -> None:
    factors, start = _problem(3, angle_sigma=0.05)
    gn = gauss_newton_pose2(factors, start, relative_error_tol=1e-9)
    lm = levenberg_marquardt_pose2(
        factors, start, config=LevenbergMarquardtConfig(relative_error_tol=1e-9)
    )
    assert lm.linear_solves == lm.iterations  # nothing rejected
    np.testing.assert_allclose(lm.poses, gn.poses, atol=1e-8)


def test_config_is_checked() -> None:
    with pytest.raises(ValueError, match="lambda_factor must be > 1"):
        LevenbergMarquardtConfig(lambda_factor=1.0)
    with pytest.raises(ValueError, match="lambda_initial must be > 0"):
        LevenbergMarquardtConfig(lambda_initial=0.0)


def test_free_component_gets_damped_steps() -> None:
    """Without a prior the normal equations are singular; damping still gives descent."""
    factors, start = _problem(4, angle_sigma=0.3)
    free = Pose2Factors(n=factors.n, ij=factors.ij, z=factors.z, info=factors.info)
    res = levenberg_marquardt_pose2(free, start)
    assert (np.diff(res.chi2_history) < 0).all()
    assert res.chi2 < 1e-2 * res.chi2_history[0]


def _ring(n: int = 400, seed: int = 1) -> G2oGraph:
    """A ring with 0.1 rad heading noise a step closed by one weak loop edge."""
    rng = np.random.default_rng(seed)
    step = np.array([1.0, 0.0, 2.0 * np.pi / n])
    truth = np.zeros((n, 3))
    for k in range(1, n):
        truth[k] = se2.compose(truth[k - 1], step)
    ij = [(k, k + 1) for k in range(n - 1)] + [(n - 1, 0)]
    z, info = [], []
    for i, j in ij:
        sig = np.array([1.0, 1.0, 0.3]) if (i, j) == (n - 1, 0) else np.array([0.05, 0.05, 0.1])
        z.append(se2.compose(se2.between(truth[i], truth[j]), rng.normal(0.0, sig)))
        info.append(np.diag(1.0 / sig**2))
    return G2oGraph(np.arange(n), truth, np.array(ij), np.array(z), np.array(info))


def test_weak_loop_restarts_from_the_spanning_tree() -> None:
    """From chained odometry the ring's LM lands in a local minimum (the loop's winding) far
    above the chi2 test; the batch solve restarts from the tree and reaches GTSAM LM's best."""
    g = _ring()
    chained = initial_poses(g, "chained").poses
    tree = initial_poses(g, "tree").poses
    factors, _ = pose2_factors_from_g2o(g, chained)
    alone = levenberg_marquardt_pose2(factors, chained)
    assert alone.chi2 > chi2_test_threshold(factors)
    sol = solve_pose2(factors, chained)
    assert sol.start == "spanning_tree"
    assert [name for name, _ in sol.runs] == ["given", "spanning_tree"]
    for _, hist in sol.runs:
        assert (np.diff(hist) < 0).all()
    best = min(_gtsam_lm_chi2(*to_gtsam(g, poses=p)) for p in (chained, tree))
    assert sol.chi2 <= best * (1 + 1e-3)
    no_restart = solve_pose2(factors, chained, restart_from_tree=False)
    assert no_restart.chi2 == pytest.approx(alone.chi2)


def test_wrapped_start_reaches_the_same_optimum() -> None:
    """Angles off by multiples of 2 pi and a start turned by ~pi (headings on the +-pi cut)
    change nothing: the same chi2 as from the plain start."""
    factors, start = _problem(8, n=30, loops=10, angle_sigma=0.2)
    plain = levenberg_marquardt_pose2(factors, start)
    rng = np.random.default_rng(2)
    wrapped = start.copy()
    wrapped[:, 2] += 2 * np.pi * rng.integers(-3, 4, size=len(start))
    res = levenberg_marquardt_pose2(factors, wrapped)
    assert res.chi2 == pytest.approx(plain.chi2, rel=1e-9)
    # Turn everything (prior included: a change of gauge) by pi - 1e-3 about the origin.
    turn = np.array([0.0, 0.0, np.pi - 1e-3])
    turned_factors = Pose2Factors(
        n=factors.n,
        ij=factors.ij,
        z=factors.z,
        info=factors.info,
        prior_index=factors.prior_index,
        prior_pose=se2.compose(turn, factors.prior_pose),
        prior_info=factors.prior_info,
    )
    turned = levenberg_marquardt_pose2(turned_factors, se2.compose(turn, wrapped))
    assert turned.chi2 == pytest.approx(plain.chi2, rel=1e-6)
    assert np.abs(turned.poses[:, 2]).max() <= np.pi


def test_batch_path_defaults_to_block_lm() -> None:
    factors, start = _problem(6)
    fg, values = _gtsam(factors, start)
    assert set(METHODS) >= {"gn", "lm", "dogleg", "block_gn", "block_lm"}
    res = optimize_batch(fg, values)
    assert res.chi2_history and (np.diff(res.chi2_history) < 0).all()
    assert res.chi2 <= _gtsam_lm_chi2(fg, values) * (1 + 1e-3)
    gn = optimize_batch(fg, values, method="block_gn")
    assert gn.chi2 <= 2 * fg.error(values)  # plain GN: never worse than the start either
    assert res.chi2 < gn.chi2


def test_gap_in_odometry_initializes_by_spanning_tree() -> None:
    """No edge 2 -> 3: chained odometry cannot cross, the spanning tree over all edges can."""
    truth = np.array([[0, 0, 0], [1, 0, 0.5], [1.5, 1, 1.5], [1, 2, 3.0], [0, 1, -2.0]])
    pairs = [(0, 1), (1, 2), (3, 4), (4, 0), (1, 3), (2, 4)]
    text = "".join(
        f"EDGE_SE2 {i} {j} "
        + " ".join(map(repr, se2.between(truth[i], truth[j]).tolist()))
        + " 100 0 0 100 0 400\n"
        for i, j in pairs
    )
    g = parse_g2o(text)
    with pytest.raises(G2oError, match="no edge between vertices 2 and 3"):
        chained_odometry(g)
    start = initial_poses(g, "chained")
    assert start.kind == "tree"
    assert "no edge between vertices 2 and 3" in start.note and "spanning tree" in start.note
    np.testing.assert_allclose(start.poses, truth, atol=1e-9)  # consistent graph: exact
    fg, values = to_gtsam(g, poses=start.poses)
    assert optimize_batch(fg, values).chi2 < 1e-12
    file_start = initial_poses(g, "file")
    assert file_start.kind == "tree" and "no VERTEX_SE2" in file_start.note
    with pytest.raises(ValueError, match="unknown kind"):
        initial_poses(g, "odometry")  # type: ignore[arg-type]


def test_graph_in_pieces_is_anchored_per_component() -> None:
    text = (
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nVERTEX_SE2 5 3 3 1\n"
        "VERTEX_SE2 7 9 9 0\nVERTEX_SE2 8 9 8 0\n"
        "EDGE_SE2 0 1 1.1 0 0 100 0 0 100 0 400\n"
        "EDGE_SE2 7 8 1.0 0.1 0.2 100 0 0 100 0 400\n"
    )
    g = parse_g2o(text)
    assert component_roots(g).tolist() == [0, 5, 7]
    fg, values = to_gtsam(g)
    assert fg.size() == 2 + 3
    for method in ("block_lm", "block_gn", "lm"):
        res = optimize_batch(fg, values, method=method)  # type: ignore[arg-type]
        assert res.chi2 < 1e-9
        np.testing.assert_allclose(se2.pose_vec(res.values.atPose2(5)), [3, 3, 1], atol=1e-6)
    tree = initial_poses(g, "tree").poses
    np.testing.assert_allclose(tree[2], [3, 3, 1])  # the isolated vertex keeps its pose
    np.testing.assert_allclose(tree[4], se2.compose(tree[3], g.edge_z[1]), atol=1e-12)
    missing = parse_g2o("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(G2oError, match="vertex 1 .* no VERTEX_SE2"):
        to_gtsam(missing)


@pytest.mark.parametrize("name", ["intel.g2o", "manhattan_olson3500.g2o"])
def test_reaches_gtsam_lm_optimum_on_shipped_graphs(posegraph_dir: Path, name: str) -> None:
    """Within 0.1% of the best chi2 GTSAM LM reaches from any start, from chained odometry and
    from the spanning tree; no accepted step raises the chi2."""
    g = read_g2o(posegraph_dir / name)
    starts = {kind: initial_poses(g, kind).poses for kind in ("chained", "tree")}
    best = min(_gtsam_lm_chi2(*to_gtsam(g, poses=p)) for p in starts.values())
    for kind, p in starts.items():
        factors, _ = pose2_factors_from_g2o(g, p)
        sol = solve_pose2(factors, p)
        assert sol.chi2 <= best * (1 + 1e-3), kind
        assert all((np.diff(h) < 0).all() for _, h in sol.runs)


def test_m3500b_from_chained_odometry_restarts(posegraph_dir: Path) -> None:
    """GTSAM LM stalls from chained odometry on manhattan_M3500b; the batch solve's chi2 test
    sends it to the spanning tree, where it reaches GTSAM LM's best (from the tree)."""
    g = read_g2o(posegraph_dir / "manhattan_M3500b.g2o")
    tree = initial_poses(g, "tree").poses
    best = _gtsam_lm_chi2(*to_gtsam(g, poses=tree))
    chained = initial_poses(g, "chained").poses
    factors, _ = pose2_factors_from_g2o(g, chained)
    sol = solve_pose2(factors, chained)
    assert sol.start == "spanning_tree"
    assert sol.chi2 <= best * (1 + 1e-3)
