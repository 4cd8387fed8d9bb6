"""The rerun adapter: operator pictures to rerun entities and blueprints (paper 6).

The ONLY module of the project that imports rerun (DESIGN section 2). :class:`RerunViews` takes
:class:`~gcs.views.operator_picture.OperatorPicture` snapshots and draws them:

* ``/world/...`` in ``map`` (metres, z up): the map as a :class:`rerun.GridMap` (unexplored
  cells dark: fog of war), robots (points labelled ``id mode task``, heading arrows), trails,
  goals, frontiers, trajectory graph, objects, danger rings (trigger 2.5 m red, blast 10 m /
  5 m orange), the SLAM graph (odometry chains, scan-match / fiducial / operator edges by
  colour, recent closures highlighted), SAGE zoom boxes;
* ``/soc/thumbnails``: the OOI thumbnails mosaic (JPEG) with classifications;
* ``/dashboard/table`` (markdown, one row per robot, anomalies marked), ``/dashboard/radio/*``
  (uplink bit/s: the total and one series per robot), ``/alerts`` (text log with severity);
* ``/sage/log`` (narrated events) and ``/sage/slot_<i>`` (the top four events' zoomed views,
  JPEG, framed in the event's severity colour).

Time is the ``mission`` timeline (seconds). :func:`operator_blueprint` lays these out as four
tabs (TOC, SOC, dashboard, SAGE) so a viewer comes up arranged.

Never in the GCS's way: :meth:`RerunViews.publish` only hands the picture to a worker thread
(a mailbox of ``queue_size`` pictures, the oldest dropped and counted when the viewer side
lags), so it costs microseconds and never blocks. The worker opens the sinks (a ``connect``
target is probed first with a short TCP connect: rerun's own gRPC connect waits 5 s), draws,
and catches everything: a failure is logged once per kind and counted in :attr:`stats`; an
unreachable viewer is retried every ``retry_s`` (wall) while no file sink is attached. Every
failure is also kept, by kind, for the GCS to take (:meth:`RerunViews.take_failures`) and put
in its journal (paper 7: the logs say when the operators could not see what the GCS knew).
"""

from __future__ import annotations

import collections
import logging
import math
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import cv2
import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from gcs.mapping.rasterization import OccupancyMap
from gcs.views.narration import TRIGGER_M, Event, blast_radius_m
from gcs.views.operator_picture import OperatorPicture, RobotStatus
from gcs.views.render import FOG, FREE, KIND_RGB, WALL, render_region, thumbnail_mosaic

__all__ = [
    "EDGE_RGB",
    "RerunViews",
    "SinkSpec",
    "ViewFailure",
    "ViewsStats",
    "operator_blueprint",
    "parse_sink",
]

log = logging.getLogger("magic.gcs.views")

DEFAULT_GRPC_PORT = 9876

#: SOC edge colours by kind (paper 6.1: the operator reads the graph's topology).
EDGE_RGB = {
    "odometry": (150, 150, 150),
    "scan_match": (0, 200, 80),
    "fiducial": (60, 120, 255),
    "operator": (255, 0, 200),
}
_SEVERITY_RGB = {1: (120, 120, 120), 2: (255, 160, 0), 3: (230, 0, 0)}
_Z_MAP, _Z_GRAPH, _Z_MARK = -0.05, 0.05, 0.2
_TOP_SLOTS = 4


@dataclass(frozen=True)
class SinkSpec:
    """Where pictures go: ``kind`` in spawn, connect, save, web, memory; ``target`` a gRPC URL
    (connect), a file path (save), or empty."""

    kind: str
    target: str = ""


def parse_sink(spec: str) -> SinkSpec:
    """``"spawn"``, ``"connect"`` / ``"connect HOST:PORT"`` / ``"connect rerun+http://..."``,
    ``"save FILE.rrd"``, ``"web"``, ``"memory"`` -> :class:`SinkSpec`; a clear ValueError else."""
    head, _, rest = spec.strip().partition(" ")
    rest = rest.strip()
    if head == "spawn" or head == "web" or head == "memory":
        if rest:
            raise ValueError(f"rerun sink {spec!r}: {head} takes no argument")
        return SinkSpec(head)
    if head == "connect":
        addr = rest or f"127.0.0.1:{DEFAULT_GRPC_PORT}"
        url = addr if "://" in addr else f"rerun+http://{addr}/proxy"
        parsed = urlparse(url)
        if not parsed.hostname or parsed.port is None:
            raise ValueError(f"rerun sink {spec!r}: expected HOST:PORT or rerun+http://HOST:PORT")
        return SinkSpec("connect", url)
    if head == "save":
        if not rest:
            raise ValueError(f"rerun sink {spec!r}: save needs a FILE.rrd")
        parent = Path(rest).expanduser().resolve().parent
        if not parent.is_dir():
            raise ValueError(f"rerun sink {spec!r}: directory {parent} does not exist")
        return SinkSpec("save", str(Path(rest).expanduser()))
    raise ValueError(
        f"rerun sink {spec!r}: expected spawn, connect [ADDR], save FILE.rrd, web or memory"
    )


@dataclass(frozen=True)
class ViewFailure:
    """Failures of one kind since the GCS last took them: ``kind`` (a sink's kind, ``open``,
    ``draw``, ``retry``, ``flush``), the first one's ``text``, how many (``count``) and the
    wall seconds (``time.time``) of the first."""

    kind: str
    text: str
    count: int
    first_wall_s: float


@dataclass
class ViewsStats:
    """What the adapter did: pictures taken / drawn / dropped (the worker lagged), draw
    failures, sink failures (by kind of sink), wall and thread-CPU seconds of drawing (and
    thread-CPU seconds by layer)."""

    published: int = 0
    drawn: int = 0
    dropped: int = 0
    draw_errors: int = 0
    sink_failures: collections.Counter[str] = field(default_factory=collections.Counter)
    draw_cpu_s: float = 0.0
    layer_cpu_s: collections.defaultdict[str, float] = field(
        default_factory=lambda: collections.defaultdict(float)
    )
    draw_wall_s: float = 0.0
    publish_wall_s: float = 0.0


def operator_blueprint() -> rrb.Blueprint:
    """Four tabs: TOC (bird's eye), SOC (SLAM graph + thumbnails), dashboard, SAGE."""
    toc = rrb.Spatial3DView(
        name="TOC: task operator",
        origin="/world",
        contents=[
            "+ /world/map",
            "+ /world/robots/**",
            "+ /world/trails/**",
            "+ /world/goals/**",
            "+ /world/frontiers",
            "+ /world/trajectory_graph",
            "+ /world/objects",
            "+ /world/danger/**",
        ],
        line_grid=False,
    )
    soc = rrb.Horizontal(
        rrb.Spatial3DView(
            name="SOC: SLAM graph",
            origin="/world",
            contents=[
                "+ /world/map",
                "+ /world/graph/**",
                "+ /world/objects",
                "+ /world/robots/**",
            ],
            line_grid=False,
        ),
        rrb.Spatial2DView(name="OOI thumbnails", origin="/soc"),
        column_shares=[3, 1],
        name="SOC: sensor operator",
    )
    dashboard = rrb.Vertical(
        rrb.TextDocumentView(name="robots", origin="/dashboard/table"),
        rrb.Horizontal(
            rrb.TimeSeriesView(name="uplink bit/s", origin="/dashboard/radio"),
            rrb.TextLogView(name="alerts", origin="/alerts"),
        ),
        row_shares=[2, 1],
        name="Status dashboard",
    )
    sage = rrb.Horizontal(
        rrb.Spatial3DView(
            name="SAGE overview",
            origin="/world",
            contents=[
                "+ /world/map",
                "+ /world/robots/**",
                "+ /world/objects",
                "+ /world/danger/**",
                "+ /world/sage/**",
            ],
            line_grid=False,
        ),
        rrb.Vertical(
            rrb.Grid(
                *[
                    rrb.Spatial2DView(name=f"event {i + 1}", origin=f"/sage/slot_{i}")
                    for i in range(_TOP_SLOTS)
                ],
                grid_columns=2,
            ),
            rrb.TextLogView(name="narration", origin="/sage/log"),
            row_shares=[3, 1],
        ),
        column_shares=[3, 2],
        name="SAGE",
    )
    return rrb.Blueprint(rrb.Tabs(toc, soc, dashboard, sage), collapse_panels=True)


def _viewer_executable() -> str | None:
    """The rerun viewer installed beside this Python (rerun-sdk ships it in the venv's
    ``bin/``), found when the venv is not activated (``.venv/bin/magic gcs --rerun spawn``
    with ``bin/`` not on PATH); None: rerun searches PATH."""
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.is_file() else None


class RerunViews:
    """Draws operator pictures into rerun sinks from a worker thread (module docstring).

    ``sinks``: one spec or several (:func:`parse_sink`), e.g. ``["spawn", "save run.rrd"]``.
    ``threaded=False`` draws inside :meth:`publish` (tests, measurements). ``zoom_px``: side of
    a SAGE zoom image; ``zoom_period_s``: a zoom slot is redrawn at most this often (mission
    seconds) unless its event changed. ``radio_flush_s``: the uplink time series are buffered and
    sent as columns this often (mission seconds; cheaper than a log call per robot per picture).
    ``slow_period_s``: trails, goals, frontiers and the trajectory graph are redrawn at most this
    often (with every graph picture otherwise); objects, rings and SAGE boxes only on change.
    :meth:`close` flushes and ends the worker (bounded).
    """

    def __init__(
        self,
        sinks: str | list[str],
        *,
        application_id: str = "magic_gcs",
        recording_id: str | None = None,
        threaded: bool = True,
        queue_size: int = 2,
        zoom_px: int = 192,
        zoom_period_s: float = 30.0,
        retry_s: float = 10.0,
        radio_flush_s: float = 5.0,
        slow_period_s: float = 5.0,
        probe_timeout_s: float = 0.3,
    ) -> None:
        specs = [sinks] if isinstance(sinks, str) else list(sinks)
        if not specs:
            raise ValueError("rerun views: no sink given")
        self.sinks = [parse_sink(s) for s in specs]
        self.stats = ViewsStats()
        self.zoom_px = zoom_px
        self.zoom_period_s = zoom_period_s
        self.retry_s = retry_s
        self.probe_timeout_s = probe_timeout_s
        self.blueprint = operator_blueprint()
        self.rec = rr.RecordingStream(
            application_id, recording_id=recording_id, send_properties=False
        )
        self.rec.set_log_time_enabled(False)  # the mission timeline is the one that matters
        self.rec.set_log_tick_enabled(False)
        self._memory: Any = None
        self._live_ok = False
        self._next_retry = 0.0
        self._reported: set[str] = set()
        # failures not yet taken by the GCS (take_failures): kind -> (first text, count, wall)
        self._failures: dict[str, tuple[str, int, float]] = {}
        self._failures_lock = threading.Lock()
        self._last_map: OccupancyMap | None = None
        self._slots: list[int | None] = [None] * _TOP_SLOTS
        self._slot_drawn_s = [-math.inf] * _TOP_SLOTS
        self._zooms: dict[int, tuple[float, rr.EncodedImage]] = {}  # event -> (drawn s, jpeg)
        self._radio_index: dict[int, int] = {}  # robot id -> its series (after the total)
        self._radio_rows: list[tuple[float, float, list[float]]] = []
        self._radio_named = -1
        self._marks: dict[str, Any] = {}  # layer -> what was drawn last (skip if unchanged)
        self._drawn_s: dict[str, float] = {}
        self.slow_period_s = slow_period_s
        self._radio_sent_s = -math.inf
        self.radio_flush_s = radio_flush_s
        self._mailbox: collections.deque[OperatorPicture] = collections.deque()
        self._queue_size = max(1, queue_size)
        self._cv = threading.Condition()
        self._closing = False
        self._thread: threading.Thread | None = None
        self._opened = False
        if threaded:
            self._thread = threading.Thread(target=self._run, name="rerun-views", daemon=True)
            self._thread.start()
        else:
            self._open()

    # ---- GCS side ---------------------------------------------------------------------------

    def publish(self, picture: OperatorPicture, now_s: float | None = None) -> None:
        """Hand a picture over; never raises, never blocks (threaded) (module docstring)."""
        t0 = time.perf_counter()
        self.stats.published += 1
        if self._thread is None:
            self._draw_safely(picture)
        else:
            with self._cv:
                while len(self._mailbox) >= self._queue_size:
                    dropped = self._mailbox.popleft()
                    self.stats.dropped += 1
                    if dropped.map is not None or dropped.graph is not None:
                        # a dropped layer must not be lost: the next picture carries it
                        picture = _carry_layers(dropped, picture)
                self._mailbox.append(picture)
                self._cv.notify()
        self.stats.publish_wall_s += time.perf_counter() - t0

    def close(self, timeout_s: float = 5.0) -> None:
        """Draw what is queued, flush the sinks (bounded by ``timeout_s``) and stop."""
        if self._thread is not None:
            with self._cv:
                self._closing = True
                self._cv.notify()
            self._thread.join(timeout_s)
            self._thread = None
        else:
            self._flush(timeout_s)

    def memory_bytes(self) -> bytes:
        """The recording so far, as .rrd bytes (``memory`` sink only)."""
        if self._memory is None:
            raise ValueError("rerun views: no memory sink")
        self.rec.flush(timeout_sec=5.0)
        data: bytes = self._memory.drain_as_bytes()
        return data

    # ---- worker side ------------------------------------------------------------------------

    def _run(self) -> None:
        self._open()
        while True:
            with self._cv:
                while not self._mailbox and not self._closing:
                    self._cv.wait(timeout=1.0)
                pictures = list(self._mailbox)
                self._mailbox.clear()
                closing = self._closing
            for p in pictures:
                self._draw_safely(p)
            if closing and not pictures:
                break
        self._flush(2.0)

    def take_failures(self) -> list[ViewFailure]:
        """The failures since the last call, one per kind (oldest kind first), and forget them.
        Thread-safe: the drawing thread reports, the GCS's thread takes."""
        with self._failures_lock:
            pending, self._failures = self._failures, {}
        return [ViewFailure(k, text, n, wall) for k, (text, n, wall) in pending.items()]

    def _report(self, kind: str, text: str) -> None:
        self.stats.sink_failures[kind] += 1
        with self._failures_lock:
            first = self._failures.get(kind)
            self._failures[kind] = (
                (text, 1, time.time()) if first is None else (first[0], first[1] + 1, first[2])
            )
        if kind not in self._reported:
            self._reported.add(kind)
            log.warning("rerun views: %s (the GCS goes on; reported once)", text)

    def _open(self) -> None:
        """Attach the sinks; anything that fails is reported and left out."""
        if self._opened:
            return
        self._opened = True
        bp = self.blueprint
        file_sinks: list[Any] = []
        for s in self.sinks:
            try:
                if s.kind == "save":
                    file_sinks.append(rr.FileSink(s.target))
                elif s.kind == "memory":
                    self._memory = self.rec.memory_recording()
            except Exception as err:
                self._report(s.kind, f"{s.kind} sink failed: {type(err).__name__}: {err}")
        live = [s for s in self.sinks if s.kind in ("spawn", "connect", "web")]
        try:
            if file_sinks and not live:
                self.rec.set_sinks(*file_sinks, default_blueprint=bp)
            elif file_sinks:
                url = self._live_url(live[0])
                if url is not None:
                    self.rec.set_sinks(*file_sinks, rr.GrpcSink(url), default_blueprint=bp)
                    self._live_ok = True
                else:
                    self.rec.set_sinks(*file_sinks, default_blueprint=bp)
            elif live:
                self._connect_live(live[0])
            if self._memory is not None:
                self.rec.send_blueprint(bp)
        except Exception as err:
            self._report("open", f"opening sinks failed: {type(err).__name__}: {err}")
        try:
            self.rec.log("/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        except Exception as err:
            self._report("draw", f"drawing failed: {type(err).__name__}: {err}")

    def _live_url(self, spec: SinkSpec) -> str | None:
        """gRPC URL of a live viewer, starting it for spawn/web; None if unreachable."""
        try:
            if spec.kind == "spawn":
                # recording=: without it rerun checks the global recording, which this
                # station never makes, and ignores the call ("Rerun is disabled")
                rr.spawn(
                    port=DEFAULT_GRPC_PORT,
                    connect=False,
                    hide_welcome_screen=True,
                    recording=self.rec,
                    executable_path=_viewer_executable(),
                )
                url = f"rerun+http://127.0.0.1:{DEFAULT_GRPC_PORT}/proxy"
            elif spec.kind == "web":
                url = self.rec.serve_grpc(default_blueprint=self.blueprint)
                rr.serve_web_viewer(open_browser=False, connect_to=url)
                return url
            else:
                url = spec.target
        except Exception as err:
            self._report(spec.kind, f"{spec.kind} failed: {type(err).__name__}: {err}")
            return None
        # a freshly spawned viewer needs a moment to listen
        if not self._reachable(url, 3.0 if spec.kind == "spawn" else 0.0):
            self._report(spec.kind, f"viewer at {url} unreachable; retrying every {self.retry_s} s")
            return None
        return url

    def _reachable(self, url: str, wait_s: float = 0.0) -> bool:
        """Whether a TCP connection to the viewer's port opens (within ``wait_s``)."""
        parsed = urlparse(url)
        host, port = parsed.hostname or "127.0.0.1", parsed.port or DEFAULT_GRPC_PORT
        deadline = time.monotonic() + wait_s
        while True:
            try:
                with socket.create_connection((host, port), timeout=self.probe_timeout_s):
                    return True
            except OSError:
                if time.monotonic() >= deadline:
                    return False
                time.sleep(0.2)

    def _connect_live(self, spec: SinkSpec) -> None:
        self._next_retry = time.monotonic() + self.retry_s
        if spec.kind == "web":
            url = self._live_url(spec)
            self._live_ok = url is not None
            return
        url = self._live_url(spec)
        if url is None:
            return
        self.rec.connect_grpc(url, default_blueprint=self.blueprint)
        self._live_ok = True

    def _maybe_retry(self) -> None:
        live = [s for s in self.sinks if s.kind in ("spawn", "connect")]
        has_file = any(s.kind in ("save", "memory") for s in self.sinks)
        if self._live_ok or not live or has_file or time.monotonic() < self._next_retry:
            return
        try:
            self._connect_live(live[0])
        except Exception as err:
            self._report("retry", f"reconnect failed: {type(err).__name__}: {err}")

    def _flush(self, timeout_s: float) -> None:
        """Send what is buffered and end the sinks: a file gets its footer (an index readers
        use). Skipped for an unreachable viewer, whose ending would wait out rerun's 5 s."""
        try:
            self._flush_radio()
            self.rec.flush(timeout_sec=timeout_s)
            live = any(s.kind in ("spawn", "connect", "web") for s in self.sinks)
            if self._live_ok or not live:
                self.rec.disconnect()
        except Exception as err:
            self._report("flush", f"flush failed: {type(err).__name__}: {err}")

    def _draw_safely(self, picture: OperatorPicture) -> None:
        self._maybe_retry()
        if not self._live_ok and not any(s.kind in ("save", "memory") for s in self.sinks):
            self.stats.dropped += 1  # nowhere to send: drawing would only fill a buffer
            return
        t0, c0 = time.perf_counter(), time.thread_time()
        try:
            self._draw(picture)
            self.stats.drawn += 1
        except Exception as err:
            self.stats.draw_errors += 1
            self._report("draw", f"drawing failed: {type(err).__name__}: {err}")
        finally:
            self.stats.draw_cpu_s += time.thread_time() - c0
            self.stats.draw_wall_s += time.perf_counter() - t0

    # ---- drawing ----------------------------------------------------------------------------

    def _draw(self, p: OperatorPicture) -> None:
        self.rec.set_time("mission", duration=float(p.time_s))
        layers: list[tuple[str, Any]] = [("robots", self._draw_robots)]
        if p.map is not None:
            layers.insert(0, ("map", lambda _: self._draw_map(p.map)))  # type: ignore[arg-type]
        layers.append(("objects", self._draw_objects))
        if p.graph is not None:
            layers.append(("graph", self._draw_graph))
        layers += [("dashboard", self._draw_dashboard), ("sage", self._draw_sage)]
        if p.new_thumbnails:
            layers.append(("thumbnails", self._draw_thumbnails))
        for name, draw in layers:
            c0 = time.thread_time()
            draw(p)
            self.stats.layer_cpu_s[name] += time.thread_time() - c0  # type: ignore[assignment]

    def _draw_thumbnails(self, p: OperatorPicture) -> None:
        mosaic = thumbnail_mosaic(p.objects)
        if mosaic is not None:
            self.rec.log("/soc/thumbnails", _jpeg(mosaic))

    def _draw_map(self, m: OccupancyMap) -> None:
        self._last_map = m
        rows, cols = m.shape
        if rows == 0 or cols == 0:
            return
        v = m.values
        gray = np.full(v.shape, FOG, dtype=np.uint8)
        gray[v == 0] = FREE
        gray[v > 0] = WALL
        self.rec.log(
            "/world/map",
            rr.GridMap(
                data=gray.tobytes(),
                format=rr.components.ImageFormat(
                    width=cols, height=rows, color_model="L", channel_datatype="U8"
                ),
                cell_size=float(m.resolution_m),
                translation=[float(m.origin_in_map[0]), float(m.origin_in_map[1]), _Z_MAP],
            ),
        )

    def _draw_robots(self, p: OperatorPicture) -> None:
        rec = self.rec
        placed = [r for r in p.robots if r.pose_in_map is not None]
        if placed:
            pose = np.array([r.pose_in_map for r in placed], dtype=np.float64)
            xyz = np.column_stack([pose[:, :2], np.full(len(placed), _Z_MARK)])
            colors = [_robot_rgb(r) for r in placed]
            rec.log(
                "/world/robots",
                rr.Points3D(
                    xyz,
                    radii=0.35,
                    colors=colors,
                    labels=[f"{r.robot_id} {r.mode} {r.task}" for r in placed],
                    show_labels=True,
                ),
            )
            vec = np.column_stack([np.cos(pose[:, 2]), np.sin(pose[:, 2]), np.zeros(len(placed))])
            rec.log("/world/robots/heading", rr.Arrows3D(origins=xyz, vectors=vec, colors=colors))
        # slow layers (trails, goals, frontiers, trajectory graph): with every graph picture,
        # else at most every slow_period_s when something changed
        mark = (
            tuple((r.robot_id, r.nodes) for r in placed),
            len(p.frontiers_in_map),
            len(p.trajectory_segments_in_map),
        )
        t = float(p.time_s)
        if p.graph is None and (
            mark == self._marks.get("plan")
            or t - self._drawn_s.get("plan", -math.inf) < self.slow_period_s
        ):
            self._log_radio(p)
            return
        self._marks["plan"] = mark
        self._drawn_s["plan"] = t
        strips = [_xyz(r.trail_in_map, _Z_GRAPH) for r in placed if len(r.trail_in_map) >= 2]
        rec.log("/world/trails", rr.LineStrips3D(strips, colors=(90, 200, 90), radii=0.04))
        goals = np.array(
            [[r.pose_in_map[:2], r.goal_in_map[:2]] for r in placed if r.goal_in_map is not None],  # type: ignore[index]
            dtype=np.float64,
        )
        rec.log(
            "/world/goals",
            rr.LineStrips3D(_segs3(goals, _Z_MARK), colors=(0, 120, 255), radii=0.03),
        )
        if len(p.frontiers_in_map):
            rec.log(
                "/world/frontiers",
                rr.Points3D(_xyz(p.frontiers_in_map, _Z_GRAPH), colors=(0, 210, 210), radii=0.15),
            )
        if len(p.trajectory_segments_in_map):
            segs = _segs3(p.trajectory_segments_in_map, _Z_GRAPH)
            rec.log(
                "/world/trajectory_graph", rr.LineStrips3D(segs, colors=(0, 160, 160), radii=0.03)
            )
        self._log_radio(p)

    def _log_radio(self, p: OperatorPicture) -> None:
        """Uplink bit/s of every robot and the total: one multi-series entity, buffered and
        sent as columns every ``radio_flush_s`` (one call per flush, whatever the team size)."""
        t = float(p.time_s)
        for r in p.robots:
            if r.robot_id not in self._radio_index:
                self._radio_index[r.robot_id] = len(self._radio_index)
        row = [math.nan] * len(self._radio_index)
        for r in p.robots:
            row[self._radio_index[r.robot_id]] = r.uplink_bps
        self._radio_rows.append((t, p.uplink_total_bps, row))
        if t - self._radio_sent_s >= self.radio_flush_s:
            self._flush_radio()
            self._radio_sent_s = t

    def _flush_radio(self) -> None:
        if not self._radio_rows:
            return
        n = len(self._radio_index)
        if n != self._radio_named:
            names = ["total"] + [f"robot {rid}" for rid in self._radio_index]
            self.rec.log("/dashboard/radio", rr.SeriesLines(names=names), static=True)
            self._radio_named = n
        values = np.full((len(self._radio_rows), n + 1), np.nan)
        for i, (_, total, row) in enumerate(self._radio_rows):
            values[i, 0] = total
            values[i, 1 : 1 + len(row)] = row
        self.rec.send_columns(
            "/dashboard/radio",
            indexes=[rr.TimeColumn("mission", duration=[r[0] for r in self._radio_rows])],
            columns=rr.Scalars.columns(scalars=values),
        )
        self._radio_rows = []

    def _draw_objects(self, p: OperatorPicture) -> None:
        rec = self.rec
        mark = (tuple((o.object_id, o.sightings) for o in p.objects), tuple(p.hazards))
        if mark == self._marks.get("objects"):
            return  # unchanged: the viewer keeps showing the latest
        self._marks["objects"] = mark
        if p.objects:
            xyz = np.array([[*o.position_in_map, _Z_MARK] for o in p.objects])
            rec.log(
                "/world/objects",
                rr.Points3D(
                    xyz,
                    colors=[KIND_RGB.get(o.kind_name, KIND_RGB["unknown"]) for o in p.objects],
                    radii=[0.4 if blast_radius_m(o.kind_name) else 0.25 for o in p.objects],
                    labels=[f"{o.object_id} {o.kind_name}" for o in p.objects],
                ),
            )
        danger = [(pos, b) for _, kind, pos in p.hazards if (b := blast_radius_m(kind))]
        trig = np.array([_circle(pos, TRIGGER_M) for pos, _ in danger]).reshape(-1, 33, 3)
        blast = np.array([_circle(pos, b) for pos, b in danger]).reshape(-1, 33, 3)
        rec.log("/world/danger/trigger", rr.LineStrips3D(trig, colors=(255, 0, 0), radii=0.05))
        rec.log("/world/danger/blast", rr.LineStrips3D(blast, colors=(255, 140, 0), radii=0.05))

    def _draw_graph(self, p: OperatorPicture) -> None:
        g = p.graph
        assert g is not None
        rec = self.rec
        chains = [_xyz(c, _Z_GRAPH) for c in g.chains_in_map.values() if len(c) >= 2]
        rec.log(
            "/world/graph/odometry",
            rr.LineStrips3D(chains, colors=EDGE_RGB["odometry"], radii=0.02),
        )
        for kind in ("scan_match", "fiducial", "operator"):
            segs = g.segments_in_map.get(kind, np.zeros((0, 2, 2)))
            rec.log(
                f"/world/graph/{kind}",
                rr.LineStrips3D(_segs3(segs, _Z_GRAPH), colors=EDGE_RGB[kind], radii=0.03),
            )
        rec.log(
            "/world/graph/recent_closures",
            rr.LineStrips3D(
                _segs3(g.recent_closures_in_map, _Z_GRAPH + 0.02),
                colors=(255, 230, 0),
                radii=0.08,
            ),
        )

    def _draw_dashboard(self, p: OperatorPicture) -> None:
        rec = self.rec
        rec.log(
            "/dashboard/table", rr.TextDocument(_dashboard_markdown(p), media_type="text/markdown")
        )
        for a in p.new_alerts:
            level = ("INFO", "WARN", "ERROR")[int(a.severity)]
            rec.log("/alerts", rr.TextLog(f"{a.subject}: {a.text}", level=level))
        for e in p.new_events:
            level = ("DEBUG", "INFO", "WARN", "ERROR")[min(3, e.severity)]
            rec.log("/sage/log", rr.TextLog(e.title(), level=level))

    def _draw_sage(self, p: OperatorPicture) -> None:
        rec = self.rec
        top = p.top_events[:_TOP_SLOTS]
        top_mark = tuple((e.event_id, e.count, e.severity) for e in top)
        if top_mark != self._marks.get("sage"):
            self._marks["sage"] = top_mark
            boxes = np.array([_square(e.zoom_center_in_map, e.zoom_half_m) for e in top])
            rec.log(
                "/world/sage/boxes",
                rr.LineStrips3D(
                    boxes.reshape(-1, 5, 3),
                    colors=[_SEVERITY_RGB.get(e.severity, (255, 255, 255)) for e in top],
                    radii=0.08,
                    labels=[f"{i + 1}: {e.kind.value}" for i, e in enumerate(top)],
                ),
            )
        for i in range(_TOP_SLOTS):
            e = top[i] if i < len(top) else None
            slot = None if e is None else e.event_id
            age_s = p.time_s - self._slot_drawn_s[i]
            # a new event is drawn at once; the same one again (merged, or robots moved) only
            # after zoom_period_s
            if slot == self._slots[i] and (e is None or age_s < self.zoom_period_s):
                continue
            self._slots[i] = slot
            self._slot_drawn_s[i] = p.time_s
            if e is None:
                rec.log(f"/sage/slot_{i}", rr.Clear(recursive=True))
                continue
            cached = self._zooms.get(e.event_id)
            if cached is None or p.time_s - cached[0] >= self.zoom_period_s:
                # an event moving between slots keeps its image (redrawn every zoom_period_s)
                img = render_region(
                    p, p.map or self._last_map, e.zoom_center_in_map, e.zoom_half_m, px=self.zoom_px
                )
                _frame(img, e)
                cached = self._zooms[e.event_id] = (p.time_s, _jpeg(img))
            rec.log(f"/sage/slot_{i}", cached[1])
        live = {e.event_id for e in top}
        for k in [k for k in self._zooms if k not in live]:
            del self._zooms[k]


def _carry_layers(old: OperatorPicture, new: OperatorPicture) -> OperatorPicture:
    """``new`` with ``old``'s map / graph where ``new`` has none (layers are not lost)."""
    import dataclasses

    return dataclasses.replace(
        new,
        map=new.map if new.map is not None else old.map,
        graph=new.graph if new.graph is not None else old.graph,
        new_alerts=old.new_alerts + new.new_alerts,
        new_events=old.new_events + new.new_events,
        new_thumbnails=old.new_thumbnails + new.new_thumbnails,
    )


def _robot_rgb(r: RobotStatus) -> tuple[int, int, int]:
    if r.anomalous:
        return (230, 0, 0)
    return (0, 190, 0) if r.linked else (240, 180, 0)


def _xyz(xy: Any, z: float) -> np.ndarray:
    a = np.asarray(xy, dtype=np.float32).reshape(-1, 2)
    return np.column_stack([a, np.full(len(a), z, dtype=np.float32)])


def _segs3(segs: Any, z: float) -> np.ndarray:
    """``(M, 2, 2)`` segments as ``(M, 2, 3)`` float32 at height ``z`` (rerun's numpy path)."""
    a = np.asarray(segs, dtype=np.float32).reshape(-1, 2, 2)
    return np.concatenate([a, np.full((len(a), 2, 1), z, dtype=np.float32)], axis=2)


def _circle(center: tuple[float, float], r_m: float, n: int = 32) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * math.pi, n + 1)
    return _xyz(np.column_stack([center[0] + r_m * np.cos(t), center[1] + r_m * np.sin(t)]), 0.1)


def _square(center: tuple[float, float], half: float) -> np.ndarray:
    cx, cy = center
    pts = [
        (cx - half, cy - half),
        (cx + half, cy - half),
        (cx + half, cy + half),
        (cx - half, cy + half),
        (cx - half, cy - half),
    ]
    return _xyz(pts, 0.3)


def _jpeg(rgb: np.ndarray) -> rr.EncodedImage:
    ok, buf = cv2.imencode(
        ".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 80]
    )
    if not ok:
        raise ValueError("jpeg encoding failed")
    return rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg")


def _frame(img: np.ndarray, e: Event) -> None:
    """Colour-code a zoom by severity and caption it (paper 6.4.2: colour, type, robot)."""
    color = _SEVERITY_RGB.get(e.severity, (255, 255, 255))
    cv2.rectangle(img, (0, 0), (img.shape[1] - 1, img.shape[0] - 1), color, 4)
    cv2.rectangle(img, (0, 0), (img.shape[1] - 1, 16), color, -1)
    cv2.putText(
        img,
        e.title()[:40],
        (4, 12),
        cv2.FONT_HERSHEY_SIMPLEX,
        0.38,
        (255, 255, 255),
        1,
        cv2.LINE_AA,
    )


def _dashboard_markdown(p: OperatorPicture) -> str:
    """One row per robot (paper 6.3); anomalies in bold with a warning mark."""
    lines = [
        f"**mission {p.time_s:.0f} s** · uplink {p.uplink_total_bps / 1000:.1f} kbit/s · "
        f"{len(p.active_alerts)} active alert(s)",
        "",
        "| robot | mode | task | last msg | uplink | battery | nodes | linked | state |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    alerted = {k[1] for k in p.active_alerts}
    for r in p.robots:
        state = "deadlock" if r.deadlock else ("stuck" if r.stuck else "ok")
        bat = "?" if not math.isfinite(r.battery_frac) else f"{100 * r.battery_frac:.0f} %"
        cells = [
            str(r.robot_id),
            r.mode,
            r.task,
            f"{r.last_message_age_s:.0f} s",
            "?" if math.isnan(r.uplink_bps) else f"{r.uplink_bps:.0f} bit/s",
            bat,
            str(r.nodes),
            "yes" if r.linked else "no",
            state,
        ]
        if f"robot {r.robot_id}" in alerted or r.anomalous:
            cells = [f"**{c}**" for c in cells]
            cells[0] = "⚠ " + cells[0]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
