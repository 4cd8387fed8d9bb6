"""Lossless codecs for binary terrain grids (paper 4.3.4): one API, codecs registered by name.

``encode_grid(grid, codec, origin_cells=..., reference=...)`` and ``decode_grid(data,
reference=...)`` are what the robot node and the GCS use; the stream's header says which codec
made it (and, for inter-frame codecs, which node's grid it was coded against), so the GCS
decodes any of them. :data:`DEFAULT_CODEC` is the codec that measures best.
"""

import compression.codecs  # noqa: F401 - registers the shipped codecs
from compression.codecs import BEST_INTRA_CODEC, DEFAULT_CODEC, MODEL_VERSION
from compression.registry import (
    MAX_GRID_CELLS,
    CodecError,
    GridHeader,
    GridReference,
    codec_names,
    decode_grid,
    decode_grid_with_header,
    encode_grid,
    is_inter,
    origin_cells_of,
    read_header,
    register_codec,
)

__all__ = [
    "BEST_INTRA_CODEC",
    "DEFAULT_CODEC",
    "MAX_GRID_CELLS",
    "MODEL_VERSION",
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
