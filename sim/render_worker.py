"""A camera-rendering worker process: a copy of the scene in another process (issue 14: speed).

Rendering a robot's camera image (PyBullet's TinyRenderer, CPU) is the simulator's largest cost
and PyBullet holds the GIL while it renders, so a thread cannot overlap it with the robots' and
the GCS's work; a process can. :class:`RenderWorkerProcess` starts ``python -m
sim.render_worker`` (:class:`sim.scene_worker.SceneWorkerProcess`, like :mod:`sim.ray_worker`),
sends it the world once, then for each image the scene state to draw (robot transforms, people,
detonated objects) and the camera; the worker renders every job as soon as it arrives and sends
the images back in the order they were asked for. Same geometry, same engine, same state: the
pixels are exactly those the parent's scene would give
(:meth:`sim.simulator.Simulator.render_image`), so runs stay repeatable; the simulator checks
at collection time that the state it sent is still the one it would have rendered with and
renders in process otherwise.

A job the worker drew among its last 16 (the same frame asked for twice, ~2 % of the small
world's jobs: a colour test and a tag search of one frame at one size) is answered with the
pixels it drew, undrawn (issue 14, session 14).
"""

from __future__ import annotations

import queue
import threading
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from sim.scene import RobotGeometry, Scene
from sim.scene_worker import SceneWorkerProcess, child_connections, serve_setup
from sim.world_generator import World

__all__ = ["RenderJob", "RenderWorkerProcess"]


@dataclass(frozen=True)
class RenderJob:
    """One image: the scene state (robots ``(N, 4, 4)`` drawn at ``robots``, people at
    ``human_xy`` / ``human_z`` unless hidden, objects ``hidden_oois`` gone) and the camera
    (the keyword arguments of :meth:`sim.scene.Scene.render`)."""

    robots: np.ndarray
    human_xy: np.ndarray
    human_z: np.ndarray
    human_hidden: np.ndarray
    hidden_oois: frozenset[int]
    eye_m: np.ndarray
    forward: np.ndarray
    up: np.ndarray
    width_px: int
    height_px: int
    fy_px: float
    near_m: float
    far_m: float


class RenderWorkerProcess(SceneWorkerProcess):
    """One worker process holding a scene of ``world``: :meth:`submit` jobs, then
    :meth:`result` in the same order."""

    def __init__(self, world: World, geometry: RobotGeometry, *, timeout_s: float = 60.0) -> None:
        self._lock = threading.Lock()  # commands may arrive on any thread
        self.pending = 0
        super().__init__("sim.render_worker", "render worker", world, geometry, timeout_s=timeout_s)

    def submit(self, job: RenderJob) -> None:
        """Queue ``job`` (rendered at once, in the worker)."""
        with self._lock:
            self._tx.send(job)
            self.pending += 1

    def result(self, timeout_s: float = 60.0) -> np.ndarray:
        """The RGB image ``(H, W, 3)`` of the oldest job not yet collected (RuntimeError if
        the worker failed on it or went away)."""
        with self._lock:
            if self.pending <= 0:
                raise RuntimeError("render worker: no job pending")
            self.pending -= 1
        if not self._rx.poll(timeout_s):
            raise RuntimeError(f"render worker: no image within {timeout_s} s")
        out = self._rx.recv()
        if isinstance(out, str):
            raise RuntimeError(f"render worker: {out}")
        return out  # type: ignore[no-any-return]


def _job_key(job: RenderJob, hidden_oois: frozenset[int]) -> tuple[object, ...]:
    """Everything an image depends on: the job's state and camera, and the objects the scene
    has hidden (bytes, shapes and dtypes of the arrays; the numbers as they are)."""
    arrays = [job.robots, job.human_xy, job.human_z, job.human_hidden, job.eye_m, job.forward]
    arrays.append(job.up)
    out: list[object] = [tuple(sorted(hidden_oois))]
    for a in arrays:
        arr = np.asarray(a)
        out += [arr.dtype.str, arr.shape, arr.tobytes()]
    out += [job.width_px, job.height_px, job.fy_px, job.near_m, job.far_m]
    return tuple(out)


class _Recent:
    """The last ``size`` images by :func:`_job_key`: a job drawn again (the same frame asked
    for twice: ~2 % of the small world's jobs) is answered with the same pixels, undrawn."""

    def __init__(self, size: int = 16) -> None:
        self.size = size
        self.images: dict[tuple[object, ...], np.ndarray] = {}
        self.hits = 0

    def draw(self, scene: Scene, job: RenderJob) -> np.ndarray:
        for ooi_id in job.hidden_oois:
            if ooi_id not in scene.hidden_oois:
                scene.hide_ooi(ooi_id)
        key = _job_key(job, scene.hidden_oois)
        rgb = self.images.get(key)
        if rgb is not None:
            self.hits += 1
            return rgb
        rgb = _draw(scene, job)
        self.images[key] = rgb
        if len(self.images) > self.size:
            del self.images[next(iter(self.images))]
        return rgb


def _draw(scene: Scene, job: RenderJob) -> np.ndarray:
    """What :meth:`sim.simulator.Simulator.render_image` draws for a recorded frame."""
    for ooi_id in job.hidden_oois:
        if ooi_id not in scene.hidden_oois:
            scene.hide_ooi(ooi_id)
    scene.set_robot_poses(job.robots)
    if len(job.human_xy):
        scene.set_human_positions(job.human_xy, job.human_z, hidden=job.human_hidden)
    return scene.render(
        eye_m=job.eye_m,
        forward=job.forward,
        up=job.up,
        width_px=job.width_px,
        height_px=job.height_px,
        fy_px=job.fy_px,
        near_m=job.near_m,
        far_m=job.far_m,
    )


def _serve(rx: Connection, tx: Connection) -> None:
    scene = serve_setup(rx, tx)
    if scene is None:
        return
    # images go back on their own thread: the next job renders while the parent has not yet
    # read the last image (a pipe holds far less than one image)
    out: queue.SimpleQueue[object] = queue.SimpleQueue()

    def send() -> None:
        while True:
            item = out.get()
            if item is None:
                return
            try:
                tx.send(item)
            except OSError:
                return

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    recent = _Recent()
    try:
        while True:
            job = rx.recv()
            if job is None:
                break
            try:
                out.put(recent.draw(scene, job))
            except Exception as err:  # noqa: BLE001 - reported to the parent
                out.put(repr(err))
    except EOFError:
        pass
    finally:
        out.put(None)
        sender.join(5.0)
        scene.close()


if __name__ == "__main__":
    import signal

    # ^C reaches the whole process group: the parent decides when this worker ends (it
    # closes the pipe), so no second traceback and no image lost mid-run
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _serve(*child_connections())
