"""YCrCb colour of LIDAR candidates (paper 5.2.1) on real PyBullet renders, and the threshold
file's round trip and errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from robot.perception.colour_classifier import (
    CLASSES,
    ColourThresholdError,
    classify_candidate,
    classify_pixels,
    load_thresholds,
    save_thresholds,
    train_thresholds,
)
from robot.perception.image_memory import ImageMemoryConfig
from sim.camera import camera_axes
from sim.scene import Scene
from sim.world_generator import Human, Ooi, Solid
from tests.sim.simworlds import box, make_world

MEM = ImageMemoryConfig()
# (label, centre, radius, height): the simulator's default objects, people and distractors
TARGETS = [
    ("static_ooi", (9.0, 12.0), 0.25, 0.8),
    ("toxic_vat", (9.0, 8.0), 0.3, 0.9),
    ("civilian", (12.0, 13.0), 0.25, 1.7),
    ("hostile", (12.0, 7.0), 0.25, 1.7),
    ("other", (12.0, 16.5), 0.2, 1.2),  # a tree trunk
    ("other", (14.3, 11.5), 0.25, 0.8),  # in front of a wall
    ("other", (9.5, 10.0), 0.25, 0.8),  # in front of a grey car
]


@pytest.fixture(scope="module")
def scene() -> Scene:
    trunk = Solid(
        "trunk",
        "cylinder",
        "obstacle",
        (12.0, 16.5, 0.6),
        (0.2, 0.2, 0.6),
        rgba=(0.4, 0.27, 0.15, 1.0),
    )  # type: ignore[arg-type]
    car = Solid(
        "car", "box", "obstacle", (10.3, 10.0, 0.6), (0.5, 1.0, 0.35), rgba=(0.5, 0.45, 0.35, 1.0)
    )  # type: ignore[arg-type]
    world = make_world(
        solids=[box("wall", 14.5, 5.0, 14.8, 15.0, 2.5), trunk, car],
        oois=[
            Ooi(0, "static_ooi", (9.0, 12.0), 0.25, 0.8, (1.0, 0.3, 0.0, 1.0)),
            Ooi(1, "toxic_vat", (9.0, 8.0), 0.3, 0.9, (0.95, 0.85, 0.0, 1.0)),
        ],
        humans=[
            Human(0, "civilian", ((12.0, 13.0),), 0.0, 0.25, 1.7, (0.1, 0.2, 0.9, 1.0)),
            Human(1, "hostile", ((12.0, 7.0),), 0.0, 0.25, 1.7, (0.9, 0.05, 0.05, 1.0)),
        ],
    )
    s = Scene(world, ray_threads=1)
    yield s
    s.close()


LIGHTS = [
    ([0.3, 0.2, 1.0], 0.65, 0.4),
    ([-1.0, 0.5, 0.3], 0.35, 0.6),
    ([0.2, -1.0, 0.8], 0.85, 0.15),
]


@pytest.mark.parametrize("light", LIGHTS, ids=["default", "low-sun", "bright-ambient"])
def test_rendered_objects_and_distractors_are_told_apart(scene: Scene, light: tuple) -> None:
    scene.light_direction, scene.light_ambient, scene.light_diffuse = light
    thresholds = load_thresholds()
    intr = MEM.intrinsics()
    wrong = []
    for label, (cx, cy), radius, height in TARGETS:
        # a robot 3-5 m away looking at the candidate (camera panned straight ahead)
        d = 3.0 + (cx + cy) % 2.0
        x, y = cx - d, cy
        yaw = 0.0
        m = np.eye(4)
        m[:2, 3] = (x, y)
        rgb = _render(scene, m)
        res = classify_candidate(
            rgb,
            (cx - x, cy - y),
            radius,
            height,
            0.0,
            MEM.mount.tilt_rad,
            intr,
            MEM.mount.camera_in_base_m,
            thresholds,
        )
        assert res is not None and yaw == 0.0
        if res.label != label:
            wrong.append((label, res.label, round(res.fraction, 2)))
    assert wrong == []


def _render(scene: Scene, world_from_base: np.ndarray) -> np.ndarray:
    intr = MEM.intrinsics()
    eye, fwd, up = camera_axes(
        world_from_base, np.array(MEM.mount.camera_in_base_m), 0.0, MEM.mount.tilt_rad
    )
    return scene.render(
        eye_m=eye,
        forward=fwd,
        up=up,
        width_px=intr.width_px,
        height_px=intr.height_px,
        fy_px=intr.fy_px,
    )


def test_a_candidate_outside_the_image_or_a_mismatched_image_is_refused(scene: Scene) -> None:
    thresholds = load_thresholds()
    intr = MEM.intrinsics()
    rgb = _render(scene, np.eye(4))
    cam = MEM.mount.camera_in_base_m
    assert (
        classify_candidate(rgb, (-3.0, 0.0), 0.25, 0.8, 0.0, -0.12, intr, cam, thresholds) is None
    )
    with pytest.raises(ValueError, match="does not match intrinsics"):
        classify_candidate(rgb[:100], (3.0, 0.0), 0.25, 0.8, 0.0, -0.12, intr, cam, thresholds)


def test_training_finds_separable_boxes_and_the_file_round_trips(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    # synthetic YCrCb clusters, each colour under 0.4x-1.2x light: Y, Cr-128, Cb-128 scale
    albedo = {
        "static_ooi": (121, 95, -68),
        "toxic_vat": (199, 31, -112),
        "civilian": (64, -27, 94),
        "hostile": (78, 108, -37),
    }
    px = {}
    for c, (y, cr, cb) in albedo.items():
        k = rng.uniform(0.4, 1.2, 500)[:, None]
        px[c] = np.clip(
            np.column_stack([y * k[:, 0], 128 + cr * k[:, 0], 128 + cb * k[:, 0]])
            + rng.normal(0, 2, (500, 3)),
            0,
            255,
        )
    thr = train_thresholds(px, trained_on="synthetic")
    for c in CLASSES:
        assert classify_pixels(px[c], thr)[0] == c
    grey = np.column_stack(
        [rng.uniform(30, 220, 300), 128 + rng.normal(0, 3, 300), 128 + rng.normal(0, 3, 300)]
    )
    assert classify_pixels(grey, thr)[0] == "other"
    path = tmp_path / "thr.json"
    save_thresholds(thr, path)
    back = load_thresholds(path)
    assert back.boxes == thr.boxes and back.min_fraction == thr.min_fraction
    assert back.trained_on == "synthetic"
    with pytest.raises(ValueError, match="hostile has 0 pixels"):
        train_thresholds({c: v for c, v in px.items() if c != "hostile"})


def _write(tmp_path: Path, doc: object) -> Path:
    p = tmp_path / "bad.json"
    p.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return p


def test_a_corrupt_or_mismatched_threshold_file_is_a_clear_error(tmp_path: Path) -> None:
    good = json.loads(Path(load_thresholds.__defaults__[0]).read_text())  # type: ignore[index]
    cases: list[tuple[object, str]] = [
        ("{not json", "not valid JSON"),
        ({"format": "something-else"}, "not a colour threshold file"),
        ({**good, "version": 2}, "threshold file version 2, this code reads version 1"),
        (
            {**good, "classes": {k: v for k, v in good["classes"].items() if k != "toxic_vat"}},
            "classes missing: toxic_vat",
        ),
        (
            {
                **good,
                "classes": {
                    **good["classes"],
                    "civilian": {**good["classes"]["civilian"], "cr": [200, 100]},
                },
            },
            r"classes.civilian.cr must be \[lo, hi\]",
        ),
        (
            {
                **good,
                "classes": {
                    **good["classes"],
                    "hostile": {**good["classes"]["hostile"], "hue_deg": [0, math.inf]},
                },
            },
            "classes.hostile.hue_deg",
        ),
        ({**good, "min_fraction": 0}, "min_fraction must be in"),
    ]
    for doc, match in cases:
        with pytest.raises(ColourThresholdError, match=match) as err:
            load_thresholds(_write(tmp_path, doc))
        assert "bad.json" in str(err.value)
    with pytest.raises(ColourThresholdError, match="cannot read"):
        load_thresholds(tmp_path / "missing.json")


def test_eight_bit_pixels_by_table_give_the_per_pixel_tests_answer() -> None:
    # uint8 pixels go through per-value tables of the box tests; float pixels through the
    # features of each pixel: the same class and share for any pixels, and the tables hold
    # exactly the per-pixel tests for every (Cr, Cb) at a few Y
    from robot.perception.colour_classifier import _class_bits, _features

    thr = load_thresholds()
    rng = np.random.default_rng(4)
    lo, hi = thr.lo_hi()
    for trial in range(400):
        n = int(rng.choice([1, 5, 17, 300, 4000]))
        k = trial % 4
        mid, half = (lo[k, :3] + hi[k, :3]) / 2, (hi[k, :3] - lo[k, :3]) / 2 + 12
        px = np.clip(np.round(rng.uniform(mid - half, mid + half, (n, 3))), 0, 255)
        if trial % 5 == 0:
            px = rng.integers(0, 256, (n, 3))
        px8 = px.astype(np.uint8)
        assert classify_pixels(px8, thr) == classify_pixels(px8.astype(float), thr)
    y_bits, cc_bits = _class_bits(thr)
    cr, cb = np.meshgrid(np.arange(256), np.arange(256), indexing="ij")
    for y in (0, 90, 181, 255):
        px8 = np.column_stack([np.full(cr.size, y), cr.ravel(), cb.ravel()]).astype(np.uint8)
        f = _features(px8.astype(float))
        inside = np.all((f[None] >= lo[:, None]) & (f[None] <= hi[:, None]), axis=2)
        bits = y_bits[px8[:, 0]] & cc_bits[px8[:, 1].astype(np.intp) * 256 + px8[:, 2]]
        for k in range(len(lo)):
            np.testing.assert_array_equal(inside[k], (bits & (1 << k)) != 0)
