"""``magic bench operator``: the operator station measured (issue 15, paper 6).

Metrics:

* ``command_to_robot_ms_p95`` (and ``..._p50``): wall milliseconds from a console's signed
  command leaving the console to the robot's :class:`~protocol.messages.TaskStatus`
  acknowledging the task arriving at the GCS, over real zenoh (console -> GCS) and the radio
  link (GCS -> robot -> GCS) of a mission in lockstep (:func:`operator_team`: the small world,
  its robots, the real GCS with its planners); ``command_to_robot_mission_ms_p95``: the same in
  mission milliseconds (the radio's share: a command waits for the next step, the task and the
  status each cross the radio at the mission's rate);
* ``views_cpu_frac``: share of the GCS process's CPU spent on the views (picture building,
  drawing and rerun's own threads) with 14 replayed robots (:func:`gcs.views.trial.run_trial`,
  recording to a file, the drawing on its own thread as in ``magic gcs``), target <= 0.10;
  ``rrd_bytes_per_robot_hour`` of that recording;
* ``forged_accepted``, ``replayed_accepted``, ``unsigned_accepted``: commands of each kind the
  GCS's verifier accepted out of ``attempts`` (1,000; must be 0), through the same zenoh path as
  real commands; ``genuine_accepted_frac``: the signed ones interleaved with them, accepted.

``--quick``: fewer commands and a shorter replay (40 nodes per robot instead of 120); every
metric still measured, but the views' share is then higher than in a longer mission, where the
station's work per node grows with the graph while a picture's cost does not.
"""

from __future__ import annotations

import contextlib
import math
import statistics
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gcs.console.client import ConsoleClient
from gcs.operator.service import OperatorService
from protocol import operator as op
from protocol.messages import TaskStatus

__all__ = ["OperatorGround", "OperatorTeam", "operator_team", "run"]

INTEL = (
    Path(__file__).resolve().parents[3] / "shared" / "datasets" / "laser" / "intel-corrected.log.gz"
)


class OperatorGround:
    """What the bench watches beside the GCS (whose ground side runs the operator service,
    :meth:`mission.assembly.GcsGround.attach_operator`, as in ``magic run``): its tap notes
    when each task was first acknowledged and the steps record the true poses."""

    def __init__(self) -> None:
        self.acks: dict[int, tuple[float, float]] = {}  # task id -> (wall s, mission s)
        self.truth: list[tuple[float, np.ndarray]] = []  # (mission s, robot poses (N, 3))

    def tap(self, robot_id: int, msg: Any, accepted: bool) -> None:
        if isinstance(msg, TaskStatus) and msg.task_id not in self.acks:
            t = float(msg.time_s)
            self.acks[msg.task_id] = (time.perf_counter(), t if math.isfinite(t) else 0.0)


@dataclass
class OperatorTeam:
    """A running mission with the operator service and a console client on its GCS."""

    assembly: Any
    ground: OperatorGround
    service: OperatorService
    client: ConsoleClient
    console_link: Any
    key: bytes
    stop: threading.Event = field(default_factory=threading.Event)
    error: list[BaseException] = field(default_factory=list)
    steps: int = 0

    @property
    def now_s(self) -> float:
        return float(self.assembly.sim.time_s)

    def wait_mission_s(self, t_s: float, timeout_s: float = 120.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while self.now_s < t_s:
            if self.error:
                raise RuntimeError("the mission thread failed") from self.error[0]
            if time.monotonic() > deadline:
                return False
            time.sleep(0.02)
        return True


@contextlib.contextmanager
def operator_team(
    *,
    world: str = "small",
    seed: int = 3,
    key: bytes | None = None,
    views: list[str] | None = None,
    on_step: Callable[[OperatorTeam], None] | None = None,
) -> Iterator[OperatorTeam]:
    """The small world's mission in lockstep with the real GCS, stepped on a thread, with an
    :class:`OperatorService` on the GCS's zenoh link and a console client connected to it."""
    from mission.assembly import assemble
    from mission.lockstep_protocol import seed_streams
    from protocol.config import config_path, load_config
    from protocol.link import Link, LinkConfig
    from protocol.radio import RadioConfig
    from sim.simulator import load_world_config

    key = key or bytes(range(32))
    ground = OperatorGround()
    radio_path = config_path("magic2010", "radio")
    with assemble(
        load_world_config(config_path(world, "world")),
        seeds=seed_streams(seed),
        radio=load_config(radio_path, RadioConfig),
        taps=[ground.tap],
    ) as asm:
        assert asm.gcs is not None
        link = asm.team.ground_link
        service = OperatorService(
            link, key=key, control=asm.gcs.control, status_period_s=0.5, views=views
        )
        asm.gcs.attach_operator(service)  # as magic run does
        console_link = Link(
            LinkConfig(connect=tuple(link.config.listen), pump_period_s=0.0),
            mission=link.mission,
        )
        client = ConsoleClient(console_link, "bench", key)
        team = OperatorTeam(asm, ground, service, client, console_link, key)

        def loop() -> None:
            try:
                while not team.stop.is_set():
                    _await_commands(client, service, team.stop)
                    asm.step()
                    team.steps += 1
                    ground.truth.append((asm.sim.time_s, np.asarray(asm.sim.robot_poses()).copy()))
                    if on_step is not None:
                        on_step(team)
            except BaseException as err:  # reported to the waiting thread
                team.error.append(err)

        thread = threading.Thread(target=loop, name="mission-steps", daemon=True)
        thread.start()
        try:
            yield team
        finally:
            team.stop.set()
            thread.join(30.0)
            client.close()
            service.close(asm.gcs.station)
            console_link.close()


def _await_commands(
    client: ConsoleClient, service: OperatorService, stop: threading.Event, wait_s: float = 30.0
) -> None:
    """Hold the mission while a console command is on its way to the GCS (zenoh, wall time),
    so that it is carried out at the ground turn after it was sent whatever the machine's
    load: a mission that steps faster than real time would otherwise run on for a varying
    number of steps meanwhile. A command lost on the way holds it ``wait_s`` wall seconds."""
    deadline = None
    while client.commands_sent > service.commands_received and not stop.is_set():
        if deadline is None:
            deadline = time.monotonic() + wait_s
        elif time.monotonic() > deadline:
            return
        time.sleep(0.0005)


# ---- the suite ------------------------------------------------------------------------------


def _latency(
    team: OperatorTeam, commands: int, progress: Callable[[str], None]
) -> dict[str, float]:
    """Send pause/resume pairs to robot 0 and time the robot's acknowledgement."""
    wall_ms: list[float] = []
    mission_ms: list[float] = []
    for i in range(commands):
        verb = "pause" if i % 2 == 0 else "resume"
        signed = team.client.signed(op.Command(verb, "0"))
        t0, m0 = time.perf_counter(), team.now_s
        reply = team.client.send_raw(signed, timeout_s=30.0)
        if reply is None or reply.status != "ok" or not reply.task_ids:
            raise RuntimeError(f"{verb} 0: no usable reply ({reply})")
        tid = reply.task_ids[0]
        deadline = time.monotonic() + 60.0
        while tid not in team.ground.acks:
            if time.monotonic() > deadline:
                raise RuntimeError(f"task {tid}: no acknowledgement from robot 0 in 60 s")
            time.sleep(0.002)
        t1, m1 = team.ground.acks[tid]
        wall_ms.append(1000.0 * (t1 - t0))
        mission_ms.append(1000.0 * (m1 - m0))
        if i % 5 == 4:
            progress(
                f"latency: {i + 1}/{commands} commands, p50 {statistics.median(wall_ms):.0f} ms"
            )
    return {
        "command_to_robot_ms_p50": float(np.percentile(wall_ms, 50)),
        "command_to_robot_ms_p95": float(np.percentile(wall_ms, 95)),
        "command_to_robot_mission_ms_p95": float(np.percentile(mission_ms, 95)),
    }


def _attacks(
    team: OperatorTeam, attempts: int, progress: Callable[[str], None]
) -> dict[str, float]:
    """Forged, replayed and unsigned commands through zenoh; each answered, none accepted."""
    client = team.client
    verifier = team.service.verifier
    assert verifier is not None  # the team's service was given its key
    accepted_before = verifier.accepted
    genuine = 0
    forged_key = bytes(32)
    captured = client.signed(op.Command("status"))
    reply = client.send_raw(captured, timeout_s=30.0)
    if reply is None or reply.status != "ok":
        raise RuntimeError(f"a genuine command was not accepted: {reply}")
    genuine += 1
    counts = {"forged": 0, "replayed": 0, "unsigned": 0}
    for i in range(attempts):
        seq = client.seq.next()
        cmd = op.Command("pause", "all")
        forged = op.sign(forged_key, client.mission, client.operator_id, seq, cmd)
        unsigned = op.SignedCommand(op.OPERATOR_PROTOCOL_VERSION, client.operator_id, seq, cmd)
        for kind, signed in (("forged", forged), ("unsigned", unsigned), ("replayed", captured)):
            team.console_link.publish(op.command_key(client.mission), op.encode(signed))
            counts[kind] += 1
        if i % 100 == 99:
            # a genuine command now and then: it gets through while the attacks are refused
            r = client.send_raw(client.signed(op.Command("status")), timeout_s=30.0)
            genuine += r is not None and r.status == "ok"
            progress(f"attacks: {3 * (i + 1)} sent, refused {dict(verifier.refused)}")
    deadline = time.monotonic() + 60.0
    total = sum(counts.values())
    while sum(verifier.refused.values()) < total and time.monotonic() < deadline:
        time.sleep(0.05)
    refused = verifier.refused
    # conservative: an attack not refused counts as accepted (lost ones too)
    out = {f"{k}_accepted": float(n - refused.get(k, 0)) for k, n in counts.items()}
    out["attack_attempts_each"] = float(attempts)
    out["accepted_beyond_genuine"] = float(verifier.accepted - accepted_before - genuine)
    out["genuine_accepted_frac"] = genuine / (1 + attempts // 100)
    return out


def run(*, quick: bool, progress: Callable[[str], None]) -> dict[str, float]:
    from gcs.views.trial import run_trial
    from mission.bench import BenchError, output_dir

    metrics: dict[str, float] = {}
    progress("starting the small world's mission with the GCS and the operator service")
    with operator_team() as team:
        if not team.client.wait_for_gcs(60.0):
            raise BenchError("operator bench: the console never heard the GCS")
        team.wait_mission_s(5.0)
        metrics.update(_latency(team, 10 if quick else 40, progress))
        metrics.update(_attacks(team, 1000, progress))
    if not INTEL.exists():
        raise BenchError(f"operator bench: the replay log {INTEL} is missing")
    progress("views: 14 replayed robots, recording to a file, drawing on its own thread")
    rrd = output_dir("operator") / "views.rrd"
    res = run_trial(
        INTEL,
        robots=14,
        max_nodes=40 if quick else 120,
        rrd_path=rrd,
        threaded=True,
    )
    # the views rasterize their own map (what runs until the planners share theirs) and, for
    # comparison, the share when the GCS hands them the map it rasterized anyway
    metrics["views_cpu_frac"] = res.views_cpu_frac
    metrics["views_cpu_frac_given_map"] = res.views_cpu_frac_given_map
    metrics["rrd_bytes_per_robot_hour"] = res.rrd_bytes_per_robot_hour
    return metrics
