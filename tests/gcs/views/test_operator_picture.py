"""The rerun-free picture: publishing schedule, rows, objects and thumbnails; cv2 rendering."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import cv2
import numpy as np
import pytest

from gcs.ground_station import GroundStation
from gcs.views.operator_picture import PictureBuilder, PlannerView, ViewsConfig
from gcs.views.render import FOG, WALL, render_region, thumbnail_mosaic
from protocol.messages import (
    AutonomyMode,
    Detection,
    DetectionImage,
    ObjectKind,
    PoseNode,
    TaskState,
    TaskStatus,
    Telemetry,
)

_spec = importlib.util.spec_from_file_location(
    "views_test_helpers", Path(__file__).with_name("test_rerun_views.py")
)
assert _spec is not None and _spec.loader is not None
helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(helpers)


def _jpeg(h: int = 120, w: int = 160) -> bytes:
    img = np.zeros((h, w, 3), np.uint8)
    img[:, :, 2] = 255  # red in BGR
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def test_layers_are_published_only_when_due_and_changed() -> None:
    station = GroundStation()
    b = PictureBuilder(ViewsConfig(robots_period_s=1.0, graph_period_s=5.0, map_period_s=5.0))
    now = helpers._feed(station, b, robots=2, nodes=4)
    assert b.due(now)
    p = b.build(station, now)
    assert p.map is not None and p.graph is not None and p.map_version == 1
    assert not b.due(now + 0.5) and b.due(now + 1.0)
    p = b.build(station, now + 1.0)
    assert p.map is None and p.graph is None  # not due yet
    p = b.build(station, now + 10.0)
    assert p.map is None and p.graph is None  # due, but nothing changed
    assert b.map_version == 1
    station.handle(0, PoseNode(4, 4.0, (4.0, 0.0, 0.0), (1.0, 0.0, 0.0), helpers.COV), now_s=4.0)
    station.handle(0, helpers._grid(4), now_s=4.0)
    station.step(now_s=4.0)
    p = b.build(station, now + 20.0)
    assert p.graph is not None and p.graph.nodes == 9 and p.graph.edges["odometry"] == 7
    assert p.map is not None and p.map_version == 2
    r0 = next(r for r in p.robots if r.robot_id == 0)
    assert r0.nodes == 5 and r0.linked and r0.pose_in_map is not None
    assert np.allclose(r0.trail_in_map[-1], [4.0, 0.0], atol=1e-6)
    assert not next(r for r in p.robots if r.robot_id == 1).linked  # own component


def test_rows_status_stuck_objects_and_thumbnails() -> None:
    station = GroundStation()
    b = PictureBuilder(ViewsConfig(stuck_s=10.0, stuck_m=0.5))
    cov = helpers.COV
    for i in range(3):
        station.handle(
            0, PoseNode(i, float(i), (float(i), 0.0, 0.0), (1.0, 0.0, 0.0), cov), now_s=float(i)
        )
    station.step(now_s=2.0)
    b.observe(0, TaskStatus(5, TaskState.ACTIVE, 0.0), now_s=0.0, nbytes=40)
    for t in range(0, 25, 2):  # parked at x = 2 for 24 s with a task: stuck
        tele = Telemetry(
            float(t), (2.0, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.5, AutonomyMode.AUTONOMOUS, 5
        )
        b.observe(0, tele, now_s=float(t), nbytes=60)
    det = Detection(9, 2, 2.0, ObjectKind.CIVILIAN, (1.0, 1.0), (0.01, 0.0, 0.01), 0.3, 1.7, 0.8)
    b.observe(0, det, now_s=24.0, nbytes=50, station=station)
    b.observe(
        0, DetectionImage(1, 9, 24.0, 0.0, "jpeg", 160, 120, _jpeg()), now_s=24.0, nbytes=3000
    )
    b.observe(0, DetectionImage(2, 9, 24.0, 0.0, "jpeg", 160, 120, b"not a jpeg"), now_s=24.0)
    p = b.build(station, 24.0)
    (r,) = p.robots
    assert r.task == "task 5 active" and r.mode == "autonomous" and r.battery_frac == 0.5
    assert r.stuck and r.anomalous
    assert r.uplink_bps == pytest.approx(8 * (40 + 13 * 60 + 50 + 3000) / 24.0)
    (o,) = p.objects
    assert o.kind_name == "civilian" and o.position_in_map == pytest.approx((3.0, 1.0))
    assert o.thumbnail is not None and o.thumbnail.shape == (72, 96, 3)
    assert o.thumbnail[36, 48, 0] > 200 and o.thumbnail[36, 48, 2] < 60  # red, as RGB
    assert p.new_thumbnails == [1] and b.bad_images == 1
    assert [a.rule for a in p.new_alerts] == ["stuck", "civilian"]  # 1.4 m from it
    mosaic = thumbnail_mosaic(p.objects)
    assert mosaic is not None and mosaic.shape == (96 + 14, 96, 3)


def test_unmetered_messages_give_no_rate_and_no_rate_alert() -> None:
    station = GroundStation()
    b = PictureBuilder()
    for t in range(0, 60, 2):
        tele = Telemetry(
            float(t), (0.0, 0.0, 0.0), (0.0, 0.0), (0.0, 0.0), 0.9, AutonomyMode.IDLE, 0
        )
        b.observe(3, tele, now_s=float(t))  # no nbytes: the GCS does not meter
    p = b.build(station, 60.0)
    (r,) = p.robots
    assert np.isnan(r.uplink_bps) and p.uplink_total_bps == 0.0
    assert p.new_alerts == []


def test_planner_view_is_checked() -> None:
    station = GroundStation()
    b = PictureBuilder()
    helpers._feed(station, b, robots=1, nodes=2)
    bad = PlannerView(trajectory_nodes_in_map=np.zeros((2, 2)), trajectory_edges=np.array([[0, 2]]))
    with pytest.raises(ValueError, match="trajectory_edges"):
        b.build(station, 5.0, planner=bad)


def test_render_is_north_up_east_right() -> None:
    station = GroundStation()
    b = PictureBuilder()
    now = helpers._feed(station, b, robots=1, nodes=3)
    p = b.build(station, now, force_layers=True)
    assert p.map is not None
    # robot 0 drove along +x; its wall is 2 m to its left (+y): above it in the image
    img = render_region(p, p.map, (1.0, 0.0), 5.0, px=100)  # 0.1 m per pixel
    gray = img.mean(axis=2)
    wall_rows = np.flatnonzero((gray == WALL).sum(axis=1) > 20)
    assert wall_rows.size and abs(int(np.median(wall_rows)) - 30) <= 1  # y = +2 m -> row 30
    far = render_region(p, p.map, (1.0, 0.0), 60.0, px=100).mean(axis=2)
    assert far[2, 2] == FOG and far[97, 97] == FOG  # 60 m away: never seen, fog of war
    robot = np.argwhere((img[:, :, 1] > 150) & (img[:, :, 0] < 50))  # green robot disc
    assert abs(robot[:, 0].mean() - 50) < 3 and abs(robot[:, 1].mean() - 60) < 3  # x = 2 m
