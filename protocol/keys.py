"""Zenoh key expressions: the only place they are built (DESIGN section 4).

::

    magic/<mission>/robot/<id>/up/<stream>      robot -> GCS radio traffic (metered)
    magic/<mission>/robot/<id>/down/<stream>    GCS -> robot radio traffic (metered)
    magic/<mission>/broadcast/down/<stream>     GCS -> every robot in range (metered once)
    magic/<mission>/gcs/<topic>                 GCS command queryable, state for consoles/views
    magic/<mission>/sim/clock                   mission clock
    magic/<mission>/sim/robot/<id>/sensors      sensor frames for a remote robot node
    magic/<mission>/sim/robot/<id>/commands     commands from a remote robot node
    magic/<mission>/sim/radio/<id>              radio grants for robot <id>
    magic/<mission>/sim/truth/<topic>           ground truth, for evaluation only
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from protocol.messages import STREAMS, Direction

__all__ = [
    "RadioKey",
    "broadcast",
    "broadcast_wildcard",
    "parse_broadcast_key",
    "gcs",
    "parse_radio_key",
    "radio",
    "radio_wildcard",
    "sim_clock",
    "sim_commands",
    "sim_radio",
    "sim_sensors",
    "sim_truth",
]

_CHUNK = re.compile(r"[A-Za-z0-9_.\-]+")
_ROBOT_ID = re.compile(r"0|[1-9][0-9]*")
ROOT = "magic"


def _chunk(value: str, what: str) -> str:
    if not isinstance(value, str) or not _CHUNK.fullmatch(value):
        raise ValueError(f"{what} {value!r}: use letters, digits, '_', '-' and '.' only")
    return value


def _robot(robot_id: int) -> str:
    if not isinstance(robot_id, int) or isinstance(robot_id, bool) or robot_id < 0:
        raise ValueError(f"robot id {robot_id!r}: expected a non-negative int")
    return str(robot_id)


def radio(mission: str, robot_id: int, direction: Direction, stream: str) -> str:
    """Key of one radio stream of one robot."""
    spec = STREAMS[direction].get(stream)
    if spec is None or spec.broadcast:
        raise ValueError(f"no {direction.value}link stream named {stream!r}")
    return (
        f"{ROOT}/{_chunk(mission, 'mission')}/robot/{_robot(robot_id)}/{direction.value}/{stream}"
    )


def radio_wildcard(mission: str, direction: Direction, robot_id: int | None = None) -> str:
    """All streams of ``direction`` for one robot, or for every robot when ``robot_id`` is None."""
    who = "*" if robot_id is None else _robot(robot_id)
    return f"{ROOT}/{_chunk(mission, 'mission')}/robot/{who}/{direction.value}/*"


def broadcast(mission: str, stream: str) -> str:
    """Key of one broadcast stream (GCS to every robot, paper 4.1)."""
    spec = STREAMS[Direction.DOWN].get(stream)
    if spec is None or not spec.broadcast:
        raise ValueError(f"no broadcast stream named {stream!r}")
    return f"{ROOT}/{_chunk(mission, 'mission')}/broadcast/down/{stream}"


def broadcast_wildcard(mission: str) -> str:
    """Every broadcast stream of ``mission``."""
    return f"{ROOT}/{_chunk(mission, 'mission')}/broadcast/down/*"


def parse_broadcast_key(key: str) -> str | None:
    """The stream of a broadcast key; None if ``key`` is not one (ValueError naming the key
    for a broadcast key with an unknown stream)."""
    parts = key.split("/")
    if len(parts) != 5 or parts[0] != ROOT or parts[2] != "broadcast" or parts[3] != "down":
        return None
    spec = STREAMS[Direction.DOWN].get(parts[4])
    if spec is None or not spec.broadcast:
        raise ValueError(f"broadcast key {key!r}: no broadcast stream {parts[4]!r}")
    return parts[4]


@dataclass(frozen=True)
class RadioKey:
    mission: str
    robot_id: int
    direction: Direction
    stream: str


def parse_radio_key(key: str) -> RadioKey:
    """Inverse of :func:`radio`; ``ValueError`` naming the key if it is not a radio key."""
    parts = key.split("/")
    if (
        len(parts) != 6
        or parts[0] != ROOT
        or not _CHUNK.fullmatch(parts[1])
        or parts[2] != "robot"
        or not _ROBOT_ID.fullmatch(parts[3])
        or parts[4] not in ("up", "down")
    ):
        raise ValueError(f"not a radio key: {key!r}")
    direction = Direction(parts[4])
    spec = STREAMS[direction].get(parts[5])
    if spec is None or spec.broadcast:
        raise ValueError(f"radio key {key!r}: no {direction.value}link stream {parts[5]!r}")
    return RadioKey(parts[1], int(parts[3]), direction, parts[5])


def gcs(mission: str, topic: str) -> str:
    """GCS keys: ``command`` (queryable), ``state/<name>`` for consoles and views."""
    topic_parts = [_chunk(p, "gcs topic") for p in topic.split("/")]
    return f"{ROOT}/{_chunk(mission, 'mission')}/gcs/" + "/".join(topic_parts)


def sim_clock(mission: str) -> str:
    return f"{ROOT}/{_chunk(mission, 'mission')}/sim/clock"


def sim_sensors(mission: str, robot_id: int) -> str:
    return f"{ROOT}/{_chunk(mission, 'mission')}/sim/robot/{_robot(robot_id)}/sensors"


def sim_commands(mission: str, robot_id: int) -> str:
    return f"{ROOT}/{_chunk(mission, 'mission')}/sim/robot/{_robot(robot_id)}/commands"


def sim_radio(mission: str, robot_id: int | None) -> str:
    """Radio grants for one robot, or (``robot_id=None``) a wildcard for all robots."""
    who = "*" if robot_id is None else _robot(robot_id)
    return f"{ROOT}/{_chunk(mission, 'mission')}/sim/radio/{who}"


def sim_truth(mission: str, topic: str) -> str:
    return f"{ROOT}/{_chunk(mission, 'mission')}/sim/truth/{_chunk(topic, 'truth topic')}"
