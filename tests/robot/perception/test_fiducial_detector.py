"""Teammates' AprilTags (paper 4.3.2) from real PyBullet renders, against the simulator's truth;
and a fiducial sighting joining two robots' graph components at the GCS."""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from gcs.ground_station import GroundStation, GroundStationConfig
from protocol.messages import HazardUpdate, PoseNode, covariance_to_upper
from protocol.se2 import compose, relative
from robot.perception.camera_model import Intrinsics
from robot.perception.fiducial_detector import (
    FiducialConfig,
    TagLayoutConfig,
    detect_tags,
    estimate_teammates,
    fiducial_observation,
    fit_rows_px,
)
from sim.camera import CameraConfig, camera_axes, intrinsics
from sim.scene import RobotGeometry, Scene
from tests.sim.simworlds import make_world

CAM = CameraConfig()
W, H = 640, 480


def _matrix(x: float, y: float, yaw: float) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    m[:2, 3] = (x, y)
    return m


@pytest.fixture(scope="module")
def scene() -> Iterator[Scene]:
    s = Scene(
        make_world(robots=((5.0, 10.0, 0.0, "sensor"), (7.0, 10.0, 2.0, "sensor"))), ray_threads=1
    )
    yield s
    s.close()


def _render(
    scene: Scene,
    observer: np.ndarray,
    observed: np.ndarray,
    pan: float = 0.0,
    size: tuple[int, int] = (W, H),
) -> tuple[np.ndarray, Intrinsics]:
    scene.set_robot_poses(np.stack([observer, observed]))
    scene.sync()
    eye, fwd, up = camera_axes(observer, np.array(scene.geometry.camera_m), pan, CAM.tilt_rad)
    w, h = size
    fx, fy, cx, cy = intrinsics(w, h, CAM)
    rgb = scene.render(eye_m=eye, forward=fwd, up=up, width_px=w, height_px=h, fy_px=fy)
    return rgb, Intrinsics(fx, fy, cx, cy, w, h)


def test_layout_defaults_are_the_simulated_robots() -> None:
    lay, geo = TagLayoutConfig(), RobotGeometry()
    assert lay.tag_size_m == geo.tag_size_m
    assert lay.head_center_in_base_m == geo.head_center_m
    assert lay.head_half_m == geo.head_half_m
    assert lay.marker_in_base_m[:2] == geo.lidar_m[:2]  # the LIDAR housing is the face cue
    assert FiducialConfig().camera_in_base_m == geo.camera_m


def test_teammate_pose_against_truth_up_to_3_m(scene: Scene) -> None:
    """Random relative poses 1-3 m ahead: every pose sent is within 0.10 m, its heading within
    3 sigma of its own covariance; p95 heading error <= 3 deg when two faces are seen."""
    rng = np.random.default_rng(11)
    pos_err, yaw_err, yaw_err_2face, sent = [], [], [], 0
    for _ in range(40):
        r, bearing = rng.uniform(1.0, 3.0), rng.uniform(-0.4, 0.4)
        observer = _matrix(5.0, 10.0, rng.uniform(-3, 3))
        rel = _matrix(r * math.cos(bearing), r * math.sin(bearing), rng.uniform(-math.pi, math.pi))
        rgb, intr = _render(scene, observer, observer @ rel)
        sightings, _ = estimate_teammates(rgb, intr, 0.0, CAM.tilt_rad, own_robot_id=0)
        if not sightings:
            continue
        (s,) = sightings
        assert s.robot_id == 1 and s.tag_id // 4 == 1  # id 4 robot + face
        sent += 1
        x, y, yaw = s.observed_in_base
        e_pos = math.hypot(x - rel[0, 3], y - rel[1, 3])
        e_yaw = abs((yaw - math.atan2(rel[1, 0], rel[0, 0]) + math.pi) % (2 * math.pi) - math.pi)
        pos_err.append(e_pos)
        yaw_err.append(e_yaw)
        assert e_pos < 0.10
        assert e_yaw < 3 * math.sqrt(s.covariance[2, 2]) + 1e-3
        assert np.all(np.linalg.eigvalsh(s.covariance) > 0)
        if len(s.faces) > 1:
            yaw_err_2face.append(math.degrees(e_yaw))
    assert sent >= 15  # the rest: tag out of view or the heading's face not told apart
    assert np.percentile(pos_err, 95) <= 0.10
    assert len(yaw_err_2face) >= 5 and np.percentile(yaw_err_2face, 95) <= 3.0


def test_a_band_of_rows_from_the_coarse_image_gives_the_full_images_sighting(
    scene: Scene,
) -> None:
    """fit_rows_px on a 320x240 image's tags: a 640-wide image of that band (scaled, with the
    robot's margin and least height) gives the same sighting as the full 640x480 image, and
    is shorter for a teammate beyond 2 m; the band grows as the teammate comes closer (its
    LIDAR housing, sampled for the face cue, lies further below the horizon)."""
    rng = np.random.default_rng(5)
    rows_by_range: list[tuple[float, int]] = []
    compared = 0
    for _ in range(40):
        r, bearing = rng.uniform(1.0, 3.5), rng.uniform(-0.4, 0.4)
        observer = _matrix(5.0, 10.0, rng.uniform(-3, 3))
        rel = _matrix(r * math.cos(bearing), r * math.sin(bearing), rng.uniform(-math.pi, math.pi))
        coarse, c_intr = _render(scene, observer, observer @ rel, size=(320, 240))
        tags = detect_tags(coarse)
        if not tags:
            continue
        dev = fit_rows_px(tags, c_intr, own_robot_id=0)
        # as the robot asks (PerceptionConfig.fiducial_band_*: 16 rows of margin, >= 192)
        rows = min(H, max(192, 2 * (math.ceil(2 * dev) + 16)))
        rows_by_range.append((r, rows))
        full, f_intr = _render(scene, observer, observer @ rel)
        band, b_intr = _render(scene, observer, observer @ rel, size=(W, rows))
        off = (H - rows) // 2
        # the same rows: TinyRenderer's rasterization may differ on a rare edge pixel
        differ = np.abs(band.astype(int) - full[off : off + rows].astype(int)).max(axis=2) > 0
        assert differ.mean() < 1e-3
        a, _ = estimate_teammates(full, f_intr, 0.0, CAM.tilt_rad, own_robot_id=0)
        b, _ = estimate_teammates(band, b_intr, 0.0, CAM.tilt_rad, own_robot_id=0)
        assert [s.robot_id for s in a] == [s.robot_id for s in b]
        for sa, sb in zip(a, b, strict=True):
            np.testing.assert_allclose(sa.observed_in_base, sb.observed_in_base, atol=1e-3)
            np.testing.assert_allclose(sa.covariance, sb.covariance, rtol=0.05, atol=1e-9)
        compared += len(a)
    assert compared >= 8
    far = [rows for r, rows in rows_by_range if r > 2.0]
    near = [rows for r, rows in rows_by_range if r < 1.5]
    assert far and max(far) < H
    assert near and np.median(near) > np.median(far)
    assert fit_rows_px([], c_intr, own_robot_id=0) == 0.0


def test_own_tags_and_tagless_images_give_nothing_and_bad_images_are_refused(scene: Scene) -> None:
    observer = _matrix(5.0, 10.0, 0.0)
    rgb, intr = _render(scene, observer, observer @ _matrix(2.0, 0.0, 2.6))
    tags = detect_tags(rgb)
    assert tags and all(d.tag_id // 4 == 1 for d in tags)  # robot 1's own faces
    assert estimate_teammates(rgb, intr, 0.0, CAM.tilt_rad, own_robot_id=1) == ([], 0)
    blank, _ = _render(scene, observer, observer @ _matrix(-3.0, 0.0, 0.0))  # behind
    assert estimate_teammates(blank, intr, 0.0, CAM.tilt_rad, own_robot_id=0) == ([], 0)
    with pytest.raises(ValueError, match="uint8"):
        detect_tags(rgb.astype(np.float32))


def test_the_observation_is_expressed_in_the_pose_nodes_base(scene: Scene) -> None:
    observer = _matrix(5.0, 10.0, 0.0)
    rgb, intr = _render(scene, observer, observer @ _matrix(2.0, 0.3, 2.6))
    (s,), _ = estimate_teammates(rgb, intr, 0.0, CAM.tilt_rad, own_robot_id=0)
    node_from_image = (0.4, -0.1, 0.2)  # the robot moved on since its pose node
    msg = fiducial_observation(s, node_index=7, time_s=12.5, node_from_image_base=node_from_image)
    np.testing.assert_allclose(
        msg.observed_in_base, compose(node_from_image, s.observed_in_base), atol=1e-5
    )
    assert (msg.node_index, msg.observed_robot_id, msg.tag_id // 4) == (7, 1, 1)


def test_a_fiducial_sighting_joins_two_robots_that_never_share_a_scan(scene: Scene) -> None:
    """Robots 0 and 1 send only pose nodes (no terrain grids: no scan can ever close a loop
    between them); robot 0's camera sees robot 1 once, from a rendered image. The GCS puts
    both in one component and places robot 1's odometry frame where it truly is."""
    cov = covariance_to_upper(np.diag([0.01**2, 0.01**2, 0.002**2]))
    start0 = np.array([5.0, 10.0, 0.0])  # robot 0's odom (and the map) starts here
    world0 = [compose(start0, (0.5 * i, 0.0, 0.0)) for i in range(8)]
    seen1 = np.array([8.7, 10.3, 2.5])  # robot 1's node 3, 1.7 m ahead of robot 0's node 4
    world1 = [compose(seen1, (0.3 * (j - 3), 0.0, 0.0)) for j in range(8)]
    gs = GroundStation(GroundStationConfig(robots=(0, 1)))
    for rid, poses, t0 in ((0, world0, 0.0), (1, world1, 1.0)):
        for i, p in enumerate(poses):
            odom = relative(poses[0], p)
            delta = (0.0, 0.0, 0.0) if i == 0 else tuple(relative(poses[i - 1], p))
            c = (0.0,) * 6 if i == 0 else cov
            assert gs.handle(rid, PoseNode(i, t0 + i, tuple(odom), delta, c), now_s=0.0)  # type: ignore[arg-type]
    out = gs.step(now_s=10.0)
    assert [f.robot_id for f in out[0][1].frames] == [0]  # robot 1 is on its own
    rgb, intr = _render(scene, _matrix(*world0[4]), _matrix(*world1[3]))
    (s,), _ = estimate_teammates(rgb, intr, 0.0, CAM.tilt_rad, own_robot_id=0)
    assert gs.handle(0, fiducial_observation(s, node_index=4, time_s=4.0), now_s=11.0)
    out = gs.step(now_s=12.0)
    update = out[0][1]
    assert isinstance(update, HazardUpdate)
    frames = {f.robot_id: np.array(f.map_from_odom) for f in update.frames}
    assert set(frames) == {0, 1}
    comp = gs.graph.components()
    assert len({comp[k] for k in comp}) == 1
    truth = relative(start0, world1[0])
    assert math.hypot(*(frames[1][:2] - truth[:2])) < 0.1
    assert abs((frames[1][2] - truth[2] + math.pi) % (2 * math.pi) - math.pi) < math.radians(3)
    assert gs.stats.fiducials == 1


@pytest.mark.parametrize(("w", "h"), [(320, 240), (160, 120), (640, 192), (16, 16)])
def test_a_flat_image_has_no_tag_and_the_detector_agrees(w: int, h: int) -> None:
    # detect_tags answers a one-grey-level image (the simulator's frame with nothing to
    # find) without searching it: the search itself finds nothing there at any level
    import cv2

    from robot.perception.fiducial_detector import _detector, _uniform

    for level in (0, 37, 128, 255):
        rgb = np.full((h, w, 3), level, dtype=np.uint8)
        gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
        assert _uniform(gray)
        assert _detector().detectMarkers(gray)[1] is None
        assert detect_tags(rgb) == []
    rgb[h // 2, w // 3] = (0, 255, 0)
    assert not _uniform(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
