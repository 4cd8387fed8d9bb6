"""Pessimistic fusion of the last single-sweep terrain maps (paper 5.3, third stage).

Each sweep's drivability map (:func:`robot.terrain.classifier.classify_sweep`) is kept in the
robot's private frame ``odom``, where the robot's trajectory is smooth (paper 4.1). The fused
map is pessimistic: a cell is an obstacle if *any* remembered sweep marked it, drivable if some
sweep saw it drivable and none marked it, unknown otherwise. Only the most recent
``memory_sweeps`` maps are kept (12 in the paper, about 15 s): odometry drift makes old
obstacles appear in the wrong place, and forgetting them lets a robot stuck behind such an
artifact move again once it is gone.

Newer evidence of free ground (``clear_after_sweeps``, 0 = the paper's pure pessimism): an
obstacle mark is dropped once at least that many *later* sweeps saw the same cell drivable
(ground-level points in the cell and no step). A moving teammate or person leaves a trail of
obstacle marks along its way that pure pessimism keeps for 15 s, closing corridors it has
long left; two fresh looks at bare ground there are a better account of the present. A
static obstacle is marked again by nearly every sweep that sees the cell, so it stays: a
cell is only cleared by sweeps that saw points on the ground in it and nothing higher.

All maps share one cell lattice in ``odom`` (:meth:`GridGeometry.centered` snaps origins), so
fusion is integer shifts and logical ors, ``O(memory_sweeps * rows * cols)``.
"""

from __future__ import annotations

import math
from collections import deque

import numpy as np
from numpy.typing import NDArray

from robot.terrain.grid import DRIVABLE, OBSTACLE, UNKNOWN, GridGeometry

__all__ = ["TerrainMapFusion"]


class TerrainMapFusion:
    """The last ``memory_sweeps`` single-sweep maps in ``odom`` and their pessimistic union."""

    def __init__(self, *, memory_sweeps: int = 12, clear_after_sweeps: int = 0) -> None:
        if memory_sweeps < 1:
            raise ValueError(f"memory_sweeps must be >= 1, got {memory_sweeps}")
        if not 0 <= clear_after_sweeps <= 1000:
            raise ValueError(f"clear_after_sweeps must be in [0, 1000], got {clear_after_sweeps}")
        self.memory_sweeps = memory_sweeps
        self.clear_after_sweeps = clear_after_sweeps
        self._maps: deque[tuple[tuple[int, int], NDArray[np.bool_], NDArray[np.bool_]]] = deque(
            maxlen=memory_sweeps
        )
        self._resolution_m: float | None = None

    def __len__(self) -> int:
        return len(self._maps)

    def clear(self) -> None:
        self._maps.clear()

    def add(self, classes: NDArray[np.uint8], geometry: GridGeometry) -> None:
        """Remember one sweep's map (``uint8`` classes laid out by ``geometry`` in ``odom``);
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
        self._check_lattice(geometry)
        self._maps.append((geometry.lattice_index(), classes == OBSTACLE, classes == DRIVABLE))

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

    def fused(self, geometry: GridGeometry) -> NDArray[np.uint8]:
        """The pessimistic union of the remembered maps over ``geometry`` (same lattice),
        less obstacle marks that ``clear_after_sweeps`` later sweeps saw drivable."""
        self._check_lattice(geometry)
        r0, c0 = geometry.lattice_index()
        obstacle = np.zeros(geometry.shape, dtype=bool)
        drivable = np.zeros(geometry.shape, dtype=bool)
        k = self.clear_after_sweeps
        later_drivable = np.zeros(geometry.shape, dtype=np.uint16) if k else None
        for (mr, mc), obs, drv in reversed(self._maps):  # newest first
            dr, dc = mr - r0, mc - c0  # map cell (i, j) is output cell (i + dr, j + dc)
            out_r = slice(max(0, dr), min(geometry.rows, dr + obs.shape[0]))
            out_c = slice(max(0, dc), min(geometry.cols, dc + obs.shape[1]))
            if out_r.start >= out_r.stop or out_c.start >= out_c.stop:
                continue
            in_r = slice(out_r.start - dr, out_r.stop - dr)
            in_c = slice(out_c.start - dc, out_c.stop - dc)
            if later_drivable is None:
                obstacle[out_r, out_c] |= obs[in_r, in_c]
            else:
                seen_free = later_drivable[out_r, out_c]
                obstacle[out_r, out_c] |= obs[in_r, in_c] & (seen_free < k)
                seen_free += drv[in_r, in_c]
            drivable[out_r, out_c] |= drv[in_r, in_c]
        out = np.full(geometry.shape, UNKNOWN, dtype=np.uint8)
        out[drivable] = DRIVABLE
        out[obstacle] = OBSTACLE
        return out
