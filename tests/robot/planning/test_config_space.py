"""Max-disc configuration space (paper 5.4) against brute force."""

from __future__ import annotations

import numpy as np
import pytest

from robot.planning.config_space import configuration_space, disc_kernel


@pytest.mark.parametrize(("seed", "radius_m"), [(0, 0.0), (1, 0.12), (2, 0.25), (3, 0.4)])
def test_matches_brute_force(seed: int, radius_m: float) -> None:
    rng = np.random.default_rng(seed)
    blocked = rng.random((23, 31)) < 0.03
    res = 0.05
    got = configuration_space(blocked, robot_radius_m=radius_m, resolution_m=res)
    obs = np.argwhere(blocked)
    want = np.zeros_like(blocked)
    for r in range(blocked.shape[0]):
        for c in range(blocked.shape[1]):
            d2 = ((obs - [r, c]) ** 2).sum(axis=1) * res * res
            want[r, c] = (d2 <= radius_m**2 + 1e-9).any()
    np.testing.assert_array_equal(got, want)


def test_kernel_is_a_disc() -> None:
    k = disc_kernel(2.0)
    assert k.shape == (5, 5)
    assert k[2, 0] == 1 and k[0, 0] == 0 and k.sum() == 13


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="blocked"):
        configuration_space(np.zeros((3, 3), np.uint8), robot_radius_m=0.1, resolution_m=0.1)
    with pytest.raises(ValueError, match="robot_radius_m"):
        configuration_space(np.zeros((3, 3), bool), robot_radius_m=np.nan, resolution_m=0.1)
