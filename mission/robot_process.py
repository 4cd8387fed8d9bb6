"""``magic robot --id N``: one robot node as its own process, on any host (DESIGN section 4).

The node's sensors come from a simulator server (``magic sim``) or a hardware process over
zenoh (:class:`~protocol.link.RemoteDriver`); its radio is a robot endpoint of the link, whose
rate follows the radio model's grants; mission time follows the simulator's clock ticks, so
rates and timeouts hold in mission time however fast the simulation runs.
"""

from __future__ import annotations

import argparse
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from mission.config import ConfigError, load_config
from protocol import keys
from protocol.clock import ManualClock
from protocol.link import Link
from protocol.messages import Direction
from protocol.process_cli import (
    add_link_arguments,
    follow_sim_clock,
    link_config,
    spin_until,
    stop_on_interrupt,
)
from protocol.radio import RadioConfig
from protocol.radio_channel import LinkBackpressure
from robot.node import RobotNode, RobotNodeConfig

__all__ = ["RobotProcess", "main"]


class RobotProcess:
    """A robot node wired to a remote driver and its radio over ``link``."""

    def __init__(
        self, link: Link, robot_id: int, clock: ManualClock, config: RobotNodeConfig
    ) -> None:
        self.link = link
        self.robot_id = robot_id
        self.clock = clock
        self.refused = 0
        self.node = RobotNode(robot_id, send=self._send, config=config)
        self.radio = link.robot_endpoint(
            robot_id, on_message=self.node.handle_downlink, follow_radio=True
        )
        self.driver = link.remote_driver(robot_id)
        self._clock_sub = follow_sim_clock(link, clock)
        self._stop = threading.Event()

    def _send(self, msg: Any) -> object:
        try:
            return self.radio.send(msg)
        except LinkBackpressure:
            self.refused += 1  # not accepted; the node's next report supersedes it
            return None

    def spin_once(self, timeout_s: float = 0.1) -> int:
        """Process the frames that arrived; returns how many."""
        frames = self.driver.poll(timeout_s)
        for command in self.node.process(frames):
            self.driver.send(command)
        return len(frames)

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
        s = self.node.stats
        pose = self.node.odometry.pose_in_odom
        up = self.link.meter.total_bytes(robot_id=self.robot_id, direction=Direction.UP)
        t = max(self.clock.now(), 1e-9)
        return (
            f"robot {self.robot_id} t={self.clock.now():7.1f}s {self.node.mode.name.lower():>13} "
            f"odom ({pose[0]:6.1f}, {pose[1]:6.1f}) sweeps {s.sweeps} nodes {s.pose_nodes} "
            f"uplink {up * 8 / t:6.0f} bps"
        )

    def stop(self) -> None:
        self._stop.set()

    def close(self) -> None:
        self._clock_sub.close()
        self.driver.close()


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="magic robot", description="Run one robot node.")
    p.add_argument("--id", type=int, required=True, help="robot id (as the simulator numbers them)")
    add_link_arguments(p)
    p.add_argument("--config", type=Path, help="robot node config YAML (RobotNodeConfig)")
    p.add_argument("--duration", type=float, help="mission seconds to run (default: until ^C)")
    p.add_argument("--progress-s", type=float, default=5.0, help="wall seconds between reports")
    return p


def main(argv: list[str]) -> int:
    """``magic robot``: returns the exit status (2 on bad arguments or configuration)."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exit_:
        return int(exit_.code or 0)
    try:
        if args.id < 0:
            raise ValueError(f"--id must be >= 0, got {args.id}")
        keys.sim_clock(args.mission)
        config = load_config(args.config, RobotNodeConfig) if args.config else RobotNodeConfig()
        radio = load_config(args.radio, RadioConfig)
    except (ConfigError, ValueError) as err:
        print(f"magic robot: {err}", file=sys.stderr)
        return 2
    clock = ManualClock()
    link = Link(link_config(radio, args), mission=args.mission, clock=clock)
    proc = RobotProcess(link, args.id, clock, config)
    print(
        f"magic robot: robot {args.id} of mission {args.mission!r} waiting for sensor frames",
        flush=True,
    )
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
