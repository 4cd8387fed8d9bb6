"""The one composition of a team: simulator, robot nodes, radio and a ground side (DESIGN 2, 4).

``magic run`` (:mod:`mission.run`), the team-mapping trial (:mod:`mission.team_mapping`) and
the benchmarks build their team here instead of wiring it themselves:

* :func:`assemble` opens the simulator on a world, brings up one robot node per robot (in this
  process, :class:`~mission.lockstep.TeamInLockstep`, or each in its own,
  :class:`~mission.lockstep.TeamOverProcesses`) and the radio between them and a ground side,
  and returns an :class:`Assembly` to step;
* :class:`GcsGround` is the real ground-control station on the ground side: a
  :class:`~gcs.mission_control.MissionControl` (the :class:`~gcs.ground_station.GroundStation`
  and the task allocator), fed only by what the robots send over the radio. Its inbox is
  handled at the start of each ground turn in arrival order (canonical in lockstep), it steps
  every ``gcs_step_period_s`` mission seconds, and in lockstep the loop closer gets no wall
  budget (its match rate in mission time binds), so the run stays deterministic;
* a *script* (any object with ``on_message(robot_id, msg)`` and ``turn(now_s)`` returning
  ``(robot_id, message)`` pairs) can ride beside the GCS or replace it (``magic run
  --scripted``, the team-mapping trial's shared waypoints).

The GCS's planners are bounded by the area of operations (:func:`area_of_operations`, the
site's rectangle: MAGIC's phase boundaries were known). Roles come from the world's roster
(sensor robots, then disruptors, paper 2). Robots start in
a staging area laid out in a known formation (``RobotsConfig``: a grid at ``spacing_m``), as in
MAGIC, where the operators knew where they had put each robot; the GCS gets that deployment
plan, with the placement uncertainty ``hint_sigma_*`` (and a seeded error of that size), as
start hints (:meth:`~gcs.ground_station.GroundStation.add_start_hint`), which links every
robot's private frame to ``map`` (robot ``map_robot``'s private frame) from the first pose
node on. That plan and the boundary are all the GCS learns that the robots did not send; the truth
(:attr:`Simulator.truth`) stays with the scoring.
"""

from __future__ import annotations

import math
import queue
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import msgspec
import numpy as np

from gcs.ground_station import GroundStation, GroundStationConfig
from gcs.journal import GcsJournal, JournaledStation, resume_control, step_control
from gcs.mission_control import MissionControl, MissionControlConfig
from gcs.tasking.allocator import Role
from mission.lockstep import RunSeeds, TeamInLockstep, TeamOverProcesses
from protocol.messages import HazardUpdate, PauseTask, ResumeTask
from protocol.radio import RadioConfig
from protocol.se2 import compose, inverse, relative, transform_points
from robot.node import RobotNodeConfig
from sim.simulator import Simulator, SimulatorConfig
from sim.world_generator import World, WorldConfig

if TYPE_CHECKING:
    from protocol.link import LinkConfig

__all__ = [
    "Assembly",
    "GcsGround",
    "GroundSide",
    "assemble",
    "roles_of",
    "staging_plan",
]

Downlink = list[tuple[int, Any]]


class GroundSide(Protocol):
    """What sits at the GCS end of the radio: takes the uplink, returns each step's downlink."""

    def on_message(self, robot_id: int, msg: Any) -> None: ...

    def turn(self, now_s: float) -> Downlink: ...


def roles_of(sim: Simulator) -> dict[int, Role]:
    """Each robot's role from the world's roster (sensor robots, then disruptors)."""
    return {
        rid: Role.DISRUPTOR if role == "disruptor" else Role.SENSOR
        for rid, role in zip(sim.robot_ids, sim.roles, strict=True)
    }


def staging_plan(world: World) -> dict[int, np.ndarray]:
    """Where the deployment plan puts each robot (``world_from_base`` at the start): the start
    zone's grid (see the module docstring)."""
    return {r.robot_id: np.asarray(r.pose_m, dtype=float) for r in world.robots}


class GcsGround:
    """The GCS on the ground side of a team (module docstring).

    ``taps``: callables ``(robot_id, message, accepted)`` told of every uplink message after the
    station took it (progress tables, scoring, a script beside the GCS). ``lockstep``: no
    wall-clock budget for loop closing (deterministic); otherwise ``budget_s`` wall seconds.
    ``journal``: the GCS journal (:mod:`gcs.journal`): every uplink message before the station
    takes it, every step and the planners' decisions, committed at the end of each turn,
    before the radio exchange acknowledges what the turn took.
    ``operator``: the operator station (:class:`gcs.operator.service.OperatorService`, set
    with :meth:`attach_operator`): it sees every uplink message after the station, and at
    the end of each turn carries out the consoles' commands (their tasks join the turn's
    downlink) and publishes status and views. With no command it changes nothing in the run.
    """

    def __init__(
        self,
        control: MissionControl,
        *,
        lockstep: bool,
        step_period_s: float = 1.0,
        budget_s: float = 0.2,
        taps: list[Callable[[int, Any, bool], None]] | None = None,
        journal: GcsJournal | None = None,
        journal_uplink: bool = True,
    ) -> None:
        if not (math.isfinite(step_period_s) and step_period_s > 0):
            raise ValueError(f"gcs step_period_s: expected seconds > 0, got {step_period_s}")
        self.control = control
        self.station = control.station
        self.lockstep = lockstep
        self.step_period_s = step_period_s
        self.budget_s = budget_s
        self.taps = list(taps or [])
        self.journal = journal
        #: False: whoever queues the uplink journaled it already (the GCS process journals
        #: each message as it arrives, under the time of this turn, before acknowledging it)
        self.journal_uplink = journal_uplink
        self.messages = 0
        self._inbox: queue.SimpleQueue[tuple[int, Any]] = queue.SimpleQueue()
        self._last_step_s = -math.inf
        self.operator: Any = None

    def attach_operator(self, service: Any) -> None:
        """Serve consoles and views with ``service`` (an ``OperatorService`` on this GCS's
        link); its commands are journaled with the run's when there is a journal."""
        if service.journal is None:
            service.journal = self.journal
        self.operator = service

    def on_message(self, robot_id: int, msg: Any) -> None:
        """The radio's delivery (any thread): queued for the next turn."""
        self._inbox.put((robot_id, msg))

    def drain(self, now_s: float) -> int:
        """Hand the queued uplink to the station (arrival order); returns how many."""
        n = 0
        while True:
            try:
                rid, msg = self._inbox.get_nowait()
            except queue.Empty:
                return n
            if self.journal is not None and self.journal_uplink:
                self.journal.uplink(rid, msg, now_s)
            accepted = self.control.handle(rid, msg, now_s=now_s)
            for tap in self.taps:
                tap(rid, msg, accepted)
            if self.operator is not None:
                self.operator.observe(rid, msg, now_s=now_s, station=self.station)
            n += 1
            self.messages += 1

    def turn(self, now_s: float) -> Downlink:
        """The inbox, then (when due) the station's step and a plan: the downlink."""
        self.drain(now_s)
        out: Downlink = []
        if now_s - self._last_step_s >= self.step_period_s:
            self._last_step_s = now_s
            budget = math.inf if self.lockstep else self.budget_s
            out = step_control(self.control, self.journal, now_s=now_s, budget_s=budget)
        if self.operator is not None:
            # the operators' primitives (accept a closure, rewind) journaled like magic gcs's
            station: Any = self.station
            if self.journal is not None:
                station = JournaledStation(self.station, self.journal)
                station._seen(now_s)
            self.operator.after_step(
                now_s=now_s, station=station, send=lambda rid, msg: out.append((rid, msg))
            )
        if self.journal is not None:
            self.journal.commit()
        return out

    def crash_and_resume(self) -> tuple[GcsGround, float]:
        """Simulate a crash of the GCS process and its restart (the chaos bench): this ground
        side is dropped without committing anything more, and a new one is rebuilt from its
        journal (:func:`gcs.journal.resume_control`): same station, allocator re-planning from
        it. Returns the new ground side and the wall seconds the rebuild took. The radio
        link is not rebuilt: in one process it survives, as the link's sequence state must."""
        if self.journal is None:
            raise ValueError("crash_and_resume needs a journaled GCS (assemble(journal_path=...))")
        path = self.journal.path
        self.journal.abandon()
        self.journal = None
        resumed = resume_control(path, self.control.config)
        resumed.control.on_event = self.control.on_event
        ground = GcsGround(
            resumed.control,
            lockstep=self.lockstep,
            step_period_s=self.step_period_s,
            budget_s=self.budget_s,
            taps=self.taps,
            journal=resumed.journal,
        )
        ground.messages = self.messages
        if self.operator is not None:  # the consoles' session survives the restart
            self.operator.control = resumed.control
            self.operator.journal = resumed.journal
            ground.operator = self.operator
        return ground, resumed.rebuild_s


@dataclass
class Assembly:
    """A team brought up by :func:`assemble`: step it, read it, close it (or use ``with``)."""

    sim: Simulator
    team: TeamInLockstep | TeamOverProcesses
    grounds: list[GroundSide]
    roles: dict[int, Role]
    gcs: GcsGround | None = None
    downlink_sent: dict[int, int] = field(default_factory=dict)
    #: the ids of the tasks sent to each robot, by the planners and the operators alike
    #: (pause and resume act on a task: not tasks of their own)
    task_ids_sent: dict[int, set[int]] = field(default_factory=dict)
    broadcast_hazards: bool = True
    broadcasts: int = 0
    #: the GCS in its own process (:class:`mission.lockstep_gcs.RemoteGcs`), or None
    remote_gcs: Any = None

    def step(self) -> None:
        """One simulator step with the robots' answers, every ground side's turn (its
        downlink sent at once), and the radio exchange."""
        self.team.step(self._ground_turn)

    def _ground_turn(self) -> None:
        now = self.sim.time_s
        for ground in self.grounds:
            out = ground.turn(now)
            # the station hands every due robot the same HazardUpdate object: one broadcast
            # (paper 4.1) instead of one copy per robot, when two or more robots are due
            shared: dict[int, int] = {}
            if self.broadcast_hazards:
                for _, msg in out:
                    if isinstance(msg, HazardUpdate):
                        shared[id(msg)] = shared.get(id(msg), 0) + 1
            sent: set[int] = set()
            radio = self.team.ground
            for rid, msg in out:
                assert radio is not None, "the ground end of the radio is in the GCS process"
                if shared.get(id(msg), 0) > 1:
                    if id(msg) not in sent:
                        sent.add(id(msg))
                        radio.broadcast(msg)
                        self.broadcasts += 1
                else:
                    radio.send(rid, msg)
                self.downlink_sent[rid] = self.downlink_sent.get(rid, 0) + 1
                task_id = getattr(msg, "task_id", None)
                if isinstance(task_id, int) and not isinstance(msg, PauseTask | ResumeTask):
                    self.task_ids_sent.setdefault(rid, set()).add(task_id)

    def restart_gcs(self) -> float:
        """The GCS killed and restarted from its journal at the end of a ground turn
        (:meth:`GcsGround.crash_and_resume`); returns the rebuild's wall seconds. Call it
        from a step's ``on_step`` hook or between steps."""
        if self.gcs is None:
            raise ValueError("no GCS on this team's ground side")
        k = self.grounds.index(self.gcs)
        ground, rebuild_s = self.gcs.crash_and_resume()
        self.grounds[k] = ground
        self.gcs = ground
        return rebuild_s

    def link_bytes(self) -> dict[tuple[int, str, str], int]:
        """Radio bytes so far by ``(robot_id, direction, stream)`` (``up``/``down``)."""
        return self.team.link_bytes()

    def close(self) -> None:
        self.team.close()


class _NoGround:
    """The ground side in this process when the GCS runs in its own: nothing to do here."""

    def on_message(self, robot_id: int, msg: Any) -> None:  # pragma: no cover - never called
        raise AssertionError("the uplink goes to the GCS process")

    def turn(self, now_s: float) -> Downlink:
        return []


def _remote_gcs_factory(
    sim: Simulator,
    roles: dict[int, Role],
    *,
    seeds: RunSeeds,
    gcs: GroundStationConfig | None,
    mission: MissionControlConfig | None,
    gcs_step_period_s: float,
    hint_sigma_xy_m: float,
    hint_sigma_yaw_rad: float,
    radio_path: str | None,
    run_dir: Path,
    standby: bool,
    operator: Any = None,
) -> Callable[..., Any]:
    """What starts the GCS process (:class:`mission.lockstep_gcs.RemoteGcs`) once the team's
    link is up: the station and planners configured as :func:`assemble` configures the
    in-process GCS (same start hints, same draws)."""
    from mission.lockstep_gcs import GcsSetup, RemoteGcs

    if radio_path is None:
        raise ValueError("gcs_process needs radio_path (the GCS process loads it)")
    ids = list(sim.robot_ids)
    station_cfg = _gcs_config(gcs or GroundStationConfig(), ids, ids[0])
    disruptors = tuple(r for r, role in roles.items() if role is Role.DISRUPTOR)
    mc = msgspec.structs.replace(mission or MissionControlConfig(), disruptors=disruptors)
    if not mc.area_in_map:
        mc = msgspec.structs.replace(mc, area_in_map=area_of_operations(sim, ids[0]))
    hints = start_hints(
        sim,
        ids[0],
        sigma_xy_m=hint_sigma_xy_m,
        sigma_yaw_rad=hint_sigma_yaw_rad,
        rng=np.random.default_rng(seeds.ground),
    )
    setup = GcsSetup(
        station=msgspec.msgpack.encode(station_cfg),
        mission=msgspec.msgpack.encode(mc),
        hints=hints,
        robots=ids,
        step_period_s=gcs_step_period_s,
        radio_path=str(Path(radio_path).resolve()),
        ground_link_seed=seeds.ground_link,
        seed=seeds.seed,
        operator=operator,
    )
    run_dir.mkdir(parents=True, exist_ok=True)

    def start(link: Any, mission_name: str, link_args: list[str], robot_done: Any) -> RemoteGcs:
        return RemoteGcs(
            link,
            mission_name,
            run_dir,
            setup,
            link_args=link_args,
            robot_done=robot_done,
            standby=standby,
        )

    return start


def _gcs_config(
    base: GroundStationConfig, robot_ids: list[int], map_robot: int
) -> GroundStationConfig:
    cfg = msgspec.structs.replace(base, robots=tuple(robot_ids))
    return msgspec.structs.replace(
        cfg, graph=msgspec.structs.replace(cfg.graph, map_robot_id=map_robot)
    )


def area_of_operations(sim: Simulator, map_robot: int) -> tuple[tuple[float, float], ...]:
    """The site's boundary (the world's rectangle, as MAGIC's phase boundaries were given to
    the teams) in ``map``, through the deployment plan's start of the map robot."""
    w, h = sim.world.size_m
    corners = np.array([[0.0, 0.0], [w, 0.0], [w, h], [0.0, h]])
    in_map = transform_points(inverse(staging_plan(sim.world)[map_robot]), corners)
    return tuple((float(x), float(y)) for x, y in in_map)


def start_hints(
    sim: Simulator,
    map_robot: int,
    *,
    sigma_xy_m: float,
    sigma_yaw_rad: float,
    rng: np.random.Generator,
) -> list[tuple[int, tuple[float, float, float], float, float]]:
    """The deployment plan as start hints (module docstring): each robot's planned start
    relative to the map robot's, with a seeded placement error of the stated size, as
    ``(robot, map_from_odom, sigma_xy_m, sigma_yaw_rad)``."""
    plan = staging_plan(sim.world)
    origin = plan[map_robot]
    out = []
    for rid in sim.robot_ids:
        if rid == map_robot:
            continue
        error = rng.normal(0.0, [sigma_xy_m, sigma_xy_m, sigma_yaw_rad])
        mfo = compose(relative(origin, plan[rid]), error)
        out.append((rid, (float(mfo[0]), float(mfo[1]), float(mfo[2])), sigma_xy_m, sigma_yaw_rad))
    return out


def give_start_hints(
    station: GroundStation | JournaledStation,
    sim: Simulator,
    *,
    sigma_xy_m: float,
    sigma_yaw_rad: float,
    rng: np.random.Generator,
) -> None:
    """:func:`start_hints` given to ``station``."""
    core = station.station if isinstance(station, JournaledStation) else station
    hints = start_hints(
        sim,
        core.config.graph.map_robot_id,
        sigma_xy_m=sigma_xy_m,
        sigma_yaw_rad=sigma_yaw_rad,
        rng=rng,
    )
    for rid, mfo, sxy, syaw in hints:
        station.add_start_hint(rid, map_from_odom=mfo, sigma_xy_m=sxy, sigma_yaw_rad=syaw)


@contextmanager
def assemble(
    world: WorldConfig | World,
    *,
    seeds: RunSeeds,
    radio: RadioConfig,
    radio_path: str | None = None,
    simulator: SimulatorConfig | None = None,
    robot: RobotNodeConfig | None = None,
    gcs: GroundStationConfig | None = None,
    mission: MissionControlConfig | None = None,
    with_gcs: bool = True,
    scripts: Callable[[Simulator], list[GroundSide]] | None = None,
    taps: list[Callable[[int, Any, bool], None]] | None = None,
    gcs_step_period_s: float = 1.0,
    gcs_budget_s: float = 0.2,
    hint_sigma_xy_m: float = 0.3,
    hint_sigma_yaw_rad: float = 0.05,
    robot_processes: bool = False,
    realtime: bool = False,
    journal_path: str | Path | None = None,
    broadcast_hazards: bool = True,
    workers: int | None = None,
    remote_robots: tuple[int, ...] = (),
    link: LinkConfig | None = None,
    worker_link_args: list[str] | None = None,
    mission_name: str | None = None,
    gcs_process: bool = False,
    gcs_standby: bool = True,
    gcs_operator: Any = None,
) -> Iterator[Assembly]:
    """Bring a team up (module docstring); closes everything on exit (links, processes, the
    simulator). ``with_gcs``: the real GCS on the ground side (roles as disruptors from the
    world's roster added to ``mission``); ``scripts(sim)``: further ground sides (after the
    GCS in each turn). ``radio_path``: the radio file robot processes load (needed with
    ``robot_processes``). Deterministic unless ``realtime`` (see :mod:`mission.lockstep`).
    ``journal_path``: the GCS journal's file (a new one; ``RUN_DIR/journal.sqlite`` for a
    run), closed on exit. ``broadcast_hazards``: the station's HazardUpdate goes out as one
    broadcast when several robots are due (else one copy per robot).

    With ``robot_processes`` (:class:`~mission.lockstep.TeamOverProcesses`): ``workers``
    worker processes (default one per core), ``remote_robots`` started elsewhere (other
    hosts), ``link`` this process's zenoh endpoints and mode, ``worker_link_args`` the
    endpoint options of the workers it starts, ``mission_name`` the zenoh mission name
    (default a fresh one). Any of them without ``robot_processes`` is a ValueError.

    ``gcs_process``: the GCS in a process of its own (:mod:`mission.lockstep_gcs`, with
    ``robot_processes`` and ``journal_path``: it journals there, and is restarted from that
    journal if it dies; ``gcs_standby``: a warm spare waits beside it); :attr:`Assembly.gcs`
    is then None and :attr:`Assembly.remote_gcs` its handle. The same run as in one process,
    bit for bit, until a restart. ``gcs_operator``
    (:class:`mission.lockstep_gcs.OperatorSetup`): the GCS process serves consoles and views."""
    spread = {
        "workers": workers is not None,
        "remote_robots": bool(remote_robots),
        "link": link is not None,
        "worker_link_args": worker_link_args is not None,
        "mission_name": mission_name is not None,
    }
    if gcs_process:
        spread["gcs_process"] = True
        if journal_path is None or not with_gcs or scripts is not None or realtime:
            raise ValueError(
                "gcs_process: needs journal_path and the GCS alone on the ground side, lockstep"
            )
    if not robot_processes and any(spread.values()):
        given = ", ".join(k for k, v in spread.items() if v)
        raise ValueError(f"{given}: only with robot_processes (robot nodes in worker processes)")
    sim_cfg = msgspec.structs.replace(simulator or SimulatorConfig(), seed=seeds.simulator)
    with Simulator(world, config=sim_cfg, radio=radio) as sim:  # its radio model grants
        roles = roles_of(sim)
        grounds: list[GroundSide] = []
        gcs_ground: GcsGround | None = None
        remote_gcs = None
        if gcs_process:
            assert journal_path is not None
            remote_gcs = _remote_gcs_factory(
                sim,
                roles,
                seeds=seeds,
                gcs=gcs,
                mission=mission,
                gcs_step_period_s=gcs_step_period_s,
                hint_sigma_xy_m=hint_sigma_xy_m,
                hint_sigma_yaw_rad=hint_sigma_yaw_rad,
                radio_path=radio_path,
                run_dir=Path(journal_path).parent,
                standby=gcs_standby,
                operator=gcs_operator,
            )
            grounds.append(_NoGround())
        elif with_gcs:
            ids = list(sim.robot_ids)
            station = GroundStation(_gcs_config(gcs or GroundStationConfig(), ids, ids[0]))
            journal = None
            if journal_path is not None:
                journal = GcsJournal.create(
                    journal_path,
                    station.config,
                    meta={"source": "magic run", "seed": str(seeds.seed)},
                )
            give_start_hints(
                station if journal is None else JournaledStation(station, journal),
                sim,
                sigma_xy_m=hint_sigma_xy_m,
                sigma_yaw_rad=hint_sigma_yaw_rad,
                rng=np.random.default_rng(seeds.ground),
            )
            disruptors = tuple(r for r, role in roles.items() if role is Role.DISRUPTOR)
            mc = msgspec.structs.replace(mission or MissionControlConfig(), disruptors=disruptors)
            if not mc.area_in_map:
                mc = msgspec.structs.replace(mc, area_in_map=area_of_operations(sim, ids[0]))
            gcs_ground = GcsGround(
                MissionControl(station, mc),
                lockstep=not realtime,
                step_period_s=gcs_step_period_s,
                budget_s=gcs_budget_s,
                taps=taps,
                journal=journal,
            )
            grounds.append(gcs_ground)
        if scripts is not None:
            grounds.extend(scripts(sim))
        if not grounds:
            raise ValueError("a team needs a ground side: the GCS, a script or both")

        def on_message(robot_id: int, msg: Any) -> None:
            for g in grounds:
                g.on_message(robot_id, msg)

        team: TeamInLockstep | TeamOverProcesses
        if robot_processes:
            if realtime:
                raise ValueError("realtime and robot_processes cannot be combined (yet)")
            if radio_path is None:
                raise ValueError("robot_processes needs radio_path (the robots load it)")
            team = TeamOverProcesses(
                sim,
                radio=radio,
                radio_path=radio_path,
                seeds=seeds,
                on_ground_message=on_message,
                robot_config=robot,
                workers=workers,
                remote_robots=remote_robots,
                link=link,
                worker_link_args=worker_link_args,
                mission=mission_name,
                remote_gcs=remote_gcs,
            )
        else:
            team = TeamInLockstep(
                sim,
                radio=radio,
                seeds=seeds,
                on_ground_message=on_message,
                robot_config=robot,
                realtime=realtime,
            )
        with team:
            asm = Assembly(
                sim, team, grounds, roles, gcs_ground, broadcast_hazards=broadcast_hazards
            )
            if isinstance(team, TeamOverProcesses):
                asm.remote_gcs = team.remote
            try:
                yield asm
            finally:
                if asm.gcs is not None and asm.gcs.journal is not None:
                    asm.gcs.journal.close()
