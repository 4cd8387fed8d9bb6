"""Run-length baselines of paper 4.3.4 / Fig. 10: ``rle`` and ``rle_zlib``.

The grid is read row-major as one bit stream; runs alternate starting with zeros (a leading
empty run of length 0 when the grid starts with a one) and each run length is written as an
unsigned LEB128 varint. ``rle_zlib`` is that byte stream compressed by zlib (level 9): RLE
exposes the structure that zlib's dictionary then exploits quickly (the paper's observation).
"""

from __future__ import annotations

import zlib

import numpy as np

__all__ = ["rle_decode", "rle_encode", "rle_zlib_decode", "rle_zlib_encode"]


def rle_encode(grid: np.ndarray) -> bytes:
    bits = np.asarray(grid, dtype=bool).ravel()
    if bits.size == 0:
        return b""
    change = np.flatnonzero(bits[1:] != bits[:-1]) + 1
    bounds = np.concatenate([[0], change, [bits.size]])
    runs = np.diff(bounds).tolist()
    if bits[0]:
        runs.insert(0, 0)
    out = bytearray()
    for n in runs:
        while n >= 0x80:
            out.append((n & 0x7F) | 0x80)
            n >>= 7
        out.append(n)
    return bytes(out)


def rle_decode(body: bytes, height: int, width: int) -> np.ndarray:
    total = height * width
    runs = []
    n = shift = 0
    for byte in body:
        n |= (byte & 0x7F) << shift
        if byte & 0x80:
            shift += 7
            if shift > 35:
                raise ValueError("run length varint too long")
            continue
        runs.append(n)
        n = shift = 0
    if shift:
        raise ValueError("stream ends inside a run length")
    if sum(runs) != total:
        raise ValueError(f"runs cover {sum(runs)} cells, the grid has {total}")
    values = np.arange(len(runs)) % 2 == 1
    return np.repeat(values, runs).reshape(height, width)


def rle_zlib_encode(grid: np.ndarray) -> bytes:
    return zlib.compress(rle_encode(grid), 9)


def rle_zlib_decode(body: bytes, height: int, width: int) -> np.ndarray:
    d = zlib.decompressobj()
    limit = 5 * height * width + 16  # every run fits in 5 varint bytes: bounded inflation
    raw = d.decompress(body, limit)
    if d.unconsumed_tail or not d.eof:
        raise ValueError("zlib body is truncated or inflates beyond the grid's bound")
    return rle_decode(raw, height, width)
