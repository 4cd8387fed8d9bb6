"""Pessimistic fusion of the last single-sweep terrain maps (paper 5.3, third stage).

Each sweep's drivability map (:func:`robot.terrain.classifier.classify_sweep`) is kept in the
robot's private frame ``odom``, where the robot's trajectory is smooth (paper 4.1). The fused
map is pessimistic: a cell is an obstacle if *any* remembered sweep marked it, drivable if some
sweep saw it drivable and none marked it, unknown otherwise. Only the most recent
``memory_sweeps`` maps are kept (12 in the paper, about 15 s): odometry drift makes old
obstacles appear in the wrong place, and forgetting them lets a robot stuck behind such an
artifact move again once it is gone.

Newer evidence of free space (``clear_after_sweeps``, 0 = the paper's pure pessimism): an
obstacle mark is dropped once at least that many *later* sweeps saw the cell free of it:
drivable (ground-level points and no step), or crossed by a beam no higher than the mark's
top less ``clear_margin_m`` (:mod:`robot.terrain.free_space`). A moving teammate or person leaves
a trail of obstacle marks along its way that pure pessimism keeps for 15 s, closing
corridors it has long left; beams now passing through where it was are a better account of
the present. A static obstacle stops the beams that reach it, and is marked again by nearly
every sweep that sees it, so it stays. Without heights (:meth:`TerrainMapFusion.add` given
classes only) a mark is only cleared by drivable observations.

Heights are kept in whole centimetres (``uint8``, up to 2.54 m; higher is "tall").

All maps share one cell lattice in ``odom`` (:meth:`GridGeometry.centered` snaps origins), so
fusion is integer shifts and logical ors, ``O(memory_sweeps * rows * cols)``.

Cost (issue 14, session 13; thread CPU, 12 maps of 400 x 400, ``clear_after_sweeps`` 2,
measured at load ~20 on the 2-core machine, same answers as before): :meth:`add` 2.8 ->
1.2 ms (heights to centimetres in one compiled pass; the clearing threshold of a mark kept
with its map), :meth:`fused` 3.2 -> 2.7 ms for a grid after a sweep and 3.2 -> 0.19 ms for
a grid moved by a few cells before the next (a robot replanning between sweeps: the cells
the last answer shares with it are taken from it, a cell's answer depending on the
remembered maps at that cell only).
"""

from __future__ import annotations

import math
from collections import deque

import numba as nb
import numpy as np
from numpy.typing import NDArray

from robot.terrain.grid import DRIVABLE, OBSTACLE, UNKNOWN, GridGeometry

__all__ = ["TerrainMapFusion"]


_NONE = 255  # uint8 centimetres: no free-space evidence / an obstacle of unknown height


@nb.njit(cache=True, nogil=True)
def _cm_kernel(v, fill, out):  # type: ignore[no-untyped-def]
    for i in range(v.shape[0]):
        x = v[i]
        if math.isfinite(x):
            y = np.floor(x * 100.0)
            out[i] = np.uint8(0.0 if y < 0.0 else (254.0 if y > 254.0 else y))
        else:
            out[i] = fill


def _to_cm(v: NDArray[np.float64], *, fill: int) -> NDArray[np.uint8]:
    """Whole centimetres ``floor(100 v)`` clipped to ``[0, 254]``, ``fill`` where not finite:
    one compiled pass, the same values as ``np.clip(np.floor(v * 100), 0, 254)`` (1.39 ->
    0.06 ms at 400 x 400; session 13)."""
    a = np.ascontiguousarray(v, dtype=np.float64)
    out = np.empty(a.shape, dtype=np.uint8)
    _cm_kernel(a.reshape(-1), np.uint8(fill), out.reshape(-1))
    return out


class TerrainMapFusion:
    """The last ``memory_sweeps`` single-sweep maps in ``odom`` and their pessimistic union,
    less what later sweeps saw gone (see the module doc)."""

    def __init__(
        self,
        *,
        memory_sweeps: int = 12,
        clear_after_sweeps: int = 0,
        clear_margin_m: float = 0.05,
    ) -> None:
        if memory_sweeps < 1:
            raise ValueError(f"memory_sweeps must be >= 1, got {memory_sweeps}")
        if not 0 <= clear_after_sweeps <= 3:
            raise ValueError(f"clear_after_sweeps must be in [0, 3], got {clear_after_sweeps}")
        if not (math.isfinite(clear_margin_m) and 0 <= clear_margin_m <= 2.5):
            raise ValueError(f"clear_margin_m must be in [0, 2.5], got {clear_margin_m}")
        self.memory_sweeps = memory_sweeps
        self.clear_after_sweeps = clear_after_sweeps
        self.clear_margin_cm = int(round(clear_margin_m * 100))
        # per map: lattice index, obstacle height (cm, 0 = none), drivable, free height (cm),
        # and the lowest free height (cm) a newer sweep must have seen, at least
        # ``clear_after_sweeps`` times, to clear the map's obstacle mark (where height > 0):
        # ``top - margin + 1`` clipped to [0, 255] (a mark of unknown height has top
        # ``margin + 1``: only drivable ground, free height 0, clears it)
        self._maps: deque[
            tuple[
                tuple[int, int],
                NDArray[np.uint8],
                NDArray[np.bool_],
                NDArray[np.uint8],
                NDArray[np.uint8],
            ]
        ] = deque(maxlen=memory_sweeps)
        self._resolution_m: float | None = None
        # the last fused() / tall() answers and the memory they were made from: a robot
        # standing still asks again for the same cells (replans, line of sight at the
        # control rate) before the next sweep changes anything
        self._version = 0
        self._fused_cache: tuple[int, int, int, NDArray[np.uint8]] | None = None
        self._tall_cache: tuple[int, GridGeometry, int, NDArray[np.bool_]] | None = None

    def __len__(self) -> int:
        return len(self._maps)

    def clear(self) -> None:
        self._maps.clear()
        self._version += 1

    def forget_older(self, *, keep: int) -> None:
        """Forget all but the newest ``keep`` maps (the memory is known to be stale)."""
        if keep < 0:
            raise ValueError(f"keep must be >= 0, got {keep}")
        while len(self._maps) > keep:
            self._maps.popleft()
            self._version += 1

    def add(
        self,
        classes: NDArray[np.uint8],
        geometry: GridGeometry,
        *,
        obstacle_height_m: NDArray[np.float64] | None = None,
        free_height_m: NDArray[np.float64] | None = None,
    ) -> None:
        """Remember one sweep's map (``uint8`` classes laid out by ``geometry`` in ``odom``)
        and optionally its evidence layers (:class:`robot.terrain.classifier.SweepLayers`);
        the oldest map is forgotten once ``memory_sweeps`` are held."""
        classes = np.asarray(classes)
        if classes.shape != geometry.shape:
            raise ValueError(f"classes: shape {classes.shape} does not match {geometry.shape}")
        if classes.dtype != np.uint8:
            raise ValueError(f"classes: expected dtype uint8, got {classes.dtype}")
        if classes.size and int(classes.max()) > OBSTACLE:
            raise ValueError(
                f"classes: values must be UNKNOWN/DRIVABLE/OBSTACLE, got {classes.max()}"
            )
        layers = (("obstacle_height_m", obstacle_height_m), ("free_height_m", free_height_m))
        for name, layer in layers:
            if layer is not None and np.shape(layer) != geometry.shape:
                raise ValueError(f"{name}: shape {np.shape(layer)} does not match {geometry.shape}")
        self._check_lattice(geometry)
        obstacle = classes == OBSTACLE
        drivable = classes == DRIVABLE
        height = np.zeros(geometry.shape, dtype=np.uint8)
        if obstacle_height_m is None:
            height[obstacle] = _NONE
        else:
            h = np.asarray(obstacle_height_m, dtype=np.float64)
            height[obstacle] = np.maximum(_to_cm(h[obstacle], fill=_NONE), 1)
        if free_height_m is None:
            free = np.full(geometry.shape, _NONE, dtype=np.uint8)
        else:
            free = _to_cm(np.asarray(free_height_m, dtype=np.float64), fill=_NONE)
        free[drivable] = 0
        # seen > top - margin, i.e. seen >= top - margin + 1: in [0, 255] for any top <= 254
        # (255, unknown, has top margin + 1), so one uint8 comparison in fused()
        top = height.astype(np.int16)
        top[height == _NONE] = self.clear_margin_cm + 1
        need = np.clip(top - (self.clear_margin_cm - 1), 0, 255).astype(np.uint8)
        self._maps.append((geometry.lattice_index(), height, drivable, free, need))
        self._version += 1

    def _check_lattice(self, geometry: GridGeometry) -> None:
        if self._resolution_m is None:
            self._resolution_m = geometry.resolution_m
        elif not math.isclose(geometry.resolution_m, self._resolution_m, rel_tol=1e-9):
            raise ValueError(
                f"geometry.resolution_m {geometry.resolution_m} differs from the fused maps' "
                f"{self._resolution_m}"
            )
        for k, v in zip(("x", "y"), geometry.origin_m, strict=True):
            cells = v / geometry.resolution_m
            if abs(cells - round(cells)) > 1e-6:
                raise ValueError(
                    f"geometry.origin_m {k}={v} is not on the {geometry.resolution_m} m lattice "
                    "(use GridGeometry.centered)"
                )

    def tall(self, geometry: GridGeometry, min_height_m: float) -> NDArray[np.bool_]:
        """Cells some remembered map marked an obstacle rising at least ``min_height_m``
        above the ground (an obstacle of unknown height counts)."""
        self._check_lattice(geometry)
        r0, c0 = geometry.lattice_index()
        cm = int(math.ceil(min_height_m * 100.0))
        hit = self._tall_cache
        if hit is not None and hit[0] == self._version and hit[1] == geometry and hit[2] == cm:
            return hit[3].copy()
        out = np.zeros(geometry.shape, dtype=bool)
        for (mr, mc), height, _, _, _ in self._maps:
            dr, dc = mr - r0, mc - c0
            out_r = slice(max(0, dr), min(geometry.rows, dr + height.shape[0]))
            out_c = slice(max(0, dc), min(geometry.cols, dc + height.shape[1]))
            if out_r.start >= out_r.stop or out_c.start >= out_c.stop:
                continue
            h = height[out_r.start - dr : out_r.stop - dr, out_c.start - dc : out_c.stop - dc]
            out[out_r, out_c] |= h >= max(cm, 1)
        self._tall_cache = (self._version, geometry, cm, out.copy())
        return out

    def fused(self, geometry: GridGeometry) -> NDArray[np.uint8]:
        """The pessimistic union of the remembered maps over ``geometry`` (same lattice),
        less obstacle marks that ``clear_after_sweeps`` later sweeps saw gone.

        A lattice cell's answer depends only on the remembered maps' values at that cell, not
        on the grid asked for: the last answer is kept with its lattice window, and a grid
        asked while the memory has not changed takes the cells the two share from it and
        computes only the rest (a robot replanning between sweeps has moved a few cells)."""
        self._check_lattice(geometry)
        r0, c0 = geometry.lattice_index()
        rows, cols = geometry.shape
        hit = self._fused_cache
        if hit is None or hit[0] != self._version:
            out = self._fused_window(r0, c0, rows, cols)
        else:
            _, hr, hc, prev = hit
            # the shared window, in lattice cells
            a_r, b_r = max(r0, hr), min(r0 + rows, hr + prev.shape[0])
            a_c, b_c = max(c0, hc), min(c0 + cols, hc + prev.shape[1])
            if a_r >= b_r or a_c >= b_c:
                out = self._fused_window(r0, c0, rows, cols)
            else:
                out = np.empty((rows, cols), dtype=np.uint8)
                out[a_r - r0 : b_r - r0, a_c - c0 : b_c - c0] = prev[
                    a_r - hr : b_r - hr, a_c - hc : b_c - hc
                ]
                # the rest: full-width bands above and below, then the sides of the shared rows
                for wr0, wr1, wc0, wc1 in (
                    (r0, a_r, c0, c0 + cols),
                    (b_r, r0 + rows, c0, c0 + cols),
                    (a_r, b_r, c0, a_c),
                    (a_r, b_r, b_c, c0 + cols),
                ):
                    if wr0 < wr1 and wc0 < wc1:
                        out[wr0 - r0 : wr1 - r0, wc0 - c0 : wc1 - c0] = self._fused_window(
                            wr0, wc0, wr1 - wr0, wc1 - wc0
                        )
        self._fused_cache = (self._version, r0, c0, out.copy())
        return out

    def _fused_window(self, r0: int, c0: int, rows: int, cols: int) -> NDArray[np.uint8]:
        """:meth:`fused` over the ``rows`` x ``cols`` lattice cells from ``(r0, c0)``."""
        shape = (rows, cols)
        obstacle = np.zeros(shape, dtype=bool)
        drivable = np.zeros(shape, dtype=bool)
        k = self.clear_after_sweeps
        # the k lowest free heights seen by newer sweeps, per cell, ascending
        lowest = np.full((k, *shape), _NONE, dtype=np.uint8)
        for (mr, mc), height, drv, free, need in reversed(self._maps):  # newest first
            dr, dc = mr - r0, mc - c0  # map cell (i, j) is output cell (i + dr, j + dc)
            out_r = slice(max(0, dr), min(rows, dr + height.shape[0]))
            out_c = slice(max(0, dc), min(cols, dc + height.shape[1]))
            if out_r.start >= out_r.stop or out_c.start >= out_c.stop:
                continue
            in_r = slice(out_r.start - dr, out_r.stop - dr)
            in_c = slice(out_c.start - dc, out_c.stop - dc)
            h = height[in_r, in_c]
            if k == 0:
                obstacle[out_r, out_c] |= h > 0
            else:
                # a mark stays unless k newer sweeps saw the cell free low enough
                seen = lowest[k - 1, out_r, out_c]
                obstacle[out_r, out_c] |= (h > 0) & (seen >= need[in_r, in_c])
                # this map's free height joins the k lowest (insertion, in place)
                f = free[in_r, in_c]
                for j in range(k):
                    cur = lowest[j, out_r, out_c]
                    f_next = np.maximum(cur, f) if j + 1 < k else f
                    np.minimum(cur, f, out=cur)
                    f = f_next
            drivable[out_r, out_c] |= drv[in_r, in_c]
        out = np.full(shape, UNKNOWN, dtype=np.uint8)
        out[drivable] = DRIVABLE
        out[obstacle] = OBSTACLE
        return out
