"""The robot's perception loop without the simulator: the pan phase learnt from two images,
image requests bounded per step, images that never come or were never asked counted, bad
sweeps survived, own hazards for the keep-out."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from protocol.messages import ObjectKind, ThumbnailRequest
from protocol.sensors import CameraImage
from robot.perception.camera_model import CameraMountConfig, pan_at
from robot.perception.onboard_perception import OnboardPerception, PerceptionConfig

MOUNT = CameraMountConfig()
PHASE_S = 3.3  # the camera's (unknown to the robot) schedule phase
# the periodic tag image every second whatever the LIDAR saw (the gate's own test below)
NO_GATE = PerceptionConfig(fiducial_period_s=1.0, image_timeout_s=60.0, tag_gate_memory_s=0.0)


def _image(request_id: int, time_s: float, w: int = 320, h: int = 240) -> CameraImage:
    fx = w / 2 / math.tan(math.radians(30))
    return CameraImage(
        request_id,
        time_s,
        pan_at(time_s, MOUNT, PHASE_S),
        MOUNT.tilt_rad,
        fx,
        fx,
        w / 2,
        h / 2,
        np.full((h, w, 3), 120, np.uint8),
    )


def _pose_at(_t: float) -> np.ndarray:
    return np.zeros(3)


def test_the_pan_phase_is_learnt_from_two_images_then_frames_are_remembered() -> None:
    p = OnboardPerception(0)
    p.on_control(0.05, np.zeros(3))
    (r1,) = p.take_requests()
    p.on_control(0.5, np.zeros(3))
    (r2,) = p.take_requests()
    assert (r1.time_s, r2.time_s) == (0.05, 0.5) and r1.request_id != r2.request_id
    # the first at full size by default: searched for teammates' tags like any other coarse
    # image; the second a probe: only its pan is used
    assert (r1.width_px, r1.height_px) == (p.config.memory.width_px, p.config.memory.height_px)
    assert (r2.width_px, r2.height_px) == (16, 16)
    for cfg, sizes in (
        (PerceptionConfig(phase_full_images=0), [16, 16]),
        (PerceptionConfig(phase_full_images=2), [320, 320]),
        (PerceptionConfig(phase_probe_px=0), [320, 320]),
    ):
        q = OnboardPerception(0, cfg)
        q.on_control(0.05, np.zeros(3))
        q.on_control(0.5, np.zeros(3))
        assert [r.width_px for r in q.take_requests()] == sizes
    assert len(p.memory) == 0  # no pan known: nothing to remember yet
    p.on_image(_image(r1.request_id, r1.time_s), _pose_at)
    p.on_image(_image(r2.request_id, r2.time_s, 16, 16), _pose_at)
    assert p.pan_phase_s is not None
    # the frames of before the phase was known are remembered now, with their pans
    assert [f.time_s for f in p.memory.frames] == [0.05, 0.5]
    assert abs(p.memory.frames[0].pan_rad - pan_at(0.05, MOUNT, PHASE_S)) < 0.02
    for t in (7.0, 11.2):
        assert abs(pan_at(t, MOUNT, p.pan_phase_s) - pan_at(t, MOUNT, PHASE_S)) < 0.02
    for k in range(20):
        p.on_control(0.6 + 0.05 * k, np.array([0.1 * k, 0.0, 0.0]))
    assert len(p.memory) == 12  # one frame per 0.1 s
    frame = p.memory.frames[-1]
    assert abs(frame.pan_rad - pan_at(frame.time_s, MOUNT, PHASE_S)) < 0.02


def test_requests_are_bounded_per_step_and_lost_images_counted() -> None:
    p = OnboardPerception(0, PerceptionConfig(fiducial_period_s=0.0, image_timeout_s=1.0))
    p.on_control(0.0, np.zeros(3))
    p._now = 0.0
    for _ in range(5):
        p._ask(0.0, [])
    assert len(p.take_requests()) == 2  # max_requests_per_step (the bootstrap one first)
    assert p.take_requests() == []  # the same mission time: nothing more
    p.on_control(0.05, np.zeros(3))
    assert len(p.take_requests()) == 2
    p.on_control(0.1, np.zeros(3))
    assert len(p.take_requests()) == 2
    asked = p.stats.images_requested
    p.on_control(1.5, np.zeros(3))  # nothing ever answered
    assert p.stats.images_lost == asked
    p.on_image(_image(999, 1.4), _pose_at)
    assert p.stats.images_unexpected == 1


def test_bad_sweeps_are_counted_not_raised() -> None:
    p = OnboardPerception(0)
    rng = np.random.default_rng(0)
    pts = rng.uniform(-5, 5, (500, 3))
    pts[:, 2] = np.abs(pts[:, 2]) * 0.1
    pts[::7] = np.nan
    p.on_sweep(pts, np.zeros(3), 1.0)
    assert p.stats.nonfinite_points == len(pts[::7]) and p.stats.sweeps == 1
    p.on_sweep(pts, np.array([0.0, math.nan, 0.0]), 2.0)
    assert p.stats.skipped_sweeps == 1


def test_own_hazards_hold_static_oois_not_vats_and_thumbnails_need_an_image() -> None:
    p = OnboardPerception(0)
    p._fuse(int(ObjectKind.STATIC_OOI), (4.0, 1.0), 0.25, 0.8, 4.0, 1.0, 1.0)
    p._fuse(int(ObjectKind.TOXIC_VAT), (9.0, -3.0), 0.3, 0.9, 9.0, 1.0, 1.0)
    assert p.take_hazards_changed()
    assert p.own_hazards_in_odom() == [(ObjectKind.STATIC_OOI, 4.0, 1.0)]
    dets = p.take_detections()
    assert [d.kind for d in dets] == [ObjectKind.STATIC_OOI, ObjectKind.TOXIC_VAT]
    assert p.on_thumbnail_request(ThumbnailRequest(1, dets[0].detection_id)) is None
    assert p.stats.thumbnail_unknown == 1


def test_a_hostile_that_turns_keeps_its_keep_out_while_it_is_re_coloured() -> None:
    """The walker turns at a corner of its route: the newest measurement leaves the track's
    line, the label goes (the tracker may have swapped people), but the track keeps its
    hostile keep-out for ``hostile_memory_s`` (a robot once drove on to 5 m of such a
    hostile, whose disk had vanished with the label); then it goes."""
    from robot.perception.person_tracker import PersonTrack

    cfg = PerceptionConfig(hostile_memory_s=10.0)
    p = OnboardPerception(0, cfg)
    # walked east at 0.6 m/s for 3 s, then 1.5 m north of that line: a turn
    hist = [(t, 5.0 + 0.6 * t, 2.0) for t in np.arange(0.0, 3.01, 0.5)]
    hist.append((3.5, 5.0 + 0.6 * 3.5, 3.5))
    x = np.array([hist[-1][1], hist[-1][2], 0.0, 0.0])
    track = PersonTrack(7, x, np.eye(4) * 0.01, 3.5, hits=8, confirmed=True, history=hist)
    track.kind = int(ObjectKind.HOSTILE)
    p.lidar.tracker.tracks.append(track)
    p.on_control(3.0, np.zeros(3))
    p._report_people(3.0)  # labelled: remembered as hostile
    p.on_control(3.5, np.zeros(3))
    p._report_people(3.5)
    assert track.kind == 0  # jumped off its line: re-coloured
    disks = [(k, x, y) for k, x, y in p.own_hazards_in_odom() if k == ObjectKind.HOSTILE]
    assert len(disks) == 1 and math.dist(disks[0][1:], (x[0], x[1])) < 1.0  # 1 s ahead
    p.on_control(12.9, np.zeros(3))
    assert len(p.own_hazards_in_odom()) == 1  # 9.4 s after its last hostile label
    p.on_control(13.6, np.zeros(3))
    assert p.own_hazards_in_odom() == []


def _walk(p: OnboardPerception, t0: float, t1: float, xy0: tuple[float, float]) -> None:
    """A walker at 0.6 m/s along +x from ``xy0`` at ``t0``, one measurement per 1.25 s sweep
    until ``t1``, through the perception's tracker and people bookkeeping."""
    t = t0
    while t < t1 + 1e-9:
        p.lidar.tracker.update(t, [[xy0[0] + 0.6 * (t - t0), xy0[1]]])
        p._now = t
        p._report_people(t)
        t += 1.25


def test_a_hostile_track_dropped_and_found_again_on_its_way_keeps_its_keep_out() -> None:
    """The tracker drops a hostile it misses for a few sweeps (behind the robot); the new
    track where the walker would be now is that hostile for the keep-out at once (no colour
    test yet); a track elsewhere is not."""
    p = OnboardPerception(0)
    _walk(p, 0.0, 5.0, (0.0, 0.0))
    (track,) = p.lidar.tracker.confirmed()
    p.lidar.tracker.set_kind(track.track_id, int(ObjectKind.HOSTILE))
    _walk(p, 6.25, 6.25, (3.75, 0.0))  # labelled, measured once more
    assert len(p.hostile_tracks_in_odom(6.25)) == 1
    for k in range(1, 7):  # six sweeps unseen: the tracker drops it
        p.lidar.tracker.update(6.25 + 1.25 * k, np.zeros((0, 2)))
        p._report_people(6.25 + 1.25 * k)
    assert not p.lidar.tracker.tracks and not len(p.hostile_tracks_in_odom(13.75))
    # seen again 9 s after its last sighting, where its walk has taken it (+5.4 m), and a
    # second walker 4 m to the side
    for t in (15.0, 16.25, 17.5):
        p.lidar.tracker.update(t, [[3.75 + 0.6 * (t - 6.25), 0.0], [3.75 + 0.6 * (t - 6.25), 4.0]])
        p._now = t
        p._report_people(t)
    hostiles = p.hostile_tracks_in_odom(17.5)
    assert len(hostiles) == 1, hostiles
    assert abs(hostiles[0, 1]) < 0.5 and hostiles[0, 0] > 9.0, hostiles
    kinds = {kind for kind, _, _ in p.own_hazards_in_odom()}
    assert kinds == {ObjectKind.HOSTILE}


def _tag_image(request_id: int, time_s: float, mates: list[int]) -> CameraImage:
    """A coarse image showing one head face of each teammate in ``mates``."""
    import cv2

    from sim.apriltag import tag_texture

    img = _image(request_id, time_s)
    for k, mate in enumerate(mates):
        face = cv2.resize(tag_texture(4 * mate), (60, 60), interpolation=cv2.INTER_AREA)
        img.rgb[90:150, 20 + 90 * k : 80 + 90 * k] = face
    return img


def test_a_teammates_pose_is_asked_again_only_after_the_refresh() -> None:
    """A coarse image showing a teammate's tag asks for a fine image of its frame, unless that
    teammate's pose was asked within ``fiducial_refresh_s``; a teammate new to the robot is
    asked at once, and the fine image is asked for every teammate it shows."""
    cfg = PerceptionConfig(fiducial_period_s=0.0, fiducial_refresh_s=3.0, image_timeout_s=60.0)
    p = OnboardPerception(0, cfg)

    def coarse(t: float, mates: list[int]) -> bool:
        """Whether the image of ``mates`` at ``t`` asked for a fine image."""
        p._now = t
        p._ask(t, [])
        (req,) = p.take_requests()
        p.on_image(_tag_image(req.request_id, t, mates), _pose_at)
        fine = p.take_requests()
        assert all(r.width_px == cfg.fiducial_width_px for r in fine)
        return len(fine) == 1

    assert coarse(1.0, [1])
    assert not coarse(2.0, [1])  # asked 1 s ago
    assert coarse(2.5, [1, 2])  # 2 is new: one fine image for both
    assert not coarse(4.1, [1])  # 1.6 s since the last
    assert not coarse(5.0, [2])
    assert coarse(5.6, [1])  # 3.1 s
    assert not coarse(6.0, [])  # no tag: nothing to ask
    assert p.stats.fiducial_fine_images == 3 and p.stats.fiducial_fine_skipped == 3
    every = OnboardPerception(0, PerceptionConfig(fiducial_period_s=0.0, fiducial_refresh_s=0.0))
    p = every
    assert coarse(1.0, [1]) and coarse(1.05, [1])  # 0: every time


def test_an_image_asked_for_a_candidate_stands_for_the_periodic_tag_image() -> None:
    """Every coarse image is searched for tags: the periodic image of now comes a period
    after the newest frame any coarse image was asked of."""
    from robot.perception.onboard_perception import _Job

    p = OnboardPerception(0, NO_GATE)
    p.pan_phase_s = PHASE_S
    p.on_control(10.0, np.zeros(3))
    assert [r.time_s for r in p.take_requests()] == [10.0]  # the periodic one
    p._ask(10.4, [_Job("cylinder", (3.0, 0.0), 0.3, 0.8)])  # a candidate's frame
    assert [r.time_s for r in p.take_requests()] == [10.4]
    p.on_control(11.05, np.zeros(3))
    assert p.take_requests() == []  # 0.65 s after the candidate's frame
    p.on_control(11.45, np.zeros(3))
    assert [r.time_s for r in p.take_requests()] == [11.45]


def test_a_lidar_candidate_at_a_teammate_just_seen_asks_for_no_image() -> None:
    """An image (a real render, 640x480: a tag's decoding range) showing teammate 1's tag
    places its head in ``odom`` (bearing from the tag, range from its height in pixels)
    within 0.3 m of the truth, at 2-3 m and turned; a candidate there then asks for no
    image, one 3 m aside does, and so does one there after ``teammate_memory_s``."""
    from sim.camera import CameraConfig, camera_axes, intrinsics
    from sim.scene import Scene
    from tests.sim.simworlds import make_world

    cam = CameraConfig()
    scene = Scene(make_world(robots=((5.0, 10.0, 0.0, "sensor"), (7.0, 10.0, 2.0, "sensor"))))
    try:
        for dist, yaw in ((2.0, 2.6), (3.0, 3.1), (3.0, -2.0)):
            p = OnboardPerception(0, PerceptionConfig(fiducial_period_s=0.0))
            observer = np.eye(4)
            observer[:3, 3] = (5.0, 10.0, 0.0)
            mate = np.eye(4)
            mate[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
            mate[:3, 3] = (5.0 + dist, 10.3, 0.0)
            scene.set_robot_poses(np.stack([observer, mate]))
            eye, fwd, up = camera_axes(
                observer, np.array(scene.geometry.camera_m), 0.0, cam.tilt_rad
            )
            w, h = 640, 480
            fx, fy, cx, cy = intrinsics(w, h, cam)
            rgb = scene.render(eye_m=eye, forward=fwd, up=up, width_px=w, height_px=h, fy_px=fy)
            p._now = 10.0
            p._ask(10.0, [])
            (req,) = p.take_requests()
            image = CameraImage(req.request_id, 10.0, 0.0, cam.tilt_rad, fx, fy, cx, cy, rgb)
            # the robot's odom is its start: the observer at (5, 10) is (0, 0) in odom
            p.on_image(image, _pose_at)
            assert p._teammates_seen, f"teammate at {dist} m not seen"
            _, x, y = p._teammates_seen[-1]
            truth = (dist - 0.12 * math.cos(yaw), 0.3 - 0.12 * math.sin(yaw))  # its head
            assert math.hypot(x - truth[0], y - truth[1]) < 0.3, (dist, (x, y), truth)
            assert p._at_teammate((dist, 0.3), 10.5)
            assert not p._at_teammate((dist, 3.3), 10.5)
            assert not p._at_teammate((dist, 0.3), 12.0)  # 2 s later: asked again
    finally:
        scene.close()


def test_a_colour_tests_image_is_as_small_as_its_candidates_allow() -> None:
    """A candidate covers colour_min_area_px (600) in the smallest 4:3 image of
    colour_widths_px: 0.25 m radius, 0.8 m tall at 3 m -> 160x120, at 4.5 m -> 240x180, at
    6 m the memory's 320x240 (beyond 5.4 m); a 0.1 m pole at 2 m 160x120; the farthest job
    of an image decides; 0: the memory's size. A small image does not stand for the
    periodic tag image."""
    from robot.perception.onboard_perception import _Job

    def size(cfg: PerceptionConfig, *ranges: float, radius_m: float = 0.25) -> tuple[int, int]:
        p = OnboardPerception(0, cfg)
        jobs = [_Job("cylinder", (r, 1.0), radius_m, 0.8) for r in ranges]
        p._ask(5.0, jobs, pose=(0.0, 1.0, 0.3))
        (req,) = p.take_requests()
        return req.width_px, req.height_px

    cfg = PerceptionConfig()
    assert size(cfg, 3.0) == (160, 120)
    assert size(cfg, 4.5) == (240, 180)
    assert size(cfg, 6.0) == (320, 240)
    assert size(cfg, 1.5, 4.5) == (240, 180)
    assert size(cfg, 2.0, radius_m=0.1) == (160, 120)
    assert size(cfg, 3.0, radius_m=0.1) == (240, 180)
    assert size(PerceptionConfig(colour_min_area_px=0.0), 1.5) == (320, 240)
    p = OnboardPerception(0, NO_GATE)
    p.pan_phase_s = PHASE_S
    p.on_control(10.0, np.zeros(3))
    p.take_requests()
    p._ask(10.4, [_Job("cylinder", (1.5, 0.0), 0.25, 0.8)], pose=(0.0, 0.0, 0.0))
    assert [(r.width_px, r.time_s) for r in p.take_requests()] == [(160, 10.4)]
    p.on_control(11.05, np.zeros(3))
    assert [r.time_s for r in p.take_requests()] == [11.05]  # the periodic one, on time


def test_cylinders_of_one_sweep_share_a_frame_that_shows_them_all() -> None:
    """A cylinder whose newest frame is newer than one chosen for another (a person's here)
    that shows it whole joins that one: one image; one that frame does not show keeps its
    own; with colour_group_s 0 each its own."""
    from robot.perception.image_memory import Candidate, RememberedFrame
    from robot.perception.onboard_perception import _Job

    def group(cfg: PerceptionConfig) -> tuple[list[tuple[float, list[str]]], int]:
        p = OnboardPerception(0, cfg)
        older = RememberedFrame(1.0, 0.0, MOUNT.tilt_rad, (0.0, 0.0, 0.0))
        newer = RememberedFrame(1.5, 0.1, MOUNT.tilt_rad, (0.0, 0.0, 0.0))
        behind = RememberedFrame(1.2, math.pi, MOUNT.tilt_rad, (0.0, 0.0, 0.0))
        a = _Job("cylinder", (4.0, 0.0), 0.25, 0.8)  # ahead: in both frames
        b = _Job("cylinder", (4.0, 0.3), 0.25, 0.8)
        c = _Job("cylinder", (-4.0, 0.1), 0.25, 0.8)  # behind
        person = _Job("person", (4.0, -0.2), 0.3, 1.6, 7)
        for f, j in ((newer, a), (older, a), (older, b), (behind, c), (older, person)):
            assert p.memory.projects_fully(f, Candidate(j.xy_in_odom, j.radius_m, j.height_m))
        assert not p.memory.projects_fully(behind, Candidate(a.xy_in_odom, 0.25, 0.8))
        grouped = p._group_by_frame([(newer, a), (older, b), (behind, c), (older, person)])
        out = [(f.time_s, sorted(f"{j.kind}{j.xy_in_odom[1]}" for j in js)) for f, js in grouped]
        return out, p.stats.colour_jobs_grouped

    assert group(PerceptionConfig()) == (
        [(1.2, ["cylinder0.1"]), (1.0, ["cylinder0.0", "cylinder0.3", "person-0.2"])],
        1,
    )
    assert group(PerceptionConfig(colour_group_s=0.0)) == (
        [(1.5, ["cylinder0.0"]), (1.2, ["cylinder0.1"]), (1.0, ["cylinder0.3", "person-0.2"])],
        0,
    )


def test_a_person_track_an_image_shows_as_a_teammate_is_not_asked_about_again() -> None:
    """A person job placed where the image (a real render, 320x240, teammate 1 at 1.9 m)
    shows teammate 1's tags is that teammate: no colour test, and the track asks for no
    image for teammate_track_hold_s; a person job 3 m aside of it is tested as before."""
    from robot.perception.onboard_perception import _Job
    from robot.perception.person_tracker import PersonTrack
    from sim.camera import CameraConfig, camera_axes, intrinsics
    from sim.scene import Scene
    from tests.sim.simworlds import make_world

    cam = CameraConfig()
    scene = Scene(make_world(robots=((5.0, 10.0, 0.0, "sensor"), (6.8, 10.3, -2.0, "sensor"))))
    try:
        observer = np.eye(4)
        observer[:3, 3] = (5.0, 10.0, 0.0)
        mate = np.eye(4)
        mate[:2, :2] = [[math.cos(-2.0), -math.sin(-2.0)], [math.sin(-2.0), math.cos(-2.0)]]
        mate[:3, 3] = (6.8, 10.3, 0.0)
        scene.set_robot_poses(np.stack([observer, mate]))
        scene.sync()
        eye, fwd, up = camera_axes(observer, np.array(scene.geometry.camera_m), 0.0, cam.tilt_rad)
        fx, fy, cx, cy = intrinsics(320, 240, cam)
        rgb = scene.render(eye_m=eye, forward=fwd, up=up, width_px=320, height_px=240, fy_px=fy)
    finally:
        scene.close()
    cfg = PerceptionConfig(fiducial_period_s=0.0, teammate_track_hold_s=10.0)
    p = OnboardPerception(0, cfg)
    p._now = 10.0
    # the robot's odom is its start: the teammate's head is near (1.85, 0.4) in odom
    at_mate = _Job("person", (1.85, 0.4), 0.3, 1.6, 7)
    aside = _Job("person", (1.85, -2.6), 0.3, 1.6, 8)
    p._ask(10.0, [at_mate, aside])
    (req,) = p.take_requests()
    p.on_image(CameraImage(req.request_id, 10.0, 0.0, cam.tilt_rad, fx, fy, cx, cy, rgb), _pose_at)
    assert p.stats.teammate_tracks == 1 and 7 in p._teammate_tracks and 8 not in p._teammate_tracks
    assert p.stats.colour_tests == 1  # the one aside only

    def track(track_id: int, x: float, y: float) -> PersonTrack:
        state = np.array([x, y, 0.0, 0.0])
        return PersonTrack(track_id, state, np.eye(4) * 0.01, 15.0, hits=8, confirmed=True)

    jobs: list[Any] = []
    before = p.stats.teammate_candidates
    p._person_jobs(track(7, 1.85, 0.4), 15.0, jobs)
    assert jobs == [] and p.stats.teammate_candidates == before + 1  # held: no image
    p._person_jobs(track(7, 1.85, 0.4), 20.5, jobs)  # 10.5 s on: no longer held
    assert 7 not in p._teammate_tracks and p.stats.teammate_candidates == before + 1


def test_the_periodic_tag_image_is_asked_only_when_it_may_show_a_teammate_or_a_person() -> None:
    """A teammate (chassis and head, boxes in a simulated sweep through the real LIDAR
    detector) 4 m away where the camera of now points: the periodic tag image is asked.
    Nothing but the ground, the teammate behind the camera's view, 8 m away, or seen only in
    a sweep older than ``tag_gate_memory_s``: no image (the period is counted as gated),
    until the gate is off. A person track 9 m away in view, not labelled yet: the image is
    asked (its colour test)."""
    from tests.robot.perception.test_lidar_shape import _scan

    def mate(x: float) -> list[tuple[float, ...]]:
        return [
            (x - 0.3, -0.25, 0.12, x + 0.3, 0.25, 0.42),
            (x - 0.1, -0.1, 0.65, x + 0.1, 0.1, 0.85),
        ]

    ground = _scan()
    near, far = _scan(boxes=mate(4.0)), _scan(boxes=mate(8.0))
    person = _scan(cylinders=[(9.0, 0.0, 0.25, 0.0, 1.7)])
    now = 10.0
    toward = -pan_at(now, MOUNT, PHASE_S)  # the yaw that points the camera of now along +x

    def periodic(
        points: np.ndarray,
        yaw: float,
        *,
        sweeps_s: tuple[float, ...] = (9.4,),
        cfg: PerceptionConfig | None = None,
    ) -> tuple[list[float], int]:
        p = OnboardPerception(0, cfg or PerceptionConfig(image_timeout_s=60.0))
        p.pan_phase_s = PHASE_S
        # the robot placed so that its LIDAR (0.2 m ahead of base) is at the sweep's origin
        pose = np.array([-0.2 * math.cos(yaw), -0.2 * math.sin(yaw), yaw])
        for t in sweeps_s:
            p.on_sweep(points, pose, t)
        p.take_requests()  # the colour tests the sweeps asked for
        p.on_control(now, pose)
        return [r.time_s for r in p.take_requests()], p.stats.fiducial_periodic_gated

    assert periodic(near, toward) == ([now], 0)
    assert periodic(ground, toward) == ([], 1)
    assert periodic(near, toward + math.pi) == ([], 1)
    assert periodic(far, toward) == ([], 1)
    assert periodic(near, toward, sweeps_s=(now - 3.0,)) == ([], 1)
    assert periodic(ground, toward, cfg=NO_GATE) == ([now], 0)
    assert periodic(person, toward, sweeps_s=(6.25, 7.5, 8.75)) == ([now], 0)
    assert periodic(person, toward + math.pi, sweeps_s=(6.25, 7.5, 8.75)) == ([], 1)
