"""Shared fixtures for the pose-graph tests: the shared datasets folder."""

from __future__ import annotations

from pathlib import Path

import pytest

DATASETS = Path(__file__).resolve().parents[3] / ".." / "shared" / "datasets"
POSEGRAPH = DATASETS / "posegraph"


@pytest.fixture
def posegraph_dir() -> Path:
    """``../shared/datasets/posegraph`` beside the repository; skips when it is absent."""
    if not POSEGRAPH.is_dir():
        pytest.skip(f"shared pose-graph datasets not found at {POSEGRAPH.resolve()}")
    return POSEGRAPH
