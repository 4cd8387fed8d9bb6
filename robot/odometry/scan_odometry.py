"""Laser-aided odometry: each step's odometry increment refined by matching the new scan
against a small local map of the last few scans.

Paper 4.1: "Within each robot's private coordinate frame, the motion of the robot is
estimated through laser- and inertially-aided odometry." Wheel or gyro odometry misreads
turns by a scale (a gyro's scale error, a skid-steer's slip): every grid built from scans
placed by it is bent by ``(s - 1) W`` for ``W`` radians turned within it, and the chain
drifts by the same share of every turn. Consecutive laser scans overlap almost entirely,
so the new scan, matched against the last few scans placed by the refined poses, measures
the step directly, to a few centimetres and a fraction of a degree.

Contract (:func:`refine_odometry`): poses ``(N, 3)`` of the robot's ``odom`` chain and each
pose's scan endpoints in ``base`` in; the refined chain ``(N, 3)`` out, starting at the same
pose. Step ``k`` is searched around the odometry's prediction, within ``+- max_shift_m`` and
``+- (turn_share * |turn| + min_turn_window_rad)``: a correlative search (coarse, then fine
around the best) of the scan's points over a likelihood field of the local map's points
(``exp(-d^2 / 2 sigma^2)`` of the distance to the nearest map point). The response gives
the match's covariance (the response-weighted spread of the candidates, as Olson's
correlative matcher does); it is fused with the odometry step's covariance in information
form, so a corridor's unconstrained direction keeps the odometry's value while its heading
is measured. A weak match (too few points, a best mean response under ``min_response``)
keeps the odometry step as it is. The local map holds the last ``map_scans`` keyframes
(a scan is added when the robot moved ``keyframe_m`` or turned ``keyframe_rad`` since the
last one), so a robot standing still does not match its own noise against itself.

:class:`ScanOdometry` is the same one scan at a time, on board (the robot's sweeps as they
come), for the heading only: the match's heading and the odometry's (its covariance summed
since the last accepted match) are fused by their variances (a pose fusion let a loose
translation drag the heading further than the match itself said). It returns each sweep's
correction and the raw heading innovation and its variance, which
:meth:`robot.odometry.inertial_odometry.InertialOdometry.correct_heading` takes to correct the
heading and to estimate the gyro's bias while driving (paper 4.2's gyro
calibration, 4.3.1's zero-velocity updates, extended to motion). A correction whose heading
innovation is implausible against the two covariances (``gate_chi2``, 1 dof) is refused and
counted (``rejected``): a teammate or a hostile filling the view, a look-alike.

Pure numpy/numba/cv2; no ground truth. Cost: a distance transform of the local map's
bounding box (at ``field_resolution_m``) and ``O(P * C)`` lookups for ``P`` points (thinned
to ``max_points``) and ``C`` candidate poses per step.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import cv2
import msgspec
import numba as nb
import numpy as np
from numpy.typing import NDArray

__all__ = [
    "ScanCorrection",
    "ScanOdometry",
    "ScanOdometryConfig",
    "ScanOdometryStats",
    "match_step",
    "refine_odometry",
]

FloatArray = NDArray[np.float64]


class ScanOdometryConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """How the odometry steps are refined (module docstring).

    ``max_shift_m`` the translation window around the prediction; the heading window is
    ``turn_share * |odometry turn| + min_turn_window_rad``. ``coarse_step_m``/``coarse_step_rad``
    and ``fine_step_m``/``fine_step_rad`` the two searches' steps. ``sigma_m`` the likelihood
    field's width; ``field_resolution_m`` its cells. ``max_range_m`` the longest return used.
    ``min_points`` and ``min_response`` (the best mean field value of the scan's points) the
    weak-match test. ``odometry_sigma_m``/``odometry_sigma_m_per_m`` and
    ``odometry_sigma_rad``/``odometry_turn_share_sigma`` the odometry step's standard deviation
    for the fusion; ``response_temperature`` scales the response into a likelihood (points
    are not independent: a mean over them times this). A step longer than ``max_step_m`` or
    turning more than ``max_step_rad`` (lost scans in between) is not matched: it keeps the
    odometry and the local map starts again from its scan (what the window around the
    prediction holds is no longer the same place).
    """

    max_shift_m: float = 0.2
    turn_share: float = 0.10
    min_turn_window_rad: float = math.radians(2.0)
    coarse_step_m: float = 0.04
    coarse_step_rad: float = math.radians(0.5)
    fine_step_m: float = 0.01
    fine_step_rad: float = math.radians(0.1)
    sigma_m: float = 0.08
    field_resolution_m: float = 0.025
    max_range_m: float = 10.0
    max_points: int = 240
    min_points: int = 40
    min_response: float = 0.35
    map_scans: int = 6
    keyframe_m: float = 0.30
    keyframe_rad: float = math.radians(5.0)
    odometry_sigma_m: float = 0.01
    odometry_sigma_m_per_m: float = 0.02
    odometry_sigma_rad: float = math.radians(1.0)
    odometry_turn_share_sigma: float = 0.20
    response_temperature: float = 40.0
    max_step_m: float = 3.0
    max_step_rad: float = math.radians(120.0)
    gate_chi2: float = 10.83  # ScanOdometry: heading innovation, 1 dof, 0.999
    # ScanOdometry: the match's position along the heading (where wheel slip shows) corrects
    # the odometry when it differs by more than along_gate_sigma of its standard deviation
    # (at least along_sigma_floor_m); 0: the translation is not corrected (heading only)
    along_gate_sigma: float = 0.0
    along_sigma_floor_m: float = 0.04

    def __post_init__(self) -> None:
        positive = {
            "max_shift_m": self.max_shift_m,
            "coarse_step_m": self.coarse_step_m,
            "coarse_step_rad": self.coarse_step_rad,
            "fine_step_m": self.fine_step_m,
            "fine_step_rad": self.fine_step_rad,
            "sigma_m": self.sigma_m,
            "field_resolution_m": self.field_resolution_m,
            "max_range_m": self.max_range_m,
            "odometry_sigma_m": self.odometry_sigma_m,
            "odometry_sigma_rad": self.odometry_sigma_rad,
            "response_temperature": self.response_temperature,
            "max_step_m": self.max_step_m,
            "max_step_rad": self.max_step_rad,
            "gate_chi2": self.gate_chi2,
        }
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"scan_odometry.{name}: expected > 0, got {value}")
        nonneg = {
            "turn_share": self.turn_share,
            "min_turn_window_rad": self.min_turn_window_rad,
            "min_response": self.min_response,
            "keyframe_m": self.keyframe_m,
            "keyframe_rad": self.keyframe_rad,
            "odometry_sigma_m_per_m": self.odometry_sigma_m_per_m,
            "odometry_turn_share_sigma": self.odometry_turn_share_sigma,
            "along_gate_sigma": self.along_gate_sigma,
            "along_sigma_floor_m": self.along_sigma_floor_m,
        }
        for name, value in nonneg.items():
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"scan_odometry.{name}: expected >= 0, got {value}")
        if self.map_scans < 1 or self.max_points < 1 or self.min_points < 3:
            raise ValueError(
                "scan_odometry: map_scans >= 1, max_points >= 1, min_points >= 3 expected, got "
                f"{self.map_scans}, {self.max_points}, {self.min_points}"
            )
        if self.fine_step_m > self.coarse_step_m or self.fine_step_rad > self.coarse_step_rad:
            raise ValueError("scan_odometry: the fine steps must not exceed the coarse ones")


class ScanOdometryStats(msgspec.Struct, kw_only=True):
    """What :func:`refine_odometry` did: ``matched`` steps refined, ``weak`` steps that kept
    the odometry (weak or no match), ``mean_yaw_change_rad`` the mean |refined - odometry|
    heading change per matched step."""

    matched: int = 0
    weak: int = 0
    mean_yaw_change_rad: float = 0.0
    rejected: int = 0  # ScanOdometry: matches refused by the heading gate


def _compose(a: FloatArray, b: FloatArray) -> FloatArray:
    c, s = math.cos(a[2]), math.sin(a[2])
    yaw = math.atan2(math.sin(a[2] + b[2]), math.cos(a[2] + b[2]))
    return np.array([a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], yaw])


def _relative(a: FloatArray, b: FloatArray) -> FloatArray:
    """``b`` in ``a``'s frame."""
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    yaw = math.atan2(math.sin(b[2] - a[2]), math.cos(b[2] - a[2]))
    return np.array([c * dx + s * dy, -s * dx + c * dy, yaw])


def _in_frame_of(
    predicted: FloatArray, matched: FloatArray, cov_world: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """A match ``matched`` (covariance ``cov_world``) as a correction in the predicted pose's
    frame, where the odometry's covariance lives: ``(delta, covariance)``."""
    c, s = math.cos(predicted[2]), math.sin(predicted[2])
    rot = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return _relative(predicted, matched), np.asarray(rot @ cov_world @ rot.T, dtype=np.float64)


def _transform(pose: FloatArray, pts: FloatArray) -> FloatArray:
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(pts)
    out[:, 0] = pose[0] + c * pts[:, 0] - s * pts[:, 1]
    out[:, 1] = pose[1] + s * pts[:, 0] + c * pts[:, 1]
    return out


def _thin(pts: FloatArray, max_points: int, cell_m: float) -> FloatArray:
    """One point per ``cell_m`` cell, then every ``k``-th to at most ``max_points``: dense
    near returns would otherwise outvote the far ones that fix the heading."""
    if len(pts) == 0:
        return pts
    cells = np.floor(pts / cell_m).astype(np.int64)
    # each cell as one integer (row-major over the cells' bounding box): the first point of
    # each cell, as np.unique(cells, axis=0) finds it, at a fraction of its cost
    lo = cells.min(axis=0)
    span = cells[:, 1].max() - lo[1] + 1
    keys = (cells[:, 0] - lo[0]) * span + (cells[:, 1] - lo[1])
    _, first = np.unique(keys, return_index=True)
    pts = pts[np.sort(first)]
    if len(pts) > max_points:
        pts = pts[np.linspace(0, len(pts) - 1, max_points).astype(np.int64)]
    return pts


_FIELD_REACH_SIGMAS = 15.0  # exp(-0.5 * 15**2) = 1e-49: 0 in float32


@nb.njit(cache=True, nogil=True)
def _scores(field, x0, y0, res, pts, yaws, dxs, dys, px, py):  # type: ignore[no-untyped-def]
    """Mean bilinear field value of ``pts`` (base) at each pose ``(px + dx, py + dy, yaw)``."""
    h, w = field.shape
    n = pts.shape[0]
    out = np.zeros((yaws.shape[0], dys.shape[0], dxs.shape[0]))
    for a in range(yaws.shape[0]):
        c = math.cos(yaws[a])
        s = math.sin(yaws[a])
        for i in range(n):
            wx = px + c * pts[i, 0] - s * pts[i, 1]
            wy = py + s * pts[i, 0] + c * pts[i, 1]
            for b in range(dys.shape[0]):
                fy = (wy + dys[b] - y0) / res
                r = int(math.floor(fy))
                if r < 0 or r >= h - 1:
                    continue
                ty = fy - r
                for d in range(dxs.shape[0]):
                    fx = (wx + dxs[d] - x0) / res
                    q = int(math.floor(fx))
                    if q < 0 or q >= w - 1:
                        continue
                    tx = fx - q
                    v = (1.0 - ty) * ((1.0 - tx) * field[r, q] + tx * field[r, q + 1]) + ty * (
                        (1.0 - tx) * field[r + 1, q] + tx * field[r + 1, q + 1]
                    )
                    out[a, b, d] += v
    return out / max(n, 1)


def _field(
    map_pts: FloatArray, cfg: ScanOdometryConfig
) -> tuple[NDArray[np.float32], float, float]:
    """The local map's likelihood field and its lower-left corner ``(field, x0, y0)``."""
    res = cfg.field_resolution_m
    pad = cfg.max_shift_m + 4 * cfg.sigma_m
    x0 = float(map_pts[:, 0].min() - pad)
    y0 = float(map_pts[:, 1].min() - pad)
    w = int(math.ceil((map_pts[:, 0].max() + pad - x0) / res)) + 1
    h = int(math.ceil((map_pts[:, 1].max() + pad - y0) / res)) + 1
    occupied = np.full((h, w), 255, dtype=np.uint8)
    cols = ((map_pts[:, 0] - x0) / res).astype(np.int64)
    rows = ((map_pts[:, 1] - y0) / res).astype(np.int64)
    occupied[rows, cols] = 0
    dist = cv2.distanceTransform(occupied, cv2.DIST_L2, cv2.DIST_MASK_PRECISE) * res
    # float32 exp(-0.5 x^2) is exactly 0 beyond x = 14.4 (below the smallest subnormal):
    # only cells nearer than _FIELD_REACH_SIGMAS sigmas are worth an exp, the same values
    # (most of a 40 m field lies far from every return)
    field = np.zeros(dist.shape, dtype=np.float32)
    near = dist < _FIELD_REACH_SIGMAS * cfg.sigma_m
    field[near] = np.exp(-0.5 * (dist[near] / cfg.sigma_m) ** 2)
    return field, x0, y0


def _window(half: float, step: float) -> FloatArray:
    n = max(int(math.floor(half / step + 1e-9)), 0)
    return np.arange(-n, n + 1, dtype=np.float64) * step


def match_step(
    map_pts: FloatArray,
    scan_pts: FloatArray,
    predicted: FloatArray,
    odometry_turn_rad: float,
    cfg: ScanOdometryConfig,
) -> tuple[FloatArray, NDArray[np.float64]] | None:
    """The scan's pose in the map's frame and its covariance ``((3,), (3, 3))``, searched
    around ``predicted``; None for a weak match (module docstring). ``map_pts`` ``(M, 2)`` in
    the map frame, ``scan_pts`` ``(K, 2)`` in ``base`` (already thinned)."""
    if len(scan_pts) < cfg.min_points or len(map_pts) < cfg.min_points:
        return None
    field, x0, y0 = _field(map_pts, cfg)
    res = cfg.field_resolution_m
    half_yaw = cfg.turn_share * abs(odometry_turn_rad) + cfg.min_turn_window_rad
    yaws = predicted[2] + _window(half_yaw, cfg.coarse_step_rad)
    shifts = _window(cfg.max_shift_m, cfg.coarse_step_m)
    px, py = float(predicted[0]), float(predicted[1])
    coarse = _scores(field, x0, y0, res, scan_pts, yaws, shifts, shifts, px, py)
    a, b, d = np.unravel_index(int(np.argmax(coarse)), coarse.shape)
    # fine: the best coarse cell's neighbourhood
    fyaws = yaws[a] + _window(cfg.coarse_step_rad, cfg.fine_step_rad)
    fdy = shifts[b] + _window(cfg.coarse_step_m, cfg.fine_step_m)
    fdx = shifts[d] + _window(cfg.coarse_step_m, cfg.fine_step_m)
    fine = _scores(field, x0, y0, res, scan_pts, fyaws, fdx, fdy, px, py)
    best = float(fine.max())
    if best < cfg.min_response:
        return None
    fa, fb, fd = np.unravel_index(int(np.argmax(fine)), fine.shape)
    pose = np.array([px + fdx[fd], py + fdy[fb], fyaws[fa]])
    # Covariance from the coarse response (it spans the whole window, so a flat direction
    # shows): candidates weighted by exp(T * (score - best)), spread about the best pose.
    weights = np.exp(cfg.response_temperature * (coarse - coarse.max()))
    weights /= weights.sum()
    ya, yb, yd = np.meshgrid(
        yaws - pose[2], shifts + py - pose[1], shifts + px - pose[0], indexing="ij"
    )
    dev = np.stack([yd.ravel(), yb.ravel(), ya.ravel()])
    cov = (dev * weights.ravel()) @ dev.T
    floor = np.array([cfg.coarse_step_m, cfg.coarse_step_m, cfg.coarse_step_rad]) ** 2 / 12.0
    cov += np.diag(floor)
    return pose, cov


def _odometry_cov(step: FloatArray, cfg: ScanOdometryConfig) -> NDArray[np.float64]:
    """The odometry step's covariance in the predicted pose's frame."""
    dist = math.hypot(step[0], step[1])
    sd_xy = cfg.odometry_sigma_m + cfg.odometry_sigma_m_per_m * dist
    sd_yaw = cfg.odometry_sigma_rad + cfg.odometry_turn_share_sigma * abs(step[2])
    return np.diag([sd_xy**2, sd_xy**2, sd_yaw**2])


def refine_odometry(
    odometry: FloatArray,
    scans_in_base: Sequence[FloatArray],
    config: ScanOdometryConfig | None = None,
    stats: ScanOdometryStats | None = None,
) -> FloatArray:
    """The odometry chain ``(N, 3)`` with each step refined by its scan (module docstring).

    ``scans_in_base[k]`` the endpoints ``(K, 2)`` of the scan taken at ``odometry[k]``, in the
    robot's ``base`` frame. The result starts at ``odometry[0]``; a step whose match is weak
    is the odometry's step. ``stats`` (optional) is filled in.
    """
    cfg = config or ScanOdometryConfig()
    odom = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    if len(scans_in_base) != len(odom):
        raise ValueError(
            f"refine_odometry: {len(scans_in_base)} scans for {len(odom)} odometry poses"
        )
    out = odom.copy()
    if len(odom) == 0:
        return out
    st = stats if stats is not None else ScanOdometryStats()
    yaw_change = 0.0

    def prepared(k: int) -> FloatArray:
        pts = np.asarray(scans_in_base[k], dtype=np.float64).reshape(-1, 2)
        pts = pts[np.hypot(pts[:, 0], pts[:, 1]) < cfg.max_range_m]
        return _thin(pts, cfg.max_points, cfg.sigma_m)

    keyframes: deque[FloatArray] = deque(maxlen=cfg.map_scans)  # map points, odom frame
    current = prepared(0)
    keyframes.append(_transform(out[0], current))
    last_key = out[0].copy()
    for k in range(1, len(odom)):
        step = _relative(odom[k - 1], odom[k])
        predicted = _compose(out[k - 1], step)
        current = prepared(k)
        if math.hypot(step[0], step[1]) > cfg.max_step_m or abs(step[2]) > cfg.max_step_rad:
            out[k] = predicted
            st.weak += 1
            keyframes.clear()
            keyframes.append(_transform(out[k], current))
            last_key = out[k].copy()
            continue
        map_pts = np.concatenate(list(keyframes))
        found = match_step(map_pts, current, predicted, float(step[2]), cfg)
        if found is None:
            out[k] = predicted
            st.weak += 1
        else:
            pose, cov_world = found
            # Fuse in the predicted pose's frame (the odometry's covariance lives there).
            delta, cov_m = _in_frame_of(predicted, pose, cov_world)
            info_m = np.linalg.inv(cov_m)
            info_o = np.linalg.inv(_odometry_cov(step, cfg))
            fused = np.asarray(np.linalg.solve(info_m + info_o, info_m @ delta), dtype=np.float64)
            out[k] = _compose(predicted, fused)
            st.matched += 1
            yaw_change += abs(fused[2])
        moved = _relative(last_key, out[k])
        if math.hypot(moved[0], moved[1]) >= cfg.keyframe_m or abs(moved[2]) >= cfg.keyframe_rad:
            keyframes.append(_transform(out[k], current))
            last_key = out[k].copy()
    st.mean_yaw_change_rad = yaw_change / max(st.matched, 1)
    return out


class ScanCorrection(msgspec.Struct, frozen=True, kw_only=True):
    """One sweep's correction (:class:`ScanOdometry`): ``correction`` ``(dx, dy, dyaw)`` to
    compose onto the odometry pose the sweep was taken at (in that pose's ``base`` frame; the
    heading of the odometry and the match fused by their variances, the translation 0);
    ``innovation_yaw_rad`` the match's heading minus the odometry's, ``innovation_var_rad2`` the
    match's heading variance (for a bias estimate,
    independent of the odometry's prior); ``since_s`` the time since the previous matched
    sweep (the interval over which the odometry's heading drifted)."""

    correction: tuple[float, float, float]
    innovation_yaw_rad: float
    innovation_var_rad2: float
    since_s: float
    # with along_gate_sigma: the odometry's step since the previous sweep (m), and the
    # variance of the along-heading correction (correction[0], 0 within the gate)
    step_m: float = 0.0
    along_var_m2: float = 0.0


class ScanOdometry:
    """:func:`refine_odometry` one sweep at a time (module docstring): :meth:`observe` takes
    the odometry pose of a sweep and its points in ``base`` and returns the correction the
    scan measures against the local map of the last ``map_scans`` keyframes (placed at their
    corrected poses), or None (first sweep, weak match, a long gap, a refused heading).
    ``stats`` counts what it did. The caller applies the correction to its odometry; the next
    sweep's pose is expected to include it."""

    def __init__(self, config: ScanOdometryConfig | None = None) -> None:
        self.config = config or ScanOdometryConfig()
        self.stats = ScanOdometryStats()
        self._keyframes: deque[FloatArray] = deque(maxlen=self.config.map_scans)
        self._last_key: FloatArray | None = None
        self._last: FloatArray | None = None  # the previous sweep's (corrected) pose
        self._last_match_s: float | None = None
        self._yaw_change = 0.0
        # the odometry's covariance since the last accepted match (steps without one add up:
        # a heading that drifted through a featureless stretch is still let back)
        self._odo_cov = np.zeros((3, 3))

    def reset(self) -> None:
        """Forget the local map (e.g. the robot was moved)."""
        self._keyframes.clear()
        self._last_key = self._last = None
        self._last_match_s = None

    def observe(
        self, pose_in_odom: FloatArray, scan_in_base: FloatArray, time_s: float
    ) -> ScanCorrection | None:
        """The correction of ``pose_in_odom`` ``(3,)`` that the scan ``(K, 2)`` (points in
        ``base`` at that pose) measures, or None (class docstring). ValueError on a non-finite
        pose or time or a malformed scan."""
        cfg = self.config
        pose = np.asarray(pose_in_odom, dtype=np.float64).reshape(-1)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)) or not math.isfinite(time_s):
            raise ValueError(f"ScanOdometry.observe: bad pose {pose_in_odom} or time {time_s}")
        pts = np.asarray(scan_in_base, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2:
            raise ValueError(f"ScanOdometry.observe: scan must be (K, 2), got {pts.shape}")
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        pts = _thin(
            pts[np.hypot(pts[:, 0], pts[:, 1]) < cfg.max_range_m], cfg.max_points, cfg.sigma_m
        )
        last = self._last
        if last is None or not self._keyframes:
            self._start(pose, pts, time_s)
            return None
        step = _relative(last, pose)
        if math.hypot(step[0], step[1]) > cfg.max_step_m or abs(step[2]) > cfg.max_step_rad:
            self.stats.weak += 1
            self._start(pose, pts, time_s)
            return None
        found = match_step(np.concatenate(list(self._keyframes)), pts, pose, float(step[2]), cfg)
        result: ScanCorrection | None = None
        corrected = pose
        if found is None:
            self.stats.weak += 1
            self._odo_cov += _odometry_cov(step, cfg)
        else:
            matched, cov_world = found
            delta, cov_m = _in_frame_of(pose, matched, cov_world)
            cov_o = self._odo_cov + _odometry_cov(step, cfg)
            innovation_var = float(cov_m[2, 2] + cov_o[2, 2])
            if delta[2] ** 2 > cfg.gate_chi2 * innovation_var:
                self.stats.rejected += 1
                self._odo_cov = cov_o
            else:
                self._odo_cov = np.zeros((3, 3))
                # the heading alone, by its marginal variances: a pose fusion let a loose
                # translation drag the heading past the match's own (small world, seed 7: a
                # 1.1 deg innovation became a 2.7 deg correction); the robot's wheels and the
                # GCS's matches take care of the translation
                gain = cov_o[2, 2] / (cov_o[2, 2] + cov_m[2, 2])
                # along the heading: wheel slip the odometry cannot see (sand), taken whole
                # when beyond the match's noise (the match measures it; the odometry's own
                # error there is no noise to average but a bias)
                along_var = float(cov_m[0, 0]) + cfg.along_sigma_floor_m**2
                along = float(delta[0])
                if not (
                    cfg.along_gate_sigma > 0 and along**2 > cfg.along_gate_sigma**2 * along_var
                ):
                    along = 0.0
                fused = np.array([along, 0.0, gain * float(delta[2])])
                corrected = _compose(pose, fused)
                since = time_s - self._last_match_s if self._last_match_s is not None else math.nan
                result = ScanCorrection(
                    correction=(float(fused[0]), float(fused[1]), float(fused[2])),
                    innovation_yaw_rad=float(delta[2]),
                    innovation_var_rad2=float(cov_m[2, 2]),
                    since_s=float(since),
                    step_m=float(math.hypot(step[0], step[1])),
                    along_var_m2=along_var,
                )
                self._last_match_s = time_s
                self.stats.matched += 1
                self._yaw_change += abs(float(fused[2]))
                self.stats.mean_yaw_change_rad = self._yaw_change / self.stats.matched
        self._last = corrected
        assert self._last_key is not None
        moved = _relative(self._last_key, corrected)
        if math.hypot(moved[0], moved[1]) >= cfg.keyframe_m or abs(moved[2]) >= cfg.keyframe_rad:
            self._keyframes.append(_transform(corrected, pts))
            self._last_key = corrected.copy()
        return result

    def shift(self, dx_m: float, dy_m: float) -> None:
        """The odometry's position was moved by ``(dx_m, dy_m)`` in ``odom`` (a slip taken
        out, :meth:`robot.odometry.inertial_odometry.InertialOdometry.shift_position`): the
        local map and the last poses move with it, so the next match sees no jump."""
        if not (math.isfinite(dx_m) and math.isfinite(dy_m)):
            raise ValueError(f"ScanOdometry.shift: ({dx_m}, {dy_m}) not finite")
        d = np.array([dx_m, dy_m])
        self._keyframes = deque((k + d for k in self._keyframes), maxlen=self._keyframes.maxlen)
        for name in ("_last", "_last_key"):
            pose = getattr(self, name)
            if pose is not None:
                moved = np.array(pose, dtype=np.float64, copy=True)
                moved[:2] += d
                setattr(self, name, moved)

    def _start(self, pose: FloatArray, pts: FloatArray, time_s: float) -> None:
        self._keyframes.clear()
        self._keyframes.append(_transform(pose, pts))
        self._last_key = pose.copy()
        self._last = pose.copy()
        self._last_match_s = time_s
        self._odo_cov = np.zeros((3, 3))
