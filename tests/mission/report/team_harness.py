"""A short real mission for the report tests: the team assembly of ``magic run``
(:func:`mission.assembly.assemble`: simulator, one robot node per robot, the real GCS with its
task allocator, the radio on real zenoh sessions in lockstep) on the small world, recorded by
:class:`MissionRecorder` the way a mission loop records it."""

from __future__ import annotations

from pathlib import Path

from mission.assembly import assemble
from mission.config import CONFIGS_DIR, config_path, load_config
from mission.lockstep_protocol import seed_streams
from mission.report.recorder import MissionRecorder, ReportConfig
from protocol.radio import RadioConfig
from sim.simulator import load_world_config


def run_small_team(
    run_dir: Path,
    *,
    duration_s: float = 30.0,
    sample_period_s: float = 5.0,
    seed: int = 0,
    finish: bool = True,
    interactions_at_s: tuple[float, ...] = (),
    config: ReportConfig | None = None,
) -> tuple[dict[str, float] | None, MissionRecorder]:
    """Run the small world's mission for ``duration_s`` mission-s, recording into ``run_dir``
    (the truth track every step, a sample every ``sample_period_s``, an ``interaction`` event
    at each of ``interactions_at_s``); returns ``finish``'s metrics (None when ``finish`` is
    False: the record is closed as a run stopped early leaves it) and the recorder."""
    world = load_world_config(CONFIGS_DIR / "world" / "small.yaml")
    radio = load_config(config_path("radio/magic2010.yaml", "radio"), RadioConfig)
    with assemble(world, seeds=seed_streams(seed), radio=radio) as asm:
        sim = asm.sim
        assert asm.gcs is not None
        station = asm.gcs.station
        rec = MissionRecorder(
            run_dir,
            world_name="small",
            seed=seed,
            duration_s=duration_s,
            roles={rid: role.value for rid, role in asm.roles.items()},
            config=config,
        )

        def sample() -> None:
            modes = {}
            for rid in sim.robot_ids:
                t = station.telemetry(rid)
                modes[rid] = None if t is None else t.mode
            rec.sample(
                sim.time_s, sim=sim, station=station, link_bytes=asm.link_bytes(), modes=modes
            )

        next_sample = 0.0
        pending = sorted(interactions_at_s)
        for _ in range(int(round(duration_s / sim.config.step_s))):
            asm.step()
            now = sim.time_s
            rec.track(now, sim=sim)
            while pending and now >= pending[0]:
                rec.event(now, "interaction", command="pause", robot_id=sim.robot_ids[0])
                pending.pop(0)
            if now >= next_sample - 1e-9:
                sample()
                next_sample = now + sample_period_s
        sample()
        if not finish:
            rec.close()
            return None, rec
        return rec.finish(sim=sim, station=station), rec
