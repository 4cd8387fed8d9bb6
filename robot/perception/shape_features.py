"""Shape features of segmented objects (paper 5.2.1, second step).

"First, the length and width of each object are calculated from the maximally aligned
bounding rectangle in the X-Y dimensions. Also, cylindrical objects presented a semi-circular
cross section to the LIDAR scanner and a robust estimate of the radius of each object was
derived from a RANSAC-based circle fit (Fischler and Bolles, 1981). The circumference of the
observed portion of this circle was also calculated." (paper 5.2.1)

Functions here are pure, over ``(n, 2)`` xy arrays in metres (frame: the sweep's, ``odom``):

* :func:`aligned_rectangle`: the smallest-area rectangle enclosing the points over rotations
  (the rectangle "maximally aligned" with the object), as ``(length_m, breadth_m, yaw_rad,
  centre)`` with ``length >= breadth``;
* :func:`ransac_circle`: circle through 3 points scored by inliers within ``inlier_tol_m``,
  refined by an algebraic least-squares fit (Kasa) on the inliers;
* :func:`arc_length`: the observed arc, ``radius * angular span`` of the points about the
  centre (span = ``2 pi`` minus the largest angular gap);
* :func:`batch_features`: the classifier's feature vectors (:data:`FEATURE_NAMES`) of every
  segment of a sweep in one compiled pass (numba; the per-segment numpy version cost about
  1 ms a segment, 30 ms a sweep); :func:`shape_features` is the same for one
  :class:`~robot.perception.segmentation.Segment`.

Beside the paper's four features the vector carries:

* ``top_m`` / ``bottom_m``: the object's highest / lowest point above the ground model
  (an OOI stands on the ground and is knee high; a car body starts 0.25 m up, a person or a
  trunk is taller);
* ``overhead_frac``: the fraction of the object's bearing span in which something returns
  *above* it and no farther than it (a tree's canopy over its trunk; nothing covers a
  free-standing cylinder);
* ``side_gap_m``: how far behind the object's near face the scene continues beside it, the
  larger of the two sides (a piece of wall, fence or car cut out of its neighbours by the
  height segmentation continues at the same range on both sides; a free-standing object has
  background or nothing on at least one side). Points counted are the sweep's object points
  within ``SIDE_MARGIN_RAD`` in bearing outside the object's span and within its height range;
  a side with none scores ``SIDE_GAP_CAP_M``.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np
from numpy.typing import NDArray

from robot.perception.segmentation import Segment

__all__ = [
    "FEATURE_NAMES",
    "SIDE_GAP_CAP_M",
    "SIDE_MARGIN_RAD",
    "aligned_rectangle",
    "arc_length",
    "batch_features",
    "object_position",
    "overhead_fraction",
    "ransac_circle",
    "shape_features",
]

#: The feature vector, in order (units: m except ``overhead_frac``, a fraction).
FEATURE_NAMES: tuple[str, ...] = (
    "length_m",
    "breadth_m",
    "radius_m",
    "arc_m",
    "top_m",
    "overhead_frac",
    "bottom_m",
    "side_gap_m",
)
N_FEATURES = len(FEATURE_NAMES)
SIDE_MARGIN_RAD = 0.08  # about three 1.5 deg beams beside the object
SIDE_GAP_CAP_M = 2.0
_OVERHEAD_MARGIN_RAD = 0.03
_OVERHEAD_CLEARANCE_M = 0.3
_RANSAC_TOL_M = 0.03
_RANSAC_MAX_RADIUS_M = 2.0
_RANSAC_ITERATIONS = 40
# fixed uniform draws for the RANSAC triples of large segments: deterministic fits
_DRAWS = np.random.default_rng(0).random((3 * _RANSAC_ITERATIONS, 3))


@nb.njit(cache=True, nogil=True)
def _rect_nb(x, y):  # type: ignore[no-untyped-def]
    """(length, breadth, yaw, cx, cy): min-area rectangle over yaws in 3 deg steps, refined
    at 0.5 deg about the best."""
    n = x.shape[0]
    mx = x.mean()
    my = y.mean()
    best_a = 0.0
    best_area = np.inf
    for stage in range(2):
        if stage == 0:
            n_ang, a0, step = 30, 0.0, math.radians(3.0)
        else:
            n_ang, a0, step = 13, best_a - math.radians(3.0), math.radians(0.5)
        for k in range(n_ang):
            a = a0 + k * step
            c, s = math.cos(a), math.sin(a)
            ulo, uhi, vlo, vhi = np.inf, -np.inf, np.inf, -np.inf
            for i in range(n):
                qx, qy = x[i] - mx, y[i] - my
                u = qx * c + qy * s
                v = -qx * s + qy * c
                ulo, uhi = min(ulo, u), max(uhi, u)
                vlo, vhi = min(vlo, v), max(vhi, v)
            area = (uhi - ulo) * (vhi - vlo)
            if area < best_area - 1e-15:
                best_area = area
                best_a = a
    c, s = math.cos(best_a), math.sin(best_a)
    ulo, uhi, vlo, vhi = np.inf, -np.inf, np.inf, -np.inf
    for i in range(n):
        qx, qy = x[i] - mx, y[i] - my
        u = qx * c + qy * s
        v = -qx * s + qy * c
        ulo, uhi = min(ulo, u), max(uhi, u)
        vlo, vhi = min(vlo, v), max(vhi, v)
    uc, vc = (uhi + ulo) / 2, (vhi + vlo) / 2
    cx = mx + c * uc - s * vc
    cy = my + s * uc + c * vc
    lu, lv = uhi - ulo, vhi - vlo
    if lu >= lv:
        return lu, lv, best_a, cx, cy
    return lv, lu, best_a + math.pi / 2, cx, cy


@nb.njit(cache=True, nogil=True)
def _circle3(ax, ay, bx, by, cx, cy):  # type: ignore[no-untyped-def]
    d = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    if abs(d) < 1e-12:
        return 0.0, 0.0, np.inf
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / d
    uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / d
    return ux, uy, math.hypot(ax - ux, ay - uy)


@nb.njit(cache=True, nogil=True)
def _kasa_nb(x, y, use):  # type: ignore[no-untyped-def]
    """Algebraic circle ``x^2 + y^2 + D x + E y + F = 0`` on points ``use`` (normal
    equations, centred for conditioning): (ok, cx, cy, r)."""
    m = 0
    mx = 0.0
    my = 0.0
    for i in range(x.shape[0]):
        if use[i]:
            m += 1
            mx += x[i]
            my += y[i]
    if m < 3:
        return False, 0.0, 0.0, 0.0
    mx /= m
    my /= m
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for i in range(x.shape[0]):
        if not use[i]:
            continue
        u, v = x[i] - mx, y[i] - my
        row = (u, v, 1.0)
        rhs = -(u * u + v * v)
        for j in range(3):
            b[j] += row[j] * rhs
            for k in range(3):
                a[j, k] += row[j] * row[k]
    det = np.linalg.det(a)
    if not abs(det) > 1e-12:
        return False, 0.0, 0.0, 0.0
    sol = np.linalg.solve(a, b)
    ucx, ucy = -sol[0] / 2, -sol[1] / 2
    r2 = ucx * ucx + ucy * ucy - sol[2]
    if not (r2 > 0 and math.isfinite(r2)):
        return False, 0.0, 0.0, 0.0
    return True, ucx + mx, ucy + my, math.sqrt(r2)


@nb.njit(cache=True, nogil=True)
def _ransac_nb(x, y, draws, tol, max_r, iterations):  # type: ignore[no-untyped-def]
    """(ok, cx, cy, r, inliers): most inliers (then smallest mean residual) over all triples
    (n <= 12) or ``iterations`` triples from ``draws``; refit on >= 4 inliers."""
    n = x.shape[0]
    inl = np.zeros(n, dtype=np.bool_)
    if n < 3:
        return False, 0.0, 0.0, 0.0, inl
    best_cnt = -1
    best_res = np.inf
    bcx, bcy, br = 0.0, 0.0, 0.0
    if n <= 12:
        n_hyp = n * (n - 1) * (n - 2) // 6
    else:
        n_hyp = draws.shape[0]
    tried = 0
    i, j, k = 0, 1, 2
    for h in range(n_hyp):
        if n <= 12:
            if h > 0:  # next triple in lexicographic order
                k += 1
                if k >= n:
                    j += 1
                    if j >= n - 1:
                        i += 1
                        j = i + 1
                    k = j + 1
        else:
            if tried >= iterations:
                break
            i = int(draws[h, 0] * n)
            j = int(draws[h, 1] * n)
            k = int(draws[h, 2] * n)
            if i == j or j == k or i == k:
                continue
            tried += 1
        cx, cy, r = _circle3(x[i], y[i], x[j], y[j], x[k], y[k])
        if not r <= max_r:
            continue
        cnt = 0
        res = 0.0
        for q in range(n):
            e = abs(math.hypot(x[q] - cx, y[q] - cy) - r)
            if e <= tol:
                cnt += 1
                res += e
        res /= max(cnt, 1)
        if cnt > best_cnt or (cnt == best_cnt and res < best_res):
            best_cnt, best_res, bcx, bcy, br = cnt, res, cx, cy, r
    if best_cnt < 0:
        return False, 0.0, 0.0, 0.0, inl
    for q in range(n):
        inl[q] = abs(math.hypot(x[q] - bcx, y[q] - bcy) - br) <= tol
    if best_cnt >= 4:
        ok, cx, cy, r = _kasa_nb(x, y, inl)
        if ok and r <= max_r:
            bcx, bcy, br = cx, cy, r
            for q in range(n):
                inl[q] = abs(math.hypot(x[q] - bcx, y[q] - bcy) - br) <= tol
    return True, bcx, bcy, br, inl


@nb.njit(cache=True, nogil=True)
def _arc_nb(x, y, use, cx, cy, r):  # type: ignore[no-untyped-def]
    m = 0
    for i in range(x.shape[0]):
        if use[i]:
            m += 1
    if m < 2:
        return 0.0
    ang = np.empty(m)
    j = 0
    for i in range(x.shape[0]):
        if use[i]:
            ang[j] = math.atan2(y[i] - cy, x[i] - cx)
            j += 1
    ang.sort()
    gap = ang[0] + 2 * math.pi - ang[m - 1]
    for i in range(1, m):
        gap = max(gap, ang[i] - ang[i - 1])
    return r * (2 * math.pi - gap)


@nb.njit(cache=True, nogil=True)
def _wrap(a):  # type: ignore[no-untyped-def]
    return (a + math.pi) % (2 * math.pi) - math.pi


@nb.njit(cache=True, nogil=True)
def _segment_row(xyz, h, s, e, above, obj_xyz, sensor_x, sensor_y, draws, out):  # type: ignore[no-untyped-def]
    n = e - s
    x = np.empty(n)
    y = np.empty(n)
    sb = 0.0
    cb = 0.0
    top_h, bot_h = -np.inf, np.inf
    zlo, zhi = np.inf, -np.inf
    for i in range(n):
        x[i] = xyz[s + i, 0]
        y[i] = xyz[s + i, 1]
        b = math.atan2(y[i] - sensor_y, x[i] - sensor_x)
        sb += math.sin(b)
        cb += math.cos(b)
        top_h = max(top_h, h[s + i])
        bot_h = min(bot_h, h[s + i])
        zlo = min(zlo, xyz[s + i, 2])
        zhi = max(zhi, xyz[s + i, 2])
    ref = math.atan2(sb, cb)
    blo, bhi, rnear, rfar = np.inf, -np.inf, np.inf, -np.inf
    for i in range(n):
        d = _wrap(math.atan2(y[i] - sensor_y, x[i] - sensor_x) - ref)
        blo, bhi = min(blo, d), max(bhi, d)
        rr = math.hypot(x[i] - sensor_x, y[i] - sensor_y)
        rnear, rfar = min(rnear, rr), max(rfar, rr)
    length, breadth, _, _, _ = _rect_nb(x, y)
    out[0] = length
    out[1] = breadth
    ok, cx, cy, r, inl = _ransac_nb(
        x, y, draws, _RANSAC_TOL_M, _RANSAC_MAX_RADIUS_M, _RANSAC_ITERATIONS
    )
    if ok:
        out[2] = r
        out[3] = _arc_nb(x, y, inl, cx, cy, r)
    else:
        out[2] = np.nan
        out[3] = np.nan
    out[4] = top_h
    # overhead: 1 deg bins over the span (with a margin), hit by returns above the top
    lo, hi = blo - _OVERHEAD_MARGIN_RAD, bhi + _OVERHEAD_MARGIN_RAD
    bins = max(1, int(math.ceil((hi - lo) / math.radians(1.0))))
    hit = np.zeros(bins, dtype=np.bool_)
    far = rfar + 0.1
    zcut = zhi + _OVERHEAD_CLEARANCE_M
    for q in range(above.shape[0]):
        if above[q, 2] <= zcut:
            continue
        dx, dy = above[q, 0] - sensor_x, above[q, 1] - sensor_y
        if math.hypot(dx, dy) > far:
            continue
        d = _wrap(math.atan2(dy, dx) - ref)
        if d < lo or d > hi:
            continue
        hit[min(int((d - lo) / (hi - lo) * bins), bins - 1)] = True
    out[5] = hit.sum() / bins
    out[6] = bot_h
    # side continuity: nearest range beside each edge of the span, within the height range
    left, right = SIDE_GAP_CAP_M, SIDE_GAP_CAP_M
    for q in range(obj_xyz.shape[0]):
        if s <= q < e:
            continue
        z = obj_xyz[q, 2]
        if z < zlo or z > zhi:
            continue
        dx, dy = obj_xyz[q, 0] - sensor_x, obj_xyz[q, 1] - sensor_y
        d = _wrap(math.atan2(dy, dx) - ref)
        if blo - SIDE_MARGIN_RAD <= d < blo:
            left = min(left, math.hypot(dx, dy) - rnear)
        elif bhi < d <= bhi + SIDE_MARGIN_RAD:
            right = min(right, math.hypot(dx, dy) - rnear)
    out[7] = max(left, right)


@nb.njit(cache=True, nogil=True)
def _batch_nb(xyz, h, starts, ends, measure, max_diag, above, sensor_x, sensor_y, draws):  # type: ignore[no-untyped-def]
    out = np.full((starts.shape[0], 8), np.nan)
    for k in range(starts.shape[0]):
        if not measure[k]:
            continue
        s, e = starts[k], ends[k]
        x0, x1, y0, y1 = np.inf, -np.inf, np.inf, -np.inf
        for i in range(s, e):
            x0, x1 = min(x0, xyz[i, 0]), max(x1, xyz[i, 0])
            y0, y1 = min(y0, xyz[i, 1]), max(y1, xyz[i, 1])
        if math.hypot(x1 - x0, y1 - y0) > max_diag:
            continue
        _segment_row(xyz, h, s, e, above, xyz, sensor_x, sensor_y, draws, out[k])
    return out


def batch_features(
    xyz: NDArray[np.float64],
    height_above_ground_m: NDArray[np.float64],
    starts: NDArray[np.int64],
    ends: NDArray[np.int64],
    above_xyz: NDArray[np.float64],
    sensor_xy: NDArray[np.float64],
    *,
    measure: NDArray[np.bool_] | None = None,
    max_diagonal_m: float = math.inf,
) -> NDArray[np.float64]:
    """Feature rows ``(S, F)`` (:data:`FEATURE_NAMES`) of the segments ``xyz[starts[k]:ends[k]]``
    of one sweep. ``xyz`` ``(N, 3)`` holds every object point of the sweep (segments and the
    small groups between them: the side test looks at all of them), ``height_above_ground_m``
    their heights, ``above_xyz`` every non-ground point (overhead test); all in one frame
    with ``sensor_xy``. Rows not in ``measure`` (default: all) and segments whose xy
    bounding box has a diagonal over ``max_diagonal_m`` (walls, cars: not measured, saves
    time) are NaN. Radius and arc are NaN
    when no circle fits. ``O(S * N)`` compiled."""
    p = np.ascontiguousarray(xyz, dtype=np.float64).reshape(-1, 3)
    hh = np.ascontiguousarray(height_above_ground_m, dtype=np.float64).reshape(-1)
    st = np.ascontiguousarray(starts, dtype=np.int64).reshape(-1)
    en = np.ascontiguousarray(ends, dtype=np.int64).reshape(-1)
    if len(hh) != len(p) or len(st) != len(en):
        raise ValueError("batch_features: xyz/heights or starts/ends lengths differ")
    if len(st) and (np.any(st < 0) or np.any(en > len(p)) or np.any(en - st < 1)):
        raise ValueError("batch_features: segment bounds outside the points or empty")
    m = np.ones(len(st), dtype=np.bool_) if measure is None else np.asarray(measure, bool)
    sensor = np.asarray(sensor_xy, dtype=np.float64).reshape(2)
    above = np.ascontiguousarray(above_xyz, dtype=np.float64).reshape(-1, 3)
    return _batch_nb(  # type: ignore[no-any-return]
        p, hh, st, en, m, float(max_diagonal_m), above, float(sensor[0]), float(sensor[1]), _DRAWS
    )  # type: ignore[no-any-return]


def aligned_rectangle(xy: NDArray[np.float64]) -> tuple[float, float, float, NDArray[np.float64]]:
    """``(length_m, breadth_m, yaw_rad, centre_xy)`` of the smallest-area enclosing rectangle,
    searched over yaws in 3 deg steps (enough for sub-centimetre accuracy at object sizes)
    and refined at 0.5 deg about the best. ``length >= breadth``; ``yaw`` is the direction of
    the length. Needs at least one point."""
    p = np.asarray(xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) == 0:
        raise ValueError(f"aligned_rectangle: expected (n >= 1, 2) points, got {p.shape}")
    length, breadth, yaw, cx, cy = _rect_nb(
        np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1])
    )
    return float(length), float(breadth), float(yaw), np.array([cx, cy])


def ransac_circle(
    xy: NDArray[np.float64],
    *,
    iterations: int = _RANSAC_ITERATIONS,
    inlier_tol_m: float = _RANSAC_TOL_M,
    max_radius_m: float = _RANSAC_MAX_RADIUS_M,
) -> tuple[NDArray[np.float64], float, NDArray[np.bool_]] | None:
    """RANSAC circle fit (Fischler and Bolles, 1981): ``(centre_xy, radius_m, inliers)``, or
    None when fewer than 3 points or no circle of radius ``<= max_radius_m`` fits 3 of them.

    Every triple is tried for up to 12 points, else ``iterations`` triples from a fixed table
    of draws (deterministic). The winner (most inliers, then smallest mean residual) is
    refined by a least-squares fit on its inliers when that fit stays within the radius cap."""
    p = np.asarray(xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise ValueError(f"ransac_circle: expected (n, 2) points, got {p.shape}")
    draws = (
        _DRAWS
        if iterations <= _RANSAC_ITERATIONS
        else np.random.default_rng(0).random((3 * iterations, 3))
    )
    ok, cx, cy, r, inl = _ransac_nb(
        np.ascontiguousarray(p[:, 0]),
        np.ascontiguousarray(p[:, 1]),
        draws,
        float(inlier_tol_m),
        float(max_radius_m),
        int(iterations),
    )
    if not ok:
        return None
    return np.array([cx, cy]), float(r), inl


def arc_length(xy: NDArray[np.float64], centre: NDArray[np.float64], radius_m: float) -> float:
    """Length of the observed arc: ``radius * (2 pi - largest angular gap)`` between the
    points seen from ``centre`` (0 for fewer than two points)."""
    p = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return float(
        _arc_nb(
            np.ascontiguousarray(p[:, 0]),
            np.ascontiguousarray(p[:, 1]),
            np.ones(len(p), dtype=np.bool_),
            float(centre[0]),
            float(centre[1]),
            float(radius_m),
        )
    )


def overhead_fraction(
    segment: Segment, above_xyz: NDArray[np.float64], sensor_xy: NDArray[np.float64]
) -> float:
    """Fraction of the object's bearing span (1 deg bins, with a small margin) in which a
    return lies more than 0.3 m *above* its top and no farther than its far side: a canopy
    over a trunk, a roof over a pillar. ``above_xyz``: the sweep's non-ground points."""
    return float(
        shape_features(segment, above_xyz, sensor_xy)[FEATURE_NAMES.index("overhead_frac")]
    )


def object_position(
    xy: NDArray[np.float64],
    sensor_xy: NDArray[np.float64],
    radius_m: float,
) -> NDArray[np.float64]:
    """Centre of an upright cylinder of ``radius_m`` whose near side the points are: the
    centroid pushed away from the sensor by the mean depth of a visible half-circle,
    ``(pi / 4) * radius`` (beams spread evenly across the object's width hit its facing half
    at lateral offsets uniform in ``[-r, r]``, whose mean depth in front of the axis is
    ``pi r / 4``)."""
    c = np.asarray(xy, dtype=np.float64).mean(axis=0)
    d = c - np.asarray(sensor_xy, dtype=np.float64)
    n = float(np.hypot(d[0], d[1]))
    if n < 1e-9:
        return c  # type: ignore[no-any-return]
    return c + d / n * (math.pi / 4) * radius_m  # type: ignore[no-any-return]


def shape_features(
    segment: Segment,
    above_xyz: NDArray[np.float64],
    sensor_xy: NDArray[np.float64],
    neighbours_xyz: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """The :data:`FEATURE_NAMES` vector of one segment; ``neighbours_xyz``: the sweep's other
    object points for the side test (default: none, so ``side_gap_m`` is the cap)."""
    own = np.asarray(segment.xyz, dtype=np.float64)
    others = np.zeros((0, 3)) if neighbours_xyz is None else np.asarray(neighbours_xyz, float)
    xyz = np.vstack([own, others.reshape(-1, 3)])
    h = np.r_[segment.height_above_ground_m, np.zeros(len(others.reshape(-1, 3)))]
    return batch_features(xyz, h, np.array([0]), np.array([len(own)]), above_xyz, sensor_xy)[0]
