"""A room of boxes and an ideal laser in it, for the scan-odometry tests: wall segments from
axis-aligned boxes, and each beam's nearest wall as an endpoint in the robot's base frame."""

from __future__ import annotations

import numpy as np


def box_segments(boxes: list[tuple[float, float, float, float]]) -> np.ndarray:
    """``(4 * len(boxes), 4)`` wall segments ``(x0, y0, x1, y1)`` of boxes ``(x0, y0, x1, y1)``."""
    segs = []
    for x0, y0, x1, y1 in boxes:
        segs += [(x0, y0, x1, y0), (x1, y0, x1, y1), (x1, y1, x0, y1), (x0, y1, x0, y0)]
    return np.array(segs)


def scan_in_base(
    pose: np.ndarray, segs: np.ndarray, angles_rad: np.ndarray, max_range_m: float
) -> np.ndarray:
    """Endpoints in base of a laser at ``pose`` with beams at ``angles_rad`` (from the
    heading): each beam's nearest wall beyond 5 cm, beams with none within ``max_range_m``
    left out."""
    ang = np.asarray(angles_rad, dtype=np.float64)
    d = np.stack([np.cos(ang + pose[2]), np.sin(ang + pose[2])], axis=1)  # (B, 2)
    p = segs[:, :2]
    e = segs[:, 2:] - p  # (S, 2)
    w = p[None, :, :] - pose[None, None, :2]  # (1, S, 2)
    den = d[:, None, 0] * e[None, :, 1] - d[:, None, 1] * e[None, :, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (w[..., 0] * e[None, :, 1] - w[..., 1] * e[None, :, 0]) / den
        u = (w[..., 0] * d[:, None, 1] - w[..., 1] * d[:, None, 0]) / den
    ok = (np.abs(den) > 1e-12) & (t > 0.05) & (u >= 0) & (u <= 1)
    r = np.where(ok, t, np.inf).min(axis=1)
    keep = np.isfinite(r) & (r < max_range_m)
    return np.stack([r[keep] * np.cos(ang[keep]), r[keep] * np.sin(ang[keep])], axis=1)
