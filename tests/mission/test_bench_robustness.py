"""The replay part of ``magic bench robustness``: which perturbations are held to the
perturbed-over-clean target (mission.bench.robustness, module docstring)."""

from __future__ import annotations

import pytest

from mission.bench.robustness import INFORMATION_BOUND, KINDS, PERTURBATIONS, ratio_metrics


def test_every_perturbation_has_a_kind_and_only_the_data_gap_is_reported_apart() -> None:
    assert set(KINDS) == set(PERTURBATIONS)
    assert INFORMATION_BOUND == ("data_gap",)
    assert "odometry_gap" in PERTURBATIONS  # the "odometry gap" is held to the target


def test_the_data_gap_is_reported_under_its_own_name_outside_the_held_maximum() -> None:
    metrics = ratio_metrics(
        [("turns_0.92", 1.05), ("turns_1.08", 0.97), ("clock_jump", 1.0), ("odometry_gap", 1.14)]
        + [("data_gap", 1.33), ("odometry_gap", 1.09)]
    )
    assert metrics == {
        "perturbed_ate_ratio_max": pytest.approx(1.14),
        "perturbed_ate_ratio_max_turns": pytest.approx(1.05),
        "perturbed_ate_ratio_max_clock": pytest.approx(1.0),
        "perturbed_ate_ratio_max_odometry_gap": pytest.approx(1.14),
        "perturbed_ate_ratio_max_data_gap": pytest.approx(1.33),
    }
    # a worse odometry gap is held to the target like any other perturbation
    assert ratio_metrics([("odometry_gap", 1.5), ("data_gap", 1.2)])[
        "perturbed_ate_ratio_max"
    ] == pytest.approx(1.5)
    assert "perturbed_ate_ratio_max" not in ratio_metrics([("data_gap", 1.33)])
