"""Binary arithmetic (range) coder with exact termination (paper 4.3.4's "arithmetic encoder").

The coder is LZMA's binary range coder: 32-bit range, 33-bit low with carry propagation through
a cached byte, probabilities as 16-bit integers ``p0 = P(bit = 0) * 65536`` in ``[1, 65535]``.
Two changes make it tighter for the ~100-byte streams of terrain grids:

* the encoder's first output byte is always 0 (LZMA's cache starts empty), so it is not
  written and the decoder assumes it;
* termination picks, inside the final interval ``[low, low + range)``, the value with the most
  trailing zero bytes, and trailing zero bytes of the stream are dropped: the decoder reads
  zeros past the end. Termination costs 1-2 bytes instead of LZMA's 5.

The kernels are numba functions usable from other compiled code (the context-model codecs);
:class:`ReferenceEncoder` / :class:`ReferenceDecoder` are the same algorithm in plain Python,
kept only to check in tests that the compiled coder produces identical bytes.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = [
    "PROB_ONE",
    "ReferenceDecoder",
    "ReferenceEncoder",
    "decode_bits",
    "encode_bits",
    "max_encoded_bytes",
]

PROB_BITS = 16
PROB_ONE = 1 << PROB_BITS  # probabilities are p0 * PROB_ONE, clamped to [1, PROB_ONE - 1]
_TOP = 1 << 24
_MASK32 = 0xFFFFFFFF

# encoder state slots (int64 array of 5)
_LOW, _RANGE, _CACHE, _CACHE_SIZE, _POS = 0, 1, 2, 3, 4


def max_encoded_bytes(n_bits: int) -> int:
    """An upper bound on the stream size for ``n_bits`` decisions (each costs <= 16 bits)."""
    return 2 * n_bits + 16


@numba.njit(cache=True, inline="always")
def enc_init(state: np.ndarray) -> None:
    state[_LOW] = 0
    state[_RANGE] = _MASK32
    state[_CACHE] = 0
    state[_CACHE_SIZE] = 1
    state[_POS] = -1  # the first byte (always 0) is not written


@numba.njit(cache=True, inline="always")
def _shift_low(state: np.ndarray, out: np.ndarray) -> None:
    low = state[_LOW]
    if low < 0xFF000000 or low >= (1 << 32):
        carry = low >> 32
        temp = state[_CACHE]
        while True:
            pos = state[_POS]
            if pos >= 0:
                out[pos] = (temp + carry) & 0xFF
            state[_POS] = pos + 1
            temp = 0xFF
            state[_CACHE_SIZE] -= 1
            if state[_CACHE_SIZE] == 0:
                break
        state[_CACHE] = (low >> 24) & 0xFF
    state[_CACHE_SIZE] += 1
    state[_LOW] = (low & 0x00FFFFFF) << 8


@numba.njit(cache=True, inline="always")
def enc_bit(state: np.ndarray, out: np.ndarray, bit: int, p0: int) -> None:
    """Encode ``bit`` whose probability of being 0 is ``p0 / 65536``."""
    rng = state[_RANGE]
    bound = (rng >> PROB_BITS) * p0
    if bit == 0:
        state[_RANGE] = bound
    else:
        state[_LOW] += bound
        state[_RANGE] = rng - bound
    while state[_RANGE] < _TOP:
        state[_RANGE] = (state[_RANGE] << 8) & _MASK32
        _shift_low(state, out)


@numba.njit(cache=True)
def enc_finish(state: np.ndarray, out: np.ndarray) -> int:
    """Terminate the stream; returns its length in bytes (trailing zeros dropped)."""
    low = state[_LOW]
    rng = state[_RANGE]
    for k in range(4, -1, -1):  # the value in [low, low + range) with most trailing zeros
        unit = 1 << (8 * k)
        v = ((low + unit - 1) // unit) * unit
        if v < low + rng:
            state[_LOW] = v
            break
    for _ in range(5):
        _shift_low(state, out)
    n = state[_POS]
    while n > 0 and out[n - 1] == 0:
        n -= 1
    return n


@numba.njit(cache=True, inline="always")
def dec_init(state: np.ndarray, data: np.ndarray) -> None:
    """Decoder state slots: 0 code, 1 range, 2 read position."""
    code = 0
    for i in range(4):
        code = (code << 8) | (data[i] if i < data.shape[0] else 0)
    state[0] = code
    state[1] = _MASK32
    state[2] = 4


@numba.njit(cache=True, inline="always")
def dec_bit(state: np.ndarray, data: np.ndarray, p0: int) -> int:
    rng = state[1]
    code = state[0]
    bound = (rng >> PROB_BITS) * p0
    if code < bound:
        rng = bound
        bit = 0
    else:
        code -= bound
        rng -= bound
        bit = 1
    while rng < _TOP:
        pos = state[2]
        byte = data[pos] if pos < data.shape[0] else 0
        state[2] = pos + 1
        rng = (rng << 8) & _MASK32
        code = ((code << 8) | byte) & _MASK32
    state[0] = code
    state[1] = rng
    return bit


@numba.njit(cache=True)
def _encode_bits(bits: np.ndarray, p0: np.ndarray, out: np.ndarray) -> int:
    state = np.empty(5, dtype=np.int64)
    enc_init(state)
    for i in range(bits.shape[0]):
        enc_bit(state, out, bits[i], p0[i])
    return enc_finish(state, out)


@numba.njit(cache=True)
def _decode_bits(data: np.ndarray, p0: np.ndarray, bits: np.ndarray) -> None:
    state = np.empty(3, dtype=np.int64)
    dec_init(state, data)
    for i in range(bits.shape[0]):
        bits[i] = dec_bit(state, data, p0[i])


def _check_probs(p0: np.ndarray, n: int) -> np.ndarray:
    p = np.ascontiguousarray(p0, dtype=np.int64)
    if p.shape != (n,):
        raise ValueError(f"p0 must have shape ({n},), got {p.shape}")
    if p.size and (p.min() < 1 or p.max() > PROB_ONE - 1):
        raise ValueError(f"p0 values must be in [1, {PROB_ONE - 1}]")
    return p


def encode_bits(bits: np.ndarray, p0: np.ndarray) -> bytes:
    """Encode a bit sequence with a per-bit probability of 0 (``p0 / 65536``)."""
    b = np.ascontiguousarray(bits, dtype=np.uint8)
    if b.ndim != 1 or (b.size and b.max() > 1):
        raise ValueError("bits must be a 1-D array of 0 and 1")
    p = _check_probs(p0, b.shape[0])
    out = np.zeros(max_encoded_bytes(b.shape[0]), dtype=np.uint8)
    n = _encode_bits(b, p, out)
    return out[:n].tobytes()


def decode_bits(data: bytes, p0: np.ndarray) -> np.ndarray:
    """Decode ``len(p0)`` bits encoded by :func:`encode_bits` with the same probabilities."""
    p = _check_probs(p0, np.asarray(p0).shape[0])
    bits = np.empty(p.shape[0], dtype=np.uint8)
    _decode_bits(np.frombuffer(data, dtype=np.uint8), p, bits)
    return bits


class ReferenceEncoder:
    """Plain-Python twin of the compiled encoder (tests only)."""

    def __init__(self) -> None:
        self.low, self.range, self.cache, self.cache_size = 0, _MASK32, 0, 1
        self.out: list[int] = []
        self._first = True

    def _shift_low(self) -> None:
        if self.low < 0xFF000000 or self.low >= (1 << 32):
            carry = self.low >> 32
            temp = self.cache
            while True:
                byte = (temp + carry) & 0xFF
                if self._first:
                    assert byte == 0, "the first byte of a range-coded stream is 0"
                    self._first = False
                else:
                    self.out.append(byte)
                temp = 0xFF
                self.cache_size -= 1
                if self.cache_size == 0:
                    break
            self.cache = (self.low >> 24) & 0xFF
        self.cache_size += 1
        self.low = (self.low & 0x00FFFFFF) << 8

    def encode(self, bit: int, p0: int) -> None:
        bound = (self.range >> PROB_BITS) * p0
        if bit == 0:
            self.range = bound
        else:
            self.low += bound
            self.range -= bound
        while self.range < _TOP:
            self.range = (self.range << 8) & _MASK32
            self._shift_low()

    def finish(self) -> bytes:
        for k in range(4, -1, -1):
            unit = 1 << (8 * k)
            v = -(-self.low // unit) * unit
            if v < self.low + self.range:
                self.low = v
                break
        for _ in range(5):
            self._shift_low()
        return bytes(self.out).rstrip(b"\x00")


class ReferenceDecoder:
    """Plain-Python twin of the compiled decoder (tests only)."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 4
        self.code = int.from_bytes(data[:4].ljust(4, b"\x00"), "big")
        self.range = _MASK32

    def decode(self, p0: int) -> int:
        bound = (self.range >> PROB_BITS) * p0
        if self.code < bound:
            self.range = bound
            bit = 0
        else:
            self.code -= bound
            self.range -= bound
            bit = 1
        while self.range < _TOP:
            byte = self.data[self.pos] if self.pos < len(self.data) else 0
            self.pos += 1
            self.range = (self.range << 8) & _MASK32
            self.code = ((self.code << 8) | byte) & _MASK32
        return bit
