"""The GCS core: pose nodes into the graph, grids by header, frames out, bad input counted."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from compression import encode_grid, origin_cells_of
from gcs.graph.pose_graph import Provenance
from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.loops.correlative_matcher import MatchResult
from protocol.messages import (
    Detection,
    FiducialObservation,
    HazardUpdate,
    ObjectKind,
    PoseNode,
    TerrainGrid,
    covariance_to_upper,
)
from protocol.se2 import compose, relative

COV = covariance_to_upper(np.diag([0.01**2, 0.01**2, 0.002**2]))


def nodes_along(
    path_in_odom: np.ndarray, t0: float = 0.0, cov_upper: tuple[float, ...] = COV
) -> list[PoseNode]:
    out = []
    for i, pose in enumerate(path_in_odom):
        delta = (0.0, 0.0, 0.0) if i == 0 else tuple(relative(path_in_odom[i - 1], pose))
        cov = (0.0,) * 6 if i == 0 else cov_upper
        out.append(PoseNode(i, t0 + i, tuple(pose), delta, cov))  # type: ignore[arg-type]
    return out


def straight(n: int, heading: float = 0.0) -> np.ndarray:
    s = np.arange(n) * 0.5
    return np.stack([s * np.cos(heading), s * np.sin(heading), np.full(n, heading)], axis=1)


def grid_msg(index: int, grid: np.ndarray, *, res: float = 0.1) -> TerrainGrid:
    h, w = grid.shape
    return TerrainGrid(index, res, encode_grid(grid, origin_cells=(-(w // 2), -(h // 2))))


def test_map_robot_gets_its_frame_and_others_wait_until_linked() -> None:
    gs = GroundStation(GroundStationConfig(robots=(0, 1)))
    for msg in nodes_along(straight(6)):
        assert gs.handle(0, msg, now_s=0.0)
    path1 = straight(6, heading=0.3)
    for msg in nodes_along(path1):
        assert gs.handle(1, msg, now_s=0.0)
    out = gs.step(now_s=10.0)
    assert {rid for rid, _ in out} == {0, 1}
    update = out[0][1]
    assert isinstance(update, HazardUpdate)
    assert [f.robot_id for f in update.frames] == [0]  # robot 1 is not linked to map yet
    np.testing.assert_allclose(update.frames[0].map_from_odom, (0, 0, 0), atol=1e-6)

    # Robot 1 truly starts at (3, 2, 0.5) in map: its node 2 sees robot 0's node 4 via a tag.
    map_from_odom1 = np.array([3.0, 2.0, 0.5])
    map_from_base1 = compose(map_from_odom1, path1[2])
    map_from_base0 = straight(6)[4]
    seen = relative(map_from_base1, map_from_base0)
    tag = FiducialObservation(2, 4.0, 0, 7, tuple(seen), COV)  # type: ignore[arg-type]
    assert gs.handle(1, tag, now_s=11.0)
    assert gs.step(now_s=11.0) == []  # frames are periodic
    out = gs.step(now_s=12.0)
    frames = {f.robot_id: np.array(f.map_from_odom) for f in out[0][1].frames}
    assert set(frames) == {0, 1}
    np.testing.assert_allclose(frames[1], map_from_odom1, atol=1e-4)
    assert gs.stats.fiducials == 1


def test_out_of_order_nodes_wait_duplicates_count_and_a_lasting_gap_is_bridged() -> None:
    gs = GroundStation(GroundStationConfig(max_pending_nodes=3))
    msgs = nodes_along(straight(12))
    for i in (0, 2, 1, 1, 3):
        gs.handle(0, msgs[i], now_s=0.0)
    assert gs.stats.pose_nodes == 4 and gs.stats.duplicates == 1
    for i in (5, 6, 7, 8):  # node 4 is lost for good
        gs.handle(0, msgs[i], now_s=0.0)
    assert gs.stats.gaps_bridged == 1 and gs.stats.pose_nodes == 8
    gs.step(now_s=1.0)
    keys, poses = gs.graph.poses(0)
    np.testing.assert_allclose(poses[-1], straight(12)[8], atol=1e-6)
    assert gs.key_of(0, 8) == keys[-1] and gs.key_of(0, 4) is None


def test_grids_are_decoded_by_header_and_wait_for_their_pose_node() -> None:
    gs = GroundStation()
    rng = np.random.default_rng(3)
    grid = rng.random((40, 60)) < 0.1
    msgs = nodes_along(straight(3))
    gs.handle(0, msgs[0], now_s=0.0)
    assert gs.handle(0, grid_msg(1, grid), now_s=0.0)  # before its node: held
    assert gs.stats.terrain_grids == 0
    gs.handle(0, msgs[1], now_s=0.0)
    key = gs.key_of(0, 1)
    assert key is not None and gs.stats.terrain_grids == 1
    np.testing.assert_array_equal(gs.grids[key].grid, grid)
    assert gs.grids[key].origin_in_base == pytest.approx((-3.0, -2.0))


def test_bad_input_is_rejected_counted_and_the_station_keeps_going() -> None:
    gs = GroundStation(GroundStationConfig(robots=(0,)))
    msgs = nodes_along(straight(4))
    gs.handle(0, msgs[0], now_s=0.0)
    gs.handle(0, msgs[1], now_s=0.0)
    grid = np.zeros((10, 10), dtype=bool)
    grid[3, 4] = True
    good = grid_msg(1, grid)
    cases = {
        "unknown_robot": (5, msgs[0]),
        "bad_grid": (0, TerrainGrid(1, 0.1, good.data[:-3])),
    }
    for reason, (rid, msg) in cases.items():
        assert not gs.handle(rid, msg, now_s=0.0)
        assert gs.stats.rejected[reason] == 1, reason
    # a stream that is no grid, a silly resolution, a NaN pose
    assert not gs.handle(0, TerrainGrid(1, 0.1, b"\xfe\x00"), now_s=0)
    assert not gs.handle(0, TerrainGrid(1, 50.0, good.data), now_s=0)
    nan = PoseNode(2, 2.0, (float("nan"), 0.0, 0.0), (0.5, 0.0, 0.0), COV)
    assert not gs.handle(0, nan, now_s=0.0)
    assert gs.stats.rejected["bad_grid"] == 3 and gs.stats.rejected["non_finite"] == 1
    assert "unknown codec id 254" in "\n".join(gs.stats.errors)
    assert not gs.handle(0, "hello", now_s=0.0)
    # ... and still accepts good input
    assert gs.handle(0, good, now_s=0.0) and gs.handle(0, msgs[2], now_s=0.0)
    assert gs.stats.terrain_grids == 1 and gs.stats.pose_nodes == 3


def test_dangerous_detections_become_hazards_in_map() -> None:
    gs = GroundStation()
    path = straight(3, heading=np.pi / 2)
    for msg in nodes_along(path):
        gs.handle(0, msg, now_s=0.0)
    for det_id, offset in ((1, 0.0), (2, 0.3)):  # the same bomb seen twice
        det = Detection(
            det_id, 2, 2.0, ObjectKind.STATIC_OOI, (4.0 + offset, 0.0), (0.1, 0, 0.1), 0.3, 0.5, 0.9
        )
        assert gs.handle(0, det, now_s=0.0)
    civilian = Detection(3, 2, 2.0, ObjectKind.CIVILIAN, (1.0, 1.0), (0.1, 0, 0.1), 0.3, 1.7, 0.9)
    gs.handle(0, civilian, now_s=0.0)
    (update,) = [m for _, m in gs.step(now_s=5.0)]
    assert len(update.hazards) == 1
    h = update.hazards[0]
    np.testing.assert_allclose(h.position_in_map, (0.0, 1.0 + 4.15), atol=1e-5)  # the mean
    assert h.radius_m == 2.5
    assert gs.stats.detections == 3


def test_a_static_hazard_follows_the_pose_it_was_seen_from() -> None:
    # placed from node 2's estimate; a closure then moves node 2: the hazard moves with it (as
    # the map does), so sightings from robots whose poses a closure corrected agree again
    gs = GroundStation()
    for msg in nodes_along(straight(3)):
        gs.handle(0, msg, now_s=0.0)
    det = Detection(1, 2, 2.0, ObjectKind.STATIC_OOI, (3.0, 0.0), (0.1, 0, 0.1), 0.3, 0.5, 0.9)
    assert gs.handle(0, det, now_s=0.0)
    gs.step(now_s=1.0)
    k0, k2 = gs.key_of(0, 0), gs.key_of(0, 2)
    assert k0 is not None and k2 is not None
    before = np.asarray(gs.hazards[0].position_in_map)
    a_from_b = np.asarray(relative(gs.graph.pose(k0), gs.graph.pose(k2))) + (0.0, 1.0, 0.0)
    tight = np.diag([1e-4, 1e-4, 1e-6])
    result = MatchResult(a_from_b, a_from_b, tight, 100, 0.9, 1)
    gs.accept_closure(k0, k2, result, now_s=1.0)
    gs.step(now_s=2.0)
    moved = np.asarray(gs.graph.pose(k2))
    expected = compose(moved, np.array([3.0, 0.0, 0.0]))[:2]
    assert np.linalg.norm(expected - before) > 0.2  # the closure moved node 2
    np.testing.assert_allclose(gs.hazards[0].position_in_map, expected, atol=1e-6)


def test_the_global_map_is_rasterized_from_the_grids_at_their_posteriors() -> None:
    gs = GroundStation()
    wall = np.zeros((60, 60), dtype=bool)
    wall[:, 50] = True  # a wall 2 m ahead of each node: x in base = -3 + 50.5 * 0.1
    path = straight(5)
    for i, msg in enumerate(nodes_along(path)):
        gs.handle(0, msg, now_s=0.0)
        gs.handle(0, grid_msg(i, wall), now_s=0.0)
    gs.step(now_s=1.0)
    occupancy = gs.rasterize()
    occupied = np.argwhere(occupancy.values == 100)
    assert len(occupied) > 0
    xs = occupancy.origin_in_map[0] + (occupied[:, 1] + 0.5) * occupancy.resolution_m
    wall_x = path[:, 0] + 2.05
    assert np.all(np.min(np.abs(xs[:, None] - wall_x[None, :]), axis=1) < 0.11)
    assert np.any(occupancy.values == 0) and np.any(occupancy.values == -1)


DRIFT = np.diag([0.02**2, 0.02**2, 0.01**2])


def _out_and_back(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, list[TerrainGrid]]:
    """A robot drives 12 m out and back through a random world: true poses, drifting odometry
    (noise drawn from :data:`DRIFT`) and the grids of what it saw."""
    from gcs.loops.synthetic_scenes import random_world, scan_grid, scan_points

    world = random_world(rng, size_m=40.0)
    out = [(x, 0.5, 0.0) for x in np.arange(-6.0, 6.01, 1.0)]
    back = [(x, -0.5, np.pi) for x in np.arange(6.0, -6.01, -1.0)]
    truth = np.array(out + back)
    odom = [truth[0]]
    for i in range(1, len(truth)):
        step = relative(truth[i - 1], truth[i])
        odom.append(compose(odom[-1], step + rng.multivariate_normal(np.zeros(3), DRIFT)))
    grids = []
    for i, pose in enumerate(truth):
        grid, origin = scan_grid(scan_points(world, pose, rng=rng))
        h, w = grid.shape
        data = encode_grid(grid, origin_cells=origin_cells_of(origin, 0.1))
        grids.append(TerrainGrid(i, 0.1, data))
    return truth, np.array(odom), grids


def test_loops_close_and_the_operator_can_suggest_accept_and_rewind() -> None:
    rng = np.random.default_rng(11)
    truth, odom, grids = _out_and_back(rng)
    gs = GroundStation()
    for i, (node, grid) in enumerate(
        zip(nodes_along(odom, cov_upper=covariance_to_upper(DRIFT)), grids, strict=True)
    ):
        assert gs.handle(0, node, now_s=float(i)) and gs.handle(0, grid, now_s=float(i))
        gs.step(now_s=float(i), budget_s=1.0)
    for t in range(len(truth), len(truth) + 5):
        gs.step(now_s=float(t), budget_s=1.0)
    auto = gs.graph.edges(Provenance.LOOP_AUTO)
    assert len(auto) >= 3
    for e in auto:
        assert e.key_b is not None
        true_rel = relative(truth[e.key_a & 0xFFFFFFFF], truth[e.key_b & 0xFFFFFFFF])
        assert np.hypot(*(e.z[:2] - true_rel[:2])) < 0.15
    _, poses = gs.graph.poses(0)
    drift = np.hypot(*(odom[-1, :2] - truth[-1, :2]))
    assert np.hypot(*(poses[-1, :2] - truth[-1, :2])) < 0.3 * drift

    # the operator asks for a match between the first node and the last, and accepts it
    first, last = gs.key_of(0, 0), gs.key_of(0, len(truth) - 1)
    assert first is not None and last is not None
    result = gs.suggest_closure(first, last)
    np.testing.assert_allclose(result.a_from_b[:2], relative(truth[0], truth[-1])[:2], atol=0.15)
    gs.accept_closure(first, last, result, now_s=100.0)
    assert len(gs.graph.edges(Provenance.LOOP_OPERATOR)) == 1
    # rewinding the automatic closures keeps the operator's
    assert gs.rewind_closures(since_s=-1.0) == len(auto)
    assert gs.graph.edges(Provenance.LOOP_AUTO) == []
    assert len(gs.graph.edges(Provenance.LOOP_OPERATOR)) == 1
    gs.restart_loop_closer()
    gs.step(now_s=200.0, budget_s=1.0)  # optimizes without the rewound edges


def test_a_large_graph_simplifies_itself_after_a_solve_and_the_station_goes_on() -> None:
    """Algorithm 1 by itself (issue 16 item 3; paper 4.7) once the graph passes its size, at a
    known-good state: the estimate is unchanged by it, edges are merged away, and the station
    keeps closing loops, solving and serving frames afterwards."""
    from gcs.graph.pose_graph import AutoSimplifyConfig, PoseGraphConfig

    rng = np.random.default_rng(11)
    truth, odom, grids = _out_and_back(rng)
    auto = AutoSimplifyConfig(min_poses=len(truth), max_edges_per_pose=1.0, min_interval_s=0.0)
    gs = GroundStation(GroundStationConfig(graph=PoseGraphConfig(auto_simplify=auto)))
    nodes = nodes_along(odom, cov_upper=covariance_to_upper(DRIFT))
    for t in range(len(truth) + 20):
        if t < len(truth):
            assert gs.handle(0, nodes[t], now_s=float(t)) and gs.handle(0, grids[t], now_s=float(t))
        gs.step(now_s=float(t), budget_s=1.0)
        if gs.stats.simplifications:
            break
    assert gs.stats.simplifications == 1 and gs.stats.edges_simplified_away > 0
    relative_edges = [e for e in gs.graph.edges() if e.key_b is not None]
    assert len(relative_edges) <= len(truth)  # was above one edge a pose
    # the kept edges are re-expressed at the estimate: it is still the optimum
    after = gs.graph.poses(0)[1].copy()
    gs.graph.optimize()
    np.testing.assert_allclose(gs.graph.poses(0)[1], after, atol=1e-6)
    out = gs.step(now_s=1000.0, budget_s=1.0)
    assert any(isinstance(m, HazardUpdate) for _, m in out)
    assert gs.stats.internal_errors == 0 and gs.stats.loop_closer_faults == 0
    _, poses = gs.graph.poses(0)
    drift = np.hypot(*(odom[-1, :2] - truth[-1, :2]))
    assert np.hypot(*(poses[-1, :2] - truth[-1, :2])) < 0.3 * drift
    # the operator's simplify goes through the station too, and is counted there
    removed = gs.simplify_graph()
    assert gs.stats.simplifications == 1 + bool(removed)


def test_inter_frame_grids_are_decoded_against_the_previous_nodes_grid() -> None:
    from compression import DEFAULT_CODEC, GridReference, is_inter, origin_cells_of
    from gcs.loops.synthetic_scenes import random_world, scan_grid, scan_points

    rng = np.random.default_rng(5)
    truth, odom, _ = _out_and_back(rng)

    world = random_world(np.random.default_rng(6), size_m=40.0)
    nodes = nodes_along(odom[:6])
    grids: list[tuple[np.ndarray, tuple[int, int]]] = []
    msgs: list[TerrainGrid] = []
    for i, pose in enumerate(truth[:6]):
        grid, origin = scan_grid(scan_points(world, pose, rng=rng))
        cells = origin_cells_of(origin, 0.1)
        ref = None
        if i > 0:
            prev_grid, prev_cells = grids[-1]
            ref = GridReference(i - 1, prev_grid, prev_cells, nodes[i].odom_delta, 0.1)
        data = encode_grid(grid, DEFAULT_CODEC, origin_cells=cells, reference=ref)
        grids.append((grid, cells))
        msgs.append(TerrainGrid(i, 0.1, data))
    assert is_inter(DEFAULT_CODEC)

    gs = GroundStation()
    for node in nodes:
        gs.handle(0, node, now_s=0.0)
    for i in (0, 2, 1, 3):  # grid 2 waits for grid 1, its reference
        assert gs.handle(0, msgs[i], now_s=0.0)
    assert gs.stats.terrain_grids == 4
    for i in range(4):
        key = gs.key_of(0, i)
        assert key is not None
        np.testing.assert_array_equal(gs.grids[key].grid, grids[i][0])
    # grid 4 claims a model this build does not have: grid 5, coded against it, is lost too
    data = msgs[4].data
    bad = msgspec.structs.replace(msgs[4], data=data[:1] + bytes([99]) + data[2:])
    assert not gs.handle(0, bad, now_s=0.0)
    assert not gs.handle(0, msgs[5], now_s=0.0)
    assert gs.stats.rejected["missing_reference"] == 1


# ---- robustness: solver faults, non-physical covariances, clocks (issue 19) -----------------


def _two_robots_with_a_tag(gs: GroundStation, *, fault_at: dict[int, str] | None = None) -> None:
    """Robot 0 (map) and robot 1 drive 20 nodes each; robot 1's node 8 sees robot 0's node 8.
    Steps after every pair of nodes; ``fault_at[i]`` injects a solver fault before step ``i``."""
    path0, path1 = straight(20), straight(20, heading=0.4)
    map_from_odom1 = np.array([2.0, -1.0, 0.3])
    msgs0, msgs1 = nodes_along(path0), nodes_along(path1)
    seen = relative(compose(map_from_odom1, path1[8]), path0[8])
    for i in range(20):
        assert gs.handle(0, msgs0[i], now_s=float(i))
        assert gs.handle(1, msgs1[i], now_s=float(i))
        if i == 8:
            tag = FiducialObservation(8, 8.0, 0, 7, tuple(seen), COV)  # type: ignore[arg-type]
            assert gs.handle(1, tag, now_s=float(i))
        if fault_at and i in fault_at:
            gs.graph.inject_solver_fault(fault_at[i])  # type: ignore[arg-type]
        gs.step(now_s=float(i))


def test_a_solver_fault_mid_run_is_recovered_and_the_estimate_is_unchanged() -> None:
    clean = GroundStation()
    _two_robots_with_a_tag(clean)
    faulty = GroundStation()
    _two_robots_with_a_tag(faulty, fault_at={4: "indeterminate", 9: "nan", 15: "indeterminate"})
    s = faulty.stats
    assert s.solver_faults == 3 and s.solver_recoveries == 3
    assert clean.stats.solver_faults == 0
    assert any("Indeterminate linear system" in e for e in s.errors)
    assert s.pose_nodes == 40 and s.fiducials == 1  # nothing accepted was lost
    for r in (0, 1):
        np.testing.assert_allclose(faulty.graph.poses(r)[1], clean.graph.poses(r)[1], atol=1e-6)
    (update,) = {id(m): m for _, m in faulty.step(now_s=30.0)}.values()
    assert isinstance(update, HazardUpdate) and len(update.frames) == 2
    frames = {f.robot_id: np.array(f.map_from_odom) for f in update.frames}
    np.testing.assert_allclose(frames[1], (2.0, -1.0, 0.3), atol=1e-4)
    # the station's iSAM2 is healthy again: later updates are incremental and fault-free
    msg = nodes_along(straight(21))[20]
    assert faulty.handle(0, msg, now_s=31.0)
    faulty.step(now_s=31.0)
    assert s.solver_faults == 3


def test_non_physical_covariances_are_rejected_and_the_chain_is_bridged_at_once() -> None:
    gs = GroundStation(GroundStationConfig(robots=(0,)))
    path = straight(12)
    msgs = nodes_along(path)
    bad = {
        3: (float("nan"), 0.0, 0.0, 1e-4, 0.0, 4e-6),  # NaN
        5: (1e-4, 0.0, 0.0, -1e-4, 0.0, 4e-6),  # not positive definite
        8: (1e-4, 0.0, 0.0, 1e-4, 0.0, 1.7e4),  # a clock jump's yaw variance
        9: (4e8, 0.0, 0.0, 1e-4, 0.0, 4e-6),  # 20 km sigma
    }
    for i, msg in enumerate(msgs):
        if i in bad:
            msg = msgspec.structs.replace(msg, odom_covariance=bad[i])
            assert not gs.handle(0, msg, now_s=0.0)
        else:
            assert gs.handle(0, msg, now_s=0.0)
    s = gs.stats
    assert s.rejected["non_physical_covariance"] == 4 and s.rejected_total == 4
    text = "\n".join(s.errors)
    assert "robot 0 PoseNode: node 8 odom_covariance: yaw variance 1.7e+04 rad^2" in text
    assert "node 5 odom_covariance: not positive definite" in text
    assert "node 3 odom_covariance: non-finite entry" in text
    assert "node 9 odom_covariance: xy sigma 2e+04 m above the 1000 m bound" in text
    # every good node is in the chain at once (no wait for max_pending_nodes), bridged
    assert s.pose_nodes == 8 and s.gaps_bridged == 3
    assert [gs.key_of(0, i) is not None for i in range(12)] == [i not in bad for i in range(12)]
    gs.step(now_s=1.0)
    _, poses = gs.graph.poses(0)
    np.testing.assert_allclose(poses[-1], path[-1], atol=1e-6)
    bound = np.array([1000.0**2, 1000.0**2, (2 * np.pi) ** 2])
    for e in gs.graph.edges(Provenance.ODOMETRY):
        assert np.all(np.diag(e.covariance) <= bound) and np.linalg.eigvalsh(e.covariance)[0] > 0

    # a fiducial and a detection with non-physical covariances are refused the same way
    gs1 = GroundStation()
    for r in (0, 1):
        for msg in nodes_along(straight(3)):
            gs1.handle(r, msg, now_s=0.0)
    tag = FiducialObservation(1, 1.0, 0, 7, (1.0, 0.0, 0.0), (1e-4, 0, 0, 1e-4, 0, 0.0))
    det = Detection(1, 2, 2.0, ObjectKind.STATIC_OOI, (4.0, 0.0), (1e7, 0, 1e7), 0.3, 0.5, 0.9)
    assert not gs1.handle(1, tag, now_s=0.0) and not gs1.handle(0, det, now_s=0.0)
    assert gs1.stats.rejected["non_physical_covariance"] == 2
    assert "fiducial of node 1 covariance" in gs1.stats.errors[0]
    assert "detection 1 position_covariance: xy sigma" in gs1.stats.errors[1]


def test_a_bridge_over_a_rejected_node_stays_within_the_physical_bounds() -> None:
    cfg = GroundStationConfig(max_sigma_xy_m=1.0, max_sigma_yaw_rad=1.0, gap_covariance_scale=4.0)
    gs = GroundStation(cfg)
    near_bound = covariance_to_upper(np.diag([0.9**2, 0.9**2, 0.9**2]))
    msgs = nodes_along(straight(4), cov_upper=near_bound)
    msgs[2] = msgspec.structs.replace(msgs[2], odom_covariance=(float("inf"),) + (0.0,) * 5)
    for msg in msgs:
        gs.handle(0, msg, now_s=0.0)
    bridge = gs.graph.edges(Provenance.ODOMETRY)[-1]
    np.testing.assert_allclose(np.diag(bridge.covariance), [1.0, 1.0, 1.0])  # 4 x 0.81, capped


def test_clock_anomalies_are_reported_once_per_kind_and_times_stay_monotone() -> None:
    gs = GroundStation()
    msgs = nodes_along(straight(16))
    raw = [0.0, 1.0, 2.0, 3.0, 3.0, 3.0, 4.0, 5.0, 4.29e9 + 6, 4.29e9 + 7, 1.5, 2.5, 2.5, 3.5,
           float("nan"), 5.5]  # fmt: skip
    for msg, t in zip(msgs, raw, strict=True):
        assert gs.handle(0, msgspec.structs.replace(msg, time_s=t), now_s=0.0)
    s = gs.stats
    assert s.pose_nodes == 16 and s.rejected_total == 0  # nothing lost
    assert dict(s.clock_anomalies) == {"frozen": 1, "jump": 1, "backwards": 1, "non_finite": 1}
    assert s.clock_substitutions == 6  # 2 frozen, 1 jump, 1 backwards, 1 frozen, 1 NaN
    assert sum("clock" in e for e in s.errors) == 4  # one line per kind
    times = np.array([n.time_s for n in gs.graph.nodes(0)])
    assert np.all(np.diff(times) > 0) and times[-1] < 20.0
    np.testing.assert_allclose(np.diff(times), 1.0)  # plausible steps were all 1 s
    # odometry covariances are the robot's, whatever its clock did
    for e in gs.graph.edges(Provenance.ODOMETRY):
        np.testing.assert_allclose(e.covariance, np.diag([0.01**2, 0.01**2, 0.002**2]), rtol=1e-6)
    gs.step(now_s=1.0)
    # the station's own clock going backwards or jumping is reported once and substituted
    gs.step(now_s=0.5)
    gs.step(now_s=1e10)
    out = gs.step(now_s=1e10 + 3.0)
    assert s.clock_anomalies["backwards"] == 2 and s.clock_anomalies["jump"] == 2
    assert out and out[0][1].time_s == pytest.approx(4.0)


def test_a_near_singular_tag_covariance_is_refused_at_the_door() -> None:
    gs = GroundStation()
    for r in (0, 1):
        for msg in nodes_along(straight(5)):
            gs.handle(r, msg, now_s=0.0)
    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cov = covariance_to_upper(rot @ np.diag([1e-4, 1e-12, 1e-6]) @ rot.T)
    tag = FiducialObservation(4, 4.0, 0, 7, (1.0, 0.0, 0.0), cov)  # type: ignore[arg-type]
    assert not gs.handle(1, tag, now_s=0.0)
    assert "fiducial of node 4 covariance: near singular (condition number" in gs.stats.errors[-1]
    assert "above 1e+06)" in gs.stats.errors[-1]
    gs.step(now_s=1.0)
    assert gs.stats.solver_faults == 0


def test_what_the_allocator_reads_status_heard_time_poses_trajectories_hostiles() -> None:
    from protocol.messages import AutonomyMode, TaskState, TaskStatus, Telemetry

    gs = GroundStation(GroundStationConfig(robots=(0, 1)))
    assert gs.robot_ids == [] and gs.last_heard_s(0) is None and gs.last_status(0) is None
    for k, msg in enumerate(nodes_along(straight(5))):
        assert gs.handle(0, msg, now_s=float(k))
    for msg in nodes_along(straight(3, heading=1.0)):
        gs.handle(1, msg, now_s=2.0)
    status = TaskStatus(7, TaskState.ACTIVE, 4.5)
    gs.handle(0, status, now_s=5.0)
    gs.handle(0, msg, now_s=4.0)  # a late, refused message still says the robot was heard
    assert gs.last_status(0) == status and gs.last_heard_s(0) == 5.0
    assert gs.last_heard_s(1) == 2.0 and gs.robot_ids == [0, 1]
    gs.step(now_s=5.0)
    # robot 0 defines map; robot 1 has no link to it yet
    assert gs.linked(0) and not gs.linked(1) and gs.pose_in_map(1) is None
    np.testing.assert_allclose(gs.pose_in_map(0), straight(5)[-1], atol=1e-6)
    telemetry = Telemetry(
        5.2, (2.3, 0.1, 0.05), (0.3, 0.0), (0.0, 0.0), 0.9, AutonomyMode.AUTONOMOUS, 7
    )
    gs.handle(0, telemetry, now_s=5.2)
    np.testing.assert_allclose(gs.pose_in_map(0), (2.3, 0.1, 0.05), atol=1e-5)
    assert gs.telemetry(0) == telemetry
    ids, keys, xy = gs.trajectories()
    assert ids.tolist() == [0] * 5 and np.all(np.diff(keys) > 0)
    np.testing.assert_allclose(xy, straight(5)[:, :2], atol=1e-6)
    assert gs.robot_of_key(gs.key_of(1, 2)) == 1 and gs.robot_of_key(int(keys[3])) == 0
    # a hostile walks: the same object at its latest sighting, who saw it when
    cov = (0.01, 0.0, 0.01)
    seen = [(1, 3.0, (4.0, 0.0)), (2, 3.5, (5.5, 0.5)), (4, 4.0, (5.0, 1.0))]
    for i, (node, t, p) in enumerate(seen):
        det = Detection(i, node, t, ObjectKind.HOSTILE, p, cov, 0.3, 1.7, 0.9)
        assert gs.handle(0, det, now_s=t)
    hostiles = [h for h in gs.hazards if h.kind == ObjectKind.HOSTILE]
    assert len(hostiles) == 1
    np.testing.assert_allclose(hostiles[0].position_in_map, (straight(5)[4, 0] + 5.0, 1.0))
    assert gs.hostile_sightings() == {hostiles[0].hazard_id: {0: 4.0}}
    # one far away is another hostile
    far = Detection(9, 4, 4.5, ObjectKind.HOSTILE, (15.0, 0.0), cov, 0.3, 1.7, 0.9)
    gs.handle(0, far, now_s=4.5)
    assert len(gs.hostile_sightings()) == 2


def test_sightings_before_their_pose_node_wait_for_it() -> None:
    # a radio backlog drains the detection stream before the pose nodes (issue 17 item 2)
    gs = GroundStation(GroundStationConfig(robots=(0, 1)))
    path = straight(6)
    nodes = nodes_along(path)
    gs.handle(0, nodes[0], now_s=0.0)
    det = Detection(1, 3, 3.0, ObjectKind.STATIC_OOI, (2.0, 1.0), (0.01, 0.0, 0.01), 0.3, 0.6, 0.9)
    assert gs.handle(0, det, now_s=1.0)  # held, not refused
    assert gs.hazards == [] and gs.stats.sightings_held == 1
    for msg in nodes[1:4]:
        gs.handle(0, msg, now_s=2.0)
    assert len(gs.hazards) == 1
    np.testing.assert_allclose(gs.hazards[0].position_in_map, path[3, :2] + (2.0, 1.0), atol=1e-6)
    # a node that was passed for good: refused with the reason, as before
    old = Detection(2, 1, 1.0, ObjectKind.STATIC_OOI, (5.0, 5.0), (0.01, 0.0, 0.01), 0.3, 0.6, 0.9)
    gs.handle(0, nodes[4], now_s=3.0)
    late = Detection(3, 9, 4.0, ObjectKind.TOXIC_VAT, (1.0, 0.0), (0.01, 0.0, 0.01), 0.3, 0.9, 0.9)
    assert gs.handle(0, late, now_s=3.0)
    assert gs.handle(0, old, now_s=3.0)  # node 1 is in the graph: a second hazard
    assert gs.stats.rejected["orphan_detection"] == 0 and len(gs.hazards) == 2
    # the station gives up on node 9 once the stream passes it (a lost node bridged over)
    gs2 = GroundStation(GroundStationConfig(max_pending_nodes=2))
    msgs = nodes_along(straight(14))
    gs2.handle(0, msgs[0], now_s=0.0)
    assert gs2.handle(0, late, now_s=0.0)
    for i in list(range(1, 9)) + list(range(10, 14)):  # node 9 never comes
        gs2.handle(0, msgs[i], now_s=0.0)
    assert gs2.stats.gaps_bridged == 1 and gs2.key_of(0, 9) is None
    assert gs2.stats.rejected["orphan_detection"] == 1


def test_a_fiducial_waits_for_the_teammate_node_of_its_time() -> None:
    # the robots' streams race: robot 1's tag of t=6 s may come before robot 0's node 6
    path0, path1 = straight(8), straight(8, heading=0.3)
    seen = relative(compose(np.array([2.0, -1.0, 0.3]), path1[6]), path0[6])
    tag = FiducialObservation(6, 6.0, 0, 7, tuple(seen), COV)  # type: ignore[arg-type]
    gs = GroundStation(GroundStationConfig(robots=(0, 1)))
    n0, n1 = nodes_along(path0), nodes_along(path1)
    for m in n0[:3] + n1[:7]:
        gs.handle(0 if m in n0[:3] else 1, m, now_s=6.0)
    assert gs.handle(1, tag, now_s=6.0) and gs.stats.fiducials == 0  # waits for node 6 of 0
    for m in n0[3:7]:
        gs.handle(0, m, now_s=6.5)
    assert gs.stats.fiducials == 1
    (edge,) = gs.graph.edges(Provenance.FIDUCIAL)
    assert edge.key_b == gs.key_of(0, 6)  # the node of its time, not the latest of t=2 s
    # a teammate standing still makes no new node: after fiducial_wait_s its latest one serves
    # (a stand-in's heading is loose by construction: the bound on it is lifted here, so that
    # the stand-in's covariance can be checked; tests/gcs/test_ground_station_fiducials.py)
    gs2 = GroundStation(
        GroundStationConfig(
            robots=(0, 1), fiducial_wait_s=5.0, fiducial_max_sigma_yaw_rad=2 * math.pi
        )
    )
    for m in n0[:3]:
        gs2.handle(0, m, now_s=6.0)
    for m in n1[:7]:
        gs2.handle(1, m, now_s=6.0)
    gs2.handle(1, tag, now_s=6.0)
    gs2.step(now_s=9.0)
    assert gs2.stats.fiducials == 0
    gs2.step(now_s=11.5)
    assert gs2.stats.fiducials == 1 and gs2.stats.rejected_total == 0
    # ... but it may have driven since its last node (t=2 s, seen at 6 s): the stand-in's
    # sigma grows by the top speed and turn rate over those 4 s (a fixed 0.5 m tied two robots
    # 19 m apart in a mission whose teammate had gone silent)
    (edge,) = gs2.graph.edges(Provenance.FIDUCIAL)
    sigma = np.sqrt(np.diag(edge.covariance))
    cfg = gs2.config
    stale_xy = cfg.fiducial_standin_sigma_xy_m + 4.0 * cfg.fiducial_standin_speed_m_s
    assert edge.key_b == gs2.key_of(0, 2) and sigma[0] >= stale_xy and sigma[1] >= stale_xy
    assert sigma[2] >= min(math.pi, 0.2 + 4.0 * cfg.fiducial_standin_turn_rate_rad_s) - 1e-9
