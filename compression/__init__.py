"""Lossless codecs for binary terrain grids (paper 4.3.4): one API, codecs registered by name.

``encode_grid(grid, codec="zlib")`` and ``decode_grid(data)`` are what the robot node and the
GCS use; the stream's header says which codec made it, so the GCS decodes any of them.
"""

import compression.codecs  # noqa: F401 - registers the shipped codecs
from compression.registry import (
    MAX_GRID_CELLS,
    CodecError,
    codec_names,
    decode_grid,
    encode_grid,
    register_codec,
)

__all__ = [
    "MAX_GRID_CELLS",
    "CodecError",
    "codec_names",
    "decode_grid",
    "encode_grid",
    "register_codec",
]
