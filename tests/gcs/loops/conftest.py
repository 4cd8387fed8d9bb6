"""Shared fixtures for the loop-closing tests: the real laser logs in the shared datasets."""

from __future__ import annotations

from pathlib import Path

import pytest

from gcs.replay.carmen_log import CarmenLog, read_carmen_log

LASER = Path(__file__).resolve().parents[3] / ".." / "shared" / "datasets" / "laser"


@pytest.fixture(scope="session")
def intel_log() -> CarmenLog:
    """The corrected Intel Research Lab log; skips when the shared datasets are absent."""
    path = LASER / "intel-corrected.log.gz"
    if not path.is_file():
        pytest.skip(f"shared laser datasets not found at {LASER.resolve()}")
    return read_carmen_log(path)
