"""A covering of the pose graph's nodes: skip nodes whose observations are all overwritten
(paper 4.8; Strom and Olson 2011).

The global map gives each cell the value of the *latest* node, by ``(time, key)``, that
observes it (:mod:`gcs.mapping.rasterization`). A node that is the latest observer of no cell
can be left out without changing a single cell, and so can any set of such nodes (every
cell's latest observer stays). Finding them needs each node's *footprint*: which map cells it
observes at its current pose. Footprints are kept on a lattice of 16 x 16-cell blocks aligned
with the map lattice: per block the node touches, a 256-bit mask of its observed cells (four
``uint64`` words, bit ``16 r + c`` for the block's cell ``(r, c)``). The rasterizer packs them
from the very samples it draws with (:func:`footprint` of a node's map-aligned patch is the
reference), so they are exact, and keeps them in a :class:`FootprintPool` while the node's
pose holds still.

Why exact and not the paper's sensor-origin heuristic: under latest-wins a block holding a
wall is never observed *completely* by anyone (behind the wall is unknown), so any block-level
test rejects almost every node; and the naive and covered maps must agree cell for cell.
Redundant nodes are typically those re-observing a place a later node saw from about the
same spot (a robot standing still, a route driven again).

:func:`cover_sweep` visits nodes from the latest to the earliest with the union of the masks
seen so far: a node whose every mask is inside that union is redundant. A node is dropped if
and only if it is the latest observer of no cell. ``O(blocks touched)`` per node and sweep.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

__all__ = ["BLOCK_CELLS", "FootprintPool", "compact_footprint", "cover_sweep", "footprint"]

#: Side of a covering block in map cells (a block's mask is 16 x 16 = 256 bits).
BLOCK_CELLS = 16


@numba.njit(cache=True, nogil=True)
def _footprint(patch, row0, col0):  # type: ignore[no-untyped-def]
    rows, cols = patch.shape
    bi0 = row0 // 16
    bj0 = col0 // 16
    nbi = (row0 + rows - 1) // 16 - bi0 + 1
    nbj = (col0 + cols - 1) // 16 - bj0 + 1
    masks = np.zeros((nbi, nbj, 4), dtype=np.int64)
    for r in range(rows):
        gi = row0 + r
        bi = gi // 16 - bi0
        sub_r = gi - (gi // 16) * 16
        for c in range(cols):
            if patch[r, c] != 0:
                gj = col0 + c
                bj = gj // 16 - bj0
                bit = sub_r * 16 + gj - (gj // 16) * 16
                masks[bi, bj, bit >> 6] |= np.int64(1) << np.int64(bit & 63)
    return _compact(masks, bi0, bj0)


def footprint(patch: NDArray[np.int8], row0: int, col0: int) -> NDArray[np.int64]:
    """The footprint ``(blocks, 6)`` of a node from its map-aligned ``patch`` (non-zero where
    it observes; cell ``(0, 0)`` is map cell ``(row0, col0)``): rows ``(block_row, block_col,
    mask0..mask3)`` for every block with an observed cell (masks are uint64 bit patterns held
    as int64), in row-major block order."""
    if patch.size == 0:
        return np.zeros((0, 6), dtype=np.int64)
    return _footprint(patch, int(row0), int(col0))  # type: ignore[no-any-return]


@numba.njit(cache=True, nogil=True)
def _compact(masks, bi0, bj0):  # type: ignore[no-untyped-def]
    nbi, nbj, _ = masks.shape
    n = 0
    for bi in range(nbi):
        for bj in range(nbj):
            if masks[bi, bj, 0] | masks[bi, bj, 1] | masks[bi, bj, 2] | masks[bi, bj, 3]:
                n += 1
    out = np.empty((n, 6), dtype=np.int64)
    k = 0
    for bi in range(nbi):
        for bj in range(nbj):
            if masks[bi, bj, 0] | masks[bi, bj, 1] | masks[bi, bj, 2] | masks[bi, bj, 3]:
                out[k, 0] = bi + bi0
                out[k, 1] = bj + bj0
                out[k, 2:6] = masks[bi, bj]
                k += 1
    return out


def compact_footprint(masks: NDArray[np.int64], bi0: int, bj0: int) -> NDArray[np.int64]:
    """The :func:`footprint` rows of a dense ``(blocks_r, blocks_c, 4)`` mask array whose
    block ``(0, 0)`` is block ``(bi0, bj0)`` of the map (the rasterizer fills one while it
    samples a node)."""
    return _compact(masks, int(bi0), int(bj0))  # type: ignore[no-any-return]


class FootprintPool:
    """The current footprint of every node in one growing array: node ``n``'s rows are
    ``rows[offset[n] : offset[n] + count[n]]``. Replacing a footprint appends it; the pool is
    compacted when more than half of it is stale."""

    def __init__(self) -> None:
        self.rows = np.zeros((1024, 6), dtype=np.int64)
        self._offset = np.zeros(64, dtype=np.int64)
        self._count = np.zeros(64, dtype=np.int64)
        self._n = 0
        self._end = 0
        self._live = 0

    def __len__(self) -> int:
        return self._n

    @property
    def offset(self) -> NDArray[np.int64]:
        return self._offset[: self._n]

    @property
    def count(self) -> NDArray[np.int64]:
        return self._count[: self._n]

    def add_node(self) -> None:
        """Room for one more node, with an empty footprint."""
        n = self._n
        if n == len(self._offset):
            self._offset = np.concatenate([self._offset, np.zeros(n, dtype=np.int64)])
            self._count = np.concatenate([self._count, np.zeros(n, dtype=np.int64)])
        self._offset[n] = 0
        self._count[n] = 0
        self._n = n + 1

    def set(self, n: int, rows: NDArray[np.int64]) -> None:
        """Replace node ``n``'s footprint by ``rows`` ``(k, 6)``."""
        k = len(rows)
        self._live += k - int(self._count[n])
        if self._end + k > len(self.rows):
            if 2 * self._live < self._end:
                self._compact()
            if self._end + k > len(self.rows):
                grown = np.zeros((max(2 * len(self.rows), self._end + k), 6), dtype=np.int64)
                grown[: self._end] = self.rows[: self._end]
                self.rows = grown
        self.rows[self._end : self._end + k] = rows
        self._offset[n] = self._end
        self._count[n] = k
        self._end += k

    def set_many(
        self, nodes: NDArray[np.int64], rows: NDArray[np.int64], counts: NDArray[np.int64]
    ) -> None:
        """Replace the footprints of ``nodes`` (distinct): node ``nodes[i]`` gets the next
        ``counts[i]`` rows of ``rows``."""
        k = len(rows)
        self._live += k - int(self._count[nodes].sum())
        if self._end + k > len(self.rows):
            if 2 * self._live < self._end:
                self._compact()
            if self._end + k > len(self.rows):
                grown = np.zeros((max(2 * len(self.rows), self._end + k), 6), dtype=np.int64)
                grown[: self._end] = self.rows[: self._end]
                self.rows = grown
        self.rows[self._end : self._end + k] = rows
        starts = np.cumsum(counts) - counts
        self._offset[nodes] = self._end + starts
        self._count[nodes] = counts
        self._end += k

    def _compact(self) -> None:
        order = np.argsort(self.offset, kind="stable")
        lens = self.count[order]
        starts = self.offset[order]
        total = int(lens.sum())
        new_off = np.concatenate([[0], np.cumsum(lens)[:-1]]) if len(lens) else lens
        src = np.repeat(starts - new_off, lens) + np.arange(total)
        self.rows[:total] = self.rows[src]
        self._offset[order] = new_off
        self._end = total


@numba.njit(cache=True, nogil=True)
def _cover_sweep(order, rows, offset, count, n_nodes, bi_lo, bj_lo, nbi, nbj):  # type: ignore[no-untyped-def]
    kept = np.zeros(n_nodes, dtype=np.bool_)
    covered = np.zeros((max(nbi, 0), max(nbj, 0), 4), dtype=np.int64)
    for q in range(order.shape[0]):
        m = order[q]
        f = rows[offset[m] : offset[m] + count[m]]
        redundant = True
        for k in range(f.shape[0]):
            bi = f[k, 0] - bi_lo
            bj = f[k, 1] - bj_lo
            for w in range(4):
                if f[k, 2 + w] & ~covered[bi, bj, w]:
                    redundant = False
            if not redundant:
                break
        kept[m] = not redundant
        if not redundant:  # a redundant node's cells are all in the union already
            for k in range(f.shape[0]):
                bi = f[k, 0] - bi_lo
                bj = f[k, 1] - bj_lo
                for w in range(4):
                    covered[bi, bj, w] |= f[k, 2 + w]
    return kept


def cover_sweep(
    order: NDArray[np.int64],
    feet: FootprintPool,
    blocks: tuple[int, int, int, int],
) -> NDArray[np.bool_]:
    """The covering: ``kept`` ``(nodes,)`` bool, False for every node that is the latest
    observer of no cell.

    ``order``: indices of the nodes with a pose, latest first; ``feet``: every node's
    :func:`footprint`; ``blocks`` ``(row_lo, row_hi, col_lo, col_hi)`` block range holding
    every footprint of ``order``. Nodes not in ``order`` come out False.
    """
    bi_lo, bi_hi, bj_lo, bj_hi = blocks
    return _cover_sweep(  # type: ignore[no-any-return]
        order,
        feet.rows,
        feet.offset,
        feet.count,
        len(feet),
        bi_lo,
        bj_lo,
        bi_hi - bi_lo,
        bj_hi - bj_lo,
    )
