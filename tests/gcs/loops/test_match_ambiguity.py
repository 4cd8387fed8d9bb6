"""A match that fixes its translation or heading too loosely is no closure (issue 19): each
sigma is held to half of what makes a closure false (0.5 m, 5 deg)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gcs.graph.pose_graph import PoseGraph
from gcs.loops.loop_closer import LoopCloser, LoopCloserConfig


def cov(sigma_xy_m: float, sigma_yaw_deg: float) -> np.ndarray:
    return np.diag([sigma_xy_m**2, (0.5 * sigma_xy_m) ** 2, math.radians(sigma_yaw_deg) ** 2])


def test_a_loose_heading_or_translation_is_ambiguous() -> None:
    closer = LoopCloser(PoseGraph())
    assert not closer._ambiguous(cov(0.1, 1.5))
    assert not closer._ambiguous(cov(0.24, 2.4))
    # Freiburg 079's nodes 247 and 241: 3.0 deg, the match 5.1 deg off
    assert closer._ambiguous(cov(0.1, 3.0))
    assert closer._ambiguous(cov(0.3, 1.0))  # a corridor's ridge
    loose = LoopCloser(PoseGraph(), LoopCloserConfig(max_match_sigma_yaw_rad=math.radians(5.0)))
    assert not loose._ambiguous(cov(0.1, 3.0))
    with pytest.raises(ValueError, match="max_match_sigma_yaw_rad"):
        LoopCloserConfig(max_match_sigma_yaw_rad=0.0)
