"""Training and held-out evaluation of the camera colour classifier (paper 5.2.1).

The paper learnt YCrCb thresholds "from a training set of images that were obtained under
various lighting conditions". Here: seeded simulated worlds (:func:`training_world`), each
object of interest and person seen from random robot poses 1.5-8 m away with the robot's own
camera geometry, under a random light per image (direction, ambient and diffuse strength:
the scene's ``light_*`` settings, which :meth:`sim.scene.Scene.render` uses). Labels come from
PyBullet's segmentation mask (ground truth: allowed here, never on a robot).

:func:`evaluate` runs the robot's own classifier (:func:`robot.perception.colour_classifier.
classify_candidate`) on held-out worlds, on the objects and on distractors (tree trunks, car,
wall and fence faces) placed where a LIDAR candidate would be, and reports the confusion
matrix over {static_ooi, toxic_vat, civilian, hostile, other}, the confusion rate and the time
per candidate.

``python -m mission.perception_camera_training --out robot/perception/colour_thresholds_v1.json``
trains, writes the versioned file and prints the held-out evaluation.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from protocol.cli_parser import CommandParser
from robot.perception.camera_model import Intrinsics
from robot.perception.colour_classifier import (
    CLASSES,
    ColourThresholdError,
    ColourThresholds,
    classify_candidate,
    load_thresholds,
    save_thresholds,
    train_thresholds,
)
from robot.perception.image_memory import ImageMemoryConfig
from sim.camera import camera_axes
from sim.quiet_pybullet import import_pybullet
from sim.scene import Scene
from sim.world_generator import (
    CarsConfig,
    HumansConfig,
    ObjectsConfig,
    TreesConfig,
    World,
    WorldConfig,
    generate_world,
)

__all__ = ["View", "evaluate", "main", "record_pixels", "training_world", "views"]

pb = import_pybullet()

TRAIN_SEEDS = (101, 102, 103, 104)
TEST_SEEDS = (201, 202, 203)
LABELS = (*CLASSES, "other")


def training_world(seed: int) -> World:
    """A world with more objects, people, trees and cars than a contest phase."""
    return generate_world(
        WorldConfig(
            seed=seed,
            static_oois=ObjectsConfig(count=4),
            toxic_vats=ObjectsConfig(
                count=3, radius_m=0.3, height_m=0.9, rgba=(0.95, 0.85, 0.0, 1.0)
            ),
            civilians=HumansConfig(count=3),
            hostiles=HumansConfig(count=3, rgba=(0.9, 0.05, 0.05, 1.0)),
            trees=TreesConfig(count=8),
            cars=CarsConfig(count=5),
        )
    )


@dataclass(frozen=True)
class View:
    """One rendered image of one target: its label, the candidate cylinder in the camera
    robot's ``base``, the image, the segmentation-visible share of the candidate outline."""

    label: str
    center_in_base: tuple[float, float]
    radius_m: float
    height_m: float
    bottom_z_m: float
    rgb: np.ndarray
    target_mask: np.ndarray  # pixels of the target body


def _randomize_light(scene: Scene, rng: np.random.Generator) -> None:
    az = rng.uniform(0, 2 * math.pi)
    el = rng.uniform(0.15, 1.4)
    scene.light_direction = [math.cos(az) * math.cos(el), math.sin(az) * math.cos(el), math.sin(el)]
    scene.light_ambient = float(rng.uniform(0.3, 0.85))
    scene.light_diffuse = float(rng.uniform(0.15, 0.7))


def _targets(
    world: World, scene: Scene
) -> list[tuple[str, int, tuple[float, float], float, float, float]]:
    """``(label, body, xy, radius, height, ground z)`` of objects, people and distractors."""
    out: list[tuple[str, int, tuple[float, float], float, float, float]] = []
    for o in world.oois:
        out.append((o.kind, scene.ooi_body[o.ooi_id], o.xy_m, o.radius_m, o.height_m, o.ground_z_m))
    for h, b in zip(world.humans, scene.human_body, strict=True):
        out.append((h.kind, b, h.route_m[0], h.radius_m, h.height_m, 0.0))
    solid_bodies = [
        b for b, k in scene.body_kind.items() if k[0] == "solid" and b != scene.ground_body
    ]
    for s, b in zip(world.solids, solid_bodies, strict=True):
        if s.kind == "trunk":
            out.append(
                (
                    "other",
                    b,
                    (s.center_m[0], s.center_m[1]),
                    s.half_extents_m[0],
                    min(1.2, 2 * s.half_extents_m[2]),
                    0.0,
                )
            )
        elif s.kind in ("car", "wall", "fence") and s.center_m[2] - s.half_extents_m[2] < 0.3:
            out.append(("other", b, (s.center_m[0], s.center_m[1]), -1.0, 0.9, 0.0))  # on its face
    return out


def views(
    world: World,
    rng: np.random.Generator,
    *,
    per_target: int,
    memory: ImageMemoryConfig | None = None,
) -> Iterator[View]:
    """Rendered views of every target from random robot poses (random light each)."""
    mem = memory or ImageMemoryConfig()
    intr = mem.intrinsics()
    cam_m = np.array(mem.mount.camera_in_base_m)
    scene = Scene(world, ray_threads=1)
    try:
        for label, body, xy, radius, height, z0 in _targets(world, scene):
            for _ in range(per_target):
                d = rng.uniform(1.5, 8.0)
                bearing = rng.uniform(-math.pi, math.pi)
                cx, cy = xy
                if radius < 0:  # a box's face: the candidate stands on the face nearest the robot
                    x, y = cx + d * math.cos(bearing), cy + d * math.sin(bearing)
                    frac, hit = scene.ray_cast(np.array([[x, y, 0.45]]), np.array([[cx, cy, 0.45]]))
                    if hit[0] != body:
                        continue
                    cx, cy = x + (cx - x) * frac[0], y + (cy - y) * frac[0]
                    cx, cy = cx + 0.2 * math.cos(bearing), cy + 0.2 * math.sin(bearing)
                    r_cand = 0.25
                else:
                    x, y = cx + d * math.cos(bearing), cy + d * math.sin(bearing)
                    r_cand = radius
                yaw = math.atan2(cy - y, cx - x) + rng.uniform(-0.35, 0.35)
                m = np.eye(4)
                m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
                m[:2, 3] = (x, y)
                eye, fwd, up = camera_axes(m, cam_m, 0.0, mem.mount.tilt_rad)
                _randomize_light(scene, rng)
                rgb, seg = _render_with_segmentation(scene, eye, fwd, up, intr)
                dx, dy = cx - x, cy - y
                c, s = math.cos(yaw), math.sin(yaw)
                center = (c * dx + s * dy, -s * dx + c * dy)
                yield View(label, center, r_cand, height, z0, rgb, seg == body)
    finally:
        scene.close()


def _render_with_segmentation(
    scene: Scene, eye: np.ndarray, fwd: np.ndarray, up: np.ndarray, intr: Intrinsics
) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`Scene.render`'s image plus the body-id segmentation mask (training labels)."""
    w, h = intr.width_px, intr.height_px
    view = pb.computeViewMatrix(eye.tolist(), (eye + fwd).tolist(), up.tolist())
    vfov = math.degrees(2 * math.atan(h / 2 / intr.fy_px))
    proj = pb.computeProjectionMatrixFOV(vfov, w / h, 0.05, 80.0)
    out = pb.getCameraImage(
        w,
        h,
        view,
        proj,
        renderer=pb.ER_TINY_RENDERER,
        shadow=0,
        lightDirection=scene.light_direction,
        lightAmbientCoeff=scene.light_ambient,
        lightDiffuseCoeff=scene.light_diffuse,
        lightSpecularCoeff=0.0,
        flags=pb.ER_SEGMENTATION_MASK_OBJECT_AND_LINKINDEX,
        physicsClientId=scene.client,
    )
    rgba = np.reshape(np.asarray(out[2], dtype=np.uint8), (h, w, 4))
    seg = np.reshape(np.asarray(out[4], dtype=np.int64), (h, w))
    seg = np.where(seg >= 0, seg & ((1 << 24) - 1), -1)
    return np.ascontiguousarray(rgba[:, :, :3]), seg


def record_pixels(
    seeds: Sequence[int], *, per_target: int, rng_seed: int = 0
) -> dict[str, np.ndarray]:
    """YCrCb pixels of every colour class, from the segmentation of training views."""
    import cv2

    rng = np.random.default_rng(rng_seed)
    acc: dict[str, list[np.ndarray]] = {c: [] for c in CLASSES}
    for seed in seeds:
        for v in views(training_world(seed), rng, per_target=per_target):
            if v.label in acc and v.target_mask.sum() >= 30:
                ycc = cv2.cvtColor(v.rgb, cv2.COLOR_RGB2YCrCb)[v.target_mask]
                acc[v.label].append(ycc[rng.permutation(len(ycc))[:400]])
    return {c: np.vstack(p) if p else np.zeros((0, 3)) for c, p in acc.items()}


def evaluate(
    thresholds: ColourThresholds, seeds: Sequence[int], *, per_target: int, rng_seed: int = 1
) -> dict[str, object]:
    """Confusion matrix (rows truth, columns predicted, in :data:`LABELS` order) of the
    robot's classifier on held-out views whose candidate is at least half visible, the
    confusion rate (off-diagonal share) and ms per candidate (p50, p95)."""
    mem = ImageMemoryConfig()
    intr = mem.intrinsics()
    rng = np.random.default_rng(rng_seed)
    conf = np.zeros((len(LABELS), len(LABELS)), dtype=int)
    ms: list[float] = []
    for seed in seeds:
        for v in views(training_world(seed), rng, per_target=per_target):
            from robot.perception.colour_classifier import candidate_mask

            got = candidate_mask(
                v.center_in_base,
                v.radius_m,
                v.height_m,
                0.0,
                mem.mount.tilt_rad,
                intr,
                mem.mount.camera_in_base_m,
                bottom_z_m=v.bottom_z_m,
            )
            if got is None:
                continue
            mask, (u0, v0, u1, v1) = got
            if u0 <= 0 or v0 <= 0 or u1 >= intr.width_px - 1 or v1 >= intr.height_px - 1:
                continue  # not fully in the image: the image memory would pick another frame
            if mask.sum() < 20 or (mask & v.target_mask).sum() < 0.5 * mask.sum():
                continue  # occluded: not a fair test of colour
            t = time.perf_counter()
            res = classify_candidate(
                v.rgb,
                v.center_in_base,
                v.radius_m,
                v.height_m,
                0.0,
                mem.mount.tilt_rad,
                intr,
                mem.mount.camera_in_base_m,
                thresholds,
                bottom_z_m=v.bottom_z_m,
            )
            ms.append((time.perf_counter() - t) * 1e3)
            if res is None:
                continue
            conf[LABELS.index(v.label), LABELS.index(res.label)] += 1
    n = int(conf.sum())
    return {
        "labels": list(LABELS),
        "confusion": conf.tolist(),
        "candidates": n,
        "class_confusion": float((n - np.trace(conf)) / n) if n else float("nan"),
        "colour_ms_per_candidate_p50": float(np.percentile(ms, 50)) if ms else float("nan"),
        "colour_ms_per_candidate_p95": float(np.percentile(ms, 95)) if ms else float("nan"),
    }


def main(argv: Sequence[str] | None = None) -> int:
    ap = CommandParser(prog="magic perception colour", description=__doc__.splitlines()[0])
    ap.add_argument("--train-seeds", type=int, nargs="+", default=list(TRAIN_SEEDS))
    ap.add_argument("--test-seeds", type=int, nargs="+", default=list(TEST_SEEDS))
    ap.add_argument("--per-target", type=int, default=4, help="views per object per world")
    ap.add_argument("--out", help="write the trained thresholds here (versioned JSON)")
    ap.add_argument("--thresholds", help="evaluate this file instead of training")
    args = ap.parse_args(argv)
    # bad paths are one line and status 2, before the rendering starts
    if args.out and not Path(args.out).resolve().parent.is_dir():
        print(f"magic perception colour: --out {args.out}: no such directory", file=sys.stderr)
        return 2
    if args.per_target < 1:
        print("magic perception colour: --per-target must be >= 1", file=sys.stderr)
        return 2
    if args.thresholds:
        try:
            thr = load_thresholds(args.thresholds)
        except ColourThresholdError as err:
            print(f"magic perception colour: {err}", file=sys.stderr)
            return 2
    else:
        px = record_pixels(args.train_seeds, per_target=args.per_target)
        thr = train_thresholds(
            px,
            trained_on=f"worlds {args.train_seeds}, {args.per_target} views/target, random light",
        )
        if args.out:
            save_thresholds(thr, args.out)
    report = evaluate(thr, args.test_seeds, per_target=args.per_target)
    print(json.dumps(report, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
