"""Constructed maps with known answers for the tasking tests."""

from __future__ import annotations

import numpy as np

from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap

RES = 0.25


def blank(width_m: float, height_m: float, fill: int = UNKNOWN) -> np.ndarray:
    return np.full((int(round(height_m / RES)), int(round(width_m / RES))), fill, dtype=np.int8)


def box(values: np.ndarray, x0: float, y0: float, x1: float, y1: float, v: int) -> None:
    """Set the cells of the map rectangle [x0, x1) x [y0, y1) (metres) to ``v``."""
    r0, r1 = int(round(y0 / RES)), int(round(y1 / RES))
    c0, c1 = int(round(x0 / RES)), int(round(x1 / RES))
    values[r0:r1, c0:c1] = v


def room(values: np.ndarray, x0: float, y0: float, x1: float, y1: float) -> None:
    """A free room with a 0.5 m wall inside the rectangle's border."""
    box(values, x0, y0, x1, y1, OCCUPIED)
    box(values, x0 + 0.5, y0 + 0.5, x1 - 0.5, y1 - 0.5, FREE)


def occupancy(values: np.ndarray) -> OccupancyMap:
    return OccupancyMap(values, (0.0, 0.0), RES)


__all__ = ["FREE", "OCCUPIED", "RES", "UNKNOWN", "blank", "box", "occupancy", "room"]
