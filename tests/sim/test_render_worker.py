"""The render worker process draws exactly the images the simulator draws in process: the
same recorded frames, people where they were, detonated objects gone (issue 14: speed)."""

from __future__ import annotations

import numpy as np

from protocol.sensors import CameraImage, ImageRequest, VelocityCommand
from sim.simulator import Simulator, SimulatorConfig
from sim.world_generator import Human, Ooi
from tests.sim.simworlds import box, make_world


def _world():
    ooi = Ooi(0, "static_ooi", (15.0, 10.0), 0.25, 0.8, (1, 0.3, 0, 1))
    walker = Human(0, "civilian", ((13.0, 13.0), (13.0, 7.0)), 0.5, 0.25, 1.7, (0.1, 0.2, 0.9, 1))
    robots = [(10.0, 10.0, 0.0, "sensor"), (10.0, 12.0, 0.0, "sensor")]
    wall = box("wall", 18.0, 5.0, 18.2, 15.0, 2.5)
    return make_world(oois=[ooi], humans=[walker], robots=robots, solids=[wall])


def _images(render_workers: int, kill_at: int = -1) -> tuple[list[CameraImage], int, int]:
    """Robot 0 drives into the static object (it detonates at 2.5 m, about 2.5 s in) while
    both robots ask, every step, for images of now, of 0.5 s and of 3 s ago, some at 640x480;
    the worker process is killed before step ``kill_at`` (never if negative)."""
    cfg = SimulatorConfig(render_workers=render_workers)
    out: list[CameraImage] = []
    with Simulator(_world(), config=cfg) as sim:
        sim.driver(0).send(VelocityCommand(time_s=0.0, linear_m_s=1.0, angular_rad_s=0.4))
        rid = 0
        for step in range(70):
            if step == kill_at:
                worker = sim._render_worker
                assert worker is not None
                worker._proc.kill()
                worker._proc.wait(10.0)
            for robot in (0, 1):
                for back_s in (0.0, 0.5, 3.0):
                    rid += 1
                    size = (640, 480) if rid % 5 == 0 else (320, 240)
                    t = max(0.0, sim.time_s - back_s)
                    sim.driver(robot).send(ImageRequest(rid, t, *size))
            sim.step()
            for robot in (0, 1):
                out += [f for f in sim.driver(robot).poll(0.0) if isinstance(f, CameraImage)]
        assert [e.kind for e in sim.events][:1] == ["detonation"]
        return out, sim.worker_renders, rid


def test_the_render_worker_draws_the_images_the_simulator_draws() -> None:
    here, none, asked = _images(0)
    there, used, _ = _images(1)
    assert none == 0
    # most images come from the worker; those of frames drawn before the detonation and
    # delivered after it (and of robot 0 once destroyed) are not
    assert 0.5 * asked < used < asked
    assert len(here) == len(there) > 0
    for a, b in zip(here, there, strict=True):
        assert (a.request_id, a.time_s, a.camera_pan_rad) == (
            b.request_id,
            b.time_s,
            b.camera_pan_rad,
        )
        assert (a.fx_px, a.fy_px, a.cx_px, a.cy_px) == (b.fx_px, b.fy_px, b.cx_px, b.cy_px)
        assert np.array_equal(a.rgb, b.rgb), a.request_id


def test_a_render_worker_that_dies_leaves_the_simulator_drawing_the_same_images() -> None:
    here, _, _ = _images(0)
    there, used, asked = _images(1, kill_at=10)
    assert 0 < used < 0.5 * asked  # the worker drew the first steps' images, then none
    assert len(here) == len(there)
    for a, b in zip(here, there, strict=True):
        assert a.request_id == b.request_id
        assert np.array_equal(a.rgb, b.rgb), a.request_id


def test_a_job_drawn_again_gets_the_same_pixels_undrawn() -> None:
    """The worker answers a repeated job from its recent images (speed), with the pixels a
    fresh drawing gives; a job that differs in the objects gone is drawn."""
    from sim.render_worker import RenderJob, _draw, _Recent
    from sim.scene import Scene

    world = _world()
    cfg = SimulatorConfig(render_workers=0)
    with Simulator(world, config=cfg) as sim:
        job, _ = sim._render_job(0, ImageRequest(1, 0.0, 320, 240))
        turned, _ = sim._render_job(1, ImageRequest(2, 0.0, 320, 240))
    fresh = Scene(world, analytic_ground=True, cull=True)
    kept = Scene(world, analytic_ground=True, cull=True)
    recent = _Recent(size=1)
    try:
        first = recent.draw(kept, job)
        again = recent.draw(kept, job)
        assert recent.hits == 1 and np.array_equal(again, _draw(fresh, job))
        assert np.array_equal(first, again)
        other = recent.draw(kept, turned)  # evicts the first (size 1)
        assert recent.hits == 1 and np.array_equal(other, _draw(fresh, turned))
        gone = RenderJob(**{**vars(job), "hidden_oois": frozenset({0})})
        without = recent.draw(kept, gone)
        assert recent.hits == 1 and np.array_equal(without, _draw(fresh, gone))
        assert not np.array_equal(without, first)  # the object was in view
    finally:
        fresh.close()
        kept.close()
