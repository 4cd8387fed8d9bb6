"""A mirror kept up to date by additions answers Dijkstra projections as one rebuilt from the
whole graph, and rebuilds itself after any other change (issue 16)."""

from __future__ import annotations

import numpy as np

from gcs.graph import se2
from gcs.graph.dijkstra_projection import dijkstra_projection
from gcs.graph.graph_mirror import GraphMirror
from gcs.graph.pose_graph import PoseGraph, Provenance
from tests.gcs.graph.test_pose_graph import LOOP_COV, ODO_COV


def _projection_by_key(m: GraphMirror, key: int) -> dict[int, tuple[float, ...]]:
    proj = dijkstra_projection(m.adjacency, m.index[key])
    return {
        int(k): tuple(np.round(proj.covariances[i].ravel(), 12))
        for i, k in enumerate(m.keys)
        if proj.reached[i]
    }


def test_a_mirror_grown_step_by_step_matches_one_rebuilt_and_rebuilds_after_a_removal() -> None:
    rng = np.random.default_rng(8)
    g = PoseGraph()
    mirror = GraphMirror()
    odo = {r: np.array([5.0 * r, 0.0, 0.0]) for r in range(3)}
    loops: list[int] = []
    for step in range(12):
        for r in range(3):
            for _ in range(2):
                odo[r] = se2.compose(odo[r], np.array([0.5, 0.0, rng.normal(0, 0.2)]))
                first = r not in g.robots
                g.add_pose(r, odom_from_base=odo[r], time_s=float(step),
                           odometry_covariance=None if first else ODO_COV)  # fmt: skip
        if step % 3 == 2:  # a closure between two robots' latest poses
            a, b = g.last_key(step % 3), g.last_key((step + 1) % 3)
            loops.append(
                g.add_edge(
                    a,
                    b,
                    a_from_b=np.array([1.0, 0.0, 0.0]),
                    covariance=LOOP_COV,
                    provenance=Provenance.LOOP_AUTO,
                    time_s=float(step),
                )  # fmt: skip
            )
        revision = mirror.revision
        assert mirror.update(g)
        assert not mirror.update(g)  # nothing new
        assert (mirror.revision != revision) == (step % 3 == 2 or step == 0)
        fresh = GraphMirror()
        fresh.update(g)
        assert sorted(mirror.keys.tolist()) == fresh.keys.tolist()
        assert all(mirror.keys[mirror.index[k]] == k for k in fresh.index)
        assert mirror.loop_edge_ids == fresh.loop_edge_ids == loops
        assert sorted(mirror.edge_ids) == sorted(fresh.edge_ids)
        src = int(fresh.keys[0])
        assert _projection_by_key(mirror, src) == _projection_by_key(fresh, src)
        for k in fresh.keys.tolist():
            i, j = mirror.index[k], fresh.index[k]
            assert mirror.robot_ids[i] == fresh.robot_ids[j]
            assert mirror.indices[i] == fresh.indices[j]
    assert mirror.rebuilds == 1  # only the first update
    revision = mirror.revision
    g.remove_edges([loops[0]])
    assert mirror.update(g) and mirror.rebuilds == 2 and mirror.revision != revision
    assert loops[0] not in mirror.edge_ids and mirror.loop_edge_ids == loops[1:]
    g.add_prior(g.last_key(1), map_from_base=g.pose(g.last_key(1)), covariance=LOOP_COV,
                time_s=99.0)  # fmt: skip
    assert mirror.update(g) and mirror.rebuilds == 2  # a prior is no relative edge
    assert mirror.adjacency.num_edges == len(mirror.edge_ids)
