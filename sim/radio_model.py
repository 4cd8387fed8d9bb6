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
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from protocol.radio import RadioConfig, RadioGrant

__all__ = ["RadioModel", "RadioState"]


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
