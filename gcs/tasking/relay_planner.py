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
) -> NDArray[np.int64]:
    """Highway waypoints, one per position of ``silent_in_map`` ``(S, 2)`` (where robots out
    of contact were last heard) in that order, duplicates dropped: among the waypoints in
    ``region`` (default all), not ``blocked``, and within ``contact_radius_m`` of a point of
    ``contact_in_map`` ``(C, 2)``, the one nearest (straight line) that position. Empty when
    no waypoint qualifies (no contact known yet). ``O(S * M + M * C)`` for ``M`` waypoints."""
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
    out: list[int] = []
    for p in silent:
        k = int(members[int(np.argmin(np.hypot(*(nodes[members] - p).T)))])
        if k not in out:
            out.append(k)
    return np.asarray(out, dtype=np.int64)
