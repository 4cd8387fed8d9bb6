"""A look-alike is a place the graph cannot rule out (LoopCloserConfig.look_alike_radius_m):
a match's runner-up counts only within ``look_alike_chi2`` of the guess under the candidate's
prior, and the runner-up search runs only where the prior is loose enough to hold one."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from gcs.graph.pose_graph import PoseGraph
from gcs.loops.loop_closer import LoopCloser, LoopCloserConfig
from tests.gcs.loops.test_match_ambiguity import match_one, two_rooms


@pytest.mark.parametrize(
    ("guess_x_m", "prior_sigma_m", "closure", "searched"),
    [
        (2.0, 1.0, False, True),  # either room lies within the prior: no closure
        (4.0, 0.4, True, True),  # the other room is 10 sigma off: the graph rules it out
        (4.0, 0.1, True, False),  # a prior this tight holds no place 1 m away: no search
    ],
)
def test_a_runner_up_counts_only_where_the_graph_cannot_rule_it_out(
    guess_x_m: float, prior_sigma_m: float, closure: bool, searched: bool
) -> None:
    """Node 0 saw both rooms, node 1 one of them: the match fits either room (the matcher's
    runner-up is the other, 4 m away). Node 1 truly stands in the second room (x = 4 m)."""
    room, both = two_rooms()
    cfg = LoopCloserConfig(look_alike_radius_m=1.0)
    prior = np.diag([prior_sigma_m**2, prior_sigma_m**2, 0.01])
    assert (LoopCloser(PoseGraph(), cfg)._look_alike_radius_m(prior) == 1.0) == searched
    closer, hyp = match_one(cfg, both, room, guess_x_m, wide=False, prior_sigma_m=prior_sigma_m)
    assert (hyp is not None) == closure
    assert closer.stats.look_alikes == (0 if closure else 1)
    if hyp is not None:
        np.testing.assert_allclose(hyp.a_from_b[:2], [4.0, 0.0], atol=0.1)


def test_the_matcher_reports_where_its_runner_up_is_and_the_rule_is_off_by_default() -> None:
    from gcs.loops.correlative_matcher import CorrelativeMatcher, points_grid

    room, both = two_rooms()
    cfg = LoopCloserConfig()
    assert cfg.look_alike_radius_m == 0.0  # off: the matcher's own runner_up_radius_m rules
    matcher = CorrelativeMatcher(cfg.matcher)
    grid, origin = points_grid(both, resolution_m=cfg.resolution_m)
    table = matcher.reference_table(grid, origin_m=origin, resolution_m=cfg.resolution_m)
    guess = np.array([2.0, 0.0, 0.0])
    plain = matcher.match(table, room, guess, min_score=0.5)
    assert plain is not None and plain.runner_up_a_from_b is None
    found = matcher.match(table, room, guess, min_score=0.5, runner_up_radius_m=1.0)
    assert found is not None and found.runner_up_score > 0.9 * found.normalized_score
    assert found.runner_up_a_from_b is not None
    xs = sorted([float(found.a_from_b[0]), float(found.runner_up_a_from_b[0])])
    np.testing.assert_allclose(xs, [0.0, 4.0], atol=0.15)
    with pytest.raises(ValueError, match="runner_up_radius_m"):
        matcher.match(table, room, guess, runner_up_radius_m=-1.0)
    with pytest.raises(ValueError, match="look_alike_radius_m"):
        msgspec.convert({"look_alike_radius_m": -1.0}, LoopCloserConfig)
