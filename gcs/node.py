"""``magic gcs``: the ground-control station as its own process (DESIGN section 4, paper 4.1).

A thin shell around :class:`~gcs.ground_station.GroundStation`: uplink messages arrive on the
link's thread and are queued; the node's loop hands them to the station, runs
:meth:`~gcs.ground_station.GroundStation.step` every ``step_period_s`` (mission time) and sends
what it returns on each robot's downlink. Mission time follows the simulator's clock ticks
(``--clock sim``, the default) or the host's clock (``--clock wall``) on real robots.
"""

from __future__ import annotations

import argparse
import queue
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from gcs.ground_station import GroundStation, GroundStationConfig
from protocol import keys
from protocol.clock import ManualClock, WallClock
from protocol.config import ConfigError, load_config
from protocol.link import Link
from protocol.process_cli import (
    add_link_arguments,
    follow_sim_clock,
    link_config,
    spin_until,
    stop_on_interrupt,
)
from protocol.radio import RadioConfig
from protocol.radio_channel import LinkBackpressure

__all__ = ["GcsProcess", "main"]


class GcsProcess:
    """A :class:`GroundStation` wired to the robots' radios over ``link``."""

    def __init__(
        self,
        link: Link,
        clock: Any,
        config: GroundStationConfig | None = None,
        *,
        step_period_s: float = 0.5,
        budget_s: float = 0.2,
    ) -> None:
        self.link = link
        self.clock = clock
        self.station = GroundStation(config)
        self.step_period_s = step_period_s
        self.budget_s = budget_s
        self.refused = 0
        self._inbox: queue.Queue[tuple[int, Any]] = queue.Queue()
        self.radio = link.gcs_endpoint(
            on_message=lambda rid, msg: self._inbox.put((rid, msg)), follow_radio=True
        )
        self._clock_sub = None
        if isinstance(clock, ManualClock):
            self._clock_sub = follow_sim_clock(link, clock)
        self._stop = threading.Event()
        self._last_step_s = -float("inf")

    def spin_once(self, timeout_s: float = 0.05) -> int:
        """Hand the queued messages to the station; step it when due. Returns messages taken."""
        n = 0
        try:
            item: tuple[int, Any] | None = self._inbox.get(timeout=timeout_s)
        except queue.Empty:
            item = None
        now = self.clock.now()
        while item is not None:
            self.station.handle(item[0], item[1], now_s=now)
            n += 1
            try:
                item = self._inbox.get_nowait()
            except queue.Empty:
                item = None
        if now - self._last_step_s >= self.step_period_s:
            self._last_step_s = now
            for robot_id, msg in self.station.step(now_s=now, budget_s=self.budget_s):
                try:
                    self.radio.send(robot_id, msg)
                except LinkBackpressure:
                    self.refused += 1  # the next periodic update supersedes it
        return n

    def run(
        self,
        *,
        duration_s: float | None = None,
        progress: Callable[[str], None] | None = None,
        progress_period_s: float = 5.0,
    ) -> None:
        spin_until(
            self.spin_once,
            now=self.clock.now,
            stop=self._stop,
            duration_s=duration_s,
            progress=progress,
            status=self.status_line,
            progress_period_s=progress_period_s,
        )

    def status_line(self) -> str:
        s = self.station.stats
        g = self.station.graph
        return (
            f"gcs t={self.clock.now():7.1f}s robots {len(g.robots)} "
            f"linked {len(self.station.frames())} nodes {s.pose_nodes} grids {s.terrain_grids} "
            f"edges {len(g.edges())} rejected {s.rejected_total}"
        )

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        """Release the clock subscription (the link owns the radio endpoint)."""
        if self._clock_sub is not None:
            self._clock_sub.close()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="magic gcs", description="Run the ground-control station.")
    add_link_arguments(p)
    p.add_argument("--config", type=Path, help="GCS config YAML (GroundStationConfig)")
    p.add_argument("--clock", choices=("sim", "wall"), default="sim", help="mission time source")
    p.add_argument("--duration", type=float, help="mission seconds to run (default: until ^C)")
    p.add_argument("--progress-s", type=float, default=5.0, help="wall seconds between reports")
    return p


def main(argv: list[str]) -> int:
    """``magic gcs``: returns the exit status (2 on bad arguments or configuration)."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    try:
        keys.gcs(args.mission, "state")
        config = load_config(args.config, GroundStationConfig) if args.config else None
        radio = load_config(args.radio, RadioConfig)
    except (ConfigError, ValueError) as err:
        print(f"magic gcs: {err}", file=sys.stderr)
        return 2
    clock: Any = ManualClock() if args.clock == "sim" else WallClock()
    link = Link(link_config(radio, args), mission=args.mission, clock=clock)
    proc = GcsProcess(link, clock, config)
    print(f"magic gcs: mission {args.mission!r}, waiting for robots", flush=True)
    try:
        with stop_on_interrupt(proc.stop):
            proc.run(
                duration_s=args.duration,
                progress=lambda s: print(s, flush=True),
                progress_period_s=args.progress_s,
            )
    finally:
        proc.close()
        link.close()
    print(proc.status_line(), flush=True)
    return 0
