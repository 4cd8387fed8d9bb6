"""Configuration space by max-disc dilation (paper 5.4, Fig. 16b).

The robot's footprint is enclosed in a disc of radius ``robot_radius_m``; a cell is blocked in
configuration space when an obstacle cell lies within that radius (cell centers), so the
planner can treat the robot as a point and ignore its rotation. This is a 2D max filter with a
disc kernel (cv2.dilate), ``O(rows * cols * r)``.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
from numpy.typing import NDArray

__all__ = ["configuration_space", "disc_kernel"]


def disc_kernel(radius_cells: float) -> NDArray[np.uint8]:
    """``(2k+1, 2k+1)`` uint8 kernel of the offsets ``(i, j)`` with ``i^2 + j^2 <= r^2``."""
    if not (math.isfinite(radius_cells) and radius_cells >= 0):
        raise ValueError(f"radius_cells must be finite and >= 0, got {radius_cells}")
    k = int(math.floor(radius_cells + 1e-9))
    i, j = np.mgrid[-k : k + 1, -k : k + 1]
    return (i * i + j * j <= radius_cells * radius_cells + 1e-9).astype(np.uint8)


def configuration_space(
    blocked: NDArray[np.bool_], *, robot_radius_m: float, resolution_m: float
) -> NDArray[np.bool_]:
    """Cells whose center is within ``robot_radius_m`` of a ``blocked`` cell's center."""
    b = np.asarray(blocked)
    if b.ndim != 2 or b.dtype != np.bool_:
        raise ValueError(f"blocked: expected a 2D bool grid, got {b.dtype} {b.shape}")
    if not (math.isfinite(resolution_m) and resolution_m > 0):
        raise ValueError(f"resolution_m must be > 0, got {resolution_m}")
    if not (math.isfinite(robot_radius_m) and robot_radius_m >= 0):
        raise ValueError(f"robot_radius_m must be >= 0, got {robot_radius_m}")
    kernel = disc_kernel(robot_radius_m / resolution_m)
    out = cv2.dilate(b.view(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return out.astype(bool)
