"""Frames with nothing to find are answered flat, every other frame is rendered as before
(issue 16: camera renders at scale, :mod:`sim.camera`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from protocol.sensors import CameraImage, ImageRequest
from sim.camera import CameraConfig, camera_axes, in_frustum
from sim.simulator import Simulator, SimulatorConfig
from sim.world_generator import Human, Ooi
from tests.sim.simworlds import box, make_world


def _hits(points: list[tuple[float, float, float]], radius: float, range_m: float) -> list[bool]:
    # a camera at the origin looking along +x, 60 x 45 deg
    out = in_frustum(
        np.zeros(3),
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 0.0, 1.0]),
        hfov_rad=math.radians(60),
        vfov_rad=math.radians(45),
        near_m=0.05,
        centers_m=np.array(points, dtype=float),
        radii_m=np.full(len(points), radius),
        ranges_m=np.full(len(points), range_m),
    )
    return [bool(v) for v in out]


def test_spheres_in_front_and_touching_the_edges_count_and_others_do_not() -> None:
    t30 = math.tan(math.radians(30))
    points = [
        (5.0, 0.0, 0.0),  # straight ahead
        (-5.0, 0.0, 0.0),  # behind
        (5.0, 5.0 * t30 + 0.2, 0.0),  # just outside the left edge, 0.2 m from its line
        (5.0, -5.0 * t30 - 0.2, 0.0),  # the same on the right
        (5.0, 5.0 * t30 + 0.6, 0.0),  # farther out
        (5.0, 0.0, 3.0),  # above the top edge (22.5 deg: 2.07 m at 5 m)
        (30.0, 0.0, 0.0),  # beyond the range
    ]
    assert _hits(points, 0.3, 20.0) == [True, False, True, True, False, False, False]
    # the range counts to the sphere's surface
    assert _hits([(20.2, 0.0, 0.0)], 0.3, 20.0) == [True]


def _world(with_subjects: bool):
    robots = [(10.0, 10.0, 0.0, "sensor"), (10.0, 30.0, 0.0, "sensor")]  # 20 m apart
    wall = box("wall", 16.0, 0.0, 16.2, 40.0, 2.5)  # terrain: 40 m long
    if not with_subjects:
        return make_world(robots=robots, solids=[wall], size_m=(40.0, 40.0))
    ooi = Ooi(0, "static_ooi", (14.0, 10.5), 0.25, 0.8, (1, 0.3, 0, 1))
    walker = Human(0, "civilian", ((13.0, 8.0),), 0.0, 0.25, 1.7, (0.1, 0.2, 0.9, 1))
    return make_world(
        robots=robots, solids=[wall], oois=[ooi], humans=[walker], size_m=(40.0, 40.0)
    )


def _image(with_subjects: bool, skip_empty: bool, size: tuple[int, int]) -> CameraImage:
    cfg = SimulatorConfig(
        render_workers=0, camera=CameraConfig(pan_rate_rad_s=0.0, skip_empty=skip_empty)
    )
    with Simulator(_world(with_subjects), config=cfg) as sim:
        sim.driver(0).send(ImageRequest(1, 0.0, *size))
        sim.step()
        img = next(f for f in sim.driver(0).poll(0.0) if isinstance(f, CameraImage))
        assert sim.empty_frames == (1 if skip_empty and not with_subjects else 0)
        return img


@pytest.mark.parametrize("size", [(320, 240), (640, 480)])
def test_a_frame_of_terrain_only_is_flat_and_one_with_subjects_is_rendered(
    size: tuple[int, int],
) -> None:
    flat = _image(False, True, size)
    drawn = _image(False, False, size)
    assert flat.rgb.shape == drawn.rgb.shape == (size[1], size[0], 3)
    assert np.all(flat.rgb == np.array(CameraConfig().empty_rgb, dtype=np.uint8))
    assert len(np.unique(drawn.rgb.reshape(-1, 3), axis=0)) >= 3  # ground, sky, the wall
    assert (flat.time_s, flat.camera_pan_rad, flat.fx_px) == (
        drawn.time_s,
        drawn.camera_pan_rad,
        drawn.fx_px,
    )
    # an object and a person in view: the very pixels of a render
    a = _image(True, True, size)
    b = _image(True, False, size)
    assert np.array_equal(a.rgb, b.rgb)


def test_a_teammate_counts_while_its_tag_can_span_min_tag_px() -> None:
    cc = CameraConfig(pan_rate_rad_s=0.0)
    with Simulator(make_world(robots=[(10.0, 10.0, 0.0, "sensor")]), config=SimulatorConfig(
        camera=cc, render_workers=0
    )) as sim:  # fmt: skip
        fx = 160 / math.tan(math.radians(30))
        tag_range = fx * sim.geometry.tag_size_m / cc.min_tag_px  # 4.7 m at 320 px
        assert 4.0 < tag_range < 5.0
        for dist, expect in ((tag_range - 0.5, True), (tag_range + 1.5, False)):
            robots = [(10.0, 10.0, 0.0, "sensor"), (10.0 + dist, 10.0, math.pi, "sensor")]
            with Simulator(make_world(robots=robots), config=sim.config) as s2:
                req = ImageRequest(1, 0.0, 320, 240)
                j, _ = s2._recorded(req)
                assert s2._frame_has_subjects(0, j, req) is expect
                # twice the pixels: twice the range
                big = ImageRequest(2, 0.0, 640, 480)
                assert s2._frame_has_subjects(0, j, big) is True


def test_camera_axes_look_where_the_frustum_test_assumes() -> None:
    eye, fwd, up = camera_axes(np.eye(4), np.array([0.0, 0.0, 1.0]), 0.0, 0.0)
    assert np.allclose(eye, [0, 0, 1]) and np.allclose(fwd, [1, 0, 0])
    assert np.allclose(up, [0, 0, 1])
