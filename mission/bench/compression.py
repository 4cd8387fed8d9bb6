"""``magic bench compression``: terrain-grid codecs on the held-out corpus (issue 5; paper
4.3.4, Fig. 9-10).

The corpus ``compression/corpus/terrain_test.npz`` holds the vertical-surface grids of every
pose node of whole robot teams in worlds the models were *not* trained on (see
:mod:`mission.codec_training`). Each grid is coded as the robot node sends it: cropped to its
occupied bounding box, with its origin; inter-frame codecs code it against the previous node's
grid (a key frame for a sequence's first node). Bytes are whole streams (header + body).

Metrics:

- ``bytes_<codec>`` for every registered codec; ``bytes_zlib``, ``bytes_rle``,
  ``bytes_rle_zlib``, ``bytes_magic4`` (the paper's coder: 4 neighbours, static trained
  probabilities), ``bytes_best_intra`` / ``bytes_best_inter`` (the intra / inter-frame codec
  with the fewest bytes; the progress log names them);
- ``ratio_intra_vs_magic4`` (target <= 0.75), ``ratio_inter_vs_magic4`` (target <= 0.5),
  ``ratio_magic4_vs_zlib`` (the paper: 0.35);
- ``roundtrip_exact``: 1 if every codec decoded every grid exactly, else 0;
- ``grids_per_s``: grids encoded plus decoded per second on one core with the default codec,
  the time being the process's CPU time (the coders are single-threaded: that is the time
  they hold one core; median of repeats over the corpus). ``grids_per_s_wall`` the same by
  wall clock, which on a shared machine also counts the neighbours' share of the core.
  ``grids_per_s_<codec>`` (CPU) for the best intra codec and ``magic4``;
- ``mean_grid_pixels``: mean cells of the cropped grids; ``inter_frame_frac``: grids that had
  a reference;
- ``uncropped_bytes_<codec>``: the same grids sent whole (150 x 150 around the robot) instead
  of cropped, for the default codec and ``magic4``: does the crop pay for its header?
- ``wire_bytes_per_grid``: what the radio carries for a grid with the default codec, the
  :class:`~protocol.messages.TerrainGrid` in its frame (the stream plus about 17 bytes);
  ``header_bytes_<codec>``: the mean stream header of the default codec and ``magic4``;
- what inter-frame coding can hope for, on the whole grids with the previous whole grid
  warped by odometry (:mod:`compression.reference_warp`): ``inter_new_cell_frac``, occupied
  cells with no reference cell within one cell (news the previous grid cannot predict), and
  ``inter_vanished_ref_frac``, reference cells landing in the grid with no occupied cell
  within one cell (walls that left the field of view or were not seen again).

Writes the Fig. 10 plot (bytes per grid by method) to ``fig10_bytes_per_grid.png`` in
:func:`mission.bench.output_dir` ``("compression")`` (``$MAGIC_BENCH_DIR`` or the system temp
dir).
"""

from __future__ import annotations

__all__ = ["run"]

import statistics
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage

from compression import (
    DEFAULT_CODEC,
    CodecError,
    GridReference,
    codec_names,
    decode_grid,
    encode_grid,
    origin_cells_of,
    read_header,
)
from compression.codecs import reference_code_for
from mission.bench import BenchError, output_dir
from mission.codec_training import CORPUS_DIR, CodingCase, Corpus, coding_cases, load_corpus
from protocol.messages import TerrainGrid, encode_frame

PAPER_BYTES = {"zlib": 378.0, "rle_zlib": 300.0, "magic4": 132.0}  # Fig. 10 (rle_zlib: 132/0.44)


def _code_all(codec: str, cases: list[CodingCase]) -> tuple[float, bool]:
    """Mean stream bytes and whether every grid came back exactly."""
    total = 0
    exact = True
    for c in cases:
        data = encode_grid(c.grid, codec, origin_cells=c.origin_cells, reference=c.reference)
        total += len(data)
        try:
            out = decode_grid(data, reference=c.reference)
        except CodecError:
            exact = False
            continue
        exact &= out.shape == c.grid.shape and bool(np.array_equal(out, c.grid))
    return total / max(len(cases), 1), exact


def _speed(codec: str, cases: list[CodingCase], repeats: int) -> tuple[float, float]:
    """Grids per second (encode + decode), median wall and median process CPU time."""

    def once() -> None:
        for c in cases:
            data = encode_grid(c.grid, codec, origin_cells=c.origin_cells, reference=c.reference)
            decode_grid(data, reference=c.reference)

    once()  # warm-up: compiled kernels and caches
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        once()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    n = len(cases)
    return n / statistics.median(wall), n / statistics.median(cpu)


def _wire_bytes(codec: str, cases: list[CodingCase], corpus: Corpus) -> float:
    """Mean frame bytes of the TerrainGrid messages that carry the grids (sequence numbers and
    node indices as a mission's would be)."""
    total = 0
    for seq, (c, node) in enumerate(zip(cases, corpus.node_index, strict=True)):
        data = encode_grid(c.grid, codec, origin_cells=c.origin_cells, reference=c.reference)
        total += len(encode_frame(seq, TerrainGrid(int(node), corpus.resolution_m, data)))
    return total / max(len(cases), 1)


def _header_bytes(codec: str, cases: list[CodingCase]) -> float:
    sizes = [
        read_header(
            encode_grid(c.grid, codec, origin_cells=c.origin_cells, reference=c.reference)
        ).size
        for c in cases
    ]
    return float(np.mean(sizes))


def _churn(whole: list[CodingCase]) -> tuple[float, float]:
    """``(new cell fraction, vanished reference fraction)`` over the grids with a reference."""
    occupied = new = landed = vanished = 0
    for c in whole:
        if c.reference is None:
            continue
        h, w = c.grid.shape
        code = reference_code_for(h, w, c.origin_cells, c.reference)
        near = ndimage.binary_dilation(c.grid, structure=np.ones((3, 3), dtype=bool))
        occupied += int(c.grid.sum())
        new += int((c.grid & (code == 0)).sum())
        landed += int((code == 2).sum())
        vanished += int(((code == 2) & ~near).sum())
    return new / max(occupied, 1), vanished / max(landed, 1)


def _uncropped(
    cases: list[CodingCase], corpus_grids: np.ndarray, base: tuple[int, int]
) -> list[CodingCase]:
    """The same grids sent whole, the reference being the previous whole grid."""
    out: list[CodingCase] = []
    for c, full in zip(cases, corpus_grids, strict=True):
        ref = None
        if c.reference is not None:
            prev = out[-1]
            ref = GridReference(
                c.reference.node_index,
                prev.grid,
                base,
                c.reference.reference_from_current,
                c.reference.resolution_m,
            )
        out.append(CodingCase(full, base, ref, c.run))
    return out


def _plot(path: Path, bars: list[tuple[str, float, float | None]]) -> None:
    """A bar chart like the paper's Fig. 10: bytes per grid by method (paper's in grey)."""
    width, height, left, bottom, top = 960, 520, 70, 90, 50
    img = np.full((height, width, 3), 255, np.uint8)
    vmax = max(b for _, b, _ in bars) * 1.15
    n = len(bars)
    slot = (width - left - 20) / n
    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(img, "Terrain-grid compression: bytes per grid (held-out worlds)", (left, 30),
                font, 0.7, (0, 0, 0), 2, cv2.LINE_AA)  # fmt: skip
    for k in range(0, int(vmax) + 1, 10 if vmax < 150 else 50):
        y = int(height - bottom - k / vmax * (height - bottom - top))
        cv2.line(img, (left, y), (width - 20, y), (225, 225, 225), 1)
        cv2.putText(img, str(k), (10, y + 5), font, 0.45, (80, 80, 80), 1, cv2.LINE_AA)
    for i, (name, value, paper) in enumerate(bars):
        x0 = int(left + i * slot + slot * 0.2)
        x1 = int(left + (i + 1) * slot - slot * 0.2)
        y = int(height - bottom - value / vmax * (height - bottom - top))
        ours = name.startswith(("inter", "intra", "ctx"))
        colour = (200, 120, 40) if ours else (90, 90, 200)  # BGR: blue, red
        cv2.rectangle(img, (x0, y), (x1, height - bottom), colour, -1)
        cv2.putText(img, f"{value:.1f}", (x0, y - 6), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
        cv2.putText(img, name, (x0 - 5, height - bottom + 20), font, 0.45, (0, 0, 0), 1,
                    cv2.LINE_AA)  # fmt: skip
        if paper is not None:
            cv2.putText(img, f"paper {paper:.0f}", (x0 - 5, height - bottom + 40), font, 0.4,
                        (120, 120, 120), 1, cv2.LINE_AA)  # fmt: skip
    cv2.putText(img, "red: baselines and the paper's coders (magic4, magic10); blue: this build's;"
                " grey: the paper's Fig. 10 values",
                (left, height - 15), font, 0.45, (60, 60, 60), 1, cv2.LINE_AA)  # fmt: skip
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), img)


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    path = CORPUS_DIR / "terrain_test.npz"
    if not path.is_file():
        raise BenchError(f"held-out corpus {path} not found (magic codec record --split test)")
    corpus = load_corpus(path)
    cases = coding_cases(corpus)
    progress(f"{len(cases)} held-out grids from {len(corpus.runs)} robot runs")
    out: dict[str, float] = {}
    exact = True
    for codec in codec_names():
        out[f"bytes_{codec}"], ok = _code_all(codec, cases)
        exact &= ok
    intra = min(codec_names(inter=False), key=lambda c: out[f"bytes_{c}"])
    inter = min(codec_names(inter=True), key=lambda c: out[f"bytes_{c}"])
    progress(f"best intra: {intra}, best inter-frame: {inter}, default: {DEFAULT_CODEC}")
    out["bytes_best_intra"] = out[f"bytes_{intra}"]
    out["bytes_best_inter"] = out[f"bytes_{inter}"]
    out["ratio_intra_vs_magic4"] = out["bytes_best_intra"] / out["bytes_magic4"]
    out["ratio_inter_vs_magic4"] = out["bytes_best_inter"] / out["bytes_magic4"]
    out["ratio_magic4_vs_zlib"] = out["bytes_magic4"] / out["bytes_zlib"]
    out["roundtrip_exact"] = 1.0 if exact else 0.0
    out["mean_grid_pixels"] = float(np.mean([c.grid.size for c in cases]))
    out["inter_frame_frac"] = float(np.mean([c.reference is not None for c in cases]))

    repeats = 3 if quick else 7
    progress(f"speed: {DEFAULT_CODEC}, {intra}, magic4 ({repeats} repeats)")
    out["grids_per_s_wall"], out["grids_per_s"] = _speed(DEFAULT_CODEC, cases, repeats)
    for codec in dict.fromkeys((intra, "magic4")):
        out[f"grids_per_s_{codec}"] = _speed(codec, cases, repeats)[1]

    out["wire_bytes_per_grid"] = _wire_bytes(DEFAULT_CODEC, cases, corpus)
    base = origin_cells_of(corpus.origin_in_base, corpus.resolution_m)
    whole = _uncropped(cases, corpus.grids, base)
    for codec in dict.fromkeys((DEFAULT_CODEC, "magic4")):
        out[f"uncropped_bytes_{codec}"] = _code_all(codec, whole)[0]
        out[f"header_bytes_{codec}"] = _header_bytes(codec, cases)
    out["inter_new_cell_frac"], out["inter_vanished_ref_frac"] = _churn(whole)

    bars = [(c, out[f"bytes_{c}"], PAPER_BYTES.get(c)) for c in ("rle", "zlib", "rle_zlib")]
    bars += [(c, out[f"bytes_{c}"], PAPER_BYTES.get(c)) for c in ("magic4", "magic10")]
    bars += [(intra, out["bytes_best_intra"], None), (inter, out["bytes_best_inter"], None)]
    figure = output_dir("compression") / "fig10_bytes_per_grid.png"
    _plot(figure, bars)
    progress(f"wrote {figure}")
    headline = [f"bytes_{c}" for c in ("zlib", "rle", "rle_zlib", "magic4")] + [
        "bytes_best_intra",
        "bytes_best_inter",
        "ratio_intra_vs_magic4",
        "ratio_inter_vs_magic4",
        "ratio_magic4_vs_zlib",
        "roundtrip_exact",
        "grids_per_s",
        "mean_grid_pixels",
    ]
    return {k: out[k] for k in headline} | {k: v for k, v in out.items() if k not in headline}
