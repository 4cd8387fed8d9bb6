"""Reader for CARMEN 2D laser logs (text, optionally gzip-compressed).

Real logs replace the simulator to test loop closing on data with known answers (issue 7
item 7; the MAGIC paper evaluates on its own logs, section 7). Two laser record formats are
understood; every other record (``ODOM``, ``PARAM`` except the laser offset, ``SYNC``,
``NEFF``, ``TRUEPOS``, ``RLASER``, ...) is skipped and counted by type:

* ``FLASER n r_1..r_n x y theta odom_x odom_y odom_theta ipc_timestamp host logger_timestamp``:
  the front laser's pose ``(x, y, theta)`` (the corrected pose in a "corrected" log) and the
  robot's odometry pose at the scan.
* The old Duke DP-SLAM format: ``Odometry x y theta`` lines, each followed by
  ``Laser n r_1..r_n``; no timestamps.

Beam angles of ``FLASER``/``Laser`` are not stored; they follow CARMEN's guess from the beam
count (``carmen_laser_guess_fov``): 180 or 181 beams one degree apart, 360 or 361 half a degree
apart, centred on the heading (180 beams span -89.5..+89.5 deg, 181 span -90..+90); any other
count spreads the beams evenly over 180 deg. A range within ``no_return_tolerance_m`` of the
SICK's error codes (8.183..8.191 m in the 8 m mode, 81.83..81.91 m in the 80 m mode: "no
return", dazzled, ...) or at least ``max_range_m`` is no return.

Frames: the log's world frame is called ``log``; ``laser_in_log`` is the laser's pose,
``odometry_in_log`` the robot's raw odometry (the robot base), and ``base_in_log`` the robot base
derived from the laser pose and the laser's forward offset (``PARAM robot_frontlaser_offset``,
0 when absent). Points of a scan are returned in the robot ``base`` frame.
"""

from __future__ import annotations

import gzip
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from protocol.se2 import compose

__all__ = [
    "NO_RETURN_BANDS_M",
    "CarmenLog",
    "CarmenLogError",
    "beam_angles_rad",
    "parse_carmen_log",
    "read_carmen_log",
]

FloatArray = NDArray[np.float64]

#: Bands of ranges that SICK scanners use as error codes ("no return", dazzled, ...) in the 8 m
#: and 80 m modes: 8183..8191 in mm or cm units.
NO_RETURN_BANDS_M: tuple[tuple[float, float], ...] = ((8.183, 8.191), (81.83, 81.91))


class CarmenLogError(ValueError):
    """A log could not be read; the message names the file, the line and what is wrong."""


def beam_angles_rad(n_beams: int) -> FloatArray:
    """Bearings of ``n_beams`` beams in the laser frame (CARMEN's guess, module docstring)."""
    if n_beams < 2:
        raise ValueError(f"a scan needs at least 2 beams, got {n_beams}")
    if n_beams in (180, 181):
        step = math.pi / 180.0
    elif n_beams in (360, 361):
        step = math.pi / 360.0
    else:
        step = math.pi / (n_beams - 1)
    return (np.arange(n_beams, dtype=np.float64) - (n_beams - 1) / 2.0) * step  # type: ignore[no-any-return]


@dataclass(frozen=True)
class CarmenLog:
    """The laser scans of one log, in file order (``N`` scans of ``B`` beams).

    ``ranges_m`` ``(N, B)``; ``angles_rad`` ``(B,)`` bearings in the laser frame;
    ``laser_in_log``, ``odometry_in_log``, ``base_in_log`` ``(N, 3)`` poses (module docstring);
    ``time_s`` ``(N,)`` the logger timestamps (NaN throughout when the log has none);
    ``laser_offset_m`` the laser's forward offset on the robot; ``line_numbers`` ``(N,)`` the
    1-based line of each scan; ``skipped`` counts the records that were not scans, by type.
    """

    path: str
    ranges_m: FloatArray
    angles_rad: FloatArray
    laser_in_log: FloatArray
    odometry_in_log: FloatArray
    base_in_log: FloatArray
    time_s: FloatArray
    laser_offset_m: float
    line_numbers: NDArray[np.int64]
    skipped: dict[str, int] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.ranges_m.shape[0])

    def subset(self, scans: slice | NDArray[np.int64] | list[int]) -> CarmenLog:
        """The log restricted to some scans (a slice or indices), e.g. its first minutes."""
        idx = np.arange(len(self))[scans]
        return CarmenLog(
            path=self.path,
            ranges_m=self.ranges_m[idx],
            angles_rad=self.angles_rad,
            laser_in_log=self.laser_in_log[idx],
            odometry_in_log=self.odometry_in_log[idx],
            base_in_log=self.base_in_log[idx],
            time_s=self.time_s[idx],
            laser_offset_m=self.laser_offset_m,
            line_numbers=self.line_numbers[idx],
            skipped=dict(self.skipped),
        )

    @property
    def has_timestamps(self) -> bool:
        return bool(len(self) > 0 and np.all(np.isfinite(self.time_s)))

    def valid_mask(
        self, *, max_range_m: float = 80.0, no_return_tolerance_m: float = 0.002
    ) -> NDArray[np.bool_]:
        """``(N, B)``: beams with a return (positive, finite, below ``max_range_m`` and outside
        the no-return bands)."""
        return _returns(self.ranges_m, max_range_m, no_return_tolerance_m)

    def points_in_base(
        self, scan: int, *, max_range_m: float = 80.0, no_return_tolerance_m: float = 0.002
    ) -> FloatArray:
        """Endpoints ``(K, 2)`` of scan ``scan``'s returns in the robot ``base`` frame (m)."""
        if not 0 <= scan < len(self):
            raise IndexError(f"{self.path}: scan {scan} out of range 0..{len(self) - 1}")
        r = self.ranges_m[scan]
        ok = _returns(r, max_range_m, no_return_tolerance_m)
        a = self.angles_rad[ok]
        return np.stack([self.laser_offset_m + r[ok] * np.cos(a), r[ok] * np.sin(a)], axis=1)


def _returns(r: FloatArray, max_range_m: float, tolerance_m: float) -> NDArray[np.bool_]:
    ok = np.isfinite(r) & (r > 0.0) & (r < max_range_m)
    for lo, hi in NO_RETURN_BANDS_M:
        ok &= (r < lo - tolerance_m) | (r > hi + tolerance_m)
    return ok  # type: ignore[no-any-return]


def _floats(tokens: list[str], where: str, what: str) -> list[float]:
    try:
        values = [float(t) for t in tokens]
    except ValueError as exc:
        raise CarmenLogError(f"{where}: {what}: {exc}") from None
    if not all(math.isfinite(v) for v in values):
        raise CarmenLogError(f"{where}: {what}: non-finite value")
    return values


def _count(tok: str, where: str, what: str) -> int:
    try:
        n = int(tok)
    except ValueError:
        raise CarmenLogError(f"{where}: {what}: expected an integer, got {tok!r}") from None
    if not 2 <= n <= 10000:
        raise CarmenLogError(f"{where}: {what}: {n} is not a plausible beam count")
    return n


def parse_carmen_log(text: str, *, path: str = "<string>") -> CarmenLog:
    """Parse the text of a CARMEN log (see the module docstring for the formats).

    Raises :class:`CarmenLogError` naming ``path:line`` for a malformed scan or odometry line,
    a beam count that changes within the log, or a log without any scan.
    """
    ranges: list[list[float]] = []
    laser: list[list[float]] = []
    odom: list[list[float]] = []
    times: list[float] = []
    lines: list[int] = []
    angles: FloatArray | None = None
    offset_m = 0.0
    skipped: Counter[str] = Counter()
    last_odometry: list[float] | None = None  # DP-SLAM format: the pose the next Laser uses

    def add_scan(
        r: list[float],
        a: FloatArray,
        lp: list[float],
        op: list[float],
        t: float,
        line: int,
        where: str,
    ) -> None:
        nonlocal angles
        if angles is None:
            angles = a
        elif len(a) != len(angles) or not np.allclose(a, angles, atol=1e-9):
            raise CarmenLogError(
                f"{where}: scan has {len(a)} beams with other angles than the first scan's "
                f"{len(angles)}; one laser per log is supported"
            )
        ranges.append(r)
        laser.append(lp)
        odom.append(op)
        times.append(t)
        lines.append(line)

    for lineno, raw in enumerate(text.splitlines(), start=1):
        tok = raw.split()
        if not tok or tok[0].startswith("#"):
            continue
        kind = tok[0]
        where = f"{path}:{lineno}"
        if kind == "FLASER":
            if len(tok) < 2:
                raise CarmenLogError(f"{where}: FLASER without a beam count")
            n = _count(tok[1], where, "FLASER beam count")
            if len(tok) < 2 + n + 9:
                raise CarmenLogError(
                    f"{where}: FLASER with {n} beams needs {2 + n + 9} fields, got {len(tok)}"
                )
            r = _floats(tok[2 : 2 + n], where, "FLASER ranges")
            pose = _floats(tok[2 + n : 2 + n + 6], where, "FLASER poses")
            stamp = _floats(tok[-1:], where, "FLASER logger timestamp")[0]
            add_scan(r, beam_angles_rad(n), pose[:3], pose[3:6], stamp, lineno, where)
        elif kind == "Odometry":
            if len(tok) != 4:
                raise CarmenLogError(
                    f"{where}: Odometry needs x y theta, got {len(tok) - 1} fields"
                )
            last_odometry = _floats(tok[1:4], where, "Odometry pose")
        elif kind == "Laser":
            if len(tok) < 2:
                raise CarmenLogError(f"{where}: Laser without a beam count")
            n = _count(tok[1], where, "Laser beam count")
            if len(tok) != 2 + n:
                raise CarmenLogError(f"{where}: Laser with {n} beams has {len(tok) - 2} ranges")
            if last_odometry is None:
                raise CarmenLogError(f"{where}: Laser before any Odometry line")
            r = _floats(tok[2:], where, "Laser ranges")
            add_scan(r, beam_angles_rad(n), last_odometry, last_odometry, math.nan, lineno, where)
        elif kind == "PARAM" and len(tok) >= 3 and tok[1] == "robot_frontlaser_offset":
            offset_m = _floats(tok[2:3], where, "robot_frontlaser_offset")[0]
        else:
            skipped[kind] += 1

    if not ranges or angles is None:
        # Name a few of the most common first words, not all of them: a text that is no log
        # at all (a README) has thousands of distinct words.
        common = sorted(skipped.items(), key=lambda kv: (-kv[1], kv[0]))[:3]
        found = ", ".join(f"{k[:20]} x{v}" for k, v in common) or "nothing"
        more = f" and {len(skipped) - 3} other kinds" if len(skipped) > 3 else ""
        raise CarmenLogError(
            f"{path}: no laser scans (FLASER or Laser lines), not a CARMEN log; found {found}{more}"
        )
    laser_in_log = np.asarray(laser, dtype=np.float64)
    # FLASER's pose is the laser's; the base is offset_m behind it along the heading.
    base_in_log = compose(laser_in_log, np.array([-offset_m, 0.0, 0.0]))
    return CarmenLog(
        path=path,
        ranges_m=np.asarray(ranges, dtype=np.float64),
        angles_rad=np.asarray(angles, dtype=np.float64),
        laser_in_log=laser_in_log,
        odometry_in_log=np.asarray(odom, dtype=np.float64),
        base_in_log=base_in_log,
        time_s=np.asarray(times, dtype=np.float64),
        laser_offset_m=float(offset_m),
        line_numbers=np.asarray(lines, dtype=np.int64),
        skipped=dict(skipped),
    )


def read_carmen_log(path: str | Path) -> CarmenLog:
    """Read a CARMEN log file (``.gz`` files are decompressed); errors name the file."""
    p = Path(path)
    try:
        if p.suffix == ".gz":
            with gzip.open(p, "rt", encoding="ascii", errors="replace") as fh:
                text = fh.read()
        else:
            text = p.read_text(encoding="ascii", errors="replace")
    except (OSError, EOFError, gzip.BadGzipFile) as exc:
        raise CarmenLogError(f"{p}: cannot read: {exc}") from None
    return parse_carmen_log(text, path=str(p))
