"""The in-process simulator with real PyBullet: driver contract, LIDAR, camera and AprilTags,
rules with real lines of sight, bad commands, lockstep, repeatability."""

from __future__ import annotations

import math
import threading

import cv2
import msgspec
import numpy as np
import pytest

from protocol.sensors import (
    BatteryState,
    CameraImage,
    ImageRequest,
    ImuSample,
    LaserPointerCommand,
    LidarSweep,
    RobotDriver,
    VelocityCommand,
    WheelTicks,
)
from sim.camera import CameraConfig
from sim.lidar import LidarConfig
from sim.simulator import CommandError, Simulator, SimulatorConfig, load_world_config
from sim.world_generator import Human, Ooi
from tests.sim.simworlds import REPO, box, make_world

SMALL = REPO / "configs/world/small.yaml"


def _sweeps(frames):
    return [f for f in frames if isinstance(f, LidarSweep)]


def _run_until_sweep(sim: Simulator, robot_id: int = 0, max_s: float = 5.0) -> LidarSweep:
    d = sim.driver(robot_id)
    for _ in range(int(max_s / sim.config.step_s)):
        sim.step()
        got = _sweeps(d.poll(0.0))
        if got:
            return got[0]
    raise AssertionError("no sweep")


def test_driver_contract_and_sensor_frames() -> None:
    with Simulator(make_world()) as sim:
        d = sim.driver(0)
        assert isinstance(d, RobotDriver) and d.robot_id == 0
        sim.run_for(1.3)
        frames = d.poll(0.0)
        kinds = {type(f) for f in frames}
        assert {ImuSample, WheelTicks, LidarSweep} <= kinds
        imu = [f for f in frames if isinstance(f, ImuSample)]
        acc = np.array([f.linear_acceleration_m_s2 for f in imu])
        assert np.allclose(acc.mean(0), [0, 0, 9.81], atol=0.1)  # gravity, standing still
        times = [f.time_s for f in imu]
        assert times == sorted(times) and times[-1] == pytest.approx(sim.time_s)
        battery = [f for f in frames if isinstance(f, BatteryState)]
        assert [b.time_s for b in battery] == pytest.approx([1.0])  # once a second
        assert 0.99 < battery[0].charge_frac < 1.0  # 720 Wh drain slowly
        assert d.poll(0.0) == []
        with pytest.raises(KeyError, match="no robot 7"):
            sim.driver(7)


def test_lidar_ranges_to_a_known_wall_match_within_the_noise() -> None:
    wall = box("wall", 15.0, 2.0, 15.2, 18.0, 2.5)
    cfg = SimulatorConfig(lidar=LidarConfig(range_noise_m=0.01))
    with Simulator(
        make_world(solids=[wall], robots=[(10.0, 10.0, 0.0, "sensor")]), config=cfg
    ) as sim:
        sweep = _run_until_sweep(sim)
        p = sweep.points_in_base
        assert p.dtype == np.float32 and sweep.point_time_s.shape == (len(p),)
        on_wall = p[(p[:, 2] > 0.1) & (p[:, 0] > 3.0)]
        assert len(on_wall) > 500
        err = on_wall[:, 0] - 5.0  # wall face 5 m ahead of the base origin
        assert np.abs(err).max() < 5 * 0.01
        assert abs(err.mean()) < 0.003 and 0.005 < err.std() < 0.015
        ground = p[p[:, 2] < 0.05]
        assert np.abs(ground[:, 2]).max() < 0.05  # flat ground at z = 0 in base
        assert (
            0.0 <= sweep.point_time_s.min() and sweep.point_time_s.max() <= sweep.duration_s + 1e-6
        )
        assert sweep.duration_s == pytest.approx(1.25 - 1.25 / 25, abs=0.051)
        # no hits on the robot itself
        own = (np.abs(p[:, 0]) < 0.35) & (np.abs(p[:, 1]) < 0.3)
        assert not own.any()


def _run_small(steps: int) -> tuple[str, list[LidarSweep]]:
    with Simulator(load_world_config(SMALL)) as sim:
        for rid in sim.robot_ids:
            sim.driver(rid).send(VelocityCommand(time_s=0.0, linear_m_s=0.7, angular_rad_s=0.3))
        for _ in range(steps):
            sim.step()
        return sim.world.fingerprint(), _sweeps(sim.driver(1).poll(0.0))


def test_same_seed_gives_the_same_world_and_the_same_sweep() -> None:
    a_world, a = _run_small(60)
    b_world, b = _run_small(60)
    assert a_world == b_world
    assert len(a) == len(b) >= 2
    for sa, sb in zip(a, b, strict=True):
        assert msgspec.msgpack.encode(sa.time_s) == msgspec.msgpack.encode(sb.time_s)
        assert np.array_equal(sa.points_in_base, sb.points_in_base)
        assert np.array_equal(sa.point_time_s, sb.point_time_s)


def _detect(rgb: np.ndarray) -> list[int]:
    det = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
        cv2.aruco.DetectorParameters(),
    )
    _, ids, _ = det.detectMarkers(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY))
    return [] if ids is None else sorted(int(i) for i in ids.ravel())


@pytest.mark.parametrize(
    ("yaw", "face"), [(math.pi, 0), (math.pi / 2, 1), (0.0, 2), (-math.pi / 2, 3)]
)
def test_a_tag_rendered_at_2_m_is_decoded_with_the_right_id(yaw: float, face: int) -> None:
    # robot 1's head face towards robot 0's camera (x = 9.88) is 2 m away, whichever face;
    # each face has its own id, 4 robot + face (front, left, back, right)
    head_x = 9.88 + 2.0 + 0.1
    robots = [
        (10.0, 10.0, 0.0, "sensor"),
        (head_x + 0.12 * math.cos(yaw), 10.0, yaw, "sensor"),  # head is 0.12 m behind base
        (10.0, 14.0, 0.0, "sensor"),
    ]
    cfg = SimulatorConfig(camera=CameraConfig(pan_rate_rad_s=0.0))
    with Simulator(make_world(robots=robots), config=cfg) as sim:
        sim.driver(0).send(ImageRequest(request_id=5, time_s=sim.time_s))
        sim.step()
        images = [f for f in sim.driver(0).poll(0.0) if isinstance(f, CameraImage)]
        assert len(images) == 1
        img = images[0]
        assert img.request_id == 5 and img.rgb.shape == (240, 320, 3)
        assert img.fx_px == pytest.approx(160 / math.tan(math.radians(30)))
        assert _detect(img.rgb) == [4 * 1 + face]


def test_tags_are_found_up_to_about_4_m_at_640x480() -> None:
    # paper 4.3.2: robots detected each other up to about 5 m (752 x 480 camera)
    robots = [(10.0, 10.0, 0.0, "sensor"), (9.88 + 4.0 + 0.1 - 0.12, 10.0, math.pi, "sensor")]
    cfg = SimulatorConfig(camera=CameraConfig(pan_rate_rad_s=0.0))
    with Simulator(make_world(robots=robots), config=cfg) as sim:
        sim.driver(0).send(ImageRequest(request_id=1, time_s=0.0, width_px=640, height_px=480))
        sim.step()
        img = next(f for f in sim.driver(0).poll(0.0) if isinstance(f, CameraImage))
        assert _detect(img.rgb) == [4 * 1 + 0]  # robot 1's front face


def test_images_come_from_the_recorded_camera_pose_of_the_requested_time() -> None:
    robots = [(10.0, 10.0, 0.0, "sensor"), (12.0, 10.0, math.pi, "sensor")]
    # every frame drawn (a frame of terrain only would be flat: tests/sim/test_camera_frustum)
    cfg = SimulatorConfig(camera=CameraConfig(skip_empty=False))
    with Simulator(make_world(robots=robots), config=cfg) as sim:
        sim.run_for(2.0)
        t_past = 1.0
        sim.driver(0).send(ImageRequest(request_id=1, time_s=t_past))
        sim.driver(0).send(ImageRequest(request_id=2, time_s=sim.time_s))
        sim.step()
        img = {f.request_id: f for f in sim.driver(0).poll(0.0) if isinstance(f, CameraImage)}
        assert img[1].time_s == pytest.approx(t_past)
        assert img[1].camera_pan_rad == pytest.approx(sim.camera_pan(0, t_past))
        assert img[1].camera_pan_rad != pytest.approx(img[2].camera_pan_rad)
        assert not np.array_equal(img[1].rgb, img[2].rgb)


def test_nan_and_inf_commands_are_refused_clearly_and_the_simulator_runs_on() -> None:
    with Simulator(make_world()) as sim:
        d = sim.driver(0)
        d.send(VelocityCommand(time_s=0.0, linear_m_s=0.5, angular_rad_s=0.0))
        bad = [
            (
                VelocityCommand(time_s=0.0, linear_m_s=math.nan, angular_rad_s=0.0),
                r"robot 0: VelocityCommand.linear_m_s = nan: must be a finite number",
            ),
            (
                VelocityCommand(time_s=0.0, linear_m_s=0.1, angular_rad_s=math.inf),
                r"robot 0: VelocityCommand.angular_rad_s = inf",
            ),
            (
                LaserPointerCommand(time_s=0.0, on=True, pan_rad=-math.inf, tilt_rad=0.0),
                r"robot 0: LaserPointerCommand.pan_rad = -inf",
            ),
            (
                ImageRequest(request_id=1, time_s=0.0, width_px=0, height_px=240),
                r"robot 0: ImageRequest.width_px = 0",
            ),
            ("drive!", r"robot 0: not a robot command: str"),
        ]
        for cmd, msg in bad:
            with pytest.raises(CommandError, match=msg):
                d.send(cmd)  # type: ignore[arg-type]
        assert sim.rejected_commands == len(bad)
        for k in range(4):
            d.send(ImageRequest(request_id=k, time_s=0.0))
        with pytest.raises(CommandError, match="robot 0: ImageRequest refused: 4 already pending"):
            d.send(ImageRequest(request_id=9, time_s=0.0))
        sim.step()
        assert len([f for f in d.poll(0.0) if isinstance(f, CameraImage)]) == 4
        sim.run_for(2.0)
        assert sim.robot_poses()[0, 0] > 5.5  # still driving on the last good command
        assert np.isfinite(sim.robot_poses()).all()


def test_laser_neutralizes_a_static_ooi_only_with_line_of_sight() -> None:
    ooi = Ooi(0, "static_ooi", (16.0, 10.0), 0.25, 0.8, (1, 0.3, 0, 1))
    ooi2 = Ooi(1, "static_ooi", (16.0, 4.0), 0.25, 0.8, (1, 0.3, 0, 1))
    wall = box("wall", 14.0, 2.0, 14.15, 6.0, 2.5)  # hides the second one
    robots = [(10.0, 10.0, 0.0, "disruptor"), (10.0, 4.0, 0.0, "disruptor")]
    with Simulator(make_world(solids=[wall], oois=[ooi, ooi2], robots=robots)) as sim:
        head_x, head_z = 10.0 - 0.12, 0.75
        tilt = math.atan2(0.4 - head_z, 16.0 - head_x)
        for rid in (0, 1):
            sim.driver(rid).send(
                LaserPointerCommand(time_s=0.0, on=True, pan_rad=0.0, tilt_rad=tilt)
            )
        sim.run_for(14.9)
        assert sim.events == []
        sim.run_for(0.2)
        assert [(e.kind, e.subject) for e in sim.events] == [("neutralized", "static_ooi:0")]
        assert sim.events[0].time_s == pytest.approx(15.05)
        sim.run_for(5.0)
        assert len(sim.events) == 1  # the hidden one never is


def test_driving_into_a_static_ooi_detonates_it_and_disables_robots_in_the_blast() -> None:
    ooi = Ooi(0, "static_ooi", (15.0, 10.0), 0.25, 0.8, (1, 0.3, 0, 1))
    civ = Human(0, "civilian", ((15.0, 18.0),), 0.5, 0.25, 1.7, (0.1, 0.2, 0.9, 1))
    robots = [(10.0, 10.0, 0.0, "sensor"), (10.0, 16.0, 0.0, "sensor"), (26.0, 10.0, 0.0, "sensor")]
    with Simulator(make_world(oois=[ooi], humans=[civ], robots=robots)) as sim:
        sim.driver(0).send(VelocityCommand(time_s=0.0, linear_m_s=1.0, angular_rad_s=0.0))
        sim.run_for(6.0)
        kinds = [(e.kind, e.subject) for e in sim.events]
        assert kinds[0] == ("detonation", "static_ooi:0")
        assert ("robot_lost", "robot:0") in kinds and ("robot_lost", "robot:1") in kinds
        assert ("civilian_harmed", "civilian:0") in kinds
        assert ("robot_lost", "robot:2") not in kinds
        x_at = sim.robot_poses()[0, 0]
        assert 15.0 - x_at == pytest.approx(2.5, abs=0.06)  # triggered at 2.5 m
        assert list(sim.alive()) == [False, False, True]
        sim.driver(0).poll(0.0)
        sim.run_for(1.0)
        assert sim.driver(0).poll(0.0) == []  # a destroyed robot is silent
        assert sim.radio_grants()[0].uplink_bps == 0.0


def test_two_sensor_robots_neutralize_a_hostile_with_a_30_s_visual_lock() -> None:
    host = Human(0, "hostile", ((15.0, 10.0),), 0.5, 0.25, 1.7, (0.9, 0.05, 0.05, 1))
    robots = [
        (9.0, 10.0, 0.0, "sensor"),
        (15.0, 16.0, 0.0, "sensor"),
        (15.0, 4.0, 0.0, "disruptor"),
    ]
    with Simulator(make_world(humans=[host], robots=robots)) as sim:
        sim.run_for(29.9)
        assert sim.events == []
        sim.run_for(0.2)
        assert [(e.kind, e.subject, e.robots) for e in sim.events] == [
            ("neutralized", "hostile:0", (0, 1))
        ]


def test_lockstep_waits_for_every_node_to_answer_its_sweep() -> None:
    robots = [(10.0, 10.0, 0.0, "sensor"), (10.0, 14.0, 0.0, "sensor")]
    with Simulator(make_world(robots=robots)) as sim:
        for _ in range(30):
            sim.step()  # both robots' first sweeps are out
        assert sim.driver(0).last_sweep_sent == 0 and sim.driver(1).last_sweep_sent == 0
        assert sim.ready()  # no node attached: nobody to wait for
        sim.driver(0).poll(0.0)  # robot 0's node shows up
        assert not sim.ready() and not sim.wait_ready(0.01)
        sim.driver(1).poll(0.0)
        assert not sim.ready()  # reading is not answering (default lockstep_ack: command)
        for rid in (0, 1):
            t = sim.driver(rid).last_sweep_time_s
            sim.driver(rid).send(VelocityCommand(time_s=t, linear_m_s=0.0, angular_rad_s=0.0))
        assert sim.ready()

    cfg = SimulatorConfig(lockstep_ack="poll")
    with Simulator(make_world(robots=robots), config=cfg) as sim:
        for rid in (0, 1):
            sim.driver(rid).poll(0.0)
        for _ in range(30):
            sim.step()
        assert not sim.ready()
        sim.driver(0).poll(0.0)
        assert not sim.ready()
        sim.driver(1).poll(0.0)
        assert sim.ready()


def _lockstep_run(steps: int) -> tuple[list[LidarSweep], np.ndarray]:
    """Two nodes in threads that answer every sweep with a command depending on it."""
    robots = [(10.0, 10.0, 0.0, "sensor"), (10.0, 14.0, 0.3, "sensor")]
    wall = box("wall", 16.0, 2.0, 16.2, 18.0, 2.5)
    sweeps: list[LidarSweep] = []
    stop = threading.Event()
    with Simulator(make_world(solids=[wall], robots=robots)) as sim:

        def node(rid: int) -> None:
            d = sim.driver(rid)
            while not stop.is_set():
                for f in d.poll(0.02):
                    if isinstance(f, LidarSweep):
                        if rid == 0:
                            sweeps.append(f)
                        p = f.points_in_base
                        ahead = p[(np.abs(p[:, 1]) < 0.3) & (p[:, 2] > 0.15) & (p[:, 0] > 0)]
                        near = float(ahead[:, 0].min()) if len(ahead) else 30.0
                        v = 0.8 if near > 2.0 else 0.0
                        d.send(VelocityCommand(time_s=f.time_s, linear_m_s=v, angular_rad_s=0.1))

        threads = [threading.Thread(target=node, args=(r,), daemon=True) for r in (0, 1)]
        for t in threads:
            t.start()
        try:
            for _ in range(steps):
                assert sim.wait_ready(10.0)
                sim.step()
        finally:
            stop.set()
            for t in threads:
                t.join(5.0)
        return sweeps, sim.robot_poses()


def test_a_lockstep_run_with_nodes_in_threads_repeats_exactly() -> None:
    a_sweeps, a_poses = _lockstep_run(150)
    b_sweeps, b_poses = _lockstep_run(150)
    assert len(a_sweeps) >= 5
    assert np.array_equal(a_poses, b_poses)
    assert a_poses[0, 0] > 11.0  # the nodes did drive
    n = min(len(a_sweeps), len(b_sweeps))
    for sa, sb in zip(a_sweeps[:n], b_sweeps[:n], strict=True):
        assert np.array_equal(sa.points_in_base, sb.points_in_base)


def test_a_steps_motion_comes_before_the_sweep_it_ends() -> None:
    """A node deskews a sweep with its odometry: the step's IMU sample and encoder ticks
    must be in its hands before the sweep that ends at the same instant."""
    with Simulator(make_world()) as sim:
        d = sim.driver(0)
        seen = 0
        for _ in range(60):
            d.send(VelocityCommand(sim.time_s, 0.0, 0.5))
            sim.step()
            kinds = [type(f) for f in d.poll(0.0)]
            if LidarSweep in kinds:
                seen += 1
                i = kinds.index(LidarSweep)
                assert ImuSample in kinds[:i] and WheelTicks in kinds[:i]
        assert seen >= 2
