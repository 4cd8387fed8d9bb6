from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from gcs.graph import se2
from gcs.graph.g2o import (
    G2oError,
    chained_odometry,
    merge_repeated_edges,
    parse_g2o,
    read_g2o,
    reverse_edge,
    to_gtsam,
    write_g2o,
)
from gcs.graph.optimization import optimize_batch

GOOD = """\
# a comment
VERTEX_SE2 0 0 0 0
VERTEX_SE2 1 1 0 0.1
VERTEX_SE2 2 2 0.1 0.2
EDGE_SE2 0 1 1 0 0.1 100 0 0 100 0 400
EDGE_SE2 1 2 1 0.05 0.1 100 0 0 100 0 400
EDGE_SE2 2 0 -2 0.3 -0.2 10 1 0 10 0 40
"""


def test_parse_good() -> None:
    g = parse_g2o(GOOD)
    assert g.vertex_ids.tolist() == [0, 1, 2]
    assert g.edge_ij.tolist() == [[0, 1], [1, 2], [2, 0]]
    np.testing.assert_allclose(g.edge_info[2], [[10, 1, 0], [1, 10, 0], [0, 0, 40]])
    assert g.edge_lines.tolist() == [5, 6, 7]


@pytest.mark.parametrize(
    ("line", "message"),
    [
        ("EDGE_SE2 0 1 1 0 0 1 0 0 1 0", r"g2o line 3: EDGE_SE2 expects 11 numbers, got 10"),
        ("EDGE_SE2 0 1 1 x 0 1 0 0 1 0 1", r"g2o line 3: EDGE_SE2: 'x' is not a number"),
        ("EDGE_SE2 0 1 1 nan 0 1 0 0 1 0 1", r"g2o line 3: EDGE_SE2: non-finite value 'nan'"),
        ("EDGE_SE2 0 1 1 0 0 1 0 0 -1 0 1", r"g2o line 3: EDGE_SE2 0 1: information matrix"),
        ("EDGE_SE2 0 0 1 0 0 1 0 0 1 0 1", r"g2o line 3: EDGE_SE2 connects vertex 0 to itself"),
        ("EDGE_SE2 a 1 1 0 0 1 0 0 1 0 1", r"g2o line 3: EDGE_SE2: vertex id 'a'"),
        ("VERTEX_SE2 0 1 2", r"g2o line 3: VERTEX_SE2 expects 4 numbers, got 3"),
        ("VERTEX_SE2 0 1 2 3", r"g2o line 3: VERTEX_SE2 0 already defined on line 1"),
        ("VERTEX_XYZ 0 1 2 3", r"g2o line 3: unsupported record 'VERTEX_XYZ'"),
    ],
)
def test_malformed_lines_name_the_line(line: str, message: str) -> None:
    text = "VERTEX_SE2 0 0 0 0\n\n" + line + "\n"
    with pytest.raises(G2oError, match=message):
        parse_g2o(text)


def test_read_names_file(tmp_path: Path) -> None:
    p = tmp_path / "bad.g2o"
    p.write_text("VERTEX_SE2 0 0 0\n")
    with pytest.raises(G2oError, match=r"bad\.g2o: g2o line 1"):
        read_g2o(p)


def test_write_read_round_trip(tmp_path: Path) -> None:
    g = parse_g2o(GOOD + "FIX 0\n")
    p = tmp_path / "g.g2o"
    write_g2o(p, g)
    h = read_g2o(p)
    np.testing.assert_array_equal(h.edge_ij, g.edge_ij)
    np.testing.assert_array_equal(h.edge_z, g.edge_z)
    np.testing.assert_array_equal(h.edge_info, g.edge_info)
    np.testing.assert_array_equal(h.vertex_poses, g.vertex_poses)
    assert h.fixed == (0,)


def test_reverse_edge_is_the_same_factor_to_first_order() -> None:
    rng = np.random.default_rng(3)
    z = np.array([1.0, 2.0, 0.7])
    a = rng.normal(size=(3, 3))
    info = a @ a.T + np.eye(3)
    zr, ir = reverse_edge(z, info)
    f1 = gtsam.BetweenFactorPose2(0, 1, se2.pose2(z), gtsam.noiseModel.Gaussian.Information(info))
    f2 = gtsam.BetweenFactorPose2(1, 0, se2.pose2(zr), gtsam.noiseModel.Gaussian.Information(ir))
    x0 = gtsam.Pose2(0.3, -0.2, 0.1)
    values = gtsam.Values()
    values.insert(0, x0)
    values.insert(1, x0.compose(se2.pose2(z)).compose(gtsam.Pose2.Expmap([1e-3, -2e-3, 1e-3])))
    assert f2.error(values) == pytest.approx(f1.error(values), rel=1e-6)


def _random_graph_text(rng: np.random.Generator, n: int = 12) -> str:
    truth = np.cumsum(rng.normal([0.8, 0.0, 0.1], 0.2, size=(n, 3)), axis=0)
    lines = []
    pairs = [(i, i + 1) for i in range(n - 1)] + [(0, 5), (3, 9), (9, 3), (0, 5), (2, 11)]
    for i, j in pairs:
        z = se2.between(truth[i], truth[j]) + rng.normal(0, [0.05, 0.05, 0.02])
        info = [100.0 * rng.uniform(0.5, 2), 5.0, 1.0, 100.0, -2.0, 400.0]
        lines.append(f"EDGE_SE2 {i} {j} " + " ".join(f"{v:.12g}" for v in (*z, *info)))
    return "\n".join(lines) + "\n"


def test_merge_repeated_edges_is_lossless() -> None:
    text = _random_graph_text(np.random.default_rng(7))
    raw = parse_g2o(text, merge_repeated=False)
    merged = merge_repeated_edges(raw)
    assert len(raw.edge_ij) == len(merged.edge_ij) + 2
    init = chained_odometry(raw)
    results = []
    for g in (raw, merged):
        fg, values = to_gtsam(g, poses=init)
        res = optimize_batch(fg, values, method="gn", relative_error_tol=1e-12)
        results.append(np.array([se2.pose_vec(res.values.atPose2(k)) for k in range(12)]))
        # chi2 at the optimum, offset included, agrees with the unmerged graph's.
        assert g.chi2(res.values) == pytest.approx(raw.chi2(res.values), rel=1e-3)
    assert np.abs(results[0] - results[1]).max() < 1e-3


def test_chained_odometry_missing_edge() -> None:
    g = parse_g2o("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(G2oError, match="no edge between vertices 1 and 2"):
        chained_odometry(g)


def test_olson_repeated_pairs_merged(posegraph_dir: Path) -> None:
    raw = read_g2o(posegraph_dir / "manhattan_olson3500.g2o", merge_repeated=False)
    merged = merge_repeated_edges(raw)
    assert len(raw.edge_ij) == 5598
    pairs = {(min(i, j), max(i, j)) for i, j in raw.edge_ij.tolist()}
    assert len(merged.edge_ij) == len(pairs) < 5598
    assert merged.chi2_offset > 0
