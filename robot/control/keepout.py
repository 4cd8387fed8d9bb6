"""Keep-out disks around dangerous objects, in the robot's private frame (paper 4.1, 2).

Robots are trusted with their own safety: a robot never drives within 2.5 m of a static OOI
(its trigger distance; 10 m blast) or 5 m of a hostile, plus a margin. Hazards come from two
places: the GCS's :class:`~protocol.messages.HazardUpdate` (in ``map``, with every robot's
``map_from_odom``: each robot converts with its own entry, paper 4.1) and the robot's own
detections (already in ``odom``). The disks feed the planner (as obstacles) and the path
follower's last-moment check.
"""

from __future__ import annotations

import msgspec
import numpy as np

from protocol.messages import HazardUpdate, ObjectKind
from protocol.se2 import inverse, transform_points

__all__ = ["KeepoutConfig", "keepout_disks_in_odom", "rasterize_disks"]


class KeepoutConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    static_ooi_radius_m: float = 2.5
    hostile_radius_m: float = 5.0
    margin_m: float = 0.75


def _kind_radius(kind: ObjectKind, cfg: KeepoutConfig) -> float:
    if kind is ObjectKind.HOSTILE:
        return cfg.hostile_radius_m
    if kind in (ObjectKind.STATIC_OOI, ObjectKind.TOXIC_VAT):
        return cfg.static_ooi_radius_m
    return 0.0


def keepout_disks_in_odom(
    robot_id: int,
    update: HazardUpdate | None,
    own_detections_in_odom: list[tuple[ObjectKind, float, float]] = (),  # type: ignore[assignment]
    *,
    config: KeepoutConfig | None = None,
) -> np.ndarray:
    """Disks ``(N, 3)`` of ``(x_m, y_m, radius_m)`` in this robot's ``odom``.

    A hazard's own ``radius_m`` is used when it is larger than the kind's default; the margin
    is always added. Without this robot's ``map_from_odom`` in the update, its hazards cannot be
    placed and only the robot's own detections count.
    """
    cfg = config or KeepoutConfig()
    disks: list[tuple[float, float, float]] = []
    if update is not None and update.hazards:
        frame = next((f for f in update.frames if f.robot_id == robot_id), None)
        if frame is not None:
            odom_from_map = inverse(np.asarray(frame.map_from_odom, dtype=np.float64))
            pts = np.array([h.position_in_map for h in update.hazards], dtype=np.float64)
            in_odom = transform_points(odom_from_map, pts)
            for h, p in zip(update.hazards, in_odom, strict=True):
                r = max(float(h.radius_m), _kind_radius(h.kind, cfg)) + cfg.margin_m
                disks.append((float(p[0]), float(p[1]), r))
    for kind, x, y in own_detections_in_odom:
        r = _kind_radius(kind, cfg)
        if r > 0:
            disks.append((x, y, r + cfg.margin_m))
    return np.array(disks, dtype=np.float64).reshape(-1, 3)


def rasterize_disks(
    obstacles: np.ndarray,
    disks_in_odom: np.ndarray,
    *,
    origin_in_odom: tuple[float, float],
    resolution_m: float,
) -> np.ndarray:
    """Mark every cell whose centre lies in a disk as an obstacle (returns a new bool grid).

    Cell ``(row, col)`` has its centre at ``origin + (col + 0.5, row + 0.5) * resolution_m``.
    """
    out = np.array(obstacles, dtype=bool, copy=True)
    h, w = out.shape
    for x, y, r in np.asarray(disks_in_odom, dtype=np.float64).reshape(-1, 3):
        c0 = int(np.floor((x - r - origin_in_odom[0]) / resolution_m))
        c1 = int(np.ceil((x + r - origin_in_odom[0]) / resolution_m))
        r0 = int(np.floor((y - r - origin_in_odom[1]) / resolution_m))
        r1 = int(np.ceil((y + r - origin_in_odom[1]) / resolution_m))
        c0, c1, r0, r1 = max(c0, 0), min(c1, w), max(r0, 0), min(r1, h)
        if c0 >= c1 or r0 >= r1:
            continue
        cols = origin_in_odom[0] + (np.arange(c0, c1) + 0.5) * resolution_m
        rows = origin_in_odom[1] + (np.arange(r0, r1) + 0.5) * resolution_m
        inside = (cols[None, :] - x) ** 2 + (rows[:, None] - y) ** 2 <= r * r
        out[r0:r1, c0:c1] |= inside
    return out
