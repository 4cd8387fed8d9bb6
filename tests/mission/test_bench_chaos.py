"""``magic bench chaos``'s secured-transport metrics over real zenoh and mutual TLS (issue 17
item 5): forged publishes and reads counted, with a control that the count sees a breach."""

from __future__ import annotations

from pathlib import Path

from mission.bench.chaos import unauthenticated_attempts


def test_no_forged_publish_or_read_gets_through_mutual_tls_and_access_control(
    tmp_path: Path,
) -> None:
    out = unauthenticated_attempts(tmp_path / "on", attempts=30)
    assert out["security_attempts"] == 30 * (4 * 4 - 1)  # 4 peers x 4 keys, robot 1's own not
    assert out["authorized_delivered_frac"] == 1.0  # the mission's own traffic flows
    for name in (
        "unauthenticated_publishes_accepted",
        "unauthorized_publishes_accepted",
        "unauthenticated_reads",
        "unauthorized_reads",
    ):
        assert out[name] == 0, (name, out)


def test_without_access_control_the_metrics_see_the_stranger(tmp_path: Path) -> None:
    """TLS alone lets any holder of a mission certificate in: the count is not vacuous."""
    out = unauthenticated_attempts(tmp_path / "off", attempts=30, enforce=False)
    assert out["unauthenticated_publishes_accepted"] == 0  # another CA: no connection at all
    assert out["unauthorized_publishes_accepted"] > 0
    assert out["unauthorized_reads"] > 0
