"""``magic bench scale``: a hundred robots on one radio, over worker processes, with one GCS
(issue 16).

Metrics:

* the radio (:mod:`mission.bench.radio_scale`'s measurement: 100 synthetic robots through the
  real link code in lockstep): ``radio_use_frac_100`` (<= 0.8), ``downlink_bps_per_robot_100``
  (<= 100), ``uplink_bytes_per_node``;
* the whole team: ``rtf_full_64`` (>= 1) and ``rtf_full_100`` (>= 0.5): mission seconds per
  wall second of the simulator + 64 (100) robot nodes + the GCS, the nodes in worker
  processes (:class:`~mission.lockstep.TeamOverProcesses`, one per core), the simulator and
  the GCS in this one, after one warm-up mission-second; ``cpu_s_per_robot_mission_s``: CPU
  seconds the worker processes spent per robot per mission second (100 robots; less
  sensitive than the real-time factor to the machine's other load, which is reported as
  ``load_avg_1m``); ``cpu_s_sim_gcs_per_mission_s``: this process and its other children
  per mission second, split into ``cpu_s_main_per_mission_s`` (the simulator's physics and
  sensors, the lockstep exchange, the GCS) and ``cpu_s_sim_helpers_per_mission_s`` (the
  simulator's ray-casting and rendering worker processes);
* the GCS at 100 robots, in a child process: synthetic traffic of 100 robots (5 robots per
  60 m tile of buildings, walls and cars, tiles 200 m apart; a pose node every metre, 15 deg
  or 30 s with its odometry noise, a scan grid of the true surroundings coded as on board,
  start hints as the deployment plan gives) fed to a :class:`~gcs.ground_station.GroundStation`
  at mission pace: the station works as one thread in real time, a step every second with
  its default loop-closing budget, each message handled when it has arrived and the station
  is free (between steps: a step starts on its tick unless handling or the last step still
  holds the station; the step is given its tick's mission time, as ``magic run``'s lockstep
  gives it), frames every ``FRAMES_PERIOD_S`` (1 s; the radio measurement broadcasts them as
  often). ``gcs_node_to_frame_s_p95_100`` (<= 2.0): from a node's arrival
  to the end of the first step that sends a ``map_from_odom`` of its robot computed with it
  (the step's wall time counted; when the station falls behind, the wait for it too);
  ``_p50``; ``gcs_node_to_estimate_s_p95_100`` to the end of the first step whose
  optimization included it (the difference: the wait for a step that sends frames);
  ``gcs_nodes_100`` nodes fed; ``gcs_behind_s_100`` the most a step started after its time
  (the station behind the mission clock); ``gcs_step_s_p95_100``;
  ``gcs_handle_s_per_node_100``, ``gcs_{close,optimize,frames}_s_per_step_100`` where the
  time goes. The station's work is timed in CPU seconds of its process (as on a core of its
  own: the machine's other load does not inflate it; :func:`gcs_latency` with
  ``cpu_paced=False`` paces it by the wall clock instead), and its loop-closing budget (wall
  seconds) is stretched by the recent wall-over-CPU ratio of its steps (at load 25 on two
  cores, 0.2 wall-s held 0.04 CPU-s: candidate generation ate it and no match ever ran);
  ``gcs_closures_100`` closures accepted;
  ``gcs_peak_rss_mb_100`` the child's peak resident memory. The last steps run under
  cProfile: the functions taking the most time go to the progress lines and to
  ``gcs_profile.txt`` in :func:`mission.bench.output_dir` ``("scale")``.

The GCS's child runs while the radio and the 64-robot team's set-up and warm-up run here
(bytes and CPU-paced steps do not depend on the load; the team's measured stretch waits for
the child to end), which takes the quick run's wall time down by about their length.

``--quick``: the radio over 60 mission-s, the teams on ``magic_phase`` (its 14 robots' site
crowded to 64 and 100) for 0.5 mission-s after 1 s, the GCS over 60 mission-s of traffic.
The 64-robot team then runs on and is measured again over 2.5-3.75 mission-s
(:data:`STEADY_AFTER_S`, :data:`STEADY_S`: one whole sweep period once the first sweep's
images are answered): ``rtf_full_64`` and ``cpu_s_per_robot_mission_s_64`` are that steady
window's, the rate the crowd keeps up; the crowd's first half second stays beside them as
``rtf_full_64_crowd`` / ``cpu_s_per_robot_mission_s_64_crowd`` (``rtf_full_100`` and
``cpu_s_per_robot_mission_s`` remain the 100-robot team's crowd window). Measured (session
15, at 22fda16, load 13): rtf_full_64 0.064 over the steady window against 0.028 over the
crowd's; a robot node 0.072 CPU-s a mission-s there (0.116 in the crowd), the simulator and
GCS 4.3 (7.4): ~8.9 CPU-s a mission-s in all, so at most ~0.22 on two free cores; the quick
bench 3.4 min wall (the steady stretch ~35 s of it).
The window holds every robot's first LIDAR sweep (its last line at 1.2-1.25 s) and what it
sets off: the sweep's terrain and perception on board, the colour-test, tag and fine images
it asks for, rendered and searched (before session 11 the window was 0.25-0.75 s, the team's
start before any sweep: 1.10 at 64 robots where mission-s 1-2 ran at 0.06). It is the crowd's
busiest half second (64 robots in one staging area, each asking about every teammate its
first sweep takes for a cylinder); the full run's 10 s measure the next ones. Measured in
this window at 64 robots (session 11, load 14-20, CPU seconds per mission second): the robot
workers ~8.7 (on board: tag fits and searches ~3, the sweep pipeline ~2.5), the simulator's
render and ray workers ~7.1 (~380 images a mission-second: colour tests of LIDAR cylinders,
fine tag images, the periodic tag images; ~20 ms each), this process ~1.2: about 17 CPU-s,
so at most ~0.12 on two free cores.
Full: 600 mission-s of radio, the teams on ``magic_team100`` for 10 mission-s after
1 s, the GCS over 300 mission-s (about 15,000 nodes). On the shared 2-core machine the teams
alone take minutes (the simulator's camera renders dominate: see the README's scale rows).
"""

from __future__ import annotations

import cProfile
import io
import math
import multiprocessing as mp
import os
import pstats
import resource
import time
from collections.abc import Callable, Iterator
from typing import Any

import msgspec
import numpy as np

from mission.bench import output_dir

__all__ = ["full_team", "gcs_latency", "run", "synthetic_team_traffic"]

ROBOTS = 100
TILE_ROBOTS = 5
TILE_M = 60.0
TILE_SPACING_M = 200.0
STEP_S = 0.25
RES_M = 0.1
#: How often the GCS sends hazards and every robot's frame, in both measurements (the radio's
#: broadcast and the station's ``frames_period_s``): 1 s keeps the downlink within its budget
#: (74 bps a robot at 100 robots, 60 bps at 2 s) and a node's frame within 2 s of its arrival.
FRAMES_PERIOD_S = 1.0
#: ``--quick``'s steady window for the 64-robot team: after the crowd's window (1.0-1.5 s) the
#: team runs on to 2.5 s and is measured over 2.5-3.75 s, one whole LIDAR sweep period (every
#: robot's second sweep ends at 2.45-2.5 s, its images answered in the window; its third at
#: 3.7-3.75 s): the work a sweep sets off once teammates' tags are known, over a sweep.
STEADY_AFTER_S = 1.0
STEADY_S = 1.25


# ---- the whole team ------------------------------------------------------------------------


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system, every thread) process ``pid`` has used; 0 if gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    out = []
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat", "rb") as f:
                ppid = int(f.read().rsplit(b")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if ppid == pid:
            out.append(int(entry))
    return out


def full_team(
    robots: int,
    *,
    world: str,
    mission_s: float,
    warmup_s: float = 1.0,
    seed: int = 0,
    before_measure: Callable[[], object] | None = None,
    steady_after_s: float = 0.0,
    steady_s: float = 0.0,
) -> dict[str, float]:
    """The simulator + ``robots`` robot nodes in worker processes + the GCS on ``world``
    (its team resized, 7 sensor robots to 3 disruptors) for ``warmup_s + mission_s``:
    real-time factor and CPU over the last ``mission_s``. ``before_measure``: called after
    the warm-up, before the measured stretch (e.g. to wait for other work to end).
    ``steady_s`` > 0: the team then runs ``steady_after_s`` more, unmeasured, and
    ``steady_s`` measured again: the same keys with ``_steady`` appended (a window of whole
    LIDAR sweep periods after the crowd's first sweep: the rate the team keeps up)."""
    from mission.assembly import assemble
    from mission.lockstep import TeamOverProcesses, seed_streams
    from protocol.config import CONFIGS_DIR, config_path, load_config
    from protocol.radio import RadioConfig
    from sim.simulator import load_world_config
    from sim.world_generator import RobotsConfig

    wc = load_world_config(config_path(world, "world"))
    sensors = int(round(robots * 0.7))
    wc = msgspec.structs.replace(
        wc, robots=RobotsConfig(sensors=sensors, disruptors=robots - sensors)
    )
    radio_path = CONFIGS_DIR / "radio" / "magic2010.yaml"
    t0 = time.perf_counter()
    with assemble(
        wc,
        seeds=seed_streams(seed),
        radio=load_config(radio_path, RadioConfig),
        radio_path=str(radio_path),
        robot_processes=True,
    ) as asm:
        setup_s = time.perf_counter() - t0
        sim = asm.sim
        team = asm.team
        assert isinstance(team, TeamOverProcesses)
        step_s = sim.config.step_s
        for _ in range(int(round(warmup_s / step_s))):
            asm.step()
        if before_measure is not None:
            before_measure()
        workers = team.worker_pids

        def measure(seconds: float) -> dict[str, float]:
            others = [p for p in _children(os.getpid()) if p not in workers]
            w0 = sum(_cpu_s(p) for p in workers)
            m0 = time.process_time()
            o0 = sum(_cpu_s(p) for p in others)
            t_start, wall0 = sim.time_s, time.perf_counter()
            for _ in range(int(round(seconds / step_s))):
                asm.step()
            wall = time.perf_counter() - wall0
            done_s = sim.time_s - t_start
            worker_cpu = sum(_cpu_s(p) for p in workers) - w0
            main_cpu = time.process_time() - m0
            other_cpu = sum(_cpu_s(p) for p in others) - o0
            return {
                "rtf": done_s / wall,
                "cpu_s_per_robot_mission_s": worker_cpu / robots / done_s,
                "cpu_s_sim_gcs_per_mission_s": (main_cpu + other_cpu) / done_s,
                "cpu_s_main_per_mission_s": main_cpu / done_s,
                "cpu_s_sim_helpers_per_mission_s": other_cpu / done_s,
            }

        out = measure(mission_s)
        if steady_s > 0:
            for _ in range(int(round(steady_after_s / step_s))):
                asm.step()
            out.update({f"{k}_steady": v for k, v in measure(steady_s).items()})
        nodes = len(asm.gcs.station.graph.nodes()) if asm.gcs is not None else 0
    out.update({"setup_s": setup_s, "workers": float(len(workers)), "gcs_nodes": float(nodes)})
    return out


# ---- the GCS at 100 robots -----------------------------------------------------------------


def synthetic_team_traffic(
    robots: int, duration_s: float, seed: int = 11
) -> tuple[list[tuple[float, int, Any]], dict[int, np.ndarray]]:
    """Uplink of ``robots`` robots over ``duration_s`` (module docstring), in arrival order
    ``(time_s, robot_id, message)``, and each robot's true start pose in the world."""
    from compression import encode_grid, origin_cells_of
    from gcs.loops.synthetic_scenes import random_world, scan_grid, scan_points
    from protocol.messages import PoseNode, TerrainGrid
    from protocol.se2 import compose, relative

    rng = np.random.default_rng(seed)
    tiles = math.ceil(robots / TILE_ROBOTS)
    side = math.ceil(math.sqrt(tiles))
    worlds = []
    for k in range(tiles):
        centre = np.array([(k % side) * TILE_SPACING_M, (k // side) * TILE_SPACING_M])
        segs = random_world(rng, size_m=TILE_M, buildings=8, walls=14, boxes=30)
        worlds.append((centre, segs + np.tile(centre, 2)))
    starts: dict[int, np.ndarray] = {}
    state = []
    for rid in range(robots):
        centre, segs = worlds[rid // TILE_ROBOTS]
        start = np.array([*(centre + rng.uniform(-4, 4, 2)), rng.uniform(-math.pi, math.pi)])
        starts[rid] = start
        state.append(
            {
                "true": start.copy(),
                "node_true": start.copy(),
                "odom": np.zeros(3),
                "index": 0,
                "last_s": 0.0,
                "speed": 0.8,
                "turn": 0.0,
                "change_s": 0.0,
                "segs": segs,
                "centre": centre,
                "rng": np.random.default_rng([seed, rid]),
            }
        )
    out: list[tuple[float, int, Any]] = []
    for t in np.arange(0.0, duration_s, STEP_S):
        t = float(t)
        for rid, s in enumerate(state):
            r = s["rng"]
            if t >= s["change_s"]:
                s["speed"] = float(r.uniform(0.4, 1.2)) if r.random() > 0.25 else 0.0
                s["turn"] = float(r.normal(0.0, 0.2))
                s["change_s"] = t + float(r.uniform(5.0, 20.0))
            x, y, th = s["true"]
            away = np.array([x, y]) - s["centre"]
            if np.hypot(*away) > TILE_M / 2 - 5:  # stay on the tile: head back to its centre
                th = math.atan2(-away[1], -away[0])
            th += s["turn"] * STEP_S
            d = s["speed"] * STEP_S
            s["true"] = np.array(
                [x + d * math.cos(th), y + d * math.sin(th), math.remainder(th, math.tau)]
            )
            delta_true = relative(s["node_true"], s["true"])
            moved = float(np.hypot(delta_true[0], delta_true[1]))
            turned = abs(float(delta_true[2]))
            if not (s["index"] == 0 or moved >= 1.0 or turned >= 0.26 or t - s["last_s"] >= 30.0):
                continue
            sxy = max(0.005, 0.03 * math.sqrt(moved))
            sth = max(0.002, 0.02 * math.sqrt(turned))
            cov = (sxy**2, 0.0, 0.0, sxy**2, 0.0, sth**2)
            if s["index"] == 0:
                delta = np.zeros(3)
            else:
                delta = delta_true + r.normal(0.0, [sxy, sxy, sth])
                s["odom"] = compose(s["odom"], delta)
            node = PoseNode(s["index"], t, tuple(s["odom"]), tuple(delta), cov)  # type: ignore[arg-type]
            pts = scan_points(
                s["segs"], s["true"], n_beams=360, max_range_m=10.0, noise_m=0.02, rng=r
            )
            grid, origin = scan_grid(pts, size_cells=200, resolution_m=RES_M)
            data = encode_grid(grid, "ctx4a", origin_cells=origin_cells_of(origin, RES_M))
            out.append((t, rid, node))
            out.append((t, rid, TerrainGrid(s["index"], RES_M, data)))
            s["node_true"] = s["true"].copy()
            s["index"] += 1
            s["last_s"] = t
    return out, starts


def _timed(obj: Any, name: str, acc: dict[str, float], clock: Callable[[], float]) -> None:
    """Wrap ``obj.name`` so that its time by ``clock`` adds up in ``acc[name]`` (the instance
    only)."""
    inner = getattr(obj, name)

    def wrapper(*args: Any, **kwargs: Any) -> Any:
        t0 = clock()
        try:
            return inner(*args, **kwargs)
        finally:
            acc[name] = acc.get(name, 0.0) + clock() - t0

    setattr(obj, name, wrapper)


def gcs_latency(
    robots: int,
    duration_s: float,
    *,
    period_s: float = 1.0,
    profile_steps: int = 10,
    cpu_paced: bool = True,
    frames_period_s: float | None = FRAMES_PERIOD_S,
) -> dict[str, Any]:
    """The GCS at ``robots`` robots' traffic (module docstring); returns the metrics and
    ``"profile"``: the top of a cProfile of the last ``profile_steps`` busy steps.
    ``cpu_paced``: the station's work is timed in this process's CPU seconds (what it would
    take on a core of its own: the figure does not swing with the machine's other load);
    else in wall seconds. ``frames_period_s``: the station's (default: its config's)."""
    clock = time.process_time if cpu_paced else time.perf_counter
    from gcs.ground_station import GroundStation, GroundStationConfig
    from protocol.messages import HazardUpdate, PoseNode
    from protocol.se2 import compose, relative

    t_gen = time.perf_counter()
    traffic, starts = synthetic_team_traffic(robots, duration_s)
    gen_s = time.perf_counter() - t_gen
    base = GroundStationConfig()
    ids = list(range(robots))
    cfg = msgspec.structs.replace(base, robots=tuple(ids))
    if frames_period_s is not None:
        cfg = msgspec.structs.replace(cfg, frames_period_s=frames_period_s)
    cfg = msgspec.structs.replace(cfg, graph=msgspec.structs.replace(cfg.graph, map_robot_id=0))
    station = GroundStation(cfg)
    rng = np.random.default_rng(3)
    for rid in ids[1:]:
        err = rng.normal(0.0, [0.3, 0.3, 0.05])
        station.add_start_hint(
            rid,
            map_from_odom=compose(relative(starts[0], starts[rid]), err),
            sigma_xy_m=0.3,
            sigma_yaw_rad=0.05,
        )
    phases: dict[str, float] = {}
    for name in ("_close_loops", "_optimize", "_downlink"):
        _timed(station, name, phases, clock)
    pending: dict[int, list[float]] = {}
    latencies: list[float] = []
    unsolved: list[float] = []  # arrivals of nodes no optimization has included yet
    solved: list[float] = []  # arrival to the end of the first step that optimized with it
    step_s: list[float] = []
    handle_s = 0.0
    nodes = 0
    idx = 0
    gcs_free_s = 0.0  # when the station's thread is next free, in mission (= wall) seconds
    behind_s = 0.0  # the most a step started after its time
    cpu_used = wall_used = 0.0  # recent steps' CPU and wall seconds (decaying sums)
    traffic_steps = int(math.ceil(duration_s / period_s))
    n_steps = traffic_steps + 5  # the last nodes' frames
    profiler = cProfile.Profile()
    profiled = range(traffic_steps - profile_steps + 1, traffic_steps + 1)  # busy ones
    k = 0
    while True:
        k += 1
        # on until every node fed was framed (a station that fell behind is waited for)
        if k > n_steps and idx >= len(traffic) and not any(pending.values()):
            break
        if k > 4 * n_steps:
            break
        profiling = k in profiled
        if k == profiled.start:
            profiler.enable()
        elif k == profiled.stop:
            profiler.disable()
        # messages are handled as they arrive whenever the station is free (between steps);
        # the step starts on its tick unless handling (or the last step) still holds it
        start = max(k * period_s, gcs_free_s)
        while idx < len(traffic) and traffic[idx][0] <= start:
            t_a, rid, msg = traffic[idx]
            idx += 1
            w0 = clock()
            station.handle(rid, msg, now_s=t_a)
            h = clock() - w0
            handle_s += h
            gcs_free_s = max(gcs_free_s, t_a) + h
            start = max(start, gcs_free_s)
            if isinstance(msg, PoseNode):
                nodes += 1
                pending.setdefault(rid, []).append(t_a)
                unsolved.append(t_a)
        behind_s = max(behind_s, start - k * period_s)
        optimizations = station.stats.optimizations
        # the loop closer's budget is wall seconds: on a loaded machine a wall second holds
        # a fraction of a CPU second, so a CPU-paced station gets its budget in CPU terms
        slowdown = max(1.0, wall_used / cpu_used) if cpu_paced and cpu_used > 0 else 1.0
        w0, c0, p0 = clock(), time.process_time(), time.perf_counter()
        # the step is the one of tick k, as the lockstep assembly steps the station (on
        # mission time k * period_s): its frames period counts in ticks, not in the moment
        # its work could start (that is when the work is timed from)
        out = station.step(now_s=k * period_s, budget_s=cfg.loop_budget_s * slowdown)
        w = clock() - w0
        cpu_used = 0.9 * cpu_used + (time.process_time() - c0)
        wall_used = 0.9 * wall_used + (time.perf_counter() - p0)
        step_s.append(w)
        gcs_free_s = start + w
        if station.stats.optimizations != optimizations:
            if not profiling:
                solved.extend(gcs_free_s - t_a for t_a in unsolved)
            unsolved = []
        for _rid, msg in out:
            if isinstance(msg, HazardUpdate):
                for f in msg.frames:
                    for t_a in pending.pop(f.robot_id, []):
                        if not profiling:
                            latencies.append(gcs_free_s - t_a)
                break
    profiler.disable()
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats("cumulative").print_stats(25)
    unresolved = sum(len(v) for v in pending.values())
    steps = max(len(step_s), 1)
    return {
        "gcs_node_to_frame_s_p95": float(np.percentile(latencies, 95)) if latencies else -1.0,
        "gcs_node_to_frame_s_p50": float(np.percentile(latencies, 50)) if latencies else -1.0,
        "gcs_node_to_estimate_s_p95": float(np.percentile(solved, 95)) if solved else -1.0,
        "gcs_nodes": float(nodes),
        "gcs_nodes_never_framed": float(unresolved),
        "gcs_behind_s": behind_s,
        "gcs_step_s_p95": float(np.percentile(step_s, 95)),
        "gcs_handle_s_per_node": handle_s / max(nodes, 1),
        "gcs_close_s_per_step": phases.get("_close_loops", 0.0) / steps,
        "gcs_optimize_s_per_step": phases.get("_optimize", 0.0) / steps,
        "gcs_frames_s_per_step": phases.get("_downlink", 0.0) / steps,
        "gcs_closures": float(station.loop_closer.stats.accepted),
        "gcs_traffic_gen_s": gen_s,
        "gcs_peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        "profile": text.getvalue(),
    }


def _child(fn_name: str, kwargs: dict[str, Any], conn: Any) -> None:
    try:
        conn.send(("ok", globals()[fn_name](**kwargs)))
    except BaseException as err:  # noqa: BLE001 - reported to the parent
        conn.send(("error", f"{type(err).__name__}: {err}"))


def _start_child(fn_name: str, **kwargs: Any) -> tuple[Any, Any]:
    """Start ``fn_name(**kwargs)`` in a fresh process (its own peak memory, no state shared);
    :func:`_finish_child` collects it."""
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe(duplex=False)
    proc = ctx.Process(target=_child, args=(fn_name, kwargs, child))
    proc.start()
    child.close()
    return proc, parent


def _finish_child(fn_name: str, proc: Any, parent: Any) -> dict[str, Any]:
    from mission.bench import BenchError

    try:
        status, value = parent.recv()
    except EOFError:
        proc.join()
        raise BenchError(f"{fn_name} child process died (exit status {proc.exitcode})") from None
    except BaseException:  # a stop (^C, SIGTERM): the child goes too
        proc.terminate()
        proc.join(10)
        raise
    proc.join()
    if status != "ok":
        raise BenchError(f"{fn_name} failed: {value}")
    return value  # type: ignore[no-any-return]


def _in_child(fn_name: str, **kwargs: Any) -> dict[str, Any]:
    """``fn_name(**kwargs)`` in a fresh process (its own peak memory, no state shared)."""
    proc, parent = _start_child(fn_name, **kwargs)
    return _finish_child(fn_name, proc, parent)


def _profile_lines(text: str, n: int = 8) -> Iterator[str]:
    """The top ``n`` rows of a cumulative-time pstats listing, one line each."""
    shown = 0
    for ln in text.splitlines():
        parts = ln.split(None, 5)
        if len(parts) != 6 or shown >= n:
            continue
        try:
            cumulative = float(parts[3])
        except ValueError:
            continue  # the header lines
        if "(" not in parts[5]:
            continue  # "List reduced from ..."
        shown += 1
        yield f"  {cumulative:7.2f} s cumulative  {parts[5]}"


def _report_gcs(
    gcs: dict[str, Any], metrics: dict[str, float], progress: Callable[[str], None]
) -> None:
    for key, value in gcs.items():
        if key != "profile":
            metrics[f"{key}_100"] = float(value)
    path = output_dir("scale") / "gcs_profile.txt"
    path.write_text(gcs["profile"], encoding="utf-8")
    progress(
        f"GCS: p95 node-to-frame {gcs['gcs_node_to_frame_s_p95']:.2f} s (to its estimate "
        f"{gcs['gcs_node_to_estimate_s_p95']:.2f} s), behind "
        f"{gcs['gcs_behind_s']:.1f} s, step p95 {gcs['gcs_step_s_p95']:.2f} s (close "
        f"{gcs['gcs_close_s_per_step']:.3f}, optimize {gcs['gcs_optimize_s_per_step']:.3f}, "
        f"frames {gcs['gcs_frames_s_per_step']:.3f} s a step; handle "
        f"{gcs['gcs_handle_s_per_node'] * 1e3:.1f} ms a node); profile of the last steps "
        f"({path}):"
    )
    for line in _profile_lines(gcs["profile"]):
        progress(line)


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    from mission.bench import radio_scale

    load = os.getloadavg()[0]
    metrics: dict[str, float] = {"load_avg_1m": load}
    # the GCS's child starts first: its traffic is generated while the radio runs here
    # (neither measurement depends on the other's load: bytes, and CPU-paced steps)
    gcs_s = 60.0 if quick else 300.0
    progress(f"GCS: {ROBOTS} robots' synthetic traffic, {gcs_s:.0f} mission-s, in a child")
    child = _start_child("gcs_latency", robots=ROBOTS, duration_s=gcs_s)
    radio_s = 60.0 if quick else 600.0
    progress(f"radio: {ROBOTS} robots, {radio_s:.0f} mission-s through the real link")
    try:
        radio = radio_scale.simulate(
            robots=ROBOTS, duration_s=radio_s, frames_period_s=FRAMES_PERIOD_S
        )
    except BaseException:
        child[0].terminate()
        child[0].join(10)
        raise
    for name in ("radio_use_frac_100", "downlink_bps_per_robot_100", "uplink_bytes_per_node"):
        metrics[name] = radio[name]
    world = "magic_phase" if quick else "magic_team100"
    team_s, warmup_s = (0.5, 1.0) if quick else (10.0, 1.0)
    # quick: the 64-robot team's rtf over a steady window too (see _teams)
    steady = (STEADY_AFTER_S, STEADY_S) if quick else (0.0, 0.0)
    gcs: dict[str, Any] = {}

    def gcs_done() -> dict[str, Any]:
        """The GCS's child ends before the team's measured stretch (the team's set-up and
        warm-up overlap it; nothing of them is measured)."""
        if not gcs:
            gcs.update(_finish_child("gcs_latency", *child))
        return gcs

    try:
        _teams(world, team_s, warmup_s, gcs_done, metrics, progress, steady=steady)
        gcs_done()
    finally:
        if not gcs:  # a failure before the GCS's result was read: it goes too
            child[0].terminate()
            child[0].join(10)
    metrics["load_avg_1m_end"] = os.getloadavg()[0]
    return metrics


def _teams(
    world: str,
    team_s: float,
    warmup_s: float,
    gcs_done: Callable[[], dict[str, Any]],
    metrics: dict[str, float],
    progress: Callable[[str], None],
    *,
    steady: tuple[float, float] = (0.0, 0.0),
) -> None:
    """The 64- and 100-robot teams. ``steady`` (after, seconds): the 64-robot team also runs
    ``after`` mission-s more unmeasured and ``seconds`` measured; then ``rtf_full_64`` and
    ``cpu_s_per_robot_mission_s_64`` are that steady window's, and the crowd window's
    ``rtf_full_64_crowd`` / ``cpu_s_per_robot_mission_s_64_crowd`` are kept beside them."""
    for n in (64, 100):
        after_s, steady_s = steady if n == 64 else (0.0, 0.0)
        progress(
            f"team: simulator + {n} robot nodes in workers + GCS on {world}, {warmup_s:g} s "
            f"warm-up then {team_s:g} mission-s measured"
            + (f", then {after_s:g} s on and {steady_s:g} s measured" if steady_s > 0 else "")
        )
        r = full_team(
            n,
            world=world,
            mission_s=team_s,
            warmup_s=warmup_s,
            before_measure=gcs_done,
            steady_after_s=after_s,
            steady_s=steady_s,
        )
        metrics[f"rtf_full_{n}"] = r["rtf"]
        metrics[f"setup_s_{n}"] = r["setup_s"]
        if steady_s > 0:
            metrics[f"rtf_full_{n}_crowd"] = r["rtf"]
            metrics[f"cpu_s_per_robot_mission_s_{n}_crowd"] = r["cpu_s_per_robot_mission_s"]
            metrics[f"rtf_full_{n}"] = r["rtf_steady"]
            metrics[f"cpu_s_per_robot_mission_s_{n}"] = r["cpu_s_per_robot_mission_s_steady"]
            metrics[f"cpu_s_sim_gcs_per_mission_s_{n}"] = r["cpu_s_sim_gcs_per_mission_s_steady"]
            progress(
                f"  crowd window: rtf {r['rtf']:.3f}, {r['cpu_s_per_robot_mission_s']:.3f} CPU-s "
                f"per robot per mission-s; steady window: rtf {r['rtf_steady']:.3f}, "
                f"{r['cpu_s_per_robot_mission_s_steady']:.3f} per robot, simulator+GCS "
                f"{r['cpu_s_sim_gcs_per_mission_s_steady']:.2f} per mission-s"
            )
        if n == 100:
            metrics["cpu_s_per_robot_mission_s"] = r["cpu_s_per_robot_mission_s"]
            for key in (
                "cpu_s_sim_gcs_per_mission_s",
                "cpu_s_main_per_mission_s",
                "cpu_s_sim_helpers_per_mission_s",
            ):
                metrics[key] = r[key]
        progress(
            f"  rtf {r['rtf']:.3f}, workers {r['workers']:.0f}, CPU "
            f"{r['cpu_s_per_robot_mission_s']:.3f} s per robot per mission-s, simulator+GCS "
            f"{r['cpu_s_sim_gcs_per_mission_s']:.2f} s per mission-s, setup {r['setup_s']:.0f} s"
        )
        if n == 64:
            _report_gcs(gcs_done(), metrics, progress)
