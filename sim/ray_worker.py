"""Ray-casting worker processes: a copy of the scene in another process (issue 3: speed).

PyBullet holds the GIL and spends most of each ray's time in per-ray bookkeeping, so more
threads do not make ``rayTestBatch`` faster; a second process with its own copy of the
scene does. :class:`RayWorkerProcess` starts ``python -m sim.ray_worker`` (a plain
subprocess, so scripts need no ``__main__`` guard), sends it the world once, then for each
batch the dynamic state (robots, people, detonated objects; only when it changed) and its
share of the rays; the worker answers with body ids and hit fractions. Same geometry, same
engine: the results are exactly those of the parent's scene, so runs stay repeatable.
"""

from __future__ import annotations

import os
import subprocess
import sys
from multiprocessing.connection import Connection

import numpy as np

from sim.scene import DynamicState, RobotGeometry, Scene
from sim.world_generator import World

__all__ = ["RayWorkerProcess"]


class RayWorkerProcess:
    """One worker process holding a scene of ``world``."""

    def __init__(self, world: World, geometry: RobotGeometry, *, timeout_s: float = 60.0) -> None:
        to_child_r, to_child_w = os.pipe()
        from_child_r, from_child_w = os.pipe()
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "sim.ray_worker", str(to_child_r), str(from_child_w)],
            pass_fds=(to_child_r, from_child_w),
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
        )
        os.close(to_child_r)
        os.close(from_child_w)
        self._tx = Connection(to_child_w, readable=False)
        self._rx = Connection(from_child_r, writable=False)
        self._sent_version = -1
        self._tx.send((world, geometry))
        if not self._rx.poll(timeout_s):
            self.close()
            raise RuntimeError(f"ray worker did not start within {timeout_s} s")
        ready = self._rx.recv()
        if ready != "ready":
            self.close()
            raise RuntimeError(f"ray worker failed to start: {ready}")

    def submit(self, version: int, state: DynamicState, f: np.ndarray, end: np.ndarray) -> None:
        """Send rays (and the dynamic state, if ``version`` is new) to cast."""
        payload = None if version == self._sent_version else state
        self._sent_version = version
        self._tx.send((payload, f, end))

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        """Body ids and hit fractions of the last submitted rays."""
        out = self._rx.recv()
        if isinstance(out, str):
            raise RuntimeError(f"ray worker: {out}")
        return out  # type: ignore[no-any-return]

    def close(self) -> None:
        try:
            self._tx.send(None)
        except OSError:
            pass
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait(5.0)
        self._tx.close()
        self._rx.close()


def _serve(rx: Connection, tx: Connection) -> None:
    world, geometry = rx.recv()
    try:
        scene = Scene(world, geometry=geometry, ray_threads=1)
    except Exception as err:  # noqa: BLE001 - reported to the parent
        tx.send(repr(err))
        return
    tx.send("ready")
    try:
        while True:
            msg = rx.recv()
            if msg is None:
                break
            state, f, end = msg
            try:
                if state is not None:
                    scene.apply_state(state)
                tx.send(scene.cast_raw(f, end))
            except Exception as err:  # noqa: BLE001 - reported to the parent
                tx.send(repr(err))
    except EOFError:
        pass
    finally:
        scene.close()


if __name__ == "__main__":
    _serve(
        Connection(int(sys.argv[1]), writable=False), Connection(int(sys.argv[2]), readable=False)
    )
