"""Synthetic 3D LIDAR scenes with known truth, for testing and benchmarking terrain
classification (issue 4: "finds every obstacle >= 10 cm high, <= 1% false obstacles on drivable
ground including a 15 deg ramp, overhanging canopy stays free").

A scene is a flat ground plane ``z = 0`` plus convex solids (boxes, walls, a curb, a wedge
ramp, a tree trunk with an overhanging canopy), each an intersection of half-spaces. A nodding
planar LIDAR (270 deg, tilting like paper 3.1's sensor) at ``sensor_height_m`` above the robot
base casts rays analytically (Cyrus-Beck clipping against each solid, so occlusion is exact)
with Gaussian range noise; density falls off with range as on the real sensor.

Truth per hit: the surface it came from (:data:`GROUND`, :data:`RAMP`, :data:`FACE` of an
obstacle, :data:`TOP` of an obstacle, :data:`CANOPY`). :func:`truth_grids` turns hits into the
cells that must be obstacles and the drivable cells that must not be.

Not an on-robot algorithm: it lives here so tests and ``magic bench robot`` share it without
importing ``sim/`` (DESIGN 2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from robot.terrain.grid import GridGeometry

__all__ = [
    "CANOPY",
    "FACE",
    "GROUND",
    "RAMP",
    "TOP",
    "LidarHits",
    "Scene",
    "Solid",
    "box",
    "cast_sweep",
    "prism",
    "random_scene",
    "score_classification",
    "issue_scene",
    "truth_grids",
    "wedge_ramp",
]

GROUND, RAMP, FACE, TOP, CANOPY = 0, 1, 2, 3, 4


@dataclass(frozen=True)
class Solid:
    """A convex solid ``{p : normals @ p <= offsets}`` with a surface label per plane."""

    normals: NDArray[np.float64]  # (P, 3), unit
    offsets: NDArray[np.float64]  # (P,)
    labels: NDArray[np.int64]  # (P,)


def _solid(planes: list[tuple[tuple[float, float, float], float, int]]) -> Solid:
    n = np.array([p[0] for p in planes], dtype=np.float64)
    d = np.array([p[1] for p in planes], dtype=np.float64)
    norm = np.linalg.norm(n, axis=1)
    return Solid(n / norm[:, None], d / norm, np.array([p[2] for p in planes], dtype=np.int64))


def box(
    center_xy: tuple[float, float],
    size_xy: tuple[float, float],
    height_m: float,
    *,
    yaw_rad: float = 0.0,
    z0_m: float = 0.0,
    label_top: int = TOP,
    label_side: int = FACE,
    label_bottom: int = TOP,
) -> Solid:
    """An oriented box on ``z0_m`` (a wall is a thin box, a curb a low wide one)."""
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    cx, cy = center_xy
    hx, hy = size_xy[0] / 2, size_xy[1] / 2
    planes = []
    for (nx, ny), h in (((c, s), hx), ((-c, -s), hx), ((-s, c), hy), ((s, -c), hy)):
        planes.append(((nx, ny, 0.0), nx * cx + ny * cy + h, label_side))
    planes.append(((0.0, 0.0, 1.0), z0_m + height_m, label_top))
    planes.append(((0.0, 0.0, -1.0), -z0_m, label_bottom))
    return _solid(planes)


def prism(
    center_xy: tuple[float, float],
    radius_m: float,
    z0_m: float,
    z1_m: float,
    *,
    sides: int = 12,
    label_side: int = FACE,
    label_top: int = TOP,
    label_bottom: int = TOP,
) -> Solid:
    """A vertical regular prism (a tree trunk, or a canopy slab) between ``z0_m`` and ``z1_m``."""
    planes = []
    for k in range(sides):
        a = 2 * math.pi * k / sides
        nx, ny = math.cos(a), math.sin(a)
        planes.append(((nx, ny, 0.0), nx * center_xy[0] + ny * center_xy[1] + radius_m, label_side))
    planes.append(((0.0, 0.0, 1.0), z1_m, label_top))
    planes.append(((0.0, 0.0, -1.0), -z0_m, label_bottom))
    return _solid(planes)


def wedge_ramp(
    x0_m: float, y0_m: float, length_m: float, width_m: float, slope_deg: float
) -> Solid:
    """A ramp rising along +x from ``x0_m`` at ``slope_deg``, with a vertical back face."""
    t = math.tan(math.radians(slope_deg))
    return _solid(
        [
            ((-t, 0.0, 1.0), -t * x0_m, RAMP),
            ((1.0, 0.0, 0.0), x0_m + length_m, FACE),
            ((0.0, 1.0, 0.0), y0_m + width_m, FACE),
            ((0.0, -1.0, 0.0), -y0_m, FACE),
            ((0.0, 0.0, -1.0), 0.0, TOP),
        ]
    )


@dataclass(frozen=True)
class Scene:
    solids: list[Solid] = field(default_factory=list)


@dataclass(frozen=True)
class LidarHits:
    """One sweep: ``points_in_base`` ``(N, 3)`` float32 (noisy), ``points_in_odom`` (noisy,
    float64), the surface label of each hit, the index of the solid hit (``-1``: ground), the
    robot's ``odom_from_base`` pose, and each hit's scan line (hits come line by line, each
    line in beam order, like :class:`~protocol.sensors.LidarSweep`)."""

    points_in_base: NDArray[np.float32]
    points_in_odom: NDArray[np.float64]
    labels: NDArray[np.int64]
    solid_index: NDArray[np.int64]
    odom_from_base: NDArray[np.float64]
    line_index: NDArray[np.int64]


def _ray_dirs(beams: int, lines: int, tilt_min_deg: float, tilt_max_deg: float) -> NDArray:
    a = np.linspace(-math.radians(135), math.radians(135), beams)
    t = np.radians(np.linspace(tilt_min_deg, tilt_max_deg, lines))
    grid_a, grid_t = np.meshgrid(a, t)
    aa, tt = grid_a.ravel(), grid_t.ravel()
    return np.stack([np.cos(aa) * np.cos(tt), np.sin(aa), np.cos(aa) * np.sin(tt)], axis=1)


def cast_sweep(
    scene: Scene,
    odom_from_base: tuple[float, float, float],
    *,
    rng: np.random.Generator,
    beams: int = 1081,
    lines: int = 46,
    tilt_min_deg: float = -40.0,
    tilt_max_deg: float = 20.0,
    sensor_height_m: float = 0.6,
    range_max_m: float = 30.0,
    range_noise_m: float = 0.01,
) -> LidarHits:
    """Cast one nodding-LIDAR sweep (``beams * lines`` rays) from a robot at ``odom_from_base``."""
    x, y, yaw = odom_from_base
    c, s = math.cos(yaw), math.sin(yaw)
    d_base = _ray_dirs(beams, lines, tilt_min_deg, tilt_max_deg)
    d = np.stack(
        [c * d_base[:, 0] - s * d_base[:, 1], s * d_base[:, 0] + c * d_base[:, 1], d_base[:, 2]],
        axis=1,
    )
    o = np.array([x, y, sensor_height_m])
    best_t = np.full(len(d), np.inf)
    label = np.full(len(d), -1, dtype=np.int64)
    down = d[:, 2] < -1e-12
    best_t[down] = -o[2] / d[down, 2]
    label[down] = GROUND
    which = np.full(len(d), -1, dtype=np.int64)
    for index, solid in enumerate(scene.solids):
        num = solid.offsets - solid.normals @ o  # (P,) >= 0 where the sensor is inside
        den = d @ solid.normals.T  # (R, P)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = num[None, :] / den
        entering = den < -1e-12
        exiting = den > 1e-12
        t_in = np.where(entering, t, -np.inf)
        plane_in = np.argmax(t_in, axis=1)
        t_enter = t_in[np.arange(len(d)), plane_in]
        t_exit = np.where(exiting, t, np.inf).min(axis=1)
        parallel_out = ((~entering & ~exiting) & (num[None, :] < 0)).any(axis=1)
        hit = (~parallel_out) & (t_enter <= t_exit) & (t_enter > 0) & (t_enter < best_t)
        best_t[hit] = t_enter[hit]
        label[hit] = solid.labels[plane_in[hit]]
        which[hit] = index
    ok = (label >= 0) & (best_t <= range_max_m) & (best_t >= 0.1)
    r = best_t[ok] + rng.normal(0.0, range_noise_m, int(ok.sum()))
    pts = o + d[ok] * r[:, None]
    rel = pts - np.array([x, y, 0.0])
    in_base = np.stack(
        [c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], axis=1
    )
    return LidarHits(
        in_base.astype(np.float32),
        pts,
        label[ok],
        which[ok],
        np.array([x, y, yaw], dtype=np.float64),
        np.flatnonzero(ok) // beams,
    )


def issue_scene() -> Scene:
    """The issue's scene around a robot at the origin: boxes and walls, a 10 cm curb, a 15 deg
    ramp, and a tree whose canopy (bottom 1.5 m) overhangs the ground around its trunk."""
    return Scene(
        [
            box((4.0, 3.0), (1.0, 1.0), 0.8),  # crate
            box((-3.0, -4.0), (0.6, 0.6), 0.25),  # low box
            box((0.0, 7.0), (8.0, 0.2), 2.5),  # wall
            box((-6.0, 0.0), (0.2, 6.0), 1.2, yaw_rad=0.3),  # fence
            box((5.0, -4.0), (6.0, 2.0), 0.10),  # curb (sidewalk 10 cm high)
            box((-4.0, 4.0), (0.4, 0.4), 0.12),  # small 12 cm obstacle
            wedge_ramp(2.0, -1.5, 1.5, 1.6, 15.0),  # rises to 40 cm
            prism((-3.0, -1.0), 0.15, 0.0, 3.0),  # trunk
            prism(
                (-3.0, -1.0),
                1.8,
                1.6,
                2.6,
                label_side=CANOPY,
                label_top=CANOPY,
                label_bottom=CANOPY,
            ),  # canopy
        ]
    )


def random_scene(
    rng: np.random.Generator, *, extent_m: float = 9.0, keep_clear_m: float = 1.0, count: int = 14
) -> Scene:
    """A random scene of boxes, walls, curbs, ramps and trees within ``extent_m`` of the
    origin, none within ``keep_clear_m`` of it (where the robot stands)."""
    solids: list[Solid] = []
    while len(solids) < count:
        cx, cy = rng.uniform(-extent_m, extent_m, 2)
        if math.hypot(cx, cy) < keep_clear_m + 2.0:
            continue
        kind = rng.integers(5)
        yaw = float(rng.uniform(-math.pi, math.pi))
        if kind == 0:
            solids.append(
                box(
                    (cx, cy),
                    tuple(rng.uniform(0.3, 1.5, 2)),
                    float(rng.uniform(0.1, 1.5)),
                    yaw_rad=yaw,
                )
            )
        elif kind == 1:
            solids.append(
                box(
                    (cx, cy),
                    (float(rng.uniform(2, 6)), 0.2),
                    float(rng.uniform(1.0, 2.5)),
                    yaw_rad=yaw,
                )
            )
        elif kind == 2:
            solids.append(
                box(
                    (cx, cy),
                    (float(rng.uniform(2, 5)), float(rng.uniform(1, 2))),
                    float(rng.uniform(0.10, 0.2)),
                    yaw_rad=yaw,
                )
            )
        elif kind == 3:
            solids.append(
                wedge_ramp(
                    cx,
                    cy,
                    float(rng.uniform(1, 2)),
                    float(rng.uniform(1, 2)),
                    float(rng.uniform(5, 15)),
                )
            )
        else:
            solids.append(prism((cx, cy), float(rng.uniform(0.1, 0.25)), 0.0, 3.0))
            solids.append(
                prism(
                    (cx, cy),
                    float(rng.uniform(1.0, 2.0)),
                    1.5,
                    2.6,
                    label_side=CANOPY,
                    label_top=CANOPY,
                    label_bottom=CANOPY,
                )
            )
    return Scene(solids)


def _near_faces(scene: Scene, geometry: GridGeometry, margin_m: float) -> NDArray[np.bool_]:
    """Cells whose center lies within ``margin_m`` (horizontally) of a vertical obstacle face
    of ``scene``, visible or not."""
    rr, cc = np.mgrid[0 : geometry.rows, 0 : geometry.cols]
    xy = geometry.center_of(np.stack([rr, cc], axis=-1))
    out = np.zeros(geometry.shape, dtype=bool)
    for solid in scene.solids:
        vertical = np.abs(solid.normals[:, 2]) < 1e-9
        n, d, lab = solid.normals[vertical, :2], solid.offsets[vertical], solid.labels[vertical]
        sd = xy @ n.T - d  # (rows, cols, P) signed distance to each vertical plane
        inside_ext = (sd < margin_m).all(axis=-1)
        for k in np.flatnonzero(lab == FACE):
            out |= inside_ext & (np.abs(sd[..., k]) < margin_m)
    return out


def truth_grids(
    hits: LidarHits,
    geometry: GridGeometry,
    scene: Scene,
    *,
    min_obstacle_m: float = 0.09,
    overhead_clearance_m: float = 1.1,
    evidence_radius_m: float = 0.15,
    margin_cells: int = 5,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """``(must_be_obstacle, must_be_drivable)`` cells of ``geometry`` from one sweep's hits.

    Obstacle: a cell holding a hit on an obstacle's vertical face (below the overhead
    clearance) where the obstacle's rim is evidenced: within one cell a face or top hit lies
    at least ``min_obstacle_m`` above a ground (or ramp) hit within ``evidence_radius_m``.
    ``min_obstacle_m`` is the issue's 10 cm less the 1 cm range noise, so a 10 cm curb counts;
    with the default 15 cm radius that is a rise steeper than 30 deg, beyond any climbable
    slope. Without a lower hit that close the sweep cannot tell a face from a slope (grazing
    views from afar, shadows behind boxes), so no classifier could be held to it.
    Drivable: a cell holding only ground, ramp or canopy hits, farther than ``margin_cells``
    (the up-detector's reach) from any cell holding a face or top hit and from any vertical
    face of ``scene`` (the rim of a drop, such as a ramp's side, is an obstacle too, seen or
    not). Other cells are not scored.
    """
    import cv2  # local: only truth building needs it

    rc = geometry.cell_of(hits.points_in_odom[:, :2])
    inside = (
        (rc[:, 0] >= 0) & (rc[:, 0] < geometry.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < geometry.cols)
    )
    rc, lab, z = rc[inside], hits.labels[inside], hits.points_in_odom[inside, 2]
    shape = geometry.shape
    seen = np.zeros(shape, dtype=bool)
    seen[rc[:, 0], rc[:, 1]] = True
    solid_hit = np.zeros(shape, dtype=bool)
    sel = (lab == FACE) | (lab == TOP)
    solid_hit[rc[sel, 0], rc[sel, 1]] = True
    low = np.full(shape, np.inf, dtype=np.float32)
    sel = (lab == GROUND) | (lab == RAMP)
    np.minimum.at(low, (rc[sel, 0], rc[sel, 1]), z[sel].astype(np.float32))
    r = max(0, int(round(evidence_radius_m / geometry.resolution_m)))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    low_near = cv2.erode(low, disc, borderValue=np.inf)
    rim = np.full(shape, -np.inf, dtype=np.float32)
    sel = ((lab == FACE) | (lab == TOP)) & (z <= overhead_clearance_m)
    np.maximum.at(rim, (rc[sel, 0], rc[sel, 1]), z[sel].astype(np.float32))
    rim_near = cv2.dilate(rim, np.ones((3, 3), np.uint8), borderValue=-np.inf)
    face = np.zeros(shape, dtype=bool)
    sel = (lab == FACE) & (z <= overhead_clearance_m)
    face[rc[sel, 0], rc[sel, 1]] = True
    obstacle = face & (rim_near - low_near >= min_obstacle_m)
    k = 2 * margin_cells + 1
    near = cv2.dilate(solid_hit.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    margin_m = (margin_cells + 0.75) * geometry.resolution_m
    drivable = seen & ~near & ~_near_faces(scene, geometry, margin_m)
    return obstacle, drivable


def score_classification(
    obstacle_map: NDArray[np.bool_],
    must_be_obstacle: NDArray[np.bool_],
    must_be_drivable: NDArray[np.bool_],
) -> tuple[float, float, float]:
    """``(recall, recall_exact, false_obstacle_frac)``: the fraction of ``must_be_obstacle``
    cells with an obstacle within one cell (the up-detector puts a face in the cell of its
    highest point, which quantization can shift by one), the same in the exact cell, and the
    fraction of ``must_be_drivable`` cells marked obstacle. Empty truths score 1, 1, 0."""
    import cv2

    near = cv2.dilate(obstacle_map.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    n_obs = int(must_be_obstacle.sum())
    n_drv = int(must_be_drivable.sum())
    recall = float(near[must_be_obstacle].sum() / n_obs) if n_obs else 1.0
    exact = float(obstacle_map[must_be_obstacle].sum() / n_obs) if n_obs else 1.0
    false = float(obstacle_map[must_be_drivable].sum() / n_drv) if n_drv else 0.0
    return recall, exact, false
