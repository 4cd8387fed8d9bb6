"""Deduplication of detected objects on the robot: one object, one detection id (paper 5.2).

The radio is scarce (paper 4.1): a static object seen in every sweep for half a minute must
cross it about once. :class:`ObjectRegistry` keeps the objects this robot has reported, in its
private frame ``odom`` (smooth: positions stay comparable for as long as odometry drifts
little, a few hundred metres), and fuses each new sighting into the object it belongs to:

* a sighting within ``merge_m`` of a known object is that object (nearest first, whatever the
  colour said: an object does not change kind; the kind is the majority of its sightings);
* fusion is the information-weighted mean of the positions (a Kalman update of a static
  point), so the covariance shrinks with each sighting;
* an object is reported when first seen, and again (same id) only when its fused position has
  moved more than ``resend_shift_m`` from what was last reported or its kind changed: the
  uplink carries each object about once, refined positions later.

Pure: no clocks, no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = ["ObjectRegistry", "RegisteredObject", "RegistryConfig"]


class RegistryConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``merge_m``: sightings this close to a known object are that object (objects of
    interest stand metres apart, paper 2); ``resend_shift_m``: a refined position is sent when
    it moved this far from the reported one; ``min_sigma_m``: the fused position's standard
    deviation never drops below this (the cylinder model's own error)."""

    merge_m: float = 1.0
    resend_shift_m: float = 0.25
    min_sigma_m: float = 0.03

    def __post_init__(self) -> None:
        for name in ("merge_m", "resend_shift_m", "min_sigma_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"registry.{name} must be > 0, got {v}")


@dataclass
class RegisteredObject:
    """One object: ``detection_id``, ``kind`` (an ``ObjectKind`` value: the majority of the
    sightings' ``votes``), fused ``position_in_odom`` with ``covariance`` (2x2, m²)."""

    detection_id: int
    kind: int
    position_in_odom: NDArray[np.float64]
    covariance: NDArray[np.float64]
    radius_m: float
    height_m: float
    first_seen_s: float
    last_seen_s: float
    sightings: int = 1
    votes: dict[int, int] = field(default_factory=dict)
    reported_position: NDArray[np.float64] | None = None
    reported_kind: int = -1


class ObjectRegistry:
    """The objects one robot has detected (see the module docstring)."""

    def __init__(self, config: RegistryConfig | None = None, *, first_id: int = 1) -> None:
        self.config = config or RegistryConfig()
        self.objects: list[RegisteredObject] = []
        self._next_id = first_id

    def __len__(self) -> int:
        return len(self.objects)

    def nearest(self, xy_in_odom: ArrayLike, within_m: float) -> RegisteredObject | None:
        """The known object nearest ``xy_in_odom`` within ``within_m``, or None."""
        p = np.asarray(xy_in_odom, dtype=np.float64)
        best, best_d = None, within_m
        for o in self.objects:
            d = float(np.hypot(*(o.position_in_odom - p)))
            if d <= best_d:
                best, best_d = o, d
        return best

    def observe(
        self,
        kind: int,
        xy_in_odom: ArrayLike,
        covariance: ArrayLike,
        *,
        radius_m: float,
        height_m: float,
        time_s: float,
    ) -> tuple[RegisteredObject, bool]:
        """Fuse one sighting; returns the object and whether it should be (re)reported.
        Raises ValueError on a non-finite position or a covariance that is not positive
        definite (the sighting is then not fused)."""
        p = np.asarray(xy_in_odom, dtype=np.float64).reshape(2)
        c = np.asarray(covariance, dtype=np.float64).reshape(2, 2)
        if not (np.all(np.isfinite(p)) and np.all(np.isfinite(c))):
            raise ValueError(f"ObjectRegistry.observe: non-finite sighting {p.tolist()}")
        c = 0.5 * (c + c.T)
        if np.linalg.eigvalsh(c)[0] <= 0:
            raise ValueError(f"ObjectRegistry.observe: covariance not positive definite {c}")
        cfg = self.config
        o = self.nearest(p, cfg.merge_m)
        if o is None:
            o = RegisteredObject(
                self.new_id(),
                int(kind),
                p.copy(),
                c.copy(),
                float(radius_m),
                float(height_m),
                time_s,
                time_s,
                votes={int(kind): 1},
            )
            self.objects.append(o)
        else:
            info = np.linalg.inv(o.covariance) + np.linalg.inv(c)
            cov = np.linalg.inv(info)
            o.position_in_odom = cov @ (
                np.linalg.solve(o.covariance, o.position_in_odom) + np.linalg.solve(c, p)
            )
            floor = cfg.min_sigma_m**2
            w, v = np.linalg.eigh(0.5 * (cov + cov.T))
            o.covariance = (v * np.maximum(w, floor)) @ v.T
            n = o.sightings
            o.radius_m = (o.radius_m * n + float(radius_m)) / (n + 1)
            o.height_m = (o.height_m * n + float(height_m)) / (n + 1)
            o.sightings = n + 1
            o.last_seen_s = max(o.last_seen_s, time_s)
            o.votes[int(kind)] = o.votes.get(int(kind), 0) + 1
            # the majority; ties keep the kind first reported
            o.kind = max(o.votes, key=lambda k: (o.votes[k], k == o.kind))
        due = (
            o.reported_position is None
            or o.kind != o.reported_kind
            or float(np.hypot(*(o.position_in_odom - o.reported_position))) > cfg.resend_shift_m
        )
        return o, due

    def mark_reported(self, obj: RegisteredObject) -> None:
        """Record that ``obj`` as it is now has been sent."""
        obj.reported_position = obj.position_in_odom.copy()
        obj.reported_kind = obj.kind

    def new_id(self) -> int:
        """A fresh detection id from the same sequence (for objects not kept here: tracks)."""
        self._next_id += 1
        return self._next_id - 1

    def get(self, detection_id: int) -> RegisteredObject | None:
        return next((o for o in self.objects if o.detection_id == detection_id), None)
