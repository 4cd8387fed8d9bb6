"""The synthetic LIDAR used to test terrain classification is itself checked: hits lie on
the surfaces they are labelled with, nothing is seen through solids, frames agree."""

from __future__ import annotations

import math

import numpy as np

from robot.terrain.synthetic_scene import (
    FACE,
    GROUND,
    TOP,
    Scene,
    box,
    cast_sweep,
    issue_scene,
)


def test_hits_lie_on_their_surfaces() -> None:
    scene = Scene([box((3.0, 0.0), (1.0, 2.0), 0.5)])
    hits = cast_sweep(scene, (0.0, 0.0, 0.0), rng=np.random.default_rng(0), range_noise_m=0.0)
    p, lab = hits.points_in_odom, hits.labels
    assert np.allclose(p[lab == GROUND, 2], 0.0, atol=1e-9)
    face = p[lab == FACE]
    assert len(face) > 50
    # Seen from the origin only the near face x = 2.5 (and the box top) is visible.
    assert np.allclose(face[:, 0], 2.5, atol=1e-9)
    assert (face[:, 2] >= -1e-9).all() and (face[:, 2] <= 0.5 + 1e-9).all()
    assert np.allclose(p[lab == TOP, 2], 0.5, atol=1e-9)
    # Nothing behind the box within its shadow on the ground.
    ground = p[lab == GROUND]
    shadow = (ground[:, 0] > 2.5) & (ground[:, 0] < 3.5) & (np.abs(ground[:, 1]) < 0.9)
    assert not shadow.any()


def test_base_and_odom_points_agree() -> None:
    pose = (1.0, -2.0, 0.7)
    hits = cast_sweep(issue_scene(), pose, rng=np.random.default_rng(1))
    c, s = math.cos(pose[2]), math.sin(pose[2])
    b = hits.points_in_base.astype(np.float64)
    odom = np.c_[pose[0] + c * b[:, 0] - s * b[:, 1], pose[1] + s * b[:, 0] + c * b[:, 1], b[:, 2]]
    np.testing.assert_allclose(odom, hits.points_in_odom, atol=1e-4)
    assert hits.points_in_base.dtype == np.float32
    assert len(hits.labels) == len(hits.solid_index) == len(b)


def test_density_falls_off_with_range() -> None:
    hits = cast_sweep(Scene(), (0.0, 0.0, 0.0), rng=np.random.default_rng(2))
    r = np.hypot(hits.points_in_odom[:, 0], hits.points_in_odom[:, 1])
    near = ((r > 1) & (r < 2)).sum() / (math.pi * (4 - 1))
    far = ((r > 8) & (r < 9)).sum() / (math.pi * (81 - 64))
    assert near > 5 * far
