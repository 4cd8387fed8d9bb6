from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.g2o import G2oGraph, read_g2o, write_g2o
from gcs.graph.keys import pose_key
from gcs.graph.pose_graph import (
    EdgeRecord,
    PoseGraph,
    PoseGraphConfig,
    PoseGraphError,
    PoseGraphSnapshot,
    Provenance,
)
from mission.config import ConfigError, load_config_text

ODO_COV = np.diag([0.02**2, 0.02**2, 0.01**2])
FID_COV = np.diag([0.05**2, 0.05**2, 0.02**2])
LOOP_COV = np.diag([0.1**2, 0.1**2, 0.03**2])


def trajectory(rng: np.random.Generator, n: int, start: np.ndarray) -> np.ndarray:
    """Ground-truth map_from_base poses: a wiggly path starting at ``start``."""
    steps = np.column_stack([np.full(n - 1, 1.0), np.zeros(n - 1), rng.normal(0, 0.15, n - 1)])
    poses = [start]
    for s in steps:
        poses.append(se2.compose(poses[-1], s))
    return np.array(poses)


def drive(
    graph: PoseGraph,
    robot: int,
    truth_map: np.ndarray,
    map_from_odom_true: np.ndarray,
    rng: np.random.Generator,
    *,
    t0: float = 0.0,
    noise: float = 1.0,
) -> list[int]:
    """Feed a robot's noisy odometry (private frame) into the graph; returns its keys."""
    odom_from_map = se2.inverse(map_from_odom_true)
    odom_pose = se2.compose(odom_from_map, truth_map[0])
    keys = [graph.add_pose(robot, odom_from_base=odom_pose, time_s=t0)]
    for k in range(1, len(truth_map)):
        step = se2.between(truth_map[k - 1], truth_map[k]) + noise * rng.normal(
            0, [0.02, 0.02, 0.01]
        )
        odom_pose = se2.compose(odom_pose, step)
        keys.append(
            graph.add_pose(
                robot, odom_from_base=odom_pose, time_s=t0 + k, odometry_covariance=ODO_COV
            )
        )
    return keys


def angle_diff(a: float, b: float) -> float:
    return abs(float(se2.wrap_angle(a - b)))


def test_two_robots_unknown_start_merge_on_one_constraint() -> None:
    rng = np.random.default_rng(1)
    graph = PoseGraph(PoseGraphConfig(map_robot_id=0, map_from_odom=(0.0, 0.0, 0.0)))
    truth0 = trajectory(rng, 30, np.zeros(3))
    truth1 = trajectory(rng, 30, np.array([4.0, -3.0, 2.5]))
    true_mfo1 = np.array([-7.0, 12.0, -2.0])  # robot 1's private frame, unknown to the GCS
    keys0 = drive(graph, 0, truth0, np.zeros(3), rng, noise=0.1)
    keys1 = drive(graph, 1, truth1, true_mfo1, rng, noise=0.1)
    assert len(set(graph.components().values())) == 2
    summary = graph.optimize()
    assert summary.components == 2
    # Before the link robot 1 floats: its guess of map_from_odom is the identity.
    np.testing.assert_allclose(graph.map_from_odom(1), np.zeros(3), atol=1e-6)

    # One fiducial observation: robot 0 at pose 20 sees robot 1 at pose 25.
    z = se2.between(truth0[20], truth1[25]) + rng.normal(0, [0.002, 0.002, 0.001])
    graph.add_edge(
        keys0[20],
        keys1[25],
        a_from_b=z,
        covariance=FID_COV,
        provenance=Provenance.FIDUCIAL,
        time_s=31.0,
    )
    assert len(set(graph.components().values())) == 1
    # The rigid merge already puts robot 1 near the truth, before optimizing.
    assert np.linalg.norm(graph.map_from_odom(1)[:2] - true_mfo1[:2]) < 0.3
    graph.optimize()
    mfo1 = graph.map_from_odom(1)
    assert np.linalg.norm(mfo1[:2] - true_mfo1[:2]) < 0.3
    assert angle_diff(mfo1[2], true_mfo1[2]) < 0.01
    np.testing.assert_allclose(graph.map_from_odom(0), 0.0, atol=1e-3)
    _, est1 = graph.poses(1)
    assert np.linalg.norm(est1[:, :2] - truth1[:, :2], axis=1).max() < 0.3
    # The merged graph has a single anchor (the map robot's); no weak anchor remains.
    assert graph.anchored_components() == set(graph.components().values())


def test_map_anchor_by_configuration() -> None:
    cfg = PoseGraphConfig(map_robot_id=3, map_from_odom=(10.0, -5.0, 0.5))
    graph = PoseGraph(cfg)
    graph.add_pose(3, odom_from_base=(1.0, 0.0, 0.0), time_s=0.0)
    graph.add_pose(3, odom_from_base=(2.0, 0.0, 0.0), time_s=1.0, odometry_covariance=ODO_COV)
    graph.optimize()
    np.testing.assert_allclose(graph.map_from_odom(3), [10.0, -5.0, 0.5], atol=1e-6)
    np.testing.assert_allclose(
        graph.pose(pose_key(3, 0)),
        se2.compose(np.array([10, -5, 0.5]), np.array([1.0, 0, 0])),
        atol=1e-6,
    )


def _looped_graph(rng: np.random.Generator) -> tuple[PoseGraph, list[int], np.ndarray]:
    graph = PoseGraph()
    truth = trajectory(rng, 40, np.zeros(3))
    keys = drive(graph, 0, truth, np.zeros(3), rng)
    for a, b in [(0, 30), (5, 35), (10, 39)]:
        z = se2.between(truth[a], truth[b]) + rng.normal(0, [0.05, 0.05, 0.01])
        graph.add_edge(
            keys[a],
            keys[b],
            a_from_b=z,
            covariance=LOOP_COV,
            provenance=Provenance.LOOP_AUTO,
            time_s=50.0,
        )
    return graph, keys, truth


def test_rewind_restores_previous_solution() -> None:
    rng = np.random.default_rng(2)
    graph, keys, truth = _looped_graph(rng)
    graph.optimize()
    _, before = graph.poses(0)
    # Two wrong automatic loop closures arrive later and distort the map.
    for a, b in [(3, 25), (8, 33)]:
        graph.add_edge(
            keys[a],
            keys[b],
            a_from_b=(0.0, 0.0, 0.0),
            covariance=LOOP_COV,
            provenance=Provenance.LOOP_AUTO,
            time_s=100.0,
        )
    operator = graph.add_edge(
        keys[1],
        keys[2],
        a_from_b=se2.between(truth[1], truth[2]),
        covariance=LOOP_COV,
        provenance=Provenance.LOOP_OPERATOR,
        time_s=101.0,
    )
    graph.optimize()
    _, distorted = graph.poses(0)
    assert np.abs(distorted[:, :2] - before[:, :2]).max() > 1.0
    assert len(graph.edges(Provenance.LOOP_AUTO)) == 5
    removed = graph.rewind(60.0)
    assert [e.time_s for e in removed] == [100.0, 100.0]
    assert all(e.provenance is Provenance.LOOP_AUTO for e in removed)
    assert operator in {e.edge_id for e in graph.edges(Provenance.LOOP_OPERATOR)}
    graph.remove_edges([operator])
    graph.optimize()
    _, after = graph.poses(0)
    assert np.abs(after - before).max() < 1e-4


def test_snapshot_restore_is_exact() -> None:
    rng = np.random.default_rng(3)
    graph, keys, _ = _looped_graph(rng)
    graph.optimize()
    snap = graph.snapshot()
    edges_before = [e.edge_id for e in graph.edges()]
    _, before = graph.poses(0)
    graph.add_pose(0, odom_from_base=(100.0, 0.0, 0.0), time_s=99.0, odometry_covariance=ODO_COV)
    graph.add_edge(
        keys[0],
        keys[20],
        a_from_b=(1.0, 1.0, 0.0),
        covariance=LOOP_COV,
        provenance=Provenance.LOOP_AUTO,
        time_s=99.0,
    )
    graph.optimize()
    graph.restore(snap)
    assert [e.edge_id for e in graph.edges()] == edges_before
    _, restored = graph.poses(0)
    np.testing.assert_array_equal(restored, before)
    assert graph.last_key(0) == keys[-1]
    # New edge ids never reuse ids handed out before the restore.
    new = graph.add_edge(
        keys[0],
        keys[20],
        a_from_b=(1.0, 1.0, 0.0),
        covariance=LOOP_COV,
        provenance=Provenance.LOOP_AUTO,
        time_s=99.0,
    )
    assert new > max(edges_before) + 1


def test_edges_by_provenance_and_time() -> None:
    rng = np.random.default_rng(4)
    graph, _, _ = _looped_graph(rng)
    assert len(graph.edges(Provenance.ODOMETRY)) == 39
    assert len(graph.edges((Provenance.LOOP_AUTO, Provenance.FIDUCIAL))) == 3
    assert len(graph.edges(after_time_s=38.5)) == 4
    assert all(e.time_s > 38.5 for e in graph.edges(after_time_s=38.5))


def test_prior_anchors_and_moves_a_floating_robot() -> None:
    graph = PoseGraph()
    graph.add_pose(0, odom_from_base=(0.0, 0.0, 0.0), time_s=0.0)
    k = graph.add_pose(5, odom_from_base=(0.0, 0.0, 0.0), time_s=0.0)
    graph.add_pose(5, odom_from_base=(1.0, 0.0, 0.0), time_s=1.0, odometry_covariance=ODO_COV)
    graph.add_prior(k, map_from_base=(3.0, 4.0, np.pi / 2), covariance=FID_COV, time_s=2.0)
    graph.optimize()
    np.testing.assert_allclose(graph.map_from_odom(5), [3.0, 4.0, np.pi / 2], atol=1e-6)
    assert graph.edges(Provenance.PRIOR)[0].key_b is None


def test_bad_input_is_named() -> None:
    graph = PoseGraph()
    k0 = graph.add_pose(0, odom_from_base=(0.0, 0.0, 0.0), time_s=0.0)
    k1 = graph.add_pose(0, odom_from_base=(1.0, 0.0, 0.0), time_s=1.0, odometry_covariance=ODO_COV)
    with pytest.raises(PoseGraphError, match="unknown robot 7"):
        graph.map_from_odom(7)
    with pytest.raises(PoseGraphError, match=r"unknown pose \(robot 7, index 3\)"):
        graph.add_edge(
            k0,
            pose_key(7, 3),
            a_from_b=(0, 0, 0),
            covariance=FID_COV,
            provenance=Provenance.FIDUCIAL,
            time_s=2.0,
        )
    with pytest.raises(PoseGraphError, match="non-finite"):
        graph.add_edge(
            k0,
            k1,
            a_from_b=(np.nan, 0, 0),
            covariance=FID_COV,
            provenance=Provenance.FIDUCIAL,
            time_s=2.0,
        )
    with pytest.raises(PoseGraphError, match="singular"):
        graph.add_edge(
            k0,
            k1,
            a_from_b=(1, 0, 0),
            covariance=np.diag([1.0, 1.0, 0.0]),
            provenance=Provenance.FIDUCIAL,
            time_s=2.0,
        )
    with pytest.raises(PoseGraphError, match="odometry covariance missing"):
        graph.add_pose(0, odom_from_base=(2.0, 0.0, 0.0), time_s=2.0)
    with pytest.raises(PoseGraphError, match="odometry and cannot be removed"):
        graph.remove_edges([0])
    # Nothing accepted was lost by the failures.
    assert len(graph.edges()) == 1 and graph.last_key(0) == k1


def test_config_from_yaml() -> None:
    cfg = load_config_text("map_robot_id: 2\nordering: emd\nmethod: gn\n", PoseGraphConfig)
    assert cfg.map_robot_id == 2 and cfg.ordering == "emd"
    with pytest.raises(ConfigError, match="unknown key"):
        load_config_text("alpha: 1\n", PoseGraphConfig)
    with pytest.raises(ConfigError, match="ordering"):
        load_config_text("ordering: amd\n", PoseGraphConfig)


def test_incremental_isam2_matches_batch() -> None:
    rng = np.random.default_rng(6)
    truth0 = trajectory(rng, 25, np.zeros(3))
    truth1 = trajectory(rng, 25, np.array([2.0, 3.0, 1.0]))
    true_mfo1 = np.array([5.0, -4.0, 1.5])
    graph = PoseGraph()
    odo0 = truth0[0].copy()
    odo1 = se2.compose(se2.inverse(true_mfo1), truth1[0])
    k0 = [graph.add_pose(0, odom_from_base=odo0, time_s=0.0)]
    k1 = [graph.add_pose(1, odom_from_base=odo1, time_s=0.0)]
    graph.optimize_incremental()
    for k in range(1, 25):
        for robot, truth, keys in ((0, truth0, k0), (1, truth1, k1)):
            step = se2.between(truth[k - 1], truth[k]) + rng.normal(0, [0.02, 0.02, 0.01])
            odo = se2.compose(graph.nodes(robot)[-1].odom_from_base, step)
            keys.append(
                graph.add_pose(robot, odom_from_base=odo, time_s=k, odometry_covariance=ODO_COV)
            )
        if k == 12:
            z = se2.between(truth0[12], truth1[12])
            graph.add_edge(
                k0[12],
                k1[12],
                a_from_b=z,
                covariance=FID_COV,
                provenance=Provenance.FIDUCIAL,
                time_s=k,
            )
        if k == 20:
            z = se2.between(truth0[2], truth0[20]) + rng.normal(0, [0.05, 0.05, 0.01])
            graph.add_edge(
                k0[2],
                k0[20],
                a_from_b=z,
                covariance=LOOP_COV,
                provenance=Provenance.LOOP_AUTO,
                time_s=k,
            )
        graph.optimize_incremental()
    incremental = np.concatenate([graph.poses(0)[1], graph.poses(1)[1]])
    assert np.linalg.norm(graph.map_from_odom(1)[:2] - true_mfo1[:2]) < 0.5
    graph.optimize()
    batch = np.concatenate([graph.poses(0)[1], graph.poses(1)[1]])
    assert np.abs(incremental[:, :2] - batch[:, :2]).max() < 0.02


def test_from_g2o_reaches_optimum_and_exports(posegraph_dir: Path, tmp_path: Path) -> None:
    g = read_g2o(posegraph_dir / "manhattan_olson3500.g2o")
    graph = PoseGraph.from_g2o(g, config=PoseGraphConfig(method="gn", ordering="emd"))
    assert len(graph.edges(Provenance.ODOMETRY)) == 3499
    assert len(graph.edges()) == len(g.edge_ij)
    graph.optimize()
    out = graph.to_g2o()
    assert out.chi2(dict(zip(out.vertex_ids.tolist(), out.vertex_poses, strict=True))) + (
        g.chi2_offset
    ) == pytest.approx(146.08, rel=1e-3)
    write_g2o(tmp_path / "m.g2o", out)
    back = read_g2o(tmp_path / "m.g2o")
    assert len(back.edge_ij) == len(out.edge_ij)


def test_from_g2o_bridges_a_gap_in_the_odometry_chain(posegraph_dir: Path) -> None:
    """A chain with a gap starts from the spanning tree and keeps the file's optimum."""
    g = read_g2o(posegraph_dir / "intel.g2o")
    keep = ~np.all(np.sort(g.edge_ij, axis=1) == [700, 701], axis=1)
    assert keep.sum() == len(keep) - 1
    gap = G2oGraph(
        vertex_ids=g.vertex_ids,
        vertex_poses=g.vertex_poses,
        edge_ij=g.edge_ij[keep],
        edge_z=g.edge_z[keep],
        edge_info=g.edge_info[keep],
        chi2_offset=g.chi2_offset,
    )
    graph = PoseGraph.from_g2o(gap)
    assert len(graph.edges(Provenance.ODOMETRY)) == g.vertex_ids.size - 1
    graph.optimize()
    out = graph.to_g2o()
    poses = dict(zip(out.vertex_ids.tolist(), out.vertex_poses, strict=True))
    # the file's own optimum without the removed edge: at most the full graph's 45.004
    assert gap.chi2(poses) + gap.chi2_offset == pytest.approx(45.0, abs=0.5)


def test_simplify_keeps_solution_and_drops_edges() -> None:
    rng = np.random.default_rng(8)
    graph, keys, truth = _looped_graph(rng)
    for a, b in [(1, 31), (0, 30), (2, 32), (11, 39)]:  # near-duplicates and a repeat
        z = se2.between(truth[a], truth[b]) + rng.normal(0, [0.05, 0.05, 0.01])
        graph.add_edge(
            keys[a],
            keys[b],
            a_from_b=z,
            covariance=LOOP_COV,
            provenance=Provenance.LOOP_AUTO,
            time_s=60.0,
        )
    graph.optimize()
    _, before = graph.poses(0)
    n_before = len(graph.edges())
    removed = graph.simplify(alpha=5.0)
    assert removed and len(graph.edges()) == n_before - len(removed)
    assert len(graph.edges(Provenance.ODOMETRY)) == 39
    summary = graph.optimize()
    _, after = graph.poses(0)
    assert np.abs(after - before).max() < 1e-6
    assert summary.chi2 < 1e-8


def test_spanning_tree_initialization_and_projection() -> None:
    rng = np.random.default_rng(9)
    graph, keys, _ = _looped_graph(rng)
    graph.optimize()
    _, optimum = graph.poses(0)
    # Scramble the estimate, re-initialize from the map anchor's tree, solve again.
    scrambled = gtsam.Values()
    for k in keys:
        noise = rng.normal(0, [3.0, 3.0, 1.0]) if k != keys[0] else np.zeros(3)
        scrambled.insert(k, se2.pose2(graph.pose(k) + noise))
    graph.set_estimate(scrambled)
    graph.initialize_from_spanning_trees()
    _, init = graph.poses(0)
    assert np.abs(init[:, :2] - optimum[:, :2]).max() < 2.0
    graph.optimize()
    _, again = graph.poses(0)
    assert np.abs(again - optimum).max() < 1e-5
    pkeys, proj = graph.projection(keys[0])
    cov_exact = graph.marginal_covariance(keys[25])
    row = int(np.searchsorted(pkeys, keys[25]))
    assert np.trace(proj.covariances[row]) >= np.trace(cov_exact) * 0.999


def _partition(labels: dict[int, int]) -> set[frozenset[int]]:
    groups: dict[int, set[int]] = {}
    for k, c in labels.items():
        groups.setdefault(c, set()).add(k)
    return {frozenset(g) for g in groups.values()}


def test_component_tracking_matches_recomputation() -> None:
    rng = np.random.default_rng(10)
    graph = PoseGraph()
    keys: list[int] = []
    for step in range(120):
        robot = int(rng.integers(0, 4))
        if robot in graph.robots:
            odo = se2.compose(graph.nodes(robot)[-1].odom_from_base, np.array([1.0, 0.0, 0.1]))
            keys.append(
                graph.add_pose(robot, odom_from_base=odo, time_s=step, odometry_covariance=ODO_COV)
            )
        else:
            keys.append(graph.add_pose(robot, odom_from_base=(0.0, 0.0, 0.0), time_s=step))
        graph.components()  # keep the cache alive so additions update it incrementally
        if step % 17 == 16:
            a, b = (int(k) for k in rng.choice(keys, 2, replace=False))
            graph.add_edge(
                a,
                b,
                a_from_b=(1.0, 0.0, 0.0),
                covariance=FID_COV,
                provenance=Provenance.FIDUCIAL,
                time_s=step,
            )
        tracked = _partition(graph.components())
        graph._components = None
        assert tracked == _partition(graph.components())


def test_rewind_that_splits_components_restores_weak_anchor() -> None:
    rng = np.random.default_rng(12)
    graph = PoseGraph()
    truth0 = trajectory(rng, 10, np.zeros(3))
    truth1 = trajectory(rng, 10, np.array([3.0, 3.0, 0.5]))
    keys0 = drive(graph, 0, truth0, np.zeros(3), rng)
    keys1 = drive(graph, 1, truth1, np.array([1.0, 2.0, 0.3]), rng)
    graph.add_edge(
        keys0[5],
        keys1[5],
        a_from_b=se2.between(truth0[5], truth1[5]),
        covariance=LOOP_COV,
        provenance=Provenance.LOOP_AUTO,
        time_s=20.0,
    )
    graph.optimize()
    assert len(set(graph.components().values())) == 1
    linked = graph.map_from_odom(1)
    graph.rewind(15.0)
    assert len(set(graph.components().values())) == 2
    fg, _ = graph.factor_graph()
    assert fg.size() == len(graph.edges()) + 2  # map anchor + robot 1's weak anchor
    graph.optimize()
    np.testing.assert_allclose(graph.map_from_odom(1), linked, atol=1e-6)
    graph.optimize_incremental()
    np.testing.assert_allclose(graph.map_from_odom(1), linked, atol=1e-6)


# ---- solver faults (issue 19) ----------------------------------------------------------------


def _two_linked_robots(rng: np.random.Generator) -> tuple[PoseGraph, list[int], list[int]]:
    g = PoseGraph()
    truth0 = trajectory(rng, 30, np.zeros(3))
    truth1 = trajectory(rng, 30, np.array([3.0, 4.0, 1.0]))
    k0 = drive(g, 0, truth0, np.zeros(3), rng)
    k1 = drive(g, 1, truth1, np.array([3.0, 4.0, 1.0]), rng)
    g.add_edge(k0[10], k1[12], a_from_b=se2.between(truth0[10], truth1[12]), covariance=FID_COV,
               provenance=Provenance.FIDUCIAL, time_s=12.0)  # fmt: skip
    g.add_edge(k0[20], k0[3], a_from_b=se2.between(truth0[20], truth0[3]), covariance=LOOP_COV,
               provenance=Provenance.LOOP_AUTO, time_s=20.0)  # fmt: skip
    return g, k0, k1


def test_an_isam2_fault_is_recovered_by_a_batch_solve_and_a_fresh_isam2() -> None:
    rng = np.random.default_rng(4)
    clean, _, _ = _two_linked_robots(rng)
    assert clean.optimize_incremental() is None
    faulty, _, _ = _two_linked_robots(np.random.default_rng(4))
    assert faulty.optimize_incremental() is None
    for kind in ("indeterminate", "nan"):
        faulty.inject_solver_fault(kind)  # type: ignore[arg-type]
        for g in (clean, faulty):
            g.add_pose(0, odom_from_base=(40.0, 1.0, 0.2), time_s=40.0, odometry_covariance=ODO_COV)
        assert clean.optimize_incremental() is None
        fault = faulty.optimize_incremental()
        assert fault is not None and fault.recovered
        assert fault.error.startswith("RuntimeError: Indeterminate linear system")
        assert "batch re-solved" in fault.action and "fresh iSAM2 seeded" in fault.action
        # the recovered estimate is the batch optimum of the same graph; iSAM2's (one
        # relinearization per update) is close to it
        batch = clean.copy()
        batch.optimize()
        for r in (0, 1):
            np.testing.assert_allclose(faulty.poses(r)[1], batch.poses(r)[1], atol=1e-6)
            np.testing.assert_allclose(faulty.poses(r)[1], clean.poses(r)[1], atol=0.05)
    # a fault in the re-seeding iSAM2 too: the batch estimate stands, iSAM2 is retried later
    faulty.inject_solver_fault("indeterminate", count=2)
    faulty.add_pose(1, odom_from_base=(9.0, 9.0, 0.0), time_s=41.0, odometry_covariance=ODO_COV)
    fault = faulty.optimize_incremental()
    assert fault is not None and fault.recovered and "re-seeding iSAM2 failed" in fault.action
    assert faulty.optimize_incremental() is None
    with pytest.raises(ValueError, match="unknown kind"):
        faulty.inject_solver_fault("boom")  # type: ignore[arg-type]


def test_when_the_batch_solve_fails_too_the_last_good_estimate_is_kept() -> None:
    g, k0, _ = _two_linked_robots(np.random.default_rng(5))
    assert g.optimize_incremental() is None
    good = {r: g.poses(r)[1].copy() for r in (0, 1)}
    # an edge whose measurement is NaN (only restore() can put one in: add_edge refuses it)
    snap = g.snapshot()
    bad = EdgeRecord(snap.next_edge_id, k0[5], k0[25], np.array([np.nan, 0.0, 0.0]), LOOP_COV,
                     Provenance.LOOP_AUTO, 30.0)  # fmt: skip
    g.restore(PoseGraphSnapshot(snap.nodes, {**snap.edges, bad.edge_id: bad}, snap.estimate,
                                snap.next_edge_id + 1))  # fmt: skip
    for _ in range(2):  # every later solve tries again, and fails the same way
        fault = g.optimize_incremental()
        assert fault is not None and not fault.recovered
        assert "kept the last good estimate" in fault.action
        for r in (0, 1):
            np.testing.assert_array_equal(g.poses(r)[1], good[r])
    g.remove_edges([bad.edge_id])  # the operator removes it: solving works again
    assert g.optimize_incremental() is None


def test_add_edge_refuses_non_positive_definite_and_numerically_singular_covariances() -> None:
    g, k0, k1 = _two_linked_robots(np.random.default_rng(6))
    for cov, why in (
        (np.diag([1e-4, 1e-4, -1e-6]), "not positive definite"),
        (np.diag([1e-4, 1e-4, 0.0]), "not positive definite"),
        (np.diag([1.0, 1.0, 1e-14]), "condition limit"),
        (np.array([[1e-2, 1e-2, 0], [1e-2, 1e-2, 0], [0, 0, 1e-4]]), "not positive definite"),
    ):
        with pytest.raises(PoseGraphError, match="singular or not positive definite") as info:
            g.add_edge(k0[2], k1[2], a_from_b=(1.0, 0.0, 0.0), covariance=cov,
                       provenance=Provenance.LOOP_OPERATOR, time_s=1.0)  # fmt: skip
        assert why in str(info.value) or why == "not positive definite"


def test_a_real_indeterminate_system_from_a_near_singular_joining_edge_is_recovered() -> None:
    """GTSAM's own fault, no injection: an edge of condition 1e8 (allowed here, refused from
    robots at the GCS's door) is the only link between two robots; iSAM2 (incremental and
    fresh alike) raises "Indeterminate linear system", the batch solve does not."""
    g = PoseGraph()
    for r in (0, 1):
        for i in range(10):
            g.add_pose(r, odom_from_base=(0.5 * i, 0.0, 0.0), time_s=float(i),
                       odometry_covariance=ODO_COV if i else None)  # fmt: skip
    assert g.optimize_incremental() is None
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    near_singular = rot @ np.diag([1e-4, 1e-12, 1e-6]) @ rot.T
    g.add_edge(g.last_key(0), pose_key(1, 4), a_from_b=(1.0, 0.0, 0.0), covariance=near_singular,
               provenance=Provenance.FIDUCIAL, time_s=10.0)  # fmt: skip
    fault = g.optimize_incremental()
    assert fault is not None and fault.recovered
    assert fault.error.startswith("RuntimeError: Indeterminate linear system detected")
    n_edges = len(g.edges())
    for i in range(10, 13):  # the mission goes on: every node and edge kept, estimate finite
        g.add_pose(1, odom_from_base=(0.5 * i, 0.0, 0.0), time_s=float(i),
                   odometry_covariance=ODO_COV)  # fmt: skip
        g.optimize_incremental()
        assert len(g.edges()) == n_edges + i - 9
    _, p1 = g.poses(1)
    assert np.all(np.isfinite(p1))
    # the edge holds: robot 1's node 4 sits 1 m ahead of robot 0's last node
    np.testing.assert_allclose(se2.between(g.pose(g.last_key(0)), g.pose(pose_key(1, 4))),
                               (1.0, 0.0, 0.0), atol=1e-6)  # fmt: skip
