"""``magic bench robustness``: the faults part's metric names never collide with the replay
part's (a collision is an error of the suite, raised at the end of a full run)."""

from __future__ import annotations

import pytest

from mission.bench import robustness, robustness_faults


def test_the_full_faults_part_names_no_metric_the_replay_part_reports(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    def fake_replay_log(name, label, scenarios, progress, scans):  # type: ignore[no-untyped-def]
        return {"gcs_crashes": 0.0, **{f"{s}_ate_m": 0.1 for s in scenarios}}

    monkeypatch.setattr(robustness_faults, "_replay_log", fake_replay_log)
    names = set(robustness_faults._run(quick=False, progress=lambda line: None))
    assert "clean_ate_m" in names and "faults_intel_clean_ate_m" in names
    replay = {
        f"{log}_{run}_{what}"
        for log in robustness.LOGS
        for run in ("clean", *robustness.PERTURBATIONS)
        for what in ("ate_m", "closures")
    }
    assert not names & replay
