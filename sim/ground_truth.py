"""Ground-truth layers of a generated world, for evaluation and for the simulator's own physics.

Rasterizes a :class:`~sim.world_generator.World` at ``resolution_m`` (10 cm) over
``[0, W] x [0, H]``; cell ``[i, j]`` covers ``x in [j*res, (j+1)*res)``,
``y in [i*res, (i+1)*res)``. Layers (all ``(ny, nx)`` arrays):

- ``height_m``: ground surface height (curbs, dock platforms, ramps, sand), float32;
- ``vertical_occupancy``: vertical structures at robot height (walls, fences, cars, trunks,
  canopies whose underside is below ``robot_height_m``, OOIs), bool, conservatively covering
  every cell a structure touches (thin fences stay closed lines);
- ``cliff``: cells at a height step larger than a robot can climb (``step_max_m``);
- ``slip``: extra wheel slip fraction (sand);
- ``drivable``: neither occupied nor a cliff;
- ``reachable``: cells where a robot's centre (a disc of ``robot_radius_m``) can get to from
  the start zone, 8-connected.

Ground truth stays inside ``sim/`` and ``mission/`` evaluation (DESIGN section 2). Pure numpy
and OpenCV (distance transform, flood fill); no PyBullet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from sim.world_generator import Ooi, Solid, World

__all__ = ["GroundTruth", "rasterize", "step_map"]

#: An obstacle counts as a vertical structure if it reaches below robot height and above this.
_MIN_OBSTACLE_ABOVE_GROUND_M = 0.05


@dataclass(frozen=True)
class GroundTruth:
    resolution_m: float
    height_m: np.ndarray
    vertical_occupancy: np.ndarray
    cliff: np.ndarray
    slip: np.ndarray
    drivable: np.ndarray
    reachable: np.ndarray
    oois: tuple[Ooi, ...]

    @property
    def shape(self) -> tuple[int, int]:
        return self.height_m.shape  # type: ignore[return-value]

    def cells(self, xy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Row and column indices of world points ``(..., 2)``, clipped to the raster."""
        xy = np.asarray(xy_m, dtype=np.float64)
        j = np.clip((xy[..., 0] / self.resolution_m).astype(np.int64), 0, self.shape[1] - 1)
        i = np.clip((xy[..., 1] / self.resolution_m).astype(np.int64), 0, self.shape[0] - 1)
        return i, j

    def height_at(self, x_m: np.ndarray | float, y_m: np.ndarray | float) -> np.ndarray:
        i, j = self.cells(np.stack(np.broadcast_arrays(x_m, y_m), axis=-1))
        return self.height_m[i, j]


def _window(
    s: Solid, res: float, shape: tuple[int, int], grow_m: float
) -> tuple[slice, slice, np.ndarray, np.ndarray] | None:
    """Cells under the solid's (yawed) footprint grown by ``grow_m``; returns the window's
    slices and the footprint's local coordinates ``u, v`` of the cell centres."""
    cx, cy, _ = s.center_m
    hx, hy, _ = s.half_extents_m
    if s.shape == "cylinder":
        hy = hx
    c, sn = math.cos(s.yaw_rad), math.sin(s.yaw_rad)
    ex = abs(c) * hx + abs(sn) * hy + grow_m
    ey = abs(sn) * hx + abs(c) * hy + grow_m
    j0 = max(0, int(math.floor((cx - ex) / res)))
    j1 = min(shape[1], int(math.ceil((cx + ex) / res)) + 1)
    i0 = max(0, int(math.floor((cy - ey) / res)))
    i1 = min(shape[0], int(math.ceil((cy + ey) / res)) + 1)
    if j0 >= j1 or i0 >= i1:
        return None
    xs = (np.arange(j0, j1) + 0.5) * res - cx
    ys = (np.arange(i0, i1) + 0.5) * res - cy
    dx, dy = np.meshgrid(xs, ys)
    u = c * dx + sn * dy
    v = -sn * dx + c * dy
    return slice(i0, i1), slice(j0, j1), u, v


def _footprint(s: Solid, u: np.ndarray, v: np.ndarray, grow_m: float) -> np.ndarray:
    hx, hy, _ = s.half_extents_m
    if s.shape == "cylinder":
        return np.hypot(u, v) <= hx + grow_m
    return (np.abs(u) <= hx + grow_m) & (np.abs(v) <= hy + grow_m)


def rasterize(world: World, *, step_max_m: float = 0.12) -> GroundTruth:
    """Rasterize ``world`` (see the module docstring); ``O(cells + sum of solid footprints)``."""
    cfg = world.config
    res = cfg.resolution_m
    W, H = world.size_m
    shape = (int(math.ceil(H / res)), int(math.ceil(W / res)))
    height = np.zeros(shape, dtype=np.float32)
    occ = np.zeros(shape, dtype=bool)
    slip = np.zeros(shape, dtype=np.float32)

    for s in world.solids:
        if s.layer != "ground":
            continue
        win = _window(s, res, shape, 0.0)
        if win is None:
            continue
        si, sj, u, v = win
        inside = _footprint(s, u, v, 0.0)
        hx, _, hz = s.half_extents_m
        bottom = s.center_m[2] - hz
        if s.shape == "wedge":
            top = bottom + (np.clip(u, -hx, hx) + hx) / (2 * hx) * (2 * hz)
        else:
            top = np.full(u.shape, s.center_m[2] + hz)
        sub = height[si, sj]
        height[si, sj] = np.where(inside, np.maximum(sub, top), sub)

    grow = res / 2
    obstacles = [s for s in world.solids if s.layer == "obstacle"]
    obstacles += [
        Solid(
            "ooi",
            "cylinder",
            "obstacle",
            (o.xy_m[0], o.xy_m[1], o.ground_z_m + o.height_m / 2),
            (o.radius_m, o.radius_m, o.height_m / 2),
        )
        for o in world.oois
    ]
    for s in obstacles:
        win = _window(s, res, shape, grow)
        if win is None:
            continue
        si, sj, u, v = win
        inside = _footprint(s, u, v, grow)
        ground = height[si, sj]
        bottom = s.center_m[2] - s.half_extents_m[2]
        top = s.center_m[2] + s.half_extents_m[2]
        in_band = (bottom < ground + cfg.robot_height_m) & (
            top > ground + _MIN_OBSTACLE_ABOVE_GROUND_M
        )
        occ[si, sj] |= inside & in_band

    for x0, y0, x1, y1, extra in world.sand_m:
        i0, i1 = int(y0 / res), int(math.ceil(y1 / res))
        j0, j1 = int(x0 / res), int(math.ceil(x1 / res))
        slip[i0:i1, j0:j1] = np.maximum(slip[i0:i1, j0:j1], extra)

    cliff = step_map(height) > step_max_m
    drivable = ~occ & ~cliff

    # Configuration space of the robot's centre, then flood fill from the start zone.
    dist_m = cv2.distanceTransform(drivable.astype(np.uint8), cv2.DIST_L2, 5) * res
    cspace = (dist_m > cfg.robot_radius_m).astype(np.uint8)
    n, labels = cv2.connectedComponents(cspace, connectivity=8)
    zx0, zy0, zx1, zy1 = world.start_zone_m
    zone = labels[int(zy0 / res) : int(math.ceil(zy1 / res)), int(zx0 / res) : int(zx1 / res)]
    ids = np.unique(zone[zone > 0])
    reachable = np.isin(labels, ids) if len(ids) else np.zeros(shape, dtype=bool)

    return GroundTruth(
        resolution_m=res,
        height_m=height,
        vertical_occupancy=occ,
        cliff=cliff,
        slip=slip,
        drivable=drivable,
        reachable=reachable,
        oois=world.oois,
    )


def step_map(height_m: np.ndarray) -> np.ndarray:
    """Largest absolute height difference of each cell to its 4 neighbours."""
    step = np.zeros(height_m.shape, dtype=np.float32)
    dv = np.abs(np.diff(height_m, axis=0))
    dh = np.abs(np.diff(height_m, axis=1))
    step[1:, :] = np.maximum(step[1:, :], dv)
    step[:-1, :] = np.maximum(step[:-1, :], dv)
    step[:, 1:] = np.maximum(step[:, 1:], dh)
    step[:, :-1] = np.maximum(step[:, :-1], dh)
    return step
