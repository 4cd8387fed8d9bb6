"""The binary range coder: exact round trips, identical bytes to the Python reference,
near-Shannon efficiency and tight termination."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from compression.binary_coder import (
    PROB_ONE,
    ReferenceDecoder,
    ReferenceEncoder,
    decode_bits,
    encode_bits,
)


def reference_encode(bits: np.ndarray, p0: np.ndarray) -> bytes:
    enc = ReferenceEncoder()
    for b, p in zip(bits.tolist(), p0.tolist(), strict=True):
        enc.encode(b, p)
    return enc.finish()


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(st.integers(0, 1), st.integers(1, PROB_ONE - 1)), max_size=400),
)
def test_compiled_equals_reference_and_round_trips(pairs: list[tuple[int, int]]) -> None:
    bits = np.array([b for b, _ in pairs], dtype=np.uint8)
    p0 = np.array([p for _, p in pairs], dtype=np.int64)
    data = encode_bits(bits, p0)
    assert data == reference_encode(bits, p0)
    assert np.array_equal(decode_bits(data, p0), bits)
    dec = ReferenceDecoder(data)
    assert [dec.decode(int(p)) for p in p0] == bits.tolist()


@pytest.mark.parametrize("p1", [0.5, 0.1, 0.01, 0.001])
def test_efficiency_near_the_entropy(p1: float) -> None:
    rng = np.random.default_rng(1)
    n = 200_000
    bits = (rng.random(n) < p1).astype(np.uint8)
    p0 = np.full(n, round((1 - p1) * PROB_ONE), dtype=np.int64)
    data = encode_bits(bits, p0)
    ideal_bytes = (-(bits.sum() * math.log2(p1) + (n - bits.sum()) * math.log2(1 - p1))) / 8
    assert len(data) <= ideal_bytes * 1.002 + 4
    assert np.array_equal(decode_bits(data, p0), bits)


def test_termination_is_tight() -> None:
    # a certain stream (p0 near 1, all zeros) costs almost nothing, even for many bits
    bits = np.zeros(10_000, dtype=np.uint8)
    p0 = np.full(10_000, PROB_ONE - 1, dtype=np.int64)
    assert len(encode_bits(bits, p0)) <= 2
    assert encode_bits(np.zeros(0, np.uint8), np.zeros(0, np.int64)) == b""


def test_bad_arguments_raise() -> None:
    with pytest.raises(ValueError, match="0 and 1"):
        encode_bits(np.array([2], np.uint8), np.array([100]))
    with pytest.raises(ValueError, match=r"\[1, 65535\]"):
        encode_bits(np.array([1], np.uint8), np.array([0]))
    with pytest.raises(ValueError, match="shape"):
        encode_bits(np.array([1, 0], np.uint8), np.array([100]))


def test_decoding_garbage_never_fails_or_reads_out_of_bounds() -> None:
    rng = np.random.default_rng(5)
    for _ in range(50):
        data = rng.integers(0, 256, rng.integers(0, 20)).astype(np.uint8).tobytes()
        p0 = rng.integers(1, PROB_ONE, 300)
        bits = decode_bits(data, p0)
        assert bits.shape == (300,) and set(np.unique(bits)) <= {0, 1}
