"""Vectorized SE(2) against gtsam.Pose2 (the oracle), single and batched."""

from __future__ import annotations

import math

import gtsam
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from protocol.se2 import compose, inverse, relative, transform_points, wrap_angle

coords = st.floats(min_value=-1e3, max_value=1e3)
angles = st.floats(min_value=-20.0, max_value=20.0)  # beyond pi on purpose: must be wrapped
poses = st.tuples(coords, coords, angles).map(np.array)
points = st.tuples(coords, coords).map(np.array)
SETTINGS = settings(max_examples=60, deadline=None)


def g(p: np.ndarray) -> gtsam.Pose2:
    return gtsam.Pose2(float(p[0]), float(p[1]), float(p[2]))


def as_array(p: gtsam.Pose2) -> np.ndarray:
    return np.array([p.x(), p.y(), p.theta()])


def assert_poses_close(got: np.ndarray, want: np.ndarray) -> None:
    """Positions to 1e-9 relative (plus 1e-9 m); angles modulo 2 pi; angles in [-pi, pi)."""
    got, want = np.asarray(got), np.asarray(want)
    assert got.shape == want.shape and got.dtype == np.float64
    np.testing.assert_allclose(got[..., :2], want[..., :2], rtol=1e-9, atol=1e-9)
    dtheta = np.angle(np.exp(1j * (got[..., 2] - want[..., 2])))
    np.testing.assert_allclose(dtheta, 0.0, atol=1e-9)
    assert np.all((got[..., 2] >= -np.pi) & (got[..., 2] < np.pi))


@SETTINGS
@given(a=poses, b=poses)
def test_single_poses_match_gtsam(a: np.ndarray, b: np.ndarray) -> None:
    assert_poses_close(compose(a, b), as_array(g(a).compose(g(b))))
    assert_poses_close(inverse(a), as_array(g(a).inverse()))
    assert_poses_close(relative(a, b), as_array(g(a).between(g(b))))


@SETTINGS
@given(a=poses, p=points)
def test_transform_point_matches_gtsam(a: np.ndarray, p: np.ndarray) -> None:
    got = transform_points(a, p)
    assert got.shape == (2,)
    np.testing.assert_allclose(got, g(a).transformFrom(p), rtol=1e-9, atol=1e-9)


def _batch(rng: np.random.Generator, n: int) -> np.ndarray:
    return np.column_stack(
        [rng.uniform(-100, 100, n), rng.uniform(-100, 100, n), rng.uniform(-10, 10, n)]
    )


@pytest.mark.parametrize("n", [0, 1, 37])
def test_batches_match_gtsam(n: int) -> None:
    rng = np.random.default_rng(n)
    a, b = _batch(rng, n), _batch(rng, n)
    one = _batch(rng, 1)[0]
    expect_compose = [as_array(g(x).compose(g(y))) for x, y in zip(a, b, strict=True)]
    expect_left = [as_array(g(one).compose(g(y))) for y in b]
    expect_right = [as_array(g(x).compose(g(one))) for x in a]
    expect_inverse = [as_array(g(x).inverse()) for x in a]
    expect_between = [as_array(g(x).between(g(y))) for x, y in zip(a, b, strict=True)]
    expect_between_left = [as_array(g(one).between(g(y))) for y in b]

    def arr(rows: list[np.ndarray]) -> np.ndarray:
        return np.array(rows).reshape(n, 3)

    assert_poses_close(compose(a, b), arr(expect_compose))
    assert_poses_close(compose(one, b), arr(expect_left))
    assert_poses_close(compose(a, one), arr(expect_right))
    assert_poses_close(inverse(a), arr(expect_inverse))
    assert_poses_close(relative(a, b), arr(expect_between))
    assert_poses_close(relative(one, b), arr(expect_between_left))
    pts = rng.uniform(-50, 50, (n, 2))
    want = np.array([g(one).transformFrom(p) for p in pts]).reshape(n, 2)
    np.testing.assert_allclose(transform_points(one, pts), want, rtol=1e-9, atol=1e-9)


def test_batch_of_one_broadcasts() -> None:
    a = np.array([[1.0, 2.0, 0.3]])
    b = np.array([[0.5, -1.0, 0.2], [2.0, 0.0, -3.0]])
    assert compose(a, b).shape == (2, 3)
    assert_poses_close(compose(a, b)[1], as_array(g(a[0]).compose(g(b[1]))))


def test_known_values() -> None:
    # 90 degrees left then 1 m forward: end up at (0, 1) facing +y.
    np.testing.assert_allclose(
        compose([0, 0, math.pi / 2], [1, 0, 0]), [0, 1, math.pi / 2], atol=1e-15
    )
    np.testing.assert_allclose(inverse([1, 0, math.pi / 2]), [0, 1, -math.pi / 2], atol=1e-15)
    np.testing.assert_allclose(transform_points([1, 2, math.pi], [[1, 0]]), [[0, 2]], atol=1e-15)
    # Half-turns come out as -pi, never +pi.
    assert compose([0, 0, math.pi / 2], [0, 0, math.pi / 2])[2] == -math.pi
    assert inverse([0, 0, -math.pi])[2] == -math.pi


@SETTINGS
@given(a=poses)
def test_compose_with_inverse_is_identity(a: np.ndarray) -> None:
    ident = compose(a, inverse(a))
    np.testing.assert_allclose(ident[:2], 0.0, atol=1e-9)
    assert abs(ident[2]) < 1e-9
    assert_poses_close(relative(a, a), np.zeros(3))


@settings(max_examples=200, deadline=None)
@given(t=st.floats(min_value=-1e6, max_value=1e6))
def test_wrap_angle_range(t: float) -> None:
    w = float(wrap_angle(t))
    assert -math.pi <= w < math.pi
    assert abs(math.remainder(w - t, 2 * math.pi)) < 1e-9 * max(1.0, abs(t))


def test_wrap_angle_edges() -> None:
    below = np.nextafter(-np.pi, -np.inf)  # the modulo rounds to 2 pi here: must not give +pi
    edges = np.array([-np.pi, np.pi, below, np.nextafter(np.pi, np.inf), 3 * np.pi, -1e-300])
    w = wrap_angle(edges)
    assert np.all((w >= -np.pi) & (w < np.pi))
    assert w[0] == -np.pi and w[1] == -np.pi and w[5] == 0.0
    ks = np.arange(-41, 42) * np.pi
    many = np.concatenate([np.nextafter(ks, -np.inf), ks, np.nextafter(ks, np.inf)])
    wm = wrap_angle(many)
    assert np.all((wm >= -np.pi) & (wm < np.pi))
    assert isinstance(wrap_angle(1.0), np.floating | np.ndarray)
    assert wrap_angle(np.zeros((2, 2))).shape == (2, 2)


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda: compose([1.0, 2.0], [0, 0, 0]), "a_from_b"),
        (lambda: compose([0, 0, 0], [1.0, 2.0, 3.0, 4.0]), "b_from_c"),
        (lambda: compose(np.zeros((2, 2, 3)), [0, 0, 0]), "a_from_b"),
        (lambda: compose(np.zeros((2, 3)), np.zeros((5, 3))), "b_from_c"),
        (lambda: compose(0.0, [0, 0, 0]), "a_from_b"),
        (lambda: inverse(np.zeros((4, 2))), "a_from_b"),
        (lambda: relative(np.zeros(2), np.zeros(3)), "world_from_a"),
        (lambda: relative(np.zeros(3), np.zeros((3, 4))), "world_from_b"),
        (lambda: relative(np.zeros((3, 3)), np.zeros((4, 3))), "world_from_b"),
        (lambda: transform_points(np.zeros((2, 3)), np.zeros((2, 2))), "a_from_b"),
        (lambda: transform_points(np.zeros(3), np.zeros(3)), "points_in_b"),
        (lambda: transform_points(np.zeros(3), np.zeros((4, 3))), "points_in_b"),
        (lambda: transform_points(np.zeros(3), np.zeros((1, 4, 2))), "points_in_b"),
    ],
)
def test_bad_shapes_name_the_argument(call: object, name: str) -> None:
    with pytest.raises(ValueError, match=rf"^{name}: "):
        call()  # type: ignore[operator]
