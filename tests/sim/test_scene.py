"""The PyBullet scene: ray casts (ground clipping, chunking, attribution) and ray workers."""

from __future__ import annotations

import numpy as np
import pytest

from sim.scene import MAX_RAYS_PER_CALL, Scene
from sim.world_generator import Ooi
from tests.sim.simworlds import box, make_world


def _world():
    wall = box("wall", 10.0, 2.0, 10.2, 18.0, 2.5)
    ooi = Ooi(0, "static_ooi", (6.0, 5.0), 0.25, 0.8, (1, 0.3, 0, 1))
    return make_world(solids=[wall], oois=[ooi], robots=[(4.0, 10.0, 0.0, "sensor")])


def _robot_at(x: float, y: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = (x, y, 0.0)
    return m[None]


def test_ray_cast_hits_walls_ground_objects_and_robots() -> None:
    scene = Scene(_world())
    try:
        scene.set_robot_poses(_robot_at(4.0, 10.0))
        scene.sync()
        f = np.array(
            [
                [0.5, 10.0, 1.0],
                [0.5, 10.0, 1.0],
                [0.5, 5.0, 0.4],
                [1.0, 10.0, 0.3],
                [0.5, 15.0, 1.0],
            ]
        )
        t = np.array(
            [
                [20.5, 10.0, 1.0],
                [0.5, 10.0, -1.0],
                [10.5, 5.0, 0.4],
                [7.0, 10.0, 0.3],
                [0.5, 15.0, 5.0],
            ]
        )
        frac, body = scene.ray_cast(f, t)
        assert scene.body_kind[int(body[0])] == ("solid", "wall")
        assert frac[0] * 20.0 == pytest.approx(9.5, abs=1e-4)
        assert body[1] == scene.ground_body and frac[1] == pytest.approx(0.5)
        assert scene.ooi_of_body[body[2]] == 0 and frac[2] * 10.0 == pytest.approx(5.25, abs=1e-3)
        assert scene.robot_of_body[body[3]] == 0  # the chassis (x from 3.7)
        assert frac[3] * 6.0 == pytest.approx(2.7, abs=1e-3)
        assert body[4] == -1 and frac[4] == 1.0  # into the sky
    finally:
        scene.close()


def test_batches_larger_than_one_call_are_chunked() -> None:
    scene = Scene(_world())
    try:
        n = 2 * MAX_RAYS_PER_CALL + 17
        f = np.tile([[0.5, 10.0, 1.0]], (n, 1))
        t = np.tile([[20.5, 10.0, 1.0]], (n, 1))
        frac, body = scene.ray_cast(f, t)
        assert (body == body[0]).all() and np.allclose(frac, 9.5 / 20.0)
    finally:
        scene.close()


def test_a_ray_worker_process_gives_exactly_the_same_hits() -> None:
    world = _world()
    alone, pooled = Scene(world), Scene(world, ray_workers=1)
    try:
        rng = np.random.default_rng(5)
        n = 9000
        f = np.column_stack([rng.uniform(1, 19, n), rng.uniform(1, 19, n), rng.uniform(0.1, 2, n)])
        t = f + rng.normal(size=(n, 3)) * 10.0
        for x in (4.0, 8.5):  # the robot moves; the worker follows
            for s in (alone, pooled):
                s.set_robot_poses(_robot_at(x, 10.0))
                s.sync()
            a, b = alone.ray_cast(f, t), pooled.ray_cast(f, t)
            assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
        for s in (alone, pooled):
            s.hide_ooi(0)
        a, b = alone.ray_cast(f, t), pooled.ray_cast(f, t)
        assert np.array_equal(a[1], b[1])
        assert not (alone.ooi_of_body[np.clip(a[1], 0, None)] == 0).any()
    finally:
        alone.close()
        pooled.close()


def test_the_analytic_ground_gives_the_pixels_tinyrenderer_draws() -> None:
    """The ground filled in after rendering (not rasterized) is the drawn ground, pixel for
    pixel but a few on its outline, in views along the ground, down at it and over the
    world's edge; a hidden robot (under the ground) stays out of view."""
    world = _world()
    fast, drawn = Scene(world, analytic_ground=True), Scene(world)
    try:
        assert fast.ground_rgb is not None and drawn.ground_rgb is None
        poses = np.concatenate([_robot_at(4.0, 10.0), _robot_at(8.0, 12.0)])
        for s in (fast, drawn):
            s.set_robot_poses(poses, hidden=np.array([False, True]))
        views = [  # eye, forward (not unit), image size
            ((2.0, 10.0, 0.9), (1.0, 0.0, -0.12), (320, 240)),
            ((2.0, 10.0, 0.9), (0.3, 1.0, -0.4), (160, 120)),
            ((8.0, 12.0, 3.0), (0.0, 0.2, -1.0), (96, 64)),  # down at the hidden robot
            ((18.0, 3.0, 1.5), (1.0, -0.7, -0.05), (200, 150)),  # over the edge
        ]
        ground_px = 0
        for eye, fwd, (w, h) in views:
            f = np.array(fwd) / np.linalg.norm(fwd)
            side = np.cross(f, [0.0, 0.0, 1.0])
            up = np.cross(side / np.linalg.norm(side), f)
            kw = dict(
                eye_m=np.array(eye), forward=f, up=up, width_px=w, height_px=h,
                fy_px=w / 2 / np.tan(np.radians(30.0)), near_m=0.05, far_m=80.0,
            )  # fmt: skip
            a, b = fast.render(**kw), drawn.render(**kw)
            # pixels on the ground's outline may round the other way (float32 in TinyRenderer)
            differ = int((a != b).any(axis=2).sum())
            assert differ <= max(2, w * h // 2000), f"view from {eye}: {differ} px"
            ground_px += int((a == fast.ground_rgb).all(axis=2).sum())
        assert ground_px > 10_000  # the views do show ground
    finally:
        fast.close()
        drawn.close()


def test_the_compiled_ground_fill_gives_the_ground_pixels_exactly() -> None:
    """The one-pass compiled fill (``Scene._fill_ground``) colours exactly the pixels the
    reference mask (``Scene._ground_pixels``) selects, in views along the ground, down at it,
    over the world's edge and from below the ground plane's far end."""
    world = _world()
    scene = Scene(world, analytic_ground=True)
    try:
        assert scene.ground_rgb is not None
        scene.set_robot_poses(np.concatenate([_robot_at(4.0, 10.0), _robot_at(8.0, 12.0)]))
        rng = np.random.default_rng(5)
        filled = 0
        for k in range(24):
            eye = np.array([rng.uniform(-5, 25), rng.uniform(-5, 25), rng.uniform(0.3, 6.0)])
            f = np.array([rng.normal(), rng.normal(), rng.uniform(-1.0, 0.2)])
            f /= np.linalg.norm(f)
            side = np.cross(f, [0.0, 0.0, 1.0])
            up = np.cross(side / np.linalg.norm(side), f)
            w, h = ((320, 240), (160, 120), (640, 192), (48, 48))[k % 4]
            fy = w / 2 / np.tan(np.radians(30.0))
            rgb, depth = scene._render_raw(eye, f, up, w, h, fy, 0.05, 80.0)
            want = rgb.copy()
            mask = scene._ground_pixels(depth, eye, f, up, fy, 0.05, 80.0)
            want[mask] = scene.ground_rgb
            got = rgb.copy()
            scene._fill_ground(got, depth, eye, f, up, fy, 0.05, 80.0)
            assert np.array_equal(got, want), f"view {k} from {eye.round(2)}"
            filled += int(mask.sum())
        assert filled > 50_000  # the views do show ground
    finally:
        scene.close()


def test_culled_bodies_leave_the_image_unchanged() -> None:
    """Bodies outside the camera's frustum are made transparent for the render
    (TinyRenderer skips them) and the image is the one with every body drawn: posts all
    around, near and beyond the far plane's depth at the frustum's corners, robots that move
    (one hidden), a detonated object; later views bring culled bodies back."""
    rng = np.random.default_rng(3)
    posts = [
        box("post", x - 0.2, y - 0.2, x + 0.2, y + 0.2, float(rng.uniform(0.5, 3.0)))
        for x, y in rng.uniform(0.0, 120.0, (60, 2))
    ]
    oois = [Ooi(0, "static_ooi", (12.0, 8.0), 0.25, 0.8, (1, 0.3, 0, 1))]
    robots = [(float(x), float(y), float(t), "sensor") for x, y, t in rng.uniform(5, 60, (6, 3))]
    world = make_world(solids=posts, oois=oois, robots=robots, size_m=(120.0, 120.0))
    culled, full = Scene(world, cull=True), Scene(world)
    try:
        mats = np.concatenate([_robot_at(x, y) for x, y, _, _ in robots])
        differ = drawn_min = 0
        for step in range(8):
            mats[:, 0, 3] += 0.7  # the robots move on
            hidden = np.arange(len(robots)) == step % len(robots)
            for s in (culled, full):
                s.set_robot_poses(mats, hidden=hidden)
                if step == 4:
                    s.hide_ooi(0)
            eye = np.array([*rng.uniform(0.0, 30.0, 2), rng.uniform(0.5, 2.0)])
            yaw = rng.uniform(0.0, 2 * np.pi)
            f = np.array([np.cos(yaw), np.sin(yaw), rng.uniform(-0.3, 0.1)])
            f /= np.linalg.norm(f)
            side = np.cross(f, [0.0, 0.0, 1.0])
            up = np.cross(side / np.linalg.norm(side), f)
            kw = dict(
                eye_m=eye, forward=f, up=up, width_px=160, height_px=120,
                fy_px=80 / np.tan(np.radians(30.0)), near_m=0.05, far_m=80.0,
            )  # fmt: skip
            a, b = culled.render(**kw), full.render(**kw)
            differ += int((a != b).any(axis=2).sum())
            drawn_min = max(drawn_min, len(posts) - int(culled._cull_drawn.sum()))
        assert differ == 0
        assert drawn_min > 10  # bodies were culled
    finally:
        culled.close()
        full.close()
