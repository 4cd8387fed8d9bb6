"""Regular 2D grids over the ground plane, shared by terrain classification and path planning.

A :class:`GridGeometry` places a ``(rows, cols)`` array in a frame (``odom`` for the terrain
map, ``base`` for the vertical-surface grid): cell ``(row, col)`` covers the square
``origin_m + (col, row) * resolution_m`` to ``origin_m + (col + 1, row + 1) * resolution_m``
(x along columns, y along rows), the convention of ``protocol.messages.TerrainGrid``.

Terrain cells are classified as :data:`UNKNOWN`, :data:`DRIVABLE` or :data:`OBSTACLE`
(paper 5.3, Fig. 15) and stored as ``uint8``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["DRIVABLE", "OBSTACLE", "UNKNOWN", "GridGeometry", "check_points"]

#: Cell classes of a terrain map (``uint8``).
UNKNOWN = 0
DRIVABLE = 1
OBSTACLE = 2


@dataclass(frozen=True)
class GridGeometry:
    """Where a ``(rows, cols)`` grid lies in its frame.

    ``origin_m`` is the corner ``(x, y)`` of cell ``(0, 0)``; ``resolution_m`` the cell side.
    """

    origin_m: tuple[float, float]
    resolution_m: float
    rows: int
    cols: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution_m) and self.resolution_m > 0):
            raise ValueError(f"GridGeometry.resolution_m must be > 0, got {self.resolution_m}")
        if self.rows < 1 or self.cols < 1:
            raise ValueError(f"GridGeometry: need rows, cols >= 1, got {self.rows}x{self.cols}")
        if not all(math.isfinite(v) for v in self.origin_m) or len(self.origin_m) != 2:
            raise ValueError(f"GridGeometry.origin_m must be 2 finite numbers: {self.origin_m}")

    @classmethod
    def centered(
        cls, center_m: ArrayLike, *, resolution_m: float, rows: int, cols: int
    ) -> GridGeometry:
        """A grid about ``center_m`` whose origin is snapped to the ``resolution_m`` lattice.

        Snapping makes grids built around different robot positions share cell boundaries,
        so maps from different sweeps combine by integer shifts (no resampling).
        """
        c = np.asarray(center_m, dtype=np.float64)
        if c.shape != (2,) or not np.all(np.isfinite(c)):
            raise ValueError(f"center_m: expected 2 finite numbers, got {c!r}")
        ox = math.floor(c[0] / resolution_m - cols / 2) * resolution_m
        oy = math.floor(c[1] / resolution_m - rows / 2) * resolution_m
        return cls((ox, oy), resolution_m, rows, cols)

    @property
    def shape(self) -> tuple[int, int]:
        return (self.rows, self.cols)

    def lattice_index(self) -> tuple[int, int]:
        """``(row, col)`` of cell ``(0, 0)`` on the global lattice of cells of this size."""
        return (
            round(self.origin_m[1] / self.resolution_m),
            round(self.origin_m[0] / self.resolution_m),
        )

    def cell_of(self, xy_m: ArrayLike) -> NDArray[np.int64]:
        """``(row, col)`` integer indices of points ``(..., 2)`` (may lie outside the grid)."""
        p = np.asarray(xy_m, dtype=np.float64)
        col = np.floor((p[..., 0] - self.origin_m[0]) / self.resolution_m)
        row = np.floor((p[..., 1] - self.origin_m[1]) / self.resolution_m)
        return np.stack([row, col], axis=-1).astype(np.int64)

    def cell_index(self, xy_m: ArrayLike) -> tuple[int, int]:
        """``(row, col)`` of one point ``(x, y)`` (may lie outside the grid)."""
        rc = self.cell_of(np.asarray(xy_m, dtype=np.float64).reshape(2))
        return int(rc[0]), int(rc[1])

    def center_of(self, rc: ArrayLike) -> NDArray[np.float64]:
        """``(x, y)`` of cells or fractional cell coordinates ``(..., 2)`` given as (row, col);
        an integer ``(row, col)`` maps to the cell's center."""
        a = np.asarray(rc, dtype=np.float64)
        x = self.origin_m[0] + (a[..., 1] + 0.5) * self.resolution_m
        y = self.origin_m[1] + (a[..., 0] + 0.5) * self.resolution_m
        return np.stack([x, y], axis=-1)

    def contains(self, xy_m: ArrayLike) -> NDArray[np.bool_]:
        rc = self.cell_of(xy_m)
        return (  # type: ignore[no-any-return]
            (rc[..., 0] >= 0)
            & (rc[..., 0] < self.rows)
            & (rc[..., 1] >= 0)
            & (rc[..., 1] < self.cols)
        )


def check_points(name: str, points: ArrayLike, *, dims: int = 3) -> NDArray[np.float64]:
    """``points`` as a finite float64 ``(N, dims)`` array, or a ValueError naming the problem."""
    a = np.asarray(points)
    if a.ndim != 2 or a.shape[1] != dims:
        raise ValueError(f"{name}: expected shape (N, {dims}), got {a.shape}")
    if not np.issubdtype(a.dtype, np.number) or np.issubdtype(a.dtype, np.complexfloating):
        raise ValueError(f"{name}: expected real numbers, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    bad = ~np.isfinite(a)
    if bad.any():
        first = int(np.argwhere(bad.any(axis=1))[0, 0])
        raise ValueError(
            f"{name}: {int(bad.any(axis=1).sum())} points are not finite (first at row {first}: "
            f"{a[first].tolist()})"
        )
    return a
