"""The in-process simulator: a world, a team of robots, their sensors, the rules and the radio.

Typical use (a robot node gets a :class:`SimDriver`, the protocol's ``RobotDriver``)::

    sim = Simulator(load_world_config("configs/world/small.yaml"))
    driver = sim.driver(0)                      # RobotDriver for robot 0
    driver.send(VelocityCommand(time_s=sim.time_s, linear_m_s=0.5, angular_rad_s=0.0))
    sim.run_for(2.5)                            # or sim.step() in your own loop
    frames = driver.poll(timeout_s=0.0)         # ImuSample, WheelTicks, LidarSweep, ...
    grants = sim.radio_grants()                 # {robot_id: RadioGrant}

Each :meth:`Simulator.step` (``step_s``, 50 ms by default) applies the latest commands
(accelerations limited), moves the people along their routes and the robots over the terrain
(:mod:`sim.robot_body`), casts the LIDAR lines that fell due for every robot as one batch
(:mod:`sim.lidar`), samples IMU and encoders, renders requested camera images from the
camera pose recorded at the requested time (:mod:`sim.camera`), applies the rules
(:mod:`sim.rules`: triggers, blasts, laser and visual-lock neutralization) and, every
``radio_period_s``, the radio model (:mod:`sim.radio_model`). Frames go to each robot's
driver queue (bounded: the oldest are dropped and counted when nobody reads).

Lockstep (repeatable runs): :meth:`ready` is true when every live robot's node has answered
its latest sweep with a command (any command stamped at or after the sweep's ``time_s``, in
process or over the network); a runner steps only then (:meth:`wait_ready`). A robot counts
once its node has polled its driver or sent a command: robots nobody drives never hold the
world back. Because the answer is the command itself, it is always applied at the same
step: a seeded run repeats exactly. ``lockstep_ack: poll`` also counts a sweep polled in
process as consumed (for nodes that never command; not repeatable if they do). Threads:
drivers may be used from any thread; stepping happens on one thread.

Seeded throughout: the same world config and ``SimulatorConfig.seed`` with the same commands
at the same steps give the same sweeps.

Cost (issue 14, session 14; quick mission, small world, 300 mission-s, at 38fac2c, seeds 0 /
7, one run each at load ~12, thread CPU, reports identical): a run costs 120.5 / 116.7 CPU-s
(0.40 / 0.39 CPU-s a mission-s): the render worker 22.7 / 20.6 (TinyRenderer, ~11 ms a
320 x 240 image, ~1750 images; pixels cannot be cut without changing them), the LIDAR and
rule ray casts 11.3 / 10.4 on this thread plus ~6.5 on PyBullet's second ray thread
(rayTestBatch: ~4.2 us a ray that hits a body, ~1.2 us one that does not; a padded
bounding-box pre-filter that skipped the rays crossing no box left 48 % of them out but
saved nothing: Bullet's broadphase already answers those in ~0.3 us), the rest of the step
~10 (bodies 3.3, rules 1.8, scene sync 1.4, LIDAR bookkeeping 1.5); the robot nodes 45 / 42,
the GCS 11.6 / 13.6. Whether a frame shows anything (:meth:`Simulator._frame_has_subjects`)
is asked at a request and again at its rendering: kept between them (render_image 0.62 ->
0.11 CPU-s).
"""

from __future__ import annotations

import bisect
import collections
import logging
import math
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import msgspec
import numpy as np

from protocol.clock import ManualClock
from protocol.config import load_config
from protocol.radio import RadioConfig, RadioGrant
from protocol.sensors import (
    BatteryState,
    CameraImage,
    ImageRequest,
    ImuSample,
    LaserPointerCommand,
    LidarSweep,
    RobotCommand,
    SensorFrame,
    VelocityCommand,
    WheelTicks,
)
from sim.actors import PatrolRoutes
from sim.camera import CameraConfig, camera_axes, in_frustum, intrinsics, pan_angle
from sim.ground_truth import GroundTruth, rasterize
from sim.imu import EncoderConfig, ImuConfig, Imus, wheel_ticks
from sim.lidar import LidarConfig, NoddingLidars
from sim.radio_model import RadioBlackouts, RadioModel, RadioState
from sim.render_worker import RenderJob, RenderWorkerProcess
from sim.robot_body import RobotBodyConfig, SkidSteerBodies
from sim.rules import Event, Rules, RulesConfig
from sim.scene import RobotGeometry, Scene
from sim.world_generator import World, WorldConfig, generate_world

__all__ = [
    "CommandError",
    "SimDriver",
    "Simulator",
    "SimulatorConfig",
    "load_world_config",
]

log = logging.getLogger(__name__)

#: Renders cost tens of milliseconds: a node may ask for this many images per step.
_MAX_IMAGE_REQUESTS_PER_STEP = 4


class SimulatorConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``step_s``: simulation step; ``seed``: sensor noise and slip (the world has its own);
    ``queue_limit_frames``: per-driver bound on unread frames. ``ray_threads``: PyBullet's
    threads per ray batch; ``ray_workers``: extra processes with a copy of the scene that cast
    part of each LIDAR batch (-1: one when there are at least ``16`` robots and two cores).
    ``render_workers``: a process with a copy of the scene that renders the camera images
    while the robots and the ground side work, started at the first image request (-1: one
    when there are two cores; 0: images rendered in this process; the same pixels either
    way, :mod:`sim.render_worker`).

    ``step_s`` 0.1 (10 Hz: control, IMU, encoders, two LIDAR lines a step) measured on the
    quick mission (issue 14, session 15, at 8183549, seeds 0 / 7 / 3 / 11, together with
    the perception's 2 s tag images at 240 x 180, see ``PerceptionConfig``): 93.4 / 95.7 /
    99.2 / 92.5 CPU-s a run against 120.8 / 124.8 (seeds 0 / 7) at 0.05 (load 10-16; the
    robot nodes' control 12 -> 7.5, the step 20.5 -> 17, the ground side's per-step work
    halved), but the map worse: ATE median 0.144 -> 0.212 m (0.102 / 0.218 / 0.398 /
    0.207), F1 median 0.906 -> 0.774 (0.849 / 0.767 / 0.724 / 0.781); the same perception
    alone gave 0.195 m / 0.864, so most of the loss is the 10 Hz odometry (the gyro's
    noise and turns integrated at half the rate). Stays 0.05."""

    step_s: float = 0.05
    seed: int = 0
    body: RobotBodyConfig = RobotBodyConfig()
    lidar: LidarConfig = LidarConfig()
    camera: CameraConfig = CameraConfig()
    imu: ImuConfig = ImuConfig()
    encoders: EncoderConfig = EncoderConfig()
    rules: RulesConfig = RulesConfig()
    radio_period_s: float = 1.0
    ray_threads: int = 2
    ray_workers: int = -1
    render_workers: int = -1
    queue_limit_frames: int = 4000
    lockstep_ack: Literal["command", "poll"] = "command"
    battery_period_s: float = 1.0
    # scheduled radio outages (robot_id, start_s, duration_s): sim.radio_model.RadioBlackouts
    radio_blackouts: tuple[tuple[int, float, float], ...] = ()

    def __post_init__(self) -> None:
        if not (math.isfinite(self.step_s) and 0.001 <= self.step_s <= 0.5):
            raise ValueError(f"step_s must be in [0.001, 0.5], got {self.step_s}")
        if not (math.isfinite(self.radio_period_s) and self.radio_period_s > 0):
            raise ValueError(f"radio_period_s must be > 0, got {self.radio_period_s}")
        if not 0 <= self.ray_threads <= 64:
            raise ValueError(f"ray_threads must be in [0, 64], got {self.ray_threads}")
        if not -1 <= self.ray_workers <= 16:
            raise ValueError(f"ray_workers must be in [-1, 16], got {self.ray_workers}")
        if not -1 <= self.render_workers <= 1:
            raise ValueError(f"render_workers must be in [-1, 1], got {self.render_workers}")
        if not (math.isfinite(self.battery_period_s) and self.battery_period_s > 0):
            raise ValueError(f"battery_period_s must be > 0, got {self.battery_period_s}")
        if self.queue_limit_frames < 10:
            raise ValueError(f"queue_limit_frames must be >= 10, got {self.queue_limit_frames}")


def load_world_config(path: str | Path) -> WorldConfig:
    """Read ``configs/world/*.yaml``; errors name the file and the dotted key."""
    return load_config(path, WorldConfig)


class CommandError(ValueError):
    """A command was refused (not finite, out of range, unknown type); the simulator runs on."""


def _finite(robot_id: int, command: object, *names: str) -> None:
    for name in names:
        v = getattr(command, name)
        if not isinstance(v, int | float) or not math.isfinite(v):
            what = f"robot {robot_id}: {type(command).__name__}.{name} = {v!r}"
            raise CommandError(f"{what}: must be a finite number")


def validate_command(robot_id: int, command: RobotCommand) -> None:
    """Raise :class:`CommandError` naming the robot, the field and the value if bad."""
    if isinstance(command, VelocityCommand):
        _finite(robot_id, command, "time_s", "linear_m_s", "angular_rad_s")
    elif isinstance(command, LaserPointerCommand):
        _finite(robot_id, command, "time_s", "pan_rad", "tilt_rad")
    elif isinstance(command, ImageRequest):
        _finite(robot_id, command, "time_s")
        for name in ("width_px", "height_px"):
            v = getattr(command, name)
            if not (isinstance(v, int) and 16 <= v <= 2048):
                raise CommandError(
                    f"robot {robot_id}: ImageRequest.{name} = {v!r}: must be an int in [16, 2048]"
                )
    else:
        raise CommandError(f"robot {robot_id}: not a robot command: {type(command).__name__}")


class SimDriver:
    """The protocol's ``RobotDriver`` for one simulated robot (in process).

    ``poll`` returns the frames since the last call (waiting up to ``timeout_s`` for the
    first); ``send`` validates a command (raising :class:`CommandError` on bad input, which
    leaves the simulator untouched) and hands it to the next step.
    """

    def __init__(self, sim: Simulator, robot_id: int) -> None:
        self.robot_id = robot_id
        self._sim = sim
        self._cond = threading.Condition()
        self._frames: collections.deque[SensorFrame] = collections.deque()
        self.dropped_frames = 0
        self.last_sweep_sent = -1
        self.last_sweep_time_s = -math.inf
        self.last_sweep_consumed = -1

    def _push(self, frames: list[SensorFrame]) -> None:
        limit = self._sim.config.queue_limit_frames
        with self._cond:
            for f in frames:
                if isinstance(f, LidarSweep):
                    self.last_sweep_sent = f.sweep_index
                    self.last_sweep_time_s = f.time_s
                self._frames.append(f)
            while len(self._frames) > limit:
                self._frames.popleft()
                self.dropped_frames += 1
            self._cond.notify_all()

    def poll(self, timeout_s: float) -> list[SensorFrame]:
        with self._cond:
            if not self._frames and timeout_s > 0:
                self._cond.wait_for(lambda: bool(self._frames), timeout=timeout_s)
            out = list(self._frames)
            self._frames.clear()
        self._sim._attach(self.robot_id)
        for f in out:
            if isinstance(f, LidarSweep):
                self._sim._ack_sweep(self.robot_id, f.sweep_index)
        return out

    def send(self, command: RobotCommand) -> None:
        self._sim.command(self.robot_id, command)

    def take_frames(self) -> list[SensorFrame]:
        """Frames waiting, without acknowledging sweeps: for a server forwarding them to a
        remote node (which acknowledges with its commands' ``time_s``)."""
        with self._cond:
            out = list(self._frames)
            self._frames.clear()
        return out


@dataclass(frozen=True)
class _RenderTicket:
    """An image request handed to the render worker: the recorded frame it drew and the
    objects then gone (the worker's image is used only if both still hold at the step)."""

    time_s: float
    hidden_oois: frozenset[int]


#: A robot's bounding sphere for :meth:`Simulator._frame_has_subjects`: centred this high
#: over ``base`` with this radius, it holds the chassis and the tagged head
#: (:class:`sim.scene.RobotGeometry`: the head's far corner is 0.45 m from the centre).
_ROBOT_SPHERE_Z_M = 0.5
_ROBOT_SPHERE_RADIUS_M = 0.8
#: Solids at most this wide (half extent, m) on the obstacle layer are clutter a LIDAR may take
#: for a candidate (trunks, canopies, posts, cars); wider ones and the ground and roof layers
#: are terrain.
_CLUTTER_HALF_EXTENT_M = 2.5


@dataclass(frozen=True)
class _StaticSubjects:
    """Bounding spheres of what never moves but may be looked for: clutter solids first
    (``n_static``), then the objects of interest (``ooi_ids`` in order); and the people's
    sphere sizes (their centres move)."""

    centers_m: np.ndarray
    radii_m: np.ndarray
    n_static: int
    ooi_ids: tuple[int, ...]
    human_radii_m: np.ndarray
    human_half_height_m: np.ndarray

    @staticmethod
    def of(world: World) -> _StaticSubjects:
        clutter = [
            s
            for s in world.solids
            if s.layer == "obstacle" and max(s.half_extents_m[:2]) <= _CLUTTER_HALF_EXTENT_M
        ]
        centers = [s.center_m for s in clutter]
        radii = [float(np.linalg.norm(s.half_extents_m)) for s in clutter]
        for o in world.oois:
            centers.append((o.xy_m[0], o.xy_m[1], o.ground_z_m + o.height_m / 2))
            radii.append(math.hypot(o.radius_m, o.height_m / 2))
        hs = world.humans
        return _StaticSubjects(
            centers_m=np.array(centers, dtype=float).reshape(-1, 3),
            radii_m=np.array(radii, dtype=float),
            n_static=len(clutter),
            ooi_ids=tuple(o.ooi_id for o in world.oois),
            human_radii_m=np.array([math.hypot(h.radius_m, h.height_m / 2) for h in hs]),
            human_half_height_m=np.array([h.height_m / 2 for h in hs]),
        )


@dataclass
class _Inbox:
    velocity: dict[int, tuple[float, float]] = field(default_factory=dict)
    laser: dict[int, LaserPointerCommand] = field(default_factory=dict)
    images: list[tuple[int, ImageRequest]] = field(default_factory=list)
    tickets: list[_RenderTicket | None] = field(default_factory=list)  # one per image


class Simulator:
    """A world (or a world config to generate) with its robots; see the module docstring."""

    def __init__(
        self,
        world: World | WorldConfig,
        *,
        config: SimulatorConfig | None = None,
        radio: RadioConfig | None = None,
        geometry: RobotGeometry | None = None,
    ) -> None:
        self.config = cfg = config or SimulatorConfig()
        self.world = world if isinstance(world, World) else generate_world(world)
        self.truth: GroundTruth = rasterize(self.world, step_max_m=cfg.body.climb_max_m)
        self.geometry = geometry or RobotGeometry()
        workers = cfg.ray_workers
        if workers < 0:
            workers = 1 if (os.cpu_count() or 1) >= 2 and len(self.world.robots) >= 16 else 0
        self.scene = Scene(
            self.world,
            geometry=self.geometry,
            ray_threads=cfg.ray_threads,
            ray_workers=workers,
            analytic_ground=True,
            cull=True,
        )
        renderers = cfg.render_workers
        if renderers < 0:
            renderers = 1 if (os.cpu_count() or 1) >= 2 else 0
        self._render_wanted = renderers > 0
        self._render_worker: RenderWorkerProcess | None = None
        self.worker_renders = 0  # images the render worker drew that were used
        self.empty_frames = 0  # images answered flat: nothing to find in them (sim.camera)
        self.clock = ManualClock(0.0)
        self.time_s = 0.0
        self.steps = 0
        robots = self.world.robots
        self.robot_ids = [r.robot_id for r in robots]
        self.roles = [r.role for r in robots]
        self._is_sensor = np.array([r == "sensor" for r in self.roles], dtype=bool)
        n = len(robots)
        starts = np.array([r.pose_m for r in robots], dtype=np.float64).reshape(-1, 3)
        ss = np.random.SeedSequence([cfg.seed, self.world.config.seed])
        s_body, s_lidar, s_imu = (int(s.generate_state(1)[0]) for s in ss.spawn(3))
        self.bodies = SkidSteerBodies(starts, self.truth, config=cfg.body, seed=s_body)
        self.lidars = NoddingLidars(
            n, config=cfg.lidar, lidar_in_base_m=self.geometry.lidar_m, seed=s_lidar
        )
        self.imus = Imus(n, config=cfg.imu, seed=s_imu)
        self.routes = PatrolRoutes(self.world.humans)
        humans = self.world.humans
        self._hostile_idx = [k for k, h in enumerate(humans) if h.kind == "hostile"]
        self._civilian_idx = [k for k, h in enumerate(humans) if h.kind == "civilian"]
        statics = [o for o in self.world.oois if o.kind == "static_ooi"]
        self._static_ooi_ids = [o.ooi_id for o in statics]
        self.rules = Rules(
            static_ids=self._static_ooi_ids,
            static_xy_m=np.array([o.xy_m for o in statics]).reshape(-1, 2),
            hostile_ids=[humans[k].human_id for k in self._hostile_idx],
            civilian_ids=[humans[k].human_id for k in self._civilian_idx],
            robot_roles=self.roles,
            config=cfg.rules,
        )
        self.radio_config = radio or RadioConfig()
        self.radio_model = RadioModel(
            self.radio_config,
            occupancy=self.truth.vertical_occupancy,
            resolution_m=self.truth.resolution_m,
            gcs_xy_m=self.world.gcs_antenna_m[:2],
        )
        self.radio_blackouts = RadioBlackouts(cfg.radio_blackouts, self.robot_ids)
        self.relay = np.zeros(n, dtype=bool)
        self.radio_state: RadioState | None = None
        self.radio_updates = 0
        self._next_radio_s = 0.0
        self._human_xy = self.routes.positions(0.0) if len(humans) else np.zeros((0, 2))
        self._human_hidden = np.zeros(len(humans), dtype=bool)
        self._human_frozen = np.zeros(len(humans), dtype=bool)
        self._velocity = np.zeros((n, 2))
        self._laser: dict[int, LaserPointerCommand] = {}
        self._inbox = _Inbox()
        self._inbox_lock = threading.Lock()
        self._drivers = {rid: SimDriver(self, rid) for rid in self.robot_ids}
        self._ready = threading.Condition()
        self._acked = np.full(n, -1, dtype=np.int64)
        self._acked_time = np.full(n, -math.inf)
        self._attached = np.zeros(n, dtype=bool)  # a node has polled or commanded
        self.rejected_commands = 0
        self._history: collections.deque[tuple[float, np.ndarray, np.ndarray, np.ndarray]] = (
            collections.deque(maxlen=max(2, int(cfg.camera.history_s / cfg.step_s) + 1))
        )
        self._history_t: collections.deque[float] = collections.deque(maxlen=self._history.maxlen)
        self._cam_phase = np.arange(n) * 1.7
        self._subjects = _StaticSubjects.of(self.world)
        # _frame_has_subjects' answers from the requests' submission to their rendering at the
        # next step (a pure function of the recorded frame, the request's size and the objects
        # gone): asked twice per image, computed once
        self._subjects_memo: dict[tuple[int, float, int, int, frozenset[int]], bool] = {}
        self._sync_scene()
        self._record()
        self._update_radio()

    # ------------------------------------------------------------------ public API
    def driver(self, robot_id: int) -> SimDriver:
        """The ``RobotDriver`` of robot ``robot_id``."""
        if robot_id not in self._drivers:
            raise KeyError(f"no robot {robot_id}; robots are {self.robot_ids}")
        return self._drivers[robot_id]

    @property
    def events(self) -> list[Event]:
        return self.rules.events

    def command(self, robot_id: int, command: RobotCommand) -> None:
        """Queue a command for the next step (any thread); bad ones raise
        :class:`CommandError` and are counted in ``rejected_commands``."""
        try:
            if robot_id not in self._drivers:
                raise CommandError(f"no robot {robot_id}; robots are {self.robot_ids}")
            validate_command(robot_id, command)
        except CommandError:
            self.rejected_commands += 1
            raise
        with self._inbox_lock:
            ib = self._inbox
            if isinstance(command, VelocityCommand):
                ib.velocity[robot_id] = (command.linear_m_s, command.angular_rad_s)
            elif isinstance(command, LaserPointerCommand):
                ib.laser[robot_id] = command
            else:
                pending = sum(1 for rid, _ in ib.images if rid == robot_id)
                if pending >= _MAX_IMAGE_REQUESTS_PER_STEP:
                    self.rejected_commands += 1
                    raise CommandError(
                        f"robot {robot_id}: ImageRequest refused: {pending} already pending"
                        f" this step (at most {_MAX_IMAGE_REQUESTS_PER_STEP})"
                    )
                ib.images.append((robot_id, command))
                ib.tickets.append(self._submit_render(robot_id, command))
        with self._ready:
            k = self.robot_ids.index(robot_id)
            self._attached[k] = True
            self._acked_time[k] = max(self._acked_time[k], float(command.time_s))
            self._ready.notify_all()

    def set_relay(self, robot_id: int, on: bool) -> None:
        """Put a robot in (or out of) radio relay mode; takes effect at the next radio update."""
        self.relay[self.robot_ids.index(robot_id)] = bool(on)

    def radio_grants(self) -> dict[int, RadioGrant]:
        """The latest grant of every robot (updated every ``radio_period_s``)."""
        assert self.radio_state is not None
        return dict(zip(self.robot_ids, self.radio_state.grants, strict=True))

    def robot_poses(self) -> np.ndarray:
        """Ground truth ``world_from_base`` ``(N, 3)``; evaluation only."""
        return self.bodies.state.pose.copy()

    def alive(self) -> np.ndarray:
        return ~self.bodies.state.disabled

    def ready(self) -> bool:
        """Lockstep: every live robot's node has consumed its latest sweep."""
        with self._ready:
            return self._ready_locked()

    def _ready_locked(self) -> bool:
        alive = self.alive()
        for k, rid in enumerate(self.robot_ids):
            if not (alive[k] and self._attached[k]):
                continue
            d = self._drivers[rid]
            if d.last_sweep_sent < 0:
                continue
            # commands carry float32-rounded times on the wire: allow half a step
            by_command = self._acked_time[k] >= d.last_sweep_time_s - self.config.step_s / 2
            by_poll = self.config.lockstep_ack == "poll" and self._acked[k] >= d.last_sweep_sent
            if not (by_command or by_poll):
                return False
        return True

    def wait_ready(self, timeout_s: float) -> bool:
        with self._ready:
            return self._ready.wait_for(self._ready_locked, timeout=timeout_s)

    def _attach(self, robot_id: int) -> None:
        k = self.robot_ids.index(robot_id)
        if not self._attached[k]:
            with self._ready:
                self._attached[k] = True

    def _ack_sweep(self, robot_id: int, sweep_index: int) -> None:
        with self._ready:
            k = self.robot_ids.index(robot_id)
            self._acked[k] = max(self._acked[k], sweep_index)
            self._ready.notify_all()

    def run_for(self, duration_s: float) -> None:
        """Step (without lockstep waits) for ``duration_s`` of mission time."""
        for _ in range(int(round(duration_s / self.config.step_s))):
            self.step()

    def close(self) -> None:
        self._stop_render_worker()
        self.scene.close()

    def __enter__(self) -> Simulator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ stepping
    def step(self) -> None:
        """Advance the world by ``step_s`` (see the module docstring)."""
        cfg = self.config
        dt = cfg.step_s
        with self._inbox_lock:
            inbox, self._inbox = self._inbox, _Inbox()
        idx = {rid: k for k, rid in enumerate(self.robot_ids)}
        for rid, (v, w) in inbox.velocity.items():
            self._velocity[idx[rid]] = (v, w)
        self._laser.update(inbox.laser)

        t_new = self.time_s + dt
        # people
        if len(self.routes):
            walk = self.routes.positions(t_new)
            moving = ~self._human_frozen
            self._human_xy = np.where(moving[:, None], walk, self._human_xy)
        alive_h = ~self._human_hidden
        self.bodies.step(
            dt,
            self._velocity[:, 0],
            self._velocity[:, 1],
            others_xy_m=self._human_xy[alive_h],
            others_radius_m=np.array(
                [h.radius_m for h, a in zip(self.world.humans, alive_h, strict=True) if a]
            ),
        )
        self.time_s = t_new
        self.steps += 1
        self._sync_scene()
        alive = self.alive()
        mats = self.bodies.world_from_base_matrices()
        out: dict[int, list[SensorFrame]] = {rid: [] for rid in self.robot_ids}

        # LIDAR lines due now, all robots in one batch
        if cfg.lidar.enabled:
            due = [d for d in self.lidars.due(t_new) if alive[d[0]]]
            origin, end, dirs = self.lidars.rays(due, mats)
            if len(origin):
                frac, body = self.scene.ray_cast(origin, end)
                rid_of_ray = np.repeat([d[0] for d in due], cfg.lidar.beams)
                own = self.scene.robot_of_body[np.clip(body, 0, None)]
                self_hit = (body >= 0) & (own == rid_of_ray)
                for r, sweep in self.lidars.accept(due, t_new, dirs, frac, self_hit):
                    out[self.robot_ids[r]].append(sweep)

        # rules: lasers, visual locks, triggers
        self._apply_rules(mats, alive)
        alive = self.alive()

        # IMU and encoders
        st = self.bodies.state
        gyro, accel = self.imus.sample(
            dt,
            linear_m_s=st.linear_m_s,
            angular_rad_s=st.angular_rad_s,
            roll_rad=st.roll_rad,
            pitch_rad=st.pitch_rad,
        )
        ticks = wheel_ticks(st.left_m, st.right_m, cfg.encoders)
        gyro_l, accel_l, ticks_l = gyro.tolist(), accel.tolist(), ticks.tolist()
        period = cfg.battery_period_s
        battery_due = math.floor(t_new / period + 1e-9) != math.floor(
            t_new / period - dt / period + 1e-9
        )
        for k, rid in enumerate(self.robot_ids):
            if not alive[k]:
                out[rid] = []
                continue
            # the step's motion before the sweep it ends: a node deskewing the sweep needs
            # the odometry up to the sweep's last instant
            out[rid][:0] = [
                ImuSample(
                    time_s=t_new,
                    angular_velocity_rad_s=tuple(gyro_l[k]),  # type: ignore[arg-type]
                    linear_acceleration_m_s2=tuple(accel_l[k]),  # type: ignore[arg-type]
                ),
                WheelTicks(time_s=t_new, left_ticks=ticks_l[k][0], right_ticks=ticks_l[k][1]),
            ]
            if battery_due:
                charge = min(1.0, max(0.0, float(st.battery_wh[k]) / cfg.body.battery_wh))
                out[rid].append(BatteryState(time_s=t_new, charge_frac=charge))

        self._record()
        for (rid, req), ticket in zip(inbox.images, inbox.tickets, strict=True):
            rgb = self._collect_render(ticket, req)
            if alive[idx[rid]]:
                try:
                    out[rid].append(self.render_image(rid, req, rgb=rgb))
                except Exception as err:  # noqa: BLE001 - a bad request must not stop the world
                    self.rejected_commands += 1
                    log.warning("robot %d: image request failed: %s", rid, err)

        self._subjects_memo.clear()  # the requests to come draw newer frames
        if t_new + 1e-9 >= self._next_radio_s:
            self._update_radio()
        for rid, frames in out.items():
            if frames:
                self._drivers[rid]._push(frames)
        self.clock.set(t_new)

    def _sync_scene(self) -> None:
        self.scene.set_robot_poses(self.bodies.world_from_base_matrices())
        if len(self.routes):
            z = self.truth.height_at(self._human_xy[:, 0], self._human_xy[:, 1])
            self.scene.set_human_positions(self._human_xy, z, hidden=self._human_hidden)
        self.scene.sync()

    def _record(self) -> None:
        self._history.append(
            (
                self.time_s,
                self.bodies.world_from_base_matrices(),
                self._human_xy.copy(),
                self._human_hidden.copy(),
            )
        )
        self._history_t.append(self.time_s)

    def _update_radio(self) -> None:
        # a robot in a scheduled blackout has its radio off: like a dead one, to the radio
        radio_on = self.alive() & ~self.radio_blackouts.active(self.time_s)
        self.radio_state = self.radio_model.update(
            self.bodies.state.pose[:, :2], alive=radio_on, relay=self.relay
        )
        self._next_radio_s = min(
            self.time_s + self.config.radio_period_s, self.radio_blackouts.next_edge_s(self.time_s)
        )
        self.radio_updates += 1

    def _apply_rules(self, mats: np.ndarray, alive: np.ndarray) -> None:
        cfg = self.config
        g = self.geometry
        n = len(self.robot_ids)
        lasered = np.full(n, -1, dtype=np.int64)
        rays_from, rays_to, owners = [], [], []
        head = np.array([*g.head_center_m, 1.0])
        for rid, cmd in sorted(self._laser.items()):  # by robot: not by arrival order
            k = self.robot_ids.index(rid)
            if not (cmd.on and alive[k] and self.roles[k] == "disruptor"):
                continue
            m = mats[k]
            o = (m @ head)[:3]
            cp, sp = math.cos(cmd.pan_rad), math.sin(cmd.pan_rad)
            ct, st = math.cos(cmd.tilt_rad), math.sin(cmd.tilt_rad)
            d = m[:3, :3] @ np.array([cp * ct, sp * ct, st])
            rays_from.append(o)
            rays_to.append(o + d * cfg.rules.laser_range_m)
            owners.append(("laser", k, -1))
        hostiles = self._hostile_idx
        host_xy = self._human_xy[hostiles] if hostiles else np.zeros((0, 2))
        in_view = np.zeros((n, len(hostiles)), dtype=bool)
        if hostiles:
            active = np.array(
                [
                    not self._human_hidden[h] and self.rules.hostile_status[m_i] == "active"
                    for m_i, h in enumerate(hostiles)
                ]
            )
            sensor = alive & self._is_sensor
            hz = self.truth.height_at(host_xy[:, 0], host_xy[:, 1])
            tall = np.array([self.world.humans[h].height_m for h in hostiles])
            targets = np.column_stack([host_xy, hz + 0.6 * tall])
            eyes = mats[:, :3, :3] @ np.array(g.camera_m) + mats[:, :3, 3]
            dist = np.linalg.norm(eyes[:, None, :2] - targets[None, :, :2], axis=2)
            pk, pm = np.nonzero(
                sensor[:, None] & active[None, :] & (dist <= cfg.rules.lock_range_m)
            )
            for k, m_i in zip(pk.tolist(), pm.tolist(), strict=True):
                eye, target = eyes[k], targets[m_i]
                rays_from.append(eye)
                rays_to.append(target + (target - eye) / max(np.linalg.norm(target - eye), 1e-6))
                owners.append(("view", k, m_i))
        if rays_from:
            _, body = self.scene.ray_cast(np.array(rays_from), np.array(rays_to))
            b = np.clip(body, 0, None)
            for (what, k, m_i), hit, bb in zip(owners, body.tolist(), b.tolist(), strict=True):
                if hit < 0:
                    continue
                if what == "laser":
                    ooi = int(self.scene.ooi_of_body[bb])
                    if ooi >= 0 and ooi in self._static_ooi_ids:
                        lasered[k] = self._static_ooi_ids.index(ooi)
                else:
                    in_view[k, m_i] = self.scene.human_of_body[bb] == hostiles[m_i]
        civ = self._civilian_idx
        events = self.rules.step(
            self.time_s,
            robot_xy_m=self.bodies.state.pose[:, :2],
            civilian_xy_m=self._human_xy[civ] if civ else np.zeros((0, 2)),
            hostile_xy_m=host_xy,
            lasered=lasered,
            hostile_in_view=in_view,
        )
        for ev in events:
            log.info("t=%.2f %s %s (%s)", ev.time_s, ev.kind, ev.subject, ev.cause)
            kind, _, ident = ev.subject.partition(":")
            if ev.kind == "robot_lost":
                self.bodies.state.disabled[self.robot_ids.index(int(ident))] = True
            elif ev.kind == "civilian_harmed":
                h = next(k for k in civ if self.world.humans[k].human_id == int(ident))
                self._human_hidden[h] = True
            elif ev.kind == "detonation" and kind == "static_ooi":
                self.scene.hide_ooi(int(ident))
            elif ev.kind == "detonation" and kind == "hostile":
                h = next(k for k in hostiles if self.world.humans[k].human_id == int(ident))
                self._human_hidden[h] = True
            elif ev.kind == "neutralized" and kind == "hostile":
                h = next(k for k in hostiles if self.world.humans[k].human_id == int(ident))
                self._human_frozen[h] = True

    # ------------------------------------------------------------------ camera
    def camera_pan(self, robot_id: int, time_s: float) -> float:
        k = self.robot_ids.index(robot_id)
        return pan_angle(time_s, self.config.camera, phase_s=float(self._cam_phase[k]))

    def _recorded(self, request: ImageRequest) -> tuple[int, bool]:
        """The history entry a request draws (nearest not after its time, clamped) and
        whether it is the newest (the scene as it stands)."""
        times = list(self._history_t)
        j = max(0, min(len(times) - 1, bisect.bisect_right(times, request.time_s + 1e-9) - 1))
        return j, j == len(times) - 1

    def _frame_has_subjects(self, robot_id: int, j: int, request: ImageRequest) -> bool:
        """Whether recorded frame ``j`` of robot ``robot_id``'s camera, at the request's size,
        may show anything its perception looks for (:mod:`sim.camera`: objects, people,
        clutter within ``subject_range_m``, teammates whose tag spans ``min_tag_px``)."""
        cc = self.config.camera
        if not cc.skip_empty:
            return True
        t_rec = self._history[j][0]
        key = (robot_id, t_rec, request.width_px, request.height_px, self.scene.hidden_oois)
        known = self._subjects_memo.get(key)
        if known is None:
            known = self._subjects_memo[key] = self._has_subjects(robot_id, j, request)
        return known

    def _has_subjects(self, robot_id: int, j: int, request: ImageRequest) -> bool:
        """:meth:`_frame_has_subjects`, computed."""
        cc = self.config.camera
        k = self.robot_ids.index(robot_id)
        t_rec, mats, hxy, hidden = self._history[j]
        pan = self.camera_pan(robot_id, t_rec)
        eye, fwd, up = camera_axes(mats[k], np.array(self.geometry.camera_m), pan, cc.tilt_rad)
        w, h = request.width_px, request.height_px
        fx, fy, _, _ = intrinsics(w, h, cc)
        st = self._subjects
        centers = [st.centers_m]
        radii = [st.radii_m]
        ranges = [np.full(len(st.radii_m), cc.subject_range_m)]
        gone = self.scene.hidden_oois
        if gone:
            keep = np.array([oid not in gone for oid in st.ooi_ids], dtype=bool)
            keep = np.concatenate([np.ones(st.n_static, dtype=bool), keep])
            centers, radii, ranges = [centers[0][keep]], [radii[0][keep]], [ranges[0][keep]]
        if len(hxy):
            shown = ~np.asarray(hidden, dtype=bool)
            hz = self.truth.height_at(hxy[:, 0], hxy[:, 1])
            c = np.column_stack([hxy, hz + st.human_half_height_m])[shown]
            centers.append(c)
            radii.append(st.human_radii_m[shown])
            ranges.append(np.full(len(c), cc.subject_range_m))
        others = np.arange(len(mats)) != k
        if others.any():
            c = mats[others, :3, 3] + np.array([0.0, 0.0, _ROBOT_SPHERE_Z_M])
            centers.append(c)
            radii.append(np.full(len(c), _ROBOT_SPHERE_RADIUS_M))
            tag_range_m = fx * self.geometry.tag_size_m / cc.min_tag_px
            ranges.append(np.full(len(c), min(tag_range_m, cc.subject_range_m)))
        hits = in_frustum(
            eye,
            fwd,
            up,
            hfov_rad=math.radians(cc.hfov_deg),
            vfov_rad=2 * math.atan(h / 2 / fy),
            near_m=cc.near_m,
            centers_m=np.concatenate(centers),
            radii_m=np.concatenate(radii),
            ranges_m=np.concatenate(ranges),
        )
        return bool(hits.any())

    def _render_job(self, robot_id: int, request: ImageRequest) -> tuple[RenderJob, float]:
        """What :meth:`render_image` will draw for ``request`` at the next step, for the render
        worker, and the recorded frame's time. The newest frame now (a node asking for the
        image of now) is a past one by then: the step records another first; a request that
        is still the newest then is drawn in process (:meth:`_collect_render`)."""
        j, _ = self._recorded(request)
        cc = self.config.camera
        k = self.robot_ids.index(robot_id)
        t_rec, mats, hxy, hidden = self._history[j]
        pan = self.camera_pan(robot_id, t_rec)
        eye, fwd, up = camera_axes(mats[k], np.array(self.geometry.camera_m), pan, cc.tilt_rad)
        _, fy, _, _ = intrinsics(request.width_px, request.height_px, cc)
        hz = self.truth.height_at(hxy[:, 0], hxy[:, 1]) if len(self.routes) else np.zeros(0)
        job = RenderJob(
            robots=mats,
            human_xy=hxy if len(self.routes) else np.zeros((0, 2)),
            human_z=hz,
            human_hidden=hidden,
            hidden_oois=self.scene.hidden_oois,
            eye_m=eye,
            forward=fwd,
            up=up,
            width_px=request.width_px,
            height_px=request.height_px,
            fy_px=fy,
            near_m=cc.near_m,
            far_m=cc.far_m,
        )
        return job, t_rec

    def _submit_render(self, robot_id: int, request: ImageRequest) -> _RenderTicket | None:
        """Hand an accepted image request to the render worker (started at the first), or
        None: rendered in process at the step."""
        if not self._render_wanted:
            return None
        j, _ = self._recorded(request)
        if not self._frame_has_subjects(robot_id, j, request):
            return None  # answered flat at the step, nothing to draw
        job, t_rec = self._render_job(robot_id, request)
        if self._render_worker is None:
            try:
                self._render_worker = RenderWorkerProcess(self.world, self.geometry)
            except (OSError, RuntimeError) as err:
                log.warning("render worker unavailable, rendering in process: %s", err)
                self._render_wanted = False
                return None
        try:
            self._render_worker.submit(job)
        except OSError as err:  # the worker went away (a broken pipe): draw here from now on
            log.warning("render worker gone, rendering in process from now: %s", err)
            self._stop_render_worker()
            self._render_wanted = False
            return None
        return _RenderTicket(t_rec, job.hidden_oois)

    def _collect_render(self, ticket: _RenderTicket | None, request: ImageRequest) -> Any:
        """The worker's image for a ticket if it drew what :meth:`render_image` would draw
        now (same recorded frame, same objects gone), else None (rendered in process)."""
        if ticket is None or self._render_worker is None:
            return None
        try:
            rgb = self._render_worker.result()
        except (RuntimeError, OSError, EOFError) as err:
            log.warning("render worker failed, rendering in process from now: %s", err)
            self._stop_render_worker()
            self._render_wanted = False
            return None
        j, current = self._recorded(request)
        if (
            current
            or self._history[j][0] != ticket.time_s
            or self.scene.hidden_oois != ticket.hidden_oois
        ):
            return None
        self.worker_renders += 1
        return rgb

    def _stop_render_worker(self) -> None:
        if self._render_worker is not None:
            self._render_worker.close()
            self._render_worker = None

    def render_image(
        self, robot_id: int, request: ImageRequest, *, rgb: np.ndarray | None = None
    ) -> CameraImage:
        """Render robot ``robot_id``'s camera at the pose recorded nearest to (not after)
        ``request.time_s`` (clamped to the recorded history). ``rgb``: the image already
        drawn for exactly that (by the render worker): only the metadata is added."""
        cc = self.config.camera
        k = self.robot_ids.index(robot_id)
        j, current = self._recorded(request)
        t_rec, mats, hxy, hidden = self._history[j]
        w, h = request.width_px, request.height_px
        fx, fy, cx, cy = intrinsics(w, h, cc)
        pan = self.camera_pan(robot_id, t_rec)
        if not self._frame_has_subjects(robot_id, j, request):
            # terrain only (sim.camera): whatever the worker drew, the flat image, so that
            # the answer does not depend on where it was drawn
            self.empty_frames += 1
            rgb = np.empty((h, w, 3), dtype=np.uint8)
            rgb[:] = np.array(cc.empty_rgb, dtype=np.uint8)
        elif rgb is None:
            if not current:
                self.scene.set_robot_poses(mats)
                if len(self.routes):
                    z = self.truth.height_at(hxy[:, 0], hxy[:, 1])
                    self.scene.set_human_positions(hxy, z, hidden=hidden)
            try:
                eye, fwd, up = camera_axes(
                    mats[k], np.array(self.geometry.camera_m), pan, cc.tilt_rad
                )
                rgb = self.scene.render(
                    eye_m=eye,
                    forward=fwd,
                    up=up,
                    width_px=w,
                    height_px=h,
                    fy_px=fy,
                    near_m=cc.near_m,
                    far_m=cc.far_m,
                )
            finally:
                if not current:
                    self._sync_scene()
        return CameraImage(
            request_id=request.request_id,
            time_s=t_rec,
            camera_pan_rad=pan,
            camera_tilt_rad=cc.tilt_rad,
            fx_px=fx,
            fy_px=fy,
            cx_px=cx,
            cy_px=cy,
            rgb=rgb,
        )
