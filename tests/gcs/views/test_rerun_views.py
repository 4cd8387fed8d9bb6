"""The rerun adapter: sinks, blueprint, a saved recording read back, an unreachable viewer."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import numpy as np
import pytest
import rerun.blueprint as rrb
from rerun.chunk import RrdReader

from compression import DEFAULT_CODEC, encode_grid
from gcs.ground_station import GroundStation
from gcs.views.operator_picture import PictureBuilder, PlannerView, ViewsConfig
from gcs.views.rerun_views import RerunViews, SinkSpec, operator_blueprint, parse_sink
from protocol.messages import (
    AutonomyMode,
    Detection,
    ObjectKind,
    PoseNode,
    Telemetry,
    TerrainGrid,
    covariance_to_upper,
)

INTEL = Path(__file__).resolve().parents[4] / "shared/datasets/laser/intel-corrected.log.gz"
COV = covariance_to_upper(np.diag([0.01, 0.01, 0.001]))
RES_M = 0.1


def _grid(node_index: int) -> TerrainGrid:
    """A wall 2 m left of the robot, 4 m long, in a 6 m x 6 m grid centred on it."""
    grid = np.zeros((60, 60), dtype=bool)
    grid[50, 10:50] = True
    return TerrainGrid(node_index, RES_M, encode_grid(grid, DEFAULT_CODEC, origin_cells=(-30, -30)))


def _feed(station: GroundStation, builder: PictureBuilder, robots: int, nodes: int) -> float:
    """Robots driving straight lines (robot r along y = 5 r in its own frame)."""
    now = 0.0
    for i in range(nodes):
        for r in range(robots):
            now = float(i)
            pose = (float(i), 0.0, 0.0)
            msgs: list[object] = [
                PoseNode(i, now, pose, (1.0, 0.0, 0.0), COV),
                _grid(i),
                Telemetry(now, pose, (1.0, 0.0), (0.0, 0.0), 0.9, AutonomyMode.AUTONOMOUS, 1),
            ]
            if i == 3 and r == 0:
                msgs.append(
                    Detection(
                        7,
                        i,
                        now,
                        ObjectKind.STATIC_OOI,
                        (2.0, 0.0),
                        (0.01, 0.0, 0.01),
                        0.3,
                        1.0,
                        0.9,
                    )
                )
            for m in msgs:
                station.handle(r, m, now_s=now)
                builder.observe(r, m, now_s=now, nbytes=100, station=station)
        station.step(now_s=now)
    return now


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_parse_sink() -> None:
    assert parse_sink("spawn") == SinkSpec("spawn")
    assert parse_sink("connect") == SinkSpec("connect", "rerun+http://127.0.0.1:9876/proxy")
    assert parse_sink("connect 10.0.0.2:9000").target == "rerun+http://10.0.0.2:9000/proxy"
    assert parse_sink("connect rerun+http://h:1/proxy").target == "rerun+http://h:1/proxy"
    assert parse_sink("save /tmp/x.rrd") == SinkSpec("save", "/tmp/x.rrd")
    for bad, what in [
        ("save", "needs a FILE"),
        ("connect nohost", "HOST:PORT"),
        ("save /no/such/dir/x.rrd", "does not exist"),
        ("print", "expected spawn"),
        ("spawn now", "no argument"),
    ]:
        with pytest.raises(ValueError, match=what):
            parse_sink(bad)


def test_blueprint_has_the_four_operator_tabs() -> None:
    bp = operator_blueprint()
    assert isinstance(bp, rrb.Blueprint)
    tabs = bp.root_container
    assert isinstance(tabs, rrb.Tabs)
    names = [c.name for c in tabs.contents]  # type: ignore[union-attr]
    assert names == ["TOC: task operator", "SOC: sensor operator", "Status dashboard", "SAGE"]


def test_saved_recording_holds_map_robots_graph_and_events(tmp_path: Path) -> None:
    station = GroundStation()
    builder = PictureBuilder(ViewsConfig(graph_period_s=1.0, map_period_s=1.0))
    path = tmp_path / "views.rrd"
    views = RerunViews(f"save {path}", threaded=False)
    now = _feed(station, builder, robots=3, nodes=6)
    planner = PlannerView(
        frontiers_in_map=np.array([[1.0, 1.0], [2.0, 2.0]]),
        trajectory_nodes_in_map=np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]]),
        trajectory_edges=np.array([[0, 1], [1, 2]]),
        goals_in_map={0: (4.0, 4.0)},
        tasks={0: "neutralize 1", 1: "explore", 2: "explore"},
    )
    pic = builder.build(station, now, planner=planner, force_layers=True)
    assert pic.graph is not None and pic.graph.nodes == 18
    views.publish(pic, now)
    pic2 = builder.build(station, now + 1.0, planner=planner)  # nothing new: no map, no graph
    assert pic2.map is None and pic2.graph is None
    views.publish(pic2, now + 1.0)
    views.close()
    assert views.stats.drawn == 2 and views.stats.draw_errors == 0
    reader = RrdReader(path)
    assert len(reader.blueprints()) == 1
    last: dict[str, list[object]] = {}
    for chunk in reader.stream():
        if chunk.num_rows:
            last.setdefault(chunk.entity_path, []).append(chunk.to_record_batch())
    for entity in [
        "/world/map",
        "/world/robots",
        "/world/robots/heading",
        "/world/trails",
        "/world/goals",
        "/world/frontiers",
        "/world/trajectory_graph",
        "/world/objects",
        "/world/danger/trigger",
        "/world/danger/blast",
        "/world/graph/odometry",
        "/dashboard/table",
        "/sage/log",
        "/world/sage/boxes",
        "/sage/slot_0",
        "/dashboard/radio",
    ]:
        assert entity in last, f"{entity} missing from {sorted(last)}"

    def column(entity: str, name: str) -> list:  # type: ignore[type-arg]
        """Every row's value of a column, in the recording's order."""
        batches = [b for b in last[entity] if name in b.schema.names]  # type: ignore[attr-defined]
        return [v for b in batches for v in b.column(name).to_pylist()]  # type: ignore[attr-defined]

    assert len(column("/world/robots", "Points3D:positions")[-1]) == 3
    assert column("/world/robots", "Points3D:labels")[-1][0].startswith("0 autonomous neutralize")
    assert len(column("/world/graph/odometry", "LineStrips3D:strips")[-1]) == 3
    assert len(column("/world/danger/trigger", "LineStrips3D:strips")[-1]) == 1
    assert len(column("/world/danger/blast", "LineStrips3D:strips")[-1]) == 1
    assert len(column("/world/trajectory_graph", "LineStrips3D:strips")[-1]) == 2
    narration = [t for row in column("/sage/log", "TextLog:text") for t in row]
    assert any("new object" in t and "static_ooi" in t for t in narration)
    assert any("neutralization started" in t for t in narration)
    radio = column("/dashboard/radio", "Scalars:scalars")
    assert len(radio) == 2 and len(radio[-1]) == 1 + 3  # the total, then one per robot
    assert radio[-1][0] == pytest.approx(sum(radio[-1][1:]))
    table = column("/dashboard/table", "TextDocument:text")[-1][0]
    assert table.count("\n| ") == 3 + 1  # header row + one row per robot


def test_unreachable_viewer_neither_raises_nor_slows_publish() -> None:
    port = _free_port()  # nothing listens there
    t0 = time.perf_counter()
    views = RerunViews(f"connect 127.0.0.1:{port}", threaded=True, retry_s=0.05)
    station = GroundStation()
    builder = PictureBuilder()
    now = _feed(station, builder, robots=2, nodes=3)
    pic = builder.build(station, now, force_layers=True)
    worst = 0.0
    for i in range(200):
        s = time.perf_counter()
        views.publish(pic, now + i)
        worst = max(worst, time.perf_counter() - s)
    assert worst < 0.05  # publish only hands the picture over
    views.close(timeout_s=5.0)
    assert time.perf_counter() - t0 < 10.0
    assert views.stats.sink_failures["connect"] >= 1
    assert views.stats.drawn == 0 and views.stats.draw_errors == 0
    assert views.stats.dropped >= 150  # nothing to send to: pictures are dropped, counted


def test_unreachable_viewer_inline_is_bounded() -> None:
    port = _free_port()
    t0 = time.perf_counter()
    views = RerunViews(f"connect 127.0.0.1:{port}", threaded=False)
    station = GroundStation()
    builder = PictureBuilder()
    now = _feed(station, builder, robots=1, nodes=2)
    for i in range(20):
        views.publish(builder.build(station, now + i), now + i)
    views.close(timeout_s=1.0)
    assert time.perf_counter() - t0 < 3.0
    assert views.stats.sink_failures["connect"] >= 1
    # kept for the GCS's journal: one per kind with its count, then taken
    failures = views.take_failures()
    assert [f.kind for f in failures] == ["connect"]
    assert failures[0].count == views.stats.sink_failures["connect"]
    assert "unreachable" in failures[0].text
    assert views.take_failures() == []


@pytest.mark.skipif(not INTEL.exists(), reason=f"dataset absent: {INTEL}")
def test_trial_on_a_replay_writes_a_recording(tmp_path: Path) -> None:
    from gcs.views.trial import run_trial

    res = run_trial(
        INTEL, robots=2, max_nodes=30, rrd_path=tmp_path / "t.rrd", png_path=tmp_path / "t.png"
    )
    assert res.nodes > 30 and res.pictures > 10 and res.rrd_bytes > 0
    assert 0.0 < res.views_cpu_frac < 1.0 and res.rrd_bytes_per_robot_hour > 0
    assert (tmp_path / "t.png").stat().st_size > 0
    entities = {c.entity_path for c in RrdReader(tmp_path / "t.rrd").stream()}
    assert {"/world/map", "/world/graph/odometry", "/soc/thumbnails", "/alerts"} <= entities
