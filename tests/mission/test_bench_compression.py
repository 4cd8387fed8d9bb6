"""``magic bench compression --quick`` on the shipped held-out corpus (issue 5): the metrics the
issue names are there, every codec round-trips, the codecs order as measured, and the churn
fractions that bound inter-frame coding are proper fractions."""

from __future__ import annotations

import pytest

from mission.bench import bench_root, compression


@pytest.fixture(scope="module")
def metrics() -> dict[str, float]:
    return compression.run(quick=True, progress=lambda _msg: None)


def test_issue_metrics_are_reported(metrics: dict[str, float]) -> None:
    named = [
        "bytes_zlib",
        "bytes_rle",
        "bytes_rle_zlib",
        "bytes_magic4",
        "bytes_best_intra",
        "bytes_best_inter",
        "ratio_intra_vs_magic4",
        "ratio_inter_vs_magic4",
        "ratio_magic4_vs_zlib",
        "roundtrip_exact",
        "grids_per_s",
        "mean_grid_pixels",
    ]
    assert list(metrics)[: len(named)] == named
    assert metrics["roundtrip_exact"] == 1.0
    # written under $MAGIC_BENCH_DIR, which tests/conftest.py points at a pytest tmp dir
    figure = bench_root() / "compression" / "fig10_bytes_per_grid.png"
    assert figure.stat().st_size > 1000


def test_codecs_order_as_the_paper_and_issue_expect(metrics: dict[str, float]) -> None:
    m = metrics
    assert m["bytes_best_inter"] <= m["bytes_best_intra"] < m["bytes_magic4"] < m["bytes_zlib"]
    assert m["bytes_rle_zlib"] < m["bytes_zlib"] < m["bytes_rle"]  # paper 4.3.4
    assert m["ratio_intra_vs_magic4"] <= 0.75


def test_header_and_churn_explain_the_inter_frame_bytes(metrics: dict[str, float]) -> None:
    # header: codec id, model version, two sizes, the centre and (inter) the reference node
    assert 5 <= metrics["header_bytes_magic4"] < metrics["header_bytes_inter16"] <= 10
    assert 0.05 < metrics["inter_new_cell_frac"] < 0.6
    assert 0.05 < metrics["inter_vanished_ref_frac"] < 0.6
