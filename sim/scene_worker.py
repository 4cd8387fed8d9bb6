"""A worker process with its own copy of the scene: how the simulator's ray-casting and
camera-rendering workers (:mod:`sim.ray_worker`, :mod:`sim.render_worker`) start, meet their
parent and end (issues 3 and 14: speed).

:class:`SceneWorkerProcess` starts ``python -m MODULE`` (a plain subprocess, so scripts need
no ``__main__`` guard) with two pipes, sends it the world and the robots' geometry once and
waits for ``"ready"`` (or the error the child reports). :func:`serve_setup` is the child's
half: the scene built from what the parent sent, or None after reporting why it could not be.
"""

from __future__ import annotations

import os
import subprocess
import sys
from multiprocessing.connection import Connection

from sim.scene import RobotGeometry, Scene
from sim.world_generator import World

__all__ = ["SceneWorkerProcess", "child_connections", "serve_setup"]


class SceneWorkerProcess:
    """``python -m module`` holding a scene of ``world``; ``what`` names it in errors
    (RuntimeError when it does not start within ``timeout_s`` or reports a failure)."""

    def __init__(
        self, module: str, what: str, world: World, geometry: RobotGeometry, *, timeout_s: float
    ) -> None:
        to_child_r, to_child_w = os.pipe()
        from_child_r, from_child_w = os.pipe()
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", module, str(to_child_r), str(from_child_w)],
            pass_fds=(to_child_r, from_child_w),
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
        )
        os.close(to_child_r)
        os.close(from_child_w)
        self._tx = Connection(to_child_w, readable=False)
        self._rx = Connection(from_child_r, writable=False)
        self._tx.send((world, geometry))
        if not self._rx.poll(timeout_s):
            self.close()
            raise RuntimeError(f"{what} did not start within {timeout_s} s")
        ready = self._rx.recv()
        if ready != "ready":
            self.close()
            raise RuntimeError(f"{what} failed to start: {ready}")

    def close(self) -> None:
        """Ask the worker to end and wait for it (killed after 5 s). Results asked for and
        never collected: closing our end first gives the worker's sender a broken pipe
        instead of a wait for a reader."""
        try:
            self._tx.send(None)
        except OSError:
            pass
        self._rx.close()
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(5.0)
        self._tx.close()


def child_connections() -> tuple[Connection, Connection]:
    """The child's ends of the pipes its parent passed on the command line: (rx, tx)."""
    return (
        Connection(int(sys.argv[1]), writable=False),
        Connection(int(sys.argv[2]), readable=False),
    )


def serve_setup(rx: Connection, tx: Connection) -> Scene | None:
    """The child's scene of the world its parent sent ("ready" told), or None (the error
    told instead)."""
    world, geometry = rx.recv()
    try:
        # drawn as the simulator's own scene draws (the same pixels either way)
        scene = Scene(world, geometry=geometry, ray_threads=1, analytic_ground=True, cull=True)
    except Exception as err:  # noqa: BLE001 - reported to the parent
        tx.send(repr(err))
        return None
    tx.send("ready")
    return scene
