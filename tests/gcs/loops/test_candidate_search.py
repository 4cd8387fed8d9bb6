"""Candidate generation: Dijkstra projection gates, windows, priorities, unlinked robots."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.keys import pose_key
from gcs.graph.pose_graph import PoseGraph, Provenance
from gcs.loops.candidate_search import (
    CandidateSearchConfig,
    body_to_vector_covariance,
    search_candidates,
)

STEP_COV = np.diag([0.02**2, 0.02**2, 0.01**2])


def square_loop(
    graph: PoseGraph, robot: int, *, side: int = 10, start=(0.0, 0.0, 0.0)
) -> list[int]:
    """A robot driving a square of ``side`` 1 m steps, back to its start."""
    keys = []
    pose = np.array(start, dtype=float)
    for k in range(4 * side + 1):
        keys.append(
            graph.add_pose(
                robot,
                odom_from_base=pose,
                time_s=float(k),
                odometry_covariance=None if k == 0 else STEP_COV,
            )
        )
        turn = math.pi / 2 if (k + 1) % side == 0 else 0.0
        pose = se2.compose(pose, np.array([1.0, 0.0, turn]))
    return keys


def candidates_of(graph: PoseGraph, key: int, config: CandidateSearchConfig, scanned=None):
    keys, proj = graph.projection(key)
    nodes = {n.key: n for n in graph.nodes()}
    return search_candidates(
        key,
        keys=keys,
        robot_ids=np.array([nodes[int(k)].robot_id for k in keys]),
        indices=np.array([nodes[int(k)].index for k in keys]),
        has_scan=np.array([scanned is None or int(k) in scanned for k in keys]),
        poses=proj.poses,
        covariances=proj.covariances,
        config=config,
    )


def test_a_loop_returns_to_its_start_and_finds_it() -> None:
    graph = PoseGraph()
    keys = square_loop(graph, 0)
    cfg = CandidateSearchConfig(max_per_node=50)
    found = candidates_of(graph, keys[-1], cfg)
    targets = {c.query_key for c in found}
    assert keys[0] in targets and keys[1] in targets  # the start, 40 m of odometry away
    # consecutive nodes of the same robot are skipped (min_index_gap), far ones too
    assert not targets & set(keys[-cfg.min_index_gap :])
    for c in found:
        sigma = math.sqrt(np.linalg.eigvalsh(c.covariance_xyt[:2, :2])[-1])
        dist = float(np.hypot(*c.reference_from_query[:2]))
        assert dist - cfg.k_sigma * sigma <= cfg.max_distance_m + 1e-9
        assert c.priority <= sigma + 1e-12
        assert c.reference_key == keys[-1]
    # highest priority (expected correction) first
    pr = [round(c.priority, 2) for c in found]
    assert pr == sorted(pr, reverse=True)
    # the cap keeps the best ones
    capped = candidates_of(graph, keys[-1], CandidateSearchConfig(max_per_node=3))
    assert [c.query_key for c in capped] == [c.query_key for c in found[:3]]
    # only scanned nodes are candidates
    only = candidates_of(graph, keys[-1], cfg, scanned={keys[0], keys[-1]})
    assert [c.query_key for c in only] == [keys[0]]


def test_unlinked_robots_are_never_candidates_and_a_loose_hint_gives_a_wide_window() -> None:
    graph = PoseGraph()
    a = square_loop(graph, 0)
    b = square_loop(graph, 1, start=(0.0, 0.0, 0.0))
    cfg = CandidateSearchConfig(max_per_node=100)
    assert all(split >> 32 == 1 for split in (c.query_key for c in candidates_of(graph, b[5], cfg)))
    # an operator hint: robot 1 starts 1 m beside robot 0, give or take 1 m and 10 deg
    graph.add_edge(
        a[0],
        b[0],
        a_from_b=np.array([0.0, 1.0, 0.0]),
        covariance=np.diag([1.0, 1.0, math.radians(10) ** 2]),
        provenance=Provenance.LOOP_OPERATOR,
        time_s=0.0,
    )
    found = candidates_of(graph, b[5], cfg)
    cross = [c for c in found if c.query_key >> 32 == 0]
    assert cross, "linked robots must produce cross-robot candidates"
    assert all(c.wide for c in cross)  # 3 sigma of 1 m exceeds the +-3 m window
    assert all(c.window_xy_m == cfg.wide_xy_m for c in cross)
    assert all(math.radians(30) < c.window_yaw_rad <= cfg.wide_yaw_rad for c in cross)
    # a tight fiducial instead: the standard window
    graph2 = PoseGraph()
    a2 = square_loop(graph2, 0)
    b2 = square_loop(graph2, 1)
    graph2.add_edge(
        a2[0],
        b2[0],
        a_from_b=np.array([0.0, 1.0, 0.0]),
        covariance=np.diag([0.05**2, 0.05**2, 0.02**2]),
        provenance=Provenance.FIDUCIAL,
        time_s=0.0,
    )
    cross2 = [c for c in candidates_of(graph2, b2[5], cfg) if c.query_key >> 32 == 0]
    assert cross2 and not any(c.wide for c in cross2)
    assert pose_key(0, 5) in {c.query_key for c in cross2}


def test_too_uncertain_pairs_are_dropped() -> None:
    graph = PoseGraph()
    a = square_loop(graph, 0)
    b = square_loop(graph, 1)
    graph.add_edge(
        a[0],
        b[0],
        a_from_b=np.array([0.0, 1.0, 0.0]),
        covariance=np.diag([25.0, 25.0, 1.0]),  # 5 m: 3 sigma beyond the 8 m wide window
        provenance=Provenance.LOOP_OPERATOR,
        time_s=0.0,
    )
    found = candidates_of(graph, b[5], CandidateSearchConfig(max_per_node=100))
    assert not [c for c in found if c.query_key >> 32 == 0]


def test_body_covariance_to_vector_components_matches_a_numerical_jacobian() -> None:
    rng = np.random.default_rng(0)
    pose = np.array([1.0, -2.0, 0.7])
    a = rng.normal(size=(3, 3))
    cov_body = a @ a.T * 1e-4
    samples = rng.multivariate_normal(np.zeros(3), cov_body, size=200_000)
    perturbed = se2.compose(pose, samples)  # right perturbation
    d = perturbed - pose
    d[:, 2] = se2.wrap_angle(d[:, 2])
    emp = np.cov(d.T)
    assert np.allclose(body_to_vector_covariance(pose, cov_body), emp, atol=3e-6)


def test_bad_arrays_are_refused() -> None:
    cfg = CandidateSearchConfig()
    keys = np.array([1, 2, 3])
    good = dict(
        keys=keys,
        robot_ids=np.zeros(3, int),
        indices=np.arange(3),
        has_scan=np.ones(3, bool),
        poses=np.zeros((3, 3)),
        covariances=np.tile(np.eye(3), (3, 1, 1)),
        config=cfg,
    )
    with pytest.raises(ValueError, match="poses"):
        search_candidates(1, **{**good, "poses": np.zeros((2, 3))})
    with pytest.raises(ValueError, match="not among"):
        search_candidates(9, **good)
    with pytest.raises(ValueError, match="wide window"):
        CandidateSearchConfig(wide_xy_m=2.0)


def test_the_nodes_either_side_of_a_gap_are_candidates_however_close_in_index() -> None:
    """Lost scans: one odometry step spans 8 m with a widened covariance (the replay's
    odometry_gaps). The nodes just before and after it are fewer than min_index_gap apart and
    farther than max_distance_m, yet they are the only pairs that can tie the nodes after the
    gap to the map before it; nodes as close in index with tight odometry stay skipped."""
    graph = PoseGraph()
    keys = []
    pose = np.zeros(3)
    for k in range(12):
        gap = k == 6
        keys.append(
            graph.add_pose(
                0,
                odom_from_base=pose,
                time_s=float(k),
                odometry_covariance=None
                if k == 0
                else (np.diag([0.4**2, 0.4**2, 0.05**2]) if gap else STEP_COV),
            )
        )
        pose = se2.compose(pose, np.array([8.0 if k == 5 else 1.0, 0.0, 0.0]))
    cfg = CandidateSearchConfig(max_per_node=50)
    after = {c.query_key for c in candidates_of(graph, keys[6], cfg)}
    assert {keys[5], keys[4]} <= after  # 8 and 9 m back across the gap
    assert not {keys[7], keys[8]} & after  # tight odometry, fewer than min_index_gap
    tight = {c.query_key for c in candidates_of(graph, keys[4], cfg)}
    assert not {keys[2], keys[3], keys[5]} & tight
    never = CandidateSearchConfig(max_per_node=50, gap_sigma_xy_m=math.inf)
    assert not {keys[5], keys[4]} & {c.query_key for c in candidates_of(graph, keys[6], never)}
    with pytest.raises(ValueError, match="gap_sigma_xy_m"):
        CandidateSearchConfig(gap_sigma_xy_m=0.0)


def test_the_per_node_budget_goes_to_the_grids_that_overlap() -> None:
    """Late in a long loop every candidate of a new node shares that node's large uncertainty
    (Intel, node 840: 200 candidates, sigma 1.3-2.0 m, all within 6 m): ranked by sigma alone,
    the eight kept were those 4.4-4.6 m away whose paths were a few percent looser, and the
    pairs 3 m away that matched were never tried. ``overlap_m`` discounts the priority by how
    far apart the two grids are expected to be."""
    n = 24
    d = np.linspace(0.5, 4.9, n)  # expected distances, m
    sigma = 1.9 + 0.03 * d  # the farther a node, the slightly looser its path
    poses = np.column_stack([d, np.zeros(n), np.zeros(n)])
    covs = np.array([np.diag([s**2, s**2, math.radians(10.0) ** 2]) for s in sigma])
    keys = np.array([pose_key(0, 0)] + [pose_key(1, i) for i in range(n)])
    args = dict(
        keys=keys,
        robot_ids=np.array([0] + [1] * n),
        indices=np.array([0, *range(n)]),
        has_scan=np.ones(n + 1, dtype=bool),
        poses=np.vstack([np.zeros(3), poses]),
        covariances=np.concatenate([np.eye(3)[None] * 1e-6, covs]),
    )
    far = search_candidates(keys[0], config=CandidateSearchConfig(overlap_m=math.inf), **args)
    near = search_candidates(keys[0], config=CandidateSearchConfig(overlap_m=5.0), **args)
    dist = [float(np.hypot(*c.reference_from_query[:2])) for c in far]
    assert len(far) == 8 and min(dist) > 3.3  # sigma alone: the farthest eight
    dist = [float(np.hypot(*c.reference_from_query[:2])) for c in near]
    assert len(near) == 8 and max(dist) < 2.2  # the nearest eight
    assert all(c.wide for c in near)  # the same windows, only the choice differs
    with pytest.raises(ValueError, match="overlap_m"):
        CandidateSearchConfig(overlap_m=0.0)
