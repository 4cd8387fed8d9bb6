"""GTSAM keys of pose variables: the only place that encodes ``(robot_id, pose_index)``.

A key is the 64-bit integer ``robot_id << 32 | pose_index`` with ``0 <= robot_id < 2**24`` and
``0 <= pose_index < 2**32``. Robot 0's keys equal its pose indices, so a single-robot graph read
from a g2o file keeps the file's vertex ids as keys. The top byte stays zero, so keys never
collide with ``gtsam.Symbol`` keys that carry a character tag.
"""

from __future__ import annotations

__all__ = ["MAX_POSE_INDEX", "MAX_ROBOT_ID", "pose_index", "pose_key", "robot_of", "split_key"]

MAX_ROBOT_ID = (1 << 24) - 1
MAX_POSE_INDEX = (1 << 32) - 1


def pose_key(robot_id: int, index: int) -> int:
    """Key of pose ``index`` of robot ``robot_id``; raises ``ValueError`` when out of range."""
    if not 0 <= robot_id <= MAX_ROBOT_ID:
        raise ValueError(f"robot id {robot_id} out of range 0..{MAX_ROBOT_ID}")
    if not 0 <= index <= MAX_POSE_INDEX:
        raise ValueError(f"pose index {index} of robot {robot_id} out of range 0..{MAX_POSE_INDEX}")
    return (int(robot_id) << 32) | int(index)


def split_key(key: int) -> tuple[int, int]:
    """``(robot_id, pose_index)`` of a key made by :func:`pose_key`."""
    key = int(key)
    if not 0 <= key < (1 << 56):
        raise ValueError(f"key {key} is not a pose key")
    return key >> 32, key & MAX_POSE_INDEX


def robot_of(key: int) -> int:
    """Robot id of a pose key."""
    return split_key(key)[0]


def pose_index(key: int) -> int:
    """Pose index (within its robot) of a pose key."""
    return split_key(key)[1]
