"""Ray-casting worker processes: a copy of the scene in another process (issue 3: speed).

PyBullet holds the GIL and spends most of each ray's time in per-ray bookkeeping, so more
threads do not make ``rayTestBatch`` faster; a second process with its own copy of the
scene does. :class:`RayWorkerProcess` starts ``python -m sim.ray_worker``
(:class:`sim.scene_worker.SceneWorkerProcess`), sends it the world once, then for each
batch the dynamic state (robots, people, detonated objects; only when it changed) and its
share of the rays; the worker answers with body ids and hit fractions. Same geometry, same
engine: the results are exactly those of the parent's scene, so runs stay repeatable.
"""

from __future__ import annotations

from multiprocessing.connection import Connection

import numpy as np

from sim.scene import DynamicState, RobotGeometry
from sim.scene_worker import SceneWorkerProcess, child_connections, serve_setup
from sim.world_generator import World

__all__ = ["RayWorkerProcess"]


class RayWorkerProcess(SceneWorkerProcess):
    """One worker process holding a scene of ``world``."""

    def __init__(self, world: World, geometry: RobotGeometry, *, timeout_s: float = 60.0) -> None:
        self._sent_version = -1
        super().__init__("sim.ray_worker", "ray worker", world, geometry, timeout_s=timeout_s)

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


def _serve(rx: Connection, tx: Connection) -> None:
    scene = serve_setup(rx, tx)
    if scene is None:
        return
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
    _serve(*child_connections())
