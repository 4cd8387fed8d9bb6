"""The mission recorder: what a run did, kept in its run directory, and the report built from it
(issue 14 item 3; paper section 7, DESIGN section 8).

The mission loop (the composition root, which alone may read ground truth) calls::

    rec = MissionRecorder(run_dir, world_name="small", seed=3, duration_s=300.0,
                          roles={0: "sensor", 1: "sensor", 2: "sensor", 3: "disruptor"})
    for each simulator step:
        rec.track(sim.time_s, sim=sim)                        # cheap: the truth track
        every ~5 mission-s:
            rec.sample(sim.time_s, sim=sim, station=station,  # the GCS's estimate + scoring
                       link_bytes=link_bytes_from_meters(robot_meter, ground_meter),
                       modes={rid: telemetry.mode, ...})
        rec.event(t, "detection", object_kind="static_ooi", position_in_map=(x, y), robot_id=r)
    metrics = rec.finish(sim=sim, station=station)           # report.json, report.md, plots

``sim`` (:class:`sim.simulator.Simulator`) is the only place truth is read, for scoring;
``station`` (:class:`gcs.ground_station.GroundStation`) is the estimate. ``track`` is optional
but makes the truth track fine enough (``truth_period_s``) to score every pose node and loop
closure at its own time; without it the truth is known only at the samples and the report
says how coarse it was.

Run directory (everything ``magic report RUN_DIR`` needs to rebuild the report, nothing else)::

    record/meta.json         world, seed, duration, roles, starts, OOIs, radio capacity, config
    record/samples.jsonl     one line per sample (appended and flushed as the run goes)
    record/events.jsonl      mission events (``event``) and the simulator's rule events
    record/truth_map.npz     truth raster: vertical occupancy and reachable cells
    record/truth_track.npz   true poses over time (``finish``)
    record/final.npz         posterior pose nodes with their true poses, loop closures,
                             fiducial and operator edges, the final global map (``finish``)
    map/global_map.{pgm,yaml,png}  the final global map (ROS map_server format)
    report.json, report.md, plots/*.png   (:mod:`mission.report.report_builder`)

Events: ``kind`` is free text; these are understood by the report:
``detection`` (``object_kind``: ``static_ooi`` / ``toxic_vat`` / ``hostile`` / ...,
``position_in_map``: (x, y)), ``interaction`` (an operator command: interactions per minute),
``mode`` (``robot_id``, ``mode``: a robot's reported autonomy mode changed, :meth:`mode`),
``neutralization``, ``blast``, ``robot_lost``, ``closure``, ``robot_sighting`` (a robot's own
hostile track, ``robot_id``, ``position_world``: (x, y), recorded by ``magic run`` from
in-process robots whether or not the GCS heard of it). The simulator's own rule events
(``detonation``, ``neutralized``, ``robot_lost``, ``civilian_harmed``) are read from ``sim`` at
each sample and are what the scores count (truth), with ``source: sim``.
"""

from __future__ import annotations

import enum
import json
import logging
import math
import time
from collections.abc import Mapping
from pathlib import Path
from typing import IO, Any

import msgspec
import numpy as np

from gcs.graph.pose_graph import Provenance
from gcs.ground_station import GroundStation
from mission.report.map_scoring import cell_centres, explored_frac, world_from_map
from mission.report.trajectory_scoring import interpolate_poses
from protocol.meter import Meter
from sim.simulator import Simulator

__all__ = [
    "FORMAT_VERSION",
    "MissionRecorder",
    "ReportConfig",
    "link_bytes_from_meters",
]

log = logging.getLogger("magic.report")

#: Version of the run directory's record format (``record/meta.json``).
FORMAT_VERSION = 1


class ReportConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Tolerances of the scoring (stored in the run directory: a rebuild scores the same).

    ``truth_period_s``: spacing of the recorded truth track. ``ooi_match_m`` /
    ``hostile_match_m``: a static OOI or vat (a hostile) counts as detected when the GCS put a
    hazard or a detection this close to it (m, truth frame). ``false_closure_m`` /
    ``false_closure_rad``: a loop closure off by more is false. ``occupancy_tolerance_m``:
    distance tolerance of the occupancy F1 (:mod:`mission.report.map_scoring`).
    """

    truth_period_s: float = 0.2
    ooi_match_m: float = 2.0
    hostile_match_m: float = 5.0
    false_closure_m: float = 0.5
    false_closure_rad: float = math.radians(5.0)
    occupancy_tolerance_m: float = 0.2

    def __post_init__(self) -> None:
        for name in self.__struct_fields__:
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"report.{name}: expected a positive finite number, got {v}")


def link_bytes_from_meters(*meters: Meter) -> dict[tuple[int, str, str], int]:
    """Cumulative on-air bytes by ``(robot_id, "up"/"down", stream)`` summed over ``meters``
    (a robot side meters its uplink, the ground side its downlink)."""
    out: dict[tuple[int, str, str], int] = {}
    for meter in meters:
        for (rid, direction, stream), count in meter.snapshot().items():
            key = (int(rid), str(direction.value), str(stream))
            out[key] = out.get(key, 0) + int(count.bytes)
    return out


def _jsonable(v: Any) -> Any:
    """Plain JSON values of event fields (enums by name, arrays as lists, floats finite or
    None)."""
    if isinstance(v, enum.Enum):
        return v.name.lower() if isinstance(v.value, int) else v.value
    if isinstance(v, np.ndarray):
        return [_jsonable(x) for x in v.tolist()]
    if isinstance(v, np.generic):
        return _jsonable(v.item())
    if isinstance(v, bool | int | str) or v is None:
        return v
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, Mapping):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple | set | frozenset):
        return [_jsonable(x) for x in v]
    return str(v)


def _mode_name(mode: Any) -> str:
    if mode is None:
        return "unknown"
    if isinstance(mode, enum.Enum):
        return mode.name.lower()
    return str(mode).lower()


class MissionRecorder:
    """Records a mission into ``run_dir`` and builds its report (module docstring).

    ``roles``: robot id -> ``"sensor"`` or ``"disruptor"``. Never raises on what the run hands
    it at ``sample`` / ``event`` time beyond a wrong argument type: a run is not stopped by
    its report. Files are flushed at every sample, so an interrupted run keeps its record.
    """

    def __init__(
        self,
        run_dir: Path,
        *,
        world_name: str,
        seed: int,
        duration_s: float,
        roles: Mapping[int, str],
        config: ReportConfig | None = None,
    ) -> None:
        bad = {r: role for r, role in roles.items() if role not in ("sensor", "disruptor")}
        if bad:
            raise ValueError(f"roles: expected 'sensor' or 'disruptor', got {bad}")
        self.run_dir = Path(run_dir)
        self.record_dir = self.run_dir / "record"
        self.record_dir.mkdir(parents=True, exist_ok=True)
        self.config = config or ReportConfig()
        self.world_name = world_name
        self.seed = int(seed)
        self.duration_s = float(duration_s)
        self.roles = {int(r): str(role) for r, role in roles.items()}
        self._wall0 = time.perf_counter()
        self._started_utc = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
        self._samples: IO[str] = (self.record_dir / "samples.jsonl").open("w", encoding="utf-8")
        self._events: IO[str] = (self.record_dir / "events.jsonl").open("w", encoding="utf-8")
        self._truth_t: list[float] = []
        self._truth_pose: list[np.ndarray] = []
        self._truth_alive: list[np.ndarray] = []
        self._distance_m: np.ndarray | None = None  # truth distance driven per robot
        self._modes: dict[int, str] = {}  # each robot's latest reported autonomy mode
        self._last_xy: np.ndarray | None = None
        self._sim_events_seen = 0
        self._robot_ids: list[int] = []
        self._world_from_map: np.ndarray | None = None
        self._reachable_world: np.ndarray | None = None
        self._reachable_map: np.ndarray | None = None
        self._cell_area_m2 = 0.0
        self._finished = False
        self.faults = 0  # exceptions caught in track/sample/event (logged; the run went on)

    # ---- during the run ----------------------------------------------------------------

    def _start(self, sim: Simulator, station: GroundStation | None) -> None:
        """First contact with the simulator: the truth raster and the run's metadata."""
        if self._robot_ids:
            if self._world_from_map is None and station is not None:
                self._anchor(sim, station)
            return
        self._robot_ids = [int(r) for r in sim.robot_ids]
        truth = sim.truth
        np.savez_compressed(
            self.record_dir / "truth_map.npz",
            vertical_occupancy=truth.vertical_occupancy,
            reachable=truth.reachable,
            resolution_m=np.float64(truth.resolution_m),
        )
        self._reachable_world = cell_centres(truth.reachable, truth.resolution_m)
        self._cell_area_m2 = truth.resolution_m**2
        n = len(self._robot_ids)
        self._distance_m = np.zeros(n)
        self._last_xy = sim.robot_poses()[:, :2].copy()
        if station is not None:
            self._anchor(sim, station)
        self._write_meta(sim, station)

    def _anchor(self, sim: Simulator, station: GroundStation) -> None:
        graph_cfg = station.config.graph
        ids = self._robot_ids
        map_robot = graph_cfg.map_robot_id if graph_cfg.map_robot_id in ids else ids[0]
        start = np.asarray(sim.world.robots[ids.index(map_robot)].pose_m, dtype=float)
        self._world_from_map = world_from_map(start, np.asarray(graph_cfg.map_from_odom, float))
        assert self._reachable_world is not None
        c, s = math.cos(self._world_from_map[2]), math.sin(self._world_from_map[2])
        d = self._reachable_world - self._world_from_map[:2]
        self._reachable_map = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], 1)
        self._map_robot = map_robot
        self._write_meta(sim, station)

    def _write_meta(self, sim: Simulator, station: GroundStation | None) -> None:
        world = sim.world
        humans = [
            {"human_id": h.human_id, "kind": h.kind, "route_m": [list(p) for p in h.route_m]}
            for h in world.humans
        ]
        meta = {
            "format_version": FORMAT_VERSION,
            "world_name": self.world_name,
            "seed": self.seed,
            "duration_s": self.duration_s,
            "started_utc": self._started_utc,
            "roles": {str(r): role for r, role in self.roles.items()},
            "robot_ids": self._robot_ids,
            "world_size_m": list(world.size_m),
            "world_fingerprint": world.fingerprint(),
            "starts": {str(r.robot_id): list(r.pose_m) for r in world.robots},
            "oois": [
                {"ooi_id": o.ooi_id, "kind": o.kind, "xy_m": list(o.xy_m)} for o in world.oois
            ],
            "humans": humans,
            "radio_capacity_bps": float(sim.radio_config.shared_capacity_bps),
            "step_s": float(sim.config.step_s),
            "world_from_map": None
            if self._world_from_map is None
            else self._world_from_map.tolist(),
            "map_robot_id": getattr(self, "_map_robot", None),
            "report_config": msgspec.to_builtins(self.config),
        }
        (self.record_dir / "meta.json").write_text(json.dumps(meta, indent=1), encoding="utf-8")

    def _fault(self, where: str, t_s: float) -> None:
        """A bug of the recorder must not stop the run: logged with its traceback, counted,
        and noted in the record."""
        self.faults += 1
        log.exception("mission recorder: %s failed at t=%.2f s (the run goes on)", where, t_s)
        try:
            line = {"t_s": float(t_s), "kind": "recorder_fault", "source": "report", "in": where}
            self._events.write(json.dumps(line) + "\n")
        except Exception:  # the record file itself is the problem
            pass

    def track(self, t_s: float, *, sim: Simulator, force: bool = False) -> None:
        """Record the true poses if ``truth_period_s`` has passed since the last (call every
        step: the distance driven is summed at every call). Never raises (see ``faults``)."""
        try:
            self._track(t_s, sim=sim, force=force)
        except Exception:
            self._fault("track", t_s)

    def _track(self, t_s: float, *, sim: Simulator, force: bool = False) -> None:
        self._start(sim, None)
        poses = sim.robot_poses()
        assert self._distance_m is not None and self._last_xy is not None
        self._distance_m += np.hypot(*(poses[:, :2] - self._last_xy).T)
        self._last_xy = poses[:, :2].copy()
        if (
            not force
            and self._truth_t
            and t_s - self._truth_t[-1] < self.config.truth_period_s - 1e-9
        ):
            return
        if self._truth_t and t_s <= self._truth_t[-1]:
            return
        self._truth_t.append(float(t_s))
        self._truth_pose.append(poses.copy())
        self._truth_alive.append(np.asarray(sim.alive(), dtype=bool).copy())

    def _drain_sim_events(self, sim: Simulator) -> None:
        events = sim.events
        for e in events[self._sim_events_seen :]:
            line = {
                "t_s": float(e.time_s),
                "kind": e.kind,
                "source": "sim",
                "subject": e.subject,
                "cause": e.cause,
                "robots": [self._robot_ids[i] for i in e.robots if i < len(self._robot_ids)],
                "civilians": list(e.civilians),
            }
            self._events.write(json.dumps(line) + "\n")
        self._sim_events_seen = len(events)

    def sample(
        self,
        t_s: float,
        *,
        sim: Simulator,
        station: GroundStation,
        link_bytes: dict[tuple[int, str, str], int],
        modes: dict[int, Any],
    ) -> None:
        """One point of the time series: truth, the GCS's estimate and map (explored area
        scored against the truth now), radio bytes so far (cumulative, by robot, ``"up"`` /
        ``"down"`` or :class:`~protocol.messages.Direction`, stream), autonomy modes (robot id
        -> :class:`~protocol.messages.AutonomyMode`, a name, or None). Never raises (see
        ``faults``)."""
        try:
            self._sample(t_s, sim=sim, station=station, link_bytes=link_bytes, modes=modes)
        except Exception:
            self._fault("sample", t_s)

    def _sample(
        self,
        t_s: float,
        *,
        sim: Simulator,
        station: GroundStation,
        link_bytes: dict[tuple[int, str, str], int],
        modes: dict[int, Any],
    ) -> None:
        self._start(sim, station)
        self._track(t_s, sim=sim, force=True)
        self._drain_sim_events(sim)
        graph = station.graph
        estimate: dict[str, list[float]] = {}
        for r in graph.robots:
            estimate[str(r)] = [float(v) for v in graph.pose(graph.last_key(r))]
        occupancy = station.rasterize()
        known_cells = int(np.count_nonzero(occupancy.values != -1))
        frac = float("nan")
        if self._reachable_map is not None:
            frac, _ = explored_frac(occupancy, self._reachable_map)
        hostiles = []
        if sim.world.humans:
            xy = sim.routes.positions(sim.time_s)
            hostiles = [
                [h.human_id, float(xy[k][0]), float(xy[k][1])]
                for k, h in enumerate(sim.world.humans)
                if h.kind == "hostile"
            ]
        poses = sim.robot_poses()
        alive = sim.alive()
        assert self._distance_m is not None
        line = {
            "t_s": float(t_s),
            "wall_s": time.perf_counter() - self._wall0,
            "truth": {str(r): [float(v) for v in poses[k]] for k, r in enumerate(self._robot_ids)},
            "alive": {str(r): bool(alive[k]) for k, r in enumerate(self._robot_ids)},
            "distance_m": {
                str(r): float(self._distance_m[k]) for k, r in enumerate(self._robot_ids)
            },
            "estimate": estimate,
            "modes": {str(int(r)): _mode_name(m) for r, m in modes.items()},
            "link_bytes": [
                [int(r), str(d.value if isinstance(d, enum.Enum) else d), str(s), int(b)]
                for (r, d, s), b in sorted(link_bytes.items(), key=lambda kv: str(kv[0]))
            ],
            "hazards": [
                [
                    h.hazard_id,
                    h.kind.name.lower(),
                    float(h.position_in_map[0]),
                    float(h.position_in_map[1]),
                ]
                for h in station.hazards
            ],  # fmt: skip
            "hostiles_truth": hostiles,
            "known_area_m2": known_cells * occupancy.resolution_m**2,
            "explored_frac": frac,
            "pose_nodes": int(station.stats.pose_nodes),
            "terrain_grids": int(station.stats.terrain_grids),
            "closures": len(graph.edges(Provenance.LOOP_AUTO)),
            "rejected": int(station.stats.rejected_total),
        }
        self._samples.write(json.dumps(_jsonable(line)) + "\n")
        self._samples.flush()
        self._events.flush()

    def event(self, t_s: float, kind: str, **fields: Any) -> None:
        """A mission event (module docstring lists the kinds the report understands). Never
        raises (see ``faults``)."""
        try:
            line = {"t_s": float(t_s), "kind": str(kind), "source": "mission"}
            line.update({k: _jsonable(v) for k, v in fields.items() if k not in line})
            self._events.write(json.dumps(line) + "\n")
        except Exception:
            self._fault(f"event {kind!r}", t_s)

    def mode(self, t_s: float, robot_id: int, mode: Any) -> None:
        """A robot's autonomy mode as its telemetry reports it (call with every telemetry);
        a change is kept as a ``mode`` event, from which the report charges time and truth
        distance per mode at the truth track's resolution (paper Tables 4-5) instead of at
        the samples'. Never raises."""
        try:
            name = _mode_name(mode)
            rid = int(robot_id)
            if self._modes.get(rid) != name and math.isfinite(float(t_s)):
                self._modes[rid] = name
                self.event(t_s, "mode", robot_id=rid, mode=name)
        except Exception:
            self._fault("mode", t_s)

    # ---- at the end ----------------------------------------------------------------------

    def finish(self, *, sim: Simulator, station: GroundStation) -> dict[str, float]:
        """Write the final record (posterior graph with the true pose of every node, loop
        closures, final map, truth track), then the report; returns the metrics."""
        from gcs.mapping.map_export import write_pgm_yaml, write_png
        from mission.report.report_builder import build_report

        self._start(sim, station)
        self._track(sim.time_s, sim=sim, force=True)
        self._drain_sim_events(sim)
        self._samples.close()
        self._events.close()
        t = np.asarray(self._truth_t)
        track = np.asarray(self._truth_pose).reshape(len(t), len(self._robot_ids), 3)
        alive = np.asarray(self._truth_alive).reshape(len(t), len(self._robot_ids))
        np.savez_compressed(
            self.record_dir / "truth_track.npz",
            time_s=t,
            robot_ids=np.asarray(self._robot_ids, dtype=np.int64),
            world_from_base=track,
            alive=alive,
            wall_s=np.float64(time.perf_counter() - self._wall0),
        )
        graph = station.graph
        nodes = graph.nodes()
        keys = np.array([n.key for n in nodes], dtype=np.int64)
        robots = np.array([n.robot_id for n in nodes], dtype=np.int64)
        times = np.array([n.time_s for n in nodes], dtype=np.float64)
        est = np.array([graph.pose(n.key) for n in nodes], dtype=np.float64).reshape(-1, 3)
        truth = np.full((len(nodes), 3), np.nan)
        for r in set(robots.tolist()):
            if r in self._robot_ids:
                k = self._robot_ids.index(r)
                sel = robots == r
                truth[sel] = interpolate_poses(t, track[:, k, :], times[sel])
        edges = {
            prefix: graph.edges(provenance)
            for prefix, provenance in (
                ("closure", Provenance.LOOP_AUTO),
                ("fiducial", Provenance.FIDUCIAL),
                ("operator", Provenance.LOOP_OPERATOR),
            )
        }
        edge_arrays: dict[str, Any] = {}  # (Any: numpy's stub types savez's keywords as bool)
        for prefix, found in edges.items():
            rel = [e for e in found if e.key_b is not None]
            edge_arrays[f"{prefix}_key_a"] = np.array([e.key_a for e in rel], dtype=np.int64)
            edge_arrays[f"{prefix}_key_b"] = np.array([e.key_b for e in rel], dtype=np.int64)
            edge_arrays[f"{prefix}_a_from_b"] = np.array(
                [e.z for e in rel], dtype=np.float64
            ).reshape(-1, 3)
            edge_arrays[f"{prefix}_time_s"] = np.array([e.time_s for e in rel], dtype=np.float64)
        occupancy = station.rasterize()
        np.savez_compressed(
            self.record_dir / "final.npz",
            node_key=keys,
            node_robot=robots,
            node_time_s=times,
            node_map_from_base=est,
            node_world_from_base=truth,
            **edge_arrays,
            map_values=occupancy.values,
            map_origin_m=np.asarray(occupancy.origin_in_map, dtype=np.float64),
            map_resolution_m=np.float64(occupancy.resolution_m),
        )
        if occupancy.values.size:
            write_pgm_yaml(occupancy, self.run_dir / "map" / "global_map")
            write_png(occupancy, self.run_dir / "map" / "global_map.png")
        self._finished = True
        return build_report(self.run_dir)

    def close(self) -> None:
        """Close the record files without a report (a run that ends before ``finish``; the
        samples so far stay readable)."""
        for f in (self._samples, self._events):
            if not f.closed:
                f.close()
