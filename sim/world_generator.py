"""Seeded procedural generation of a MAGIC urban phase (paper section 2, Fig. 2-3).

:func:`generate_world` turns a :class:`WorldConfig` (``configs/world/*.yaml``) into a
:class:`World`: plain data (solids, objects of interest, people with patrol routes, robot
start poses) that :mod:`sim.ground_truth` rasterizes and :mod:`sim.scene` builds in PyBullet.
The same config (seed included) always gives the same world.

Frame: ``world`` (x east, y north, z up, metres); the phase covers ``[0, size_m[0]] x
[0, size_m[1]]`` with the ground at ``z = 0``. Everything is axis-aligned except cylinders.

Contents (paper section 2): buildings made of rooms along a corridor with doorways (indoor
parts, with a roof), chain-link fences (thin), sidewalks raised by 10 cm curbs, loading docks
reached by 15 deg ramps, sand (more wheel slip), trees whose canopy overhangs at or above robot
height, cars; objects of interest: static OOIs (bombs) and toxic vats (coloured cylinders),
civilians (blue) and hostiles (red) who walk patrol routes (mobile OOIs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import msgspec
import numpy as np

__all__ = [
    "Human",
    "Ooi",
    "RobotStart",
    "Solid",
    "World",
    "WorldConfig",
    "generate_world",
]

Range = tuple[float, float]
Rgba = tuple[float, float, float, float]


def _check_range(name: str, r: Range, *, lo: float = 0.0) -> None:
    if not (math.isfinite(r[0]) and math.isfinite(r[1]) and lo <= r[0] <= r[1]):
        raise ValueError(f"{name} must be [min, max] with {lo} <= min <= max, got {list(r)}")


def _check_rgba(name: str, c: Rgba) -> None:
    if not all(0.0 <= v <= 1.0 for v in c):
        raise ValueError(f"{name} components must be in [0, 1], got {list(c)}")


class RobotsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The team (paper 2): sensor robots explore; disruptors only neutralize static OOIs.

    Ids: sensor robots ``0 .. sensors-1``, then the disruptors. ``spacing_m``: grid spacing in
    the start zone (the zone grows with the team).
    """

    sensors: int = 3
    disruptors: int = 1
    spacing_m: float = 1.5

    def __post_init__(self) -> None:
        if self.sensors < 0 or self.disruptors < 0 or self.sensors + self.disruptors < 1:
            raise ValueError("sensors and disruptors must be >= 0 with at least one robot in all")
        if self.sensors + self.disruptors > 146:
            raise ValueError(
                "sensors + disruptors must be <= 146 (AprilTag 36h11 has 587 ids, four a robot)"
            )
        if not self.spacing_m >= 1.0:
            raise ValueError(f"spacing_m must be >= 1.0, got {self.spacing_m}")


class BuildingsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Buildings: a corridor along the long axis with rooms on both sides, doorways."""

    count: int = 2
    size_m: Range = (12.0, 24.0)
    wall_height_m: float = 2.5
    wall_thickness_m: float = 0.15
    door_width_m: float = 1.1
    corridor_width_m: float = 1.8
    room_width_m: Range = (3.0, 5.0)
    roof: bool = True

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")
        _check_range("size_m", self.size_m, lo=6.0)
        _check_range("room_width_m", self.room_width_m, lo=1.5)
        if not 0.05 <= self.wall_thickness_m <= 0.5:
            raise ValueError("wall_thickness_m must be in [0.05, 0.5]")
        if not 0.8 <= self.door_width_m <= 3.0:
            raise ValueError("door_width_m must be in [0.8, 3.0]")
        if not 1.2 <= self.corridor_width_m <= 4.0:
            raise ValueError("corridor_width_m must be in [1.2, 4.0]")
        if not self.wall_height_m >= 1.5:
            raise ValueError("wall_height_m must be >= 1.5")


class FencesConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Chain-link fences: thin, tall, each with one gate gap; plus one around the phase."""

    count: int = 3
    length_m: Range = (6.0, 18.0)
    thickness_m: float = 0.05
    height_m: float = 2.0
    gate_width_m: float = 1.6
    perimeter: bool = True

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")
        _check_range("length_m", self.length_m, lo=2.0)
        if not 0.01 <= self.thickness_m <= 0.3:
            raise ValueError("thickness_m must be in [0.01, 0.3]")


class CurbsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Sidewalks raised by a curb of ``height_m`` (paper 3.1: robots mount 10 cm curbs)."""

    count: int = 3
    height_m: float = 0.10
    length_m: Range = (6.0, 16.0)
    width_m: Range = (2.0, 4.0)

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")
        if not 0.0 < self.height_m <= 0.3:
            raise ValueError(f"height_m must be in (0, 0.3], got {self.height_m}")
        _check_range("length_m", self.length_m, lo=1.0)
        _check_range("width_m", self.width_m, lo=1.0)


class RampsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Loading docks: a raised platform reached by one ramp of ``slope_deg``."""

    count: int = 1
    slope_deg: float = 15.0
    platform_height_m: float = 0.5
    platform_size_m: Range = (3.0, 5.0)
    ramp_width_m: float = 2.0

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")
        if not 1.0 <= self.slope_deg <= 30.0:
            raise ValueError(f"slope_deg must be in [1, 30], got {self.slope_deg}")
        if not 0.05 <= self.platform_height_m <= 2.0:
            raise ValueError("platform_height_m must be in [0.05, 2]")
        _check_range("platform_size_m", self.platform_size_m, lo=1.5)
        if not 1.0 <= self.ramp_width_m <= self.platform_size_m[0]:
            raise ValueError("ramp_width_m must be in [1, platform_size_m min]")


class SandConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Sand pits: flat, but the wheels slip more (``slip`` fraction of wheel speed lost)."""

    count: int = 1
    size_m: Range = (6.0, 10.0)
    slip: float = 0.25

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")
        _check_range("size_m", self.size_m, lo=1.0)
        if not 0.0 <= self.slip < 1.0:
            raise ValueError(f"slip must be in [0, 1), got {self.slip}")


class TreesConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Trees: a trunk and a canopy cylinder whose underside is at ``canopy_bottom_m``."""

    count: int = 6
    trunk_radius_m: Range = (0.1, 0.25)
    canopy_radius_m: Range = (1.2, 2.5)
    canopy_bottom_m: Range = (0.5, 1.6)
    canopy_depth_m: Range = (1.5, 3.0)

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")
        for name in ("trunk_radius_m", "canopy_radius_m", "canopy_bottom_m", "canopy_depth_m"):
            _check_range(name, getattr(self, name), lo=0.01)


class CarsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    count: int = 3

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")


class ObjectsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Cylindrical objects of interest: static OOIs (bombs) and toxic vats (paper 2, Fig. 3)."""

    count: int = 2
    radius_m: float = 0.25
    height_m: float = 0.8
    rgba: Rgba = (1.0, 0.3, 0.0, 1.0)

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")
        if not 0.05 <= self.radius_m <= 1.0:
            raise ValueError(f"radius_m must be in [0.05, 1], got {self.radius_m}")
        if not 0.1 <= self.height_m <= 3.0:
            raise ValueError(f"height_m must be in [0.1, 3], got {self.height_m}")
        _check_rgba("rgba", self.rgba)


class HumansConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """People (paper 2): civilians wear blue, hostiles red; ``mobile_fraction`` of them walk
    a looped patrol route at ``speed_m_s`` (mobile OOIs), the rest stand still."""

    count: int = 2
    mobile_fraction: float = 0.5
    speed_m_s: float = 0.6
    radius_m: float = 0.25
    height_m: float = 1.7
    rgba: Rgba = (0.1, 0.2, 0.9, 1.0)

    def __post_init__(self) -> None:
        if self.count < 0:
            raise ValueError(f"count must be >= 0, got {self.count}")
        if not 0.0 <= self.mobile_fraction <= 1.0:
            raise ValueError(f"mobile_fraction must be in [0, 1], got {self.mobile_fraction}")
        if not 0.0 < self.speed_m_s <= 3.0:
            raise ValueError(f"speed_m_s must be in (0, 3], got {self.speed_m_s}")
        _check_rgba("rgba", self.rgba)


class WorldConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """A phase of the contest: its size, seed, team and contents (``configs/world/*.yaml``).

    ``resolution_m`` is the ground-truth raster cell (10 cm). ``robot_height_m``: obstacles
    whose underside is below it block a robot (overhanging canopies included).
    """

    seed: int = 0
    size_m: tuple[float, float] = (60.0, 40.0)
    resolution_m: float = 0.1
    robot_height_m: float = 0.95
    robot_radius_m: float = 0.4
    robots: RobotsConfig = RobotsConfig()
    buildings: BuildingsConfig = BuildingsConfig()
    fences: FencesConfig = FencesConfig()
    curbs: CurbsConfig = CurbsConfig()
    ramps: RampsConfig = RampsConfig()
    sand: SandConfig = SandConfig()
    trees: TreesConfig = TreesConfig()
    cars: CarsConfig = CarsConfig()
    static_oois: ObjectsConfig = ObjectsConfig()
    toxic_vats: ObjectsConfig = ObjectsConfig(
        count=1, radius_m=0.3, height_m=0.9, rgba=(0.95, 0.85, 0.0, 1.0)
    )
    civilians: HumansConfig = HumansConfig()
    hostiles: HumansConfig = HumansConfig(count=1, rgba=(0.9, 0.05, 0.05, 1.0))

    def __post_init__(self) -> None:
        w, h = self.size_m
        if not (math.isfinite(w) and math.isfinite(h) and 20.0 <= w <= 2000 and 20 <= h <= 2000):
            raise ValueError(f"size_m must be [width, height] in [20, 2000] m, got {[w, h]}")
        if not 0.02 <= self.resolution_m <= 0.5:
            raise ValueError(f"resolution_m must be in [0.02, 0.5], got {self.resolution_m}")
        if not 0.3 <= self.robot_height_m <= 2.0:
            raise ValueError(f"robot_height_m must be in [0.3, 2], got {self.robot_height_m}")
        if not 0.1 <= self.robot_radius_m <= 1.0:
            raise ValueError(f"robot_radius_m must be in [0.1, 1], got {self.robot_radius_m}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")


# --------------------------------------------------------------------------------------------
# The generated world: plain data


Layer = Literal["ground", "obstacle", "roof"]
Shape = Literal["box", "cylinder", "wedge"]


@dataclass(frozen=True)
class Solid:
    """One static rigid piece of the world.

    ``shape``: ``box`` (``half_extents_m`` along the yawed local axes), ``cylinder`` (vertical;
    radius ``half_extents_m[0]``, half height ``half_extents_m[2]``) or ``wedge`` (a ramp: a box
    whose top rises linearly along local +x from its bottom face at ``-hx`` to its top at
    ``+hx``). ``layer``: ``ground`` pieces are driven on (curbs, platforms, ramps, sand),
    ``obstacle`` pieces block, ``roof`` pieces are overhead. ``kind`` names what it is
    (``wall``, ``fence``, ``curb``, ``ramp``, ``car``, ``trunk``, ``canopy``, ...).
    """

    kind: str
    shape: Shape
    layer: Layer
    center_m: tuple[float, float, float]
    half_extents_m: tuple[float, float, float]
    yaw_rad: float = 0.0
    rgba: Rgba = (0.7, 0.7, 0.7, 1.0)


OoiKind = Literal["static_ooi", "toxic_vat"]


@dataclass(frozen=True)
class Ooi:
    """A cylindrical object of interest standing on the ground at ``xy_m``."""

    ooi_id: int
    kind: OoiKind
    xy_m: tuple[float, float]
    radius_m: float
    height_m: float
    rgba: Rgba
    ground_z_m: float = 0.0


HumanKind = Literal["civilian", "hostile"]


@dataclass(frozen=True)
class Human:
    """A civilian or hostile walking the closed polyline ``route_m`` (``(K, 2)``) at
    ``speed_m_s``; one waypoint means standing still. Hostiles are the mobile OOIs."""

    human_id: int
    kind: HumanKind
    route_m: tuple[tuple[float, float], ...]
    speed_m_s: float
    radius_m: float
    height_m: float
    rgba: Rgba


@dataclass(frozen=True)
class RobotStart:
    robot_id: int
    role: Literal["sensor", "disruptor"]
    pose_m: tuple[float, float, float]  # world_from_base (x, y, yaw)


@dataclass(frozen=True)
class World:
    """Everything :func:`generate_world` decided; pure data (no PyBullet).

    ``start_zone_m``: ``(x0, y0, x1, y1)``. ``gcs_antenna_m``: the GCS radio antenna (x, y, z).
    ``sand_m``: ``(x0, y0, x1, y1, slip)`` per sand pit.
    """

    config: WorldConfig
    size_m: tuple[float, float]
    solids: tuple[Solid, ...]
    oois: tuple[Ooi, ...]
    humans: tuple[Human, ...]
    robots: tuple[RobotStart, ...]
    start_zone_m: tuple[float, float, float, float]
    gcs_antenna_m: tuple[float, float, float]
    sand_m: tuple[tuple[float, float, float, float, float], ...] = field(default=())

    def fingerprint(self) -> str:
        """A stable digest of the world's content (same seed and config -> same digest)."""
        import hashlib

        h = hashlib.sha256()
        h.update(repr((self.solids, self.oois, self.humans, self.robots)).encode())
        return h.hexdigest()[:16]


# --------------------------------------------------------------------------------------------
# Generation

_WALL_RGBA: Rgba = (0.78, 0.74, 0.68, 1.0)
_ROOF_RGBA: Rgba = (0.45, 0.35, 0.3, 1.0)
_FENCE_RGBA: Rgba = (0.6, 0.62, 0.65, 1.0)
_CURB_RGBA: Rgba = (0.62, 0.62, 0.6, 1.0)
_DOCK_RGBA: Rgba = (0.55, 0.55, 0.58, 1.0)
_SAND_RGBA: Rgba = (0.86, 0.76, 0.5, 1.0)
_TRUNK_RGBA: Rgba = (0.4, 0.27, 0.15, 1.0)
_CANOPY_RGBA: Rgba = (0.15, 0.5, 0.15, 1.0)
_CAR_RGBAS: tuple[Rgba, ...] = (
    (0.2, 0.2, 0.25, 1.0),
    (0.85, 0.85, 0.88, 1.0),
    (0.25, 0.35, 0.3, 1.0),
    (0.5, 0.45, 0.35, 1.0),
)
_PLACE_RES_M = 0.5


class _Planner:
    """Coarse (0.5 m) claim map used to place things without overlap."""

    def __init__(self, size_m: tuple[float, float]) -> None:
        self.nx = int(math.ceil(size_m[0] / _PLACE_RES_M))
        self.ny = int(math.ceil(size_m[1] / _PLACE_RES_M))
        self.size_m = size_m
        self.taken = np.zeros((self.ny, self.nx), dtype=bool)

    def _slice(self, x0: float, y0: float, x1: float, y1: float) -> tuple[slice, slice]:
        j0 = max(0, int(math.floor(x0 / _PLACE_RES_M)))
        j1 = min(self.nx, int(math.ceil(x1 / _PLACE_RES_M)))
        i0 = max(0, int(math.floor(y0 / _PLACE_RES_M)))
        i1 = min(self.ny, int(math.ceil(y1 / _PLACE_RES_M)))
        return slice(i0, i1), slice(j0, j1)

    def free(self, x0: float, y0: float, x1: float, y1: float, margin: float) -> bool:
        w, h = self.size_m
        if x0 - margin < 0.5 or y0 - margin < 0.5 or x1 + margin > w - 0.5 or y1 + margin > h - 0.5:
            return False
        return not self.taken[self._slice(x0 - margin, y0 - margin, x1 + margin, y1 + margin)].any()

    def claim(self, x0: float, y0: float, x1: float, y1: float, margin: float = 0.0) -> None:
        self.taken[self._slice(x0 - margin, y0 - margin, x1 + margin, y1 + margin)] = True

    def place_rect(
        self, rng: np.random.Generator, w: float, h: float, margin: float, tries: int = 200
    ) -> tuple[float, float, float, float] | None:
        W, H = self.size_m
        for _ in range(tries):
            x0 = float(rng.uniform(1.0, max(1.0, W - w - 1.0)))
            y0 = float(rng.uniform(1.0, max(1.0, H - h - 1.0)))
            if self.free(x0, y0, x0 + w, y0 + h, margin):
                self.claim(x0, y0, x0 + w, y0 + h, margin)
                return x0, y0, x0 + w, y0 + h
        return None


def _box(
    kind: str,
    layer: Layer,
    x0: float,
    y0: float,
    z0: float,
    x1: float,
    y1: float,
    z1: float,
    rgba: Rgba,
) -> Solid:
    return Solid(
        kind=kind,
        shape="box",
        layer=layer,
        center_m=((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2),
        half_extents_m=((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
        rgba=rgba,
    )


def _wall(
    axis: str,
    fixed: float,
    a0: float,
    a1: float,
    gaps: list[tuple[float, float]],
    *,
    thickness: float,
    height: float,
    kind: str = "wall",
    rgba: Rgba = _WALL_RGBA,
) -> list[Solid]:
    """Axis-aligned wall from ``a0`` to ``a1`` along ``axis`` at ``fixed``, minus ``gaps``."""
    pieces: list[tuple[float, float]] = []
    cur = a0
    for g0, g1 in sorted(gaps):
        if g0 > cur + 0.05:
            pieces.append((cur, g0))
        cur = max(cur, g1)
    if a1 > cur + 0.05:
        pieces.append((cur, a1))
    out: list[Solid] = []
    t = thickness / 2
    for p0, p1 in pieces:
        if axis == "x":
            out.append(_box(kind, "obstacle", p0, fixed - t, 0.0, p1, fixed + t, height, rgba))
        else:
            out.append(_box(kind, "obstacle", fixed - t, p0, 0.0, fixed + t, p1, height, rgba))
    return out


def _building(
    rng: np.random.Generator, cfg: BuildingsConfig, x0: float, y0: float, x1: float, y1: float
) -> list[Solid]:
    """A corridor along the long axis, rooms on both sides, one doorway per room, doors at
    both corridor ends (so every room is reachable)."""
    th, hgt, dw = cfg.wall_thickness_m, cfg.wall_height_m, cfg.door_width_m
    solids: list[Solid] = []
    along_x = (x1 - x0) >= (y1 - y0)
    # Work in a local frame where the long axis is "u" and the short axis is "v".
    u0, u1, v0, v1 = (x0, x1, y0, y1) if along_x else (y0, y1, x0, x1)
    cw = cfg.corridor_width_m
    vc = float(rng.uniform(v0 + (v1 - v0) * 0.4, v0 + (v1 - v0) * 0.6))
    two_rows = (v1 - v0) >= cw + 2 * cfg.room_width_m[0]

    def wall_u(v: float, a: float, b: float, gaps: list[tuple[float, float]]) -> list[Solid]:
        return _wall("x" if along_x else "y", v, a, b, gaps, thickness=th, height=hgt)

    def wall_v(u: float, a: float, b: float, gaps: list[tuple[float, float]]) -> list[Solid]:
        return _wall("y" if along_x else "x", u, a, b, gaps, thickness=th, height=hgt)

    if two_rows:
        c0, c1 = vc - cw / 2, vc + cw / 2
        end_gap = [(vc - dw / 2, vc + dw / 2)]
    else:
        c0 = c1 = vc
        end_gap = [(vc - dw / 2, vc + dw / 2)]
    # Exterior: long sides, short sides with the corridor doors.
    long_gaps_lo: list[tuple[float, float]] = []
    long_gaps_hi: list[tuple[float, float]] = []
    if two_rows:
        # Rooms: split [u0, u1] into widths for each row, a doorway to the corridor each.
        for row, (ra, rb) in enumerate(((v0, c0), (c1, v1))):
            cuts = [u0]
            while cuts[-1] < u1:
                w = float(rng.uniform(*cfg.room_width_m))
                cuts.append(min(u1, cuts[-1] + w) if u1 - (cuts[-1] + w) >= 2.0 else u1)
            door_gaps = []
            for a, b in zip(cuts[:-1], cuts[1:], strict=True):
                if b - a < dw + 0.6:
                    continue
                dc = float(rng.uniform(a + dw / 2 + 0.3, b - dw / 2 - 0.3))
                door_gaps.append((dc - dw / 2, dc + dw / 2))
                # occasionally a door to the outside as well
                if rng.random() < 0.3 and b - a >= dw + 0.6:
                    oc = float(rng.uniform(a + dw / 2 + 0.3, b - dw / 2 - 0.3))
                    (long_gaps_lo if row == 0 else long_gaps_hi).append((oc - dw / 2, oc + dw / 2))
            corridor_wall_v = c0 if row == 0 else c1
            solids += wall_u(corridor_wall_v, u0, u1, door_gaps)
            for cut in cuts[1:-1]:
                solids += wall_v(cut, ra, rb, [])
    solids += wall_u(v0, u0, u1, long_gaps_lo)
    solids += wall_u(v1, u0, u1, long_gaps_hi)
    solids += wall_v(u0, v0, v1, end_gap)
    solids += wall_v(u1, v0, v1, end_gap)
    if cfg.roof:
        solids.append(_box("roof", "roof", x0, y0, hgt, x1, y1, hgt + 0.1, _ROOF_RGBA))
    return solids


def _seg_clear(free: np.ndarray, res: float, a: np.ndarray, b: np.ndarray) -> bool:
    n = max(2, int(np.linalg.norm(b - a) / (res * 0.5)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    p = a[None, :] * (1 - t) + b[None, :] * t
    j = np.clip((p[:, 0] / res).astype(int), 0, free.shape[1] - 1)
    i = np.clip((p[:, 1] / res).astype(int), 0, free.shape[0] - 1)
    return bool(free[i, j].all())


def _seg_min_dist(route: np.ndarray, pts: np.ndarray) -> float:
    """Minimum distance from the closed polyline ``route`` to any of ``pts``."""
    if len(pts) == 0:
        return math.inf
    if len(route) == 1:
        return float(np.min(np.linalg.norm(pts - route[0], axis=1)))
    a = route
    b = np.roll(route, -1, axis=0)
    ab = b - a
    ap = pts[:, None, :] - a[None, :, :]
    t = np.clip((ap * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
    d = np.linalg.norm(ap - t[..., None] * ab, axis=-1)
    return float(d.min())


def generate_world(config: WorldConfig) -> World:
    """Generate the phase described by ``config``; deterministic in ``config`` (seed included).

    Structures first (buildings, docks, curbs, sand, fences, cars, trees) on a coarse claim map
    that keeps them apart; then objects and people on cells a robot can reach from the start
    zone, with clearances that keep a freshly generated world safe (no OOI next to the start
    zone, no civilian route within trigger range of a bomb or a hostile's route).
    """
    from sim.ground_truth import rasterize  # local: ground truth imports this module

    rng = np.random.default_rng(config.seed)
    W, H = config.size_m
    planner = _Planner((W, H))
    solids: list[Solid] = []
    sand: list[tuple[float, float, float, float, float]] = []

    # Start zone on the west edge, sized for the team; the GCS antenna behind it.
    n_robots = config.robots.sensors + config.robots.disruptors
    sp = config.robots.spacing_m
    cols = int(math.ceil(math.sqrt(n_robots)))
    rows = int(math.ceil(n_robots / cols))
    zone_w, zone_h = rows * sp + 1.0, cols * sp + 1.0
    if zone_w + 4 > W or zone_h + 4 > H:
        raise ValueError(f"size_m {[W, H]} is too small for {n_robots} robots' start zone")
    zx0, zy0 = 2.0, H / 2 - zone_h / 2
    start_zone = (zx0, zy0, zx0 + zone_w, zy0 + zone_h)
    planner.claim(*start_zone, margin=4.0)
    robots: list[RobotStart] = []
    for k in range(n_robots):
        r, c = divmod(k, cols)
        x = zx0 + 0.5 + sp / 2 + (rows - 1 - r) * sp
        y = zy0 + 0.5 + sp / 2 + c * sp
        role: Literal["sensor", "disruptor"] = (
            "sensor" if k < config.robots.sensors else "disruptor"
        )
        robots.append(RobotStart(k, role, (x, y, 0.0)))
    gcs_antenna = (1.0, H / 2, 3.0)

    bc = config.buildings
    for _ in range(bc.count):
        bw = float(rng.uniform(*bc.size_m))
        bh = float(rng.uniform(*bc.size_m)) * float(rng.uniform(0.55, 0.9))
        bh = max(bh, 6.0)
        rect = planner.place_rect(rng, bw, bh, margin=3.0)
        if rect is not None:
            solids += _building(rng, bc, *rect)

    rc = config.ramps
    for _ in range(rc.count):
        pw = float(rng.uniform(*rc.platform_size_m))
        ph = float(rng.uniform(*rc.platform_size_m))
        ramp_len = rc.platform_height_m / math.tan(math.radians(rc.slope_deg))
        rect = planner.place_rect(rng, pw + ramp_len, ph, margin=2.0)
        if rect is None:
            continue
        x0, y0, x1, y1 = rect
        flip = bool(rng.random() < 0.5)  # ramp on the west or the east side
        px0, px1 = (x0 + ramp_len, x1) if not flip else (x0, x1 - ramp_len)
        solids.append(
            _box("dock", "ground", px0, y0, 0.0, px1, y1, rc.platform_height_m, _DOCK_RGBA)
        )
        yc = float(rng.uniform(y0 + rc.ramp_width_m / 2, y1 - rc.ramp_width_m / 2))
        rx0, rx1 = (x0, x0 + ramp_len) if not flip else (x1 - ramp_len, x1)
        solids.append(
            Solid(
                kind="ramp",
                shape="wedge",
                layer="ground",
                center_m=((rx0 + rx1) / 2, yc, rc.platform_height_m / 2),
                half_extents_m=(ramp_len / 2, rc.ramp_width_m / 2, rc.platform_height_m / 2),
                yaw_rad=0.0 if not flip else math.pi,
                rgba=_DOCK_RGBA,
            )
        )

    cc = config.curbs
    for _ in range(cc.count):
        a = float(rng.uniform(*cc.length_m))
        b = float(rng.uniform(*cc.width_m))
        w, h = (a, b) if rng.random() < 0.5 else (b, a)
        rect = planner.place_rect(rng, w, h, margin=1.5)
        if rect is not None:
            x0, y0, x1, y1 = rect
            solids.append(_box("curb", "ground", x0, y0, 0.0, x1, y1, cc.height_m, _CURB_RGBA))

    sc = config.sand
    for _ in range(sc.count):
        w = float(rng.uniform(*sc.size_m))
        h = float(rng.uniform(*sc.size_m))
        rect = planner.place_rect(rng, w, h, margin=1.0)
        if rect is not None:
            x0, y0, x1, y1 = rect
            solids.append(_box("sand", "ground", x0, y0, 0.0, x1, y1, 0.01, _SAND_RGBA))
            sand.append((x0, y0, x1, y1, sc.slip))

    fc = config.fences
    for _ in range(fc.count):
        length = float(rng.uniform(*fc.length_m))
        along_x = bool(rng.random() < 0.5)
        w, h = (length, fc.thickness_m) if along_x else (fc.thickness_m, length)
        rect = planner.place_rect(rng, w, h, margin=1.5)
        if rect is None:
            continue
        x0, y0, x1, y1 = rect
        a0, a1 = (x0, x1) if along_x else (y0, y1)
        g = float(rng.uniform(a0 + 0.5, max(a0 + 0.5, a1 - 0.5 - fc.gate_width_m)))
        solids += _wall(
            "x" if along_x else "y",
            (y0 + y1) / 2 if along_x else (x0 + x1) / 2,
            a0,
            a1,
            [(g, g + fc.gate_width_m)],
            thickness=fc.thickness_m,
            height=fc.height_m,
            kind="fence",
            rgba=_FENCE_RGBA,
        )
    if fc.perimeter:
        t = fc.thickness_m
        kw = {"thickness": t, "height": fc.height_m, "kind": "fence", "rgba": _FENCE_RGBA}
        solids += _wall("x", t / 2, 0.0, W, [], **kw)  # type: ignore[arg-type]
        solids += _wall("x", H - t / 2, 0.0, W, [], **kw)  # type: ignore[arg-type]
        solids += _wall("y", t / 2, t, H - t, [], **kw)  # type: ignore[arg-type]
        solids += _wall("y", W - t / 2, t, H - t, [], **kw)  # type: ignore[arg-type]

    for _ in range(config.cars.count):
        along_x = bool(rng.random() < 0.5)
        L, B = 4.4, 1.8
        w, h = (L, B) if along_x else (B, L)
        rect = planner.place_rect(rng, w, h, margin=1.2)
        if rect is None:
            continue
        x0, y0, x1, y1 = rect
        rgba = _CAR_RGBAS[int(rng.integers(len(_CAR_RGBAS)))]
        solids.append(_box("car", "obstacle", x0, y0, 0.25, x1, y1, 0.95, rgba))
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        hx, hy = (1.2, 0.8) if along_x else (0.8, 1.2)
        solids.append(_box("car", "obstacle", cx - hx, cy - hy, 0.95, cx + hx, cy + hy, 1.45, rgba))

    tc = config.trees
    for _ in range(tc.count):
        cr = float(rng.uniform(*tc.canopy_radius_m))
        rect = planner.place_rect(rng, 1.0, 1.0, margin=1.0)
        if rect is None:
            continue
        cx, cy = (rect[0] + rect[2]) / 2, (rect[1] + rect[3]) / 2
        tr = float(rng.uniform(*tc.trunk_radius_m))
        bottom = float(rng.uniform(*tc.canopy_bottom_m))
        depth = float(rng.uniform(*tc.canopy_depth_m))
        solids.append(
            Solid(
                "trunk",
                "cylinder",
                "obstacle",
                (cx, cy, bottom / 2),
                (tr, tr, bottom / 2),
                rgba=_TRUNK_RGBA,
            )
        )
        solids.append(
            Solid(
                "canopy",
                "cylinder",
                "obstacle",
                (cx, cy, bottom + depth / 2),
                (cr, cr, depth / 2),
                rgba=_CANOPY_RGBA,
            )
        )

    # Objects and people go where a robot can go (reachable from the start zone).
    pre = World(
        config, (W, H), tuple(solids), (), (), tuple(robots), start_zone, gcs_antenna, tuple(sand)
    )
    truth = rasterize(pre)
    res = truth.resolution_m
    # candidate places: reachable cells on a 0.5 m lattice (keeps memory small on big phases)
    stride = max(1, int(round(_PLACE_RES_M / res)))
    import cv2

    dist_m = cv2.distanceTransform(truth.drivable.astype(np.uint8), cv2.DIST_L2, 5) * res
    iy, ix = np.nonzero(truth.reachable[::stride, ::stride])
    if len(ix) == 0:
        raise ValueError("world has no area reachable from the start zone")
    iy, ix = iy * stride, ix * stride
    cand = np.stack([(ix + 0.5) * res, (iy + 0.5) * res], axis=1)
    clear_of = dist_m[iy, ix]  # distance of each candidate from anything blocking
    zc = np.array([(start_zone[0] + start_zone[2]) / 2, (start_zone[1] + start_zone[3]) / 2])
    from_start = np.linalg.norm(cand - zc, axis=1)

    oois: list[Ooi] = []
    placed = np.zeros((0, 2))

    def pick(min_clear: float, min_start: float, min_sep: float, avoid: np.ndarray) -> int | None:
        ok = np.nonzero((clear_of >= min_clear) & (from_start >= min_start))[0]
        for _ in range(300):
            if len(ok) == 0:
                return None
            k = int(ok[rng.integers(len(ok))])
            p = cand[k]
            if len(avoid) and np.min(np.linalg.norm(avoid - p, axis=1)) < min_sep:
                continue
            return k
        return None

    ooi_kinds: tuple[tuple[OoiKind, ObjectsConfig], ...] = (
        ("static_ooi", config.static_oois),
        ("toxic_vat", config.toxic_vats),
    )
    for ooi_kind, oc in ooi_kinds:
        for _ in range(oc.count):
            cell = pick(oc.radius_m + 1.0, 14.0 + zone_w, 4.0, placed)
            if cell is None:
                continue
            p = cand[cell]
            placed = np.vstack([placed, p])
            gz = float(truth.height_at(p[0], p[1]))
            oois.append(
                Ooi(
                    len(oois),
                    ooi_kind,
                    (float(p[0]), float(p[1])),
                    oc.radius_m,
                    oc.height_m,
                    oc.rgba,
                    gz,
                )
            )
    bombs = np.array([o.xy_m for o in oois if o.kind == "static_ooi"]).reshape(-1, 2)
    free_walk = truth.drivable & (dist_m >= 0.45)

    humans: list[Human] = []
    hostile_routes: list[np.ndarray] = []
    human_kinds: tuple[tuple[HumanKind, HumansConfig], ...] = (
        ("hostile", config.hostiles),
        ("civilian", config.civilians),
    )
    for kind, hc in human_kinds:
        n_mobile = int(round(hc.count * hc.mobile_fraction))
        for n in range(hc.count):
            min_start = 12.0 + zone_w if kind == "hostile" else 4.0 + zone_w
            route: np.ndarray | None = None
            for _ in range(40):
                cell = pick(0.6, min_start, 3.0, placed)
                if cell is None:
                    break
                pts = [cand[cell]]
                if n < n_mobile:
                    for _ in range(int(rng.integers(1, 4))):
                        for _ in range(30):
                            ang = rng.uniform(-math.pi, math.pi)
                            dist = rng.uniform(5.0, 20.0)
                            q = pts[-1] + dist * np.array([math.cos(ang), math.sin(ang)])
                            if (
                                0 < q[0] < W
                                and 0 < q[1] < H
                                and np.linalg.norm(q - zc) >= min_start
                                and _seg_clear(free_walk, res, pts[-1], q)
                            ):
                                pts.append(q)
                                break
                    if len(pts) > 2 and not _seg_clear(free_walk, res, pts[-1], pts[0]):
                        pts = pts[:2]  # walk back and forth instead of looping
                cand_route = np.array(pts)
                if kind == "civilian":
                    if _seg_min_dist(cand_route, bombs) < 4.0:
                        continue
                    if any(_seg_min_dist(cand_route, _densify(hr)) < 4.0 for hr in hostile_routes):
                        continue
                route = cand_route
                break
            if route is None:
                continue
            if kind == "hostile":
                hostile_routes.append(route)
            placed = np.vstack([placed, route[0]])
            humans.append(
                Human(
                    len(humans),
                    kind,
                    tuple((float(x), float(y)) for x, y in route),
                    hc.speed_m_s,
                    hc.radius_m,
                    hc.height_m,
                    hc.rgba,
                )
            )

    return World(
        config,
        (W, H),
        tuple(solids),
        tuple(oois),
        tuple(humans),
        tuple(robots),
        start_zone,
        gcs_antenna,
        tuple(sand),
    )


def _densify(route: np.ndarray, step_m: float = 0.5) -> np.ndarray:
    if len(route) == 1:
        return route
    out = []
    closed = np.vstack([route, route[:1]])
    for a, b in zip(closed[:-1], closed[1:], strict=True):
        n = max(1, int(np.linalg.norm(b - a) / step_m))
        t = np.linspace(0, 1, n, endpoint=False)[:, None]
        out.append(a * (1 - t) + b * t)
    return np.vstack(out)
