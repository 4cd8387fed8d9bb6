"""Image memory of the panning camera (paper 5.2.1, Fig. 13) and the camera model."""

from __future__ import annotations

import math

import numpy as np
import pytest

from robot.perception.camera_model import (
    CameraMountConfig,
    base_from_camera,
    fit_pan_phase,
    pan_at,
)
from robot.perception.image_memory import Candidate, ImageMemory, ImageMemoryConfig, RememberedFrame
from sim.camera import CameraConfig, camera_axes, pan_angle
from sim.scene import RobotGeometry


def test_mount_defaults_are_the_simulated_robots() -> None:
    mount, cam, geo = CameraMountConfig(), CameraConfig(), RobotGeometry()
    assert mount.camera_in_base_m == geo.camera_m
    assert (mount.pan_rate_rad_s, mount.pan_limit_rad, mount.tilt_rad) == (
        cam.pan_rate_rad_s,
        cam.pan_limit_rad,
        cam.tilt_rad,
    )
    assert ImageMemoryConfig().hfov_deg == cam.hfov_deg


@pytest.mark.parametrize(("pan", "tilt"), [(0.0, -0.12), (1.1, -0.12), (-2.5, 0.3)])
def test_camera_axes_match_the_simulators(pan: float, tilt: float) -> None:
    world_from_base = np.eye(4)
    eye, fwd, up = camera_axes(world_from_base, np.array(RobotGeometry().camera_m), pan, tilt)
    m = base_from_camera(pan, tilt, RobotGeometry().camera_m)
    np.testing.assert_allclose(m[:3, 3], eye)
    np.testing.assert_allclose(m[:3, 2], fwd, atol=1e-12)  # optical axis
    np.testing.assert_allclose(-m[:3, 1], up, atol=1e-12)  # image rows grow downwards


def test_the_pan_phase_is_learnt_from_two_images() -> None:
    cam, mount = CameraConfig(), CameraMountConfig()
    phase = 3.7
    samples = [(t, pan_angle(t, cam, phase_s=phase)) for t in (10.0, 10.4, 31.2)]
    est, rms = fit_pan_phase(samples, mount)
    assert rms < 0.01
    for t in np.linspace(0, 40, 17):
        assert pan_at(float(t), mount, est) == pytest.approx(
            pan_angle(float(t), cam, phase_s=phase), abs=0.02
        )
    with pytest.raises(ValueError, match="no"):
        fit_pan_phase([], mount)


def _fig13_memory() -> ImageMemory:
    """A robot driving along +x at 0.5 m/s whose camera pans left (0.6 rad/s); frames every
    0.5 s: A..E (Fig. 13's five images)."""
    mem = ImageMemory(ImageMemoryConfig())
    for k in range(5):
        t = 1.0 + 0.5 * k
        mem.record(RememberedFrame(t, -0.6 + 0.6 * k, -0.12, (0.5 * k, 0.0, 0.0)))
    return mem


def test_fig13_the_newest_image_in_which_the_object_projects_fully() -> None:
    mem = _fig13_memory()
    frames = mem.frames
    # object 1: across the left edge of A (pan -0.6), fully in B (pan 0) only
    obj1 = Candidate((4.0, -0.35), 0.25, 0.8)
    full = [mem.projects_fully(f, obj1) for f in frames]
    assert full[:2] == [False, True]
    assert mem.choose(obj1) is frames[1]
    # object 2: to the left: fully in C and D (pan 0.6, 1.2): the newer, D, is returned
    obj2 = Candidate((3.0, 3.5), 0.3, 0.9)
    full = [mem.projects_fully(f, obj2) for f in frames]
    assert full[2] and full[3] and not full[4]
    assert mem.choose(obj2) is frames[3]
    assert mem.choose(obj2, not_after_s=frames[2].time_s) is frames[2]
    # behind the robot: no frame
    assert mem.choose(Candidate((-3.0, 0.0), 0.25, 0.8)) is None


def test_frames_are_forgotten_after_the_history_and_bad_frames_are_counted() -> None:
    mem = ImageMemory(ImageMemoryConfig(history_s=2.0))
    for k in range(10):
        assert mem.record(RememberedFrame(float(k), 0.0, -0.12, (0.0, 0.0, 0.0)))
    assert [f.time_s for f in mem.frames] == [7.0, 8.0, 9.0]
    assert not mem.record(RememberedFrame(9.0, 0.0, -0.12, (0.0, 0.0, 0.0)))  # not newer
    assert not mem.record(RememberedFrame(10.0, math.nan, -0.12, (0.0, 0.0, 0.0)))
    assert mem.out_of_order == 2 and len(mem) == 3


def test_the_test_before_the_projection_refuses_only_what_the_projection_would() -> None:
    """projects_fully with its quick bearing test and without it agree on 20,000 random
    cylinders and frames (ranges 0.2-13 m, radii 0.05-0.6 m, heights 0.2-1.8 m, bottoms
    +-0.5 m, tilts -0.3..0.3 rad); the quick test decides more than half of them alone."""
    mem = ImageMemory()
    rng = np.random.default_rng(1)
    aside = 0
    for _ in range(20000):
        pose = (rng.uniform(-5, 5), rng.uniform(-5, 5), rng.uniform(-3.2, 3.2))
        frame = RememberedFrame(0.0, rng.uniform(-2.6, 2.6), rng.uniform(-0.3, 0.3), pose)
        d, b = rng.uniform(0.2, 13.0), rng.uniform(-math.pi, math.pi)
        cand = Candidate(
            (pose[0] + d * math.cos(b), pose[1] + d * math.sin(b)),
            rng.uniform(0.05, 0.6),
            rng.uniform(0.2, 1.8),
            rng.uniform(-0.5, 0.5),
        )
        quick = mem._clearly_aside(frame, cand)
        aside += quick
        got = mem.projects_fully(frame, cand)
        mem._clearly_aside = lambda *_: False  # type: ignore[method-assign]
        assert mem.projects_fully(frame, cand) == got
        assert not (quick and got)
        del mem._clearly_aside
    assert aside > 10000
