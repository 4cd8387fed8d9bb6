"""Perturbations of a CARMEN log for the robustness bench (issue 19 items 3 and 6).

Pure functions over a :class:`~gcs.replay.carmen_log.CarmenLog` that return a new log with one
defect public logs are known to carry, so a replay can be scored on data it was never tuned on:

* :func:`scale_turns`: every odometry heading increment multiplied by ``factor`` (0.92 / 1.08: a
  gyro or wheel-base calibration error) and the odometry re-chained from the first pose, each
  translation increment kept in the robot frame. Only ``odometry_in_log`` changes; the laser and
  base poses (the reference in a corrected log) stay. For a corrected log, whose odometry
  repeats the reference, the replay's added noise then comes on top of the bias.
* :func:`freeze_clock`: every timestamp 0 (a logger without a clock).
* :func:`coarsen_clock`: timestamps quantized to ``step_s`` (1e4 s) around ``epoch_s``
  (1.13486e9): what ``%g`` printing of a Unix time gives (``1.13486e+09``).
* :func:`jump_clock`: ``jump_s`` (4.29e9 s, a 32-bit wrap) added to every stamp from one scan on.
* :func:`freeze_odometry`: an odometry gap: the wheel encoders drop out for a stretch of scans
  while the laser keeps coming. What a CARMEN log then shows: every laser record carries the
  last odometry pose the base reported, so the odometry is *frozen* (bitwise the same pose) over
  the stretch; when the encoders come back the increments resume from the frozen pose, and the
  motion driven meanwhile is simply missing from the odometry (the offset between ``odom`` and
  the world has jumped by it). A driver that restarts instead resets to a new origin; the
  frozen stretch in front of it is the same, and it is the one modelled here.
* :func:`drop_scans`: a stretch of scans removed, laser and odometry both (a *data* gap: a
  logger that stopped writing). No estimator can recover what nobody recorded: see
  :mod:`mission.bench.robustness` for why this one is reported apart.

Each function leaves its input untouched (the arrays are copied).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gcs.replay.carmen_log import CarmenLog
from protocol.se2 import compose, relative, wrap_angle

__all__ = [
    "COARSE_CLOCK_EPOCH_S",
    "COARSE_CLOCK_STEP_S",
    "CLOCK_JUMP_S",
    "coarsen_clock",
    "drop_scans",
    "freeze_clock",
    "freeze_odometry",
    "jump_clock",
    "scale_turns",
]

#: The coarse clock of the public logs: ``1.13486e+09`` changing every 1e4 s.
COARSE_CLOCK_EPOCH_S = 1.13486e9
COARSE_CLOCK_STEP_S = 1.0e4
#: A 32-bit wrap of a microsecond/second counter seen in public logs.
CLOCK_JUMP_S = 4.29e9


def scale_turns(log: CarmenLog, factor: float) -> CarmenLog:
    """``log`` with every odometry heading increment multiplied by ``factor``, re-chained.

    The increments ``relative(odom[i-1], odom[i])`` keep their translation (in the robot frame
    of scan ``i-1``) and get their yaw multiplied by ``factor``; the odometry is composed again
    from the first scan's pose, so the heading error grows with the total turning as a
    mis-calibrated gyro's does.
    """
    if not np.isfinite(factor) or factor <= 0.0:
        raise ValueError(f"scale_turns: factor must be positive and finite, got {factor!r}")
    odom = np.array(log.odometry_in_log, dtype=np.float64, copy=True)
    if len(odom) >= 2:
        inc = relative(odom[:-1], odom[1:])
        inc[:, 2] = wrap_angle(inc[:, 2]) * factor
        out = np.empty_like(odom)
        out[0] = odom[0]
        for i in range(1, len(odom)):
            out[i] = compose(out[i - 1], inc[i - 1])
        out[:, 2] = wrap_angle(out[:, 2])
        odom = out
    return dataclasses.replace(log, odometry_in_log=odom)


def _with_time(log: CarmenLog, time_s: np.ndarray) -> CarmenLog:
    return dataclasses.replace(log, time_s=np.asarray(time_s, dtype=np.float64))


def freeze_clock(log: CarmenLog, value_s: float = 0.0) -> CarmenLog:
    """``log`` with every timestamp ``value_s`` (0: a frozen clock)."""
    return _with_time(log, np.full(len(log), float(value_s)))


def coarsen_clock(
    log: CarmenLog,
    step_s: float = COARSE_CLOCK_STEP_S,
    epoch_s: float = COARSE_CLOCK_EPOCH_S,
) -> CarmenLog:
    """``log`` with its clock moved near ``epoch_s`` and quantized to ``step_s``.

    The stamps keep their spacing (relative to the first finite one) before quantization; the
    log is placed so that the middle of its span falls on a quantization boundary, so a log
    shorter than ``step_s`` still shows two distinct values (as ``%g`` stamps do when the clock
    rolls over), not one: a coarse clock, not a frozen one.
    """
    if not step_s > 0.0:
        raise ValueError(f"coarsen_clock: step_s must be positive, got {step_s!r}")
    t = np.asarray(log.time_s, dtype=np.float64)
    finite = np.isfinite(t)
    t0 = float(t[finite][0]) if finite.any() else 0.0
    rel = np.where(finite, t - t0, np.arange(len(t), dtype=np.float64) * 0.1)
    start = epoch_s + 0.5 * step_s - 0.5 * float(np.max(rel) - np.min(rel))
    return _with_time(log, np.round((start + rel) / step_s) * step_s)


def jump_clock(
    log: CarmenLog, from_scan: int | None = None, jump_s: float = CLOCK_JUMP_S
) -> CarmenLog:
    """``log`` with ``jump_s`` added to the stamps of scans ``from_scan..`` (default: middle)."""
    n = len(log)
    start = n // 2 if from_scan is None else int(from_scan)
    if not 0 <= start <= n:
        raise ValueError(f"jump_clock: from_scan {start} outside 0..{n}")
    t = np.array(log.time_s, dtype=np.float64, copy=True)
    t[start:] += jump_s
    return _with_time(log, t)


def freeze_odometry(log: CarmenLog, start: int, count: int) -> CarmenLog:
    """``log`` whose odometry is frozen over scans ``start .. start+count-1`` (an odometry gap).

    Those scans carry scan ``start - 1``'s odometry pose (the last one the base reported); from
    scan ``start + count`` on the odometry's own increments resume from that pose, so the motion
    of the ``count`` steps from ``start - 1`` to ``start + count - 1`` is lost (module
    docstring). The laser, the laser poses and the base poses (the reference) are untouched.
    """
    n = len(log)
    if not (1 <= start < n and count > 0):
        raise ValueError(
            f"freeze_odometry: start {start}, count {count} outside 1..{n - 1} (a pose before)"
        )
    odom = np.array(log.odometry_in_log, dtype=np.float64, copy=True)
    stop = min(n, start + count)
    frozen = odom[start - 1].copy()
    out = odom.copy()
    out[start:stop] = frozen
    if stop < n:
        # the increments after the dropout, chained from the frozen pose
        after = relative(odom[stop - 1], odom[stop:]).reshape(-1, 3)
        out[stop:] = compose(frozen, after)
        out[stop:, 2] = wrap_angle(out[stop:, 2])
    return dataclasses.replace(log, odometry_in_log=out)


def drop_scans(log: CarmenLog, start: int, count: int) -> CarmenLog:
    """``log`` without scans ``start .. start+count-1`` (a data gap: laser and odometry)."""
    n = len(log)
    if not (0 <= start < n and count > 0):
        raise ValueError(f"drop_scans: start {start}, count {count} outside a log of {n} scans")
    keep = np.r_[np.arange(0, start), np.arange(min(n, start + count), n)]
    if len(keep) == 0:
        raise ValueError("drop_scans: no scan would remain")
    return log.subset(keep.astype(np.int64))
