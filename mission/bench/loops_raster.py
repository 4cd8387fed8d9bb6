"""``magic bench loops`` part: global map rasterization (issue 7 item 5; paper 4.8, Table 2).

A synthetic MAGIC-sized phase: a 220 x 160 m city (blocks of buildings with doorways, a
perimeter fence, parked cars, trees) at 10 cm, eight robots driving random routes along its
streets and revisiting them, a pose node every metre of driving (about 4000 in all). Each
node's binary grid is what a robot would send: the vertical-surface cells its rays hit within
the 15 m window around it (``150 x 150`` at 10 cm, cropped to the occupied bounding box).

The sequence (the same for every method): the first nodes in time order are added and
rasterized once (untimed: it samples every node); then each step appends the next nodes in
time order and applies a loop closure to one robot (round-robin) that moves its last
``CLOSURE_NODES`` nodes by a smooth correction (translation and rotation ramped along the
chain), and rasterizes. Metrics (mean wall time per step, after warm-up, one core):

- ``raster_mean_s``: covering and cached submaps (:meth:`Rasterizer.rasterize`);
- ``raster_naive_mean_s``: every node, nothing cached (:meth:`Rasterizer.rasterize_naive`);
- ``raster_cover_mean_s``: covering only (``cache=False``), Table 2's middle row, over the
  first third of the steps;
- ``raster_speedup_vs_naive``: ``raster_naive_mean_s / raster_mean_s``;
- ``raster_mean_cpu_s``, ``raster_naive_mean_cpu_s``: the same in process CPU time, which a
  shared machine inflates less than wall time;
- ``raster_naive_mismatch_cells``: cells where the cached map differs from the naive one,
  summed over all steps (must be 0);
- ``raster_kept_frac``: nodes kept by the covering over nodes, at the last step;
  ``raster_sampled_per_step``: nodes sampled again per step (new or moved);
  ``raster_submaps_reused_frac``; ``raster_nodes`` and ``raster_map_mcells`` at the end.
"""

from __future__ import annotations

__all__ = ["run", "synthetic_city", "robot_routes", "node_grids"]

import math
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np

from gcs.mapping.rasterization import OccupancyMap, RasterConfig, Rasterizer

RES_M = 0.1
WORLD_M = (220.0, 160.0)
ROBOTS = 8
NODES = 4000
WINDOW_CELLS = 150
CLOSURE_NODES = 250
NEW_PER_STEP = 25


@dataclass(frozen=True)
class City:
    """``walls`` ``(rows, cols)`` bool at ``RES_M`` (cell ``(r, c)`` covers ``(c, r) * RES_M``
    in ``map``); street centre lines at ``street_x`` / ``street_y`` (m)."""

    walls: np.ndarray
    street_x: np.ndarray
    street_y: np.ndarray


def _cells(v_m: float) -> int:
    return int(round(v_m / RES_M))


def synthetic_city(seed: int = 7) -> City:
    """A 220 x 160 m city: streets 10 m wide between blocks of 25..40 m, one or two
    buildings per block (0.2 m walls, 1.2 m doorways), cars and trees along the kerbs, a
    perimeter fence."""
    rng = np.random.default_rng(seed)
    w_m, h_m = WORLD_M
    walls = np.zeros((_cells(h_m), _cells(w_m)), dtype=bool)

    def street_lines(length: float) -> np.ndarray:
        lines = [8.0]
        while lines[-1] < length - 40.0:
            lines.append(lines[-1] + rng.uniform(32.0, 46.0))
        lines[-1] = min(lines[-1], length - 8.0)
        return np.asarray(lines)

    sx, sy = street_lines(w_m), street_lines(h_m)

    def rect(x0: float, y0: float, x1: float, y1: float, *, thick: float, filled: bool) -> None:
        c0, c1, r0, r1 = _cells(x0), _cells(x1), _cells(y0), _cells(y1)
        if filled:
            walls[r0:r1, c0:c1] = True
            return
        t = max(1, _cells(thick))
        walls[r0 : r0 + t, c0:c1] = True
        walls[r1 - t : r1, c0:c1] = True
        walls[r0:r1, c0 : c0 + t] = True
        walls[r0:r1, c1 - t : c1] = True

    half_street = 5.0
    for i in range(len(sx) - 1):
        for j in range(len(sy) - 1):
            bx0, bx1 = sx[i] + half_street + 1.0, sx[i + 1] - half_street - 1.0
            by0, by1 = sy[j] + half_street + 1.0, sy[j + 1] - half_street - 1.0
            if bx1 - bx0 < 6 or by1 - by0 < 6:
                continue
            parts = [(bx0, bx1)]
            if bx1 - bx0 > 24 and rng.random() < 0.6:
                cut = rng.uniform(bx0 + 10, bx1 - 10)
                parts = [(bx0, cut - 1.0), (cut + 1.0, bx1)]
            for x0, x1 in parts:
                rect(x0, by0, x1, by1, thick=0.2, filled=False)
                for _ in range(rng.integers(1, 4)):  # doorways
                    side = rng.integers(4)
                    if side < 2:
                        xd = rng.uniform(x0 + 1.5, x1 - 2.7)
                        yr = by0 if side == 0 else by1 - 0.2
                        walls[_cells(yr) : _cells(yr + 0.2), _cells(xd) : _cells(xd + 1.2)] = False
                    else:
                        yd = rng.uniform(by0 + 1.5, by1 - 2.7)
                        xr = x0 if side == 2 else x1 - 0.2
                        walls[_cells(yd) : _cells(yd + 1.2), _cells(xr) : _cells(xr + 0.2)] = False
                if x1 - x0 > 8 and by1 - by0 > 8:  # an inner wall
                    xm = rng.uniform(x0 + 3, x1 - 3)
                    walls[_cells(by0) : _cells(by1 - 2.0), _cells(xm) : _cells(xm + 0.2)] = True
    # parked cars and trees along the kerbs
    for _ in range(120):
        if rng.random() < 0.5:
            x = rng.uniform(5, w_m - 10)
            y = sy[rng.integers(len(sy))] + rng.choice([-1, 1]) * 3.8
            rect(x, y - 0.9, x + 4.5, y + 0.9, thick=0.1, filled=True)
        else:
            x = sx[rng.integers(len(sx))] + rng.choice([-1, 1]) * 3.8
            y = rng.uniform(5, h_m - 10)
            rect(x - 0.9, y, x + 0.9, y + 4.5, thick=0.1, filled=True)
    for _ in range(150):
        if rng.random() < 0.5:
            x, y = rng.uniform(5, w_m - 5), sy[rng.integers(len(sy))] + rng.choice([-1, 1]) * 4.6
        else:
            x, y = sx[rng.integers(len(sx))] + rng.choice([-1, 1]) * 4.6, rng.uniform(5, h_m - 5)
        rect(x - 0.2, y - 0.2, x + 0.2, y + 0.2, thick=0.1, filled=True)
    rect(1.0, 1.0, w_m - 1.0, h_m - 1.0, thick=0.1, filled=False)  # the perimeter fence
    # keep the street centres drivable
    for x in sx:
        walls[:, _cells(x - 2.5) : _cells(x + 2.5)] &= False
    for y in sy:
        walls[_cells(y - 2.5) : _cells(y + 2.5), :] &= False
    rect(1.0, 1.0, w_m - 1.0, h_m - 1.0, thick=0.1, filled=False)
    return City(walls, sx, sy)


def robot_routes(
    city: City, *, robots: int, nodes: int, seed: int = 11
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random routes on the street grid, a node per metre: ``(robot (N,), time_s (N,),
    pose_in_map (N, 3))`` sorted by time. Each robot starts at a random crossing 5 s after
    the previous one, drives 1 m/s with a lateral offset per street segment."""
    rng = np.random.default_rng(seed)
    per_robot = nodes // robots
    out_r, out_t, out_p = [], [], []
    nx, ny = len(city.street_x), len(city.street_y)
    for r in range(robots):
        i, j = int(rng.integers(nx)), int(rng.integers(ny))
        prev = (-1, -1)
        pts: list[np.ndarray] = []
        while len(pts) < per_robot:
            moves = [(i + di, j + dj) for di, dj in ((1, 0), (-1, 0), (0, 1), (0, -1))]
            moves = [m for m in moves if 0 <= m[0] < nx and 0 <= m[1] < ny and m != prev]
            ni, nj = moves[int(rng.integers(len(moves)))]
            a = np.array([city.street_x[i], city.street_y[j]])
            b = np.array([city.street_x[ni], city.street_y[nj]])
            d = b - a
            length = float(np.hypot(*d))
            u = d / length
            side = np.array([-u[1], u[0]]) * rng.uniform(-1.5, 1.5)
            yaw = math.atan2(u[1], u[0])
            for s in np.arange(0.5, length, 1.0):
                p = a + u * s + side
                pts.append(np.array([p[0], p[1], yaw + rng.normal(0, 0.03)]))
            prev, i, j = (i, j), ni, nj
        pts = pts[:per_robot]
        out_r.append(np.full(per_robot, r))
        out_t.append(5.0 * r + np.arange(per_robot) * 1.0 + rng.uniform(0, 0.1, per_robot))
        out_p.append(np.stack(pts))
    robot, t, p = np.concatenate(out_r), np.concatenate(out_t), np.concatenate(out_p)
    order = np.argsort(t, kind="stable")
    return robot[order], t[order], p[order]


@numba.njit(cache=True, nogil=True)
def _first_hits(walls, x, y, yaw, n, res, n_rays):  # type: ignore[no-untyped-def]
    """The ``n x n`` window (``res`` cells) centred on pose ``(x, y, yaw)`` in its ``base``
    frame: True where a ray from the centre first hits a wall of ``walls`` (a LIDAR's
    returns), by the 4-connected grid traversal of Amanatides and Woo. Only the cells the rays
    cross are looked up in the world."""
    rows, cols = walls.shape
    hits = np.zeros((n, n), dtype=np.bool_)
    c = math.cos(yaw)
    s = math.sin(yaw)
    half = n * res / 2.0
    u0 = n / 2.0 + 1e-7
    v0 = n / 2.0 + 1e-7
    for k in range(n_rays):
        a = 2.0 * math.pi * k / n_rays
        dx = math.cos(a)
        dy = math.sin(a)
        ix = int(math.floor(u0))
        iy = int(math.floor(v0))
        sx = 1 if dx > 0 else -1
        sy = 1 if dy > 0 else -1
        tdx = abs(1.0 / dx) if dx != 0 else math.inf
        tdy = abs(1.0 / dy) if dy != 0 else math.inf
        tx = ((ix + 1 - u0) if dx > 0 else (u0 - ix)) * tdx if dx != 0 else math.inf
        ty = ((iy + 1 - v0) if dy > 0 else (v0 - iy)) * tdy if dy != 0 else math.inf
        while 0 <= ix < n and 0 <= iy < n:
            bx = (ix + 0.5) * res - half
            by = (iy + 0.5) * res - half
            wi = int(math.floor((y + s * bx + c * by) / res))
            wj = int(math.floor((x + c * bx - s * by) / res))
            if 0 <= wi < rows and 0 <= wj < cols and walls[wi, wj]:
                hits[iy, ix] = True
                break
            if tx < ty:
                tx += tdx
                ix += sx
            else:
                ty += tdy
                iy += sy
    return hits


def node_grids(
    city: City, poses_in_map: np.ndarray
) -> list[tuple[np.ndarray, tuple[float, float]]]:
    """Per node ``(grid, origin_in_base)``: the wall cells its rays hit in the 15 m window
    around it, in its ``base`` frame, cropped to their bounding box."""
    n = WINDOW_CELLS
    half = n * RES_M / 2
    out = []
    for x, y, yaw in poses_in_map:
        hits = _first_hits(city.walls, x, y, yaw, n, RES_M, 720)
        r_any = np.flatnonzero(hits.any(axis=1))
        if len(r_any) == 0:
            out.append((np.zeros((0, 0), dtype=bool), (-half, -half)))
            continue
        c_any = np.flatnonzero(hits.any(axis=0))
        r0, r1, c0, c1 = r_any[0], r_any[-1] + 1, c_any[0], c_any[-1] + 1
        out.append((hits[r0:r1, c0:c1].copy(), (-half + c0 * RES_M, -half + r0 * RES_M)))
    return out


def _close_loop(poses: np.ndarray, chain: np.ndarray, rng: np.random.Generator) -> None:
    """Move the nodes ``chain`` (in driving order) by a correction ramped along it: rotation
    about the first node and a translation, growing from 0 to full at the last node."""
    if len(chain) == 0:
        return
    d_yaw = rng.normal(0.0, 0.01)
    d_xy = rng.normal(0.0, 0.1, 2)
    pivot = poses[chain[0], :2].copy()
    ramp = (np.arange(len(chain)) + 1.0) / len(chain)
    for w, n in zip(ramp, chain, strict=True):
        a = w * d_yaw
        c, s = math.cos(a), math.sin(a)
        rel = poses[n, :2] - pivot
        poses[n, 0] = pivot[0] + c * rel[0] - s * rel[1] + w * d_xy[0]
        poses[n, 1] = pivot[1] + s * rel[0] + c * rel[1] + w * d_xy[1]
        poses[n, 2] += a


def _sequence(
    robot: np.ndarray, true_poses: np.ndarray, steps: int, seed: int
) -> tuple[int, list[np.ndarray]]:
    """``(initial node count, posterior poses per step)``: the nodes present at step ``k``
    are the first ``initial + k * NEW_PER_STEP``."""
    rng = np.random.default_rng(seed)
    n0 = len(robot) - steps * NEW_PER_STEP
    poses = true_poses.copy()
    out = []
    for k in range(steps):
        present = n0 + (k + 1) * NEW_PER_STEP
        r = k % ROBOTS
        mine = np.flatnonzero(robot[:present] == r)
        _close_loop(poses, mine[-CLOSURE_NODES:], rng)
        out.append(poses[:present].copy())
    return n0, out


@dataclass
class _Replay:
    """Wall times per step of the method under test (and of the naive path when checked),
    rasterizer statistics per step, cells where the two differed, and the last map."""

    seconds: list[float]
    naive_seconds: list[float]
    cpu_seconds: list[float]
    naive_cpu_seconds: list[float]
    stats: list[dict[str, float]]
    mismatch_cells: int
    final: OccupancyMap | None


def _replay(
    rasterizer: Rasterizer,
    keys: np.ndarray,
    times: np.ndarray,
    grids: list[tuple[np.ndarray, tuple[float, float]]],
    n0: int,
    steps: list[np.ndarray],
    *,
    check_naive: bool,
) -> _Replay:
    """Feed the sequence through ``rasterizer.rasterize`` and time each step; with
    ``check_naive`` also time ``rasterize_naive`` on the same posterior and count cells that
    differ (shape or origin differences count every cell)."""

    def add(lo: int, hi: int) -> None:
        for n in range(lo, hi):
            grid, origin = grids[n]
            rasterizer.add_node(int(keys[n]), float(times[n]), grid, origin, RES_M)

    add(0, n0)
    rasterizer.rasterize((keys[:n0], steps[0][:n0]))  # warm-up: samples every node once
    out = _Replay([], [], [], [], [], 0, None)
    present = n0
    for poses in steps:
        add(present, len(poses))
        present = len(poses)
        posterior = (keys[:present], poses)
        t0, c0 = time.perf_counter(), time.process_time()
        result = rasterizer.rasterize(posterior)
        out.seconds.append(time.perf_counter() - t0)
        out.cpu_seconds.append(time.process_time() - c0)
        st = rasterizer.stats
        out.stats.append(
            {"kept": st.kept, "nodes": st.nodes, "sampled": st.sampled,
             "reused": st.reused, "submaps": st.submaps}
        )  # fmt: skip
        out.final = result
        if check_naive:
            t0, c0 = time.perf_counter(), time.process_time()
            ref = rasterizer.rasterize_naive(posterior)
            out.naive_seconds.append(time.perf_counter() - t0)
            out.naive_cpu_seconds.append(time.process_time() - c0)
            if ref.values.shape != result.values.shape or ref.origin_in_map != result.origin_in_map:
                out.mismatch_cells += max(ref.values.size, result.values.size)
            else:
                out.mismatch_cells += int(np.count_nonzero(ref.values != result.values))
    return out


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    steps_n = 8 if quick else 30
    progress("raster: synthetic 220 x 160 m city and routes")
    city = synthetic_city()
    robot, times, true_poses = robot_routes(city, robots=ROBOTS, nodes=NODES)
    keys = (robot.astype(np.int64) << 32) | np.arange(len(robot), dtype=np.int64)
    progress(f"raster: {len(keys)} node grids")
    grids = node_grids(city, true_poses)
    n0, steps = _sequence(robot, true_poses, steps_n, seed=5)

    progress("raster: covering + cached submaps, and the naive path on the same posteriors")
    main = _replay(Rasterizer(RasterConfig()), keys, times, grids, n0, steps, check_naive=True)
    progress("raster: covering only")
    cover_steps = steps[: max(3, len(steps) // 3)]
    cover = _replay(
        Rasterizer(RasterConfig(cache=False)), keys, times, grids, n0, cover_steps,
        check_naive=False,
    )  # fmt: skip
    mean_cached = statistics.fmean(main.seconds)
    mean_naive = statistics.fmean(main.naive_seconds)
    last = main.stats[-1]
    assert main.final is not None
    return {
        "raster_mean_s": mean_cached,
        "raster_naive_mean_s": mean_naive,
        "raster_mean_cpu_s": statistics.fmean(main.cpu_seconds),
        "raster_naive_mean_cpu_s": statistics.fmean(main.naive_cpu_seconds),
        "raster_cover_mean_s": statistics.fmean(cover.seconds),
        "raster_speedup_vs_naive": mean_naive / mean_cached,
        "raster_naive_mismatch_cells": float(main.mismatch_cells),
        "raster_kept_frac": last["kept"] / last["nodes"],
        "raster_sampled_per_step": statistics.fmean(s["sampled"] for s in main.stats),
        "raster_submaps_reused_frac": statistics.fmean(
            s["reused"] / s["submaps"] for s in main.stats
        ),
        "raster_nodes": float(last["nodes"]),
        "raster_map_mcells": main.final.values.size / 1e6,
    }
