"""The terrain-grid corpus and the training of the codec models (issue 5): recording from a
real simulator run, files that round-trip and refuse garbage, references only between
consecutive nodes, and the shipped model file being exactly what the shipped corpus trains."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from compression.model_file import MODEL_FILE, load_model_file, save_model_file
from mission.cli import main
from mission.codec_training import (
    CORPUS_DIR,
    Corpus,
    ModelSpec,
    RecordRun,
    coding_cases,
    load_corpus,
    node_crop,
    record_corpus,
    save_corpus,
    train_models,
)


def tiny_corpus() -> Corpus:
    rng = np.random.default_rng(0)
    grids = np.zeros((6, 20, 20), bool)
    for k in range(6):
        grids[k, 5 + k % 3, 2:15] = True
        grids[k] |= rng.random((20, 20)) < 0.01
    grids[3] = False  # an empty grid
    return Corpus(
        sequence=np.array([0, 0, 0, 1, 1, 1], np.int32),
        node_index=np.array([0, 1, 3, 0, 1, 2], np.int32),  # a gap in sequence 0
        pose_in_odom=np.zeros((6, 3)),
        odom_delta=np.tile([0.2, 0.0, 0.05], (6, 1)),
        grids=grids,
        origin_in_base=(-1.0, -1.0),
        resolution_m=0.1,
        runs=("world/a.yaml:1:robot0", "world/b.yaml:2:robot0"),
    )


def test_node_crop_is_the_occupied_bounding_box() -> None:
    g = np.zeros((10, 12), bool)
    g[3, 4] = g[6, 9] = True
    crop, r0, c0 = node_crop(g)
    assert (r0, c0) == (3, 4) and crop.shape == (4, 6) and crop.sum() == 2
    assert node_crop(np.zeros((5, 5), bool))[0].shape == (0, 0)


def test_corpus_file_round_trips_and_refuses_garbage(tmp_path: Path) -> None:
    corpus = tiny_corpus()
    save_corpus(corpus, tmp_path / "c.npz")
    back = load_corpus(tmp_path / "c.npz")
    assert np.array_equal(back.grids, corpus.grids) and back.runs == corpus.runs
    assert np.array_equal(back.odom_delta, corpus.odom_delta)
    (tmp_path / "bad.npz").write_bytes(b"not a corpus")
    with pytest.raises(ValueError, match="bad.npz: not a terrain-grid corpus"):
        load_corpus(tmp_path / "bad.npz")


def test_references_link_consecutive_nodes_only() -> None:
    cases = coding_cases(tiny_corpus())
    refs = [None if c.reference is None else c.reference.node_index for c in cases]
    assert refs == [None, 0, None, None, 0, 1]  # node 3 follows a gap: key frame
    _, r0, c0 = node_crop(tiny_corpus().grids[1])
    assert cases[1].origin_cells == (-10 + c0, -10 + r0)
    assert cases[4].reference is not None and cases[4].reference.grid.shape == (0, 0)
    assert [c.run for c in cases[:1]] == ["world/a.yaml:1"]


def test_training_and_model_file(tmp_path: Path) -> None:
    specs = (
        ModelSpec(name="s4", codec_id=200, template="4", adaptive=False),
        ModelSpec(name="r6", codec_id=201, template="6", extrapolate=True, reference=True),
    )
    model_file = train_models(tiny_corpus(), version=3, specs=specs, strengths=(1.0, 4.0))
    s4, r6 = model_file.models
    assert s4.n0.sum() + s4.n1.sum() == sum(
        g.size for g in (c.grid for c in coding_cases(tiny_corpus()))
    )
    assert r6.strength in (1.0, 4.0) and r6.n1.sum() > 0
    save_model_file(tmp_path / "m.npz", model_file)
    back = load_model_file(tmp_path / "m.npz")
    assert back.version == 3 and [m.name for m in back.models] == ["s4", "r6"]
    for a, b in zip(back.models, model_file.models, strict=True):
        assert np.array_equal(a.n0, b.n0) and np.array_equal(a.n1, b.n1)
    (tmp_path / "bad.npz").write_bytes(b"junk")
    with pytest.raises(ValueError, match="bad.npz: not a terrain-codec model file"):
        load_model_file(tmp_path / "bad.npz")


@pytest.mark.slow
def test_shipped_model_is_what_the_shipped_corpus_trains() -> None:
    shipped = load_model_file(MODEL_FILE)
    trained = train_models(load_corpus(CORPUS_DIR / "terrain_train.npz"), version=shipped.version)
    assert [m.name for m in trained.models] == [m.name for m in shipped.models]
    for a, b in zip(trained.models, shipped.models, strict=True):
        assert (a.strength, a.template, a.extrapolate, a.reference) == (
            b.strength, b.template, b.extrapolate, b.reference,
        )  # fmt: skip
        assert np.array_equal(a.n0, b.n0) and np.array_equal(a.n1, b.n1)


def test_train_and_test_corpora_come_from_different_worlds() -> None:
    train = {r.rsplit(":", 1)[0] for r in load_corpus(CORPUS_DIR / "terrain_train.npz").runs}
    test = {r.rsplit(":", 1)[0] for r in load_corpus(CORPUS_DIR / "terrain_test.npz").runs}
    assert train and test and not train & test
    trained_on = load_model_file(MODEL_FILE).meta["trained_on"]
    assert isinstance(trained_on, list) and set(trained_on) == train


@pytest.mark.slow
def test_recording_a_short_run_keeps_every_pose_node() -> None:
    corpus = record_corpus([RecordRun(world="world/small.yaml", seed=4, duration_s=9.0)])
    assert len(corpus) >= 4  # every robot makes its first node once it has a sweep
    assert corpus.grids.shape[1:] == (150, 150) and corpus.grids.any()
    for rows in corpus.sequences():
        assert list(corpus.node_index[rows]) == list(range(len(rows)))
        assert np.allclose(corpus.odom_delta[rows[0]], 0.0)


def test_codec_command(tmp_path: Path) -> None:
    save_corpus(tiny_corpus(), tmp_path / "c.npz")
    out = tmp_path / "m.npz"
    assert (
        main(
            [
                "codec",
                "train",
                "--corpus",
                str(tmp_path / "c.npz"),
                "--out",
                str(out),
                "--version",
                "9",
            ]
        )
        == 0
    )
    assert load_model_file(out).version == 9
    assert main(["codec", "train", "--corpus", str(tmp_path / "none.npz"), "--out", str(out)]) == 2


@pytest.mark.parametrize(
    ("argv", "named"),
    [
        (["codec", "record", "--out", "/nonexistent/dir/c.npz"], "/nonexistent/dir"),
        (["codec", "train", "--corpus", "/nonexistent/c.npz"], "/nonexistent/c.npz"),
        (["codec", "train", "--out", "/nonexistent/dir/m.npz"], "/nonexistent/dir"),
        (["codec", "train", "--version", "256", "--out", "{tmp}/m.npz"], "--version"),
    ],
)
def test_codec_paths_are_checked_before_the_work(
    argv: list[str], named: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bad path or version: one line naming it, status 2, at once (record would run the
    simulator for minutes first; nothing is written)."""
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and len(err) < 200
    assert err.startswith(f"magic codec {argv[1]}: ") and named in err
    assert list(tmp_path.iterdir()) == []
