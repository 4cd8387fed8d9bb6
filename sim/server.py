"""``magic sim``: the simulator server (issue 3, DESIGN section 4).

Steps a :class:`~sim.simulator.Simulator` and, over zenoh (``protocol.link``):

- publishes each robot's sensor frames on ``magic/<mission>/sim/robot/<id>/sensors`` and takes
  its commands from ``.../commands`` (a robot node uses ``Link.remote_driver(id)``);
- publishes the mission clock (a ``ClockTick``) on ``magic/<mission>/sim/clock`` every step;
- publishes every robot's radio grant on ``magic/<mission>/sim/radio/<id>`` when the radio
  model updates (endpoints that follow the radio apply it);
- declares, while it runs, a zenoh liveliness token on ``magic/<mission>/sim/radio/<id>`` for
  every robot it simulates (``Link.present`` lists them: a ``magic robot --id N`` checks that
  the simulator has robot N);
- publishes ground truth for evaluation only on ``magic/<mission>/sim/truth/events`` (each rule
  event, JSON) and ``.../truth/poses`` (all robots' poses once per mission second, JSON).

Pacing: ``--rtf R`` runs at R times real time (0: as fast as possible); ``--lockstep``
advances only when every live robot node has consumed its latest sweep (a remote node
acknowledges a sweep by sending any command stamped at or after the sweep's ``time_s``),
which keeps the world at most a sweep ahead of its nodes; it does not make a run repeat
exactly (commands between sweeps land at steps that depend on wall-clock timing, and the
radio and a ground side are outside it): for a mission that repeats bit for bit use ``magic
run``, with ``--robot-processes`` for nodes in their own processes. ^C (SIGINT) and
SIGTERM stop the server cleanly: the link is closed, the last status line and the events are
printed, exit status 130 / 143. Bad commands (NaN/inf, undecodable) are refused, counted
and logged; the server runs on. Progress goes to stdout every ``--progress-s`` wall seconds.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import msgspec

from protocol import keys
from protocol.config import ConfigError, config_path, load_config
from protocol.process_cli import (
    exit_code_for,
    link_config,
    open_link,
    signal_name_for,
    stop_on_interrupt,
)
from protocol.radio import RadioConfig
from protocol.sensors import ClockTick, RobotCommand, encode_sensor_frame
from sim.server_args import sim_parser
from sim.simulator import CommandError, Simulator, SimulatorConfig, load_world_config

__all__ = ["SimServer", "main"]

log = logging.getLogger(__name__)


class SimServer:
    """Runs ``sim``; with ``link`` (a ``protocol.link.Link``) it serves the robots over zenoh,
    without it the simulator is only stepped (in-process drivers still work).
    ``serve_drivers=False``: the robots' frames and commands go another way (a lockstep team's
    :class:`~mission.lockstep.TeamOverProcesses` carries them in its step messages); the
    server publishes the clock, the radio grants and the truth, and declares the team."""

    def __init__(
        self,
        sim: Simulator,
        *,
        link: Any | None = None,
        mission: str = "default",
        rtf: float = 1.0,
        lockstep: bool = False,
        progress: Callable[[str], None] | None = None,
        progress_period_s: float = 2.0,
        serve_drivers: bool = True,
    ) -> None:
        if not rtf >= 0:
            raise ValueError(f"rtf must be >= 0, got {rtf}")
        self.sim = sim
        self.link = link
        self.mission = mission
        self.rtf = rtf
        self.lockstep = lockstep
        self.progress = progress
        self.progress_period_s = progress_period_s
        self.rejected_commands = 0
        self.stop_event = threading.Event()
        self._ports: dict[int, Any] = {}
        self.commands_received: dict[int, int] = {}
        self._commands = threading.Condition()
        self._radio_seen = -1
        self._events_sent = 0
        if link is not None:
            self._clock_key = keys.sim_clock(mission)
            self._events_key = keys.sim_truth(mission, "events")
            self._poses_key = keys.sim_truth(mission, "poses")
            for rid in sim.robot_ids:
                if serve_drivers:
                    self._ports[rid] = link.driver_port(rid, self._on_command(rid))
                # the team this simulator serves, for robot processes to check their --id
                link.declare_presence(keys.sim_radio(mission, rid))

    def _on_command(self, robot_id: int) -> Callable[[RobotCommand], None]:
        def handle(command: RobotCommand) -> None:
            try:
                self.sim.command(robot_id, command)
            except CommandError as err:
                self.rejected_commands += 1
                log.warning("refused command: %s", err)
            with self._commands:
                self.commands_received[robot_id] = self.commands_received.get(robot_id, 0) + 1
                self._commands.notify_all()

        return handle

    def wait_commands(self, robot_id: int, count: int, timeout_s: float) -> bool:
        """Block until ``count`` commands (accepted or refused) came from ``robot_id``'s node
        over zenoh (True) or ``timeout_s`` passes (False)."""
        with self._commands:
            return self._commands.wait_for(
                lambda: self.commands_received.get(robot_id, 0) >= count, timeout_s
            )

    def publish(self) -> None:
        """Publish what the last step produced: frames, the clock tick, new radio grants,
        events and (once per mission second) poses."""
        sim, link = self.sim, self.link
        if link is None:
            return
        for rid, port in self._ports.items():
            for frame in sim.driver(rid).take_frames():
                port.publish(frame)
        link.publish(self._clock_key, encode_sensor_frame(ClockTick(time_s=sim.time_s)))
        if sim.radio_updates != self._radio_seen:
            self._radio_seen = sim.radio_updates
            for rid, grant in sim.radio_grants().items():
                link.publish_grant(rid, grant)
        events = sim.events
        while self._events_sent < len(events):
            link.publish(self._events_key, msgspec.json.encode(events[self._events_sent]))
            self._events_sent += 1
        if sim.steps % max(1, int(round(1.0 / sim.config.step_s))) == 0:
            poses = {
                str(r): p for r, p in zip(sim.robot_ids, sim.robot_poses().tolist(), strict=True)
            }
            link.publish(
                self._poses_key, msgspec.json.encode({"time_s": sim.time_s, "poses": poses})
            )

    def run(self, duration_s: float | None = None) -> None:
        """Step until ``duration_s`` of mission time has passed (None: until :meth:`stop`)."""
        sim = self.sim
        t_end = None if duration_s is None else sim.time_s + duration_s
        wall0, sim0 = time.monotonic(), sim.time_s
        last_report = wall0
        while not self.stop_event.is_set():
            if t_end is not None and sim.time_s >= t_end - 1e-9:
                break
            if self.lockstep and not sim.wait_ready(0.5):
                continue
            sim.step()
            self.publish()
            if self.rtf > 0:
                target = wall0 + (sim.time_s - sim0) / self.rtf
                delay = target - time.monotonic()
                if delay > 0:
                    self.stop_event.wait(delay)
            now = time.monotonic()
            if self.progress is not None and now - last_report >= self.progress_period_s:
                last_report = now
                self.progress(self.status_line(now - wall0, sim.time_s - sim0))
        if self.progress is not None:
            self.progress(self.status_line(time.monotonic() - wall0, sim.time_s - sim0))

    def status_line(self, wall_s: float, sim_s: float) -> str:
        sim = self.sim
        alive = int(sim.alive().sum())
        sweeps = sum(max(0, sim.driver(r).last_sweep_sent + 1) for r in sim.robot_ids)
        rtf = sim_s / wall_s if wall_s > 0 else 0.0
        return (
            f"t={sim.time_s:8.2f} s  rtf={rtf:5.2f}  robots alive {alive}/{len(sim.robot_ids)}"
            f"  sweeps={sweeps}  events={len(sim.events)}"
            f"  refused commands={sim.rejected_commands + self.rejected_commands}"
        )

    def stop(self) -> None:
        self.stop_event.set()

    def close(self) -> None:
        for port in self._ports.values():
            port.close()
        self._ports.clear()


def main(argv: list[str]) -> int:
    """``magic sim``: returns the exit status (2 on bad arguments or configuration)."""
    try:
        args = sim_parser().parse_args(argv)
    except SystemExit as exit_:  # --help, or bad arguments (argparse printed why)
        return int(exit_.code or 0)
    out = sys.stdout
    try:
        args.world = config_path(args.world, "world")
        world_cfg = load_world_config(args.world)
        sim_cfg = (
            load_config(args.sim_config, SimulatorConfig) if args.sim_config else SimulatorConfig()
        )
        radio_cfg = load_config(args.radio, RadioConfig)
        if not (args.rtf >= 0 and (args.duration is None or args.duration >= 0)):
            raise ValueError("--rtf and --duration must be >= 0")
        keys.sim_clock(args.mission)
    except (ConfigError, ValueError) as err:
        print(f"magic sim: {err}", file=sys.stderr)
        return 2
    link = None
    if not args.no_zenoh:  # endpoints first: a port in use fails before the world is built
        try:
            link = open_link(link_config(radio_cfg, args), mission=args.mission)
        except ValueError as err:
            print(f"magic sim: {err}", file=sys.stderr)
            return 2
    print(f"magic sim: generating {args.world} ...", file=out, flush=True)
    try:
        sim = Simulator(world_cfg, config=sim_cfg, radio=radio_cfg)
    except (ValueError, KeyboardInterrupt) as problem:
        if link is not None:
            link.close()
        if isinstance(problem, ValueError):
            print(f"magic sim: {args.world}: {problem}", file=sys.stderr)
            return 2
        print(
            f"magic sim: stopped by {signal_name_for(problem)} before the simulation started",
            file=sys.stderr,
        )
        return exit_code_for(problem)
    if link is not None:
        link.clock = sim.clock  # mission time from here on
    w = sim.world
    print(
        f"magic sim: world {w.size_m[0]:.0f} x {w.size_m[1]:.0f} m, {len(w.solids)} solids, "
        f"{len(w.oois)} objects of interest, {len(w.humans)} people, {len(w.robots)} robots "
        f"({sum(r.role == 'disruptor' for r in w.robots)} disruptors); mission {args.mission!r}"
        + ("" if link is None else ", serving over zenoh")
        + (", lockstep" if args.lockstep else f", rtf {args.rtf:g}"),
        file=out,
        flush=True,
    )
    server = SimServer(
        sim,
        link=link,
        mission=args.mission,
        rtf=args.rtf,
        lockstep=args.lockstep,
        progress=lambda s: print(s, file=out, flush=True),
        progress_period_s=args.progress_s,
    )
    try:
        with stop_on_interrupt(server.stop) as stopped_by:
            server.run(args.duration)
    finally:
        server.close()
        if link is not None:
            link.close()
        sim.close()
    for ev in sim.events:
        print(f"event {ev}", file=out)
    if stopped_by:
        name = signal.Signals(stopped_by[0]).name
        print(f"magic sim: stopped by {name} at t={sim.time_s:.2f} s", file=out, flush=True)
        return 128 + stopped_by[0]
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main(sys.argv[1:]))
