"""Hand-made worlds with known geometry for the simulator tests."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from sim.world_generator import (
    Human,
    Ooi,
    RobotsConfig,
    RobotStart,
    Solid,
    World,
    WorldConfig,
)

REPO = Path(__file__).resolve().parents[2]


def box(
    kind: str,
    x0: float,
    y0: float,
    x1: float,
    y1: float,
    z1: float,
    *,
    layer: str = "obstacle",
    z0: float = 0.0,
) -> Solid:
    return Solid(
        kind,
        "box",
        layer,  # type: ignore[arg-type]
        ((x0 + x1) / 2, (y0 + y1) / 2, (z0 + z1) / 2),
        ((x1 - x0) / 2, (y1 - y0) / 2, (z1 - z0) / 2),
    )


def make_world(
    *,
    solids: Sequence[Solid] = (),
    robots: Sequence[tuple[float, float, float, str]] = ((5.0, 10.0, 0.0, "sensor"),),
    oois: Sequence[Ooi] = (),
    humans: Sequence[Human] = (),
    size_m: tuple[float, float] = (30.0, 20.0),
    sand: Sequence[tuple[float, float, float, float, float]] = (),
) -> World:
    """A world of exactly these pieces (no generator), start zone around the first robot."""
    n_s = sum(1 for r in robots if r[3] == "sensor")
    cfg = WorldConfig(size_m=size_m, robots=RobotsConfig(sensors=n_s, disruptors=len(robots) - n_s))
    x, y = robots[0][0], robots[0][1]
    return World(
        config=cfg,
        size_m=size_m,
        solids=tuple(solids),
        oois=tuple(oois),
        humans=tuple(humans),
        robots=tuple(RobotStart(k, r[3], (r[0], r[1], r[2])) for k, r in enumerate(robots)),  # type: ignore[arg-type]
        start_zone_m=(x - 0.6, y - 0.6, x + 0.6, y + 0.6),
        gcs_antenna_m=(1.0, size_m[1] / 2, 3.0),
        sand_m=tuple(sand),
    )
