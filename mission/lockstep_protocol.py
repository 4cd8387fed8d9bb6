"""What a lockstep team's processes say to each other besides sensor frames and the radio,
and the run's seed streams (``mission.lockstep``; ``magic robot --lockstep``).

Imports neither the simulator nor the robot node, so that a robot host loads only this.

Across processes zenoh keeps the order of one key's publications, not the order across keys:
each step therefore says how much of the radio's traffic is due. A process hosting robot nodes
(a *group*: ``magic robot --lockstep --id 0-7``, one robot or several) gets one
:class:`GroupGo` a step: the step's mission time and, for each of its robots
(:class:`RobotGo`), how many downlink radio packets the ground side has put on the air to it so
far, the radio grant and the robot's sensor frames of the step (encoded, in order). It answers
with one :class:`GroupDone`: each robot's :class:`StepDone` (how many uplink packets it has put
on the air so far, its counters) and the simulator commands it sent this step (encoded, in
order), which the ground side applies before it steps the simulator again. Each side waits
until the radio packets counted have arrived before it goes on. One message each way per
group and step, not several per robot (issue 16: at 100 robots the per-robot messages, a go,
the frames, an end-of-step tick, the commands and a done, cost the simulator's process about
0.45 CPU-s a mission-second in zenoh's threads).

The keys are ``magic/<mission>/gcs/lockstep/group/go/<group's first robot id>`` and
``.../lockstep/group/done`` (every group's answers, hellos included: the ground side learns the
groups from them; ``keys.gcs``); a process hosting robot nodes declares
``.../lockstep/host/<robot id>`` for each (:func:`robot_host_key`).
"""

from __future__ import annotations

from dataclasses import dataclass

import msgspec
import numpy as np

from protocol import keys
from protocol.radio import RadioGrant

__all__ = [
    "GcsDone",
    "GcsEnd",
    "GcsGo",
    "GroupDone",
    "GroupGo",
    "RobotGo",
    "RunSeeds",
    "StepDone",
    "gcs_done_key",
    "gcs_end_key",
    "gcs_go_key",
    "group_done_key",
    "group_go_key",
    "parse_robot_ids",
    "robot_host_key",
    "seed_streams",
]


class RobotGo(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """One robot's part of a :class:`GroupGo`: ``downlink_packets``: radio packets put on the
    air to it since the start (wait for them); ``grant``: the radio's grant now; ``frames``:
    its sensor frames of the step, in order (``protocol.sensors.encode_sensor_frame``)."""

    robot_id: int
    downlink_packets: int
    grant: RadioGrant
    frames: list[bytes]


class GroupGo(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """Ground side -> a group of robot nodes: step to ``time_s``, each of ``robots`` (the
    group's, in id order) with its :class:`RobotGo`; ``report_link``: answer with the radio's
    reliable uplink state (:attr:`StepDone.link_state`)."""

    time_s: float
    robots: list[RobotGo]
    report_link: bool = False


class StepDone(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """One robot's part of a :class:`GroupDone`: step ``time_s`` answered; totals since the
    start of the uplink radio packets it put on the air and of the commands it sent the
    simulator; for the run's report, the radio bytes it sent (metered) and its node's
    counters; ``worker``: which process hosts it (two processes answering for one robot is an
    error the ground names)."""

    time_s: float
    uplink_packets: int
    commands: int
    uplink_bytes: int = 0
    deadlocks: int = 0
    stuck_recoveries: int = 0
    plan_failures: int = 0
    worker: str = ""  # "<host>:<pid>" of the process hosting the robot (a robot hosted twice)
    #: downlink radio packets that arrived at the robot so far (a restarted GCS process
    #: counts its packets from there: :mod:`mission.lockstep_gcs`)
    downlink_packets_in: int = 0
    #: when the go asked (``report_link``): msgpack of ``{stream: [messages the link
    #: accepted, [sequence numbers not acknowledged yet]]}`` of the reliable uplink streams
    link_state: bytes = b""
    #: the robot's radio in relay mode (:attr:`~robot.node.RobotNode.radio_relay`: a relay
    #: task holds it); the ground side applies it to the simulator as in one process
    relay: bool = False


class GroupDone(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """A group of robot nodes -> the ground side: step ``time_s`` answered (0 with no step
    yet: the group's hello, repeated until its first step). ``group``: its first robot id
    (the key of its :class:`GroupGo`); ``robot_ids``, ``done`` and ``commands`` in the same
    order: each robot's :class:`StepDone` and the simulator commands it sent this step
    (``protocol.sensors.encode_command``, in order)."""

    time_s: float
    group: int
    robot_ids: list[int]
    done: list[StepDone]
    commands: list[list[bytes]]


class GcsGo(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """Orchestrator -> the GCS process (:mod:`mission.lockstep_gcs`): the ground side's turn
    at ``time_s`` with each robot's radio ``grants`` now."""

    time_s: float
    grants: dict[int, RadioGrant]


class GcsEnd(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """Orchestrator -> the GCS process: the step at ``time_s`` ends. ``uplink_packets``: the
    radio packets this GCS process is to have received so far (wait for them, at most
    ``wait_s`` wall seconds); ``next_time_s``: the next step's time, when the GCS takes what
    arrived (it journals it under that time before it acknowledges it)."""

    time_s: float
    uplink_packets: int
    next_time_s: float
    wait_s: float


class GcsDone(msgspec.Struct, array_like=True, frozen=True, forbid_unknown_fields=True):
    """The GCS process -> orchestrator: ``phase`` ``hello`` (up, serving), ``turn`` or ``end``
    of the step at ``time_s`` done. ``incarnation``: which start of the GCS process (1, then
    one more per restart); ``downlink_packets``: radio packets it put on the air to each
    robot since it started; ``packets_in``: radio packets it received since it started;
    ``figures``: msgpack of what the run's report shows of the GCS (``end``)."""

    time_s: float
    phase: str
    incarnation: int
    downlink_packets: dict[int, int]
    packets_in: int
    figures: bytes = b""
    pid: int = 0
    rebuild_s: float = 0.0  # wall seconds its journal took to rebuild (a restart's hello)


def gcs_go_key(mission: str) -> str:
    return keys.gcs(mission, "lockstep/gcs/go")


def gcs_end_key(mission: str) -> str:
    return keys.gcs(mission, "lockstep/gcs/end")


def gcs_done_key(mission: str) -> str:
    return keys.gcs(mission, "lockstep/gcs/done")


def group_go_key(mission: str, group: int) -> str:
    """The key of the :class:`GroupGo` of the group whose first robot id is ``group``."""
    return keys.gcs(mission, f"lockstep/group/go/{group}")


def group_done_key(mission: str) -> str:
    """The key every group's :class:`GroupDone` goes on."""
    return keys.gcs(mission, "lockstep/group/done")


def robot_host_key(mission: str, robot_id: int) -> str:
    """The presence key a process hosting robot ``robot_id``'s node declares (a second
    process for the same id sees it and refuses to start)."""
    return keys.gcs(mission, f"lockstep/host/{robot_id}")


def parse_robot_ids(text: str) -> list[int]:
    """``"0,1,4-7"`` -> ``[0, 1, 4, 5, 6, 7]`` (``magic robot --id``); ValueError naming the
    part at fault: not an id, a range backwards, an id given twice."""
    ids: list[int] = []
    seen: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        lo_text, sep, hi_text = part.partition("-")
        try:
            lo = int(lo_text)
            hi = int(hi_text) if sep else lo
        except ValueError:
            raise ValueError(f"robot ids {text!r}: {part!r} is not an id or a range") from None
        if lo < 0 or hi < lo:
            raise ValueError(f"robot ids {text!r}: {part!r} is not an id >= 0 or a range a-b")
        for rid in range(lo, hi + 1):
            if rid in seen:
                raise ValueError(f"robot ids {text!r}: robot id {rid} given twice")
            seen.add(rid)
            ids.append(rid)
    return ids


def _draw(ss: np.random.SeedSequence) -> int:
    return int(ss.generate_state(1, dtype=np.uint32)[0])


@dataclass(frozen=True)
class RunSeeds:
    """Independent seeds of one run, all derived from its seed (numpy ``SeedSequence``
    children: the same seed always gives the same streams, distinct streams never overlap)."""

    seed: int
    simulator: int  # the simulator's sensor noise and slip (with the world's own seed)
    ground: int  # the ground side's draws (scripted goals)
    ground_link: int  # loss draws of the ground's radio channels
    robot_link: int  # loss draws of the robots' radio channels

    def robot(self, robot_id: int) -> int:
        """Robot ``robot_id``'s node draws (deadlock back-off): by id, so that a robot node
        in its own process (``magic robot --id N --seed S``) draws the same."""
        return _draw(np.random.SeedSequence(self.seed, spawn_key=(4, robot_id)))


def seed_streams(seed: int, *, simulator_seed: int = 0) -> RunSeeds:
    """Seeds for every random stream of a run, from ``seed`` (``simulator_seed``:
    ``SimulatorConfig.seed``, mixed in so that it still matters)."""
    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    sim_ss, ground, ground_link, robot_link = np.random.SeedSequence(seed).spawn(4)
    return RunSeeds(
        seed=seed,
        simulator=_draw(np.random.SeedSequence([_draw(sim_ss), simulator_seed])),
        ground=_draw(ground),
        ground_link=_draw(ground_link),
        robot_link=_draw(robot_link),
    )
