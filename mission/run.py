"""``magic run``: the MAGIC mission on one machine, on the embedded default (no server to start).

The simulator, one robot node per robot and the ground-control station run in this process
(:mod:`mission.assembly`), in lockstep with the simulator's mission clock; robots and the GCS
talk over two real zenoh sessions on loopback through the radio link (rates granted by the
simulator's radio model, every byte metered). The GCS is the real one
(:class:`~gcs.mission_control.MissionControl`: the :class:`~gcs.ground_station.GroundStation`
with loop closing, iSAM2, rasterization, hazards and ``map_from_odom``, and the task allocator
of paper 5.1): it learns only what the robots send over the radio, and its planners task the
sensor robots to explore and the disruptors to neutralize the static OOIs the robots detect.
The team (sensor robots and disruptors) comes from the world's configuration. Mission time is
deterministic (:mod:`mission.lockstep`): the same world, seed, duration and configuration
give the same run, bit for bit, whatever the load; ``robot_processes`` puts each robot node
in its own process and gives the same run again; ``realtime`` delivers radio traffic on
wall-clock threads and promises no repeatability.

``scripted`` (``magic run --scripted``) replaces the GCS by the old script: goals drawn
(seeded) from the ground truth's reachable area, away from walls and objects of interest, and
every hazard sent where the truth has it, every ``hazard_period_s``. That mode reads the truth
to drive the robots (this composition root may, DESIGN section 2) and is kept for comparisons
only. Either way the report counts, from the truth, how close each robot came to each kind of
hazard; robots never see the truth.
"""

from __future__ import annotations

import contextlib
import logging
import math
import struct
import tempfile
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import cv2
import msgspec
import numpy as np

from gcs.graph.pose_graph import Provenance
from gcs.ground_station import GroundStationConfig
from gcs.mission_control import MissionControlConfig
from mission.assembly import Assembly, GroundSide, assemble
from mission.config import config_path, load_config
from mission.lockstep import TeamOverProcesses, WorkerDied, seed_streams
from mission.run_args import DEFAULT_DURATION_S, DEFAULT_SEED, run_parser
from protocol.messages import (
    Detection,
    GoToTask,
    Hazard,
    HazardUpdate,
    ObjectKind,
    PoseNode,
    RobotFrame,
    TaskState,
    TaskStatus,
    Telemetry,
    TerrainGrid,
)
from protocol.radio import RadioConfig
from protocol.se2 import compose, inverse, transform_points
from robot.node import RobotNodeConfig
from sim.simulator import Simulator, SimulatorConfig, load_world_config

if TYPE_CHECKING:
    from gcs.ground_station import GroundStation
    from mission.report.recorder import MissionRecorder
    from protocol.link import LinkConfig

__all__ = [
    "RobotProgress",
    "RunConfig",
    "RunReport",
    "TeamSetupError",
    "fields_differing",
    "main",
    "run_mission",
    "scripted_goals",
]


class RunConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """A run (``magic run --config YAML``): which world, how long, the GCS and its planners
    (``gcs``, ``mission``; the GCS steps every ``gcs_step_period_s`` mission seconds), or with
    ``scripted`` the goal script (``goals_per_robot`` ... ``hazard_period_s``). ``world`` and
    ``radio`` name a YAML file: a path, a path under ``configs/``, or a config name
    (``small``: ``configs/world/small.yaml``)."""

    world: str = "world/small.yaml"
    radio: str = "radio/magic2010.yaml"
    duration_s: float = DEFAULT_DURATION_S
    scripted: bool = False  # goals drawn from the truth instead of the GCS (comparisons only)
    gcs_step_period_s: float = 1.0
    gcs_budget_s: float = 0.2  # wall seconds of loop closing per GCS step, --realtime only
    gcs: GroundStationConfig = GroundStationConfig()
    mission: MissionControlConfig = MissionControlConfig()
    goals_per_robot: int = 4
    goal_min_m: float = 6.0
    goal_max_m: float = 18.0
    goal_clearance_m: float = 1.2  # from walls and other structures
    goal_separation_m: float = 8.0  # teammates' goals at the same step stay this far apart
    ooi_clearance_m: float = 7.0  # goals stay well away from objects of interest
    hazard_period_s: float = 1.0  # hazard updates to every robot (0: none)
    seed: int = DEFAULT_SEED  # every random stream of the run derives from it (mission.lockstep)
    realtime: bool = False  # wall-clock delivery (hardware in the loop): not repeatable
    robot_processes: bool = False  # robot nodes in worker processes (magic robot --lockstep)
    workers: int | None = None  # robot worker processes (robot_processes; None: one per core)
    remote_robots: tuple[int, ...] = ()  # robots whose workers another host starts
    #: the GCS in a process of its own (mission.lockstep_gcs; with robot_processes), restarted
    #: from its journal when it dies: the same run as in this process until then
    gcs_process: bool = False
    simulator: SimulatorConfig = SimulatorConfig()
    robot: RobotNodeConfig = RobotNodeConfig()

    def __post_init__(self) -> None:
        if not (math.isfinite(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"duration_s must be > 0 mission-seconds, got {self.duration_s}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.realtime and self.robot_processes:
            raise ValueError("realtime and robot_processes cannot be combined (yet)")
        if self.workers is not None and self.workers < 1:
            raise ValueError(f"workers must be >= 1 processes, got {self.workers}")
        if (self.workers is not None or self.remote_robots) and not self.robot_processes:
            raise ValueError("workers and remote_robots need robot_processes: true")
        if self.gcs_process and (self.scripted or self.realtime or not self.robot_processes):
            raise ValueError("gcs_process needs robot_processes: true, and no scripted or realtime")
        if any(r < 0 for r in self.remote_robots) or len(set(self.remote_robots)) != len(
            self.remote_robots
        ):
            raise ValueError(f"remote_robots must be distinct ids >= 0, got {self.remote_robots}")
        if self.goals_per_robot < 0:
            raise ValueError(f"goals_per_robot must be >= 0, got {self.goals_per_robot}")
        if not (math.isfinite(self.gcs_step_period_s) and self.gcs_step_period_s > 0):
            raise ValueError(f"gcs_step_period_s must be > 0, got {self.gcs_step_period_s}")


class TeamSetupError(ValueError):
    """The team could not be brought up (an endpoint in use or unreachable, a robot worker
    that died or never answered): bad input for ``magic run`` (status 2, one line)."""


@dataclass
class RobotProgress:
    robot_id: int
    goals_sent: int = 0
    goals_succeeded: int = 0
    goals_failed: int = 0
    last_state: str = "-"
    mode: str = "-"
    distance_m: float = 0.0
    pose_nodes: int = 0
    terrain_grids: int = 0
    uplink_bytes: int = 0
    alive: bool = True
    stuck_recoveries: int = 0
    plan_failures: int = 0
    blocked_steps: int = 0  # steps the simulator refused the robot's motion (ground truth)
    deadlocks: int = 0  # teammate deadlocks the robot detected and backed off from
    closest_static_m: float = float("inf")  # to a static OOI or toxic vat (truth; trigger 2.5)
    closest_hostile_m: float = float("inf")  # to a hostile (truth; keep-out 5 m)
    final_pose: tuple[float, ...] = ()  # world_from_base x, y, yaw at the end (truth)


@dataclass
class RunReport:
    """What a run did. ``events``: the simulator's rule events (ground truth), e.g. a robot
    disabled by a static OOI's trigger or a hostile, a hostile neutralized, a civilian
    lasered. ``interrupted``: the ``KeyboardInterrupt`` (SIGINT, or SIGTERM's subclass) that
    ended the run early, or None."""

    mission_s: float
    wall_s: float
    robots: dict[int, RobotProgress] = field(default_factory=dict)
    events: list[str] = field(default_factory=list)
    realtime: bool = False
    interrupted: BaseException | None = None
    setup_s: float = 0.0  # wall seconds to build the world and bring the team up
    scripted: bool = False
    run_dir: str = ""  # where the recorder wrote the run ("" : nothing written)
    metrics: dict[str, float] = field(default_factory=dict)  # the report's, scored vs truth
    gcs: dict[str, float] = field(default_factory=dict)  # the GCS's own figures (no truth)
    tasking_events: list[str] = field(default_factory=list)  # the planners' journal
    processes: str = ""  # where the robot nodes ran ("": in this process)

    @property
    def rtf(self) -> float:
        """Mission seconds per wall second of stepping (setup excluded)."""
        return self.mission_s / max(self.wall_s, 1e-9)

    def fields(self) -> dict[str, float | str]:
        """Every figure of the run by name (team summary, per-robot progress and final pose,
        each event): two runs are the same run when these compare equal, floats bit for bit."""
        out: dict[str, float | str] = {"mission_s": self.mission_s}
        out.update(self.summary())
        for rid, p in sorted(self.robots.items()):
            for name, value in vars(p).items():
                if name == "final_pose":
                    for axis, v in zip(("x_m", "y_m", "yaw_rad"), value, strict=False):
                        out[f"robot{rid}.final_{axis}"] = v
                elif name != "robot_id":
                    out[f"robot{rid}.{name}"] = value if isinstance(value, str) else float(value)
        for k, event in enumerate(self.events):
            out[f"event{k}"] = event
        out.update(self.gcs)
        for k, event in enumerate(self.tasking_events):
            out[f"tasking{k}"] = event
        return out

    def summary(self) -> dict[str, float]:
        """Team numbers: goals, distances to hazards (truth), events."""
        ps = list(self.robots.values())
        return {
            "goals_sent": float(sum(p.goals_sent for p in ps)),
            "goals_succeeded": float(sum(p.goals_succeeded for p in ps)),
            "goals_failed": float(sum(p.goals_failed for p in ps)),
            "distance_m": float(sum(p.distance_m for p in ps)),
            "closest_static_m": min((p.closest_static_m for p in ps), default=float("inf")),
            "closest_hostile_m": min((p.closest_hostile_m for p in ps), default=float("inf")),
            "deadlocks": float(sum(p.deadlocks for p in ps)),
            "events": float(len(self.events)),
        }


def fields_differing(a: dict[str, float | str], b: dict[str, float | str]) -> list[str]:
    """Names of the :meth:`RunReport.fields` that differ between two runs (or exist in one
    only); floats compare bit for bit (``-0.0 != 0.0``, NaN equals the same NaN)."""

    def bits(v: float | str | None) -> object:
        return struct.pack("<d", v) if isinstance(v, float) else v

    return [k for k in sorted(a.keys() | b.keys()) if bits(a.get(k)) != bits(b.get(k))]


def scripted_goals(
    sim: Simulator,
    robot_index: int,
    config: RunConfig,
    rng: np.random.Generator,
    *,
    avoid: list[np.ndarray] = (),  # type: ignore[assignment]
) -> np.ndarray:
    """``(K, 2)`` goals in the world frame: reachable, clear of structures and OOIs, each
    between ``goal_min_m`` and ``goal_max_m`` from the previous one (the first from the start),
    and at each step ``goal_separation_m`` from the goals in ``avoid`` (teammates' ``(K, 2)``
    sequences), so that robots spread out instead of jamming each other."""
    truth = sim.truth
    res = truth.resolution_m
    free = truth.reachable.astype(np.uint8)
    clearance = cv2.distanceTransform(free, cv2.DIST_L2, 5) * res
    ok = clearance >= config.goal_clearance_m
    rows, cols = np.nonzero(ok)
    cells = np.stack([(cols + 0.5) * res, (rows + 0.5) * res], axis=1)
    for ooi in truth.oois:
        far = (
            np.hypot(cells[:, 0] - ooi.xy_m[0], cells[:, 1] - ooi.xy_m[1]) >= config.ooi_clearance_m
        )
        cells = cells[far]
    if len(cells) == 0:
        raise ValueError("no reachable goal cells clear of structures and OOIs in this world")
    goals = []
    here = sim.robot_poses()[robot_index][:2]
    for step in range(config.goals_per_robot):
        d = np.hypot(cells[:, 0] - here[0], cells[:, 1] - here[1])
        ok = (d >= config.goal_min_m) & (d <= config.goal_max_m)
        for other in avoid:
            sep = np.hypot(cells[:, 0] - other[step, 0], cells[:, 1] - other[step, 1])
            if np.any(ok & (sep >= config.goal_separation_m)):
                ok &= sep >= config.goal_separation_m
        pick = np.flatnonzero(ok)
        if len(pick) == 0:
            pick = np.array([int(np.argmax(d))])
        here = cells[rng.choice(pick)]
        goals.append(here)
    return np.array(goals)


class _GroundScript:
    """The ground side until the GCS node lands: sends goals, follows the reports."""

    def __init__(
        self,
        sim: Simulator,
        config: RunConfig,
        progress: dict[int, RobotProgress],
        rng: np.random.Generator,
    ) -> None:
        self.sim = sim
        self.progress = progress
        self.hazard_period_s = config.hazard_period_s
        self._next_hazards_s = 0.0
        self.goals_in_odom: dict[int, np.ndarray] = {}
        chosen: list[np.ndarray] = []
        for k, rid in enumerate(sim.robot_ids):
            world_goals = scripted_goals(sim, k, config, rng, avoid=chosen)
            chosen.append(world_goals)
            odom_from_world = inverse(sim.robot_poses()[k])  # odom starts at the start pose
            self.goals_in_odom[rid] = transform_points(odom_from_world, world_goals)
        self.active: dict[int, int] = {}  # robot -> task id in flight
        self.next_task_id = 1
        self.frames = [  # map = the world; each odom starts at the robot's start pose
            RobotFrame(rid, tuple(float(v) for v in sim.robot_poses()[k]))  # type: ignore[arg-type]
            for k, rid in enumerate(sim.robot_ids)
        ]

    def hazards(self, sim: Simulator) -> HazardUpdate:
        """Every hazard where it is now, as the GCS would send it once found (paper 4.1)."""
        hazards: list[Hazard] = []
        for ooi in sim.truth.oois:
            kind = ObjectKind.TOXIC_VAT if ooi.kind == "toxic_vat" else ObjectKind.STATIC_OOI
            if ooi.kind in ("static_ooi", "toxic_vat"):
                hazards.append(Hazard(len(hazards), kind, ooi.xy_m, 2.5))
        for human, xy in _hostiles(sim):
            hazards.append(Hazard(1000 + human, ObjectKind.HOSTILE, (xy[0], xy[1]), 5.0))
        return HazardUpdate(sim.time_s, hazards, self.frames)

    def on_message(self, robot_id: int, msg: Any) -> None:
        p = self.progress.get(robot_id)
        if p is None:
            return
        if isinstance(msg, TaskStatus):
            p.last_state = msg.state.name.lower() + (f" ({msg.detail})" if msg.detail else "")
            if msg.task_id == self.active.get(robot_id) and msg.state in (
                TaskState.SUCCEEDED,
                TaskState.FAILED,
                TaskState.REJECTED,
                TaskState.CANCELED,
            ):
                del self.active[robot_id]
                if msg.state is TaskState.SUCCEEDED:
                    p.goals_succeeded += 1
                else:
                    p.goals_failed += 1
        elif isinstance(msg, PoseNode):
            p.pose_nodes += 1
        elif isinstance(msg, TerrainGrid):
            p.terrain_grids += 1
        elif isinstance(msg, Telemetry):
            p.mode = msg.mode.name.lower()

    def turn(self, now_s: float) -> list[tuple[int, Any]]:
        """The script's turn in a step: hazards to every robot when due, the next goals."""
        out: list[tuple[int, Any]] = []
        if self.hazard_period_s > 0 and now_s >= self._next_hazards_s:
            update = self.hazards(self.sim)
            out.extend((rid, update) for rid in self.sim.robot_ids)
            self._next_hazards_s = now_s + self.hazard_period_s
        for rid in self.sim.robot_ids:
            task = self.next_goal(rid, now_s)
            if task is not None:
                out.append((rid, task))
        return out

    def next_goal(self, robot_id: int, now_s: float) -> GoToTask | None:
        if robot_id in self.active:
            return None
        p = self.progress[robot_id]
        if p.goals_sent >= len(self.goals_in_odom[robot_id]):
            return None
        goal = self.goals_in_odom[robot_id][p.goals_sent]
        task = GoToTask(self.next_task_id, now_s, [(float(goal[0]), float(goal[1]))])
        self.active[robot_id] = self.next_task_id
        self.next_task_id += 1
        p.goals_sent += 1
        return task


class _ProgressTap:
    """Follows the uplink the GCS took (task reports, nodes, grids, telemetry) for the
    progress table; how each task the GCS sent ended (:meth:`settle`: tasks ok/sent count
    the same tasks, the planners' and the operators')."""

    def __init__(self, progress: dict[int, RobotProgress]) -> None:
        self.progress = progress
        #: robot -> task id -> whether it succeeded, at its first end (a robot reports a
        #: task's end once, but a resumed GCS may hear it again)
        self.ended: dict[int, dict[int, bool]] = {}

    def __call__(self, robot_id: int, msg: Any, accepted: bool) -> None:
        p = self.progress.get(robot_id)
        if p is None:
            return
        if isinstance(msg, TaskStatus):
            p.last_state = msg.state.name.lower() + (f" ({msg.detail})" if msg.detail else "")
            if msg.state in (TaskState.SUCCEEDED, TaskState.FAILED, TaskState.REJECTED):
                ends = self.ended.setdefault(robot_id, {})
                ends.setdefault(int(msg.task_id), msg.state is TaskState.SUCCEEDED)
        elif isinstance(msg, PoseNode):
            p.pose_nodes += 1
        elif isinstance(msg, TerrainGrid):
            p.terrain_grids += 1
        elif isinstance(msg, Telemetry):
            p.mode = msg.mode.name.lower()

    def settle(self, sent: dict[int, set[int]]) -> None:
        """Each robot's tasks sent (``sent``: the ids, planners' and operators'), and of
        those, how many succeeded and how many failed or were rejected."""
        for rid, p in self.progress.items():
            ids = sent.get(rid, set())
            ends = [ok for tid, ok in self.ended.get(rid, {}).items() if tid in ids]
            p.goals_sent = len(ids)
            p.goals_succeeded = sum(ends)
            p.goals_failed = len(ends) - p.goals_succeeded


def _journal_path(out_dir: str | Path | None, config: RunConfig) -> Path | None:
    """The GCS journal of a run with a run directory (DESIGN 8): ``RUN_DIR/journal.sqlite``,
    what ``magic replay RUN_DIR`` replays; a scripted run has no GCS to journal."""
    if out_dir is None or config.scripted:
        return None
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    return Path(out_dir) / "journal.sqlite"


def run_mission(
    config: RunConfig,
    *,
    on_progress: Callable[[RunReport], None] | None = None,
    progress_period_s: float = 0.5,
    on_step: Callable[[Assembly], None] | None = None,
    out_dir: str | Path | None = None,
    operator: Callable[[Any, Any], Any] | None = None,
    gcs_operator: Any = None,
    on_console: Callable[[str], None] | None = None,
    link: LinkConfig | None = None,
    mission_name: str | None = None,
    worker_link_args: list[str] | None = None,
) -> RunReport:
    """Run the team for ``config.duration_s`` mission-seconds; returns what happened.

    The GCS and its planners on the ground side (``config.scripted``: the truth-drawn goal
    script instead). ``on_step(assembly)`` is called after every step (tests). ``out_dir``:
    the run directory the mission recorder (:mod:`mission.report`) writes (record, map,
    ``report.json``, ``report.md``, plots; the metrics in :attr:`RunReport.metrics`); a
    scripted run has no GCS and writes none. ``operator(link, control)``: the operator station
    (:class:`gcs.operator.service.OperatorService`) on the GCS's link, for consoles and views
    (``magic run`` always has one; with ``config.gcs_process``, ``gcs_operator``: the
    :class:`mission.lockstep_gcs.OperatorSetup` the GCS process serves them with instead);
    ``on_console(line)`` is told the ``magic console`` command
    that reaches it; its interactions and the robots' autonomy modes go into the report.
    Deterministic unless ``config.realtime`` (see :mod:`mission.lockstep`). ^C or SIGTERM
    (any ``KeyboardInterrupt``) ends the run early: links are closed and the report so far is
    returned with ``interrupted`` set to the exception; an interrupt before the team is up
    propagates. With ``config.robot_processes`` the robot nodes run in ``config.workers``
    worker processes (``config.remote_robots`` in workers started on other hosts); ``link``
    (this process's zenoh endpoints and mode), ``mission_name`` and ``worker_link_args`` go
    to :func:`mission.assembly.assemble`.
    """
    world_cfg = load_world_config(config_path(config.world, "world"))
    radio_path = config_path(config.radio, "radio")
    radio_cfg = load_config(radio_path, RadioConfig)
    seeds = seed_streams(config.seed, simulator_seed=config.simulator.seed)
    t_setup = time.perf_counter()
    report = RunReport(0.0, 0.0, realtime=config.realtime, scripted=config.scripted)
    for rid in range(world_cfg.robots.sensors + world_cfg.robots.disruptors):
        report.robots[rid] = RobotProgress(rid)

    def scripts(sim: Simulator) -> list[GroundSide]:
        rng = np.random.default_rng(seeds.ground)
        return [_GroundScript(sim, config, report.robots, rng)]

    with contextlib.ExitStack() as stack:
        journal_path = _journal_path(out_dir, config)
        if journal_path is None and config.gcs_process:  # the GCS process journals somewhere
            tmp = stack.enter_context(tempfile.TemporaryDirectory(prefix="magic-run-gcs-"))
            journal_path = Path(tmp) / "journal.sqlite"
        team = assemble(
            world_cfg,
            seeds=seeds,
            radio=radio_cfg,
            radio_path=str(radio_path),
            simulator=config.simulator,
            robot=config.robot,
            gcs=config.gcs,
            mission=config.mission,
            with_gcs=not config.scripted,
            scripts=scripts if config.scripted else None,
            taps=[_ProgressTap(report.robots)],
            gcs_step_period_s=config.gcs_step_period_s,
            gcs_budget_s=config.gcs_budget_s,
            robot_processes=config.robot_processes,
            realtime=config.realtime,
            journal_path=journal_path,
            gcs_process=config.gcs_process,
            workers=config.workers,
            remote_robots=config.remote_robots,
            link=link,
            worker_link_args=worker_link_args,
            mission_name=mission_name,
            gcs_operator=gcs_operator if config.gcs_process else None,
        )
        try:
            asm = stack.enter_context(team)
        except (ValueError, TimeoutError, WorkerDied) as exc:
            # an endpoint in use or unreachable, a worker that died or never came up
            raise TeamSetupError(f"the team did not come up: {exc}") from exc
        if isinstance(asm.team, TeamOverProcesses):  # robot nodes in worker processes
            groups = asm.team.groups
            n = f"{len(groups)} worker process" + ("es" if len(groups) != 1 else "")
            report.processes = f"robot nodes in {n} (" + (
                "; ".join(",".join(map(str, g)) for g in groups) + ")"
            )
            if config.remote_robots:
                remote = ",".join(map(str, config.remote_robots))
                report.processes += f", robots {remote} on other hosts"
            if asm.remote_gcs is not None:
                report.processes += f", the GCS in its own (pid {asm.remote_gcs.pid})"
        if operator is not None and asm.gcs is not None:  # consoles and views (issue 15)
            asm.gcs.attach_operator(operator(asm.team.ground_link, asm.gcs.control))
            if on_console is not None:
                from gcs.operator.node_hooks import console_command

                on_console(console_command(asm.team.ground_link))
        if gcs_operator is not None and asm.remote_gcs is not None and on_console is not None:
            from gcs.operator.node_hooks import console_command

            on_console(console_command(asm.team.ground_link))  # zenoh routes to the GCS's
        recorder: _Recording | _RemoteRecording | None = None
        if out_dir is not None and asm.gcs is not None:
            recorder = _Recording(Path(out_dir), config, asm)
            report.run_dir = str(out_dir)
        elif out_dir is not None and asm.remote_gcs is not None:
            recorder = _RemoteRecording(Path(out_dir), config, asm, journal_path)
            report.run_dir = str(out_dir)
        steps = [] if on_step is None else [on_step]
        if recorder is not None:
            steps.insert(0, recorder.step)
        report.setup_s = time.perf_counter() - t_setup
        t_wall = time.perf_counter()
        try:
            _run_steps(config, asm, report, on_progress, progress_period_s, steps)
        except KeyboardInterrupt as exc:
            report.interrupted = exc
        finally:
            if asm.gcs is not None and asm.gcs.operator is not None:
                asm.gcs.operator.close(asm.gcs.station)  # last picture, views flushed
        _fill_bytes(report, asm)
        _fill_poses(report, asm.sim)
        _fill_gcs(report, asm)
        report.wall_s = time.perf_counter() - t_wall
        if recorder is not None:
            report.metrics = recorder.finish()
        return report


def _sample_into(rec: MissionRecorder, asm: Assembly, station: GroundStation) -> None:
    """One report sample of the run now: the simulator, the station and the robots' modes."""
    modes = {}
    for rid in asm.sim.robot_ids:
        t = station.telemetry(rid)
        modes[rid] = None if t is None else t.mode
    rec.sample(
        asm.sim.time_s,
        sim=asm.sim,
        station=station,
        link_bytes=asm.link_bytes(),
        modes=modes,
    )


class _RemoteRecording:
    """The mission recorder of a run whose GCS is in its own process: the truth track every
    step, and one sample at the end, of the station rebuilt from the GCS's journal (the
    latest checkpoint and what follows); no time series of the GCS's map, no detection
    events (they are the GCS process's)."""

    def __init__(
        self, run_dir: Path, config: RunConfig, asm: Assembly, journal: Path | None
    ) -> None:
        from mission.report.recorder import MissionRecorder

        assert journal is not None
        self.asm = asm
        self.journal = journal
        self.rec = MissionRecorder(
            run_dir,
            world_name=Path(config.world).stem,
            seed=config.seed,
            duration_s=config.duration_s,
            roles={rid: role.value for rid, role in asm.roles.items()},
        )

    def step(self, asm: Assembly) -> None:
        self.rec.track(asm.sim.time_s, sim=asm.sim)

    def finish(self) -> dict[str, float]:
        from gcs.journal import GcsJournal, rebuild_station

        reader = GcsJournal.open(self.journal)
        try:
            station, _ = rebuild_station(reader)
        finally:
            reader.close()
        _sample_into(self.rec, self.asm, station)
        return self.rec.finish(sim=self.asm.sim, station=station)


class _Recording:
    """The mission recorder fed from the assembly: the truth track every step, a sample every
    ``sample_period_s`` mission seconds, the GCS's detections and planner decisions as events
    (scoring reads the truth; the GCS never does)."""

    sample_period_s = 5.0
    sighting_period_s = 1.0

    def __init__(self, run_dir: Path, config: RunConfig, asm: Assembly) -> None:
        from mission.report.recorder import MissionRecorder

        assert asm.gcs is not None
        self.asm = asm
        self.gcs = asm.gcs
        self.rec = MissionRecorder(
            run_dir,
            world_name=Path(config.world).stem,
            seed=config.seed,
            duration_s=config.duration_s,
            roles={rid: role.value for rid, role in asm.roles.items()},
        )
        self._next_sample_s = 0.0
        self._next_sighting_s = 0.0
        self.gcs.taps.append(self._on_uplink)
        self.gcs.control.on_event = self._on_planner_event
        if self.gcs.operator is not None:  # operator commands: interactions (paper Fig. 24)
            self.gcs.operator.on_interaction = self._on_interaction

    def _on_interaction(self, t_s: float, who: str, text: str, robots: tuple[int, ...]) -> None:
        self.rec.event(t_s, "interaction", operator=who, command=text, robots=list(robots))

    def _on_uplink(self, robot_id: int, msg: Any, accepted: bool) -> None:
        if isinstance(msg, Telemetry):  # mode changes: time and distance per autonomy mode
            t = float(msg.time_s)
            self.rec.mode(t if math.isfinite(t) else self.asm.sim.time_s, robot_id, msg.mode)
        if not (accepted and isinstance(msg, Detection)):
            return
        station = self.gcs.station
        key = station.key_of(robot_id, msg.node_index)
        if key is None:
            return
        xy = transform_points(station.graph.pose(key), np.asarray(msg.position_in_base))
        self.rec.event(
            self.asm.sim.time_s,
            "detection",
            object_kind=msg.kind.name.lower(),
            position_in_map=(float(xy[0]), float(xy[1])),
            robot_id=robot_id,
            confidence=float(msg.confidence),
        )

    def _on_planner_event(self, event: Any) -> None:
        self.rec.event(
            event.time_s,
            f"planner_{event.kind}",
            robot_id=event.robot_id,
            hazard_id=event.hazard_id,
            text=event.text,
        )

    def step(self, asm: Assembly) -> None:
        sim = asm.sim
        self.rec.track(sim.time_s, sim=sim)
        if sim.time_s + 1e-9 >= self._next_sighting_s:
            self._next_sighting_s = sim.time_s + self.sighting_period_s
            self._record_sightings(asm)
        if sim.time_s + 1e-9 >= self._next_sample_s:
            self._next_sample_s = sim.time_s + self.sample_period_s
            self._sample()

    def _record_sightings(self, asm: Assembly) -> None:
        """Each in-process robot's own hostile tracks as ``robot_sighting`` events in the world
        frame (the robot's track in its ``odom``, placed through its true pose: scoring only), so
        the report can tell a hostile seen by a robot the GCS never heard from one nobody saw.
        Robots in worker processes (``--robot-processes``) are not read: their sightings are
        not recorded and the report says n/a."""
        sim = asm.sim
        nodes = asm.team.nodes
        if not nodes:
            return
        alive = sim.alive()
        poses = sim.robot_poses()
        for k, rid in enumerate(sim.robot_ids):
            node = nodes.get(rid)
            if node is None or node.perception is None or not alive[k]:
                continue
            tracks = node.perception.hostile_tracks_in_odom(sim.time_s)
            if not len(tracks):
                continue
            world_from_odom = compose(poses[k], inverse(node.odometry.pose_in_odom))
            for x_w, y_w in transform_points(world_from_odom, tracks[:, :2]):
                self.rec.event(
                    sim.time_s,
                    "robot_sighting",
                    object_kind="hostile",
                    robot_id=rid,
                    position_world=[float(x_w), float(y_w)],
                )

    def _sample(self) -> None:
        _sample_into(self.rec, self.asm, self.gcs.station)

    def finish(self) -> dict[str, float]:
        self._sample()
        return self.rec.finish(sim=self.asm.sim, station=self.gcs.station)


def _run_steps(
    config: RunConfig,
    asm: Assembly,
    report: RunReport,
    on_progress: Callable[[RunReport], None] | None,
    progress_period_s: float,
    on_step: list[Callable[[Assembly], None]],
) -> None:
    sim = asm.sim
    t_wall = time.perf_counter()
    last_pose = {rid: sim.robot_poses()[k][:2].copy() for k, rid in enumerate(sim.robot_ids)}
    last_report = time.perf_counter()
    statics = np.array(
        [o.xy_m for o in sim.truth.oois if o.kind in ("static_ooi", "toxic_vat")]
    ).reshape(-1, 2)
    n_steps = int(round(config.duration_s / sim.config.step_s))
    for _ in range(n_steps):
        asm.step()
        alive = sim.alive()
        poses = sim.robot_poses()
        blocked = sim.bodies.state.blocked_steps
        hostiles = np.array([xy for _, xy in _hostiles(sim)]).reshape(-1, 2)
        for k, rid in enumerate(sim.robot_ids):
            p = report.robots[rid]
            p.alive = bool(alive[k])
            p.blocked_steps = int(blocked[k])
            p.deadlocks, p.stuck_recoveries, p.plan_failures = asm.team.node_counters(rid)
            for points, attr in ((statics, "closest_static_m"), (hostiles, "closest_hostile_m")):
                if len(points):
                    d = float(np.min(np.hypot(*(points - poses[k][:2]).T)))
                    setattr(p, attr, min(getattr(p, attr), d))
            p.distance_m += float(np.hypot(*(poses[k][:2] - last_pose[rid])))
            last_pose[rid] = poses[k][:2].copy()
        for event in sim.events[len(report.events) :]:
            report.events.append(str(event))
        report.mission_s = sim.time_s
        for call in on_step:
            call(asm)
        if on_progress is not None and time.perf_counter() - last_report >= progress_period_s:
            _fill_bytes(report, asm)
            _fill_gcs(report, asm)
            report.wall_s = time.perf_counter() - t_wall
            on_progress(report)
            last_report = time.perf_counter()


def _hostiles(sim: Simulator) -> list[tuple[int, tuple[float, float]]]:
    """Each hostile's id and where it is now (ground truth)."""
    if not sim.world.humans:
        return []
    xy = sim.routes.positions(sim.time_s)
    return [
        (h.human_id, (float(xy[k][0]), float(xy[k][1])))
        for k, h in enumerate(sim.world.humans)
        if h.kind == "hostile"
    ]


def _fill_bytes(report: RunReport, asm: Assembly) -> None:
    for rid, p in report.robots.items():
        p.uplink_bytes = asm.team.uplink_bytes(rid)
    remote = asm.remote_gcs
    if remote is not None:  # the GCS process's progress rows (its _ProgressTap's)
        for rid, row in remote.figures.get("progress", {}).items():
            q = report.robots.get(int(rid))
            if q is not None:
                q.last_state, q.mode, q.pose_nodes, q.terrain_grids = row[:4]
                q.goals_sent, q.goals_succeeded, q.goals_failed = row[4:7]
    if asm.gcs is not None:  # a script counts its own goals
        for tap in asm.gcs.taps:
            if isinstance(tap, _ProgressTap):
                tap.settle(asm.task_ids_sent)


def _fill_gcs(report: RunReport, asm: Assembly) -> None:
    """The GCS's own figures (its estimate, its planners), none from the truth."""
    remote = asm.remote_gcs
    if remote is not None:  # told by the GCS process each step
        report.gcs = {k: float(v) for k, v in remote.figures.get("gcs", {}).items()}
        size = remote.setup_journal_size
        report.tasking_events = list(remote.events[-size:] if size else remote.events)
        return
    if asm.gcs is None:
        return
    st = asm.gcs.station
    control = asm.gcs.control
    closures = st.graph.edges(Provenance.LOOP_AUTO)
    report.gcs = {
        "gcs_pose_nodes": float(st.stats.pose_nodes),
        "gcs_grids": float(st.stats.terrain_grids),
        "gcs_rejected": float(st.stats.rejected_total),
        "gcs_linked": float(len(st.frames())),
        "gcs_closures": float(len(closures)),
        "gcs_hazards": float(len(st.hazards)),
        "tasks_sent": float(sum(control.tasks_sent.values())),
        "tasking_events": float(len(control.journal)),
        "plans": float(control.allocator.stats.plans),
        "explored": float(control.explored),
    }
    report.tasking_events = [f"{e.time_s:.1f} s {e.kind}: {e.text}" for e in control.journal]


def _fill_poses(report: RunReport, sim: Simulator) -> None:
    for k, rid in enumerate(sim.robot_ids):
        report.robots[rid].final_pose = tuple(float(v) for v in sim.robot_poses()[k])


def _footer(report: RunReport) -> list[str]:
    """The lines under the table, each short enough never to wrap mid-phrase."""
    summary = report.summary()
    lines = [
        f"events (rule events, truth): {len(report.events)}"
        + (f"; last: {report.events[-1]}" if report.events else "")
    ]
    near = [
        f"{name} {summary[key]:.1f} m"
        for name, key in (("static OOI", "closest_static_m"), ("hostile", "closest_hostile_m"))
        if np.isfinite(summary[key])
    ]
    if near:
        lines.append(f"closest to a {', '.join(near)} (truth)")
    lines.append(f"teammate deadlocks broken: {summary['deadlocks']:.0f}")
    if report.gcs:
        g = report.gcs
        lines.append(
            f"gcs: {g['gcs_pose_nodes']:.0f} pose nodes, {g['gcs_linked']:.0f} robots linked, "
            f"{g['gcs_closures']:.0f} loop closures, {g['gcs_hazards']:.0f} hazards known, "
            f"{g['tasks_sent']:.0f} tasks sent" + (", area explored" if g["explored"] else "")
        )
        if report.tasking_events:
            lines.append(f"planner: {report.tasking_events[-1]}"[:150])
    elif report.scripted:
        lines.append("ground side: --scripted (goals and hazards from the truth)")
    lines.append(
        "mode: --realtime, wall-clock delivery (not repeatable)"
        if report.realtime
        else "mode: deterministic lockstep (same seed, same run)"
    )
    if report.processes:
        lines.append(report.processes)
    return lines


def format_progress(report: RunReport, duration_s: float | None = None) -> Any:
    """The run so far (of ``duration_s`` mission-seconds, if given): a rich table of the
    robots, then one short line per team figure."""
    from rich.console import Group
    from rich.table import Table
    from rich.text import Text

    of = f" / {duration_s:g}" if duration_s is not None else ""
    table = Table(
        title=f"magic run: {report.mission_s:.1f}{of} mission-s, x{report.rtf:.1f} real time"
    )
    goals = "goals ok/sent" if report.scripted else "tasks ok/sent"
    for col in ("robot", "mode", goals, "task", "driven m", "nodes", "uplink B/s"):
        table.add_column(col, justify="right" if col not in ("mode", "task") else "left")
    for rid, p in sorted(report.robots.items()):
        bps = p.uplink_bytes / max(report.mission_s, 1e-9)
        table.add_row(
            str(rid),
            p.mode if p.alive else "[red]disabled[/red]",
            f"{p.goals_succeeded}/{p.goals_sent}",
            p.last_state[:40],
            f"{p.distance_m:.1f}",
            str(p.pose_nodes),
            f"{bps:.0f}",
        )
    return Group(table, *(Text(line, no_wrap=True, overflow="ignore") for line in _footer(report)))


class _LogCounter(logging.Handler):
    """Counts the records at WARNING and above (the summary says how many went to the log)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.warnings = 0

    def emit(self, record: logging.LogRecord) -> None:
        self.warnings += 1


@contextlib.contextmanager
def _library_logging(path: Path | None) -> Iterator[_LogCounter]:
    """During a run, the library's log records (the GCS refusing a message, a robot's bad
    frame, ...) go to ``path`` (the run directory's ``run.log``), INFO and above, and are
    counted; stderr keeps the progress alone (a record printed through the live table tore
    it). ``path`` None: logging is left as it is, and only counted."""
    root = logging.getLogger()
    counter = _LogCounter()
    handlers: list[logging.Handler] = [counter]
    if path is not None:
        file = logging.FileHandler(path, encoding="utf-8")
        file.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
        file.setLevel(logging.INFO)
        handlers.append(file)
    level = root.level
    if path is not None and root.getEffectiveLevel() > logging.INFO:
        root.setLevel(logging.INFO)
    for h in handlers:
        root.addHandler(h)
    try:
        yield counter
    finally:
        for h in handlers:
            root.removeHandler(h)
            h.close()
        root.setLevel(level)


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like ^C so that the run stops the same way (exit 143)."""


def _terminated_type() -> type[KeyboardInterrupt]:
    """The process-wide SIGTERM exception if :mod:`protocol.process_cli` defines one."""
    from protocol import process_cli

    shared = getattr(process_cli, "Terminated", None)
    if isinstance(shared, type) and issubclass(shared, KeyboardInterrupt):
        return shared
    return _Terminated


def _exit_status(exc: BaseException) -> tuple[int, str]:
    if isinstance(exc, _terminated_type() | _Terminated):
        return 143, "SIGTERM"
    return 130, "SIGINT"


def _check_inputs(config: RunConfig) -> None:
    """Everything a run reads, read before it starts (ConfigError/ValueError naming it)."""
    world = load_world_config(config_path(config.world, "world"))
    load_config(config_path(config.radio, "radio"), RadioConfig)
    team = world.robots.sensors + world.robots.disruptors
    if team < 1:  # pragma: no cover - config refuses
        raise ValueError(f"world {config.world}: no robots")
    beyond = [r for r in config.remote_robots if r >= team]
    if beyond:
        raise ValueError(
            f"remote robots {beyond}: world {config.world} has robots 0-{team - 1} only"
        )


def _remote_robot_ids(text: str) -> list[int]:
    """``--remote-robots``' ids (ValueError naming the option and the part at fault)."""
    from mission.lockstep_protocol import parse_robot_ids

    try:
        return parse_robot_ids(text)
    except ValueError as exc:
        raise ValueError(f"--remote-robots: {exc}") from None


def _remote_hint(
    config: RunConfig, mission: str, link: LinkConfig | None, out_dir: Path | None
) -> str:
    """The command that starts the remote robots' workers on their host (their robot config,
    when not the default, written to ``out_dir/robot.json`` for them)."""
    ids = ",".join(map(str, config.remote_robots))
    where = "" if link is None else " ".join(f"--connect {e}" for e in link.connect or link.listen)
    command = f"magic robot --lockstep --id {ids} --mission {mission} --seed {config.seed}"
    hint = f"waiting for robots {ids}: start them with {command} {where}".rstrip()
    if config.robot != RobotNodeConfig() and out_dir is not None:
        path = out_dir / "robot.json"  # JSON is YAML
        path.write_bytes(msgspec.json.encode(config.robot))
        hint += f" --config {path} (this run's robot config: copy it to that host)"
    return hint


def _run_link(config: RunConfig, args: Any) -> LinkConfig:
    """This process's zenoh endpoints and mode from ``--connect``, ``--listen``, ``--mode``,
    ``--link-config`` and ``--security`` (:func:`protocol.process_cli.link_config`). The
    workers connect to what it connects to or, when it connects nowhere, to its listen
    endpoints: those need a port (loopback's default ``:0`` becomes a free port)."""
    from protocol.loopback import free_loopback_port
    from protocol.process_cli import link_config

    radio = load_config(config_path(config.radio, "radio"), RadioConfig)
    link = link_config(radio, args)
    if not link.connect:
        default = "tcp/127.0.0.1:0"
        listen = tuple(
            f"tcp/127.0.0.1:{free_loopback_port()}" if e == default else e for e in link.listen
        )
        for e in listen:
            if e.endswith(":0"):
                raise ValueError(
                    f"--listen {e}: the robot workers connect to this endpoint: give it a "
                    "port, or --connect to a router"
                )
        link = msgspec.structs.replace(link, listen=listen)
    return link


def _kernels_cold() -> bool:
    """True when no compiled numba kernel is cached yet (the first run after an install):
    the robots' and the GCS's kernels are then compiled before the mission moves, minutes
    on a small machine. Numba caches next to the sources, or under ``NUMBA_CACHE_DIR``."""
    import os

    cache_dir = os.environ.get("NUMBA_CACHE_DIR")
    if cache_dir:
        return not any(Path(cache_dir).rglob("*.nbi"))
    root = Path(__file__).resolve().parent.parent
    return not any(root.glob("robot/**/__pycache__/*.nbi"))


def _run_dir(out: str | None, config: RunConfig) -> Path:
    """The run directory: ``out``, or a fresh ``runs/<UTC date-time>-<world>-<seed>``; a
    directory that already holds a run (``record/``) is refused (ValueError)."""
    if out:
        path = Path(out)
    else:
        stamp = time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        path = Path("runs") / f"{stamp}-{Path(config.world).stem}-{config.seed}"
    if (path / "record").exists() or (path / "journal.sqlite").exists():
        raise ValueError(
            f"--out {path}: already holds a run (record/, journal.sqlite); give another directory"
        )
    if path.exists() and not path.is_dir():
        raise ValueError(f"--out {path}: not a directory")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ValueError(f"--out {path}: cannot create it: {err.strerror}") from None
    return path


def _headline(report: RunReport) -> str:
    """The report's main scores (against the truth) in one line, and where the report is."""
    m = report.metrics

    def f(name: str, fmt: str = ".2f") -> str:
        v = m.get(name, math.nan)
        return "n/a" if not math.isfinite(v) else format(v, fmt)

    return (
        f"report: explored {f('explored_frac')}, static OOIs detected "
        f"{f('static_ooi_detected_frac')} neutralized {f('static_ooi_neutralized_frac')}, "
        f"robots lost {f('robots_lost', '.0f')}, civilians harmed "
        f"{f('civilians_harmed', '.0f')}, false closures {f('false_closures', '.0f')}, "
        f"ATE {f('ate_rmse_m')} m, occupancy F1 {f('occupancy_f1')}, radio use "
        f"{f('radio_use_frac', '.3f')}: {report.run_dir}/report.md"
    )


def main(argv: list[str] | None = None) -> int:
    """``magic run``: 0 when the run completes, 2 on bad input (one line on stderr), 130 on
    SIGINT and 143 on SIGTERM (partial summary printed)."""
    import signal
    import sys

    from rich.console import Console
    from rich.live import Live

    from mission.config import ConfigError

    args = run_parser().parse_args(argv)
    err = Console(stderr=True, highlight=False)
    # a pipe or a file: lines are never wrapped mid-phrase (a terminal keeps its width)
    out = Console(highlight=False) if sys.stdout.isatty() else Console(width=160, soft_wrap=True)

    def fail(problem: object) -> int:
        text = " ".join(str(problem).split())
        err.print(f"magic run: {text}", style="red", markup=False, soft_wrap=True)
        return 2

    link = None
    try:
        config = load_config(args.config, RunConfig) if args.config else RunConfig()
        remote = None
        if args.remote_robots is not None:
            remote = tuple(_remote_robot_ids(args.remote_robots))
        link_given = bool(args.connect or args.listen or args.mode or args.link_config)
        link_given = link_given or bool(args.security)
        spread = link_given or bool(args.mission) or args.workers is not None or bool(remote)
        overrides = {
            k: v
            for k, v in (
                ("world", args.world),
                ("duration_s", args.duration),
                ("seed", args.seed),
                ("realtime", True if args.realtime else None),
                (
                    "robot_processes",
                    True if args.robot_processes or args.gcs_process or spread else None,
                ),
                ("gcs_process", True if args.gcs_process else None),
                ("workers", args.workers),
                ("remote_robots", remote),
                ("radio", None if args.radio is None else str(args.radio)),
                ("scripted", True if args.scripted else None),
            )
            if v is not None
        }
        if overrides:
            config = msgspec.structs.replace(config, **overrides)
        _check_inputs(config)
        if args.print_config:
            import yaml

            out.print(
                yaml.safe_dump(msgspec.to_builtins(config), sort_keys=False).rstrip(),
                markup=False,
                soft_wrap=True,
            )
            return 0
        if config.remote_robots and not args.mission:
            ids = ",".join(map(str, config.remote_robots))
            raise ValueError(
                f"--remote-robots {ids}: give --mission NAME too (the workers on the other "
                "host join that mission)"
            )
        if link_given or config.remote_robots:  # remote workers need a known endpoint
            link = _run_link(config, args)
        from gcs.operator.node_hooks import check_operator_arguments, operator_service

        no_consoles = ""
        try:
            check_operator_arguments(args)
        except ValueError as exc:
            if args.operator_key is not None or not str(exc).startswith("--operator-key"):
                raise
            # the default key file is unusable: the run goes on, without consoles
            no_consoles = f"no consoles for this run: the default {exc}"
        if config.scripted and (args.rerun or args.rerun_save):
            raise ValueError("--rerun/--rerun-save: a --scripted run has no GCS to show")
        out_dir = None if config.scripted else _run_dir(args.out, config)
    except (ConfigError, ValueError) as exc:
        return fail(exc)
    total_s = config.duration_s
    terminated = _terminated_type()

    def on_sigterm(_signum: int, _frame: object) -> None:
        raise terminated("SIGTERM")

    previous = signal.signal(signal.SIGTERM, on_sigterm)
    if config.realtime:
        err.print(
            "magic run: --realtime: radio delivery on wall-clock threads; this run is not "
            "repeatable",
            markup=False,
            soft_wrap=True,
        )
    log_path = None if out_dir is None else out_dir / "run.log"
    logs = contextlib.ExitStack()
    logged = logs.enter_context(_library_logging(log_path))

    def operators(link: Any, control: Any) -> Any:  # consoles and views (issue 15)
        return operator_service(args, link, control)

    def console_line(command: str, console: Any = err) -> None:
        if args.operator_key is not None:
            command += f" --operator-key {args.operator_key}"
        console.print(f"magic run: operators: {command}", markup=False, soft_wrap=True)

    ops: dict[str, Any] = {}
    if config.gcs_process and not no_consoles:  # the GCS process serves them
        from gcs.operator.node_hooks import _sinks
        from mission.lockstep_gcs import OperatorSetup

        ops["gcs_operator"] = OperatorSetup(key_file=args.operator_key, views=_sinks(args))
    elif not (config.scripted or no_consoles):
        ops["operator"] = operators
    ops.update(link=link, mission_name=args.mission)
    if config.remote_robots:
        hint = _remote_hint(config, args.mission, link, out_dir)
        err.print(f"magic run: {hint}", markup=False, soft_wrap=True)
    if no_consoles:
        err.print(f"magic run: {no_consoles}", markup=False, soft_wrap=True)
    if not args.quiet and _kernels_cold():
        err.print(
            "magic run: first run after install: compiling the robots' and the GCS's numba "
            "kernels before the mission moves (a few minutes, once; later runs load them "
            "from the cache)",
            markup=False,
            soft_wrap=True,
        )
    try:
        if args.quiet:
            report = run_mission(config, out_dir=out_dir, on_console=console_line, **ops)
        elif err.is_terminal:
            # transient: the final table is printed once, below, not left here as well
            with Live(console=err, refresh_per_second=4, transient=True) as live:
                report = run_mission(
                    config,
                    on_progress=lambda r: live.update(format_progress(r, total_s)),
                    out_dir=out_dir,
                    on_console=lambda c: console_line(c, live.console),
                    **ops,
                )
        else:  # a log or a pipe: a line every tenth of the run, not a redrawn table
            next_s = [0.0]

            def line(r: RunReport) -> None:
                if r.mission_s >= next_s[0]:
                    next_s[0] += total_s / 10
                    g = r.gcs
                    gcs = (
                        f", gcs: {g['gcs_pose_nodes']:.0f} nodes, {g['gcs_closures']:.0f} "
                        f"closures, {g['gcs_hazards']:.0f} hazards, {g['tasks_sent']:.0f} tasks"
                        if g
                        else ""
                    )
                    err.print(
                        f"magic run: {r.mission_s:.0f} / {total_s:g} mission-s, "
                        f"x{r.rtf:.1f} real time, {len(r.events)} rule events{gcs}",
                        markup=False,
                        soft_wrap=True,
                    )

            report = run_mission(
                config, on_progress=line, out_dir=out_dir, on_console=console_line, **ops
            )
    except KeyboardInterrupt as exc:  # before the team was up: nothing ran
        status, name = _exit_status(exc)
        err.print(f"magic run: stopped by {name} before the run started", soft_wrap=True)
        return status
    except (ConfigError, TeamSetupError) as exc:
        return fail(exc)
    finally:
        signal.signal(signal.SIGTERM, previous)
        logs.close()
    out.print(format_progress(report, total_s))
    if report.run_dir:
        out.print(_headline(report), soft_wrap=True, markup=False)
    if args.rerun_save:
        out.print(f"views: the rerun recording is {args.rerun_save}", soft_wrap=True, markup=False)
    if log_path is not None:
        where = f"log: {logged.warnings} warnings and errors in {log_path}"
        out.print(where, soft_wrap=True, markup=False)
    elif logged.warnings:
        out.print(f"log: {logged.warnings} warnings and errors", soft_wrap=True, markup=False)
    if report.interrupted is not None:
        status, name = _exit_status(report.interrupted)
        err.print(
            f"magic run: stopped by {name} at {report.mission_s:.2f} of {total_s:g} "
            "mission-s; the summary above is the run so far",
            markup=False,
            soft_wrap=True,
        )
        return status
    return 0
