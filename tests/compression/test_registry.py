"""The codec registry, its header and the zlib codec: exact round trips and hostile streams."""

from __future__ import annotations

import zlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from compression import (
    MAX_GRID_CELLS,
    CodecError,
    GridReference,
    codec_names,
    decode_grid,
    decode_grid_with_header,
    encode_grid,
    origin_cells_of,
    read_header,
)


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


@pytest.mark.parametrize(
    "shape, origin",
    [((0, 0), (0, 0)), ((90, 130), (-75, -20)), ((150, 150), (-75, -75)), ((3, 300), (5000, -7))],
)
def test_header_carries_size_and_origin(shape: tuple[int, int], origin: tuple[int, int]) -> None:
    data = encode_grid(np.zeros(shape, bool), "zlib", origin_cells=origin)
    hdr = read_header(data)
    assert (hdr.codec, hdr.height, hdr.width) == ("zlib", *shape)
    assert hdr.origin_cells == origin and hdr.reference_node is None
    grid, hdr2 = decode_grid_with_header(data)
    assert grid.shape == shape and hdr2 == hdr


def test_header_is_small_for_robot_grids() -> None:
    """A cropped robot grid (about 100 x 100 around the robot) costs 6 header bytes."""
    data = encode_grid(np.zeros((100, 120), bool), "rle", origin_cells=(-70, -40))
    assert read_header(data).size == 6


def test_origin_cells_of_metres() -> None:
    assert origin_cells_of((-7.5, -7.2), 0.1) == (-75, -72)
    assert origin_cells_of((float(np.float32(-7.5 + 3 * 0.1)), 0.0), float(np.float32(0.1))) == (
        -72,
        0,
    )
    with pytest.raises(CodecError, match="whole number"):
        origin_cells_of((0.05, 0.0), 0.1)
    with pytest.raises(CodecError, match="resolution"):
        origin_cells_of((0.0, 0.0), 0.0)


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
    with pytest.raises(CodecError, match="origin_cells"):
        encode_grid(np.zeros((2, 2), bool), origin_cells=(1 << 30, 0))
    with pytest.raises(CodecError, match="two integers"):
        encode_grid(np.zeros((2, 2), bool), origin_cells=("a", 0))  # type: ignore[arg-type]


def test_hostile_streams_give_codec_errors() -> None:
    good = encode_grid(np.eye(20, dtype=bool))
    with pytest.raises(CodecError, match="shorter than"):
        decode_grid(good[:1])
    with pytest.raises(CodecError, match="ends inside the header's height"):
        decode_grid(good[:3])
    with pytest.raises(CodecError, match="unknown codec id 200"):
        decode_grid(bytes([200]) + good[1:])
    with pytest.raises(CodecError, match="model version 9, this build has 0"):
        decode_grid(good[:1] + bytes([9]) + good[2:])
    huge = bytes([1, 0, 0xFF, 0xFF, 0x03, 0xFF, 0xFF, 0x03, 0, 0])  # claims 65535 x 65535
    with pytest.raises(CodecError, match="more than"):
        decode_grid(huge)
    with pytest.raises(CodecError, match="longer than 4 bytes"):
        decode_grid(bytes([1, 0]) + b"\xff" * 8)
    bomb = zlib.compress(bytes(10_000_000), 9)  # claims 20x20, inflates to 10 MB
    with pytest.raises(CodecError, match="exactly 50 bytes"):
        decode_grid(good[:6] + bomb)
    with pytest.raises(CodecError):
        decode_grid(good[:-4])
    assert MAX_GRID_CELLS == 1024 * 1024


def test_reference_checks() -> None:
    ref = GridReference(3, np.eye(5, dtype=bool), (0, 0), (0.1, 0.0, 0.0), 0.1)
    data = encode_grid(np.eye(5, dtype=bool), "inter16", reference=ref)
    assert read_header(data).reference_node == 3
    with pytest.raises(CodecError, match="coded against node 3 .* needs that grid"):
        decode_grid(data)
    other = GridReference(4, ref.grid, (0, 0), (0.1, 0.0, 0.0), 0.1)
    with pytest.raises(CodecError, match="coded against node 3 .* reference given is node 4"):
        decode_grid(data, reference=other)
    bad = GridReference(3, ref.grid, (0, 0), (float("nan"), 0.0, 0.0), 0.1)
    with pytest.raises(CodecError, match="finite"):
        encode_grid(ref.grid, "inter16", reference=bad)
    with pytest.raises(CodecError, match="reference grid must be 2-D"):
        encode_grid(ref.grid, "inter16", reference=GridReference(3, np.zeros(3), (0, 0), (0, 0, 0)))


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64))
def test_random_bytes_only_raise_codec_error(data: bytes) -> None:
    try:
        grid = decode_grid(bytes([1, 0]) + data)
    except CodecError:
        return
    assert grid.dtype == bool and grid.size <= MAX_GRID_CELLS
