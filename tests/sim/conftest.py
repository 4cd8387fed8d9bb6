"""Make ``sim`` importable before the editable install is refreshed to include it."""

from __future__ import annotations

import sys
from pathlib import Path

_ROOT = str(Path(__file__).resolve().parents[2])
if _ROOT not in sys.path:  # ``sim`` may be newer than the editable install's package list
    sys.path.insert(0, _ROOT)
