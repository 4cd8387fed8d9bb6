"""Per-sweep LIDAR perception: cylinders by shape and tracked people (paper 5.2.1, 2).

:class:`LidarDetector` is what a robot node calls once per de-skewed sweep (points in
``odom``): segmentation (:mod:`robot.perception.segmentation`), features
(:mod:`robot.perception.shape_features`), learned thresholds
(:mod:`robot.perception.shape_classifier`), and the people tracker
(:mod:`robot.perception.person_tracker`). It returns

* ``cylinders``: candidate cylinders of OOI / toxic-vat size (shape only: the colour
  classifier decides which, from the image memory), each with its centre in ``odom``;
* ``people``: confirmed person tracks (position and velocity in ``odom``);

and counts what it skipped. No I/O, no clocks: the caller passes the sweep's time.
"""

from __future__ import annotations

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
    object_position,
    ransac_circle,
    shape_features,
)

__all__ = ["CylinderCandidate", "LidarDetector", "LidarDetectorConfig", "SweepPerception"]

_I_RADIUS = FEATURE_NAMES.index("radius_m")
_I_LENGTH = FEATURE_NAMES.index("length_m")
_I_BREADTH = FEATURE_NAMES.index("breadth_m")
_I_TOP = FEATURE_NAMES.index("top_m")


class LidarDetectorConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """``max_extent_m``: segments longer than this are not measured at all (walls, cars:
    saves time); ``nominal_radius_m``: the cylinder radius used to place a candidate whose
    circle fit is unreliable (the OOIs' size, paper 2)."""

    segmentation: SegmentationConfig = SegmentationConfig()
    tracker: TrackerConfig = TrackerConfig()
    max_extent_m: float = 1.5
    nominal_radius_m: float = 0.27


@dataclass(frozen=True)
class CylinderCandidate:
    """A segment whose shape passed the ``cylinder`` thresholds: centre ``(x, y)`` in odom,
    fitted ``radius_m`` (the nominal one when the fit failed), ``height_m`` above ground,
    its ``features`` (:data:`FEATURE_NAMES`) and point count."""

    position_in_odom: NDArray[np.float64]
    radius_m: float
    height_m: float
    features: NDArray[np.float64]
    n_points: int


@dataclass(frozen=True)
class SweepPerception:
    time_s: float
    cylinders: list[CylinderCandidate]
    people: list[PersonTrack]
    person_positions_in_odom: NDArray[np.float64]
    segments: int
    dropped_nonfinite: int


class LidarDetector:
    """Shape detector and people tracker of one robot (see the module docstring).

    ``thresholds``: learned :class:`ShapeThresholds`, or a path to their file (default: the
    shipped ``shape_thresholds_v1.json``); a bad file raises ``ThresholdFileError`` here,
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
        self.sweeps = 0
        self.dropped_nonfinite = 0

    def features(
        self, points_in_odom: ArrayLike, sensor_xy_in_odom: ArrayLike
    ) -> tuple[list[NDArray[np.float64]], NDArray[np.float64], NDArray[np.float64], int]:
        """Segment a sweep and measure every small segment: ``(segment_xyz list, features
        (n, F), sensor_xy, dropped_nonfinite)``; large segments are left out."""
        seg = segment_sweep(points_in_odom, sensor_xy_in_odom, config=self.config.segmentation)
        xyzs: list[NDArray[np.float64]] = []
        feats: list[NDArray[np.float64]] = []
        lim = self.config.max_extent_m
        for s in seg.segments:
            span = s.xyz[:, :2].max(axis=0) - s.xyz[:, :2].min(axis=0)
            if math.hypot(span[0], span[1]) > lim * math.sqrt(2):
                continue
            xyzs.append(s.xyz)
            feats.append(shape_features(s, seg.above_ground_xyz, seg.sensor_xy))
        f = np.array(feats).reshape(-1, len(FEATURE_NAMES))
        return xyzs, f, seg.sensor_xy, seg.dropped_nonfinite

    def process(
        self, points_in_odom: ArrayLike, sensor_xy_in_odom: ArrayLike, time_s: float
    ) -> SweepPerception:
        """One sweep: candidates and tracks (see :class:`SweepPerception`)."""
        xyzs, f, sensor, dropped = self.features(points_in_odom, sensor_xy_in_odom)
        self.sweeps += 1
        self.dropped_nonfinite += dropped
        cyl = self.thresholds.accepts("cylinder", f) if len(f) else np.zeros(0, bool)
        per = (
            self.thresholds.accepts("person", f)
            if len(f) and "person" in self.thresholds.boxes
            else np.zeros(len(f), bool)
        )
        cylinders: list[CylinderCandidate] = []
        for k in np.flatnonzero(cyl):
            cylinders.append(self._place(xyzs[k], f[k], sensor))
        person_xy = np.array(
            [object_position(xyzs[k][:, :2], sensor, 0.2) for k in np.flatnonzero(per & ~cyl)]
        ).reshape(-1, 2)
        people = self.tracker.update(time_s, person_xy)
        return SweepPerception(time_s, cylinders, people, person_xy, len(f), dropped)

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
