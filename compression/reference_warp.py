"""The previous grid warped into the current one: context for inter-frame coding (issue 5).

The paper's coder (4.3.4) codes each grid alone. Consecutive pose nodes of a robot see mostly
the same walls, so the grid the receiver already has predicts the new one: each occupied cell
of the reference is carried by the odometry between the two nodes into the current grid, and
the current grid's cells get a feature ``0`` (no reference cell within one cell), ``1`` (a
reference cell within one cell) or ``2`` (a reference cell on this cell).

The warp must be identical on the robot and at the GCS, on any platform. So the pose is first
rounded to float32 (what the radio carries), then quantized: translation to 1/256 cell, angle
to 2*pi/65536, and the warp runs in integer arithmetic with a sine table in Q16 (rounded from
``math.sin``; :data:`SINE_TABLE_CHECKSUM` pins it). The reference cells are mapped forward (one
point per occupied cell, the cell's centre), so the cost is O(occupied cells), not O(pixels).
"""

from __future__ import annotations

import math
import struct
import zlib

import numba
import numpy as np

__all__ = ["SINE_TABLE_CHECKSUM", "quantize_pose", "reference_code", "sine_table"]

_ANGLE_STEPS = 1 << 16
_F32 = struct.Struct("<4f")  # rounds to float32 like the radio
_SUB = 256  # translation quantum: 1/256 cell


def sine_table() -> np.ndarray:
    """``round(sin(2 pi k / 65536) * 65536)`` for ``k`` in ``0 .. 65535`` (int64)."""
    k = range(_ANGLE_STEPS)
    return np.array([round(math.sin(2 * math.pi * i / _ANGLE_STEPS) * 65536) for i in k], np.int64)


_SIN = sine_table()
#: CRC-32 of the sine table's int64 bytes. A platform whose ``math.sin`` rounded differently
#: would warp differently and garble inter-frame streams, so importing refuses it.
SINE_TABLE_CHECKSUM = 2860823005
if zlib.crc32(_SIN.tobytes()) != SINE_TABLE_CHECKSUM:
    raise RuntimeError(
        "compression.reference_warp: this platform's math.sin gives a different sine table "
        f"(CRC-32 {zlib.crc32(_SIN.tobytes())}, expected {SINE_TABLE_CHECKSUM}): inter-frame "
        "streams would not decode elsewhere"
    )


def quantize_pose(
    reference_from_current: tuple[float, float, float], resolution_m: float
) -> tuple[int, int, int]:
    """``(tx, ty, angle)``: translation in 1/256 cell and angle in 2*pi/65536 steps, from the
    float32-rounded pose and resolution (sender and receiver see the same float32 values)."""
    x, y, th, res = _F32.unpack(_F32.pack(*reference_from_current, resolution_m))
    tx = round(x / res * _SUB)
    ty = round(y / res * _SUB)
    angle = round(th / (2 * math.pi) * _ANGLE_STEPS) % _ANGLE_STEPS
    limit = 1 << 40
    if abs(tx) > limit or abs(ty) > limit:
        raise ValueError(f"reference_from_current {reference_from_current} is absurdly far")
    return int(tx), int(ty), int(angle)


@numba.njit(cache=True)
def _reference_code(ref, ref_ox, ref_oy, tx, ty, c, s, ox, oy, h, w):  # type: ignore[no-untyped-def]
    code = np.zeros((h, w), dtype=np.uint8)
    rh, rw = ref.shape
    for rr in range(rh):
        for rc in range(rw):
            if not ref[rr, rc]:
                continue
            # cell centre in the reference base, 1/256 cell, minus the translation
            dx = ((ref_ox + rc) * 256 + 128) - tx
            dy = ((ref_oy + rr) * 256 + 128) - ty
            # rotate by -theta into the current base (Q16 sine and cosine, floor)
            x = (c * dx + s * dy) >> 16
            y = (c * dy - s * dx) >> 16
            col = (x >> 8) - ox
            row = (y >> 8) - oy
            if row < -1 or row > h or col < -1 or col > w:
                continue
            for r in range(max(row - 1, 0), min(row + 2, h)):
                for q in range(max(col - 1, 0), min(col + 2, w)):
                    if code[r, q] == 0:
                        code[r, q] = 1
            if 0 <= row < h and 0 <= col < w:
                code[row, col] = 2
    return code


def reference_code(
    reference_grid: np.ndarray,
    reference_origin_cells: tuple[int, int],
    pose: tuple[int, int, int],
    origin_cells: tuple[int, int],
    height: int,
    width: int,
) -> np.ndarray:
    """The ``(height, width)`` uint8 feature (0/1/2) of the current grid at ``origin_cells``
    from the reference grid, with ``pose`` from :func:`quantize_pose`."""
    tx, ty, angle = pose
    s = int(_SIN[angle])
    c = int(_SIN[(angle + _ANGLE_STEPS // 4) % _ANGLE_STEPS])
    ref = np.ascontiguousarray(reference_grid, dtype=np.bool_)
    return _reference_code(
        ref,
        int(reference_origin_cells[0]),
        int(reference_origin_cells[1]),
        tx,
        ty,
        c,
        s,
        int(origin_cells[0]),
        int(origin_cells[1]),
        int(height),
        int(width),
    )
