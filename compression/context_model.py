"""Context-model coding of binary grids (paper 4.3.4, Fig. 9).

Each pixel, in row-major order, is predicted from a *causal template*: pixels above it or to
its left, already known to the decoder. The template's bits form a context index; a table
gives ``P(pixel = 1 | context)`` and the binary range coder (:mod:`compression.binary_coder`)
codes the pixel with it. Pixels outside the grid read as 0.

Probabilities are count-based with a prior (a Beta prior per context):

    P(1 | c) = (n1[c] + s * prior1[c]) / (n0[c] + n1[c] + s)

* *static*: ``prior1`` trained on a corpus, counts never updated (the paper's model);
* *adaptive*: uniform ``prior1 = 1/2`` with a small strength (Krichevsky-Trofimov-like),
  counts updated as pixels are coded;
* *trained-adaptive*: trained ``prior1`` with strength ``s``, counts updated.

Templates (offsets ``(dy, dx)``; W = (0, -1), N = (-1, 0)): ``4`` is W, NW, N, NE (the paper's
four neighbours); ``6``, ``9``, ``10`` and ``16`` widen it (``10`` is JBIG2's 10-pixel
template). The table has ``2**len(template)`` entries.

Complexity: O(pixels * template size), one compiled pass for encoding or decoding.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from compression.binary_coder import (
    PROB_ONE,
    dec_bit,
    dec_init,
    enc_bit,
    enc_finish,
    enc_init,
    max_encoded_bytes,
)

__all__ = ["TEMPLATES", "ContextModel", "context_counts", "decode_context", "encode_context"]

TEMPLATES: dict[str, tuple[tuple[int, int], ...]] = {
    "4": ((0, -1), (-1, -1), (-1, 0), (-1, 1)),
    "6": ((0, -1), (-1, -1), (-1, 0), (-1, 1), (0, -2), (-2, 0)),
    "9": ((0, -1), (-1, -1), (-1, 0), (-1, 1), (0, -2), (-2, 0), (-1, -2), (-1, 2), (-2, -1)),
    "10": (
        (0, -1),
        (0, -2),
        (-1, -2),
        (-1, -1),
        (-1, 0),
        (-1, 1),
        (-1, 2),
        (-2, -1),
        (-2, 0),
        (-2, 1),
    ),  # fmt: skip
    "16": (
        (0, -1),
        (0, -2),
        (0, -3),
        (0, -4),
        (-1, -3),
        (-1, -2),
        (-1, -1),
        (-1, 0),
        (-1, 1),
        (-1, 2),
        (-1, 3),
        (-2, -2),
        (-2, -1),
        (-2, 0),
        (-2, 1),
        (-2, 2),
    ),  # fmt: skip
}


@dataclass(frozen=True)
class ContextModel:
    """A template with its prior table, prior strength, and whether counts adapt."""

    template: str
    prior1: np.ndarray  # float64 (2**K,): P(1 | context) before any counts
    strength: float
    adaptive: bool

    def __post_init__(self) -> None:
        if self.template not in TEMPLATES:
            raise ValueError(f"unknown template {self.template!r}; known: {sorted(TEMPLATES)}")
        k = len(TEMPLATES[self.template])
        if self.prior1.shape != (1 << k,):
            raise ValueError(f"prior1 must have shape ({1 << k},), got {self.prior1.shape}")
        if not (np.all(self.prior1 > 0) and np.all(self.prior1 < 1)):
            raise ValueError("prior1 entries must lie strictly between 0 and 1")
        if not self.strength > 0:
            raise ValueError(f"strength must be > 0, got {self.strength}")

    @classmethod
    def uniform(cls, template: str, *, strength: float = 0.4) -> ContextModel:
        """An adaptive model that starts knowing nothing."""
        if template not in TEMPLATES:
            raise ValueError(f"unknown template {template!r}; known: {sorted(TEMPLATES)}")
        k = len(TEMPLATES[template])
        return cls(template, np.full(1 << k, 0.5), strength, True)

    @property
    def offsets(self) -> np.ndarray:
        return np.array(TEMPLATES[self.template], dtype=np.int64)


def _pad(grid: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, int, int]:
    top = int(max(0, -offsets[:, 0].min()))
    left = int(max(0, -offsets[:, 1].min()))
    right = int(max(0, offsets[:, 1].max()))
    h, w = grid.shape
    padded = np.zeros((h + top, w + left + right), dtype=np.uint8)
    padded[top:, left : left + w] = grid
    return padded, top, left


@numba.njit(cache=True, inline="always")
def _context(p: np.ndarray, r: int, c: int, offsets: np.ndarray) -> int:
    ctx = 0
    for k in range(offsets.shape[0]):
        ctx = (ctx << 1) | p[r + offsets[k, 0], c + offsets[k, 1]]
    return ctx


@numba.njit(cache=True, inline="always")
def _p0(n0: np.ndarray, n1: np.ndarray, prior1: np.ndarray, s: float, ctx: int) -> int:
    p1 = (n1[ctx] + s * prior1[ctx]) / (n0[ctx] + n1[ctx] + s)
    q = int((1.0 - p1) * PROB_ONE + 0.5)
    return min(max(q, 1), PROB_ONE - 1)


@numba.njit(cache=True)
def _encode(padded, top, left, h, w, offsets, prior1, s, adaptive, out):  # type: ignore[no-untyped-def]
    n0 = np.zeros(prior1.shape[0], dtype=np.float64)
    n1 = np.zeros(prior1.shape[0], dtype=np.float64)
    state = np.empty(5, dtype=np.int64)
    enc_init(state)
    for r in range(top, top + h):
        for c in range(left, left + w):
            ctx = _context(padded, r, c, offsets)
            bit = padded[r, c]
            enc_bit(state, out, bit, _p0(n0, n1, prior1, s, ctx))
            if adaptive:
                if bit:
                    n1[ctx] += 1.0
                else:
                    n0[ctx] += 1.0
    return enc_finish(state, out)


@numba.njit(cache=True)
def _decode(data, padded, top, left, h, w, offsets, prior1, s, adaptive):  # type: ignore[no-untyped-def]
    n0 = np.zeros(prior1.shape[0], dtype=np.float64)
    n1 = np.zeros(prior1.shape[0], dtype=np.float64)
    state = np.empty(3, dtype=np.int64)
    dec_init(state, data)
    for r in range(top, top + h):
        for c in range(left, left + w):
            ctx = _context(padded, r, c, offsets)
            bit = dec_bit(state, data, _p0(n0, n1, prior1, s, ctx))
            padded[r, c] = bit
            if adaptive:
                if bit:
                    n1[ctx] += 1.0
                else:
                    n0[ctx] += 1.0


@numba.njit(cache=True)
def _count(padded, top, left, h, w, offsets, n0, n1):  # type: ignore[no-untyped-def]
    for r in range(top, top + h):
        for c in range(left, left + w):
            ctx = _context(padded, r, c, offsets)
            if padded[r, c]:
                n1[ctx] += 1.0
            else:
                n0[ctx] += 1.0


def encode_context(grid: np.ndarray, model: ContextModel) -> bytes:
    """Code a binary ``(height, width)`` grid with ``model`` (no header: see the registry)."""
    g = np.ascontiguousarray(grid, dtype=np.uint8)
    offsets = model.offsets
    padded, top, left = _pad(g, offsets)
    h, w = g.shape
    out = np.zeros(max_encoded_bytes(h * w), dtype=np.uint8)
    n = _encode(padded, top, left, h, w, offsets, model.prior1, model.strength, model.adaptive, out)
    return out[:n].tobytes()


def decode_context(data: bytes, height: int, width: int, model: ContextModel) -> np.ndarray:
    """Decode a grid coded by :func:`encode_context` with the same model."""
    offsets = model.offsets
    padded, top, left = _pad(np.zeros((height, width), dtype=np.uint8), offsets)
    buf = np.frombuffer(data, dtype=np.uint8)
    _decode(
        buf, padded, top, left, height, width, offsets, model.prior1, model.strength, model.adaptive
    )
    return padded[top:, left : left + width].astype(bool)


def context_counts(grids: list[np.ndarray], template: str) -> tuple[np.ndarray, np.ndarray]:
    """Counts ``(n0, n1)`` of each context over a corpus of grids (for training priors)."""
    offsets = np.array(TEMPLATES[template], dtype=np.int64)
    n0 = np.zeros(1 << len(offsets), dtype=np.float64)
    n1 = np.zeros_like(n0)
    for grid in grids:
        g = np.ascontiguousarray(grid, dtype=np.uint8)
        padded, top, left = _pad(g, offsets)
        _count(padded, top, left, g.shape[0], g.shape[1], offsets, n0, n1)
    return n0, n1
