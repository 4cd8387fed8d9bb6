"""The radio model: who reaches the GCS, how well, and how much of the shared channel each
robot gets (paper 4.1, 4.3.4: one 115.2 kbps channel for 14 robots and the GCS).

Pure numpy over a 2D occupancy raster (walls attenuate). For a link of length ``d`` crossing
``w`` walls (runs of occupied cells along the segment) the margin is
``10 * path_loss_exponent * log10(range_m / d) - wall_loss_db * w`` dB
(:class:`~protocol.radio.RadioConfig`); it is connected while the margin is positive, and its
quality ``q = clip(margin / fade_margin_db, 0, 1)``. Robots in relay mode forward traffic:
each robot uses the route to the GCS with the best bottleneck quality (widest path), over at
most ``relay_max_hops`` hops, preferring fewer hops on ties.

Sharing: every connected, transmitting robot gets an equal share ``1 / n`` of the air time;
a route of ``h`` hops and quality ``q`` turns it into ``capacity * q / (n * h)`` bps (every hop
re-sends the bytes), split ``uplink_fraction`` to the GCS and the rest from it. Hence the sum
over robots of ``(uplink + downlink) * hops`` never exceeds the shared capacity, and neither
does the plain sum of grants. Message loss is ``max_loss * (1 - q)``. A disconnected robot
gets 0 bps (its link holds messages until it reconnects).

Scheduled blackouts (:class:`RadioBlackouts`, ``SimulatorConfig.radio_blackouts``): a robot's
radio is off for ``[start_s, start_s + duration_s)`` of mission time, as if out of range: it
gets 0 bps both ways, hears no broadcast and relays for no one (faults for the chaos bench,
issue 17). :func:`blackout_schedule` draws such a schedule from a seed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from protocol.radio import RadioConfig, RadioGrant

__all__ = ["RadioBlackouts", "RadioModel", "RadioState", "blackout_schedule"]

#: One scheduled outage: ``(robot_id, start_s, duration_s)`` in mission seconds.
Blackout = tuple[int, float, float]
_EPS_S = 1e-9  # step times are sums of float steps: an edge at 30.0 is met by 29.999999999


class RadioBlackouts:
    """When each robot's radio is off: the union of its ``(robot_id, start_s, duration_s)``
    intervals ``[start_s, start_s + duration_s)`` (mission seconds).

    ``robot_ids``: the team, in the simulator's order; a blackout of another robot, a
    negative or non-finite start or a duration that is not > 0 raise ``ValueError`` naming the
    entry. Pure: ``active(t)`` depends on ``t`` only, so lockstep runs repeat exactly.
    """

    def __init__(self, blackouts: tuple[Blackout, ...] | list[Blackout], robot_ids: list[int]):
        index = {rid: k for k, rid in enumerate(robot_ids)}
        rows: list[tuple[int, float, float]] = []
        for i, entry in enumerate(blackouts):
            where = f"radio_blackouts[{i}]"
            if len(entry) != 3:
                raise ValueError(f"{where}: expected (robot_id, start_s, duration_s), got {entry}")
            rid, start_s, duration_s = int(entry[0]), float(entry[1]), float(entry[2])
            if rid not in index:
                raise ValueError(f"{where}: no robot {rid}; robots are {robot_ids}")
            if not (math.isfinite(start_s) and start_s >= 0):
                raise ValueError(f"{where}: start_s must be finite and >= 0, got {start_s}")
            if not (math.isfinite(duration_s) and duration_s > 0):
                raise ValueError(f"{where}: duration_s must be finite and > 0, got {duration_s}")
            rows.append((index[rid], start_s, start_s + duration_s))
        self._n = len(robot_ids)
        self._k = np.array([r[0] for r in rows], dtype=np.int64)
        self._start = np.array([r[1] for r in rows], dtype=np.float64)
        self._end = np.array([r[2] for r in rows], dtype=np.float64)
        self._edges = np.unique(np.concatenate([self._start, self._end]))

    def __len__(self) -> int:
        return len(self._k)

    def active(self, time_s: float) -> np.ndarray:
        """``(N,)`` bool: whose radio is off at ``time_s``."""
        on = (self._start <= time_s + _EPS_S) & (time_s + _EPS_S < self._end)
        out = np.zeros(self._n, dtype=bool)
        out[self._k[on]] = True
        return out

    def next_edge_s(self, time_s: float) -> float:
        """The first start or end after ``time_s`` (inf: none left); the simulator updates
        the radio then, so an outage begins and ends on time, not at the radio period."""
        i = int(np.searchsorted(self._edges, time_s + _EPS_S, side="right"))
        return float(self._edges[i]) if i < len(self._edges) else math.inf


def blackout_schedule(
    robot_ids: list[int],
    *,
    per_robot: int,
    duration_s: float,
    start_s: float,
    end_s: float,
    seed: int,
) -> tuple[Blackout, ...]:
    """``per_robot`` outages of ``duration_s`` for every robot inside ``[start_s, end_s]``,
    drawn from ``seed`` (the same arguments give the same schedule): the window is cut into
    ``per_robot`` equal slots and each outage starts uniformly at random within its slot, so
    a robot's outages never overlap and each robot gets its own times (e.g. the chaos bench's
    two 60 s blackouts per robot). Sorted by start time, then robot."""
    if per_robot < 0:
        raise ValueError(f"per_robot must be >= 0, got {per_robot}")
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ValueError(f"duration_s must be finite and > 0, got {duration_s}")
    slot_s = (end_s - start_s) / max(per_robot, 1)
    if not (math.isfinite(start_s) and start_s >= 0 and math.isfinite(end_s)):
        raise ValueError(f"need a finite window with start_s >= 0, got [{start_s}, {end_s}]")
    if per_robot and slot_s < duration_s:
        raise ValueError(
            f"{per_robot} outages of {duration_s} s do not fit in [{start_s}, {end_s}] s"
        )
    rng = np.random.default_rng(seed)
    out: list[Blackout] = []
    for rid in robot_ids:
        for j in range(per_robot):
            t0 = start_s + j * slot_s + float(rng.uniform(0.0, slot_s - duration_s))
            out.append((int(rid), t0, float(duration_s)))
    return tuple(sorted(out, key=lambda b: (b[1], b[0])))


@dataclass(frozen=True)
class RadioState:
    """Per robot: grants, route quality, hops (0: disconnected), next hop (-1: the GCS)."""

    grants: tuple[RadioGrant, ...]
    quality: np.ndarray
    hops: np.ndarray
    next_hop: np.ndarray


class RadioModel:
    """Radio links over ``occupancy`` (``(ny, nx)`` bool, cell ``resolution_m``, origin at
    world ``(0, 0)``) with the GCS antenna at ``gcs_xy_m``."""

    def __init__(
        self,
        config: RadioConfig,
        *,
        occupancy: np.ndarray,
        resolution_m: float,
        gcs_xy_m: tuple[float, float],
        sample_step_m: float = 0.2,
    ) -> None:
        self.config = config
        self._occ = np.asarray(occupancy, dtype=bool)
        self._res = float(resolution_m)
        self._gcs = np.asarray(gcs_xy_m, dtype=np.float64)
        self._step = float(sample_step_m)

    def walls_between(self, a_xy: np.ndarray, b_xy: np.ndarray) -> np.ndarray:
        """Number of walls (free -> occupied transitions) on each segment ``a[k] -> b[k]``."""
        a = np.asarray(a_xy, dtype=np.float64).reshape(-1, 2)
        b = np.asarray(b_xy, dtype=np.float64).reshape(-1, 2)
        if len(a) == 0:
            return np.zeros(0, dtype=np.int64)
        length = np.linalg.norm(b - a, axis=1)
        n = max(2, int(math.ceil(float(length.max()) / self._step)) + 1)
        t = np.linspace(0.0, 1.0, n)
        p = a[:, None, :] + (b - a)[:, None, :] * t[None, :, None]
        ny, nx = self._occ.shape
        j = np.clip((p[..., 0] / self._res).astype(np.int64), 0, nx - 1)
        i = np.clip((p[..., 1] / self._res).astype(np.int64), 0, ny - 1)
        occ = self._occ[i, j]
        rising = occ[:, 1:] & ~occ[:, :-1]
        return rising.sum(axis=1) + occ[:, 0]  # type: ignore[no-any-return]

    def quality(self, a_xy: np.ndarray, b_xy: np.ndarray) -> np.ndarray:
        """Link quality in ``[0, 1]`` of each segment (0: out of reach)."""
        cfg = self.config
        a = np.asarray(a_xy, dtype=np.float64).reshape(-1, 2)
        b = np.asarray(b_xy, dtype=np.float64).reshape(-1, 2)
        d = np.maximum(np.linalg.norm(b - a, axis=1), 1.0)
        margin = 10.0 * cfg.path_loss_exponent * np.log10(cfg.range_m / d)
        margin -= cfg.wall_loss_db * self.walls_between(a, b)
        q = np.clip(margin / cfg.fade_margin_db, 0.0, 1.0)
        return np.where(margin > 0, np.maximum(q, 1e-3), 0.0)

    def update(
        self,
        robot_xy_m: np.ndarray,
        *,
        alive: np.ndarray,
        relay: np.ndarray,
        transmitting: np.ndarray | None = None,
    ) -> RadioState:
        """Grants for every robot at positions ``(N, 2)``; dead robots get nothing and relay
        for no one; ``transmitting`` (default: all alive) robots share the air time."""
        cfg = self.config
        xy = np.asarray(robot_xy_m, dtype=np.float64).reshape(-1, 2)
        n = len(xy)
        alive = np.asarray(alive, dtype=bool)
        relays = np.nonzero(alive & np.asarray(relay, dtype=bool))[0]
        q_direct = np.where(alive, self.quality(xy, np.repeat(self._gcs[None], n, 0)), 0.0)

        # Widest path from the GCS over relays (few relays: dense Bellman-Ford on them).
        best_q = q_direct.copy()
        hops = np.where(best_q > 0, 1, 0)
        next_hop = np.full(n, -1, dtype=np.int64)
        if len(relays):
            rq = best_q[relays].copy()
            rh = hops[relays].copy()
            rnext = np.full(len(relays), -1, dtype=np.int64)
            ia, ib = np.meshgrid(np.arange(len(relays)), np.arange(len(relays)), indexing="ij")
            q_rr = self.quality(xy[relays][ia.ravel()], xy[relays][ib.ravel()]).reshape(ia.shape)
            np.fill_diagonal(q_rr, 0.0)
            for _ in range(cfg.relay_max_hops - 1):
                via = np.minimum(q_rr, rq[None, :])  # a reaches the GCS via b
                h_via = rh[None, :] + 1
                ok = (rh[None, :] > 0) & (h_via <= cfg.relay_max_hops) & (via > 0)
                cand = np.where(ok, via, 0.0)
                kbest = np.argmax(cand, axis=1)
                qbest = cand[np.arange(len(relays)), kbest]
                better = qbest > rq + 1e-12
                rq = np.where(better, qbest, rq)
                rh = np.where(better, rh[kbest] + 1, rh)
                rnext = np.where(better, relays[kbest], rnext)
            best_q[relays], hops[relays], next_hop[relays] = rq, rh, rnext
            # every other robot may go through any relay
            others = np.nonzero(alive)[0]
            if len(others):
                ia, ib = np.meshgrid(others, relays, indexing="ij")
                q_or = self.quality(xy[ia.ravel()], xy[ib.ravel()]).reshape(ia.shape)
                q_or[ia == ib] = 0.0
                via = np.minimum(q_or, rq[None, :])
                ok = (rh[None, :] > 0) & (rh[None, :] + 1 <= cfg.relay_max_hops)
                via = np.where(ok, via, 0.0)
                k = np.argmax(via, axis=1)
                qv = via[np.arange(len(others)), k]
                better = qv > best_q[others] + 1e-12
                idx = others[better]
                best_q[idx] = qv[better]
                hops[idx] = rh[k[better]] + 1
                next_hop[idx] = relays[k[better]]

        connected = alive & (best_q > 0) & (hops > 0)
        tx = connected if transmitting is None else connected & np.asarray(transmitting, bool)
        n_tx = int(tx.sum())
        grants: list[RadioGrant] = []
        for r in range(n):
            if not connected[r]:
                grants.append(RadioGrant(0.0, 0.0, 0.0))
                continue
            share = cfg.shared_capacity_bps / max(n_tx, 1) if tx[r] else 0.0
            rate = share * float(best_q[r]) / int(hops[r])
            grants.append(
                RadioGrant(
                    uplink_bps=rate * cfg.uplink_fraction,
                    downlink_bps=rate * (1.0 - cfg.uplink_fraction),
                    loss=min(cfg.max_loss * (1.0 - float(best_q[r])), 0.999),
                )
            )
        return RadioState(
            tuple(grants), np.where(connected, best_q, 0.0), np.where(connected, hops, 0), next_hop
        )
