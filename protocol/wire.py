"""Wire encoding shared by every message family: msgpack arrays via msgspec.

Three things msgspec does not do on its own live here:

* **float32 on the wire.** Radio bandwidth is scarce (paper 4.1), so quantities whose precision
  allows it travel as msgpack float32 (5 bytes instead of 9). Such fields hold :class:`f32`
  values, a ``float`` subclass already rounded to float32, so a decoded message compares equal
  to the one that was sent.
* **numpy arrays** (sensor frames) travel as a msgpack extension: dtype code, ndim, shape as
  uint32 little-endian, then the raw little-endian data. Decoded arrays are read-only views.
* **errors that name fields.** msgspec reports array-like structs by index (``$[2][3]``);
  :func:`describe_path` maps that back to ``TerrainGrid.data`` using the declared types.

Every decoding failure, whatever its cause, surfaces as :class:`ProtocolError`.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Iterable
from typing import Any

import msgspec
import numpy as np
from msgspec import inspect as mi

__all__ = [
    "MAX_ARRAY_BYTES",
    "PROTOCOL_VERSION",
    "ProtocolError",
    "check_array",
    "dec_hook",
    "describe_path",
    "enc_hook",
    "ext_hook",
    "f32",
    "f32s",
]

#: Bumped whenever a message layout changes; a frame of another version is refused.
PROTOCOL_VERSION = 3

#: Largest numpy array a frame may carry (a 3D sweep of 50k points is 600 kB; an image 230 kB).
MAX_ARRAY_BYTES = 64 * 1024 * 1024

_NDARRAY_EXT = 1
_DTYPES: dict[int, np.dtype[Any]] = {
    1: np.dtype("<f4"),
    2: np.dtype("<f8"),
    3: np.dtype("u1"),
    4: np.dtype("i1"),
    5: np.dtype("<u2"),
    6: np.dtype("<i2"),
    7: np.dtype("<u4"),
    8: np.dtype("<i4"),
    9: np.dtype("<i8"),
    10: np.dtype("?"),
}
_DTYPE_CODES = {dt: code for code, dt in _DTYPES.items()}
_MAX_NDIM = 4
_F32 = struct.Struct(">f")


class ProtocolError(ValueError):
    """Bytes or values that do not form a valid message; the text says what and where."""


class f32(float):  # noqa: N801 - named like numpy's scalar types on purpose
    """A float rounded to IEEE single precision, encoded as msgpack float32."""

    __slots__ = ()

    def __new__(cls, value: float = 0.0) -> f32:
        try:
            rounded = _F32.unpack(_F32.pack(value))[0]
        except OverflowError:  # beyond float32's range: IEEE rounding gives an infinity
            rounded = math.copysign(math.inf, value)
        return super().__new__(cls, rounded)


def f32s(values: Iterable[float]) -> tuple[f32, ...]:
    """Round a sequence of numbers to a tuple of :class:`f32`."""
    return tuple(f32(v) for v in values)


def enc_hook(obj: Any) -> Any:
    """msgspec encoding hook: :class:`f32` as float32, numpy arrays as an extension."""
    if type(obj) is f32:
        return msgspec.Raw(b"\xca" + _F32.pack(obj))
    if isinstance(obj, np.ndarray):
        code = _DTYPE_CODES.get(
            obj.dtype.newbyteorder("<") if obj.dtype.byteorder == ">" else obj.dtype
        )
        if code is None or obj.ndim > _MAX_NDIM:
            raise TypeError(f"cannot encode array of dtype {obj.dtype} with {obj.ndim} dimensions")
        data = np.ascontiguousarray(obj, dtype=_DTYPES[code]).tobytes()
        head = struct.pack(f"<BB{obj.ndim}I", code, obj.ndim, *obj.shape)
        return msgspec.msgpack.Ext(_NDARRAY_EXT, head + data)
    if isinstance(obj, np.floating):
        return float(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    raise NotImplementedError(f"cannot encode objects of type {type(obj).__name__}")


def ext_hook(code: int, data: memoryview) -> Any:
    """msgspec extension hook: decode the numpy array extension, refuse anything else."""
    if code != _NDARRAY_EXT:
        raise ProtocolError(f"unknown msgpack extension type {code}")
    if len(data) < 2:
        raise ProtocolError("array extension shorter than its header")
    dtype = _DTYPES.get(data[0])
    ndim = data[1]
    if dtype is None:
        raise ProtocolError(f"array extension has unknown dtype code {data[0]}")
    if ndim > _MAX_NDIM:
        raise ProtocolError(f"array extension has {ndim} dimensions, at most {_MAX_NDIM} allowed")
    end = 2 + 4 * ndim
    if len(data) < end:
        raise ProtocolError("array extension shorter than its shape")
    shape = struct.unpack_from(f"<{ndim}I", data, 2)
    count = 1
    for n in shape:
        count *= n
    nbytes = count * dtype.itemsize
    if nbytes > MAX_ARRAY_BYTES:
        raise ProtocolError(f"array of shape {shape} exceeds {MAX_ARRAY_BYTES} bytes")
    if len(data) - end != nbytes:
        raise ProtocolError(
            f"array of shape {shape} and dtype {dtype} needs {nbytes} bytes, got {len(data) - end}"
        )
    return np.frombuffer(data[end:], dtype=dtype).reshape(shape)


def dec_hook(type_: type, obj: Any) -> Any:
    """msgspec decoding hook: accept arrays produced by :func:`ext_hook` for ndarray fields."""
    if type_ is np.ndarray:
        if isinstance(obj, np.ndarray):
            return obj
        raise ValueError(f"expected array, got {type(obj).__name__}")
    raise NotImplementedError(f"cannot decode type {type_}")


def check_array(name: str, arr: Any, dtype: str, shape: tuple[int | None, ...]) -> np.ndarray:
    """Validate ``arr``'s dtype and shape (``None`` = any length); raise ``ValueError`` naming it.

    Used in ``__post_init__`` so the same check runs at construction and on decoding.
    """
    if not isinstance(arr, np.ndarray):
        raise ValueError(f"{name}: expected a numpy array, got {type(arr).__name__}")
    if arr.dtype != np.dtype(dtype):
        raise ValueError(f"{name}: expected dtype {np.dtype(dtype)}, got {arr.dtype}")
    if arr.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(arr.shape, shape, strict=True)
    ):
        want_txt = "(" + ", ".join("N" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"{name}: expected shape {want_txt}, got {arr.shape}")
    return arr


def _parse_path(path: str) -> list[int | str]:
    """``[2][3].x[1]`` -> ``[2, 3, 'x', 1]``."""
    out: list[int | str] = []
    i = 0
    while i < len(path):
        if path[i] == "[":
            j = path.index("]", i)
            out.append(int(path[i + 1 : j]))
            i = j + 1
        elif path[i] == ".":
            j = i + 1
            while j < len(path) and path[j] not in ".[":
                j += 1
            out.append(path[i + 1 : j])
            i = j
        else:
            break
    return out


def _struct_for(tinfo: mi.Type, raw: Any) -> mi.StructType | None:
    """The struct type that ``raw`` (generically decoded) is an instance of, if determinable."""
    if isinstance(tinfo, mi.StructType):
        return tinfo
    if isinstance(tinfo, mi.UnionType) and isinstance(raw, list) and raw:
        for t in tinfo.types:
            if isinstance(t, mi.StructType) and t.tag == raw[0]:
                return t
    return None


def describe_path(root: type, raw: Any, path: str) -> str:
    """Name the field that msgspec's ``$``-relative ``path`` points at, e.g. ``TerrainGrid.data``.

    ``raw`` is the same bytes decoded without a type (plain lists), used to read union tags.
    Falls back to the raw path where the structure does not match the declared types.
    """
    tinfo: mi.Type = mi.type_info(root)
    name = ""
    for step in _parse_path(path):
        if isinstance(tinfo, mi.ListType | mi.VarTupleType):
            name += f"[{step}]"
            tinfo = tinfo.item_type
            raw = (
                raw[step]
                if isinstance(raw, list) and isinstance(step, int) and step < len(raw)
                else None
            )
            continue
        if isinstance(tinfo, mi.TupleType) and isinstance(step, int):
            name += f"[{step}]"
            tinfo = tinfo.item_types[step] if step < len(tinfo.item_types) else mi.AnyType()
            raw = raw[step] if isinstance(raw, list) and step < len(raw) else None
            continue
        st = _struct_for(tinfo, raw)
        if st is None or not isinstance(step, int):
            return f"{name or root.__name__}{''.join(f'[{s}]' for s in [step])}"
        offset = 1 if st.tag is not None else 0
        idx = step - offset
        if idx < 0:
            name = f"{st.cls.__name__} tag"
            break
        if idx >= len(st.fields):
            return f"{st.cls.__name__}[{step}]"
        field = st.fields[idx]
        name = f"{st.cls.__name__}.{field.name}" if (not name or offset) else f"{name}.{field.name}"
        tinfo = field.type
        raw = raw[step] if isinstance(raw, list) and step < len(raw) else None
    return name or root.__name__
