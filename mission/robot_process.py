"""``magic robot --id N``: one robot node as its own process, on any host (DESIGN section 4).

The node's sensors come from a simulator server (``magic sim``) or a hardware process over
zenoh (:class:`~protocol.link.RemoteDriver`); its radio is a robot endpoint of the link, whose
rate follows the radio model's grants; mission time follows the simulator's clock ticks, so
rates and timeouts hold in mission time however fast the simulation runs.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
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
)
from protocol.radio import RadioConfig
from protocol.radio_channel import LinkBackpressure
from robot.node import RobotNode, RobotNodeConfig

__all__ = ["NotServed", "RobotProcess", "main"]


class NotServed(RuntimeError):
    """The mission's simulator does not simulate this robot id."""


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
        self.frames_seen = 0

    def _send(self, msg: Any) -> object:
        try:
            return self.radio.send(msg)
        except LinkBackpressure:
            self.refused += 1  # not accepted; the node's next report supersedes it
            return None

    def spin_once(self, timeout_s: float = 0.1) -> int:
        """Process the frames that arrived; returns how many."""
        frames = self.driver.poll(timeout_s)
        self.frames_seen += len(frames)
        for command in self.node.process(frames):
            self.driver.send(command)
        return len(frames)

    def simulator_robots(self, timeout_s: float = 1.0) -> list[int]:
        """The robot ids a simulator of this mission serves (its presence tokens; empty when
        no simulator is up, or the sensors come from hardware)."""
        ids = set()
        for key in self.link.present(keys.sim_radio(self.link.mission, None), timeout_s):
            try:
                ids.add(int(key.rsplit("/", 1)[1]))
            except ValueError:
                continue
        return sorted(ids)

    def check_served(self) -> None:
        """Raise :class:`NotServed` if a simulator is up and does not have this robot."""
        robots = self.simulator_robots()
        if robots and self.robot_id not in robots:
            raise NotServed(
                f"the simulator of mission {self.link.mission!r} has no robot {self.robot_id}; "
                f"its robots are {', '.join(map(str, robots))}"
            )

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


@contextlib.contextmanager
def _stop_on_signals(stop: Callable[[], None]) -> Iterator[list[int]]:
    """SIGINT and SIGTERM call ``stop`` within the block; yields the signals received (the
    same as ``sim.server.stop_on_signals``, kept here so that a robot host needs no
    simulator)."""
    got: list[int] = []
    previous: dict[int, Any] = {}

    def handler(signum: int, _frame: object) -> None:
        got.append(signum)
        stop()

    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, handler)
    try:
        yield got
    finally:
        for signum, old in previous.items():
            signal.signal(signum, old)


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
    next_check = [0.0]

    def spin_once() -> None:
        # until frames flow, check now and then that a simulator that is up has this robot
        if proc.frames_seen == 0 and time.monotonic() >= next_check[0]:
            proc.check_served()
            next_check[0] = time.monotonic() + 1.0
        proc.spin_once()

    try:
        with _stop_on_signals(proc.stop) as stopped_by:
            proc.check_served()
            print(
                f"magic robot: robot {args.id} of mission {args.mission!r} waiting for sensor "
                "frames",
                flush=True,
            )
            spin_until(
                spin_once,
                now=proc.clock.now,
                stop=proc._stop,
                duration_s=args.duration,
                progress=lambda s: print(s, flush=True),
                status=proc.status_line,
                progress_period_s=args.progress_s,
            )
    except NotServed as err:
        print(f"magic robot: {err}", file=sys.stderr)
        return 2
    finally:
        proc.close()
        link.close()
    print(proc.status_line(), flush=True)
    if stopped_by:
        print(f"magic robot: stopped by {signal.Signals(stopped_by[0]).name}", flush=True)
        return 128 + stopped_by[0]
    return 0
