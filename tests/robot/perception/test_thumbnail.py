"""Thumbnails of detections for the operator: small, cropped around the object, decodable."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from robot.perception.colour_classifier import candidate_mask
from robot.perception.image_memory import ImageMemoryConfig
from robot.perception.thumbnail import make_thumbnail
from sim.camera import camera_axes
from sim.scene import Scene
from sim.world_generator import Ooi
from tests.sim.simworlds import box, make_world


def test_a_rendered_object_thumbnail_is_small_and_shows_the_object() -> None:
    mem = ImageMemoryConfig()
    intr = mem.intrinsics()
    world = make_world(
        solids=[box("wall", 14.0, 5.0, 14.3, 15.0, 2.5)],
        oois=[Ooi(0, "static_ooi", (9.0, 10.5), 0.25, 0.8, (1.0, 0.3, 0.0, 1.0))],
    )
    scene = Scene(world, ray_threads=1)
    sizes = []
    try:
        for d in (1.5, 3.0, 6.0):
            m = np.eye(4)
            m[:2, 3] = (9.0 - d, 10.5)
            eye, fwd, up = camera_axes(m, np.array(mem.mount.camera_in_base_m), 0.0, -0.12)
            rgb = scene.render(
                eye_m=eye,
                forward=fwd,
                up=up,
                width_px=intr.width_px,
                height_px=intr.height_px,
                fy_px=intr.fy_px,
            )
            got = candidate_mask((d, 0.0), 0.25, 0.8, 0.0, -0.12, intr, mem.mount.camera_in_base_m)
            assert got is not None
            thumb = make_thumbnail(rgb, got[1])
            sizes.append(len(thumb.data))
            assert thumb.encoding == "jpeg" and max(thumb.width, thumb.height) <= 64
            img = cv2.imdecode(np.frombuffer(thumb.data, np.uint8), cv2.IMREAD_COLOR)
            assert img.shape[:2] == (thumb.height, thumb.width)
            # the centre of the crop is the orange object (BGR: red high, blue low)
            b, g, r = img[img.shape[0] // 2, img.shape[1] // 2].astype(int)
            assert r > 150 and b < 80
    finally:
        scene.close()
    assert max(sizes) <= 2000


def test_a_busy_crop_still_fits_and_bad_boxes_are_refused() -> None:
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (240, 320, 3), dtype=np.uint8)  # worst case for JPEG
    thumb = make_thumbnail(noise, (100, 50, 220, 200), max_bytes=2000)
    assert len(thumb.data) <= 2500  # the lowest quality is used when none fits
    with pytest.raises(ValueError, match="empty bbox"):
        make_thumbnail(noise, (10, 10, 10, 20))
    with pytest.raises(ValueError, match="outside"):
        make_thumbnail(noise, (400, 300, 500, 400))
    with pytest.raises(ValueError, match="uint8"):
        make_thumbnail(noise.astype(np.float32), (0, 0, 10, 10))
