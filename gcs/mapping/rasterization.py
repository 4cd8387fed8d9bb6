"""Global map rasterization: the pose graph's posterior turned into an occupancy grid in ``map``
(paper 4.8, Table 2; Strom and Olson 2011).

**Fusion rule.** Each node contributes its local raster (occupied / free / unknown in its own
``base`` frame, :mod:`gcs.mapping.visibility`, computed once when the node arrives). A map
cell takes the value of the *latest* node, ordered by ``(time_s, key)``, that observes it
(free or occupied); cells no node observes are unknown. Latest-wins removes the trails of
moving objects and keeps walls sharp (no blur from averaging many slightly misaligned views).

**Sampling.** A node is drawn by inverse nearest-neighbour sampling: the centre of map cell
``(i, j)``, ``((j + 0.5) res, (i + 0.5) res)`` on the global lattice of ``map``, is moved into
the node's ``base`` frame with its posterior pose and looked up in the local raster. The
sample depends only on the cell's global indices, the pose and the raster, never on the
buffer it is written into, and one compiled kernel does all sampling, so every path below
produces bit-identical cells.

**Naive** (:meth:`Rasterizer.rasterize_naive`): draw every node, earliest first, overwriting.

**Covering** (:mod:`gcs.mapping.covering`): a node that is the latest observer of no cell is
skipped. Its footprint (observed cells per 16 x 16 block, exact) is sampled when its pose
changes and cached; the sample is reused to draw the node, so the covering costs no extra
sampling.

**Cached submaps**: nodes are partitioned into submaps of ``submap_nodes`` consecutive nodes
of one robot (in the order they were added). A submap holds per cell the code of its latest
drawn node (dense over a box of whole map tiles of ``tile_cells``). Latest-wins is associative
and commutative, so the map is the per-cell latest over all submaps: exactly the naive map
when every node the covering keeps is drawn in its submap at its current pose. So per
rasterization a submap is

- reused when none of its drawn nodes moved (beyond ``pose_tolerance_m`` /
  ``pose_tolerance_rad``; 0, the default, means not at all, which keeps the map exact) or lost
  its pose, and every kept node of it is drawn;
- extended when only new or newly kept nodes are missing: they are drawn on top, keeping the
  cells of later nodes;
- redrawn from its kept nodes otherwise.

Only the map tiles a changed submap touches (before or now) are combined again, with a
per-node rank table that turns latest-wins into a plain maximum; the other tiles keep their
values from the previous map.

Cell codes: ``0`` unknown, ``2 (i + 1) + occupied`` for node ``i`` (of the map in the naive
path, of the submap in submaps). Complexity: naive ``O(nodes x window cells)``; cached
``O(moved nodes x window cells + dirty tiles x submaps per tile + map cells)``.
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import msgspec
import numba
import numpy as np
from numba.typed import List as TypedList
from numpy.typing import ArrayLike, NDArray

from gcs.mapping.covering import BLOCK_CELLS, FootprintPool, cover_sweep
from gcs.mapping.visibility import LocalRaster, local_raster

__all__ = [
    "FREE",
    "OCCUPIED",
    "UNKNOWN",
    "OccupancyMap",
    "PosesInMap",
    "RasterConfig",
    "RasterStats",
    "Rasterizer",
]

#: Values of :attr:`OccupancyMap.values` (ROS ``nav_msgs/OccupancyGrid`` convention).
UNKNOWN = -1
FREE = 0
OCCUPIED = 100

#: Samples of moved nodes kept within one rasterization to draw them without sampling again.
_PATCH_BUDGET_BYTES = 64 * 1024 * 1024
#: Submap codes are uint8 ``2 (local index + 1) + occupied``.
MAX_SUBMAP_NODES = 126
#: Placeholders for the optional arguments of :func:`_sample`.
_NO_MASKS = np.zeros((0, 0, 4), dtype=np.int64)
_NO_PRIO = np.zeros(0, dtype=np.int64)


class RasterConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Rasterization of the global map (paper 4.8).

    ``resolution_m`` of the map; ``free_range_m`` how far from a node its rays mark free space
    (half the 15 m local window) and ``free_fov_rad`` within which angle around the base's +x
    axis: the robot's nodding Hokuyo UTM-30LX scans 270 degrees (paper 3.1, ``sim.lidar``), so
    the 90 degrees behind it are never seen and a wall there is missing from the grid (with
    ``2 pi`` the rays ran through it: free space outside the perimeter and into buildings, and
    walls other nodes saw erased by latest-wins); the default 240 degrees leaves 15 degrees at
    each edge for the robot turning during the 1.25 s sweep (a wall near the edge is then
    seen by too few scan lines to count as vertical); ``2 pi`` for an all-round sensor, ``pi``
    for a forward 180-degree laser; ``wall_gap_m`` rays do not pass gaps in a wall narrower than
    this (sparse returns at range or at grazing angles leave such holes; a robot cannot
    drive through them either, and doorways are wider); ``cover``
    skip nodes that are the latest observer of no cell; ``cache`` reuse submaps of
    ``submap_nodes`` nodes while their poses hold still within ``pose_tolerance_m`` /
    ``pose_tolerance_rad`` (0: exact; an incremental smoother that nudges every pose a little
    needs a small tolerance for the cache to pay);
    ``tile_cells`` side of the map tiles submaps are stored and combined in;
    ``max_map_cells`` refuses maps larger than this (a wild pose would allocate gigabytes).
    """

    resolution_m: float = 0.1
    free_range_m: float = 7.5
    free_fov_rad: float = 4.0 * math.pi / 3.0
    wall_gap_m: float = 0.4
    cover: bool = True
    cache: bool = True
    submap_nodes: int = 32
    tile_cells: int = 64
    pose_tolerance_m: float = 0.0
    pose_tolerance_rad: float = 0.0
    max_map_cells: int = 100_000_000

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution_m) and 0.001 <= self.resolution_m <= 10):
            raise ValueError(f"resolution_m must be in [0.001, 10], got {self.resolution_m}")
        if not (math.isfinite(self.free_range_m) and 0 <= self.free_range_m <= 1000):
            raise ValueError(f"free_range_m must be in [0, 1000], got {self.free_range_m}")
        if not (math.isfinite(self.free_fov_rad) and 0 <= self.free_fov_rad <= 2 * math.pi):
            raise ValueError(f"free_fov_rad must be in [0, 2 pi], got {self.free_fov_rad}")
        if not (math.isfinite(self.wall_gap_m) and 0 <= self.wall_gap_m <= 10):
            raise ValueError(f"wall_gap_m must be in [0, 10], got {self.wall_gap_m}")
        if not 1 <= self.submap_nodes <= MAX_SUBMAP_NODES:
            raise ValueError(
                f"submap_nodes must be in [1, {MAX_SUBMAP_NODES}], got {self.submap_nodes}"
            )
        if not 8 <= self.tile_cells <= 1024:
            raise ValueError(f"tile_cells must be in [8, 1024], got {self.tile_cells}")
        for name in ("pose_tolerance_m", "pose_tolerance_rad"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")
        if self.max_map_cells < 1:
            raise ValueError(f"max_map_cells must be >= 1, got {self.max_map_cells}")


@dataclass(frozen=True)
class OccupancyMap:
    """The global occupancy grid in ``map``.

    ``values`` ``(rows, cols)`` int8: :data:`UNKNOWN` (-1), :data:`FREE` (0), :data:`OCCUPIED`
    (100). Cell ``(row, col)`` covers ``origin_in_map + (col, row) * resolution_m``
    (``origin_in_map`` is the corner of cell ``(0, 0)``; rows go along +y). An empty map
    (no node with a pose) is ``0 x 0``.
    """

    values: NDArray[np.int8]
    origin_in_map: tuple[float, float]
    resolution_m: float

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.values.shape[0]), int(self.values.shape[1]))

    def cells_of(self, points_in_map: ArrayLike) -> NDArray[np.int64]:
        """``(N, 2)`` ``(row, col)`` of the cells holding ``points_in_map`` ``(N, 2)`` (they may
        lie outside the grid)."""
        pts = np.asarray(points_in_map, dtype=np.float64).reshape(-1, 2)
        col = np.floor((pts[:, 0] - self.origin_in_map[0]) / self.resolution_m)
        row = np.floor((pts[:, 1] - self.origin_in_map[1]) / self.resolution_m)
        return np.stack([row, col], axis=1).astype(np.int64)


@dataclass
class RasterStats:
    """What the last rasterization did: ``nodes`` with a pose, ``kept`` by the covering,
    ``sampled`` (footprints recomputed: new or moved nodes), ``drawn`` into a submap or the
    map, submaps ``reused`` / ``rebuilt``, ``dirty_tiles`` combined again, ``unknown_keys`` in
    the poses given (no node for them), map ``cells`` and wall-clock ``seconds``."""

    nodes: int = 0
    kept: int = 0
    sampled: int = 0
    drawn: int = 0
    submaps: int = 0
    reused: int = 0
    rebuilt: int = 0
    dirty_tiles: int = 0
    unknown_keys: int = 0
    cells: int = 0
    seconds: float = 0.0


@dataclass
class _Submap:
    """Consecutive nodes of one robot and the latest-wins codes of those drawn into it.

    ``codes`` (``2 (i + 1) + occupied`` for ``nodes[i]``) is dense over a tile-aligned box
    whose cell ``(0, 0)`` is map cell ``(row0, col0)``; ``tiles`` the map tiles where it has
    cells, with the rows and columns ``(r0, r1, c0, c1)`` within the tile that hold them."""

    nodes: list[int]
    codes: NDArray[np.uint8] = field(default_factory=lambda: np.zeros((0, 0), dtype=np.uint8))
    row0: int = 0
    col0: int = 0
    tiles: dict[tuple[int, int], tuple[int, int, int, int]] = field(default_factory=dict)


# ---------------------------------------------------------------------------------------------
# Kernels


@numba.njit(cache=True, nogil=True)
def _span(alpha, beta, lo, hi):  # type: ignore[no-untyped-def]
    """Integers ``j`` with ``lo <= alpha + beta j < hi``, as ``[j0, j1)`` (up to rounding at
    the ends: the caller clamps)."""
    big = 1e15
    if beta > 0.0:
        u = min(max((lo - alpha) / beta, -big), big)
        v = min(max((hi - alpha) / beta, -big), big)
        return int(math.ceil(u)), int(math.ceil(v))
    if beta < 0.0:
        u = min(max((hi - alpha) / beta, -big), big)
        v = min(max((lo - alpha) / beta, -big), big)
        return int(math.floor(u)) + 1, int(math.floor(v)) + 1
    if lo <= alpha < hi:
        return -(1 << 50), 1 << 50
    return 0, 0


@numba.njit(cache=True, nogil=True)
def _sample(
    buf, row0, col0, base, cells, ox, oy, lres, x, y, yaw, res, bbox, prio, node_prio, masks
):  # type: ignore[no-untyped-def]  # noqa: E501
    """Write ``base + v`` into ``buf`` (whose cell ``(0, 0)`` is map cell ``(row0, col0)``)
    at the map cells of ``bbox`` whose centres fall into an observed cell ``v`` (1 free,
    2 occupied) of the node's local raster ``cells``. The only sampling code: every path
    draws through it, and which cells it samples and how depends on the node, its pose and
    the cell's global indices only (never on ``buf``), so all paths agree bit for bit.

    Per map row, the columns whose centres fall inside the raster rectangle are solved for,
    the raster indices computed in a vectorizable pass and clamped (a centre within rounding
    of the rectangle's edge samples the edge cell), then looked up.

    ``node_prio >= 0``: keep a cell whose code names a node of larger ``prio`` (latest wins);
    ``masks`` ``(blocks_r, blocks_c, 4)`` non-empty: also set the footprint bit of every
    observed cell (blocks counted from ``bbox``'s first block)."""
    h, w = buf.shape
    rows, cols = cells.shape
    flat = cells.ravel()
    c = math.cos(yaw)
    s = math.sin(yaw)
    inv = 1.0 / lres
    footprint = masks.shape[0] > 0
    bi0 = bbox[0] // 16
    bj0 = bbox[2] // 16
    lin = np.empty(max(bbox[3] - bbox[2], 0), dtype=np.int64)
    # the row's raster values, placed so that index 0 is a block's first column (pad cells
    # before and after are 0): 16 values of a block are two uint64 words of the view
    vals = np.zeros((max(bbox[3] - bbox[2], 0) // 16 + 3) * 16, dtype=np.uint8)
    words = vals.view(np.uint64)
    for gi in range(max(bbox[0], row0), min(bbox[1], row0 + h)):
        dy = (gi + 0.5) * res - y
        a = s * dy - ox
        b = c * dy - oy
        # raster column (row) of map column gj: (c dx + a) / lres ((b - s dx) / lres) with
        # dx = (gj + 0.5) res - x
        j0, j1 = _span((c * (0.5 * res - x) + a) * inv, c * res * inv, 0.0, cols)
        k0, k1 = _span((b - s * (0.5 * res - x)) * inv, -s * res * inv, 0.0, rows)
        j0 = max(j0, k0, bbox[2], col0)
        j1 = min(j1, k1, bbox[3], col0 + w)
        n = j1 - j0
        if n <= 0:
            continue
        for q in range(n):
            dx = (j0 + q + 0.5) * res - x
            lc = min(max(int((c * dx + a) * inv), 0), cols - 1)
            lr = min(max(int((b - s * dx) * inv), 0), rows - 1)
            lin[q] = lr * cols + lc
        pad = j0 & 15
        for q in range(pad):
            vals[q] = 0
        for q in range(n):
            vals[pad + q] = flat[lin[q]]
        for q in range(pad + n, pad + n + 16):
            vals[q] = 0
        if footprint:
            # this row's 16 bits of each block it crosses: byte -> bit packing of the words
            bi = gi // 16 - bi0
            sub_row = gi - (gi // 16) * 16
            word = sub_row >> 2
            shift = np.uint64((sub_row & 3) * 16)
            first_bj = j0 // 16
            for k in range((pad + n + 15) // 16):
                w0 = words[2 * k]
                w1 = words[2 * k + 1]
                w0 = (w0 | (w0 >> np.uint64(1))) & np.uint64(0x0101010101010101)
                w1 = (w1 | (w1 >> np.uint64(1))) & np.uint64(0x0101010101010101)
                bits = ((w0 * np.uint64(0x0102040810204080)) >> np.uint64(56)) | (
                    ((w1 * np.uint64(0x0102040810204080)) >> np.uint64(56)) << np.uint64(8)
                )
                if bits:
                    masks[bi, first_bj + k - bj0, word] |= np.int64(bits << shift)
        r = gi - row0
        for q in range(n):
            v = vals[pad + q]
            if v == 0:
                continue
            gj = j0 + q
            if node_prio >= 0:
                o = buf[r, gj - col0]
                if o != 0 and prio[(o >> 1) - 1] > node_prio:
                    continue
            buf[r, gj - col0] = base + v


@numba.njit(cache=True, nogil=True)
def _draw_patch(buf, row0, col0, patch, p_row0, p_col0, base, prio, node_prio):  # type: ignore[no-untyped-def]
    """``buf = base + patch`` where ``patch`` (a node's samples, cell ``(0, 0)`` at map cell
    ``(p_row0, p_col0)``) is non-zero; with ``node_prio >= 0`` only where ``buf`` holds no
    later node (by ``prio``)."""
    h, w = buf.shape
    ph, pw = patch.shape
    i_lo = max(row0, p_row0)
    i_hi = min(row0 + h, p_row0 + ph)
    j_lo = max(col0, p_col0)
    j_hi = min(col0 + w, p_col0 + pw)
    if node_prio < 0:
        for gi in range(i_lo, i_hi):
            src = patch[gi - p_row0, j_lo - p_col0 : j_hi - p_col0]
            dst = buf[gi - row0, j_lo - col0 : j_hi - col0]
            for q in range(j_hi - j_lo):
                v = src[q]
                dst[q] = dst[q] if v == 0 else base + v
        return
    for gi in range(i_lo, i_hi):
        for gj in range(j_lo, j_hi):
            v = patch[gi - p_row0, gj - p_col0]
            if v != 0:
                o = buf[gi - row0, gj - col0]
                if o == 0 or prio[(o >> 1) - 1] < node_prio:
                    buf[gi - row0, gj - col0] = base + v


@numba.njit(cache=True, nogil=True)
def _sample_feet(nodes, poses, bbox, rect, lres, cells, res, patches, patch_off, blocks, masks):  # type: ignore[no-untyped-def]  # noqa: E501
    """Sample every node of ``nodes`` into its patch (``patches[patch_off[k]:]``, the node's
    ``bbox``) and its dense footprint masks (``masks`` from ``blocks[k, 4]`` on, ``(blocks[k,
    2], blocks[k, 3], 4)`` from block ``(blocks[k, 0], blocks[k, 1])``); returns the compact
    footprint rows of all nodes and how many belong to each."""
    no_prio = np.zeros(0, dtype=np.int64)
    counts = np.zeros(nodes.shape[0], dtype=np.int64)
    for k in range(nodes.shape[0]):
        n = nodes[k]
        b = bbox[n]
        h = b[1] - b[0]
        w = b[3] - b[2]
        patch = patches[patch_off[k] : patch_off[k] + h * w].reshape((h, w))
        m_lo = blocks[k, 4]
        m = masks[m_lo : m_lo + blocks[k, 2] * blocks[k, 3] * 4].reshape(
            (blocks[k, 2], blocks[k, 3], 4)
        )
        c = cells[n]
        if c.size:
            _sample(patch, b[0], b[2], 0, c, rect[n, 0], rect[n, 1], lres[n], poses[n, 0],
                    poses[n, 1], poses[n, 2], res, b, no_prio, -1, m)  # fmt: skip
        for q in range(blocks[k, 2] * blocks[k, 3]):
            i = m_lo + 4 * q
            if masks[i] | masks[i + 1] | masks[i + 2] | masks[i + 3]:
                counts[k] += 1
    rows = np.empty((counts.sum(), 6), dtype=np.int64)
    r = 0
    for k in range(nodes.shape[0]):
        m_lo = blocks[k, 4]
        nbj = blocks[k, 3]
        for q in range(blocks[k, 2] * nbj):
            i = m_lo + 4 * q
            if masks[i] | masks[i + 1] | masks[i + 2] | masks[i + 3]:
                rows[r, 0] = blocks[k, 0] + q // nbj
                rows[r, 1] = blocks[k, 1] + q % nbj
                rows[r, 2] = masks[i]
                rows[r, 3] = masks[i + 1]
                rows[r, 4] = masks[i + 2]
                rows[r, 5] = masks[i + 3]
                r += 1
    return rows, counts


@numba.njit(cache=True, nogil=True)
def _tile_spans(view, t):  # type: ignore[no-untyped-def]
    """Per ``t x t`` tile of ``view`` (whole tiles) that holds a non-zero cell: ``(tile row,
    tile col, r0, r1, c0, c1)``, the rows and columns within the tile that hold them."""
    nti = view.shape[0] // t
    ntj = view.shape[1] // t
    out = np.empty((nti * ntj, 6), dtype=np.int64)
    k = 0
    for a in range(nti):
        for b in range(ntj):
            r0 = t
            r1 = 0
            c0 = t
            c1 = 0
            for i in range(t):
                row = view[a * t + i, b * t : b * t + t]
                for j in range(t):
                    if row[j] != 0:
                        r0 = min(r0, i)
                        r1 = i + 1
                        c0 = min(c0, j)
                        c1 = max(c1, j + 1)
            if r1 > 0:
                out[k, 0] = a
                out[k, 1] = b
                out[k, 2] = r0
                out[k, 3] = r1
                out[k, 4] = c0
                out[k, 5] = c1
                k += 1
    return out[:k]


@numba.njit(cache=True, nogil=True)
def _combine_tiles(slots, ptr, sub_ids, sub_i0, sub_j0, spans, sub_codes, rank, store):  # type: ignore[no-untyped-def]
    """Combine tile ``k`` (into ``store[slots[k]]`` as values) from the submaps
    ``sub_ids[ptr[k]:ptr[k+1]]``, whose codes hold the tile at ``(sub_i0, sub_j0)``: per cell
    the latest node's value. ``rank[sid, code]`` is ``2 (prio + 1) + occupied`` of the node
    submap ``sid``'s code names (0 for no node), so latest-wins is a plain maximum; only the
    rows and columns ``spans[p]`` of the tile that hold the submap's cells are read."""
    t = store.shape[1]
    best = np.zeros((t, t), dtype=np.int32)
    for k in range(slots.shape[0]):
        best[:, :] = 0
        for p in range(ptr[k], ptr[k + 1]):
            sid = sub_ids[p]
            sub = sub_codes[sid]
            table = rank[sid]
            i0 = sub_i0[p]
            j0 = sub_j0[p]
            c0 = spans[p, 2]
            c1 = spans[p, 3]
            for i in range(spans[p, 0], spans[p, 1]):
                row = sub[i0 + i, j0 + c0 : j0 + c1]
                out = best[i, c0:c1]
                for j in range(c1 - c0):
                    out[j] = max(out[j], table[row[j]])
        values = store[slots[k]]
        for i in range(t):
            for j in range(t):
                v = best[i, j]
                values[i, j] = -1 if v == 0 else (100 if v & 1 else 0)


@numba.njit(cache=True, nogil=True)
def _assemble(values, row0, col0, store, used, tile_rc):  # type: ignore[no-untyped-def]
    """Copy every used tile of ``store`` (map tile ``tile_rc[slot]``) into ``values``, whose
    cell ``(0, 0)`` is map cell ``(row0, col0)``."""
    h, w = values.shape
    t = store.shape[1]
    for slot in range(used.shape[0]):
        if not used[slot]:
            continue
        i0 = tile_rc[slot, 0] * t
        j0 = tile_rc[slot, 1] * t
        a0 = max(i0, row0)
        a1 = min(i0 + t, row0 + h)
        b0 = max(j0, col0)
        b1 = min(j0 + t, col0 + w)
        if a0 < a1 and b0 < b1:
            values[a0 - row0 : a1 - row0, b0 - col0 : b1 - col0] = store[
                slot, a0 - i0 : a1 - i0, b0 - j0 : b1 - j0
            ]


@numba.njit(cache=True, nogil=True)
def _values(codes):  # type: ignore[no-untyped-def]
    h, w = codes.shape
    out = np.empty((h, w), dtype=np.int8)
    for i in range(h):
        for j in range(w):
            v = codes[i, j]
            out[i, j] = -1 if v == 0 else (100 if v & 1 else 0)
    return out


@numba.njit(cache=True, nogil=True)
def _node_bboxes(poses, rect, res):  # type: ignore[no-untyped-def]
    """Map-cell box ``(row_lo, row_hi, col_lo, col_hi)`` (half-open, with a margin) holding
    every map cell whose centre can fall into each node's local raster rectangle ``rect``
    ``(N, 4)`` = ``(ox, oy, width_m, height_m)`` in ``base``. Sampling never leaves it."""
    n = poses.shape[0]
    out = np.empty((n, 4), dtype=np.int64)
    for k in range(n):
        c = math.cos(poses[k, 2])
        s = math.sin(poses[k, 2])
        x_lo = y_lo = math.inf
        x_hi = y_hi = -math.inf
        for corner in range(4):
            bx = rect[k, 0] + (rect[k, 2] if corner == 1 or corner == 2 else 0.0)
            by = rect[k, 1] + (rect[k, 3] if corner >= 2 else 0.0)
            mx = poses[k, 0] + c * bx - s * by
            my = poses[k, 1] + s * bx + c * by
            x_lo = min(x_lo, mx)
            x_hi = max(x_hi, mx)
            y_lo = min(y_lo, my)
            y_hi = max(y_hi, my)
        out[k, 0] = int(math.floor(y_lo / res - 0.5)) - 1
        out[k, 1] = int(math.ceil(y_hi / res - 0.5)) + 2
        out[k, 2] = int(math.floor(x_lo / res - 0.5)) - 1
        out[k, 3] = int(math.ceil(x_hi / res - 0.5)) + 2
    return out


@numba.njit(cache=True, nogil=True)
def _rows_differ(a, b, tol_m, tol_rad):  # type: ignore[no-untyped-def]
    """Per row of two ``(N, 3)`` pose arrays: moved beyond the tolerances (any change at all
    when both are 0; a NaN row always differs)."""
    n = a.shape[0]
    out = np.empty(n, dtype=np.bool_)
    exact = tol_m == 0.0 and tol_rad == 0.0
    for k in range(n):
        if exact:
            out[k] = a[k, 0] != b[k, 0] or a[k, 1] != b[k, 1] or a[k, 2] != b[k, 2]
        else:
            d = (a[k, 2] - b[k, 2] + math.pi) % (2.0 * math.pi) - math.pi
            out[k] = not (
                math.hypot(a[k, 0] - b[k, 0], a[k, 1] - b[k, 1]) <= tol_m and abs(d) <= tol_rad
            )
    return out


# ---------------------------------------------------------------------------------------------

#: ``{key: (x, y, theta)}`` or ``(keys (N,), poses (N, 3))``, poses in ``map``.
PosesInMap = Mapping[int, ArrayLike] | tuple[ArrayLike, ArrayLike]


class Rasterizer:
    """Global map rasterization with covering and cached submaps (paper 4.8).

    Feed every node's grid once with :meth:`add_node`; call :meth:`rasterize` with the current
    posterior whenever a map is needed. :meth:`rasterize_naive` is the reference (every node,
    nothing cached) that :meth:`rasterize` equals cell for cell when the pose tolerances are 0.
    Not thread-safe.
    """

    def __init__(self, config: RasterConfig | None = None) -> None:
        self.config = config if config is not None else RasterConfig()
        self.stats = RasterStats()
        self._n = 0
        self._keys: list[int] = []
        self._rasters: list[LocalRaster] = []
        self._index: dict[int, int] = {}
        # per-node arrays with spare capacity (rows [0, _n) are valid)
        self._keys_arr = np.zeros(0, dtype=np.int64)
        self._times_arr = np.zeros(0)
        self._rect = np.zeros((0, 4))  # local raster rectangle in base: ox, oy, width, height
        self._lres = np.zeros(0)  # local raster resolution
        self._cells = TypedList.empty_list(numba.types.int8[:, ::1])  # local raster cells
        self._feet_pose = np.zeros((0, 3))  # pose each footprint was sampled at (NaN: none)
        self._feet = FootprintPool()
        self._sorted_n = -1
        self._sorted_keys = np.zeros(0, dtype=np.int64)
        self._sorted_idx = np.zeros(0, dtype=np.int64)
        # submaps: each node's submap, whether it is drawn there and at which pose
        self._submaps: list[_Submap] = []
        self._sub_codes = TypedList.empty_list(numba.types.uint8[:, ::1])
        self._sub_table = np.full((0, MAX_SUBMAP_NODES), -1, dtype=np.int64)  # sid, i -> node
        self._open: dict[int, int] = {}  # robot -> index of its submap still taking nodes
        self._sub_of = np.zeros(0, dtype=np.int64)
        self._local = np.zeros(0, dtype=np.int64)  # index of each node in its submap
        self._drawn = np.zeros(0, dtype=bool)
        self._drawn_pose = np.zeros((0, 3))
        # the combined map by tile: values in slots of a store, and the submaps with cells there
        self._tile_subs: dict[tuple[int, int], set[int]] = {}
        self._tile_slot: dict[tuple[int, int], int] = {}
        self._free_slots: list[int] = []
        t = self.config.tile_cells
        self._tile_store = np.zeros((0, t, t), dtype=np.int8)
        self._tile_used = np.zeros(0, dtype=bool)
        self._tile_rc = np.zeros((0, 2), dtype=np.int64)
        # the last assembled map and its extent (reused when the extent is unchanged)
        self._map: NDArray[np.int8] | None = None
        self._map_bounds = (0, 0, 0, 0)

    # -- input ------------------------------------------------------------------------------

    def __len__(self) -> int:
        return self._n

    def __contains__(self, key: object) -> bool:
        return key in self._index

    def add_node(
        self,
        key: int,
        time_s: float,
        grid: NDArray[np.bool_],
        origin_in_base: tuple[float, float],
        resolution_m: float,
        *,
        robot_id: int | None = None,
    ) -> None:
        """Add pose node ``key`` observed at ``time_s`` with its binary vertical-surface grid
        (cell ``(row, col)`` covers ``origin_in_base + (col, row) * resolution_m`` in the
        node's ``base``; bool or 0/1, possibly ``0 x 0``). ``robot_id`` groups nodes into
        submaps; by default ``key >> 32`` (``gcs.graph.keys`` pose keys). Free space is
        inferred here, once. Raises ValueError naming the node on bad input or a repeated key.
        """
        where = f"rasterizer node {key!r}"
        if isinstance(key, bool) or not isinstance(key, int | np.integer):
            raise ValueError(f"{where}: key must be an integer")
        key = int(key)
        if not -(1 << 63) <= key < (1 << 63):
            raise ValueError(f"{where}: key does not fit in 64 bits")
        if key in self._index:
            raise ValueError(f"{where}: already added")
        t = float(time_s)
        if not math.isfinite(t):
            raise ValueError(f"{where}: time_s must be finite, got {time_s!r}")
        raster = local_raster(
            grid,
            origin_in_base,
            resolution_m,
            free_range_m=self.config.free_range_m,
            free_fov_rad=self.config.free_fov_rad,
            wall_gap_m=self.config.wall_gap_m,
            where=where,
        )
        robot = int(robot_id) if robot_id is not None else (key >> 32 if key >= 0 else -1)
        n = self._n
        if n == len(self._keys_arr):
            self._grow(max(64, 2 * n))
        self._keys.append(key)
        self._rasters.append(raster)
        self._index[key] = n
        self._keys_arr[n] = key
        self._times_arr[n] = t
        rows, cols = raster.cells.shape
        res = raster.resolution_m
        self._rect[n] = (*raster.origin_in_base, cols * res, rows * res)
        self._lres[n] = res
        self._cells.append(raster.cells)
        self._feet_pose[n] = np.nan
        self._feet.add_node()
        self._n = n + 1
        sid = self._open.get(robot)
        if sid is None or len(self._submaps[sid].nodes) >= self.config.submap_nodes:
            sid = len(self._submaps)
            self._submaps.append(_Submap(nodes=[]))
            self._sub_codes.append(self._submaps[sid].codes)
            self._open[robot] = sid
            if sid == len(self._sub_table):
                table = np.full((max(16, 2 * sid), MAX_SUBMAP_NODES), -1, dtype=np.int64)
                table[:sid] = self._sub_table
                self._sub_table = table
        sub = self._submaps[sid]
        self._local[n] = len(sub.nodes)
        self._sub_table[sid, len(sub.nodes)] = n
        sub.nodes.append(n)
        self._sub_of[n] = sid
        self._drawn[n] = False

    def local_raster(self, key: int) -> LocalRaster:
        """The occupied / free / unknown raster of node ``key`` in its ``base`` frame."""
        return self._rasters[self._index[int(key)]]

    # -- output -----------------------------------------------------------------------------

    def rasterize(self, poses_in_map: PosesInMap) -> OccupancyMap:
        """The global map for the posterior ``poses_in_map`` (``{key: (x, y, theta)}`` or
        ``(keys (N,), poses (N, 3))``), with the covering and the cached submaps as
        configured. Nodes without a pose are left out; keys without a node are counted in
        ``stats.unknown_keys``. Raises ValueError on non-finite poses or a map larger than
        ``max_map_cells``."""
        t0 = time.perf_counter()
        cfg = self.config
        poses, posed, unknown = self._poses(poses_in_map)
        prio = self._prio()
        bbox = _node_bboxes(poses, self._rect[: self._n], cfg.resolution_m)
        bounds = self._bounds(bbox, posed)
        patches: dict[int, NDArray[np.int8]] = {}
        sampled = 0
        if cfg.cover:
            sampled = self._update_feet(poses, posed, bbox, patches)
            order = np.flatnonzero(posed)
            order = order[np.argsort(-prio[order], kind="stable")]
            blocks = (
                bounds[0] // BLOCK_CELLS,
                -(-bounds[1] // BLOCK_CELLS),
                bounds[2] // BLOCK_CELLS,
                -(-bounds[3] // BLOCK_CELLS),
            )
            kept = cover_sweep(order, self._feet, blocks)
        else:
            kept = posed.copy()
        stats = RasterStats(
            nodes=int(posed.sum()),
            kept=int(kept.sum()),
            sampled=sampled,
            submaps=len(self._submaps),
            unknown_keys=unknown,
        )
        if cfg.cache:
            values = self._cached(poses, posed, kept, prio, bbox, bounds, patches, stats)
        else:
            nodes = np.flatnonzero(kept)
            codes = self._draw_all(nodes, prio, poses, bbox, bounds, patches)
            stats.drawn = len(nodes)
            values = _values(codes)
        stats.cells = int(values.size)
        stats.seconds = time.perf_counter() - t0
        self.stats = stats
        return self._result(values, bounds)

    def rasterize_naive(self, poses_in_map: PosesInMap) -> OccupancyMap:
        """The reference map: every node with a pose drawn in ``(time, key)`` order, latest
        on top; no covering, no cache. Leaves the caches alone."""
        t0 = time.perf_counter()
        poses, posed, unknown = self._poses(poses_in_map)
        prio = self._prio()
        bbox = _node_bboxes(poses, self._rect[: self._n], self.config.resolution_m)
        bounds = self._bounds(bbox, posed)
        nodes = np.flatnonzero(posed)
        codes = self._draw_all(nodes, prio, poses, bbox, bounds, {})
        values = _values(codes)
        self.stats = RasterStats(
            nodes=len(nodes),
            kept=len(nodes),
            drawn=len(nodes),
            unknown_keys=unknown,
            cells=int(values.size),
            seconds=time.perf_counter() - t0,
        )
        return self._result(values, bounds)

    def latest_observers(self, poses_in_map: PosesInMap) -> NDArray[np.int64]:
        """Keys of the nodes that are the latest observer of at least one cell, by the naive
        path: exactly the nodes the covering must keep (sorted)."""
        poses, posed, _ = self._poses(poses_in_map)
        prio = self._prio()
        bbox = _node_bboxes(poses, self._rect[: self._n], self.config.resolution_m)
        codes = self._draw_all(
            np.flatnonzero(posed), prio, poses, bbox, self._bounds(bbox, posed), {}
        )
        owners = np.unique(codes[codes != 0] >> 1) - 1
        return np.sort(self._keys_arr[owners])

    # -- internals --------------------------------------------------------------------------

    def _grow(self, cap: int) -> None:
        n = self._n

        def grown(a: NDArray[np.generic], fill: float) -> NDArray[np.generic]:
            out = np.full((cap, *a.shape[1:]), fill, dtype=a.dtype)
            out[:n] = a[:n]
            return out

        self._keys_arr = grown(self._keys_arr, 0)  # type: ignore[assignment]
        self._times_arr = grown(self._times_arr, 0.0)  # type: ignore[assignment]
        self._rect = grown(self._rect, 0.0)  # type: ignore[assignment]
        self._lres = grown(self._lres, 0.0)  # type: ignore[assignment]
        self._feet_pose = grown(self._feet_pose, np.nan)  # type: ignore[assignment]
        self._sub_of = grown(self._sub_of, 0)  # type: ignore[assignment]
        self._local = grown(self._local, 0)  # type: ignore[assignment]
        self._drawn = grown(self._drawn, False)  # type: ignore[assignment]
        self._drawn_pose = grown(self._drawn_pose, np.nan)  # type: ignore[assignment]

    def _poses(
        self, poses_in_map: PosesInMap
    ) -> tuple[NDArray[np.float64], NDArray[np.bool_], int]:
        """``(poses (N, 3), posed (N,), unknown key count)`` aligned with node indices."""
        n = self._n
        if self._sorted_n != n:
            self._sorted_idx = np.argsort(self._keys_arr[:n], kind="stable")
            self._sorted_keys = self._keys_arr[:n][self._sorted_idx]
            self._sorted_n = n
        if isinstance(poses_in_map, Mapping):
            keys = np.fromiter(
                (int(k) for k in poses_in_map), dtype=np.int64, count=len(poses_in_map)
            )
            values = [np.asarray(v, dtype=np.float64) for v in poses_in_map.values()]
            for k, v in zip(keys, values, strict=True):
                if v.shape != (3,):
                    raise ValueError(f"pose of node {int(k)} must be (x, y, theta), got {v.shape}")
            given = np.stack(values) if values else np.zeros((0, 3))
        elif isinstance(poses_in_map, tuple) and len(poses_in_map) == 2:
            keys = np.asarray(poses_in_map[0]).reshape(-1)
            if keys.size and not np.issubdtype(keys.dtype, np.integer):
                raise ValueError(f"pose keys must be integers, got dtype {keys.dtype}")
            keys = keys.astype(np.int64)
            given = np.asarray(poses_in_map[1], dtype=np.float64)
            if given.shape != (len(keys), 3):
                raise ValueError(
                    f"poses must be ({len(keys)}, 3) for {len(keys)} keys, got {given.shape}"
                )
        else:
            raise ValueError("poses_in_map must be {key: (x, y, theta)} or (keys, poses)")
        bad = ~np.all(np.isfinite(given), axis=1)
        if bad.any():
            raise ValueError(f"pose of node {int(keys[np.argmax(bad)])} is not finite")
        poses = np.zeros((n, 3))
        posed = np.zeros(n, dtype=bool)
        if len(keys) == 0 or n == 0:
            return poses, posed, len(keys)
        pos = np.minimum(np.searchsorted(self._sorted_keys, keys), n - 1)
        known = self._sorted_keys[pos] == keys
        idx = self._sorted_idx[pos[known]]
        if len(np.unique(idx)) != len(idx):
            raise ValueError("poses_in_map names a node twice")
        poses[idx] = given[known]
        posed[idx] = True
        return poses, posed, int((~known).sum())

    def _prio(self) -> NDArray[np.int64]:
        """Rank of every node in ``(time, key)`` order (later = larger). Adding nodes never
        changes the relative order of the others, so cached codes stay comparable."""
        order = np.lexsort((self._keys_arr[: self._n], self._times_arr[: self._n]))
        prio = np.empty(len(order), dtype=np.int64)
        prio[order] = np.arange(len(order))
        return prio

    def _bounds(
        self, bbox: NDArray[np.int64], posed: NDArray[np.bool_]
    ) -> tuple[int, int, int, int]:
        """Map-cell box ``(row_lo, row_hi, col_lo, col_hi)`` of the map: every posed node's."""
        if not posed.any():
            return 0, 0, 0, 0
        b = bbox[posed]
        row0, row1 = int(b[:, 0].min()), int(b[:, 1].max())
        col0, col1 = int(b[:, 2].min()), int(b[:, 3].max())
        cells = (row1 - row0) * (col1 - col0)
        if cells > self.config.max_map_cells:
            res = self.config.resolution_m
            raise ValueError(
                f"rasterizer: the nodes span {(col1 - col0) * res:.0f} x {(row1 - row0) * res:.0f}"
                f" m, {cells} cells > max_map_cells {self.config.max_map_cells}"
            )
        return row0, row1, col0, col1

    def _result(self, values: NDArray[np.int8], bounds: tuple[int, int, int, int]) -> OccupancyMap:
        res = self.config.resolution_m
        return OccupancyMap(values, (bounds[2] * res, bounds[0] * res), res)

    def _draw(
        self,
        buf: NDArray[np.int32] | NDArray[np.uint8],
        row0: int,
        col0: int,
        n: int,
        code: int,
        code_prio: NDArray[np.int64],
        poses: NDArray[np.float64],
        bbox: NDArray[np.int64],
        patches: dict[int, NDArray[np.int8]],
        *,
        latest_wins: bool,
    ) -> None:
        """Draw node ``n`` into ``buf`` as codes ``2 (code + 1) + occupied``: from its patch
        when this call sampled it already, else by sampling. ``latest_wins``: keep cells
        whose code's ``code_prio`` is larger; otherwise overwrite (the caller draws in
        ``(time, key)`` order)."""
        node_prio = int(code_prio[code]) if latest_wins else -1
        base = 2 * code + 1
        patch = patches.get(n)
        if patch is not None:
            _draw_patch(buf, row0, col0, patch, bbox[n, 0], bbox[n, 2], base, code_prio, node_prio)
            return
        r = self._rasters[n]
        if r.cells.size == 0:
            return
        x, y, yaw = poses[n]
        ox, oy = r.origin_in_base
        _sample(buf, row0, col0, base, r.cells, ox, oy, r.resolution_m, x, y, yaw,
                self.config.resolution_m, bbox[n], code_prio, node_prio, _NO_MASKS)  # fmt: skip

    def _draw_all(
        self,
        nodes: NDArray[np.int64],
        prio: NDArray[np.int64],
        poses: NDArray[np.float64],
        bbox: NDArray[np.int64],
        bounds: tuple[int, int, int, int],
        patches: dict[int, NDArray[np.int8]],
    ) -> NDArray[np.int32]:
        codes = np.zeros((bounds[1] - bounds[0], bounds[3] - bounds[2]), dtype=np.int32)
        for n in nodes[np.argsort(prio[nodes], kind="stable")].tolist():
            self._draw(codes, bounds[0], bounds[2], n, n, prio, poses, bbox, patches,
                       latest_wins=False)  # fmt: skip
        return codes

    def _update_feet(
        self,
        poses: NDArray[np.float64],
        posed: NDArray[np.bool_],
        bbox: NDArray[np.int64],
        patches: dict[int, NDArray[np.int8]],
    ) -> int:
        """Sample the nodes whose pose changed (beyond the tolerances): their footprints,
        and (within the budget) patches to draw them from."""
        n_all = self._n
        changed = np.flatnonzero(posed & self._moved(poses, self._feet_pose[:n_all]))
        if len(changed) == 0:
            return 0
        b = bbox[changed]
        size = (b[:, 1] - b[:, 0]) * (b[:, 3] - b[:, 2])
        blocks = np.empty((len(changed), 5), dtype=np.int64)
        blocks[:, 0] = b[:, 0] // BLOCK_CELLS
        blocks[:, 1] = b[:, 2] // BLOCK_CELLS
        blocks[:, 2] = (b[:, 1] - 1) // BLOCK_CELLS - blocks[:, 0] + 1
        blocks[:, 3] = (b[:, 3] - 1) // BLOCK_CELLS - blocks[:, 1] + 1
        words = 4 * blocks[:, 2] * blocks[:, 3]
        # chunks of at most the patch budget; only the first chunk's patches are kept
        ends = np.cumsum(size)
        lo = 0
        while lo < len(changed):
            hi = max(
                lo + 1,
                int(np.searchsorted(ends, ends[lo] - size[lo] + _PATCH_BUDGET_BYTES, "right")),
            )
            nodes = changed[lo:hi]
            patch_off = np.concatenate([[0], np.cumsum(size[lo:hi])])
            chunk_blocks = blocks[lo:hi].copy()
            chunk_blocks[:, 4] = np.cumsum(words[lo:hi]) - words[lo:hi]
            flat = np.zeros(int(patch_off[-1]), dtype=np.int8)
            masks = np.zeros(int(words[lo:hi].sum()), dtype=np.int64)
            rows, counts = _sample_feet(
                nodes, poses, bbox, self._rect, self._lres, self._cells,
                self.config.resolution_m, flat, patch_off, chunk_blocks, masks,
            )  # fmt: skip
            self._feet.set_many(nodes, rows, counts)
            if lo == 0:
                for k, n in enumerate(nodes.tolist()):
                    shape = (int(bbox[n, 1] - bbox[n, 0]), int(bbox[n, 3] - bbox[n, 2]))
                    patches[n] = flat[patch_off[k] : patch_off[k + 1]].reshape(shape)
            lo = hi
        self._feet_pose[changed] = poses[changed]
        return len(changed)

    def _moved(self, now: NDArray[np.float64], then: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Per row: did the pose move beyond the tolerance (any change when it is 0)?"""
        cfg = self.config
        return _rows_differ(now, then, cfg.pose_tolerance_m, cfg.pose_tolerance_rad)  # type: ignore[no-any-return]

    def _cached(
        self,
        poses: NDArray[np.float64],
        posed: NDArray[np.bool_],
        kept: NDArray[np.bool_],
        prio: NDArray[np.int64],
        bbox: NDArray[np.int64],
        bounds: tuple[int, int, int, int],
        patches: dict[int, NDArray[np.int8]],
        stats: RasterStats,
    ) -> NDArray[np.int8]:
        """Bring the submaps up to date (reuse; extend by newly kept nodes; redraw when a
        drawn node moved or lost its pose), combine again only the tiles whose submaps
        changed, and assemble the map."""
        n = self._n
        sub_of = self._sub_of[:n]
        drawn = self._drawn[:n]
        stale = drawn & (~posed | self._moved(poses, self._drawn_pose[:n]))
        redraw = np.unique(sub_of[stale])
        add = kept & ~drawn & ~np.isin(sub_of, redraw)
        extend = np.unique(sub_of[add])
        dirty: set[tuple[int, int]] = set()
        for sid in redraw.tolist():
            sub = self._submaps[sid]
            idx = np.asarray(sub.nodes, dtype=np.int64)
            now = idx[kept[idx]]
            self._redraw(sid, sub, now, poses, bbox, prio, patches, dirty)
            self._drawn[idx] = False
            self._drawn[now] = True
            self._drawn_pose[now] = poses[now]
            stats.drawn += len(now)
        for sid in extend.tolist():
            sub = self._submaps[sid]
            idx = np.asarray(sub.nodes, dtype=np.int64)
            now = idx[add[idx]]
            self._extend(sid, sub, now, poses, bbox, prio, patches, dirty)
            self._drawn[now] = True
            self._drawn_pose[now] = poses[now]
            stats.drawn += len(now)
        stats.rebuilt = len(redraw) + len(extend)
        stats.reused = len(self._submaps) - stats.rebuilt
        self._combine_dirty(dirty, prio)
        stats.dirty_tiles = len(dirty)
        row0, row1, col0, col1 = bounds
        values = self._map
        if values is None or self._map_bounds != bounds:
            values = np.full((row1 - row0, col1 - col0), UNKNOWN, dtype=np.int8)
            _assemble(values, row0, col0, self._tile_store, self._tile_used, self._tile_rc)
            self._map, self._map_bounds = values, bounds
        else:  # the same extent as last time: only the dirty tiles change
            t = self.config.tile_cells
            for key in dirty:
                i0, j0 = key[0] * t, key[1] * t
                a0, a1 = max(i0, row0), min(i0 + t, row1)
                b0, b1 = max(j0, col0), min(j0 + t, col1)
                if a0 >= a1 or b0 >= b1:
                    continue
                slot = self._tile_slot.get(key)
                region = values[a0 - row0 : a1 - row0, b0 - col0 : b1 - col0]
                if slot is None:
                    region[:] = UNKNOWN
                else:
                    region[:] = self._tile_store[slot, a0 - i0 : a1 - i0, b0 - j0 : b1 - j0]
        return values.copy()

    def _combine_dirty(self, dirty: set[tuple[int, int]], prio: NDArray[np.int64]) -> None:
        """Recompute the values of the ``dirty`` tiles from the submaps that have them."""
        t = self.config.tile_cells
        slots: list[int] = []
        ptr = [0]
        sub_ids: list[int] = []
        sub_i0: list[int] = []
        sub_j0: list[int] = []
        spans: list[tuple[int, int, int, int]] = []
        for key in dirty:
            subs = self._tile_subs.get(key)
            if not subs:
                self._tile_subs.pop(key, None)
                slot = self._tile_slot.pop(key, None)
                if slot is not None:
                    self._tile_used[slot] = False
                    self._free_slots.append(slot)
                continue
            slot = self._tile_slot.get(key)
            if slot is None:
                slot = self._new_slot()
                self._tile_slot[key] = slot
                self._tile_used[slot] = True
                self._tile_rc[slot] = key
            slots.append(slot)
            for sid in subs:
                sub = self._submaps[sid]
                sub_ids.append(sid)
                sub_i0.append(key[0] * t - sub.row0)
                sub_j0.append(key[1] * t - sub.col0)
                spans.append(sub.tiles[key])
            ptr.append(len(sub_ids))
        if slots:
            table = self._sub_table[: len(self._submaps)]
            node_rank = np.where(table >= 0, 2 * (prio[table] + 1), 0).astype(np.int32)
            rank = np.zeros((len(table), 256), dtype=np.int32)
            rank[:, 2 : 2 + 2 * MAX_SUBMAP_NODES : 2] = node_rank
            rank[:, 3 : 3 + 2 * MAX_SUBMAP_NODES : 2] = node_rank + (node_rank > 0)
            _combine_tiles(
                np.asarray(slots, dtype=np.int64),
                np.asarray(ptr, dtype=np.int64),
                np.asarray(sub_ids, dtype=np.int64),
                np.asarray(sub_i0, dtype=np.int64),
                np.asarray(sub_j0, dtype=np.int64),
                np.asarray(spans, dtype=np.int64).reshape(-1, 4),
                self._sub_codes,
                rank,
                self._tile_store,
            )

    def _new_slot(self) -> int:
        if not self._free_slots:
            cap = len(self._tile_used)
            new = max(64, 2 * cap)
            t = self.config.tile_cells
            store = np.zeros((new, t, t), dtype=np.int8)
            store[:cap] = self._tile_store
            used = np.zeros(new, dtype=bool)
            used[:cap] = self._tile_used
            rc = np.zeros((new, 2), dtype=np.int64)
            rc[:cap] = self._tile_rc
            self._tile_store, self._tile_used, self._tile_rc = store, used, rc
            self._free_slots.extend(range(new - 1, cap - 1, -1))
        return self._free_slots.pop()

    def _tiles_of(
        self, sub: _Submap, box: tuple[int, int, int, int]
    ) -> dict[tuple[int, int], tuple[int, int, int, int]]:
        """Tiles of ``sub`` within map-cell ``box`` (tile-aligned) that hold a cell, with the
        row and column range ``(r0, r1, c0, c1)`` of its cells within each."""
        t = self.config.tile_cells
        i0, i1, j0, j1 = box
        view = sub.codes[i0 - sub.row0 : i1 - sub.row0, j0 - sub.col0 : j1 - sub.col0]
        spans = _tile_spans(view, t).tolist()
        return {(i0 // t + a, j0 // t + b): (r0, r1, c0, c1) for a, b, r0, r1, c0, c1 in spans}

    def _tile_box(self, bbox: NDArray[np.int64]) -> tuple[int, int, int, int]:
        """Tile-aligned map-cell box around the boxes ``bbox`` ``(K, 4)``."""
        t = self.config.tile_cells
        return (
            int(bbox[:, 0].min()) // t * t,
            -(-int(bbox[:, 1].max()) // t) * t,
            int(bbox[:, 2].min()) // t * t,
            -(-int(bbox[:, 3].max()) // t) * t,
        )

    def _set_tiles(
        self, sid: int, sub: _Submap, tiles: dict[tuple[int, int], tuple[int, int, int, int]]
    ) -> None:
        for key in sub.tiles.keys() - tiles.keys():
            self._tile_subs[key].discard(sid)
        for key in tiles.keys() - sub.tiles.keys():
            self._tile_subs.setdefault(key, set()).add(sid)
        sub.tiles = tiles

    def _redraw(
        self,
        sid: int,
        sub: _Submap,
        draw: NDArray[np.int64],
        poses: NDArray[np.float64],
        bbox: NDArray[np.int64],
        prio: NDArray[np.int64],
        patches: dict[int, NDArray[np.int8]],
        dirty: set[tuple[int, int]],
    ) -> None:
        """Draw ``sub`` afresh from the nodes ``draw``, earliest first."""
        dirty.update(sub.tiles)
        if len(draw) == 0:
            sub.codes = np.zeros((0, 0), dtype=np.uint8)
            self._sub_codes[sid] = sub.codes
            self._set_tiles(sid, sub, {})
            return
        box = self._tile_box(bbox[draw])
        sub.row0, sub.col0 = box[0], box[2]
        sub.codes = np.zeros((box[1] - box[0], box[3] - box[2]), dtype=np.uint8)
        self._sub_codes[sid] = sub.codes
        local_prio = prio[np.asarray(sub.nodes, dtype=np.int64)]
        for n in draw[np.argsort(prio[draw], kind="stable")].tolist():
            self._draw(sub.codes, sub.row0, sub.col0, n, int(self._local[n]), local_prio,
                       poses, bbox, patches, latest_wins=False)  # fmt: skip
        self._set_tiles(sid, sub, self._tiles_of(sub, box))
        dirty.update(sub.tiles)

    def _extend(
        self,
        sid: int,
        sub: _Submap,
        add: NDArray[np.int64],
        poses: NDArray[np.float64],
        bbox: NDArray[np.int64],
        prio: NDArray[np.int64],
        patches: dict[int, NDArray[np.int8]],
        dirty: set[tuple[int, int]],
    ) -> None:
        """Draw the nodes ``add`` into ``sub`` keeping later nodes' cells (latest wins is
        associative, so this equals drawing the submap afresh)."""
        box = self._tile_box(bbox[add])
        if sub.codes.size:
            h, w = sub.codes.shape
            grown = (
                min(box[0], sub.row0),
                max(box[1], sub.row0 + h),
                min(box[2], sub.col0),
                max(box[3], sub.col0 + w),
            )
        else:
            grown = box
        if sub.codes.size == 0 or grown != (sub.row0, sub.row0 + h, sub.col0, sub.col0 + w):
            codes = np.zeros((grown[1] - grown[0], grown[3] - grown[2]), dtype=np.uint8)
            if sub.codes.size:
                i0, j0 = sub.row0 - grown[0], sub.col0 - grown[2]
                codes[i0 : i0 + h, j0 : j0 + w] = sub.codes
            sub.codes, sub.row0, sub.col0 = codes, grown[0], grown[2]
            self._sub_codes[sid] = codes
        local_prio = prio[np.asarray(sub.nodes, dtype=np.int64)]
        for n in add.tolist():
            self._draw(sub.codes, sub.row0, sub.col0, n, int(self._local[n]), local_prio,
                       poses, bbox, patches, latest_wins=True)  # fmt: skip
        touched = self._tiles_of(sub, box)
        self._set_tiles(sid, sub, sub.tiles | touched)
        dirty.update(touched)
