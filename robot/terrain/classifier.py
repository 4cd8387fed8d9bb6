"""Single-sweep terrain classification (paper 5.3, stages 1 and 2) and its configuration.

One 3D LIDAR sweep becomes a drivability map in the robot's private frame ``odom``: points
``points_in_base`` are levelled (optional roll/pitch of ``base``), moved into ``odom`` with the
sweep's ``odom_from_base`` pose (one pose, or one per point to de-skew a sweep taken while
driving), the ground model is built (:mod:`robot.terrain.ground_model`) and the up-detector
(:mod:`robot.terrain.up_detector`) marks obstacles. Cells with ground-filtered points that
are not obstacles are drivable; cells without such points are unknown.

The grid is axis-aligned with ``odom`` and snapped to the ``resolution_m`` lattice, so maps
from successive sweeps fuse by integer shifts (:mod:`robot.terrain.map_fusion`).

:func:`classify_sweep_layers` also returns what the fusion needs to forget moving things: the
height of each obstacle mark above the ground model, and, given the sensor's mounting point,
the free-space evidence of the beams (:mod:`robot.terrain.free_space`).

Cost in the 14-robot ``magic_phase`` (issue 14; its first 60 mission-s, seed 0, thread CPU,
mean of two runs at load ~20, reports identical): :func:`classify_sweep_layers` 4.5 -> 3.2
CPU-ms per robot-mission-s with session 13's ground chamfer (``ground_model``), the fusion
(:mod:`robot.terrain.map_fusion`) 3.1 -> 1.7. On the bench's dense 52k-point sweep the beam
tracing (:func:`~robot.terrain.free_space.ray_floor`) is 20 of its 25 ms: what is left.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from robot.terrain.free_space import ray_floor
from robot.terrain.grid import DRIVABLE, OBSTACLE, UNKNOWN, GridGeometry, check_points
from robot.terrain.ground_model import ground_model
from robot.terrain.up_detector import filter_height_range, up_detector

__all__ = [
    "SweepLayers",
    "TerrainConfig",
    "classify_sweep",
    "classify_sweep_layers",
    "points_in_odom",
]


class TerrainConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Terrain classification (paper 5.3). The paper's map: 400 m^2 at 5 cm.

    ``ground_slope_deg``: ground-model prior (20 deg in the paper). ``overhead_clearance_m``:
    points higher than this above the ground pass over the robot (canopy; the simulated robot
    is 0.95 m tall). ``climb_slope_deg`` and ``step_m``: Eq. 2's
    ``a = tan(climb_slope_deg) * resolution_m`` and ``b``; with 20 deg and 4 cm a 15 deg ramp
    stays drivable while a 10 cm step with ground seen within 15 cm of it is an obstacle.
    ``iterations``: message-passing rounds; the paper found two enough for its sensor, four
    (reach 25 cm) also catch steps whose nearest ground return is a few cells away, as with
    sparser scan lines. ``fill_unobserved``: cells without points send their ground-model
    estimate (see :func:`robot.terrain.up_detector.up_detector`; off by default: it lets the
    rims of raised drivable surfaces be compared with distant ground).
    ``memory_sweeps``: sweeps fused pessimistically (12, about 15 s); ``clear_after_sweeps``:
    an obstacle mark is dropped once this many later sweeps saw the cell drivable or a beam
    cross it below the mark's top (moving teammates' trails, :mod:`robot.terrain.map_fusion`;
    0: pure pessimism). ``lidar_in_base_m``: the sensor's origin in ``base`` (beams start
    there); ``beam_end_margin_m``: the end of each beam, near its return, says nothing about
    free space (:mod:`robot.terrain.free_space`). ``max_range_m``: points
    farther from the sensor (horizontally) are dropped.
    """

    resolution_m: float = 0.05
    size_cells: int = 400
    ground_slope_deg: float = 20.0
    overhead_clearance_m: float = 1.1
    climb_slope_deg: float = 20.0
    step_m: float = 0.04
    iterations: int = 4
    memory_sweeps: int = 12
    clear_after_sweeps: int = 2
    lidar_in_base_m: tuple[float, float, float] = (0.2, 0.0, 0.52)  # the MAGIC robot's mount
    beam_end_margin_m: float = 0.15
    max_range_m: float = 30.0
    fill_unobserved: bool = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.resolution_m) and 0 < self.resolution_m <= 10):
            raise ValueError(f"resolution_m must be in (0, 10], got {self.resolution_m}")
        if not 2 <= self.size_cells <= 10000:
            raise ValueError(f"size_cells must be in [2, 10000], got {self.size_cells}")
        if not 0 <= self.ground_slope_deg < 90:
            raise ValueError(f"ground_slope_deg must be in [0, 90), got {self.ground_slope_deg}")
        if not 0 <= self.climb_slope_deg < 90:
            raise ValueError(f"climb_slope_deg must be in [0, 90), got {self.climb_slope_deg}")
        if not (math.isfinite(self.overhead_clearance_m) and self.overhead_clearance_m > 0):
            raise ValueError(f"overhead_clearance_m must be > 0, got {self.overhead_clearance_m}")
        if not (math.isfinite(self.step_m) and self.step_m >= 0):
            raise ValueError(f"step_m must be >= 0, got {self.step_m}")
        if not 0 <= self.iterations <= 100:
            raise ValueError(f"iterations must be in [0, 100], got {self.iterations}")
        if not 1 <= self.memory_sweeps <= 1000:
            raise ValueError(f"memory_sweeps must be in [1, 1000], got {self.memory_sweeps}")
        if not 0 <= self.clear_after_sweeps <= 3:
            raise ValueError(f"clear_after_sweeps must be in [0, 3], got {self.clear_after_sweeps}")
        if not all(math.isfinite(v) for v in self.lidar_in_base_m):
            raise ValueError(f"lidar_in_base_m must be finite, got {self.lidar_in_base_m}")
        if not (math.isfinite(self.beam_end_margin_m) and self.beam_end_margin_m >= 0):
            raise ValueError(f"beam_end_margin_m must be >= 0, got {self.beam_end_margin_m}")
        if not (math.isfinite(self.max_range_m) and self.max_range_m > 0):
            raise ValueError(f"max_range_m must be > 0, got {self.max_range_m}")

    def geometry_around(self, center_in_odom_m: ArrayLike) -> GridGeometry:
        """The ``size_cells`` square grid about ``center_in_odom_m``, snapped to the lattice."""
        return GridGeometry.centered(
            center_in_odom_m,
            resolution_m=self.resolution_m,
            rows=self.size_cells,
            cols=self.size_cells,
        )


def _level(points: NDArray[np.float64], roll_rad: float, pitch_rad: float) -> NDArray[np.float64]:
    """Rotate body-frame points by the body's roll and pitch into a gravity-aligned frame with
    the body's yaw (``R = Ry(pitch) @ Rx(roll)``, ZYX convention without the yaw)."""
    if roll_rad == 0.0 and pitch_rad == 0.0:
        return points
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    rot = np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]])
    return points @ rot.T


def points_in_odom(
    points_in_base: ArrayLike,
    odom_from_base: ArrayLike,
    *,
    roll_rad: float = 0.0,
    pitch_rad: float = 0.0,
    pose_name: str = "odom_from_base",
) -> NDArray[np.float64]:
    """``(N, 3)`` points in ``odom`` (z unchanged by the planar pose: heights stay relative to
    the base's ground contact). ``odom_from_base``: one pose ``(3,)`` for the whole sweep or
    ``(N, 3)`` poses, one per point (de-skew). Raises ValueError naming bad input (the pose
    argument as ``pose_name``)."""
    pts = check_points("points_in_base", points_in_base)
    pose = np.asarray(odom_from_base, dtype=np.float64)
    if not (pose.shape == (3,) or pose.shape == (len(pts), 3)):
        raise ValueError(f"{pose_name}: expected shape (3,) or ({len(pts)}, 3), got {pose.shape}")
    if not np.all(np.isfinite(pose)):
        raise ValueError(f"{pose_name}: pose is not finite")
    if not (math.isfinite(roll_rad) and math.isfinite(pitch_rad)):
        raise ValueError(f"roll_rad/pitch_rad must be finite, got {roll_rad}, {pitch_rad}")
    pts = _level(pts, roll_rad, pitch_rad)
    c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
    out = np.empty_like(pts)
    out[:, 0] = pose[..., 0] + c * pts[:, 0] - s * pts[:, 1]
    out[:, 1] = pose[..., 1] + s * pts[:, 0] + c * pts[:, 1]
    out[:, 2] = pts[:, 2]
    return out


@dataclass(frozen=True)
class SweepLayers:
    """One sweep's terrain map and its evidence for the fusion, all laid out by ``geometry``:
    ``classes`` (``uint8`` UNKNOWN/DRIVABLE/OBSTACLE); ``obstacle_height_m``: how far the
    highest point of each obstacle cell rises above the ground model (0 elsewhere);
    ``free_height_m``: the lowest height above the ground model at which a beam crossed the
    cell (``inf`` where none did, or when the sensor's position was not given)."""

    classes: NDArray[np.uint8]
    geometry: GridGeometry
    obstacle_height_m: NDArray[np.float64]
    free_height_m: NDArray[np.float64]


def classify_sweep_layers(
    points_in_base: ArrayLike,
    odom_from_base: ArrayLike,
    *,
    config: TerrainConfig,
    geometry: GridGeometry | None = None,
    roll_rad: float = 0.0,
    pitch_rad: float = 0.0,
    beams: bool = True,
) -> SweepLayers:
    """:func:`classify_sweep` plus the fusion's evidence layers (see :class:`SweepLayers`);
    ``beams``: trace the beams from ``config.lidar_in_base_m`` for free space."""
    pts = points_in_odom(points_in_base, odom_from_base, roll_rad=roll_rad, pitch_rad=pitch_rad)
    pose = np.asarray(odom_from_base, dtype=np.float64)
    origin = pose[:2] if pose.ndim == 1 else pose[0, :2]
    if geometry is None:
        geometry = config.geometry_around(origin)
    sensor_xy = pose[..., :2]
    keep = np.sum((pts[:, :2] - sensor_xy) ** 2, axis=1) <= config.max_range_m**2
    if not keep.all():
        pts = pts[keep]
        if pose.ndim == 2:
            pose = pose[keep]
    ground = ground_model(pts, geometry, ground_slope_deg=config.ground_slope_deg)
    z_min, z_max = filter_height_range(
        pts, geometry, ground, overhead_clearance_m=config.overhead_clearance_m
    )
    obstacle = up_detector(
        z_min,
        z_max,
        slope_per_cell_m=math.tan(math.radians(config.climb_slope_deg)) * geometry.resolution_m,
        step_m=config.step_m,
        iterations=config.iterations,
        ground_m=ground if config.fill_unobserved else None,
    )
    classes = np.full(geometry.shape, UNKNOWN, dtype=np.uint8)
    classes[np.isfinite(z_max)] = DRIVABLE
    classes[obstacle] = OBSTACLE
    height = np.zeros(geometry.shape)
    height[obstacle] = np.maximum(z_max[obstacle] - ground[obstacle], 0.0)
    if beams and len(pts):
        mount_in_base = np.asarray([config.lidar_in_base_m], dtype=np.float64)
        mount = _level(mount_in_base, roll_rad, pitch_rad)[0]
        c, s = np.cos(pose[..., 2]), np.sin(pose[..., 2])
        sensors = np.empty((len(pts), 3))
        sensors[:, 0] = pose[..., 0] + c * mount[0] - s * mount[1]
        sensors[:, 1] = pose[..., 1] + s * mount[0] + c * mount[1]
        sensors[:, 2] = mount[2]
        free = ray_floor(pts, sensors, geometry, ground, end_margin_m=config.beam_end_margin_m)
    else:
        free = np.full(geometry.shape, np.inf)
    return SweepLayers(classes, geometry, height, free)


def classify_sweep(
    points_in_base: ArrayLike,
    odom_from_base: ArrayLike,
    *,
    config: TerrainConfig,
    geometry: GridGeometry | None = None,
    roll_rad: float = 0.0,
    pitch_rad: float = 0.0,
) -> tuple[NDArray[np.uint8], GridGeometry]:
    """Classify one sweep into ``(classes, geometry)``: a ``uint8`` grid of
    :data:`~robot.terrain.grid.UNKNOWN` / ``DRIVABLE`` / ``OBSTACLE`` in ``odom``.

    ``geometry`` defaults to ``config.geometry_around`` the sweep's (first) base position.
    ``O(N + iterations * rows * cols)``; ``magic bench robot`` times 50k points into 400 x 400
    cells (``terrain_ms_400x400``).
    """
    layers = classify_sweep_layers(
        points_in_base,
        odom_from_base,
        config=config,
        geometry=geometry,
        roll_rad=roll_rad,
        pitch_rad=pitch_rad,
        beams=False,
    )
    return layers.classes, layers.geometry
