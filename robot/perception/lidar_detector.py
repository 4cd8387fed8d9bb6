"""Per-sweep LIDAR perception: cylinders by shape and tracked people (paper 5.2.1, 2).

:class:`LidarDetector` is what a robot node calls once per de-skewed sweep (points in
``odom``): segmentation (:mod:`robot.perception.segmentation`), features
(:mod:`robot.perception.shape_features`), learned thresholds
(:mod:`robot.perception.shape_classifier`), and the people tracker
(:mod:`robot.perception.person_tracker`). It returns

* ``cylinders``: candidate cylinders of OOI / toxic-vat size (shape only: the colour
  classifier decides which, from the image memory), each with its centre in ``odom``, the
  id of the place it was seen at, and ``confirmed`` once that place was seen in two sweeps
  (``confirmed_cylinders``: what should go on to the colour test);
* ``people``: confirmed person tracks (position and velocity in ``odom``) of the segments
  of human size, cylinder-shaped ones included (a person hidden to the waist has an OOI's
  shape; a track that moves, or the colour test, tells them apart);
* ``segments_in_odom``: every segment it measured (centre, extent, top): what may be a
  teammate carrying tags (the onboard perception's gate on its periodic tag images);

and counts what it skipped. No I/O, no clocks: the caller passes the sweep's time (and,
optionally, each point's time: people are measured at the time their points were taken).
Cost: about 5 ms a sweep (p50), 8-9 ms p95, CPU of one core, 4000-point sweeps.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path

import msgspec
import numpy as np
from numpy.typing import ArrayLike, NDArray

from robot.perception.person_tracker import PersonTrack, PersonTracker, TrackerConfig
from robot.perception.segmentation import SegmentationConfig, segment_sweep
from robot.perception.shape_classifier import (
    DEFAULT_THRESHOLDS_PATH,
    ShapeThresholds,
    load_thresholds,
)
from robot.perception.shape_features import (
    FEATURE_NAMES,
    batch_features,
    object_position,
    ransac_circle,
)

__all__ = ["CylinderCandidate", "LidarDetector", "LidarDetectorConfig", "SweepPerception"]

_I_RADIUS = FEATURE_NAMES.index("radius_m")
_I_LENGTH = FEATURE_NAMES.index("length_m")
_I_BREADTH = FEATURE_NAMES.index("breadth_m")
_I_TOP = FEATURE_NAMES.index("top_m")


class LidarDetectorConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``max_extent_m``: segments longer than this are not measured at all (walls, cars:
    saves time); ``nominal_radius_m``: the cylinder radius used to place a candidate whose
    circle fit is unreliable (the OOIs' size, paper 2).

    Multi-sweep confirmation (precision): a candidate is ``confirmed`` once shape candidates
    within ``confirm_gate_m`` of each other (in ``odom``) were seen in ``confirm_sweeps``
    sweeps, the last within ``confirm_forget_s`` of the one before (a passing clutter of
    points rarely repeats at one place; an object does, from every viewpoint)."""

    segmentation: SegmentationConfig = SegmentationConfig()
    tracker: TrackerConfig = TrackerConfig()
    max_extent_m: float = 1.5
    nominal_radius_m: float = 0.27
    confirm_sweeps: int = 2
    confirm_gate_m: float = 0.5
    confirm_forget_s: float = 5.0

    def __post_init__(self) -> None:
        if self.confirm_sweeps < 1:
            raise ValueError(f"confirm_sweeps must be >= 1, got {self.confirm_sweeps}")
        for name in ("max_extent_m", "nominal_radius_m", "confirm_gate_m", "confirm_forget_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be > 0, got {v}")


@dataclass(frozen=True)
class CylinderCandidate:
    """A segment whose shape passed the ``cylinder`` thresholds: centre ``(x, y)`` in odom,
    fitted ``radius_m`` (the nominal one when the fit failed), ``height_m`` above ground,
    its ``features`` (:data:`FEATURE_NAMES`) and point count; ``object_id``: the detector's
    id of the place it was seen at (the same across sweeps), ``sweeps_seen`` there so far,
    ``confirmed`` when that reached ``confirm_sweeps``."""

    position_in_odom: NDArray[np.float64]
    radius_m: float
    height_m: float
    features: NDArray[np.float64]
    n_points: int
    object_id: int = 0
    sweeps_seen: int = 1
    confirmed: bool = False


@dataclass
class _Place:
    """A place in ``odom`` where shape candidates were seen (running mean position)."""

    object_id: int
    xy: NDArray[np.float64]
    sweeps: int
    last_s: float


@dataclass(frozen=True)
class SweepPerception:
    """One sweep's result: every shape candidate (``confirmed`` ones passed the multi-sweep
    test), confirmed person tracks, this sweep's person measurements, counts."""

    time_s: float
    cylinders: list[CylinderCandidate]
    people: list[PersonTrack]
    person_positions_in_odom: NDArray[np.float64]
    segments: int
    dropped_nonfinite: int
    # every measured (small) segment: rows (x_m, y_m, extent_m, top_m) in odom; extent: the
    # larger of its bounding rectangle's sides
    segments_in_odom: NDArray[np.float64] = dataclasses.field(
        default_factory=lambda: np.zeros((0, 4))
    )

    @property
    def confirmed_cylinders(self) -> list[CylinderCandidate]:
        return [c for c in self.cylinders if c.confirmed]


class LidarDetector:
    """Shape detector and people tracker of one robot (see the module docstring).

    ``thresholds``: learned :class:`ShapeThresholds`, or a path to their file (default: the
    shipped ``shape_thresholds_v2.json``); a bad file raises ``ThresholdFileError`` here,
    at start-up, not per sweep."""

    def __init__(
        self,
        config: LidarDetectorConfig | None = None,
        thresholds: ShapeThresholds | str | Path = DEFAULT_THRESHOLDS_PATH,
    ) -> None:
        self.config = config or LidarDetectorConfig()
        self.thresholds = (
            thresholds if isinstance(thresholds, ShapeThresholds) else load_thresholds(thresholds)
        )
        self.tracker = PersonTracker(self.config.tracker)
        self.places: list[_Place] = []
        self._next_place = 1
        self.sweeps = 0
        self.dropped_nonfinite = 0

    def reset(self) -> None:
        """Forget every place and person track (a new run; counters stay)."""
        self.tracker = PersonTracker(self.config.tracker)
        self.places = []

    def features(
        self, points_in_odom: ArrayLike, sensor_xy_in_odom: ArrayLike
    ) -> tuple[list[NDArray[np.float64]], NDArray[np.float64], NDArray[np.float64], int]:
        """Segment a sweep and measure every small segment: ``(segment_xyz list, features
        (n, F), sensor_xy, dropped_nonfinite)``; large segments are left out."""
        xyzs, f, sensor, dropped, _ = self._measure(points_in_odom, sensor_xy_in_odom)
        return xyzs, f, sensor, dropped

    def _measure(
        self, points_in_odom: ArrayLike, sensor_xy_in_odom: ArrayLike
    ) -> tuple[
        list[NDArray[np.float64]],
        NDArray[np.float64],
        NDArray[np.float64],
        int,
        list[NDArray[np.int64]],
    ]:
        seg = segment_sweep(points_in_odom, sensor_xy_in_odom, config=self.config.segmentation)
        if len(seg.starts) == 0:
            empty = np.zeros((0, len(FEATURE_NAMES)))
            return [], empty, seg.sensor_xy, seg.dropped_nonfinite, []
        f = batch_features(
            seg.object_xyz,
            seg.object_height_m,
            seg.starts,
            seg.ends,
            seg.above_ground_xyz,
            seg.sensor_xy,
            max_diagonal_m=self.config.max_extent_m * math.sqrt(2),
        )
        small = np.isfinite(f[:, 0])
        f = f[small]
        bounds = list(zip(seg.starts[small].tolist(), seg.ends[small].tolist(), strict=True))
        xyzs = [seg.object_xyz[s:e] for s, e in bounds]
        rows = [seg.object_rows[s:e] for s, e in bounds]
        return xyzs, f, seg.sensor_xy, seg.dropped_nonfinite, rows

    def process(
        self,
        points_in_odom: ArrayLike,
        sensor_xy_in_odom: ArrayLike,
        time_s: float,
        point_time_s: ArrayLike | None = None,
    ) -> SweepPerception:
        """One sweep: candidates and tracks (see :class:`SweepPerception`).

        ``point_time_s``: optional, each point's time in seconds after ``time_s`` (the
        sweep's :attr:`~protocol.sensors.LidarSweep.point_time_s`, rows as in
        ``points_in_odom``). A nodding scanner crosses a person in the first or the last
        part of its 1.25 s sweep depending on the tilt direction, so a person is measured
        at the mean time of its own points; without it, at ``time_s`` (alternate sweeps
        then disagree by up to a second: a walker's velocity error of 0.3-0.5 m/s)."""
        xyzs, f, sensor, dropped, rows = self._measure(points_in_odom, sensor_xy_in_odom)
        times: NDArray[np.float64] | None = None
        if point_time_s is not None:
            times = np.asarray(point_time_s, dtype=np.float64).reshape(-1)
            n_pts = np.asarray(points_in_odom).reshape(-1, 3).shape[0]
            if times.shape[0] != n_pts:
                raise ValueError(
                    f"point_time_s: {times.shape[0]} times for {n_pts} points_in_odom rows"
                )
        self.sweeps += 1
        self.dropped_nonfinite += dropped
        cyl = self.thresholds.accepts("cylinder", f) if len(f) else np.zeros(0, bool)
        per = (
            self.thresholds.accepts("person", f)
            if len(f) and "person" in self.thresholds.boxes
            else np.zeros(len(f), bool)
        )
        cylinders = self._confirm(
            time_s, [self._place(xyzs[k], f[k], sensor) for k in np.flatnonzero(cyl)]
        )
        ks = np.flatnonzero(per)
        person_xy = np.array([object_position(xyzs[k][:, :2], sensor, 0.2) for k in ks]).reshape(
            -1, 2
        )
        person_t = None
        if times is not None:
            person_t = np.array([time_s + float(np.mean(times[rows[k]])) for k in ks])
            person_t = np.where(np.isfinite(person_t), person_t, time_s)
        people = self.tracker.update(time_s, person_xy, measurement_times_s=person_t)
        segs = np.zeros((len(f), 4))
        for k, xyz in enumerate(xyzs):
            segs[k, :2] = xyz[:, :2].mean(axis=0)
        if len(f):
            segs[:, 2] = np.maximum(f[:, _I_LENGTH], f[:, _I_BREADTH])
            segs[:, 3] = f[:, _I_TOP]
        return SweepPerception(time_s, cylinders, people, person_xy, len(f), dropped, segs)

    def _confirm(self, time_s: float, cands: list[CylinderCandidate]) -> list[CylinderCandidate]:
        """Attach each candidate to the nearest place within the gate (one candidate a
        place a sweep, nearest pairs first), start places for the rest, forget stale ones."""
        cfg = self.config
        self.places = [p for p in self.places if time_s - p.last_s <= cfg.confirm_forget_s]
        out: list[CylinderCandidate | None] = [None] * len(cands)
        if cands and self.places:
            cxy = np.array([c.position_in_odom for c in cands])
            pxy = np.array([p.xy for p in self.places])
            d = np.hypot(*(cxy[:, None, :] - pxy[None, :, :]).transpose(2, 0, 1))
            used: set[int] = set()
            for flat in np.argsort(d, axis=None).tolist():
                i, j = divmod(flat, len(self.places))
                if d[i, j] > cfg.confirm_gate_m:
                    break
                if out[i] is not None or j in used:
                    continue
                used.add(j)
                p = self.places[j]
                p.sweeps += 1
                p.xy = p.xy + (cxy[i] - p.xy) / p.sweeps
                p.last_s = time_s
                out[i] = dataclasses.replace(
                    cands[i],
                    object_id=p.object_id,
                    sweeps_seen=p.sweeps,
                    confirmed=p.sweeps >= cfg.confirm_sweeps,
                )
        for i, c in enumerate(cands):
            if out[i] is None:
                p = _Place(self._next_place, np.array(c.position_in_odom, float), 1, time_s)
                self._next_place += 1
                self.places.append(p)
                out[i] = dataclasses.replace(
                    c, object_id=p.object_id, confirmed=cfg.confirm_sweeps <= 1
                )
        return [c for c in out if c is not None]

    def _place(
        self, xyz: NDArray[np.float64], feat: NDArray[np.float64], sensor: NDArray[np.float64]
    ) -> CylinderCandidate:
        xy = xyz[:, :2]
        r_fit = float(feat[_I_RADIUS])
        nominal = self.config.nominal_radius_m
        if math.isfinite(r_fit) and 0.6 * nominal <= r_fit <= 1.5 * nominal and len(xy) >= 6:
            fit = ransac_circle(xy)
            if fit is not None:
                centre, radius, inl = fit
                # a good fit has most points on the circle and its centre behind them
                d_c = float(np.hypot(*(centre - sensor)))
                d_p = float(np.hypot(*(xy.mean(axis=0) - sensor)))
                if inl.mean() >= 0.7 and d_c > d_p:
                    return CylinderCandidate(centre, radius, float(feat[_I_TOP]), feat, len(xy))
        r = max(float(feat[_I_BREADTH]), float(feat[_I_LENGTH])) / 2
        r = min(max(r, 0.6 * nominal), 1.5 * nominal)
        return CylinderCandidate(
            object_position(xy, sensor, r), nominal, float(feat[_I_TOP]), feat, len(xy)
        )
