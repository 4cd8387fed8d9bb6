"""The codec registry and the stream header every codec shares (paper 4.3.4).

A compressed grid is ``header + body``. The header is byte-aligned and small (6-8 bytes for a
robot's ~100 x 100 grid):

    codec_id u8 | model_version u8 | width varint | height varint
    | centre_col svarint | centre_row svarint | [reference u8 (inter-frame codecs only)]

``varint`` is unsigned LEB128 (at most 3 bytes here), ``svarint`` a zigzag LEB128. The grid's
origin travels as the *centre* of the grid in cells, ``origin_cells + size // 2``, which is
small (one byte) for a grid around the robot: cell ``(row, col)`` covers
``(origin_cells + (col, row)) * resolution_m`` in the node's ``base`` frame. The resolution is
not in the stream (the :class:`~protocol.messages.TerrainGrid` message carries it).

Codecs register by name and id. *Intra* codecs code a grid alone; *inter-frame* codecs also
use a :class:`GridReference` (the robot's previous grid, paper 4.3.4 has no such codec), and
their header ends with the reference's node index modulo 256, so the receiver knows which
grid it needs (a robot references one of its last few nodes). ``encode_grid`` with an
inter-frame codec and no reference emits a key frame with that codec's key-frame (intra)
codec. ``decode_grid`` dispatches on the header, refuses
unknown codecs, wrong model versions and a missing or wrong reference with a clear
:class:`CodecError`, and never allocates more than :data:`MAX_GRID_CELLS` cells, whatever the
bytes claim.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "MAX_GRID_CELLS",
    "CodecError",
    "GridHeader",
    "GridReference",
    "codec_names",
    "decode_grid",
    "decode_grid_with_header",
    "encode_grid",
    "is_inter",
    "origin_cells_of",
    "read_header",
    "register_codec",
]

#: Largest grid any codec decodes: 1024 x 1024 cells (a 100 m square at 10 cm).
MAX_GRID_CELLS = 1024 * 1024
_MAX_SIDE = 0xFFFF
_MAX_ORIGIN = 1 << 24  # cells; far beyond any real grid, bounds the varints


class CodecError(ValueError):
    """A grid could not be encoded, or bytes could not be decoded; the text says why."""


@dataclass(frozen=True)
class GridReference:
    """A grid the receiver already has, for inter-frame coding (issue 5).

    ``grid``: the reference grid exactly as the receiver decoded it (bool ``(rows, cols)``);
    ``origin_cells``: its origin ``(col, row)`` in cells in its node's ``base`` frame;
    ``reference_from_current``: the SE(2) pose ``(x_m, y_m, theta_rad)`` of the current node's
    base in the reference node's base (for consecutive nodes, the current
    :class:`~protocol.messages.PoseNode`'s ``odom_delta``); ``resolution_m``: cell size of both
    grids; ``node_index``: the reference's pose node (the stream records it modulo 256).

    The pose and resolution are rounded to float32 (what the radio carries), then to fixed
    point, so that sender and receiver warp the reference identically on any platform.
    """

    node_index: int
    grid: np.ndarray
    origin_cells: tuple[int, int]
    reference_from_current: tuple[float, float, float]
    resolution_m: float = 0.1


@dataclass(frozen=True)
class GridHeader:
    """What a stream's header says: codec, model version, size, origin and reference."""

    codec: str
    codec_id: int
    model_version: int
    width: int
    height: int
    origin_cells: tuple[int, int]  # (col, row) of cell (0, 0) in the node's base, in cells
    reference_node: int | None  # node index (mod 256) of the reference; None: intra
    size: int  # header length in bytes


IntraEncode = Callable[[np.ndarray], bytes]
IntraDecode = Callable[[bytes, int, int], np.ndarray]
InterEncode = Callable[[np.ndarray, tuple[int, int], GridReference], bytes]
InterDecode = Callable[[bytes, int, int, tuple[int, int], GridReference], np.ndarray]


@dataclass(frozen=True)
class _Codec:
    name: str
    codec_id: int
    model_version: int
    encode: Callable[..., bytes]
    decode: Callable[..., np.ndarray]
    key_frame_codec: str | None = None  # set for inter-frame codecs
    description: str = field(default="", compare=False)

    @property
    def inter(self) -> bool:
        return self.key_frame_codec is not None


_BY_NAME: dict[str, _Codec] = {}
_BY_ID: dict[int, _Codec] = {}


def register_codec(
    name: str,
    codec_id: int,
    *,
    encode: IntraEncode | InterEncode,
    decode: IntraDecode | InterDecode,
    model_version: int = 0,
    key_frame_codec: str | None = None,
    description: str = "",
) -> None:
    """Make a codec available by ``name`` and header ``codec_id`` (0-255, unique).

    Intra codecs: ``encode(grid) -> body``, ``decode(body, height, width) -> grid``.
    Inter-frame codecs (``key_frame_codec`` names the intra codec used without a reference):
    ``encode(grid, origin_cells, reference)``, ``decode(body, height, width, origin_cells,
    reference)``. ``model_version`` (0-255) is written in every stream and checked on decoding.
    """
    if not 0 <= codec_id <= 255:
        raise ValueError(f"codec id must be in 0..255, got {codec_id}")
    if not 0 <= model_version <= 255:
        raise ValueError(f"model version must be in 0..255, got {model_version}")
    if name in _BY_NAME or codec_id in _BY_ID:
        raise ValueError(f"codec {name!r} / id {codec_id} is already registered")
    if key_frame_codec is not None:
        key = _BY_NAME.get(key_frame_codec)
        if key is None or key.inter:
            raise ValueError(f"key-frame codec {key_frame_codec!r} must be a registered intra")
    codec = _Codec(name, codec_id, model_version, encode, decode, key_frame_codec, description)
    _BY_NAME[name] = codec
    _BY_ID[codec_id] = codec


def codec_names(*, inter: bool | None = None) -> list[str]:
    """Registered codec names (all, or only the intra / only the inter-frame ones)."""
    return sorted(n for n, c in _BY_NAME.items() if inter is None or c.inter == inter)


def is_inter(codec: str) -> bool:
    """Whether ``codec`` is an inter-frame codec (raises CodecError if unknown)."""
    return _codec(codec).inter


def _codec(name: str) -> _Codec:
    c = _BY_NAME.get(name)
    if c is None:
        raise CodecError(f"unknown codec {name!r}; known: {', '.join(codec_names())}")
    return c


# ---------------------------------------------------------------------------- header


def _put_varint(out: bytearray, v: int) -> None:
    while v >= 0x80:
        out.append((v & 0x7F) | 0x80)
        v >>= 7
    out.append(v)


def _zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def _get_varint(data: bytes, pos: int, what: str) -> tuple[int, int]:
    v = shift = 0
    for i in range(4):  # at most 28 bits
        if pos + i >= len(data):
            raise CodecError(f"stream ends inside the header's {what}")
        byte = data[pos + i]
        v |= (byte & 0x7F) << shift
        if not byte & 0x80:
            return v, pos + i + 1
        shift += 7
    raise CodecError(f"header's {what} is longer than 4 bytes")


def _pack_header(c: _Codec, h: int, w: int, origin: tuple[int, int], ref: int | None) -> bytes:
    out = bytearray((c.codec_id, c.model_version))
    _put_varint(out, w)
    _put_varint(out, h)
    _put_varint(out, _zigzag(origin[0] + w // 2))
    _put_varint(out, _zigzag(origin[1] + h // 2))
    if ref is not None:
        out.append(ref & 0xFF)
    return bytes(out)


def read_header(data: bytes) -> GridHeader:
    """Parse and check a stream's header (codec known, model version, size limits)."""
    if len(data) < 2:
        raise CodecError(f"stream of {len(data)} bytes is shorter than a header")
    codec_id, version = data[0], data[1]
    c = _BY_ID.get(codec_id)
    if c is None:
        raise CodecError(f"unknown codec id {codec_id}")
    if version != c.model_version:
        raise CodecError(
            f"codec {c.name!r} model version {version}, this build has {c.model_version}: "
            "sender and receiver must ship the same model file"
        )
    w, pos = _get_varint(data, 2, "width")
    h, pos = _get_varint(data, pos, "height")
    if h > _MAX_SIDE or w > _MAX_SIDE or h * w > MAX_GRID_CELLS:
        raise CodecError(f"header claims a {h}x{w} grid, more than {MAX_GRID_CELLS} cells")
    zc, pos = _get_varint(data, pos, "origin")
    zr, pos = _get_varint(data, pos, "origin")
    cx = (zc >> 1) ^ -(zc & 1)
    cy = (zr >> 1) ^ -(zr & 1)
    ref = None
    if c.inter:
        if pos >= len(data):
            raise CodecError("stream ends inside the header's reference node")
        ref = data[pos]
        pos += 1
    return GridHeader(c.name, codec_id, version, w, h, (cx - w // 2, cy - h // 2), ref, pos)


# ---------------------------------------------------------------------------- API


def origin_cells_of(origin_in_base: tuple[float, float], resolution_m: float) -> tuple[int, int]:
    """``origin_in_base`` (metres) as whole cells; raises CodecError if it is not on the
    cell lattice (within 1e-3 cell after float32 rounding, as the radio carries it)."""
    res = float(np.float32(resolution_m))
    if not (math.isfinite(res) and res > 0):
        raise CodecError(f"resolution_m must be > 0, got {resolution_m}")
    out = []
    for v in origin_in_base:
        cells = float(np.float32(v)) / res
        k = round(cells)
        if not (math.isfinite(cells) and abs(cells - k) <= 1e-3 * max(1.0, abs(k) / 1000)):
            raise CodecError(f"origin {origin_in_base} is not a whole number of {res} m cells")
        out.append(int(k))
    return out[0], out[1]


def _check_grid(grid: np.ndarray, what: str = "grid") -> np.ndarray:
    g = grid if isinstance(grid, np.ndarray) else np.asarray(grid)
    if g.ndim != 2:
        raise CodecError(f"{what} must be 2-D, got shape {g.shape}")
    h, w = g.shape
    if h > _MAX_SIDE or w > _MAX_SIDE or h * w > MAX_GRID_CELLS:
        raise CodecError(f"{what} {h}x{w} exceeds the maximum of {MAX_GRID_CELLS} cells")
    if g.dtype != np.bool_:
        if not np.all((g == 0) | (g == 1)):
            raise CodecError(f"{what} must be binary (bool or 0/1)")
        g = g.astype(bool)
    return g


def _check_origin(origin_cells: tuple[int, int]) -> tuple[int, int]:
    try:
        ox, oy = (int(v) for v in origin_cells)
    except (TypeError, ValueError):
        raise CodecError(f"origin_cells must be two integers, got {origin_cells!r}") from None
    if abs(ox) > _MAX_ORIGIN or abs(oy) > _MAX_ORIGIN:
        raise CodecError(f"origin_cells {origin_cells} beyond +-{_MAX_ORIGIN} cells")
    return ox, oy


def _check_reference(ref: GridReference) -> GridReference:
    if not isinstance(ref, GridReference):
        raise CodecError(f"reference must be a GridReference, got {type(ref).__name__}")
    try:
        x, y, th = (float(v) for v in ref.reference_from_current)
    except (TypeError, ValueError):
        raise CodecError(
            f"reference_from_current must be 3 numbers, got {ref.reference_from_current!r}"
        ) from None
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(th)):
        raise CodecError(f"reference_from_current must be finite, got {(x, y, th)}")
    res = float(ref.resolution_m)
    if not (math.isfinite(res) and res > 0):
        raise CodecError(f"reference resolution_m must be > 0, got {ref.resolution_m}")
    return GridReference(
        int(ref.node_index),
        _check_grid(ref.grid, "reference grid"),
        _check_origin(ref.origin_cells),
        (x, y, th),
        res,
    )


def encode_grid(
    grid: np.ndarray,
    codec: str = "zlib",
    *,
    origin_cells: tuple[int, int] = (0, 0),
    reference: GridReference | None = None,
) -> bytes:
    """Compress a binary grid ``(height, width)`` with the named codec (header included).

    ``origin_cells`` ``(col, row)``: where cell ``(0, 0)`` lies in the node's base frame, in
    cells (see :func:`origin_cells_of`). With an inter-frame codec, ``reference`` is the grid
    the receiver already has; without one the stream is a key frame of the codec's key-frame
    codec. Intra codecs ignore ``reference``.
    """
    c = _codec(codec)
    g = _check_grid(grid)
    origin = _check_origin(origin_cells)
    h, w = g.shape
    if c.inter and reference is None:
        c = _codec(c.key_frame_codec)  # type: ignore[arg-type]
    if not c.inter:
        return _pack_header(c, h, w, origin, None) + c.encode(g)
    ref = _check_reference(reference)  # type: ignore[arg-type]
    return _pack_header(c, h, w, origin, ref.node_index) + c.encode(g, origin, ref)


def decode_grid_with_header(
    data: bytes, *, reference: GridReference | None = None
) -> tuple[np.ndarray, GridHeader]:
    """Decompress bytes made by :func:`encode_grid`; returns the grid and the header.

    An inter-frame stream needs the ``reference`` it was coded against (same node index
    modulo 256, same grid): without it, or with another node's, CodecError says which node
    is needed. Any problem with the bytes raises :class:`CodecError`.
    """
    data = bytes(data)
    hdr = read_header(data)
    c = _BY_ID[hdr.codec_id]
    h, w = hdr.height, hdr.width
    body = data[hdr.size :]
    try:
        if c.inter:
            if reference is None:
                raise CodecError(
                    f"inter-frame stream coded against node {hdr.reference_node} (mod 256): "
                    "decoding needs that grid as reference"
                )
            ref = _check_reference(reference)
            if ref.node_index & 0xFF != hdr.reference_node:
                raise CodecError(
                    f"inter-frame stream coded against node {hdr.reference_node} (mod 256), "
                    f"reference given is node {ref.node_index}"
                )
            grid = c.decode(body, h, w, hdr.origin_cells, ref)
        else:
            grid = c.decode(body, h, w)
    except CodecError:
        raise
    except Exception as err:  # noqa: BLE001 - a codec's failure on bad bytes is a CodecError
        raise CodecError(f"codec {c.name!r}: corrupt stream: {err}") from None
    if grid.shape != (h, w):
        raise CodecError(f"codec {c.name!r} produced {grid.shape}, header says {(h, w)}")
    return grid, hdr


def decode_grid(data: bytes, *, reference: GridReference | None = None) -> np.ndarray:
    """Decompress bytes made by :func:`encode_grid` (see :func:`decode_grid_with_header`)."""
    return decode_grid_with_header(data, reference=reference)[0]


# ---------------------------------------------------------------------------- zlib


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


register_codec(
    "zlib", 1, encode=_zlib_encode, decode=_zlib_decode, description="packed bits + zlib -9"
)
