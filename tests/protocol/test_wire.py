"""Wire encoding: f32, the numpy array extension, hooks, array checks and field-naming paths."""

from __future__ import annotations

import math
import struct
import tracemalloc
from typing import Any

import msgspec
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from protocol.wire import (
    MAX_ARRAY_BYTES,
    ProtocolError,
    check_array,
    dec_hook,
    describe_path,
    enc_hook,
    ext_hook,
    f32,
    f32s,
)

ENCODER = msgspec.msgpack.Encoder(enc_hook=enc_hook)
DTYPES = ["<f4", "<f8", "u1", "i1", "<u2", "<i2", "<u4", "<i4", "<i8", "?"]


def r32(v: float) -> float:
    with np.errstate(over="ignore"):
        return float(np.float32(v))


def roundtrip(obj: Any) -> Any:
    return msgspec.msgpack.decode(ENCODER.encode(obj), ext_hook=ext_hook)


# ----------------------------------------------------------------------------- f32


@settings(max_examples=200, deadline=None)
@given(x=st.floats(allow_nan=False))
def test_f32_is_the_float32_rounding(x: float) -> None:
    v = f32(x)
    assert type(v) is f32
    assert v == r32(x)
    assert f32(v) == v  # idempotent
    wire = ENCODER.encode(v)
    assert wire == b"\xca" + struct.pack(">f", r32(x))
    assert msgspec.msgpack.decode(wire) == v


@settings(max_examples=100, deadline=None)
@given(x=st.floats(width=32, allow_nan=False))
def test_f32_keeps_float32_values_exactly(x: float) -> None:
    assert f32(x) == x


def test_f32_edges() -> None:
    assert f32(1e300) == math.inf and f32(-1e300) == -math.inf  # IEEE rounding overflows to inf
    assert f32(3.4028235e38) == 3.4028234663852886e38  # float32 max stays finite
    assert f32(1e-50) == 0.0
    assert math.isnan(f32(math.nan))
    assert f32(0.1) == 0.10000000149011612
    assert f32() == 0.0
    assert f32s([1, 0.1, -2.5]) == (1.0, 0.10000000149011612, -2.5)
    assert all(type(v) is f32 for v in f32s(range(3)))
    assert ENCODER.encode(f32(math.inf)) == b"\xca\x7f\x80\x00\x00"


def test_plain_floats_and_numpy_scalars_encode() -> None:
    assert ENCODER.encode(0.1) == b"\xcb" + struct.pack(">d", 0.1)
    assert msgspec.msgpack.decode(ENCODER.encode([np.float32(0.5), np.int64(-3)])) == [0.5, -3]
    with pytest.raises(NotImplementedError, match="cannot encode objects of type object"):
        enc_hook(object())


# ----------------------------------------------------------------------------- arrays


@settings(max_examples=100, deadline=None)
@given(
    arr=st.sampled_from(DTYPES).flatmap(
        lambda dt: hnp.arrays(
            np.dtype(dt), hnp.array_shapes(min_dims=0, max_dims=4, min_side=0, max_side=4)
        )
    )
)
def test_arrays_round_trip_exactly(arr: np.ndarray) -> None:
    back = roundtrip(arr)
    assert isinstance(back, np.ndarray)
    assert back.dtype == arr.dtype and back.shape == arr.shape
    assert back.tobytes() == arr.tobytes()
    assert not back.flags.writeable


def test_array_wire_layout() -> None:
    arr = np.array([[1, 2, 3], [4, 5, 6]], dtype="<i2")
    wire = ENCODER.encode(arr)
    head = struct.pack("<BB2I", 6, 2, 2, 3)
    payload = head + arr.tobytes()
    assert wire == b"\xc7" + bytes([len(payload), 1]) + payload


@pytest.mark.parametrize(
    "arr",
    [
        np.arange(12, dtype=">f8").reshape(3, 4),  # big-endian
        np.arange(24, dtype=np.int32).reshape(4, 6)[::2, 1::2],  # strided
        np.asfortranarray(np.arange(6, dtype=np.float32).reshape(2, 3)),  # column-major
        np.array(7.5, dtype=np.float64),  # 0-d
        np.zeros((0, 3), dtype=np.float32),  # empty
    ],
    ids=["big-endian", "strided", "fortran", "0-d", "empty"],
)
def test_unusual_layouts_round_trip_by_value(arr: np.ndarray) -> None:
    back = roundtrip(arr)
    assert back.dtype == arr.dtype.newbyteorder("<") if arr.dtype.byteorder == ">" else arr.dtype
    assert back.shape == arr.shape
    np.testing.assert_array_equal(back, arr)


@pytest.mark.parametrize(
    ("arr", "match"),
    [
        (np.zeros(3, dtype=np.complex64), "cannot encode array of dtype complex64"),
        (np.zeros(3, dtype=np.float16), "cannot encode array of dtype float16"),
        (np.zeros((1,) * 5, dtype=np.float32), "with 5 dimensions"),
        (np.array(["a"]), "cannot encode array of dtype <U1"),
    ],
)
def test_unsupported_arrays_are_refused(arr: np.ndarray, match: str) -> None:
    with pytest.raises(TypeError, match=match):
        ENCODER.encode(arr)


def _ext(code: int, ndim: int, shape: tuple[int, ...], nbytes: int) -> bytes:
    return struct.pack(f"<BB{len(shape)}I", code, ndim, *shape) + bytes(nbytes)


@pytest.mark.parametrize(
    ("ext_code", "data", "expected"),
    [
        (2, _ext(1, 1, (1,), 4), "unknown msgpack extension type 2"),
        (1, b"", "array extension shorter than its header"),
        (1, b"\x01", "array extension shorter than its header"),
        (1, _ext(0, 1, (1,), 4), "array extension has unknown dtype code 0"),
        (1, _ext(11, 1, (1,), 4), "array extension has unknown dtype code 11"),
        (1, _ext(1, 5, (1,) * 5, 4), "array extension has 5 dimensions, at most 4 allowed"),
        (1, _ext(1, 255, (), 0), "array extension has 255 dimensions, at most 4 allowed"),
        (1, _ext(1, 3, (2, 2), 3), "array extension shorter than its shape"),
        (
            1,
            _ext(1, 2, (2, 3), 23),
            "array of shape (2, 3) and dtype float32 needs 24 bytes, got 23",
        ),
        (
            1,
            _ext(1, 2, (2, 3), 25),
            "array of shape (2, 3) and dtype float32 needs 24 bytes, got 25",
        ),
        (1, _ext(1, 1, (0,), 1), "array of shape (0,) and dtype float32 needs 0 bytes, got 1"),
        (
            1,
            _ext(2, 4, (2**32 - 1,) * 4, 8),
            f"array of shape {(2**32 - 1,) * 4} exceeds {MAX_ARRAY_BYTES} bytes",
        ),
        (
            1,
            _ext(3, 1, (MAX_ARRAY_BYTES + 1,), 0),
            f"array of shape ({MAX_ARRAY_BYTES + 1},) exceeds {MAX_ARRAY_BYTES} bytes",
        ),
    ],
)
def test_hostile_extensions_are_refused_without_allocating(
    ext_code: int, data: bytes, expected: str
) -> None:
    wire = msgspec.msgpack.encode(msgspec.msgpack.Ext(ext_code, data))
    tracemalloc.start()
    try:
        with pytest.raises(ProtocolError) as info:
            msgspec.msgpack.decode(wire, ext_hook=ext_hook)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert str(info.value) == expected
    assert peak < 1_000_000


def test_largest_allowed_array_is_accepted() -> None:
    data = struct.pack("<BBI", 3, 1, 1024) + bytes(1024)
    arr = ext_hook(1, memoryview(data))
    assert arr.shape == (1024,) and arr.dtype == np.uint8 and not arr.any()


def test_dec_hook() -> None:
    arr = np.zeros(2)
    assert dec_hook(np.ndarray, arr) is arr
    with pytest.raises(ValueError, match="^expected array, got list$"):
        dec_hook(np.ndarray, [1, 2])
    with pytest.raises(NotImplementedError, match="cannot decode type"):
        dec_hook(complex, 1)


# ----------------------------------------------------------------------------- check_array


def test_check_array_accepts_and_returns() -> None:
    arr = np.zeros((5, 3), dtype=np.float32)
    assert check_array("S.points", arr, "float32", (None, 3)) is arr
    assert check_array("S.points", np.zeros((0, 3), np.float32), "float32", (None, 3)).size == 0


@pytest.mark.parametrize(
    ("arr", "expected"),
    [
        ([[0.0, 0.0, 0.0]], "S.points: expected a numpy array, got list"),
        (np.zeros((5, 3)), "S.points: expected dtype float32, got float64"),
        (np.zeros((5, 2), np.float32), "S.points: expected shape (N, 3), got (5, 2)"),
        (np.zeros(15, np.float32), "S.points: expected shape (N, 3), got (15,)"),
        (np.zeros((1, 5, 3), np.float32), "S.points: expected shape (N, 3), got (1, 5, 3)"),
    ],
)
def test_check_array_names_the_field(arr: Any, expected: str) -> None:
    with pytest.raises(ValueError) as info:
        check_array("S.points", arr, "float32", (None, 3))
    assert str(info.value) == expected


# ----------------------------------------------------------------------------- describe_path


class Leaf(msgspec.Struct, array_like=True):
    a: int
    b: list[tuple[float, float]]


class Tagged(msgspec.Struct, array_like=True, tag=7):
    leaves: list[Leaf]
    name: str


class Other(msgspec.Struct, array_like=True, tag=8):
    x: int


class Root(msgspec.Struct, array_like=True):
    version: int
    body: Tagged | Other


@pytest.mark.parametrize(
    ("raw", "path", "expected"),
    [
        ([1, [7, [], "n"]], "[0]", "Root.version"),
        ([1, [7, [], "n"]], "[1]", "Root.body"),
        ([1, [7, [], "n"]], "[1][2]", "Tagged.name"),
        ([1, [7, [[1, []], [2, []]], "n"]], "[1][1][1][0]", "Tagged.leaves[1].a"),
        ([1, [7, [[1, [[0, 0]]]], "n"]], "[1][1][0][1][0][1]", "Tagged.leaves[0].b[0][1]"),
        ([1, [8, 5]], "[1][1]", "Other.x"),
        ([1, [8, 5]], "[1][0]", "Other tag"),
        ([1, [9, 5]], "[1][1]", "Root.body[1]"),  # unknown tag: falls back to the raw path
        ([1, [8, 5, 6]], "[1][2]", "Other[2]"),
    ],
)
def test_describe_path(raw: Any, path: str, expected: str) -> None:
    assert describe_path(Root, raw, path) == expected


def test_describe_path_matches_msgspec_paths() -> None:
    wire = msgspec.msgpack.encode([1, [7, [[1, [[0.0, 0.0]]], [2, [[0.0, "y"]]]], "n"]])
    with pytest.raises(msgspec.ValidationError) as info:
        msgspec.msgpack.decode(wire, type=Root)
    path = str(info.value).rpartition(" - at `$")[2].rstrip("`")
    assert describe_path(Root, msgspec.msgpack.decode(wire), path) == "Tagged.leaves[1].b[0][1]"
