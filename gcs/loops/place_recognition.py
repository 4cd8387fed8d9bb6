"""Place recognition on pose nodes' scans: a polar (scan-context) descriptor and its index.

A candidate source for loops the Dijkstra projection cannot bound (paper 4.3.3 searches the
projection's window; after a long loop or across lost scans that window is larger than any
match can afford): which earlier node looks like the new one, whatever the graph believes.

**Descriptor** (Kim and Kim 2018, "Scan Context", for a 2-D laser): a node's
vertical-surface points in its ``base`` frame binned on a polar grid of ``rings`` rings of
equal width out to ``max_range_m`` and ``sectors`` sectors of equal angle, starting at the
node's heading; a cell is 1 when any point falls in it (binary: independent of how densely a
surface was sampled, which depends on range and on how many scans the node aggregated).

**Comparison.** A rotation of the node about its own axis shifts the sector columns:
:func:`descriptor_distance` tries every shift and returns the best, its distance
``1 - (sum of the cosine similarities of the columns occupied in both) / (columns occupied in
either)`` (columns seen by only one of the two count as disagreement: two views of the same
place from opposite headings share little, and are far apart), and the yaw that shift stands
for: ``a_from_b``'s yaw is ``shift * 2 pi / sectors`` when ``b``'s columns, rolled by
``shift``, match ``a``'s.

**Ring key.** The occupied fraction of each ring is invariant to that rotation;
:class:`PlaceIndex` ranks stored nodes by the L1 distance of ring keys first (cheap, every
stored node) and compares full descriptors only for the ``prefilter`` nearest (Scan Context's
two-stage search).

Pure: numpy only, no graph. Units: metres, radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import msgspec
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "PlaceDescriptorConfig",
    "PlaceIndex",
    "PlaceMatch",
    "descriptor_distance",
    "polar_descriptor",
    "ring_key",
]

FloatArray = NDArray[Any]


class PlaceDescriptorConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The polar grid of a descriptor (module docstring): ``rings`` x ``sectors`` cells out to
    ``max_range_m``; a descriptor with fewer than ``min_cells`` occupied cells says too little
    to recognize a place (it is never matched)."""

    rings: int = 10
    sectors: int = 60
    max_range_m: float = 10.0
    min_cells: int = 20

    def __post_init__(self) -> None:
        if not 1 <= self.rings <= 100:
            raise ValueError(f"rings: expected 1..100, got {self.rings}")
        if not 4 <= self.sectors <= 720:
            raise ValueError(f"sectors: expected 4..720, got {self.sectors}")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > 0):
            raise ValueError(f"max_range_m: expected > 0, got {self.max_range_m}")
        if self.min_cells < 1:
            raise ValueError(f"min_cells: expected >= 1, got {self.min_cells}")


def polar_descriptor(points_in_base: FloatArray, config: PlaceDescriptorConfig) -> FloatArray:
    """The ``(rings, sectors)`` binary polar grid of points ``(N, 2)`` (metres, ``base``).

    Points beyond ``max_range_m`` are left out; sector 0 starts at the heading (angle 0) and
    sectors run counter-clockwise. Raises ``ValueError`` on malformed or non-finite points.
    """
    pts = np.asarray(points_in_base, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise ValueError(f"polar_descriptor: points must be (N, 2), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("polar_descriptor: points must be finite")
    cfg = config
    out = np.zeros((cfg.rings, cfg.sectors), dtype=np.float32)
    r = np.hypot(pts[:, 0], pts[:, 1])
    keep = r < cfg.max_range_m
    if not keep.any():
        return out
    ring = np.minimum((r[keep] / cfg.max_range_m * cfg.rings).astype(np.int64), cfg.rings - 1)
    ang = np.mod(np.arctan2(pts[keep, 1], pts[keep, 0]), 2.0 * math.pi)
    sector = np.minimum((ang / (2.0 * math.pi) * cfg.sectors).astype(np.int64), cfg.sectors - 1)
    out[ring, sector] = 1.0
    return out


def ring_key(descriptor: FloatArray) -> FloatArray:
    """The rotation-invariant key ``(rings,)``: each ring's occupied fraction."""
    d = np.asarray(descriptor, dtype=np.float64)
    return d.mean(axis=-1)  # type: ignore[no-any-return]


def descriptor_distance(a: FloatArray, b: FloatArray) -> tuple[float, float]:
    """``(distance in [0, 1], yaw_rad)`` of two descriptors over every column shift
    (module docstring); ``yaw_rad`` estimates ``a_from_b``'s yaw, in ``(-pi, pi]``.
    Two empty descriptors are 1 apart (nothing says they are the same place)."""
    da = np.asarray(a, dtype=np.float64)
    db = np.asarray(b, dtype=np.float64)
    if da.shape != db.shape or da.ndim != 2:
        raise ValueError(f"descriptor_distance: shapes {da.shape} and {db.shape} differ")
    dist, shift = _best_shift(da, db[None])
    sectors = da.shape[1]
    yaw = float(shift[0]) * 2.0 * math.pi / sectors
    yaw = math.pi - (math.pi - yaw) % (2.0 * math.pi)
    return float(dist[0]), yaw


def _best_shift(a: FloatArray, bs: FloatArray) -> tuple[FloatArray, NDArray[np.int64]]:
    """Best distance and shift of ``a`` ``(R, S)`` against each of ``bs`` ``(M, R, S)``."""
    s = a.shape[1]
    # rolled[m, k, r, c] = bs[m, r, (c - k) % S]: b's columns rolled by k
    idx = (np.arange(s)[None, :] - np.arange(s)[:, None]) % s
    rolled = bs[:, :, idx]  # (M, R, S_k, S_c)
    rolled = np.moveaxis(rolled, 2, 1)  # (M, K, R, C)
    na = np.linalg.norm(a, axis=0)  # (C,)
    nb = np.linalg.norm(rolled, axis=2)  # (M, K, C)
    dots = np.einsum("rc,mkrc->mkc", a, rolled)
    both = (na[None, None, :] > 0) & (nb > 0)
    either = (na[None, None, :] > 0) | (nb > 0)
    cos = np.where(both, dots / np.maximum(na[None, None, :] * nb, 1e-12), 0.0)
    sim = cos.sum(axis=2) / np.maximum(either.sum(axis=2), 1)  # (M, K)
    k = np.argmax(sim, axis=1)
    best = sim[np.arange(len(bs)), k]
    return 1.0 - best, k.astype(np.int64)


@dataclass(frozen=True)
class PlaceMatch:
    """A stored node that looks like the query: its ``key``, the descriptor ``distance`` and
    the yaw of ``query_from_key`` the best column shift stands for."""

    key: int
    distance: float
    yaw_rad: float


class PlaceIndex:
    """Descriptors of stored nodes, searched by ring key then full descriptor (module
    docstring). Brute force over the ring keys (``(N, rings)``, a few microseconds per
    thousand nodes): it has no build step and takes insertions and replacements at any time."""

    def __init__(self, config: PlaceDescriptorConfig | None = None) -> None:
        self.config = config or PlaceDescriptorConfig()
        cfg = self.config
        self._keys: list[int] = []
        self._row: dict[int, int] = {}
        self._desc = np.zeros((0, cfg.rings, cfg.sectors), dtype=np.float32)
        self._ring = np.zeros((0, cfg.rings), dtype=np.float64)
        self._cells = np.zeros(0, dtype=np.int64)

    def __len__(self) -> int:
        return len(self._keys)

    def __contains__(self, key: object) -> bool:
        return key in self._row

    def describe(self, points_in_base: FloatArray) -> FloatArray:
        return polar_descriptor(points_in_base, self.config)

    def add(self, key: int, descriptor: FloatArray) -> None:
        """Store (or replace) ``key``'s descriptor."""
        cfg = self.config
        d = np.asarray(descriptor, dtype=np.float32)
        if d.shape != (cfg.rings, cfg.sectors):
            raise ValueError(
                f"PlaceIndex.add: key {key}: descriptor shape {d.shape}, need "
                f"{(cfg.rings, cfg.sectors)}"
            )
        k = int(key)
        if k in self._row:
            i = self._row[k]
            self._desc[i] = d
            self._ring[i] = ring_key(d)
            self._cells[i] = int(np.count_nonzero(d))
            return
        if len(self._keys) == len(self._desc):  # grow by doubling
            cap = max(64, 2 * len(self._desc))
            self._desc = _grow(self._desc, cap)
            self._ring = _grow(self._ring, cap)
            self._cells = _grow(self._cells, cap)
        i = len(self._keys)
        self._keys.append(k)
        self._row[k] = i
        self._desc[i] = d
        self._ring[i] = ring_key(d)
        self._cells[i] = int(np.count_nonzero(d))

    def descriptor(self, key: int) -> FloatArray:
        return self._desc[self._row[int(key)]]

    def query(
        self,
        descriptor: FloatArray,
        *,
        allowed: NDArray[np.int64] | None = None,
        k: int = 3,
        prefilter: int = 20,
        max_distance: float = 1.0,
    ) -> list[PlaceMatch]:
        """The ``k`` stored nodes nearest ``descriptor`` (distance at most ``max_distance``),
        nearest first, among ``allowed`` keys (None: all). Nodes with fewer than
        ``min_cells`` occupied cells, and a query with that few, are never matched."""
        cfg = self.config
        d = np.asarray(descriptor, dtype=np.float64)
        n = len(self._keys)
        if n == 0 or k < 1 or np.count_nonzero(d) < cfg.min_cells:
            return []
        rows = np.arange(n)
        if allowed is not None:
            want = np.asarray(allowed, dtype=np.int64)
            rows = np.array([self._row[int(x)] for x in want if int(x) in self._row], dtype=int)
            if len(rows) == 0:
                return []
        rows = rows[self._cells[rows] >= cfg.min_cells]
        if len(rows) == 0:
            return []
        l1 = np.abs(self._ring[rows] - ring_key(d)[None, :]).sum(axis=1)
        near = rows[np.argsort(l1, kind="stable")[: max(prefilter, k)]]
        dist, shift = _best_shift(d, self._desc[near].astype(np.float64))
        order = np.argsort(dist, kind="stable")
        out: list[PlaceMatch] = []
        for o in order[:k]:
            if dist[o] > max_distance:
                break
            yaw = float(shift[o]) * 2.0 * math.pi / cfg.sectors
            yaw = math.pi - (math.pi - yaw) % (2.0 * math.pi)
            out.append(PlaceMatch(self._keys[int(near[o])], float(dist[o]), yaw))
        return out


def _grow(arr: NDArray[Any], cap: int) -> NDArray[Any]:
    out = np.zeros((cap, *arr.shape[1:]), dtype=arr.dtype)
    out[: len(arr)] = arr
    return out
