"""The camera model's transform: a rotation whose right axis is forward x up, bit for bit."""

from __future__ import annotations

import math

import numpy as np

from robot.perception.camera_model import base_from_camera


def test_base_from_camera_is_a_rotation_with_right_equal_to_numpy_cross() -> None:
    rng = np.random.default_rng(0)
    for _ in range(2000):
        pan, tilt = rng.uniform(-math.pi, math.pi), rng.uniform(-1.4, 1.4)
        m = base_from_camera(pan, tilt, (-0.12, 0.0, 0.92))
        rot = m[:3, :3]
        assert np.allclose(rot.T @ rot, np.eye(3), atol=1e-12)
        assert math.isclose(float(np.linalg.det(rot)), 1.0, abs_tol=1e-12)
        fwd, up = rot[:, 2], -rot[:, 1]
        # written out in the module for speed: the same floats as numpy's cross product
        assert np.array_equal(rot[:, 0], np.cross(fwd, up))
        assert np.array_equal(m[:3, 3], [-0.12, 0.0, 0.92])
