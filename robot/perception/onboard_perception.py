"""The robot's perception loop: LIDAR candidates, image memory, colour, tracks, fiducials
(paper 5.2, 5.2.1, Fig. 13, 4.3.2), as the robot node runs it.

Everything is in the robot's private frame ``odom``; the node turns the results into radio
messages against its pose nodes. Per call:

* :meth:`OnboardPerception.on_control` (every control period, cheap): remembers the panning
  camera's frame every ``frame_period_s`` (time, pan from the pan schedule, robot pose:
  :mod:`robot.perception.image_memory`), learns the schedule's phase from the first images
  (:func:`robot.perception.camera_model.fit_pan_phase`), asks for an image of *now* every
  ``fiducial_period_s`` (teammates' tags) when it may show something (a segment of the
  recent LIDAR sweeps within a tag's range, or a people track to colour-test:
  ``tag_gate_memory_s``), and gives up on images that never came (``image_timeout_s``,
  counted).
* :meth:`OnboardPerception.on_sweep`: the LIDAR detector
  (:class:`robot.perception.lidar_detector.LidarDetector`: cylinders by shape, person tracks);
  each new cylinder candidate and each person track not yet coloured gets the newest
  remembered frame in which it projects fully (Fig. 13) and one
  :class:`~protocol.sensors.ImageRequest` per frame (candidates sharing a frame share it);
  candidates at an already known object refine it without an image; a place whose colour test
  said "other" is not asked about again for ``retest_after_s`` and at most
  ``max_negative_tests`` times. Hostile tracks are reported (with velocity) every
  ``hostile_report_period_s`` and are keep-out disks at once (:meth:`own_hazards_in_odom`).
* :meth:`OnboardPerception.on_image`: the colour test of each job of the image
  (:func:`robot.perception.colour_classifier.classify_candidate`); static OOIs and toxic vats
  go through the :class:`robot.perception.object_registry.ObjectRegistry` (one object, one id,
  refined later); people tracks get their kind; the image is searched for teammates' tags.
* :meth:`OnboardPerception.on_thumbnail_request`: a :class:`~protocol.messages.DetectionImage`
  cropped from the image the object's colour test used (only on request, paper 6.1).

CPU (issue 14, session 13; the 14-robot ``magic_phase``'s first 60 mission-s, seed 0,
thread CPU, mean of two runs at load ~20, reports identical): :meth:`OnboardPerception.on_image`
7.9 -> 6.8 CPU-ms per robot-mission-s (colour tests 2.3 -> 1.3: per-value tables in
:mod:`robot.perception.colour_classifier`; flat frames' tag search 0.22 -> 0.11); what is
left is the tag search of real images (3.3) and the teammates' pose fits (1.3);
:meth:`OnboardPerception.on_sweep` 3.2 -> 3.0. The robot node as a whole: 37.5 -> 32.1.

Bad input never stops the robot: non-finite points are dropped and counted, an image that
never arrives is counted and its candidates may be asked about again, an image of the wrong
shape is counted and skipped. A bad thresholds file is an error at construction, naming it.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import msgspec
import numpy as np
from numpy.typing import NDArray

from protocol.messages import DetectionImage, ObjectKind, ThumbnailRequest
from protocol.se2 import relative
from protocol.sensors import CameraImage, ImageRequest
from robot.perception.camera_model import Intrinsics, base_from_camera, fit_pan_phase, pan_at
from robot.perception.colour_classifier import (
    DEFAULT_THRESHOLDS_PATH as COLOUR_THRESHOLDS_PATH,
)
from robot.perception.colour_classifier import (
    ColourThresholds,
    classify_candidate,
)
from robot.perception.colour_classifier import (
    load_thresholds as load_colour_thresholds,
)
from robot.perception.fiducial_detector import (
    FiducialConfig,
    TagDetection,
    TeammateSighting,
    detect_tags,
    estimate_teammates,
    fit_rows_px,
)
from robot.perception.image_memory import Candidate, ImageMemory, ImageMemoryConfig, RememberedFrame
from robot.perception.lidar_detector import LidarDetector, LidarDetectorConfig
from robot.perception.object_registry import ObjectRegistry, RegistryConfig
from robot.perception.person_tracker import PersonTrack
from robot.perception.shape_classifier import DEFAULT_THRESHOLDS_PATH as SHAPE_THRESHOLDS_PATH
from robot.perception.thumbnail import make_thumbnail

__all__ = [
    "FiducialSighting",
    "OdomDetection",
    "OnboardPerception",
    "PerceptionConfig",
    "PerceptionStats",
]

log = logging.getLogger(__name__)

_LIDAR_IN_BASE_M = (0.2, 0.0)  # the LIDAR's mount (sim.scene.RobotGeometry.lidar_m)
_COLOUR_KIND = {"static_ooi": ObjectKind.STATIC_OOI, "toxic_vat": ObjectKind.TOXIC_VAT}
_PERSON_KIND = {"civilian": ObjectKind.CIVILIAN, "hostile": ObjectKind.HOSTILE}


class PerceptionConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """The robot's perception (see the module docstring). Paths: ``""`` means the shipped
    threshold files beside :mod:`robot.perception`."""

    enabled: bool = True
    lidar: LidarDetectorConfig = LidarDetectorConfig()
    shape_thresholds: str = ""
    colour_thresholds: str = ""
    memory: ImageMemoryConfig = ImageMemoryConfig()
    fiducial: FiducialConfig = FiducialConfig()
    registry: RegistryConfig = RegistryConfig()
    frame_period_s: float = 0.1  # image memory: one frame remembered per this period
    image_timeout_s: float = 3.0
    max_requests_per_sweep: int = 4
    max_requests_per_step: int = 2  # the simulator takes at most 4 per robot per step
    # every fiducial_period_s a coarse image of now (1 s: the 60 deg view pans 0.8 rad, so
    # consecutive images leave no gap); one showing a teammate's tag is asked
    # again at fiducial_width_px x fiducial_height_px for the pose (yaw p95 at 1-3 m: 6.6 deg
    # at 320x240, 1.3 deg at 640x480); 0: tags only in images asked for objects.
    # Issue 14, session 15 (quick mission at 8183549, seeds 0 / 7 / 3 / 11, thread CPU at
    # load 10-16): these images are most of the render worker's ~1830 a run (22.1 / 23.4
    # CPU-s of the run's 120.8 / 124.8, seeds 0 / 7). Every 2 s with the memory at 240 x 180
    # (the colour tests' largest size too): 1115-1284 images, render 11.2 / 8.7 / 9.9 / 9.0,
    # runs 106.7 / 104.2 / 107.2 / 105.7 CPU-s; but ATE 0.086 / 0.252 / 0.218 / 0.172 m
    # (median 0.144 -> 0.195), F1 0.946 / 0.571 / 0.843 / 0.885 (0.906 -> 0.864), false
    # closures 0 / 2 / 0 / 0 (0 / 0 / 1 / 0), explored median 0.920 -> 0.938, every static
    # OOI detected and neutralized: not kept (fiducial edges 4 / 3 / 0 / 1 against 1 / 10 /
    # 4 / 1: other sightings, another map)
    fiducial_period_s: float = 1.0
    # ... and only when it may show something: a small LIDAR segment (every one the
    # detector measures, at most lidar.max_extent_m across: a teammate is one like any
    # other; the robot knows its teammates only by its own sensing) seen within
    # tag_gate_memory_s whose centre lies within fiducial.max_range_m of the camera and
    # within half the field of view of the camera's pan of now, both widened by
    # tag_gate_radius_m + tag_gate_speed_m_s x the segment's age; or a people track not
    # labelled yet that projects fully into it (its colour test: a hostile is labelled from
    # any image). Else that period's image is skipped (the images asked are a subset of
    # those without the gate). 0: off (an image every period). Issue 16, session 16 (quick
    # mission at 1d6eb73, seeds 0 / 7 / 3 / 11): periodic images 1139 / 1149 / 1151 / 1151 ->
    # 856 / 857 / 862 / 865, a run's renders 1848 / 1792 / 1801 / 1776 -> 1534 / 1500 /
    # 1512 / 1490; seeds 7 / 3 / 11 the same runs to the bit as without the gate (every
    # image that showed a tag kept), run CPU (user + sys, at one load) 88.5 / 88.3 -> 84.8 /
    # 84.9 s on seeds 3 / 11; seed 0 another run from one skipped image of a teammate 6.6 m
    # away seen only in a 3.5 s old sweep (explored 0.945 -> 0.956, F1 0.696 -> 0.742, ATE
    # 0.441 -> 0.296 m, fiducial edges 3 -> 2).
    tag_gate_memory_s: float = 2.0
    tag_gate_radius_m: float = 0.5
    tag_gate_speed_m_s: float = 1.0
    fiducial_width_px: int = 640
    fiducial_height_px: int = 480
    # a teammate's pose (a fine image) is asked again at most this often: a coarse image that
    # shows only teammates asked about within it asks for no fine image (issue 16: in a crowd
    # every coarse image shows tags; their fine images were 3/4 of a 64-robot team's renders
    # and most of its tag-fitting CPU, for the same pairs again and again). 0: every time.
    fiducial_refresh_s: float = 3.0
    # the fine image is a band of rows about the principal point (same width and focal
    # length: exactly those rows of the full fine image), as tall as the teammates of the
    # coarse image need (their tags and the LIDAR housing the face cue samples:
    # fiducial_detector.fit_rows_px, scaled, plus fiducial_band_margin_px above and below)
    # and at least fiducial_band_min_px (teammates too far for the coarse image to decode sit
    # near the horizon: within 6 m, a 3 deg pitch, 85 rows of the middle). Issue 16: a
    # render's cost grows with its rows (640x240 ~60 % of 640x480). 0: the full height.
    fiducial_band_min_px: int = 192
    fiducial_band_margin_px: int = 16
    # a colour test's image is asked as small as its candidates allow: the smallest of
    # colour_widths_px (4:3, below the memory's size) in which every candidate, at its range
    # from the frame's pose, covers colour_min_area_px (its diameter x height, pixels) and
    # spans colour_min_width_px across; else the memory's size. 600 px: three times what a
    # 0.25 x 0.8 m object at the memory's 12 m range covers at 320x240 (the classifier's
    # working range). Such an object within ~5.5 m is asked at 240x180, within ~3.6 m at
    # 160x120 (1/3.5 of the render's cost). 0: the memory's size. Issue 16: in a crowd
    # nearly every colour test is of a teammate a metre or two away. Cylinders a sweep asks
    # about also join a frame asked for another within colour_group_s of their own that
    # shows them whole (one image, not two).
    colour_min_area_px: float = 600.0
    colour_min_width_px: float = 8.0
    colour_widths_px: tuple[int, ...] = (160, 240)
    colour_group_s: float = 2.0
    # of the two images that settle the pan schedule's phase, the first phase_full_images
    # are asked at the memory's size (searched for tags like any other: in the staging area
    # they show teammates, and those first sightings place the robots in the map; two 16 px
    # probes moved the team-mapping trial's ATE 0.21 -> 0.25 m), the others as probes of
    # phase_probe_px square: only their pan angle is used (issue 16: a 64-robot team's first
    # second was mostly these renders and the fine images their tags asked for). 0: full.
    phase_probe_px: int = 16
    phase_full_images: int = 1
    # a LIDAR candidate (cylinder or person) where a teammate's tag was seen lately is that
    # teammate, not asked about (issue 16: in a crowd most candidates were teammates, each an
    # image): within teammate_radius_m + teammate_speed_m_s x the time between the sighting
    # and the sweep, for sightings at most teammate_memory_s old (0: off). Positions from the
    # tags of every image: bearing from the tag's centre, range from its height in pixels.
    teammate_memory_s: float = 1.5
    teammate_radius_m: float = 0.7
    teammate_speed_m_s: float = 1.0
    # a person track an image shows as a teammate (a head whose tag this image shows within
    # teammate_radius_m of where the track was placed) is not asked about again for this
    # long (issue 16: every teammate that drives off is a person track; each was tested up
    # to max_person_tests times, an image each, by every robot that saw it). 0: off.
    teammate_track_hold_s: float = 10.0
    candidate_max_range_m: float = 10.0
    retest_after_s: float = 2.0
    wait_for_frame_s: float = 8.0  # a candidate no frame shows whole waits this long for one
    max_negative_tests: int = 2
    max_person_tests: int = 6  # colour tests of one people track before it is left unlabelled
    person_votes_needed: int = 2  # agreeing colour tests (images) before a track is labelled
    negative_radius_m: float = 0.7
    negative_places_kept: int = 512
    refine_m: float = 0.6  # a cylinder this close to a known object refines it, no image
    person_frame_window_s: float = 2.5  # people move: only recent frames for their colour
    person_radius_m: float = 0.3
    person_height_m: float = 1.6
    person_shifts_m: tuple[float, ...] = (0.0, -0.25, 0.25)
    person_shifted_min_fraction: float = 0.7
    person_merge_m: float = 1.0
    velocity_window_s: float = 4.0
    civilian_memory_s: float = 20.0  # where civilians were seen: a hostile there is re-checked
    label_jump_m: float = 1.0  # a labelled track jumping this far off its line is re-coloured
    max_report_sigma_m: float = 0.7
    hostile_report_period_s: float = 2.0
    hostile_lookahead_s: float = 1.0  # the keep-out disk sits where the hostile will be
    # a track once labelled hostile keeps its keep-out disk this long after losing the label
    # (it drops when the walker turns at a corner of its route, off its own line: small world
    # seed 0, the robot drove on to 5 m of the unlabelled hostile, whose disk had vanished)
    hostile_memory_s: float = 20.0
    # a new track within hostile_reid_m (+ hostile_reid_m_s per second since) of where a
    # dropped hostile track would be now is that hostile, for the keep-out (the tracker drops
    # a walker it misses for a few sweeps, behind the robot or a corner, and the new track
    # needs two colour tests: robots evading it lost it that way, and it walked on at them)
    hostile_reid_m: float = 1.5
    hostile_reid_m_s: float = 0.3
    hostile_reid_s: float = 10.0  # ... within this long of the drop
    # raw cylinder sightings kept this long for a fresh look at an object (the disruptor's
    # laser aims at what it sees now, not at a fused position carrying the odometry drift
    # since the object was first seen: small world, 0.58 m and 1.8 deg after 9.5 m on sand)
    recent_cylinders_s: float = 10.0
    pos_sigma_m: float = 0.06  # a cylinder centre's error at 0 m ...
    pos_sigma_per_m: float = 0.012  # ... growing with range
    thumbnail_max_bytes: int = 2000
    thumbnails_kept: int = 64

    def __post_init__(self) -> None:
        for name in ("frame_period_s", "image_timeout_s", "retest_after_s", "negative_radius_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"perception.{name} must be > 0, got {v}")
        if not (math.isfinite(self.fiducial_refresh_s) and self.fiducial_refresh_s >= 0):
            raise ValueError(
                f"perception.fiducial_refresh_s must be >= 0, got {self.fiducial_refresh_s}"
            )
        if not (math.isfinite(self.fiducial_period_s) and self.fiducial_period_s >= 0):
            raise ValueError(
                f"perception.fiducial_period_s must be >= 0, got {self.fiducial_period_s}"
            )
        for name in (
            "teammate_memory_s",
            "tag_gate_memory_s",
            "tag_gate_radius_m",
            "tag_gate_speed_m_s",
            "teammate_radius_m",
            "teammate_speed_m_s",
            "teammate_track_hold_s",
        ):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"perception.{name} must be >= 0, got {v}")
        if self.phase_probe_px != 0 and not 16 <= self.phase_probe_px <= 2048:
            raise ValueError(
                f"perception.phase_probe_px must be 0 or in [16, 2048], got {self.phase_probe_px}"
            )
        if self.fiducial_band_min_px != 0 and not 16 <= self.fiducial_band_min_px <= 2048:
            raise ValueError(
                "perception.fiducial_band_min_px must be 0 or in [16, 2048], got "
                f"{self.fiducial_band_min_px}"
            )
        if self.fiducial_band_margin_px < 0:
            raise ValueError(
                "perception.fiducial_band_margin_px must be >= 0, got "
                f"{self.fiducial_band_margin_px}"
            )
        for name in ("colour_min_area_px", "colour_min_width_px"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"perception.{name} must be >= 0, got {v}")
        if not all(16 <= w <= 2048 and w % 4 == 0 for w in self.colour_widths_px):
            raise ValueError(
                "perception.colour_widths_px must be multiples of 4 in [16, 2048], got "
                f"{self.colour_widths_px}"
            )
        if not (math.isfinite(self.colour_group_s) and self.colour_group_s >= 0):
            raise ValueError(f"perception.colour_group_s must be >= 0, got {self.colour_group_s}")
        if not 0 <= self.phase_full_images <= 2:
            raise ValueError(
                f"perception.phase_full_images must be 0, 1 or 2, got {self.phase_full_images}"
            )
        if not 1 <= self.max_requests_per_step <= 4:
            raise ValueError("perception.max_requests_per_step must be in [1, 4]")


@dataclass(frozen=True)
class OdomDetection:
    """A detection in ``odom`` for the node to send against one of its pose nodes."""

    detection_id: int
    kind: ObjectKind
    time_s: float
    position_in_odom: tuple[float, float]
    covariance: NDArray[np.float64]  # 2x2, m²
    radius_m: float
    height_m: float
    confidence: float
    velocity_in_odom: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class FiducialSighting:
    """A teammate seen in the image of ``time_s`` taken at ``pose_in_odom``."""

    sighting: TeammateSighting
    time_s: float
    pose_in_odom: tuple[float, float, float]


@dataclass
class PerceptionStats:
    sweeps: int = 0
    skipped_sweeps: int = 0  # sweeps the detector refused (counted, the node drives on)
    nonfinite_points: int = 0
    candidates: int = 0  # cylinder candidates by shape
    refined_without_image: int = 0
    no_frame: int = 0  # candidates that projected fully into no remembered frame
    images_requested: int = 0
    images_received: int = 0
    images_lost: int = 0  # never arrived within image_timeout_s
    images_unexpected: int = 0
    bad_images: int = 0
    colour_tests: int = 0
    colour_other: int = 0
    detections: int = 0  # Detection messages (first reports and refinements)
    objects: int = 0  # distinct static objects
    hostile_reports: int = 0
    fiducials: int = 0
    fiducial_dropped: int = 0
    fiducial_fine_images: int = 0  # fine images asked for a teammate's tag seen coarse
    fiducial_fine_skipped: int = 0  # coarse tags of teammates asked about lately (no image)
    fiducial_fine_rows: int = 0  # rows of the fine images asked (their heights summed)
    fiducial_periodic_images: int = 0  # periodic tag images asked
    fiducial_periodic_gated: int = 0  # periods that asked none: no segment in the view
    colour_jobs_grouped: int = 0  # cylinders asked in an image chosen for another
    teammate_tracks: int = 0  # person tracks an image showed to be a teammate (held)
    teammate_candidates: int = 0  # LIDAR candidates at a teammate just seen (no image)
    thumbnails: int = 0
    thumbnail_unknown: int = 0
    sweep_cpu_ms: deque[float] = field(default_factory=lambda: deque(maxlen=2000))
    colour_cpu_ms: deque[float] = field(default_factory=lambda: deque(maxlen=2000))
    person_colour_cpu_ms: deque[float] = field(default_factory=lambda: deque(maxlen=2000))


@dataclass
class _Job:
    kind: str  # "cylinder" or "person"
    xy_in_odom: tuple[float, float]
    radius_m: float
    height_m: float
    track_id: int = 0
    range_m: float = 0.0


@dataclass
class _Request:
    request_id: int
    time_s: float  # the frame asked for
    asked_s: float  # when
    jobs: list[_Job]
    fine: bool = False  # the fine image of a frame where a teammate's tag was seen


@dataclass
class _Thumb:
    crop: NDArray[np.uint8]
    bbox_in_crop: tuple[int, int, int, int]
    time_s: float
    pan_rad: float


def _track_velocity(track: PersonTrack, window_s: float) -> NDArray[np.float64]:
    """A track's velocity over ground (m/s, odom): the least-squares line through its
    measurements of the last ``window_s`` when they span at least half of it (a constant
    velocity fit over seconds is steadier than the filter's state after a few sweeps of a
    walker smeared across a 1.25 s sweep), else the filter's estimate."""
    h = np.array(track.history, dtype=np.float64).reshape(-1, 3)
    if len(h):
        h = h[h[:, 0] >= h[-1, 0] - window_s]
    if len(h) < 3 or h[-1, 0] - h[0, 0] < 0.5 * window_s:
        return track.velocity_m_s
    t = h[:, 0] - h[:, 0].mean()
    den = float(t @ t)
    return np.array(
        [float(t @ (h[:, 1] - h[:, 1].mean())) / den, float(t @ (h[:, 2] - h[:, 2].mean())) / den]
    )


def _jumped(track: PersonTrack, window_s: float, jump_m: float) -> bool:
    """Whether the track's newest measurement lies more than ``jump_m`` off the line fitted
    through its earlier measurements of the last ``window_s`` (at least three), or, after the
    track coasted longer than half that window, more than ``jump_m`` from where it was lost."""
    h = np.array(track.history, dtype=np.float64).reshape(-1, 3)
    if len(h) < 2:
        return False
    if h[-1, 0] - h[-2, 0] > 0.5 * window_s:
        return float(np.hypot(*(h[-1, 1:] - h[-2, 1:]))) > jump_m
    if len(h) < 4:
        return False
    last, h = h[-1], h[:-1]
    h = h[h[:, 0] >= last[0] - window_s]
    if len(h) < 3 or h[-1, 0] - h[0, 0] <= 0:
        return False
    t = h[:, 0] - h[:, 0].mean()
    den = float(t @ t)
    v = np.array([t @ (h[:, 1] - h[:, 1].mean()), t @ (h[:, 2] - h[:, 2].mean())]) / den
    pred = h[:, 1:].mean(axis=0) + v * (last[0] - h[:, 0].mean())
    return float(np.hypot(*(last[1:] - pred))) > jump_m


def _cpu_ms(t0: float) -> float:
    return (time.thread_time() - t0) * 1e3


class OnboardPerception:
    """One robot's perception (see the module docstring)."""

    def __init__(self, robot_id: int, config: PerceptionConfig | None = None) -> None:
        self.robot_id = robot_id
        self.config = cfg = config or PerceptionConfig()
        shape_path = Path(cfg.shape_thresholds) if cfg.shape_thresholds else SHAPE_THRESHOLDS_PATH
        colour_path = (
            Path(cfg.colour_thresholds) if cfg.colour_thresholds else COLOUR_THRESHOLDS_PATH
        )
        self.lidar = LidarDetector(cfg.lidar, thresholds=shape_path)  # ThresholdFileError
        self.colour: ColourThresholds = load_colour_thresholds(colour_path)  # ColourThresholdError
        self.memory = ImageMemory(cfg.memory)
        self.registry = ObjectRegistry(cfg.registry)
        self.stats = PerceptionStats()
        self._pan_samples: list[tuple[float, float]] = []
        self.pan_phase_s: float | None = None
        self._last_frame_s = -math.inf
        self._last_fiducial_ask_s = -math.inf
        self._last_coarse_frame_s = -math.inf  # the newest frame a coarse image was asked of
        # (sweep time_s, (K, 2) centres in odom) of the small segments of recent sweeps
        self._tag_subjects: deque[tuple[float, NDArray[np.float64]]] = deque()
        self._fine_asked_s: dict[int, float] = {}  # teammate -> when its pose was last asked
        # where teammates' heads were seen: (time_s, x, y) in odom, newest last
        self._teammates_seen: deque[tuple[float, float, float]] = deque(maxlen=256)
        self._next_request_id = 1
        self._queued: list[ImageRequest] = []
        self._emitted_at, self._emitted = -math.inf, 0  # requests sent at one mission time
        self._pending: dict[int, _Request] = {}
        # places whose colour said "other": (xy in odom, tests, last test time)
        self._waiting: list[tuple[_Job, float]] = []  # candidates waiting for a view, deadline
        self._negative: list[tuple[tuple[float, float], int, float]] = []
        self._person_tested: dict[int, tuple[int, float]] = {}
        self._teammate_tracks: dict[int, float] = {}  # track id -> when an image showed a mate
        self._track_ids: dict[int, int] = {}  # person track -> detection id
        self._person_votes: dict[int, dict[int, int]] = {}  # track -> kind -> colour tests
        self._civilians_seen: list[tuple[NDArray[np.float64], float]] = []
        self._reported_at: dict[int, float] = {}  # detection id of people -> last report
        self._had_hostiles = False
        self._hostile_until: dict[int, float] = {}  # track -> end of its hostile keep-out
        # hostile tracks the tracker dropped: (x, y, vx, vy, time_s, until_s), odom
        self._lost_hostiles: list[tuple[float, float, float, float, float, float]] = []
        self._hostile_last: dict[int, tuple[float, float, float, float, float]] = {}
        self._detections: list[OdomDetection] = []
        self._fiducials: list[FiducialSighting] = []
        self._thumbs: dict[int, _Thumb] = {}
        self._hazards_changed = False
        self._now = -math.inf
        self._bootstrap_asks = 0
        self._early: list[tuple[float, tuple[float, float, float]]] = []  # before the phase
        # (time_s, x, y, radius_m, range_m) of every cylinder candidate, newest last
        self._recent_cylinders: deque[tuple[float, float, float, float, float]] = deque(maxlen=512)

    # ------------------------------------------------------------------ outputs

    def take_requests(self) -> list[ImageRequest]:
        """Image requests to send now (at most ``max_requests_per_step``; the rest wait)."""
        if self._now != self._emitted_at:
            self._emitted_at, self._emitted = self._now, 0
        n = max(0, self.config.max_requests_per_step - self._emitted)  # per mission time
        out, self._queued = self._queued[:n], self._queued[n:]
        self._emitted += len(out)
        return out

    def take_detections(self) -> list[OdomDetection]:
        out, self._detections = self._detections, []
        return out

    def take_fiducials(self) -> list[FiducialSighting]:
        out, self._fiducials = self._fiducials, []
        return out

    def recent_cylinders(self, since_s: float) -> NDArray[np.float64]:
        """Cylinder candidates (shape only, no colour test) of the sweeps from ``since_s``
        on, as ``(K, 5)`` rows ``(time_s, x_m, y_m, radius_m, range_m)`` in ``odom`` at the
        odometry of their sweep, oldest first (kept ``recent_cylinders_s``)."""
        rows = [c for c in self._recent_cylinders if c[0] >= since_s]
        return np.array(rows, dtype=np.float64).reshape(-1, 5)

    def take_hazards_changed(self) -> bool:
        """Whether :meth:`own_hazards_in_odom` changed since the last call."""
        out, self._hazards_changed = self._hazards_changed, False
        return out

    def own_hazards_in_odom(self) -> list[tuple[ObjectKind, float, float]]:
        """This robot's own dangerous objects for its keep-out (paper 5.2: avoidance on the
        robot, without waiting for the GCS): static OOIs where fused, hostile tracks where
        they will be ``hostile_lookahead_s`` from now."""
        out: list[tuple[ObjectKind, float, float]] = []
        for o in self.registry.objects:
            if o.kind == ObjectKind.STATIC_OOI:
                out.append(
                    (
                        ObjectKind.STATIC_OOI,
                        float(o.position_in_odom[0]),
                        float(o.position_in_odom[1]),
                    )
                )
        la = self.config.hostile_lookahead_s
        for t in self.lidar.tracker.tracks:
            if self._hostile(t):
                p = t.position_m + la * _track_velocity(t, self.config.velocity_window_s)
                out.append((ObjectKind.HOSTILE, float(p[0]), float(p[1])))
        return out

    def movers_in_odom(self, now_s: float, memory_s: float) -> NDArray[np.float64]:
        """``(N, 2)``: what this robot saw move within ``memory_s`` of ``now_s``, in ``odom``:
        the teammates its camera placed by their tags and its confirmed person tracks
        (people, and teammates the LIDAR takes for people). The node's yield rule waits only
        for these (:mod:`robot.control.deadlock`)."""
        rows = [(x, y) for t, x, y in self._teammates_seen if now_s - t <= memory_s]
        rows += [
            (float(t.x[0]), float(t.x[1]))
            for t in self.lidar.tracker.tracks
            if t.confirmed and now_s - t.time_s <= memory_s
        ]
        return np.array(rows, dtype=np.float64).reshape(-1, 2)

    def hostile_tracks_in_odom(self, now_s: float) -> NDArray[np.float64]:
        """This robot's hostile tracks (labelled, or within ``hostile_memory_s`` of the
        label; coasting ones too) as ``(N, 4)`` rows ``(x_m, y_m, vx_m_s, vy_m_s)`` in
        ``odom``, moved on to ``now_s`` along the velocity fitted over their recent
        measurements (a track's own state is a sweep or more old, and the filter's velocity
        of a walker smeared across a sweep swings by 1 m/s from sweep to sweep)."""
        rows = []
        for t in self.lidar.tracker.tracks:
            if not self._hostile(t):
                continue
            v = _track_velocity(t, self.config.velocity_window_s)
            p = t.position_m + v * max(0.0, now_s - t.time_s)
            rows.append((float(p[0]), float(p[1]), float(v[0]), float(v[1])))
        return np.array(rows, dtype=np.float64).reshape(-1, 4)

    def _hostile(self, track: PersonTrack) -> bool:
        """Labelled hostile, or was within ``hostile_memory_s`` (for the keep-out only)."""
        return (
            track.kind == ObjectKind.HOSTILE
            or self._hostile_until.get(track.track_id, -math.inf) >= self._now
        )

    # ------------------------------------------------------------------ control period

    def on_control(self, now_s: float, pose_in_odom: NDArray[np.float64]) -> None:
        """Remember the camera's frame, bootstrap the pan phase, ask for teammate images,
        expire lost requests."""
        cfg = self.config
        self._now = max(self._now, now_s)
        pose = (float(pose_in_odom[0]), float(pose_in_odom[1]), float(pose_in_odom[2]))
        if self.pan_phase_s is None:
            # two images a few tenths of a second apart settle the schedule's phase
            if self._bootstrap_asks < 2 and now_s - self._last_fiducial_ask_s >= 0.4:
                probe = cfg.phase_probe_px > 0 and self._bootstrap_asks >= cfg.phase_full_images
                self._ask(now_s, [], probe=probe)
                self._last_fiducial_ask_s = now_s
                self._bootstrap_asks += 1
            elif self._bootstrap_asks >= 2 and not self._pending and not self._queued:
                self._bootstrap_asks = 0  # answers lost or ambiguous: ask again
            if now_s - self._last_frame_s >= cfg.frame_period_s - 1e-9:
                # the pan is a function of time: these become frames once the phase is known
                self._early.append((now_s, pose))
                self._last_frame_s = now_s
                cut = now_s - cfg.memory.history_s
                self._early = [e for e in self._early if e[0] >= cut]
        elif now_s - self._last_frame_s >= cfg.frame_period_s - 1e-9:
            pan = pan_at(now_s, cfg.memory.mount, self.pan_phase_s)
            frame = RememberedFrame(now_s, pan, cfg.memory.mount.tilt_rad, pose)
            if self.memory.record(frame):
                self._last_frame_s = now_s
                self._serve_waiting(frame)
        if (
            self.pan_phase_s is not None
            and cfg.fiducial_period_s > 0
            # any coarse image is searched for tags: one asked (for a candidate) of a frame
            # within the period covers the pan as well as an image of now would
            and now_s - max(self._last_fiducial_ask_s, self._last_coarse_frame_s)
            >= cfg.fiducial_period_s
        ):
            if self._tag_subject_in_view(now_s, pose):
                self._ask(now_s, [])
                self._last_fiducial_ask_s = now_s
                self.stats.fiducial_periodic_images += 1
            else:
                self._last_fiducial_ask_s = now_s  # this period's image is skipped
                self.stats.fiducial_periodic_gated += 1
        for rid in [r for r, q in self._pending.items() if now_s - q.asked_s > cfg.image_timeout_s]:
            del self._pending[rid]
            self.stats.images_lost += 1

    def _tag_subject_in_view(self, now_s: float, pose: tuple[float, float, float]) -> bool:
        """Whether the periodic tag image of ``now_s`` may show something: a people track
        it would colour-test, or a small segment of the recent sweeps within a tag's range
        (``PerceptionConfig.tag_gate_memory_s``); True when the gate is off."""
        cfg = self.config
        if cfg.tag_gate_memory_s <= 0:
            return True
        if self.pan_phase_s is None:
            return True
        mount = cfg.memory.mount
        pan = pan_at(now_s, mount, self.pan_phase_s)
        c, s = math.cos(pose[2]), math.sin(pose[2])
        bx, by = mount.camera_in_base_m[0], mount.camera_in_base_m[1]
        cam = np.array([pose[0] + c * bx - s * by, pose[1] + s * bx + c * by])
        heading = pose[2] + pan
        half_fov = math.radians(cfg.memory.hfov_deg) / 2
        # a people track the image would colour-test (as any image: _opportunistic_person_jobs)
        frame = RememberedFrame(now_s, pan, mount.tilt_rad, pose)
        for tr in self.lidar.tracker.tracks:
            if not tr.confirmed or tr.kind != 0:
                continue
            n, _ = self._person_tested.get(tr.track_id, (0, -math.inf))
            if n >= cfg.max_person_tests or abs(tr.time_s - now_s) > cfg.person_frame_window_s:
                continue
            p = tr.position_m - (tr.time_s - now_s) * tr.velocity_m_s
            whole = Candidate((float(p[0]), float(p[1])), cfg.person_radius_m, cfg.person_height_m)
            if self.memory.projects_fully(frame, whole) and not self._at_known_object(tr):
                return True
        for t, xy in self._tag_subjects:
            age = now_s - t
            if age > cfg.tag_gate_memory_s or len(xy) == 0:
                continue
            slack = cfg.tag_gate_radius_m + cfg.tag_gate_speed_m_s * max(0.0, age)
            d = xy - cam
            r = np.hypot(d[:, 0], d[:, 1])
            off = np.abs(
                (np.arctan2(d[:, 1], d[:, 0]) - heading + math.pi) % (2 * math.pi) - math.pi
            )
            seen = (r <= cfg.fiducial.max_range_m + slack) & (
                (r <= slack) | (off <= half_fov + np.arctan2(slack, r))
            )
            if bool(seen.any()):
                return True
        return False

    def _serve_waiting(self, frame: RememberedFrame) -> None:
        """Ask for ``frame`` if a candidate waiting for a view projects fully into it."""
        keep: list[tuple[_Job, float]] = []
        ready: list[_Job] = []
        for job, deadline in self._waiting:
            if frame.time_s > deadline or self.registry.nearest(
                job.xy_in_odom, self.config.refine_m
            ):
                continue  # too late, or found meanwhile
            cand = Candidate(job.xy_in_odom, job.radius_m, job.height_m)
            if self.memory.projects_fully(frame, cand):
                ready.append(job)
            else:
                keep.append((job, deadline))
        self._waiting = keep
        if ready:
            self._ask(frame.time_s, ready, pose=frame.pose_in_odom)

    def _ask(
        self,
        frame_time_s: float,
        jobs: list[_Job],
        *,
        fine: bool = False,
        probe: bool = False,
        fine_height_px: int | None = None,
        pose: tuple[float, float, float] | None = None,
    ) -> None:
        """Ask for the image of ``frame_time_s``: fine (a teammate's pose; ``fine_height_px``
        rows, default ``fiducial_height_px``), a phase probe (its pan angle only:
        ``phase_probe_px`` square) or coarse (the memory's size; for colour tests of ``jobs``
        seen from ``pose``, the frame's pose in ``odom``, as small as they allow:
        :meth:`_colour_size`)."""
        cfg = self.config
        if fine:
            w = cfg.fiducial_width_px
            h = cfg.fiducial_height_px if fine_height_px is None else fine_height_px
        elif probe:
            w = h = cfg.phase_probe_px
        elif jobs and pose is not None:
            w, h = self._colour_size(jobs, pose)
        else:
            w, h = cfg.memory.width_px, cfg.memory.height_px
        rid = self._next_request_id
        self._next_request_id += 1
        self._queued.append(ImageRequest(rid, float(frame_time_s), w, h))
        if not (fine or probe) and (w, h) == (cfg.memory.width_px, cfg.memory.height_px):
            # (a smaller colour-test image decodes only near tags: it does not stand in for
            # the periodic tag image)
            self._last_coarse_frame_s = max(self._last_coarse_frame_s, float(frame_time_s))
        self._pending[rid] = _Request(rid, frame_time_s, self._now, jobs, fine)
        self.stats.images_requested += 1

    # ------------------------------------------------------------------ sweeps

    def on_sweep(
        self,
        points_in_odom: NDArray[np.float64],
        pose_in_odom: NDArray[np.float64],
        time_s: float,
    ) -> None:
        """One de-skewed sweep (points in ``odom``; ``pose_in_odom``: the robot at ``time_s``,
        the sweep's middle). A sweep the detector refuses is counted, not raised."""
        cfg = self.config
        self.stats.sweeps += 1
        pts = np.asarray(points_in_odom, dtype=np.float64).reshape(-1, 3)
        finite = np.isfinite(pts).all(axis=1)
        if not finite.all():
            self.stats.nonfinite_points += int((~finite).sum())
            pts = pts[finite]
        pose = np.asarray(pose_in_odom, dtype=np.float64)
        if not (np.all(np.isfinite(pose)) and math.isfinite(time_s)):
            self.stats.skipped_sweeps += 1
            return
        c, s = math.cos(pose[2]), math.sin(pose[2])
        sensor = pose[:2] + [c * _LIDAR_IN_BASE_M[0], s * _LIDAR_IN_BASE_M[0]]
        t0 = time.thread_time()
        try:
            out = self.lidar.process(pts, sensor, time_s)
        except ValueError as err:
            self.stats.skipped_sweeps += 1
            log.warning("robot %d: perception skipped a sweep: %s", self.robot_id, err)
            return
        self.stats.sweep_cpu_ms.append(_cpu_ms(t0))
        if cfg.tag_gate_memory_s > 0:
            self._tag_subjects.append((time_s, np.array(out.segments_in_odom[:, :2])))
            while self._tag_subjects and (
                self._tag_subjects[0][0] < time_s - cfg.tag_gate_memory_s
            ):
                self._tag_subjects.popleft()
        while self._recent_cylinders and (
            self._recent_cylinders[0][0] < time_s - cfg.recent_cylinders_s
        ):
            self._recent_cylinders.popleft()
        jobs: list[tuple[RememberedFrame, _Job]] = []
        for cand in out.cylinders:
            xy = (float(cand.position_in_odom[0]), float(cand.position_in_odom[1]))
            rng = math.hypot(xy[0] - pose[0], xy[1] - pose[1])
            if rng > cfg.candidate_max_range_m:
                continue
            self.stats.candidates += 1
            self._recent_cylinders.append((time_s, xy[0], xy[1], float(cand.radius_m), rng))
            known = self.registry.nearest(xy, cfg.refine_m)
            if known is not None:
                self._fuse(int(known.kind), xy, cand.radius_m, cand.height_m, rng, time_s, 0.5)
                self.stats.refined_without_image += 1
                continue
            if not self._may_test(xy, time_s) or self._job_pending(xy):
                continue
            if self._at_teammate(xy, time_s):
                self.stats.teammate_candidates += 1
                continue
            job = _Job("cylinder", xy, float(cand.radius_m), float(max(cand.height_m, 0.3)), 0, rng)
            frame = self.memory.choose(Candidate(xy, job.radius_m, job.height_m))
            if frame is None:
                # no remembered frame shows it whole yet: the camera pans on; ask as soon as
                # one does (on_control), rather than wait for the LIDAR to find it again
                self.stats.no_frame += 1
                if not any(math.dist(w.xy_in_odom, xy) < cfg.refine_m for w, _ in self._waiting):
                    self._waiting.append((job, time_s + cfg.wait_for_frame_s))
                continue
            jobs.append((frame, job))
        for t in out.people:
            self._person_jobs(t, time_s, jobs)
        self._report_people(max(self._now, time_s))
        hostile_now = any(self._hostile(t) for t in self.lidar.tracker.tracks)
        if hostile_now or self._had_hostiles:
            self._hazards_changed = True  # hostiles move: their disks move with them
        self._had_hostiles = hostile_now
        for frame, fjobs in self._group_by_frame(jobs)[: cfg.max_requests_per_sweep]:
            self._ask(frame.time_s, fjobs, pose=frame.pose_in_odom)

    def _group_by_frame(
        self, jobs: list[tuple[RememberedFrame, _Job]]
    ) -> list[tuple[RememberedFrame, list[_Job]]]:
        """The frames to ask for ``jobs`` (each with the newest frame showing it whole),
        newest first, each with its jobs. People keep their frame (they are placed at it
        along their walk); a cylinder joins a frame already chosen that shows it whole and
        is at most ``colour_group_s`` older than its own, so that one image serves both
        (cylinders oldest first: a frame older than a cylinder's newest may show it too, a
        newer one does not)."""
        cfg = self.config
        by_frame: dict[float, tuple[RememberedFrame, list[_Job]]] = {}
        cylinders: list[tuple[RememberedFrame, _Job]] = []
        for frame, job in jobs:
            if job.kind == "cylinder":
                cylinders.append((frame, job))
            else:
                by_frame.setdefault(frame.time_s, (frame, []))[1].append(job)
        for frame, job in sorted(cylinders, key=lambda fj: fj[0].time_s):
            if frame.time_s not in by_frame and cfg.colour_group_s > 0:
                whole = Candidate(job.xy_in_odom, job.radius_m, job.height_m)
                for t in sorted(by_frame, reverse=True):
                    f, fjobs = by_frame[t]
                    if frame.time_s - cfg.colour_group_s <= t <= frame.time_s and (
                        self.memory.projects_fully(f, whole)
                    ):
                        fjobs.append(job)
                        self.stats.colour_jobs_grouped += 1
                        break
                else:
                    by_frame[frame.time_s] = (frame, [job])
                continue
            by_frame.setdefault(frame.time_s, (frame, []))[1].append(job)
        return [by_frame[t] for t in sorted(by_frame, reverse=True)]

    def _person_jobs(
        self, track: PersonTrack, time_s: float, jobs: list[tuple[RememberedFrame, _Job]]
    ) -> None:
        cfg = self.config
        if track.kind != 0 or self._at_known_object(track):
            return
        held = self._teammate_tracks.get(track.track_id)
        if held is not None:
            if time_s - held < cfg.teammate_track_hold_s:
                self.stats.teammate_candidates += 1
                return
            del self._teammate_tracks[track.track_id]
        n, last = self._person_tested.get(track.track_id, (0, -math.inf))
        if n >= cfg.max_person_tests or time_s - last < cfg.retest_after_s:
            return
        if any(j.track_id == track.track_id for q in self._pending.values() for j in q.jobs):
            return
        p_now = track.position_m
        if self._at_teammate((float(p_now[0]), float(p_now[1])), track.time_s):
            self.stats.teammate_candidates += 1
            return
        for frame in reversed(self.memory.frames):
            if time_s - frame.time_s > cfg.person_frame_window_s:
                break
            if frame.time_s > time_s + 1.0:
                continue
            p = track.position_m - (time_s - frame.time_s) * track.velocity_m_s
            xy = (float(p[0]), float(p[1]))
            job = _Job("person", xy, cfg.person_radius_m, cfg.person_height_m, track.track_id)
            if self.memory.projects_fully(frame, Candidate(xy, job.radius_m, job.height_m)):
                self._person_tested[track.track_id] = (n + 1, time_s)
                jobs.append((frame, job))
                return

    def _at_teammate(self, xy: tuple[float, float], time_s: float) -> bool:
        """Whether a teammate's head was seen near ``xy`` (odom) close to ``time_s``."""
        cfg = self.config
        if cfg.teammate_memory_s <= 0:
            return False
        for t, x, y in reversed(self._teammates_seen):
            dt = abs(time_s - t)
            if dt > cfg.teammate_memory_s:
                continue
            if (
                math.hypot(x - xy[0], y - xy[1])
                <= cfg.teammate_radius_m + cfg.teammate_speed_m_s * dt
            ):
                return True
        return False

    def _note_teammates(
        self,
        tags: list[TagDetection],
        image: CameraImage,
        intr: Intrinsics,
        pose: tuple[float, float, float],
    ) -> list[tuple[float, float, float]]:
        """Place the heads of the teammates whose tags ``image`` shows (odom, at the image's
        time; ``pose``: the robot then): along the ray through the tag's centre, at the depth
        its height in pixels gives (a head face is vertical: its height does not shrink as
        it turns away, its width does). Returns them ``(time_s, x, y)``."""
        cfg = self.config
        ipr = cfg.fiducial.layout.ids_per_robot
        size_m = cfg.fiducial.layout.tag_size_m
        m = None
        placed: list[tuple[float, float, float]] = []
        for tag in tags:
            if tag.tag_id // ipr == self.robot_id:
                continue
            c = np.asarray(tag.corners_px, dtype=np.float64).reshape(4, 2)
            h_px = 0.5 * (float(np.hypot(*(c[3] - c[0]))) + float(np.hypot(*(c[2] - c[1]))))
            if not h_px >= 2.0:
                continue
            if m is None:
                m = base_from_camera(
                    image.camera_pan_rad, image.camera_tilt_rad, cfg.memory.mount.camera_in_base_m
                )
            depth = intr.fy_px * size_m / h_px
            u, v = c.mean(axis=0)
            cam = np.array(
                [
                    (u - intr.cx_px) / intr.fx_px * depth,
                    (v - intr.cy_px) / intr.fy_px * depth,
                    depth,
                ]
            )
            bx, by = (m[:3, :3] @ cam + m[:3, 3])[:2]
            cth, sth = math.cos(pose[2]), math.sin(pose[2])
            placed.append(
                (
                    float(image.time_s),
                    pose[0] + cth * float(bx) - sth * float(by),
                    pose[1] + sth * float(bx) + cth * float(by),
                )
            )
        self._teammates_seen.extend(placed)
        return placed

    def _at_known_object(self, track: PersonTrack) -> bool:
        """A "person" standing where a static object is known is that object (a vat's
        segment can pass the person shape test): never coloured or reported as a person."""
        return self.registry.nearest(track.position_m, self.config.refine_m) is not None

    def _report_people(self, time_s: float) -> None:
        """Report labelled people tracks: hostiles every ``hostile_report_period_s``,
        civilians once. Tracks of one kind closer than ``person_merge_m`` are one person (a
        tracker may split one walker into two tracks): one detection id, the best-placed
        track's estimate; tracks placed worse than ``max_report_sigma_m`` wait. A labelled
        track whose newest measurement jumped off its own recent line (the tracker swapped
        people: a hostile's track caught a civilian) loses its label until coloured again."""
        cfg = self.config
        civilians = [
            (xy, ts) for xy, ts in self._civilians_seen if time_s - ts <= cfg.civilian_memory_s
        ]
        civilians += [
            (t.position_m, time_s)
            for t in self.lidar.tracker.tracks
            if t.kind == ObjectKind.CIVILIAN
        ]
        self._civilians_seen = civilians[-64:]
        live = {t.track_id for t in self.lidar.tracker.tracks}
        for k, until in self._hostile_until.items():
            final = self._hostile_last.get(k)
            if k not in live and until >= time_s and final is not None:
                x, y, vx, vy, seen_s = final
                self._lost_hostiles.append((x, y, vx, vy, seen_s, until))
        self._lost_hostiles = [
            g for g in self._lost_hostiles if min(g[5], g[4] + cfg.hostile_reid_s) >= time_s
        ][-16:]
        self._hostile_until = {
            k: v for k, v in self._hostile_until.items() if k in live and v >= time_s
        }
        self._hostile_last = {k: v for k, v in self._hostile_last.items() if k in live}
        for t in self.lidar.tracker.tracks:
            if t.kind != 0 or t.track_id in self._hostile_until or not t.confirmed:
                continue
            for i, (x, y, vx, vy, seen_s, until) in enumerate(self._lost_hostiles):
                age = max(0.0, t.time_s - seen_s)
                gate = cfg.hostile_reid_m + cfg.hostile_reid_m_s * age
                p = t.position_m
                if math.hypot(p[0] - x - vx * age, p[1] - y - vy * age) <= gate:
                    self._hostile_until[t.track_id] = until  # that hostile, for the keep-out
                    del self._lost_hostiles[i]
                    break
        for t in self.lidar.tracker.tracks:
            if t.kind == ObjectKind.HOSTILE:
                self._hostile_until[t.track_id] = time_s + cfg.hostile_memory_s
            if t.track_id in self._hostile_until:
                v = _track_velocity(t, cfg.velocity_window_s)
                p = t.position_m
                self._hostile_last[t.track_id] = (
                    float(p[0]),
                    float(p[1]),
                    float(v[0]),
                    float(v[1]),
                    float(t.time_s),
                )
            swapped = t.kind != 0 and _jumped(t, cfg.velocity_window_s, cfg.label_jump_m)
            # a hostile where a civilian stands: the labels conflict; look again
            conflict = t.kind == ObjectKind.HOSTILE and any(
                float(np.hypot(*(t.position_m - xy))) < cfg.person_merge_m for xy, _ in civilians
            )
            if swapped or conflict:
                t.kind = 0
                self._person_tested.pop(t.track_id, None)
                self._person_votes.pop(t.track_id, None)
                self._track_ids.pop(t.track_id, None)  # another person: another id
        tracks = [
            t
            for t in self.lidar.tracker.tracks
            if t.confirmed
            and t.missed == 0  # measured in the latest sweep: no stale or coasting reports
            and t.history
            and t.kind in (ObjectKind.HOSTILE, ObjectKind.CIVILIAN)
            and not self._at_known_object(t)
            and float(np.sqrt(np.linalg.eigvalsh(t.position_cov)[-1])) <= cfg.max_report_sigma_m
        ]
        tracks.sort(key=lambda t: float(np.trace(t.position_cov)))
        used: set[int] = set()
        for t in tracks:
            if t.track_id in used:
                continue
            cluster = [
                u
                for u in tracks
                if u.track_id not in used
                and u.kind == t.kind
                and float(np.hypot(*(u.position_m - t.position_m))) < cfg.person_merge_m
            ]
            used.update(u.track_id for u in cluster)
            did = next(
                (self._track_ids[u.track_id] for u in cluster if u.track_id in self._track_ids),
                None,
            )
            if did is None:
                did = self.registry.new_id()
            for u in cluster:
                self._track_ids[u.track_id] = did
            kind = ObjectKind(t.kind)
            last = self._reported_at.get(did)
            if last is not None and (
                kind == ObjectKind.CIVILIAN or time_s - last < cfg.hostile_report_period_s
            ):
                continue  # civilians once: nothing to avoid, nothing to dispatch
            self._reported_at[did] = time_s
            p, v = t.position_m, _track_velocity(t, cfg.velocity_window_s)
            self._detections.append(
                OdomDetection(
                    did,
                    kind,
                    float(t.history[-1][0]),
                    (float(p[0]), float(p[1])),
                    t.position_cov + np.eye(2) * cfg.registry.min_sigma_m**2,
                    cfg.person_radius_m,
                    cfg.person_height_m,
                    0.9,
                    (float(v[0]), float(v[1])),
                )
            )
            self.stats.detections += 1
            if kind == ObjectKind.HOSTILE:
                self.stats.hostile_reports += 1
                self._hazards_changed = True
        live = {t.track_id for t in self.lidar.tracker.tracks}
        self._track_ids = {k: v for k, v in self._track_ids.items() if k in live}
        self._person_votes = {k: v for k, v in self._person_votes.items() if k in live}

    def _negative_near(self, xy: tuple[float, float]) -> int | None:
        """Index of the place tested "other" within ``negative_radius_m`` of ``xy``."""
        r = self.config.negative_radius_m
        for i, (pxy, _, _) in enumerate(self._negative):
            if math.dist(pxy, xy) <= r:
                return i
        return None

    def _may_test(self, xy: tuple[float, float], time_s: float) -> bool:
        cfg = self.config
        i = self._negative_near(xy)
        if i is None:
            return True
        _, n, last = self._negative[i]
        return n < cfg.max_negative_tests and time_s - last >= cfg.retest_after_s

    def _job_pending(self, xy: tuple[float, float]) -> bool:
        for q in self._pending.values():
            for j in q.jobs:
                if j.kind == "cylinder" and math.dist(j.xy_in_odom, xy) < self.config.refine_m:
                    return True
        return False

    def _fuse(
        self,
        kind: int,
        xy: tuple[float, float],
        radius_m: float,
        height_m: float,
        range_m: float,
        time_s: float,
        confidence: float,
    ) -> int:
        cfg = self.config
        sigma = cfg.pos_sigma_m + cfg.pos_sigma_per_m * range_m
        n_before = len(self.registry)
        obj, due = self.registry.observe(
            kind, xy, np.eye(2) * sigma**2, radius_m=radius_m, height_m=height_m, time_s=time_s
        )
        if len(self.registry) != n_before:
            self.stats.objects += 1
        if due:
            self.registry.mark_reported(obj)
            self._detections.append(
                OdomDetection(
                    obj.detection_id,
                    ObjectKind(obj.kind),
                    time_s,
                    (float(obj.position_in_odom[0]), float(obj.position_in_odom[1])),
                    obj.covariance.copy(),
                    obj.radius_m,
                    obj.height_m,
                    confidence,
                )
            )
            self.stats.detections += 1
            if obj.kind == ObjectKind.STATIC_OOI:
                self._hazards_changed = True
        return obj.detection_id

    # ------------------------------------------------------------------ images

    def on_image(self, image: CameraImage, pose_at: Callable[[float], NDArray[np.float64]]) -> None:
        """An answered :class:`ImageRequest`: colour tests of its jobs and teammates' tags.
        ``pose_at(t)``: the robot's ``odom`` pose at time ``t`` (odometry)."""
        cfg = self.config
        req = self._pending.pop(image.request_id, None)
        if req is None:
            self.stats.images_unexpected += 1
            return
        self.stats.images_received += 1
        vals = (image.time_s, image.camera_pan_rad, image.camera_tilt_rad, image.fx_px, image.fy_px)
        rgb = np.asarray(image.rgb)
        if not all(math.isfinite(v) for v in vals) or rgb.ndim != 3 or rgb.shape[2] != 3:
            self.stats.bad_images += 1
            return
        if len(self._pan_samples) < 8:
            self._pan_samples.append((float(image.time_s), float(image.camera_pan_rad)))
            if len(self._pan_samples) >= 2:
                phase, rms = fit_pan_phase(self._pan_samples, cfg.memory.mount)
                if rms < 0.05 and self.pan_phase_s is None:
                    self.pan_phase_s = phase
                    mount = cfg.memory.mount
                    for t_early, pose_early in self._early:
                        pan = pan_at(t_early, mount, phase)
                        self.memory.record(
                            RememberedFrame(t_early, pan, mount.tilt_rad, pose_early)
                        )
                    self._early = []
                elif rms < 0.05:
                    self.pan_phase_s = phase
        h, w = rgb.shape[:2]
        intr = Intrinsics(image.fx_px, image.fy_px, image.cx_px, image.cy_px, w, h)
        pose = np.asarray(pose_at(float(image.time_s)), dtype=np.float64)
        pose_t = (float(pose[0]), float(pose[1]), float(pose[2]))
        cam = cfg.memory.mount.camera_in_base_m
        tags: list[TagDetection] = []
        heads: list[tuple[float, float, float]] = []
        if not req.fine:
            # a coarse image's tags first: a person job at a teammate's head is that teammate
            try:
                tags = detect_tags(rgb)
            except ValueError:
                tags = []
            heads = self._note_teammates(tags, image, intr, pose_t)
        for job in req.jobs + self._opportunistic_person_jobs(image, pose_t, req.jobs):
            if (
                job.kind == "person"
                and cfg.teammate_track_hold_s > 0
                and any(
                    math.hypot(hx - job.xy_in_odom[0], hy - job.xy_in_odom[1])
                    <= cfg.teammate_radius_m
                    for _, hx, hy in heads
                )
            ):
                if len(self._teammate_tracks) >= 256:  # tracks that ended are forgotten
                    cut = float(image.time_s) - cfg.teammate_track_hold_s
                    self._teammate_tracks = {
                        k: v for k, v in self._teammate_tracks.items() if v >= cut
                    }
                self._teammate_tracks[job.track_id] = float(image.time_s)
                self.stats.teammate_tracks += 1
                continue
            rel = relative(pose, np.array([job.xy_in_odom[0], job.xy_in_odom[1], 0.0]))
            t0 = time.thread_time()
            # a person moves during the sweep that placed it: try it a little to either side
            # across the line of sight, keep the strongest person colour
            shifts = cfg.person_shifts_m if job.kind == "person" else (0.0,)
            across = np.array([-rel[1], rel[0]]) / max(1e-6, float(np.hypot(rel[0], rel[1])))
            res = None
            try:
                for d in shifts:
                    r = classify_candidate(
                        rgb,
                        (float(rel[0] + d * across[0]), float(rel[1] + d * across[1])),
                        job.radius_m,
                        job.height_m,
                        image.camera_pan_rad,
                        image.camera_tilt_rad,
                        intr,
                        cam,
                        self.colour,
                    )
                    if r is not None and job.kind == "person" and r.label in _COLOUR_KIND:
                        if d == 0.0:  # the segment is an object of interest, not a person
                            self._person_tested[job.track_id] = (cfg.max_person_tests, 0.0)
                            res = None
                            break
                        continue
                    if r is None or (job.kind == "person" and r.label not in _PERSON_KIND):
                        continue
                    if d != 0.0 and r.fraction < cfg.person_shifted_min_fraction:
                        continue  # off the segment, only a clear person: not one behind it
                    if res is None or r.fraction > res.fraction:
                        res = r
                    if res.fraction >= 0.6:
                        break  # clear enough
            except ValueError as err:
                self.stats.bad_images += 1
                log.warning("robot %d: colour test skipped: %s", self.robot_id, err)
                continue
            if job.kind == "cylinder":
                self.stats.colour_cpu_ms.append(_cpu_ms(t0))
            else:
                self.stats.person_colour_cpu_ms.append(_cpu_ms(t0))
            self.stats.colour_tests += 1
            label = "other" if res is None else res.label
            if job.kind == "cylinder":
                kind = _COLOUR_KIND.get(label)
                if kind is None or res is None:
                    self.stats.colour_other += 1
                    i = self._negative_near(job.xy_in_odom)
                    if i is None:
                        self._negative.append((job.xy_in_odom, 1, self._now))
                        del self._negative[: -cfg.negative_places_kept]
                    else:
                        pxy, n, _ = self._negative[i]
                        self._negative[i] = (pxy, n + 1, self._now)
                    continue
                did = self._fuse(
                    int(kind),
                    job.xy_in_odom,
                    job.radius_m,
                    job.height_m,
                    job.range_m,
                    float(image.time_s),
                    float(res.fraction),
                )
                self._keep_thumb(did, rgb, res.bbox_px, float(image.time_s), image.camera_pan_rad)
            else:
                pkind = _PERSON_KIND.get(label)
                if pkind is None or res is None:
                    continue
                # a label needs agreeing tests in two images: one image can show a hostile
                # walking behind the trunk a track sits on
                votes = self._person_votes.setdefault(job.track_id, {})
                votes[int(pkind)] = votes.get(int(pkind), 0) + 1
                best = max(votes, key=lambda k: votes[k])
                others = sum(votes.values()) - votes[best]
                if votes[best] < cfg.person_votes_needed or others >= votes[best]:
                    continue
                try:
                    self.lidar.tracker.set_kind(job.track_id, best)
                except KeyError:
                    continue  # the track ended meanwhile
                self._report_people(self._now)
                tdid = self._track_ids.get(job.track_id)
                if tdid is not None:
                    self._keep_thumb(
                        tdid, rgb, res.bbox_px, float(image.time_s), image.camera_pan_rad
                    )
        if not req.fine:
            # a coarse image only says whether a teammate's tag is there; the pose comes from
            # a fine image of the same frame (the renderer's cost grows with the pixels)
            ipr = cfg.fiducial.layout.ids_per_robot
            mates = {t.tag_id // ipr for t in tags} - {self.robot_id}
            due = [
                m
                for m in mates
                if self._now - self._fine_asked_s.get(m, -math.inf) >= cfg.fiducial_refresh_s
            ]
            if due:
                # the fine image shows every teammate of this frame: all of them are asked
                for m in mates:
                    self._fine_asked_s[m] = self._now
                rows = self._fine_rows(tags, intr)
                self._ask(float(image.time_s), [], fine=True, fine_height_px=rows)
                self.stats.fiducial_fine_images += 1
                self.stats.fiducial_fine_rows += rows
            elif mates:
                self.stats.fiducial_fine_skipped += 1
            return
        try:
            sightings, dropped = estimate_teammates(
                rgb,
                intr,
                image.camera_pan_rad,
                image.camera_tilt_rad,
                own_robot_id=self.robot_id,
                config=cfg.fiducial,
            )
        except (ValueError, np.linalg.LinAlgError) as err:
            self.stats.bad_images += 1
            log.warning("robot %d: fiducial search skipped: %s", self.robot_id, err)
            return
        self.stats.fiducial_dropped += dropped
        cth, sth = math.cos(pose_t[2]), math.sin(pose_t[2])
        for s in sightings:
            self._fiducials.append(FiducialSighting(s, float(image.time_s), pose_t))
            self.stats.fiducials += 1
            bx, by = s.observed_in_base[0], s.observed_in_base[1]
            self._teammates_seen.append(
                (
                    float(image.time_s),
                    pose_t[0] + cth * bx - sth * by,
                    pose_t[1] + sth * bx + cth * by,
                )
            )

    def _colour_size(self, jobs: list[_Job], pose: tuple[float, float, float]) -> tuple[int, int]:
        """The image size for colour tests of ``jobs`` seen from ``pose`` (``odom``): the
        smallest of ``colour_widths_px`` (4:3) in which each candidate covers
        ``colour_min_area_px`` and spans ``colour_min_width_px`` at its distance from the
        robot, else the memory's size."""
        cfg = self.config
        mem_w, mem_h = cfg.memory.width_px, cfg.memory.height_px
        if cfg.colour_min_area_px <= 0:
            return mem_w, mem_h
        # at range d a cylinder (radius r, height h) spans at most fx 2 r / d by fx h / d
        # pixels; fx = w x per_w
        per_w = 1.0 / (2.0 * math.tan(math.radians(cfg.memory.hfov_deg) / 2))
        need = 0.0
        for job in jobs:
            d = math.hypot(job.xy_in_odom[0] - pose[0], job.xy_in_odom[1] - pose[1])
            across = 2.0 * max(job.radius_m, 1e-3)
            tall = max(job.height_m, 1e-3)
            fx = max(
                d * math.sqrt(cfg.colour_min_area_px / (across * tall)),
                d * cfg.colour_min_width_px / across,
            )
            need = max(need, fx / per_w)
        for w in sorted(cfg.colour_widths_px):
            if need <= w < mem_w:
                return w, w * 3 // 4
        return mem_w, mem_h

    def _fine_rows(self, tags: list[TagDetection], intr: Intrinsics) -> int:
        """The fine image's height for the teammates of a coarse image's ``tags`` (see
        ``PerceptionConfig.fiducial_band_min_px``): even, within the full fine height."""
        cfg = self.config
        full = cfg.fiducial_height_px
        if cfg.fiducial_band_min_px <= 0:
            return full
        scale = cfg.fiducial_width_px / intr.width_px  # fine pixels per coarse pixel
        try:
            dev = fit_rows_px(tags, intr, own_robot_id=self.robot_id, config=cfg.fiducial)
        except (ValueError, cv2.error):
            return full
        half = math.ceil(scale * dev) + cfg.fiducial_band_margin_px
        rows = max(cfg.fiducial_band_min_px, 2 * half)
        return int(min(full, rows + rows % 2))

    def _opportunistic_person_jobs(
        self, image: CameraImage, pose: tuple[float, float, float], jobs: list[_Job]
    ) -> list[_Job]:
        """Unlabelled people tracks that happen to project fully into ``image`` (asked for
        something else): their colour test costs no extra image."""
        cfg = self.config
        asked = {j.track_id for j in jobs if j.kind == "person"}
        frame = RememberedFrame(image.time_s, image.camera_pan_rad, image.camera_tilt_rad, pose)
        out: list[_Job] = []
        for t in self.lidar.tracker.tracks:
            if not t.confirmed or t.kind != 0 or t.track_id in asked:
                continue
            n, _ = self._person_tested.get(t.track_id, (0, -math.inf))
            if n >= cfg.max_person_tests or self._at_known_object(t):
                continue  # a trunk or post the tracker keeps: asked enough
            if abs(t.time_s - image.time_s) > cfg.person_frame_window_s:
                continue
            p = t.position_m - (t.time_s - image.time_s) * t.velocity_m_s
            job = _Job(
                "person",
                (float(p[0]), float(p[1])),
                cfg.person_radius_m,
                cfg.person_height_m,
                t.track_id,
            )
            if self.memory.projects_fully(
                frame, Candidate(job.xy_in_odom, job.radius_m, job.height_m)
            ):
                out.append(job)
                self._person_tested[t.track_id] = (n + 1, self._now)
        return out

    def _keep_thumb(
        self,
        detection_id: int,
        rgb: NDArray[np.uint8],
        bbox: tuple[int, int, int, int],
        time_s: float,
        pan_rad: float,
    ) -> None:
        """Keep a margin-grown crop (not the whole image) for a later thumbnail request."""
        h, w = rgb.shape[:2]
        u0, v0, u1, v1 = bbox
        mu, mv = (u1 - u0) // 2 + 2, (v1 - v0) // 2 + 2
        a0, b0 = max(0, u0 - mu), max(0, v0 - mv)
        a1, b1 = min(w, u1 + mu + 1), min(h, v1 + mv + 1)
        crop = np.ascontiguousarray(rgb[b0:b1, a0:a1])
        self._thumbs.pop(detection_id, None)
        self._thumbs[detection_id] = _Thumb(
            crop, (u0 - a0, v0 - b0, u1 - a0, v1 - b0), time_s, pan_rad
        )
        while len(self._thumbs) > self.config.thumbnails_kept:
            del self._thumbs[next(iter(self._thumbs))]

    def on_thumbnail_request(self, request: ThumbnailRequest) -> DetectionImage | None:
        """The thumbnail of detection ``request.detection_id`` (None, counted, if this robot
        has no image of it)."""
        th = self._thumbs.get(request.detection_id)
        if th is None:
            self.stats.thumbnail_unknown += 1
            return None
        max_bytes = request.max_bytes if request.max_bytes > 0 else self.config.thumbnail_max_bytes
        t = make_thumbnail(th.crop, th.bbox_in_crop, max_bytes=max_bytes)
        self.stats.thumbnails += 1
        return DetectionImage(
            request.request_id,
            request.detection_id,
            th.time_s,
            th.pan_rad,
            t.encoding,
            t.width,
            t.height,
            t.data,
        )
