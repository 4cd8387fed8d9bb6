"""A robot holding a RelayTask puts its radio in relay mode, in lockstep: a teammate out of
the GCS's range is then heard through it (paper 4.1: robots used as relays)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from mission.lockstep import TeamInLockstep, TeamOverProcesses, seed_streams
from protocol.messages import GoToTask, RelayTask
from protocol.radio import RadioConfig
from sim.simulator import Simulator, SimulatorConfig
from tests.sim.simworlds import make_world

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("processes", [False, True], ids=["in-process", "worker-process"])
def test_a_relay_task_carries_a_teammate_out_of_range(processes: bool, tmp_path: Path) -> None:
    """In one process and with the nodes in a worker process (the node's relay setting comes
    back in its StepDone): the same relay."""
    # GCS antenna at (1, 10); range 30 m: robot 0 at 26 m is in range, robot 1 at 44 m not,
    # but 18 m from robot 0
    world = make_world(
        robots=[(27.0, 10.0, 0.0, "sensor"), (45.0, 10.0, 0.0, "sensor")], size_m=(60.0, 20.0)
    )
    radio = RadioConfig(range_m=30.0)
    with Simulator(world, config=SimulatorConfig(seed=0), radio=radio) as sim:
        team: Any
        if processes:
            radio_path = tmp_path / "radio.yaml"
            text = (REPO / "configs" / "radio" / "magic2010.yaml").read_text()
            radio_path.write_text(text.replace("range_m: 150.0", "range_m: 30.0"))
            team = TeamOverProcesses(
                sim,
                radio=radio,
                radio_path=str(radio_path),
                seeds=seed_streams(0),
                on_ground_message=lambda rid, msg: None,
                workers=1,
            )
        else:
            team = TeamInLockstep(
                sim, radio=radio, seeds=seed_streams(0), on_ground_message=lambda rid, msg: None
            )
        with team:
            sent: list[object] = []

            def ground() -> None:
                if not sent and sim.time_s >= 0.5:
                    msg = RelayTask(1, sim.time_s, (0.0, 0.0))  # hold where it is (its odom)
                    team.ground.send(0, msg)
                    sent.append(msg)

            while sim.time_s < 3.0:
                team.step(ground)
            assert processes or team.nodes[0].radio_relay
            assert bool(sim.relay[0])
            state = sim.radio_state
            assert state is not None
            assert state.hops[1] == 2 and sim.radio_grants()[1].uplink_bps > 0
            # a goto ends relay mode: robot 1 is out of contact again
            team.ground.send(0, GoToTask(2, sim.time_s, [(0.0, 0.0)]))
            while sim.time_s < 6.0:
                team.step()
            assert processes or not team.nodes[0].radio_relay
            assert not bool(sim.relay[0])
            assert sim.radio_grants()[1].uplink_bps == 0
