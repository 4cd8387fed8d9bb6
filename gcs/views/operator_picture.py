"""The operators' picture: a plain, rerun-free snapshot of the GCS state (paper 6.1-6.4).

:class:`PictureBuilder` watches the uplink messages the GCS takes (:meth:`PictureBuilder.observe`:
message times and sizes, telemetry, task status, detections of every kind and their images) and,
when a picture is due (:meth:`PictureBuilder.due`), builds an :class:`OperatorPicture` from the
:class:`~gcs.ground_station.GroundStation` (graph, hazards, map) and, optionally, the planner's
state (:class:`PlannerView`: frontiers, trajectory graph, goals, tasks, deadlocks). The picture
holds what the four displays show:

* task operator (TOC, 6.2): the latest rasterized map with unexplored cells as fog, each robot's
  pose, id, heading, mode, task, trail and goal, frontiers, the trajectory graph, OOIs with their
  danger rings (trigger 2.5 m, blast 10 m static / 5 m hostile);
* sensor operator (SOC, 6.1): the SLAM graph, edges by kind (odometry, scan match, fiducial,
  operator), the recent closures, OOI thumbnails with their classification;
* status dashboard (6.3): one :class:`RobotStatus` row per robot and the alerts
  (:mod:`gcs.views.alerts`), uplink rates for the radio time series;
* SAGE (6.4): the top events with their zoom boxes (:mod:`gcs.views.narration`).

Publishing decisions are made here, so a viewer adapter only draws: robots and dashboard at
every picture (``robots_period_s``), the graph when the estimate changed and
``graph_period_s`` passed (or a new closure arrived and ``closure_period_s`` passed), the map
when ``map_period_s`` passed and the map differs from the last one sent. A picture's
``map`` / ``graph`` is None when that layer is not due.

All positions are in ``map`` (metres, x forward/east, y left/north), yaw in radians.
Robots whose trajectory is not yet linked to ``map`` are drawn at their weakly anchored
estimate and flagged ``linked = False``.
"""

from __future__ import annotations

import collections
import math
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from gcs.graph.pose_graph import Provenance
from gcs.mapping.rasterization import OccupancyMap
from gcs.views.alerts import Alert, AlertLog, AlertRules, AlertRulesConfig, Speaker
from gcs.views.narration import Event, NarrationConfig, Narrator
from protocol.messages import (
    AutonomyMode,
    Detection,
    DetectionImage,
    ObjectKind,
    TaskState,
    TaskStatus,
    Telemetry,
)
from protocol.se2 import transform_points

if TYPE_CHECKING:
    from gcs.ground_station import GroundStation

__all__ = [
    "EDGE_KINDS",
    "GraphPicture",
    "ObjectSighting",
    "OperatorPicture",
    "PictureBuilder",
    "PlannerView",
    "RobotStatus",
    "ViewsConfig",
]

FloatArray = NDArray[np.float64]

#: Edge kinds shown on the SOC, by pose-graph provenance (priors are not edges to draw).
EDGE_KINDS = {
    Provenance.ODOMETRY: "odometry",
    Provenance.LOOP_AUTO: "scan_match",
    Provenance.FIDUCIAL: "fiducial",
    Provenance.LOOP_OPERATOR: "operator",
}


class ViewsConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """When layers are published and how much history the views keep (mission seconds).

    The defaults (robots and dashboard every 2.5 s, the graph every 30 s or 10 s after a
    closure, the map every 60 s) cost 0.077 of the GCS process's CPU with 14 robots on the
    replay trial (:mod:`gcs.views.trial`, rerun's threads included) when the GCS hands the views
    the map it rasterized for its planners, 0.118 when the views rasterize it themselves
    (estimation-only GCS); at 2 s / 20 s / 30 s about 0.10 / 0.15.

    ``robots_period_s``: a picture (robots, dashboard, alerts, events) at most this often.
    ``graph_period_s`` / ``closure_period_s``: the SLAM graph at most this often / this often
    when a closure arrived. ``map_period_s``: the map at most this often. ``trail_nodes``: poses
    in a robot's trail. ``rate_window_s``: window of the uplink rate. ``stuck_s`` /
    ``stuck_m``: a robot with a task that moved less than ``stuck_m`` in ``stuck_s`` is stuck.
    ``recent_closure_s``: closures younger than this are highlighted. ``thumbnail_px``: size
    of an OOI thumbnail's longer side. ``merge_m``: sightings of one kind closer than this are
    one object.
    """

    robots_period_s: float = 2.5
    graph_period_s: float = 30.0
    closure_period_s: float = 10.0
    map_period_s: float = 60.0
    trail_nodes: int = 60
    rate_window_s: float = 30.0
    stuck_s: float = 60.0
    stuck_m: float = 0.5
    recent_closure_s: float = 60.0
    thumbnail_px: int = 96
    merge_m: float = 1.5
    max_objects: int = 1000
    speak: bool = False
    alerts: AlertRulesConfig = msgspec.field(default_factory=AlertRulesConfig)
    narration: NarrationConfig = msgspec.field(default_factory=NarrationConfig)

    def __post_init__(self) -> None:
        for name in (
            "robots_period_s",
            "graph_period_s",
            "closure_period_s",
            "map_period_s",
            "rate_window_s",
            "stuck_s",
            "stuck_m",
            "recent_closure_s",
            "merge_m",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"views.{name}: expected a positive finite number, got {v}")
        for name in ("trail_nodes", "thumbnail_px", "max_objects"):
            if getattr(self, name) < 1:
                raise ValueError(f"views.{name}: expected >= 1, got {getattr(self, name)}")


@dataclass(frozen=True)
class PlannerView:
    """What the task planners (``gcs/tasking``) show, all optional, all in ``map``.

    ``frontiers_in_map`` ``(F, 2)``; ``trajectory_nodes_in_map`` ``(T, 2)`` with
    ``trajectory_edges`` ``(E, 2)`` index pairs; ``goals_in_map`` robot -> ``(2,)``;
    ``tasks`` robot -> a short text whose first word is the task kind (``"explore"``,
    ``"neutralize 3"``, ``"relay"``, ``"idle"``); ``deadlocked`` robot ids.
    """

    frontiers_in_map: FloatArray | None = None
    trajectory_nodes_in_map: FloatArray | None = None
    trajectory_edges: NDArray[np.int64] | None = None
    goals_in_map: Mapping[int, Any] = field(default_factory=dict)
    tasks: Mapping[int, str] = field(default_factory=dict)
    deadlocked: frozenset[int] = frozenset()


@dataclass(frozen=True)
class RobotStatus:
    """One robot's row on the dashboard and its marker on the TOC."""

    robot_id: int
    pose_in_map: FloatArray | None  # (3,) x m, y m, yaw rad; None before its first node
    linked: bool  # its trajectory is tied to ``map`` (else drawn at a weak anchor)
    mode: str
    task: str
    task_kind: str
    battery_frac: float  # nan before telemetry
    last_message_s: float
    last_message_age_s: float
    active_s: float  # mission seconds since its first message
    uplink_bps: float  # nan when the GCS gives no message sizes
    nodes: int
    stuck: bool
    deadlock: bool
    trail_in_map: FloatArray  # (K, 2)
    goal_in_map: FloatArray | None  # (2,)

    @property
    def anomalous(self) -> bool:
        return self.stuck or self.deadlock


@dataclass(frozen=True)
class ObjectSighting:
    """An object the robots reported, merged over sightings; ``thumbnail`` RGB uint8 or None."""

    object_id: int
    kind_name: str  # ObjectKind name in lower case: static_ooi, civilian, hostile, ...
    position_in_map: tuple[float, float]
    first_seen_s: float
    last_seen_s: float
    sightings: int
    robot_id: int
    confidence: float
    thumbnail: NDArray[np.uint8] | None = None


@dataclass(frozen=True)
class GraphPicture:
    """The SLAM graph in ``map``: per-robot node chains (odometry edges drawn as polylines),
    the other edges as segments ``(M, 2, 2)`` by kind, and the recent closures."""

    chains_in_map: dict[int, FloatArray]  # robot -> (N, 2) its poses in order
    segments_in_map: dict[str, FloatArray]  # kind -> (M, 2, 2), kinds other than odometry
    recent_closures_in_map: FloatArray  # (K, 2, 2)
    nodes: int
    edges: dict[str, int]  # kind -> count, odometry included


@dataclass(frozen=True)
class OperatorPicture:
    """Everything the views show at mission time ``time_s`` (module docstring).

    ``map`` / ``graph`` are None when that layer is not due; ``map_version`` counts maps sent.
    """

    time_s: float
    robots: list[RobotStatus]
    objects: list[ObjectSighting]
    hazards: list[tuple[int, str, tuple[float, float]]]  # (hazard id, kind name, position)
    frontiers_in_map: FloatArray
    trajectory_segments_in_map: FloatArray  # (E, 2, 2)
    map: OccupancyMap | None
    map_version: int
    graph: GraphPicture | None
    new_alerts: list[Alert]
    active_alerts: dict[tuple[str, str], int]
    new_events: list[Event]
    top_events: list[Event]
    uplink_total_bps: float
    new_thumbnails: list[int] = field(default_factory=list)  # object ids with a new image


@dataclass
class _RobotWatch:
    first_s: float
    last_s: float
    bytes_window: collections.deque[tuple[float, int]] = field(default_factory=collections.deque)
    telemetry: Telemetry | None = None
    status: TaskStatus | None = None
    positions: collections.deque[tuple[float, float, float]] = field(
        default_factory=collections.deque
    )
    detections: dict[int, int] = field(default_factory=dict)  # detection id -> object id
    metered: bool = False  # observe() was given message sizes


class PictureBuilder:
    """Keeps what the views need beyond the station's state and builds pictures when due.

    ``observe`` is O(1) per message (a detection image is decoded and shrunk once); ``build``
    costs O(robots + objects) plus, when due, O(graph) for the graph and a rasterization for
    the map (skipped when the caller passes the map it already has). ``cpu_s`` accumulates the
    thread CPU seconds spent in ``build`` (``observe`` is not timed: a clock read per message
    would cost more than its work).
    """

    def __init__(self, config: ViewsConfig | None = None) -> None:
        self.config = config or ViewsConfig()
        cfg = self.config
        self.alert_rules = AlertRules(cfg.alerts)
        speaker = Speaker() if cfg.speak else None
        self.alert_log = AlertLog(cfg.alerts.log_size, speaker)
        self.narrator = Narrator(cfg.narration)
        self._robots: dict[int, _RobotWatch] = {}
        self._objects: list[ObjectSighting] = []
        self._new_thumbnails: list[int] = []
        self._last_picture_s = -math.inf
        self._last_graph_s = -math.inf
        self._last_map_s = -math.inf
        self._graph_mark: tuple[int, int, int] | None = None
        self._closure_count = 0
        self._last_map: OccupancyMap | None = None
        self._trails: dict[int, tuple[int, FloatArray]] = {}  # robot -> (last key, trail)
        self.map_version = 0
        self.cpu_s = 0.0
        self.rasterize_cpu_s = 0.0
        self.bad_images = 0

    # ---- input ----------------------------------------------------------------------------

    def observe(
        self,
        robot_id: int,
        msg: object,
        *,
        now_s: float,
        nbytes: int = 0,
        station: GroundStation | None = None,
    ) -> None:
        """Note an uplink message the GCS took (``nbytes`` on the radio). Detections need
        the ``station`` (their pose node's posterior places them in ``map``). Never raises.
        Not timed (a clock read per message would cost more than the work: O(1) updates)."""
        try:
            self._observe(robot_id, msg, float(now_s), int(nbytes), station)
        except Exception:  # the views never stop the GCS: count and go on
            self.bad_images += isinstance(msg, DetectionImage)

    def _observe(
        self, robot_id: int, msg: object, now_s: float, nbytes: int, station: GroundStation | None
    ) -> None:
        w = self._robots.get(robot_id)
        if w is None:
            w = self._robots[robot_id] = _RobotWatch(first_s=now_s, last_s=now_s)
        w.last_s = max(w.last_s, now_s)
        if nbytes > 0:
            w.bytes_window.append((now_s, nbytes))
            w.metered = True
        if isinstance(msg, Telemetry):
            w.telemetry = msg
            x, y = float(msg.pose_in_odom[0]), float(msg.pose_in_odom[1])
            w.positions.append((now_s, x, y))
        elif isinstance(msg, TaskStatus):
            w.status = msg
        elif isinstance(msg, Detection) and station is not None:
            self._on_detection(robot_id, w, msg, now_s, station)
        elif isinstance(msg, DetectionImage):
            self._on_image(robot_id, w, msg)

    def _on_detection(
        self, robot_id: int, w: _RobotWatch, msg: Detection, now_s: float, station: GroundStation
    ) -> None:
        key = station.key_of(robot_id, msg.node_index)
        if key is None or not all(math.isfinite(v) for v in msg.position_in_base):
            return
        xy = transform_points(station.graph.pose(key), np.asarray([msg.position_in_base]))[0]
        kind = _kind_name(msg.kind)
        for i, o in enumerate(self._objects):
            if o.kind_name == kind and math.dist(o.position_in_map, xy) < self.config.merge_m:
                n = o.sightings + 1
                pos = (
                    o.position_in_map[0] + (float(xy[0]) - o.position_in_map[0]) / n,
                    o.position_in_map[1] + (float(xy[1]) - o.position_in_map[1]) / n,
                )
                self._objects[i] = ObjectSighting(
                    o.object_id,
                    kind,
                    pos,
                    o.first_seen_s,
                    now_s,
                    n,
                    robot_id,
                    max(o.confidence, float(msg.confidence)),
                    o.thumbnail,
                )
                w.detections[msg.detection_id] = o.object_id
                return
        if len(self._objects) >= self.config.max_objects:
            return
        oid = len(self._objects) + 1
        self._objects.append(
            ObjectSighting(
                oid,
                kind,
                (float(xy[0]), float(xy[1])),
                now_s,
                now_s,
                1,
                robot_id,
                float(msg.confidence),
            )
        )
        w.detections[msg.detection_id] = oid

    def _on_image(self, robot_id: int, w: _RobotWatch, msg: DetectionImage) -> None:
        oid = w.detections.get(msg.detection_id)
        if oid is None:
            return
        img = cv2.imdecode(np.frombuffer(msg.data, dtype=np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            self.bad_images += 1
            return
        h, wd = img.shape[:2]
        scale = self.config.thumbnail_px / max(h, wd)
        if scale < 1.0:
            img = cv2.resize(
                img,
                (max(1, round(wd * scale)), max(1, round(h * scale))),
                interpolation=cv2.INTER_AREA,
            )
        rgb = np.ascontiguousarray(img[:, :, ::-1], dtype=np.uint8)
        i = oid - 1
        o = self._objects[i]
        self._objects[i] = ObjectSighting(
            o.object_id,
            o.kind_name,
            o.position_in_map,
            o.first_seen_s,
            o.last_seen_s,
            o.sightings,
            o.robot_id,
            o.confidence,
            rgb,
        )
        self._new_thumbnails.append(oid)

    # ---- output ---------------------------------------------------------------------------

    def due(self, now_s: float) -> bool:
        """Whether a picture is due at mission time ``now_s`` (``robots_period_s``)."""
        return now_s - self._last_picture_s >= self.config.robots_period_s

    def build(
        self,
        station: GroundStation,
        now_s: float,
        *,
        occupancy: OccupancyMap | None = None,
        planner: PlannerView | None = None,
        force_layers: bool = False,
    ) -> OperatorPicture:
        """The picture at mission time ``now_s``. ``occupancy``: a map the GCS rasterized
        already (else the station rasterizes when the map is due). ``force_layers``: include
        the graph and the map whatever the schedule (a final picture)."""
        t0 = time.thread_time()
        try:
            return self._build(
                station, float(now_s), occupancy, planner or PlannerView(), force_layers
            )
        finally:
            self.cpu_s += time.thread_time() - t0

    def _build(
        self,
        station: GroundStation,
        now_s: float,
        occupancy: OccupancyMap | None,
        planner: PlannerView,
        force: bool,
    ) -> OperatorPicture:
        cfg = self.config
        self._last_picture_s = now_s
        graph = station.graph
        robots_in_graph = set(graph.robots)
        anchored = graph.anchored_components() if robots_in_graph else set()
        comp = graph.components() if robots_in_graph else {}
        graph_pic = self._graph_picture(station, now_s, force)
        rows: list[RobotStatus] = []
        total_bps = 0.0
        for rid in sorted(set(self._robots) | robots_in_graph):
            w = self._robots.get(rid) or _RobotWatch(first_s=now_s, last_s=-math.inf)
            cutoff = now_s - cfg.rate_window_s
            while w.bytes_window and w.bytes_window[0][0] < cutoff:
                w.bytes_window.popleft()
            span = min(cfg.rate_window_s, max(now_s - w.first_s, 1e-9))
            # nan when the caller never gave sizes: no rate, rather than a false "silent radio"
            bps = 8.0 * sum(b for _, b in w.bytes_window) / span if w.metered else math.nan
            total_bps += 0.0 if math.isnan(bps) else bps
            pose = None
            linked = False
            nodes = 0
            trail = np.zeros((0, 2))
            if rid in robots_in_graph:
                last = graph.last_key(rid)
                pose = np.asarray(graph.pose(last), dtype=np.float64)
                linked = comp.get(last) in anchored
                nodes = _index_of(last) + 1
                trail = self._trail(station, rid, graph_pic)
            tele = w.telemetry
            mode = AutonomyMode(tele.mode).name.lower() if tele is not None else "unknown"
            task = planner.tasks.get(rid) or _task_text(tele, w.status)
            task_kind = task.split()[0] if task else "none"
            while w.positions and w.positions[0][0] < now_s - 2 * cfg.stuck_s:
                w.positions.popleft()
            stuck = _stuck(w.positions, now_s, cfg.stuck_s, cfg.stuck_m, task_kind, mode)
            goal = planner.goals_in_map.get(rid)
            rows.append(
                RobotStatus(
                    robot_id=rid,
                    pose_in_map=pose,
                    linked=linked,
                    mode=mode,
                    task=task,
                    task_kind=task_kind,
                    battery_frac=float(tele.battery_frac) if tele is not None else math.nan,
                    last_message_s=w.last_s,
                    last_message_age_s=max(0.0, now_s - w.last_s),
                    active_s=max(0.0, now_s - w.first_s),
                    uplink_bps=bps,
                    nodes=nodes,
                    stuck=stuck,
                    deadlock=rid in planner.deadlocked,
                    trail_in_map=trail,
                    goal_in_map=None if goal is None else np.asarray(goal, dtype=float)[:2],
                )
            )
        objects = list(self._objects)
        new_alerts = self.alert_rules.evaluate(rows, objects, now_s)
        self.alert_log.extend(new_alerts)
        new_events = self.narrator.update(rows, objects, now_s)
        map_ = self._map_if_due(station, now_s, occupancy, force)
        hazards = [
            (
                h.hazard_id,
                _kind_name(h.kind),
                (float(h.position_in_map[0]), float(h.position_in_map[1])),
            )
            for h in station.hazards
        ]
        thumbs, self._new_thumbnails = self._new_thumbnails, []
        return OperatorPicture(
            time_s=now_s,
            robots=rows,
            objects=objects,
            hazards=hazards,
            frontiers_in_map=_points(planner.frontiers_in_map),
            trajectory_segments_in_map=_segments(
                planner.trajectory_nodes_in_map, planner.trajectory_edges
            ),
            map=map_,
            map_version=self.map_version,
            graph=graph_pic,
            new_alerts=new_alerts,
            active_alerts={k: int(v) for k, v in self.alert_rules.active.items()},
            new_events=new_events,
            top_events=self.narrator.top(now_s),
            uplink_total_bps=total_bps,
            new_thumbnails=thumbs,
        )

    def _trail(
        self, station: GroundStation, rid: int, graph_pic: GraphPicture | None
    ) -> FloatArray:
        """The robot's last ``trail_nodes`` poses: refreshed from the graph picture when one
        is built (the posterior moved), else extended by the new nodes only (O(new))."""
        n = self.config.trail_nodes
        last = station.graph.last_key(rid)
        if graph_pic is not None and rid in graph_pic.chains_in_map:
            trail = graph_pic.chains_in_map[rid][-n:]
            self._trails[rid] = (last, trail)
            return trail
        cached = self._trails.get(rid)
        if cached is not None and cached[0] == last:
            return cached[1]
        # keys of one robot are consecutive pose indices (gcs.graph.keys)
        first = max(last - n + 1, last - _index_of(last))
        if cached is not None:
            first = max(first, cached[0] + 1)
        pts = []
        for k in range(first, last + 1):
            try:
                pts.append(station.graph.pose(k)[:2])
            except Exception:
                continue
        new = np.asarray(pts, dtype=float).reshape(-1, 2)
        trail = new if cached is None else np.concatenate([cached[1], new])[-n:]
        self._trails[rid] = (last, trail)
        return trail

    def _graph_picture(
        self, station: GroundStation, now_s: float, force: bool
    ) -> GraphPicture | None:
        cfg = self.config
        graph = station.graph
        stats = station.stats
        # accepted automatic closures, operator closures (optimizations follow them) and tags
        closures = station.loop_closer.stats.accepted + stats.fiducials
        mark = (stats.pose_nodes, stats.optimizations, stats.fiducials)
        if not graph.robots:
            return None
        since = now_s - self._last_graph_s
        changed = mark != self._graph_mark
        new_closure = closures != self._closure_count
        due = force or (
            changed
            and (since >= cfg.graph_period_s or (new_closure and since >= cfg.closure_period_s))
        )
        if not due:
            return None
        self._graph_mark = mark
        self._closure_count = closures
        self._last_graph_s = now_s
        records = graph.nodes()
        keys = [n.key for n in records]
        xy = np.array([graph.pose(k)[:2] for k in keys], dtype=float).reshape(-1, 2)
        at = {k: i for i, k in enumerate(keys)}
        robot = np.array([n.robot_id for n in records], dtype=np.int64)
        chains = {int(r): xy[robot == r] for r in np.unique(robot)}
        segs: dict[str, list[tuple[int, int]]] = {}
        counts: dict[str, int] = {}
        recent: list[tuple[int, int]] = []
        for e in graph.edges():
            kind = EDGE_KINDS.get(e.provenance)
            if kind is None or e.key_b is None:
                continue
            counts[kind] = counts.get(kind, 0) + 1
            if kind == "odometry":
                continue
            pair = (at[e.key_a], at[e.key_b])
            segs.setdefault(kind, []).append(pair)
            if e.provenance is not Provenance.FIDUCIAL and now_s - e.time_s <= cfg.recent_closure_s:
                recent.append(pair)
        return GraphPicture(
            chains_in_map=chains,
            segments_in_map={k: xy[np.asarray(v, dtype=np.int64)] for k, v in segs.items()},
            recent_closures_in_map=(
                xy[np.asarray(recent, dtype=np.int64)] if recent else np.zeros((0, 2, 2))
            ),
            nodes=len(keys),
            edges=counts,
        )

    def _map_if_due(
        self, station: GroundStation, now_s: float, occupancy: OccupancyMap | None, force: bool
    ) -> OccupancyMap | None:
        if not force and now_s - self._last_map_s < self.config.map_period_s:
            return None
        if not station.graph.robots:
            return None
        self._last_map_s = now_s
        if occupancy is None:
            t0 = time.thread_time()
            occupancy = station.rasterize()
            self.rasterize_cpu_s += time.thread_time() - t0
        if not isinstance(occupancy, OccupancyMap):
            # refused before it is kept: a bad map kept as the last one failed every later map
            raise TypeError(f"operator picture: occupancy is {type(occupancy).__name__}, "
                            "expected an OccupancyMap")  # fmt: skip
        last = self._last_map
        if (
            not force
            and last is not None
            and last.shape == occupancy.shape
            and last.origin_in_map == occupancy.origin_in_map
            and np.array_equal(last.values, occupancy.values)
        ):
            return None  # unchanged: nothing to send
        self._last_map = occupancy
        self.map_version += 1
        return occupancy


def _index_of(key: int) -> int:
    from gcs.graph.keys import pose_index

    return pose_index(key)


def _kind_name(kind: int) -> str:
    try:
        return ObjectKind(int(kind)).name.lower()
    except ValueError:
        return "unknown"


def _task_text(tele: Telemetry | None, status: TaskStatus | None) -> str:
    """A task line from what the robot reports when the planner says nothing."""
    if status is not None and status.state in (TaskState.ACCEPTED, TaskState.ACTIVE):
        return f"task {status.task_id} {TaskState(status.state).name.lower()}"
    if tele is not None and tele.task_id:
        return f"task {tele.task_id}"
    return "idle"


def _stuck(
    positions: collections.deque[tuple[float, float, float]],
    now_s: float,
    window_s: float,
    min_m: float,
    task_kind: str,
    mode: str,
) -> bool:
    """A robot with something to do that moved less than ``min_m`` over the last ``window_s``
    (from its telemetry's private-frame positions: smooth, no loop-closure jumps)."""
    if task_kind in ("idle", "none") or mode in ("idle", "paused", "disabled", "unknown"):
        return False
    if not positions or now_s - positions[0][0] < window_s:
        return False
    start = now_s - window_s
    x0 = y0 = None
    for t, x, y in positions:
        if t < start:
            continue
        if x0 is None or y0 is None:
            x0, y0 = x, y
        elif math.hypot(x - x0, y - y0) >= min_m:
            return False  # it moved: stop looking
    return x0 is not None


def _points(a: Any) -> FloatArray:
    if a is None:
        return np.zeros((0, 2))
    return np.asarray(a, dtype=float).reshape(-1, 2)


def _segments(nodes: Any, edges: Any) -> FloatArray:
    if nodes is None or edges is None:
        return np.zeros((0, 2, 2))
    n = np.asarray(nodes, dtype=float).reshape(-1, 2)
    e = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if e.size and (e.min() < 0 or e.max() >= len(n)):
        raise ValueError(f"planner trajectory_edges: index outside 0..{len(n) - 1}")
    return n[e]
