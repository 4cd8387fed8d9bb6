"""The codecs this build ships, registered by name and header id (paper 4.3.4, Fig. 9-10).

| name | id | what |
| --- | --- | --- |
| ``zlib`` | 1 | packed bits + zlib level 9 (registered in :mod:`compression.registry`) |
| ``rle`` | 2 | run lengths as varints |
| ``rle_zlib`` | 3 | run lengths + zlib |
| ``ctx4a``, ``ctx10a``, ``ctx16a`` | 16-18 | adaptive context models, untrained |
| ``magic4`` | 20 | **the paper's coder**: 4 neighbours, static probabilities trained on a corpus |
| ``magic6`` ... ``magic16`` | 21-24 | the paper's Fig. 9 study: larger templates, static |
| ``ctx16t`` | 28 | 16 neighbours, trained prior that adapts (counts with a prior strength) |
| ``intra16`` | 30 | the best intra codec: ``ctx16t`` plus line extrapolation and quiet runs |
| ``inter16`` | 40 | ``intra16`` plus the previous grid warped by odometry; key frames ``intra16`` |

(:mod:`compression.context_model` describes templates, features and quiet runs.) The trained
codecs (20 and up) come from the model file :data:`~compression.model_file.MODEL_FILE` and
carry its version in every stream. :data:`DEFAULT_CODEC` is the one that measures best
(``magic bench compression``: held-out worlds, 26.7 bytes per grid against ``magic4``'s 42.2).
"""

from __future__ import annotations

import numpy as np

from compression.context_model import ContextModel, decode_context, encode_context
from compression.model_file import MODEL_FILE, TrainedModel, load_model_file
from compression.reference_warp import quantize_pose, reference_code
from compression.registry import GridReference, register_codec
from compression.run_length import rle_decode, rle_encode, rle_zlib_decode, rle_zlib_encode

__all__ = [
    "BEST_INTRA_CODEC",
    "DEFAULT_CODEC",
    "MODEL_VERSION",
    "TRAINED_CODECS",
    "reference_code_for",
]

#: The robot node's default: inter-frame coding against its previous grid (key frames intra).
DEFAULT_CODEC = "inter16"
BEST_INTRA_CODEC = "intra16"

register_codec("rle", 2, encode=rle_encode, decode=rle_decode, description="run lengths")
register_codec(
    "rle_zlib", 3, encode=rle_zlib_encode, decode=rle_zlib_decode, description="RLE + zlib"
)


def _register_intra(name: str, codec_id: int, model: ContextModel, version: int, what: str) -> None:
    def encode(grid: np.ndarray) -> bytes:
        return encode_context(grid, model)

    def decode(body: bytes, height: int, width: int) -> np.ndarray:
        return decode_context(body, height, width, model)

    register_codec(
        name, codec_id, encode=encode, decode=decode, model_version=version, description=what
    )


def reference_code_for(
    height: int, width: int, origin_cells: tuple[int, int], ref: GridReference
) -> np.ndarray:
    """The inter-frame feature of a ``(height, width)`` grid at ``origin_cells`` from ``ref``
    (:mod:`compression.reference_warp`); training uses it to count reference contexts."""
    pose = quantize_pose(ref.reference_from_current, ref.resolution_m)
    return reference_code(ref.grid, ref.origin_cells, pose, origin_cells, height, width)


def _register_inter(
    name: str, codec_id: int, model: ContextModel, version: int, key: str, what: str
) -> None:
    def encode(grid: np.ndarray, origin_cells: tuple[int, int], ref: GridReference) -> bytes:
        h, w = grid.shape
        return encode_context(grid, model, reference_code_for(h, w, origin_cells, ref))

    def decode(
        body: bytes, height: int, width: int, origin_cells: tuple[int, int], ref: GridReference
    ) -> np.ndarray:
        refcode = reference_code_for(height, width, origin_cells, ref)
        return decode_context(body, height, width, model, refcode)

    register_codec(
        name,
        codec_id,
        encode=encode,
        decode=decode,
        model_version=version,
        key_frame_codec=key,
        description=what,
    )


for _name, _id, _template in (("ctx4a", 16, "4"), ("ctx10a", 17, "10"), ("ctx16a", 18, "16")):
    _register_intra(
        _name, _id, ContextModel.uniform(_template), 0, f"{_template} neighbours, adaptive"
    )


def _register_trained(models: tuple[TrainedModel, ...], version: int) -> list[str]:
    names = []
    intra = [m for m in models if not m.reference]
    inter = [m for m in models if m.reference]
    for m in intra + inter:  # key-frame codecs first
        if m.reference:
            _register_inter(
                m.name,
                m.codec_id,
                m.context_model(),
                version,
                BEST_INTRA_CODEC,
                m.description,
            )
        else:
            _register_intra(m.name, m.codec_id, m.context_model(), version, m.description)
        names.append(m.name)
    return names


if MODEL_FILE.is_file():
    _FILE = load_model_file(MODEL_FILE)
    #: The version of the shipped model file (written in every trained codec's stream).
    MODEL_VERSION = _FILE.version
    #: Names of the codecs registered from the model file.
    TRAINED_CODECS: tuple[str, ...] = tuple(_register_trained(_FILE.models, _FILE.version))
else:  # only before the first training (``magic codec train``): no trained codecs
    MODEL_VERSION = 0
    TRAINED_CODECS = ()
