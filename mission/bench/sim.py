"""``magic bench sim``: simulator speed and memory (issue 3).

Metrics:

- ``rtf_14``: real-time factor (mission seconds per wall second) of the simulator alone on
  ``configs/world/magic_phase.yaml`` with its 14 robots and default sensors, every robot
  driving (seeded random commands, changed every 2.5 s), median over chunks of the run;
- ``rtf_64``: the same with 64 robots (48 sensor robots, 16 disruptors), in a child process;
- ``lidar_rays_per_s``: LIDAR rays cast per second through :meth:`sim.scene.Scene.ray_cast`
  (batches of 16000 real sweep rays from the 14 robots, median);
- ``camera_ms_320x240``: median milliseconds to render one 320x240 camera image on request;
- ``peak_rss_mb_64``: peak resident memory (MB) of the child process that ran ``rtf_64`` plus
  that of its ray-casting worker process (:mod:`sim.ray_worker`; one by default for 64 robots).

Frames are produced and queued as for real nodes (bounded queues nobody reads).
"""

from __future__ import annotations

import multiprocessing as mp
import resource
import signal
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import msgspec
import numpy as np

from mission.bench import median_time_s
from mission.config import CONFIGS_DIR

__all__ = ["run"]

WORLD = CONFIGS_DIR / "world" / "magic_phase.yaml"


def _drive(sim, rng: np.random.Generator) -> None:  # type: ignore[no-untyped-def]
    from protocol.sensors import VelocityCommand

    for rid in sim.robot_ids:
        sim.driver(rid).send(
            VelocityCommand(
                time_s=sim.time_s,
                linear_m_s=float(rng.uniform(0.3, 1.0)),
                angular_rad_s=float(rng.uniform(-0.5, 0.5)),
            )
        )


def _rtf(robots: int | None, sim_s: float, chunk_s: float) -> tuple[float, float]:
    """Median real-time factor over chunks; returns (rtf, peak RSS MB of this process)."""
    from sim.simulator import Simulator, load_world_config
    from sim.world_generator import RobotsConfig

    wc = load_world_config(WORLD)
    if robots is not None:
        wc = msgspec.structs.replace(
            wc, robots=RobotsConfig(sensors=robots - robots // 4, disruptors=robots // 4)
        )
    rng = np.random.default_rng(3)
    with Simulator(wc) as sim:
        _drive(sim, rng)
        sim.run_for(1.0)  # warm-up
        rtfs = []
        steps = int(round(chunk_s / sim.config.step_s))
        for _ in range(int(round(sim_s / chunk_s))):
            if int(sim.time_s / 2.5) != int((sim.time_s + chunk_s) / 2.5):
                _drive(sim, rng)
            t0 = time.perf_counter()
            for _ in range(steps):
                sim.step()
            rtfs.append(chunk_s / (time.perf_counter() - t0))
    # this process's peak plus its ray workers' (they have exited: RUSAGE_CHILDREN has them)
    rss_kb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rss_kb += resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return statistics.median(rtfs), rss_kb / 1024


def _child(robots: int, sim_s: float, chunk_s: float, conn) -> None:  # type: ignore[no-untyped-def]
    # ^C at a terminal reaches the whole process group: the parent stops this child (no
    # second traceback from here). The parent's terminate() (SIGTERM) exits through
    # SystemExit so that the scene's temporary directory is removed, not left in /tmp.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(128 + signal.SIGTERM))
    try:
        conn.send(("ok", _rtf(robots, sim_s, chunk_s)))
    except Exception as err:  # noqa: BLE001 - reported to the parent
        conn.send(("error", repr(err)))
    finally:
        conn.close()


def _rtf_in_child(robots: int, sim_s: float, chunk_s: float) -> tuple[float, float]:
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(robots, sim_s, chunk_s, child))
    proc.start()
    child.close()
    try:
        status, value = parent.recv()
    except BaseException:  # a stop (^C, SIGTERM) or a broken pipe: the child goes too
        proc.terminate()
        raise
    finally:
        proc.join(60)
    if status != "ok":
        raise RuntimeError(f"64-robot run failed: {value}")
    return value  # type: ignore[no-any-return]


def _rays_and_camera(repeats: int) -> tuple[float, float]:
    from protocol.sensors import ImageRequest
    from sim.simulator import Simulator, load_world_config

    with Simulator(load_world_config(WORLD)) as sim:
        _drive(sim, np.random.default_rng(4))
        sim.run_for(3.0)
        mats = sim.bodies.world_from_base_matrices()
        lines = sim.config.lidar.lines_per_sweep
        due = [(r, 0, line) for r in range(len(sim.robot_ids)) for line in range(lines)]
        origin, end, _ = sim.lidars.rays(due, mats)
        origin, end = origin[:16000], end[:16000]
        t = median_time_s(lambda: sim.scene.ray_cast(origin, end), repeats=repeats)
        rays_per_s = len(origin) / t
        req = ImageRequest(request_id=1, time_s=sim.time_s - 1.0, width_px=320, height_px=240)
        cam_s = median_time_s(lambda: sim.render_image(0, req), repeats=repeats)
    return rays_per_s, cam_s * 1000.0


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    sim_s, chunk_s = (10.0, 2.0) if quick else (40.0, 4.0)
    progress("14 robots, magic_phase: real-time factor")
    rtf_14, _ = _rtf(None, sim_s, chunk_s)
    progress(f"rtf_14 = {rtf_14:.2f}; 64 robots in a child process")
    rtf_64, rss_64 = _rtf_in_child(64, sim_s, chunk_s)
    progress(f"rtf_64 = {rtf_64:.2f}; LIDAR rays and camera")
    rays, cam_ms = _rays_and_camera(5 if quick else 15)
    return {
        "rtf_14": rtf_14,
        "rtf_64": rtf_64,
        "lidar_rays_per_s": rays,
        "camera_ms_320x240": cam_ms,
        "peak_rss_mb_64": rss_64,
    }


if __name__ == "__main__":  # pragma: no cover - manual runs
    print(run(quick=True, progress=print), Path(__file__).name)
