from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from gcs.graph.keys import MAX_POSE_INDEX, MAX_ROBOT_ID, pose_key, robot_of, split_key


@given(st.integers(0, MAX_ROBOT_ID), st.integers(0, MAX_POSE_INDEX))
def test_round_trip(robot: int, index: int) -> None:
    key = pose_key(robot, index)
    assert split_key(key) == (robot, index)
    assert robot_of(key) == robot


def test_robot_zero_keys_are_indices() -> None:
    assert pose_key(0, 17) == 17


def test_out_of_range() -> None:
    with pytest.raises(ValueError, match="robot id"):
        pose_key(MAX_ROBOT_ID + 1, 0)
    with pytest.raises(ValueError, match="pose index"):
        pose_key(1, -1)
    with pytest.raises(ValueError, match="not a pose key"):
        split_key(1 << 60)
