"""The reference warp: integer arithmetic pinned by its sine table, the float32 rounding of the
pose, and the geometry of the feature (checked against a float warp of cell centres)."""

from __future__ import annotations

import math
import zlib

import numpy as np
import pytest

from compression.reference_warp import (
    SINE_TABLE_CHECKSUM,
    quantize_pose,
    reference_code,
    sine_table,
)


def test_sine_table_is_pinned() -> None:
    """Streams depend on this table bit for bit: it must be the same on every platform."""
    table = sine_table()
    assert table[0] == 0 and table[16384] == 65536 and table[32768] == 0
    assert table[49152] == -65536
    assert zlib.crc32(table.tobytes()) == SINE_TABLE_CHECKSUM == 2860823005


def test_pose_is_rounded_to_float32_then_quantized() -> None:
    x = 0.123456789
    assert quantize_pose((x, 0.0, 0.0), 0.1) == quantize_pose((float(np.float32(x)), 0, 0), 0.1)
    assert quantize_pose((0.1, -0.2, math.pi / 2), 0.1) == (256, -512, 16384)
    assert quantize_pose((0.0, 0.0, -math.pi / 2), 0.1)[2] == 49152
    with pytest.raises(ValueError, match="absurdly far"):
        quantize_pose((1e30, 0.0, 0.0), 0.1)


def test_identity_marks_each_cell_and_its_neighbours() -> None:
    ref = np.zeros((5, 6), bool)
    ref[2, 3] = True
    code = reference_code(ref, (0, 0), (0, 0, 0), (0, 0), 5, 6)
    expected = np.zeros((5, 6), np.uint8)
    expected[1:4, 2:5] = 1
    expected[2, 3] = 2
    assert np.array_equal(code, expected)


def test_translation_and_origins_shift_the_reference() -> None:
    ref = np.zeros((10, 10), bool)
    ref[4, 6] = True  # cell centre in the reference base: ((2 + 6.5), (-1 + 4.5)) cells
    # the current node is 3 cells ahead (+x) of the reference node: the cell is 3 cells back
    code = reference_code(ref, (2, -1), quantize_pose((0.3, 0.0, 0.0), 0.1), (0, 0), 12, 12)
    assert list(zip(*np.nonzero(code == 2), strict=True)) == [(3, 5)]


def test_rotation_matches_a_float_warp() -> None:
    rng = np.random.default_rng(0)
    ref = rng.random((40, 50)) < 0.05
    pose = (0.83, -0.41, 0.7)
    code = reference_code(ref, (-20, -25), quantize_pose(pose, 0.1), (-30, -30), 60, 60)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    hits = 0
    for r, q in zip(*np.nonzero(ref), strict=True):
        x, y = (q - 20 + 0.5) * 0.1 - pose[0], (r - 25 + 0.5) * 0.1 - pose[1]
        col = math.floor((c * x + s * y) / 0.1) + 30
        row = math.floor((-s * x + c * y) / 0.1) + 30
        if 0 <= row < 60 and 0 <= col < 60:
            hits += 1
            assert code[row, col] >= 1  # the float warp lands within the fixed-point one's reach
    assert hits > 50 and (code == 2).sum() <= ref.sum()


def test_far_away_reference_gives_nothing() -> None:
    ref = np.ones((5, 5), bool)
    code = reference_code(ref, (0, 0), quantize_pose((50.0, 0.0, 0.0), 0.1), (0, 0), 8, 8)
    assert not code.any()
