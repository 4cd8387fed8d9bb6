"""The robot node's perception against the real simulator (issue 13 items 2-6): objects by
LIDAR shape + colour from its image memory, one detection id per object, hostiles tracked
with velocity and kept out at once, thumbnails only on request, teammates' tags; bad input
(NaN points, images that never come, a corrupt thresholds file) counted, the robot drives on;
and a detection over real zenoh that a GroundStation turns into a hazard."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from gcs.ground_station import GroundStationConfig
from gcs.mission_control import MissionControlConfig
from gcs.node import GcsProcess
from protocol.clock import ManualClock
from protocol.loopback import open_pair
from protocol.messages import (
    Detection,
    DetectionImage,
    FiducialObservation,
    GoToTask,
    ObjectKind,
    PoseNode,
    TaskState,
    TaskStatus,
    ThumbnailRequest,
)
from protocol.se2 import compose, inverse, relative, transform_points
from protocol.sensors import CameraImage, LidarSweep
from robot.node import RobotNode, RobotNodeConfig
from robot.perception.colour_classifier import ColourThresholdError
from robot.perception.onboard_perception import PerceptionConfig
from sim.simulator import Simulator
from sim.world_generator import Human, Ooi
from tests.sim.simworlds import make_world

pytestmark = pytest.mark.slow

OOI_RGBA = (1.0, 0.3, 0.0, 1.0)
VAT_RGBA = (0.95, 0.85, 0.0, 1.0)
HOSTILE_RGBA = (0.9, 0.05, 0.05, 1.0)
START = np.array([3.0, 10.0, 0.0])  # robot 0's start: its odom frame in the world


def _world(**extra: Any) -> Any:
    pieces: dict[str, Any] = {
        "robots": ((3.0, 10.0, 0.0, "sensor"),),
        "oois": (
            Ooi(1, "static_ooi", (10.0, 8.0), 0.25, 0.8, OOI_RGBA),
            Ooi(2, "toxic_vat", (16.0, 12.5), 0.3, 0.9, VAT_RGBA),
        ),
    }
    pieces.update(extra)
    return make_world(**pieces)


def _run(
    sim: Simulator,
    node: RobotNode,
    seconds: float,
    *,
    until: Callable[[], bool] | None = None,
    frame_filter: Callable[[Any], Any] | None = None,
) -> None:
    driver = sim.driver(node.robot_id)
    for _ in range(int(round(seconds / sim.config.step_s))):
        sim.step()
        frames = driver.poll(0.0)
        if frame_filter is not None:
            frames = [g for g in (frame_filter(f) for f in frames) if g is not None]
        for command in node.process(frames):
            driver.send(command)
        if until is not None and until():
            return


def _in_odom(det: Detection, nodes: dict[int, PoseNode]) -> np.ndarray:
    pose = np.array(nodes[det.node_index].pose_in_odom)
    return compose(pose, np.array([*det.position_in_base, 0.0]))[:2]


def _truth_in_odom(xy_world: tuple[float, float]) -> np.ndarray:
    return relative(START, np.array([*xy_world, 0.0]))[:2]


@pytest.fixture(scope="module")
def drive() -> tuple[list[Any], RobotNode]:
    """Robot 0 drives 18 m past a static OOI (2 m right of its way) and a toxic vat (2.5 m
    left)."""
    sent: list[Any] = []
    with Simulator(_world()) as sim:
        node = RobotNode(0, send=sent.append)
        node.handle_downlink(GoToTask(1, 0.0, [(18.0, 0.0)]))
        done = lambda: any(  # noqa: E731
            isinstance(m, TaskStatus) and m.state is TaskState.SUCCEEDED for m in sent
        )
        _run(sim, node, 45.0, until=done)
    return sent, node


def test_objects_are_detected_once_each_where_they_are(drive: tuple[list[Any], RobotNode]) -> None:
    sent, node = drive
    nodes = {m.node_index: m for m in sent if isinstance(m, PoseNode)}
    dets = [m for m in sent if isinstance(m, Detection)]
    by_id: dict[int, list[Detection]] = {}
    for d in dets:
        by_id.setdefault(d.detection_id, []).append(d)
    kinds = {i: {d.kind for d in ds} for i, ds in by_id.items()}
    assert sorted(k for ks in kinds.values() for k in ks) == [
        ObjectKind.STATIC_OOI,
        ObjectKind.TOXIC_VAT,
    ], kinds  # one id per object, nothing else reported
    for ds in by_id.values():
        assert len(ds) <= 3  # about once: a refinement or two at most
        truth = {ObjectKind.STATIC_OOI: (10.0, 8.0), ObjectKind.TOXIC_VAT: (16.0, 12.5)}
        for d in ds:
            err = float(np.hypot(*(_in_odom(d, nodes) - _truth_in_odom(truth[d.kind]))))
            assert err < 0.3, (d, err)
            xx, xy, yy = d.position_covariance
            assert xx > 0 and yy > 0 and xx * yy > xy * xy
            assert d.node_index in nodes and d.velocity_in_base == (0.0, 0.0)
    # the node's own keep-out holds the static OOI at once (vats are not explosive)
    ooi = _truth_in_odom((10.0, 8.0))
    disks = node._keepout
    assert any(np.hypot(*(disk[:2] - ooi)) < 0.3 and disk[2] >= 2.5 for disk in disks)
    assert node.stats.perception_errors == 0 and node.perception is not None
    assert node.perception.stats.images_lost == 0


def test_thumbnails_only_on_request_and_within_budget(
    drive: tuple[list[Any], RobotNode],
) -> None:
    sent, node = drive
    assert not any(isinstance(m, DetectionImage) for m in sent)  # never unasked
    det = next(m for m in sent if isinstance(m, Detection) and m.kind is ObjectKind.STATIC_OOI)
    out: list[Any] = []
    node._send = out.append  # what it sends from here on
    node.handle_downlink(ThumbnailRequest(7, det.detection_id, 1500))
    node.handle_downlink(ThumbnailRequest(8, 999, 0))  # no such detection: counted, no answer
    node._apply_downlink()
    (img,) = out
    assert isinstance(img, DetectionImage) and img.detection_id == det.detection_id
    assert img.image_id == 7 and img.encoding == "jpeg" and len(img.data) <= 1500
    bgr = cv2.imdecode(np.frombuffer(img.data, np.uint8), cv2.IMREAD_COLOR)
    assert bgr is not None
    rgb = bgr[:, :, ::-1]
    assert rgb.shape[:2] == (img.height, img.width)
    # the object fills the middle: orange (R high, B low) dominates there
    h, w = rgb.shape[:2]
    mid = rgb[h // 3 : 2 * h // 3, w // 3 : 2 * w // 3].reshape(-1, 3).astype(int)
    assert np.median(mid[:, 0] - mid[:, 2]) > 60
    assert node.perception is not None and node.perception.stats.thumbnail_unknown == 1


def test_a_hostile_walking_towards_the_robot_is_tracked_reported_and_kept_out() -> None:
    """The robot stands; a hostile walks from 11 m straight at it at 0.5 m/s (stopping 3 m
    short): a HOSTILE detection with a velocity pointing at the robot, the keep-out at once."""
    hostile = Human(1, "hostile", ((14.0, 10.3), (6.0, 10.3)), 0.5, 0.25, 1.7, HOSTILE_RGBA)
    sent: list[Any] = []
    with Simulator(_world(oois=(), humans=(hostile,))) as sim:
        node = RobotNode(0, send=sent.append)
        seen = lambda: any(  # noqa: E731
            isinstance(m, Detection) and m.kind is ObjectKind.HOSTILE for m in sent
        )
        _run(sim, node, 16.0, until=seen)
        first_s = sim.time_s
    dets = [m for m in sent if isinstance(m, Detection) and m.kind is ObjectKind.HOSTILE]
    assert dets, f"no hostile report in {first_s:.1f} s"
    nodes = {m.node_index: m for m in sent if isinstance(m, PoseNode)}
    d = dets[-1]
    yaw = nodes[d.node_index].pose_in_odom[2]
    c, s = math.cos(yaw), math.sin(yaw)
    vx, vy = d.velocity_in_base
    v_odom = np.array([c * vx - s * vy, s * vx + c * vy])
    assert float(np.hypot(*(v_odom - [-0.5, 0.0]))) < 0.3, v_odom
    where = _in_odom(d, nodes)
    assert node.perception is not None
    # the keep-out disk of the hostile was in the node's planner at once
    disks = node._keepout
    assert any(np.hypot(*(disk[:2] - where)) < 1.5 and disk[2] >= 5.0 for disk in disks)


def test_a_teammate_in_view_becomes_a_fiducial_observation() -> None:
    """Robot 1 stands 1.9 m ahead of robot 0, side on: robot 0's node sends a
    FiducialObservation of robot 1 within 0.1 m of where it stands."""
    world = _world(oois=(), robots=((3.0, 10.0, 0.0, "sensor"), (4.9, 10.2, 1.2, "sensor")))
    sent: list[Any] = []
    with Simulator(world) as sim:
        node = RobotNode(0, send=sent.append)
        _run(
            sim,
            node,
            30.0,
            until=lambda: any(isinstance(m, FiducialObservation) for m in sent),
        )
    obs = [m for m in sent if isinstance(m, FiducialObservation)]
    assert obs and obs[0].observed_robot_id == 1 and obs[0].tag_id // 4 == 1
    nodes = {m.node_index: m for m in sent if isinstance(m, PoseNode)}
    o = obs[0]
    seen = compose(np.array(nodes[o.node_index].pose_in_odom), np.array(o.observed_in_base))
    truth = relative(START, np.array([4.9, 10.2, 1.2]))
    assert float(np.hypot(*(seen[:2] - truth[:2]))) < 0.1
    assert abs((seen[2] - truth[2] + math.pi) % (2 * math.pi) - math.pi) < math.radians(5)


def test_bad_input_is_counted_and_the_robot_drives_on(tmp_path: Path) -> None:
    """NaN points in every sweep and every camera image lost: counted, the rest of each
    sweep used, the robot still reaches its goal. A corrupt thresholds file is an error
    naming it."""
    sent: list[Any] = []

    def spoil(frame: Any) -> Any:
        if isinstance(frame, CameraImage):
            return None  # the image never arrives
        if isinstance(frame, LidarSweep):
            pts = frame.points_in_base.copy()
            pts[::50] = np.nan
            return LidarSweep(
                frame.sweep_index, frame.time_s, frame.duration_s, pts, frame.point_time_s
            )
        return frame

    # no static OOI on the way: a robot that cannot see one drives into its trigger radius
    with Simulator(_world(oois=())) as sim:
        node = RobotNode(0, send=sent.append)
        node.handle_downlink(GoToTask(1, 0.0, [(10.0, 0.0)]))
        done = lambda: any(  # noqa: E731
            isinstance(m, TaskStatus) and m.state is TaskState.SUCCEEDED for m in sent
        )
        _run(sim, node, 40.0, until=done, frame_filter=spoil)
    assert done()
    p = node.perception
    assert p is not None
    assert node.stats.nonfinite_points > 0 and node.stats.bad_frames == 0
    assert p.stats.images_lost > 0
    assert p.stats.images_received == 0 and node.stats.perception_errors == 0

    bad = tmp_path / "colour.json"
    bad.write_text('{"format": "magic-recon/colour-thresholds", "version": 1, "classes": ')
    with pytest.raises(ColourThresholdError, match=str(bad)):
        RobotNode(0, send=sent.append, config=RobotNodeConfig(
            perception=PerceptionConfig(colour_thresholds=str(bad))))  # fmt: skip
    with pytest.raises(ValueError, match="thresholds"):
        RobotNode(0, send=sent.append, config=RobotNodeConfig(
            perception=PerceptionConfig(shape_thresholds=str(bad))))  # fmt: skip


def test_a_detection_over_zenoh_becomes_a_hazard_at_the_gcs() -> None:
    """The node's uplink over real zenoh (loopback) to a GCS process: its static OOI becomes
    a hazard in ``map`` where the object is (through the GCS's own map_from_odom)."""
    clock = ManualClock()
    gcs_link, robot_link = open_pair(clock=clock)
    proc = GcsProcess(
        gcs_link,
        clock,
        GroundStationConfig(robots=(0,)),
        step_period_s=0.5,
        mission=MissionControlConfig(enabled=False),
    )
    radio = robot_link.robot_endpoint(0)
    node = RobotNode(0, send=radio.send)
    try:
        assert proc.radio.wait_for_robot(0, 10.0)
        world = _world(oois=(Ooi(1, "static_ooi", (9.0, 8.5), 0.25, 0.8, OOI_RGBA),))
        with Simulator(world) as sim:
            node.handle_downlink(GoToTask(1, 0.0, [(10.0, 0.0)]))
            driver = sim.driver(0)
            station = proc.station
            for _ in range(int(40.0 / sim.config.step_s)):
                sim.step()
                clock.set(sim.time_s)
                for command in node.process(driver.poll(0.0)):
                    driver.send(command)
                robot_link.pump()
                gcs_link.pump()
                proc.spin_once(timeout_s=0.0)
                if any(h.kind is ObjectKind.STATIC_OOI for h in station.hazards):
                    break
        for _ in range(40):  # let the step that follows the detection run
            clock.set(clock.now() + 0.25)
            robot_link.pump()
            gcs_link.pump()
            proc.spin_once(timeout_s=0.02)
        hazards = [h for h in proc.station.hazards if h.kind is ObjectKind.STATIC_OOI]
        assert len(hazards) == 1, proc.station.stats
        map_from_odom = proc.station.graph.map_from_odom(0)
        in_odom = transform_points(
            inverse(np.asarray(map_from_odom)), np.array([hazards[0].position_in_map])
        )[0]
        assert float(np.hypot(*(in_odom - _truth_in_odom((9.0, 8.5))))) < 0.3
        assert proc.station.stats.detections >= 1
        assert proc.station.stats.rejected_total == 0, proc.station.stats.errors
    finally:
        proc.close()
        robot_link.close()
        gcs_link.close()
