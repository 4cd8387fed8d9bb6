"""People walking their patrol routes (paper 2: civilians and hostiles, the mobile OOIs).

Pure function of time: a person with route ``P0 .. Pk`` walks the closed polyline
``P0 -> P1 -> ... -> Pk -> P0`` at constant speed, forever (a two-point route is walked back and
forth); a one-point route stands still. Positions are in ``world`` metres.
"""

from __future__ import annotations

import numpy as np

from sim.world_generator import Human

__all__ = ["PatrolRoutes"]


class PatrolRoutes:
    """Positions of all ``humans`` at any time, vectorized over people."""

    def __init__(self, humans: tuple[Human, ...]) -> None:
        self._routes = [np.asarray(h.route_m, dtype=np.float64).reshape(-1, 2) for h in humans]
        self._speed = np.array([h.speed_m_s for h in humans], dtype=np.float64)
        self._cum: list[np.ndarray] = []
        self._len = np.zeros(len(humans))
        for k, r in enumerate(self._routes):
            closed = np.vstack([r, r[:1]])
            seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
            self._cum.append(np.concatenate([[0.0], np.cumsum(seg)]))
            self._len[k] = seg.sum()

    def __len__(self) -> int:
        return len(self._routes)

    def positions(self, time_s: float) -> np.ndarray:
        """``(H, 2)`` positions at ``time_s``."""
        out = np.zeros((len(self._routes), 2))
        for k, r in enumerate(self._routes):
            if self._len[k] <= 0:
                out[k] = r[0]
                continue
            s = (self._speed[k] * time_s) % self._len[k]
            cum = self._cum[k]
            i = int(np.searchsorted(cum, s, side="right")) - 1
            i = min(i, len(r) - 1)
            a = r[i]
            b = r[(i + 1) % len(r)]
            seg = cum[i + 1] - cum[i]
            t = 0.0 if seg <= 0 else (s - cum[i]) / seg
            out[k] = a + t * (b - a)
        return out
