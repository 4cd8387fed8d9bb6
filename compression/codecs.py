"""The codecs this build ships, registered by name and header id (paper 4.3.4, Fig. 10).

| name | id | what |
| --- | --- | --- |
| ``zlib`` | 1 | packed bits + zlib level 9 (registered in :mod:`compression.registry`) |
| ``rle`` | 2 | run lengths as varints |
| ``rle_zlib`` | 3 | run lengths + zlib |
| ``ctx4a``, ``ctx10a``, ``ctx16a`` | 16-18 | adaptive context models + range coder |

Trained models (the paper's static ``magic4``, trained-adaptive priors, inter-frame context)
register here when their model files ship.
"""

from __future__ import annotations

import numpy as np

from compression.context_model import ContextModel, decode_context, encode_context
from compression.registry import register_codec
from compression.run_length import rle_decode, rle_encode, rle_zlib_decode, rle_zlib_encode

__all__: list[str] = []

register_codec("rle", 2, encode=rle_encode, decode=rle_decode)
register_codec("rle_zlib", 3, encode=rle_zlib_encode, decode=rle_zlib_decode)


def _register_context(name: str, codec_id: int, model: ContextModel) -> None:
    def encode(grid: np.ndarray) -> bytes:
        return encode_context(grid, model)

    def decode(body: bytes, height: int, width: int) -> np.ndarray:
        return decode_context(body, height, width, model)

    register_codec(name, codec_id, encode=encode, decode=decode)


for _name, _id, _template in (("ctx4a", 16, "4"), ("ctx10a", 17, "10"), ("ctx16a", 18, "16")):
    _register_context(_name, _id, ContextModel.uniform(_template))
