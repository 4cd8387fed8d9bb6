"""The codec registry and the zlib codec: exact round trips and hostile streams."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from compression import MAX_GRID_CELLS, CodecError, codec_names, decode_grid, encode_grid


@pytest.mark.parametrize("shape", [(1, 1), (150, 150), (7, 13), (0, 5)])
@pytest.mark.parametrize("fill", ["empty", "full", "one", "random"])
def test_zlib_round_trip_is_exact(shape: tuple[int, int], fill: str) -> None:
    rng = np.random.default_rng(0)
    grid = {
        "empty": np.zeros(shape, bool),
        "full": np.ones(shape, bool),
        "one": np.zeros(shape, bool),
        "random": rng.random(shape) < 0.1,
    }[fill]
    if fill == "one" and grid.size:
        grid[shape[0] // 2, shape[1] // 2] = True
    out = decode_grid(encode_grid(grid, "zlib"))
    assert out.dtype == bool and out.shape == shape and np.array_equal(out, grid)


def test_registry_names_and_errors() -> None:
    assert "zlib" in codec_names()
    with pytest.raises(CodecError, match="unknown codec 'nope'"):
        encode_grid(np.zeros((2, 2), bool), "nope")
    with pytest.raises(CodecError, match="2-D"):
        encode_grid(np.zeros(4, bool))
    with pytest.raises(CodecError, match="binary"):
        encode_grid(np.full((2, 2), 3))
    with pytest.raises(CodecError, match="exceeds"):
        encode_grid(np.zeros((2048, 1024), bool))


def test_hostile_streams_give_codec_errors() -> None:
    good = encode_grid(np.eye(20, dtype=bool))
    with pytest.raises(CodecError, match="shorter than"):
        decode_grid(good[:3])
    with pytest.raises(CodecError, match="unknown codec id 200"):
        decode_grid(bytes([200]) + good[1:])
    with pytest.raises(CodecError, match="model version"):
        decode_grid(good[:1] + bytes([9]) + good[2:])
    with pytest.raises(CodecError, match="more than"):
        decode_grid(good[:2] + (0xFFFF).to_bytes(2, "little") * 2 + good[6:])
    bomb = zlib.compress(bytes(10_000_000), 9)  # claims 20x20, inflates to 10 MB
    with pytest.raises(CodecError, match="exactly 50 bytes"):
        decode_grid(good[:8] + bomb)
    with pytest.raises(CodecError):
        decode_grid(good[:-4])
    assert MAX_GRID_CELLS == 1024 * 1024


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64))
def test_random_bytes_only_raise_codec_error(data: bytes) -> None:
    try:
        grid = decode_grid(bytes([1, 0]) + data)
    except CodecError:
        return
    assert grid.dtype == bool and grid.size <= MAX_GRID_CELLS
