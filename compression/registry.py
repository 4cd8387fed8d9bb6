"""The codec registry and the stream header every codec shares (paper 4.3.4).

A compressed grid is ``header + body``. The header (little-endian, 8 bytes) is

    codec_id u8 | model_version u8 | width u16 | height u16 | reserved u16 (0)

and the grid's origin and resolution travel in the :class:`~protocol.messages.TerrainGrid`
message around it. Codecs register by name and id; ``decode_grid`` dispatches on the header,
refuses unknown codecs and wrong model versions with a clear :class:`CodecError`, and never
allocates more than :data:`MAX_GRID_CELLS` cells, whatever the bytes claim.

The only codec here is ``zlib`` (bits packed row-major, zlib level 9): the paper's baseline and
the default until the context-model arithmetic coders of issue 5 replace it.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "MAX_GRID_CELLS",
    "CodecError",
    "codec_names",
    "decode_grid",
    "encode_grid",
    "register_codec",
]

#: Largest grid any codec decodes: 1024 x 1024 cells (a 100 m square at 10 cm).
MAX_GRID_CELLS = 1024 * 1024
_HEADER = struct.Struct("<BBHHH")


class CodecError(ValueError):
    """A grid could not be encoded, or bytes could not be decoded; the text says why."""


@dataclass(frozen=True)
class _Codec:
    name: str
    codec_id: int
    model_version: int
    encode: Callable[[np.ndarray], bytes]  # bool grid -> body
    decode: Callable[[bytes, int, int], np.ndarray]  # body, height, width -> bool grid


_BY_NAME: dict[str, _Codec] = {}
_BY_ID: dict[int, _Codec] = {}


def register_codec(
    name: str,
    codec_id: int,
    *,
    encode: Callable[[np.ndarray], bytes],
    decode: Callable[[bytes, int, int], np.ndarray],
    model_version: int = 0,
) -> None:
    """Make a codec available by ``name`` and header ``codec_id`` (0-255, unique)."""
    if not 0 <= codec_id <= 255:
        raise ValueError(f"codec id must be in 0..255, got {codec_id}")
    if name in _BY_NAME or codec_id in _BY_ID:
        raise ValueError(f"codec {name!r} / id {codec_id} is already registered")
    codec = _Codec(name, codec_id, model_version, encode, decode)
    _BY_NAME[name] = codec
    _BY_ID[codec_id] = codec


def codec_names() -> list[str]:
    return sorted(_BY_NAME)


def _check_grid(grid: np.ndarray) -> np.ndarray:
    g = np.asarray(grid)
    if g.ndim != 2:
        raise CodecError(f"grid must be 2-D, got shape {g.shape}")
    h, w = g.shape
    if h > 0xFFFF or w > 0xFFFF or h * w > MAX_GRID_CELLS:
        raise CodecError(f"grid {h}x{w} exceeds the maximum of {MAX_GRID_CELLS} cells")
    if g.dtype != np.bool_:
        if not np.all((g == 0) | (g == 1)):
            raise CodecError("grid must be binary (bool or 0/1)")
        g = g.astype(bool)
    return g


def encode_grid(grid: np.ndarray, codec: str = "zlib") -> bytes:
    """Compress a binary grid ``(height, width)`` with the named codec (header included)."""
    c = _BY_NAME.get(codec)
    if c is None:
        raise CodecError(f"unknown codec {codec!r}; known: {', '.join(codec_names())}")
    g = _check_grid(grid)
    h, w = g.shape
    return _HEADER.pack(c.codec_id, c.model_version, w, h, 0) + c.encode(g)


def decode_grid(data: bytes) -> np.ndarray:
    """Decompress bytes made by :func:`encode_grid`; any problem raises :class:`CodecError`."""
    if len(data) < _HEADER.size:
        raise CodecError(
            f"stream of {len(data)} bytes is shorter than the {_HEADER.size}-byte header"
        )
    codec_id, version, w, h, reserved = _HEADER.unpack_from(data)
    c = _BY_ID.get(codec_id)
    if c is None:
        raise CodecError(f"unknown codec id {codec_id}")
    if version != c.model_version:
        raise CodecError(
            f"codec {c.name!r} model version {version}, this build has {c.model_version}"
        )
    if reserved != 0:
        raise CodecError("reserved header field is not zero")
    if h * w > MAX_GRID_CELLS:
        raise CodecError(f"header claims a {h}x{w} grid, more than {MAX_GRID_CELLS} cells")
    try:
        grid = c.decode(bytes(data[_HEADER.size :]), h, w)
    except CodecError:
        raise
    except Exception as err:  # noqa: BLE001 - a codec's failure on bad bytes is a CodecError
        raise CodecError(f"codec {c.name!r}: corrupt stream: {err}") from None
    if grid.shape != (h, w):
        raise CodecError(f"codec {c.name!r} produced {grid.shape}, header says {(h, w)}")
    return grid


def _zlib_encode(grid: np.ndarray) -> bytes:
    return zlib.compress(np.packbits(grid, axis=None).tobytes(), 9)


def _zlib_decode(body: bytes, h: int, w: int) -> np.ndarray:
    nbytes = (h * w + 7) // 8
    d = zlib.decompressobj()
    packed = d.decompress(body, nbytes + 1)  # bounded: a zip bomb cannot allocate more
    if len(packed) != nbytes or d.unconsumed_tail or not d.eof:
        raise CodecError(f"zlib body does not hold exactly {nbytes} bytes of packed bits")
    bits = np.unpackbits(np.frombuffer(packed, dtype=np.uint8), count=h * w)
    return bits.reshape(h, w).astype(bool)


register_codec("zlib", 1, encode=_zlib_encode, decode=_zlib_decode)
