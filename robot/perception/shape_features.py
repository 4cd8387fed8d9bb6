"""Shape features of one segmented object (paper 5.2.1, second step).

"First, the length and width of each object are calculated from the maximally aligned
bounding rectangle in the X-Y dimensions. Also, cylindrical objects presented a semi-circular
cross section to the LIDAR scanner and a robust estimate of the radius of each object was
derived from a RANSAC-based circle fit (Fischler and Bolles, 1981). The circumference of the
observed portion of this circle was also calculated." (paper 5.2.1)

Functions here are pure, over ``(n, 2)`` xy arrays in metres:

* :func:`aligned_rectangle`: the smallest-area rectangle enclosing the points over rotations
  (the rectangle "maximally aligned" with the object), as ``(length_m, breadth_m, yaw_rad,
  centre)`` with ``length >= breadth``;
* :func:`ransac_circle`: circle through 3 random points scored by inliers within
  ``inlier_tol_m``, refined by an algebraic least-squares fit (Kasa) on the inliers;
* :func:`arc_length`: the observed arc, ``radius * angular span`` of the points about the
  centre (span = ``2 pi`` minus the largest angular gap);
* :func:`shape_features`: the classifier's feature vector of a
  :class:`~robot.perception.segmentation.Segment` (:data:`FEATURE_NAMES`).

Beside the paper's four features the vector carries the object's height above the ground
(``top_m``: trunks and people are taller than an OOI), and ``overhead_frac``: the fraction of
the sweep's rays over the object that return *above* it and *nearer* than it (a tree's canopy
hides the top of its trunk; nothing hides the top of a free-standing cylinder).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from robot.perception.segmentation import Segment

__all__ = [
    "FEATURE_NAMES",
    "aligned_rectangle",
    "arc_length",
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
)

_ANGLES = np.radians(np.arange(0.0, 90.0, 3.0))
_DIRS = np.stack([np.cos(_ANGLES), np.sin(_ANGLES)], axis=1)  # (A, 2)


def aligned_rectangle(xy: NDArray[np.float64]) -> tuple[float, float, float, NDArray[np.float64]]:
    """``(length_m, breadth_m, yaw_rad, centre_xy)`` of the smallest-area enclosing rectangle,
    searched over yaws in 3 deg steps (enough for sub-centimetre accuracy at object sizes)
    and refined at 0.5 deg about the best. ``length >= breadth``; ``yaw`` is the direction of
    the length. Needs at least one point."""
    p = np.asarray(xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2 or len(p) == 0:
        raise ValueError(f"aligned_rectangle: expected (n >= 1, 2) points, got {p.shape}")
    q = p - p.mean(axis=0)

    def extents(dirs: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        u = q @ dirs.T  # (n, A)
        v = q @ np.stack([-dirs[:, 1], dirs[:, 0]], axis=1).T
        return u.max(0) - u.min(0), v.max(0) - v.min(0)

    eu, ev = extents(_DIRS)
    best = float(_ANGLES[int(np.argmin(eu * ev))])
    fine = best + np.radians(np.arange(-3.0, 3.01, 0.5))
    dirs = np.stack([np.cos(fine), np.sin(fine)], axis=1)
    eu, ev = extents(dirs)
    k = int(np.argmin(eu * ev))
    a = float(fine[k])
    d = dirs[k]
    n = np.array([-d[1], d[0]])
    u, v = q @ d, q @ n
    centre = p.mean(axis=0) + d * (u.max() + u.min()) / 2 + n * (v.max() + v.min()) / 2
    lu, lv = float(eu[k]), float(ev[k])
    if lu >= lv:
        return lu, lv, a, centre
    return lv, lu, a + math.pi / 2, centre


def _circle_from_3(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Circumcentres and radii of triangles ``(T, 3, 2)``; degenerate ones get radius inf."""
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    d = 2 * (a[:, 0] * (b[:, 1] - c[:, 1]) + b[:, 0] * (c[:, 1] - a[:, 1]))
    d = d + 2 * c[:, 0] * (a[:, 1] - b[:, 1])
    a2, b2, c2 = (a**2).sum(1), (b**2).sum(1), (c**2).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (a2 * (b[:, 1] - c[:, 1]) + b2 * (c[:, 1] - a[:, 1]) + c2 * (a[:, 1] - b[:, 1])) / d
        uy = (a2 * (c[:, 0] - b[:, 0]) + b2 * (a[:, 0] - c[:, 0]) + c2 * (b[:, 0] - a[:, 0])) / d
    centre = np.stack([ux, uy], axis=1)
    r = np.linalg.norm(a - centre, axis=1)
    r[~np.isfinite(r)] = np.inf
    return centre, r


def _kasa(p: NDArray[np.float64]) -> tuple[NDArray[np.float64], float] | None:
    """Algebraic least-squares circle ``x^2 + y^2 + D x + E y + F = 0``; None if singular."""
    m = np.column_stack([p[:, 0], p[:, 1], np.ones(len(p))])
    rhs = -(p**2).sum(1)
    sol, _, rank, _ = np.linalg.lstsq(m, rhs, rcond=None)
    if rank < 3:
        return None
    cx, cy = -sol[0] / 2, -sol[1] / 2
    r2 = cx * cx + cy * cy - sol[2]
    if not (np.isfinite(r2) and r2 > 0):
        return None
    return np.array([cx, cy]), float(math.sqrt(r2))


def ransac_circle(
    xy: NDArray[np.float64],
    *,
    iterations: int = 40,
    inlier_tol_m: float = 0.03,
    max_radius_m: float = 2.0,
    seed: int = 0,
) -> tuple[NDArray[np.float64], float, NDArray[np.bool_]] | None:
    """RANSAC circle fit (Fischler and Bolles, 1981): ``(centre_xy, radius_m, inliers)``, or
    None when fewer than 3 points or no circle of radius ``<= max_radius_m`` fits 3 of them.

    Hypotheses are all drawn at once (vectorized) from a seeded generator, so the result is
    deterministic. The winning hypothesis (most inliers, then smallest mean residual) is
    refined by a least-squares fit on its inliers when that fit stays within the radius cap."""
    p = np.asarray(xy, dtype=np.float64)
    n = len(p)
    if n < 3:
        return None
    rng = np.random.default_rng(seed)
    if n <= 12:  # few points: try every triple
        idx = np.array(
            [(i, j, k) for i in range(n) for j in range(i + 1, n) for k in range(j + 1, n)]
        )
    else:
        idx = np.stack([rng.choice(n, 3, replace=False) for _ in range(iterations)])
    centres, radii = _circle_from_3(p[idx])
    ok = radii <= max_radius_m
    if not ok.any():
        return None
    centres, radii = centres[ok], radii[ok]
    resid = np.abs(np.linalg.norm(p[None, :, :] - centres[:, None, :], axis=2) - radii[:, None])
    inl = resid <= inlier_tol_m
    count = inl.sum(1)
    mean_res = np.where(inl, resid, 0).sum(1) / np.maximum(count, 1)
    best = int(np.lexsort((mean_res, -count))[0])
    inliers = inl[best]
    centre, radius = centres[best], float(radii[best])
    if inliers.sum() >= 4:
        refit = _kasa(p[inliers])
        if refit is not None and refit[1] <= max_radius_m:
            centre, radius = refit
            inliers = np.abs(np.linalg.norm(p - centre, axis=1) - radius) <= inlier_tol_m
    return centre, radius, inliers


def arc_length(xy: NDArray[np.float64], centre: NDArray[np.float64], radius_m: float) -> float:
    """Length of the observed arc: ``radius * (2 pi - largest angular gap)`` between the
    points seen from ``centre`` (0 for fewer than two points)."""
    p = np.asarray(xy, dtype=np.float64)
    if len(p) < 2:
        return 0.0
    ang = np.sort(np.arctan2(p[:, 1] - centre[1], p[:, 0] - centre[0]))
    gaps = np.diff(np.r_[ang, ang[0] + 2 * math.pi])
    return float(radius_m * (2 * math.pi - gaps.max()))


def overhead_fraction(
    segment: Segment,
    above_xyz: NDArray[np.float64],
    sensor_xy: NDArray[np.float64],
    *,
    margin_rad: float = 0.03,
    clearance_m: float = 0.3,
) -> float:
    """Fraction of the object's bearing span in which something lies *above* its top
    (by ``clearance_m``) and no farther than its far side: a canopy over a trunk, a roof
    over a pillar. Bins of 1 deg over the span; ``above_xyz`` are candidate occluders
    (the sweep's non-ground points)."""
    rel = segment.xyz[:, :2] - sensor_xy
    bearing = np.arctan2(rel[:, 1], rel[:, 0])
    ref = float(np.arctan2(np.sin(bearing).mean(), np.cos(bearing).mean()))
    b = np.angle(np.exp(1j * (bearing - ref)))
    lo, hi = float(b.min()) - margin_rad, float(b.max()) + margin_rad
    far = float(np.hypot(rel[:, 0], rel[:, 1]).max()) + 0.1
    if len(above_xyz) == 0:
        return 0.0
    top_z = float(segment.xyz[:, 2].max())
    q = above_xyz[above_xyz[:, 2] > top_z + clearance_m]
    if len(q) == 0:
        return 0.0
    qr = q[:, :2] - sensor_xy
    qb = np.angle(np.exp(1j * (np.arctan2(qr[:, 1], qr[:, 0]) - ref)))
    near = (qb >= lo) & (qb <= hi) & (np.hypot(qr[:, 0], qr[:, 1]) <= far)
    bins = max(1, int(math.ceil((hi - lo) / math.radians(1.0))))
    if not near.any():
        return 0.0
    hit = np.unique(np.minimum(((qb[near] - lo) / (hi - lo) * bins).astype(int), bins - 1))
    return float(len(hit) / bins)


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
) -> NDArray[np.float64]:
    """The :data:`FEATURE_NAMES` vector of one segment. Radius and arc are NaN when no circle
    fits (fewer than 3 points or all collinear), which no threshold accepts."""
    xy = segment.xyz[:, :2]
    length, breadth, _, _ = aligned_rectangle(xy)
    fit = ransac_circle(xy)
    if fit is None:
        radius, arc = math.nan, math.nan
    else:
        centre, radius, inl = fit
        arc = arc_length(xy[inl], centre, radius)
    over = overhead_fraction(segment, above_xyz, sensor_xy)
    return np.array([length, breadth, radius, arc, segment.top_m, over])
