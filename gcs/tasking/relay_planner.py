"""Where a radio relay should stand for robots out of contact (paper 4.1, 8).

MAGIC's radio had shadows behind buildings; a robot that drives out of range keeps its task
(store and forward), but the GCS cannot re-task it, and a minute of waiting for the link
before it backs out is a minute not exploring. Team Michigan's operators turned a robot into a
communications relay when one left radio range (paper 4.1: "robots ... used as relays"); here
the GCS does it: an idle robot (a disruptor with no OOI to neutralize) is sent to hold, in
relay mode, at a *relay spot* for each silent robot: the highway waypoint (ground robots have
driven, so reachable) where the GCS is known to reach (within ``contact_radius_m`` of a point
of radio contact) nearest to where the silent robot was last heard: the edge of the covered
ground towards it. A relay there reaches further into the shadow than the GCS does.

Relays chained outwards (``hop_m`` > 0): the radio routes over relays up to three hops (the
GCS, a relay, a second relay, the robot: the simulator's ``relay_max_hops``), so for each
silent robot more than ``hop_m`` of highway beyond its edge spot a second spot follows: on the
highway from the edge spot towards the silent robot, the farthest waypoint within ``hop_m`` of
highway (driven ground, so no more walls between the two relays than the way the robots
drove) -- where the first relay carries contact the GCS has not heard yet. Points of contact
heard through a relay are points of contact like any other, so the next silent robot's edge
spot may be one the relays made: a further relay stands at the edge of the contact the first
ones provide, and the relays follow the frontier where the sensor robots work (paper 5.1.2:
idle disruptors placed to serve the team; 8: the radio's reach bounded what was explored).
The allocator's ``TaskingConfig.relay_hop_m`` sets ``hop_m``: off by default (its measurement
there: on the full mission the relays spent most of their time driving to their spots).

Pure: arrays in, waypoint indices out.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from gcs.tasking.trajectory_graph import TrajectoryGraph

__all__ = ["relay_spots"]


def relay_spots(
    highway: TrajectoryGraph,
    silent_in_map: ArrayLike,
    contact_in_map: ArrayLike,
    *,
    contact_radius_m: float,
    region: NDArray[np.bool_] | None = None,
    blocked: NDArray[np.bool_] | None = None,
    hop_m: float = 0.0,
) -> NDArray[np.int64]:
    """Highway waypoints, one per position of ``silent_in_map`` ``(S, 2)`` (where robots out
    of contact were last heard) in that order, duplicates dropped: among the waypoints in
    ``region`` (default all), not ``blocked``, and within ``contact_radius_m`` of a point of
    ``contact_in_map`` ``(C, 2)``, the one nearest (straight line) that position. Empty when
    no waypoint qualifies (no contact known yet). ``O(S * M + M * C)`` for ``M`` waypoints.

    ``hop_m`` > 0: each edge spot is followed by its outward spot (module docstring): of the
    highway path (over the same waypoints) from the edge spot to the waypoint nearest the
    silent robot, the farthest waypoint at most ``hop_m`` of highway from the edge spot;
    none when the waypoint nearest the silent robot is within ``hop_m`` of highway of the
    edge spot (the first relay reaches it). Order: edge spot,
    outward spot, the next robot's edge spot, ... (a second relay is of no use without the
    first). ``O(S * M log M)`` more (one highway search per silent robot)."""
    silent = np.asarray(silent_in_map, dtype=np.float64).reshape(-1, 2)
    contact = np.asarray(contact_in_map, dtype=np.float64).reshape(-1, 2)
    if highway.size == 0 or len(silent) == 0 or len(contact) == 0:
        return np.zeros(0, dtype=np.int64)
    ok = np.ones(highway.size, dtype=bool) if region is None else region.copy()
    if blocked is not None:
        ok &= ~blocked
    nodes = highway.nodes_in_map
    covered = np.zeros(highway.size, dtype=bool)
    for chunk in range(0, len(contact), 4096):  # bounded memory on long missions
        c = contact[chunk : chunk + 4096]
        d2 = (nodes[:, None, 0] - c[None, :, 0]) ** 2 + (nodes[:, None, 1] - c[None, :, 1]) ** 2
        covered |= (d2 <= contact_radius_m**2).any(axis=1)
    members = np.flatnonzero(ok & covered)
    if members.size == 0:
        return np.zeros(0, dtype=np.int64)
    usable = np.flatnonzero(ok)
    out: list[int] = []
    for p in silent:
        k = int(members[int(np.argmin(np.hypot(*(nodes[members] - p).T)))])
        if k not in out:
            out.append(k)
        if hop_m > 0:
            o = _outward(highway, k, p, usable, ~ok, hop_m)
            if o is not None and o not in out:
                out.append(o)
    return np.asarray(out, dtype=np.int64)


def _outward(
    highway: TrajectoryGraph,
    edge: int,
    silent_xy: NDArray[np.float64],
    usable: NDArray[np.int64],
    blocked: NDArray[np.bool_],
    hop_m: float,
) -> int | None:
    """The waypoint at most ``hop_m`` of highway from ``edge`` on its way towards
    ``silent_xy`` (the path to the usable waypoint nearest it, reachable from ``edge``); None
    when that waypoint is within ``hop_m`` of ``edge``."""
    dist, pred = highway.distances([edge], blocked)
    reach = usable[np.isfinite(dist[0, usable])]
    if reach.size == 0:
        return None
    nodes = highway.nodes_in_map
    target = int(reach[int(np.argmin(np.hypot(*(nodes[reach] - silent_xy).T)))])
    if dist[0, target] <= hop_m:
        return None
    path = highway.path(pred[0], target)
    within = path[dist[0, path] <= hop_m]
    return int(within[-1])
