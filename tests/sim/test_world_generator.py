"""World generation: seeded, configured by YAML, with the paper's contents (section 2)."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from mission.config import ConfigError, load_config_text
from sim.ground_truth import rasterize
from sim.simulator import load_world_config
from sim.world_generator import WorldConfig, generate_world
from tests.sim.simworlds import REPO

SMALL = REPO / "configs/world/small.yaml"
PHASE = REPO / "configs/world/magic_phase.yaml"


@pytest.fixture(scope="module")
def small():
    return generate_world(load_world_config(SMALL))


def test_same_seed_same_world_and_other_seed_differs(small) -> None:
    cfg = load_world_config(SMALL)
    again = generate_world(cfg)
    assert again.fingerprint() == small.fingerprint()
    assert again.solids == small.solids and again.humans == small.humans
    other = generate_world(msgspec.structs.replace(cfg, seed=cfg.seed + 1))
    assert other.fingerprint() != small.fingerprint()


def test_small_world_has_the_contest_contents(small) -> None:
    assert small.size_m == (60.0, 40.0)
    assert len(small.robots) == 4
    assert [r.role for r in small.robots] == ["sensor"] * 3 + ["disruptor"]
    kinds = {s.kind for s in small.solids}
    assert {
        "wall",
        "roof",
        "fence",
        "curb",
        "ramp",
        "dock",
        "sand",
        "trunk",
        "canopy",
        "car",
    } <= kinds
    assert {o.kind for o in small.oois} == {"static_ooi", "toxic_vat"}
    assert {h.kind for h in small.humans} == {"civilian", "hostile"}
    assert any(len(h.route_m) > 1 for h in small.humans)  # someone patrols
    curbs = [s for s in small.solids if s.kind == "curb"]
    assert all(math.isclose(2 * s.half_extents_m[2], 0.10) for s in curbs)
    fence = [s for s in small.solids if s.kind == "fence"]
    assert all(min(s.half_extents_m[:2]) * 2 <= 0.05 + 1e-9 for s in fence)  # thin
    canopies = [s for s in small.solids if s.kind == "canopy"]
    assert all(0.5 <= s.center_m[2] - s.half_extents_m[2] <= 1.6 for s in canopies)


def test_magic_phase_is_large_with_fourteen_robots() -> None:
    cfg = load_world_config(PHASE)
    assert cfg.size_m == (220.0, 160.0)
    assert cfg.robots.sensors + cfg.robots.disruptors == 14
    assert cfg.robots.disruptors > 0


def test_ground_truth_layers(small) -> None:
    gt = rasterize(small)
    res = gt.resolution_m
    assert res == pytest.approx(0.1)
    assert gt.shape == (400, 600)
    # walls are vertical structures, curbs are not but raise the ground by 10 cm
    wall = next(s for s in small.solids if s.kind == "wall")
    i, j = gt.cells(np.array(wall.center_m[:2]))
    assert gt.vertical_occupancy[i, j] and not gt.drivable[i, j]
    curb = next(s for s in small.solids if s.kind == "curb")
    i, j = gt.cells(np.array(curb.center_m[:2]))
    assert gt.height_m[i, j] == pytest.approx(0.10) and not gt.vertical_occupancy[i, j]
    assert gt.drivable[i, j]
    # the ramp rises at 15 deg
    ramp = next(s for s in small.solids if s.kind == "ramp")
    x, y = ramp.center_m[:2]
    h = gt.height_at(np.array([x - 0.5, x + 0.5]), np.array([y, y]))
    assert abs(h[1] - h[0]) == pytest.approx(math.tan(math.radians(15)), abs=0.03)
    # every robot starts on reachable ground; every OOI stands next to reachable ground
    for r in small.robots:
        i, j = gt.cells(np.array(r.pose_m[:2]))
        assert gt.reachable[i, j]
    for o in small.oois:
        i, j = gt.cells(np.array(o.xy_m))
        assert gt.reachable[i - 15 : i + 16, j - 15 : j + 16].any()
    # sand slips more
    x0, y0, x1, y1, slip = small.sand_m[0]
    i, j = gt.cells(np.array([(x0 + x1) / 2, (y0 + y1) / 2]))
    assert gt.slip[i, j] == pytest.approx(slip)
    # the perimeter fence closes the world: the border is not reachable
    assert not gt.reachable[0, :].any() and not gt.reachable[:, -1].any()
    assert 0.3 < gt.reachable.mean() < 0.98


def test_thin_fences_leave_no_gap_in_occupancy(small) -> None:
    gt = rasterize(small)
    for s in (s for s in small.solids if s.kind == "fence"):
        cx, cy, _ = s.center_m
        hx, hy, _ = s.half_extents_m
        if hx >= hy:
            xs = np.arange(cx - hx + 0.05, cx + hx - 0.05, 0.02)
            pts = np.stack([xs, np.full_like(xs, cy)], axis=1)
        else:
            ys = np.arange(cy - hy + 0.05, cy + hy - 0.05, 0.02)
            pts = np.stack([np.full_like(ys, cx), ys], axis=1)
        i, j = gt.cells(pts)
        assert gt.vertical_occupancy[i, j].all()


@pytest.mark.parametrize(
    ("text", "key", "problem"),
    [
        ("seed: 1\nbogus: 3\n", "bogus", "unknown key"),
        ("buildings:\n  count: -1\n", "buildings.count", "must be >= 0, got -1"),
        ("size_m: [5.0, 40.0]\n", "size_m", "must be [width, height]"),
        ("trees:\n  count: many\n", "trees.count", "expected int, got str"),
        ("ramps:\n  slope_deg: 60.0\n", "ramps.slope_deg", "must be in [1, 30], got 60.0"),
        ("static_oois:\n  rgba: [2, 0, 0, 1]\n", "static_oois.rgba", "must be in [0, 1]"),
    ],
)
def test_invalid_world_configs_name_the_file_and_key(text: str, key: str, problem: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config_text(text, WorldConfig, source="configs/world/bad.yaml")
    msg = str(info.value)
    assert msg.startswith("configs/world/bad.yaml: ")
    assert msg.startswith(f"configs/world/bad.yaml: {key}: ")
    assert problem in msg


def test_team_too_big_for_the_phase_is_a_clear_error() -> None:
    cfg = load_config_text("size_m: [20.0, 20.0]\nrobots:\n  sensors: 140\n", WorldConfig)
    with pytest.raises(ValueError, match="too small for 141 robots"):
        generate_world(cfg)


def test_magic_phase_world_places_everything_reachably() -> None:
    cfg = load_world_config(PHASE)
    world = generate_world(cfg)
    gt = rasterize(world)
    assert sum(s.kind == "roof" for s in world.solids) == cfg.buildings.count
    assert sum(o.kind == "static_ooi" for o in world.oois) == cfg.static_oois.count
    assert sum(h.kind == "hostile" for h in world.humans) == cfg.hostiles.count
    assert sum(len(h.route_m) > 1 for h in world.humans) >= 4  # mobile OOIs and civilians
    for r in world.robots:
        i, j = gt.cells(np.array(r.pose_m[:2]))
        assert gt.reachable[i, j]
    for h in world.humans:
        route = np.array(h.route_m)
        i, j = gt.cells(route)
        assert gt.drivable[i, j].all()  # people walk where robots could drive


def test_the_hundred_robot_world_decodes_with_its_team() -> None:
    # generating it takes ~30 s (six phases): `magic bench scale` does; here only its config
    cfg = load_world_config(REPO / "configs/world/magic_team100.yaml")
    assert cfg.robots.sensors + cfg.robots.disruptors == 100
    assert cfg.size_m[0] * cfg.size_m[1] >= 6 * 220 * 160 * 0.99
