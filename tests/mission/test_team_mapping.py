"""Four simulated robots revisit shared places; the GCS closes loops across robots with no
false positives against the simulator's truth, and the map gets better for it (issue 7)."""

from __future__ import annotations

import numpy as np
import pytest

from gcs.graph.pose_graph import Provenance
from mission.team_mapping import TeamMappingConfig, ate_rmse_m, run_team_mapping
from protocol.se2 import compose

pytestmark = pytest.mark.slow


def test_ate_is_invariant_to_a_rigid_motion_and_sees_distortion() -> None:
    rng = np.random.default_rng(0)
    truth = np.column_stack([rng.uniform(-20, 20, (50, 2)), rng.uniform(-3, 3, 50)])
    moved = compose(np.array([5.0, -2.0, 0.7]), truth)
    assert ate_rmse_m(moved, truth) < 1e-9
    noisy = moved + np.column_stack([rng.normal(0, 0.1, (50, 2)), np.zeros(50)])
    assert 0.05 < ate_rmse_m(noisy, truth) < 0.2


def test_four_robots_close_loops_across_robots_without_false_positives() -> None:
    """Through the one assembly of a team (sim, robot nodes, radio, GCS), as magic run."""
    report, station = run_team_mapping(TeamMappingConfig(duration_s=100.0))
    assert report.robots == 4 and report.nodes > 200 and report.robots_lost == 0
    assert report.cross_robot_closures >= 3, report
    assert report.false_closures == 0, report.closure_errors_m
    # the mission's ATE target (issue 14): measured 0.20 and 0.22 m (two runs, the GCS's loop
    # closer changing in between) since the trial runs through mission.assembly with the
    # run's seed streams; 0.105 m with the old wiring's draws of start hints and sensor noise.
    # (ate_rmse_prior_m, scored over the nodes of the first closure's time, was 0.38 and
    # 0.16 m: not the same nodes, so not compared here)
    assert report.ate_rmse_m < 0.25, report
    # what the closures bought, on the same nodes: seed 0 gave 0.21 m against 1.09 m without
    # them on one install, 0.228 m against 0.371 m on another (numpy 2.4.6, OpenCV 5.0: the
    # same code at 66f8349, other draws of the odometry's error): the closures must take off
    # at least a third of what odometry alone leaves, whatever that is
    assert report.ate_rmse_m < 0.67 * report.ate_rmse_without_closures_m, report
    assert len(station.frames()) == 4  # every robot linked to map, frames published
    assert station.stats.rejected_total == 0
    closures = station.graph.edges(Provenance.LOOP_AUTO)
    assert len(closures) == report.closures
    # every robot is tied to a teammate by scan matches, not only by its start hint
    linked = {
        r
        for e in closures
        if e.key_b is not None and (e.key_a >> 32) != (e.key_b >> 32)
        for r in (e.key_a >> 32, e.key_b >> 32)
    }
    assert linked == {0, 1, 2, 3}, linked
