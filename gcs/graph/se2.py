"""SE(2) helpers for the pose graph, in GTSAM's ``Pose2`` conventions.

Composition, inversion, ``between`` and angle wrapping are the project's shared vectorized
ones (:mod:`protocol.se2`, re-exported here); this module adds what the graph needs on top:
conversion to and from ``gtsam.Pose2``, the adjoint, and covariance propagation.

A pose is ``(x, y, theta)`` (metres, radians); ``a_from_b`` composes right to left. Tangent
vectors are ``(vx, vy, omega)`` and perturbations act on the right, ``x = x_bar * Exp(xi)``, as
in GTSAM, so covariances are expressed in the body frame of the pose they belong to.
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from protocol.se2 import compose, inverse, wrap_angle
from protocol.se2 import relative as between

__all__ = [
    "adjoint",
    "between",
    "compose",
    "inverse",
    "pose2",
    "pose_vec",
    "propagate_covariance",
    "weighted_mean",
    "wrap_angle",
]

FloatArray = NDArray[np.floating[Any]]


def pose2(p: FloatArray | tuple[float, float, float]) -> gtsam.Pose2:
    """``gtsam.Pose2`` from ``(x, y, theta)``."""
    return gtsam.Pose2(float(p[0]), float(p[1]), float(p[2]))


def pose_vec(p: gtsam.Pose2) -> FloatArray:
    """``(x, y, theta)`` of a ``gtsam.Pose2``."""
    return np.array([p.x(), p.y(), p.theta()])


def adjoint(a: FloatArray) -> FloatArray:
    """Adjoint matrix ``Ad_a`` (3x3) of one pose, GTSAM ``Pose2.AdjointMap`` convention."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([[c, -s, a[1]], [s, c, -a[0]], [0.0, 0.0, 1.0]])


def propagate_covariance(
    cov_a: FloatArray, step_a_from_b: FloatArray, cov_step: FloatArray
) -> FloatArray:
    """Covariance of ``x_b = x_a * step`` given independent ``cov_a`` (of ``x_a``) and ``cov_step``.

    With right perturbations, ``x_b = x_a Exp(da) step Exp(ds) = x_b Exp(Ad_{step^-1} da + ds)``.
    """
    ad = adjoint(inverse(step_a_from_b))
    return ad @ cov_a @ ad.T + cov_step


def weighted_mean(
    poses: FloatArray,
    infos: FloatArray,
    *,
    start: int = 0,
    iterations: int = 5,
    tol: float = 1e-12,
) -> gtsam.Pose2:
    """Information-weighted mean of poses ``(K, 3)`` on the manifold.

    Gauss-Newton on ``sum_k ||Log(mean^-1 pose_k)||^2_{infos_k}`` starting from ``poses[start]``;
    stops after ``iterations`` or once a step is below ``tol``.
    """
    info_sum = infos.sum(axis=0)
    mean = pose2(poses[start])
    ps = [pose2(p) for p in poses]
    for _ in range(iterations):
        rhs = np.zeros(3)
        for pk, ik in zip(ps, infos, strict=True):
            rhs += ik @ gtsam.Pose2.Logmap(mean.between(pk))
        step = np.linalg.solve(info_sum, rhs)
        mean = mean.compose(gtsam.Pose2.Expmap(step))
        if np.abs(step).max() < tol:
            break
    return mean
