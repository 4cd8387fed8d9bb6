"""Plain-Python twin of :mod:`compression.context_model` (tests only): the same contexts,
features, fixed-point probabilities and range coder, one pixel at a time, without the
compiled kernel's shift registers, quiet-run fast path or generation stamps. Tests check that
the compiled coder produces identical bytes."""

from __future__ import annotations

import numpy as np

from compression.binary_coder import PROB_ONE, ReferenceDecoder, ReferenceEncoder
from compression.context_model import TEMPLATES, ContextModel

_ONE = 1 << 24


def _fixed_point(model: ContextModel) -> tuple[np.ndarray, np.ndarray]:
    one = float(_ONE)
    prior = np.clip(np.rint(model.prior1 * one), 1, one - 1).astype(np.int64)
    recip = np.rint(one / (np.arange(1024) + model.strength + 1.0)).astype(np.int64)
    return prior, recip


def _context(g: np.ndarray, r: int, c: int, template: str) -> int:
    h, w = g.shape
    ctx = 0
    for dy, (lo, hi) in zip((-2, -1, 0), TEMPLATES[template], strict=True):
        for dx in range(lo, hi + 1):
            rr, cc = r + dy, c + dx
            ctx = (ctx << 1) | int(0 <= rr < h and 0 <= cc < w and g[rr, cc])
    return ctx


def _code(
    grid: np.ndarray | None,
    data: bytes | None,
    shape: tuple[int, int],
    model: ContextModel,
    refcode: np.ndarray | None,
) -> tuple[np.ndarray, bytes]:
    h, w = shape
    prior, recip = _fixed_point(model)
    prob: dict[int, int] = {}
    count: dict[int, int] = {}
    marks = np.zeros((h, w), dtype=np.int64)
    ones: list[tuple[int, int]] = []
    out = np.zeros((h, w), dtype=np.uint8)
    enc = ReferenceEncoder() if data is None else None
    dec = ReferenceDecoder(data) if data is not None else None

    def full_context(r: int, c: int) -> int:
        ctx = _context(out, r, c, model.template)
        if model.extrapolate:
            ctx = ctx * 3 + min(int(marks[r, c]), 2)
        if model.reference:
            assert refcode is not None
            ctx = ctx * 3 + int(refcode[r, c])
        return ctx

    def code(bit: int | None, p1: int) -> int:
        q = min(max(PROB_ONE - (p1 >> 8), 1), PROB_ONE - 1)
        if enc is not None:
            assert bit is not None
            enc.encode(bit, q)
            return bit
        assert dec is not None
        return dec.decode(q)

    def adapt(ctx: int, p1: int, bit: int) -> None:
        if model.adaptive:
            n = count.get(ctx, 0)
            if bit:
                prob[ctx] = p1 + (((_ONE - p1) * int(recip[n])) >> 24)
            else:
                prob[ctx] = p1 - ((p1 * int(recip[n])) >> 24)
            count[ctx] = min(n + 1, 1023)

    def probability(ctx: int) -> int:
        return prob.get(ctx, int(prior[ctx])) if model.adaptive else int(prior[ctx])

    nbase = len(prior) - 64
    for r in range(h):
        c = 0
        while c < w:
            ctx = full_context(r, c)
            if model.runs and ctx == 0:
                end = c + 1
                while end < w and full_context(r, end) == 0:
                    end += 1
                extent = end - c
                rctx = nbase + 4 * min(extent.bit_length(), 15) + 2 * (c == 0) + (end == w)
                z = 0
                if grid is not None:
                    while z < extent and not grid[r, c + z]:
                        z += 1
                p1 = probability(rctx)
                bit = code(int(z < extent) if grid is not None else None, p1)
                adapt(rctx, p1, bit)
                if not bit:
                    c = end
                    continue
                v = 0
                for k in range((extent - 1).bit_length() - 1, -1, -1):
                    if v + (1 << k) <= extent - 1:
                        v += code((z >> k) & 1 if grid is not None else None, 1 << 23) << k
                c += v
            else:
                p1 = probability(ctx)
                bit = code(int(grid[r, c]) if grid is not None else None, p1)
                adapt(ctx, p1, bit)
            out[r, c] = bit
            if model.extrapolate and bit:
                for qr, qc in ones:
                    if r - qr <= 8 and abs(c - qc) <= 8:
                        tr, tc = 2 * r - qr, 2 * c - qc
                        if tr < h and 0 <= tc < w:
                            marks[tr, tc] += 1
                ones.append((r, c))
            c += 1
    return out.astype(bool), (enc.finish() if enc is not None else b"")


def reference_encode(
    grid: np.ndarray, model: ContextModel, refcode: np.ndarray | None = None
) -> bytes:
    return _code(np.asarray(grid, dtype=bool), None, grid.shape, model, refcode)[1]


def reference_decode(
    data: bytes, shape: tuple[int, int], model: ContextModel, refcode: np.ndarray | None = None
) -> np.ndarray:
    return _code(None, data, shape, model, refcode)[0]
