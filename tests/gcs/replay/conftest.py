"""Shared fixtures for the log-replay tests: the real CARMEN logs in ``../shared/datasets``."""

from __future__ import annotations

from pathlib import Path

import pytest

LASER = Path(__file__).resolve().parents[3] / ".." / "shared" / "datasets" / "laser"


@pytest.fixture
def laser_dir() -> Path:
    """``../shared/datasets/laser`` beside the repository; skips when it is absent."""
    if not LASER.is_dir():
        pytest.skip(f"shared laser logs not found at {LASER.resolve()}")
    return LASER
