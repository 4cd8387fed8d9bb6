"""``magic bench fuzz``: every entry point refuses hostile input with its own error type."""

from __future__ import annotations

import pytest

from mission.bench.fuzz import EntryPoint, entry_points, fuzz_entry, grid_body_garbage


@pytest.fixture(scope="module")
def points() -> dict[str, EntryPoint]:
    return {ep.name: ep for ep in entry_points()}


def test_every_decoder_and_parser_is_an_entry_point(points: dict[str, EntryPoint]) -> None:
    names = set(points)
    assert {"uplink_frames", "downlink_frames", "sensor_frames", "robot_commands"} <= names
    assert {"station", "journal_records", "world_configs", "carmen_logs", "g2o_graphs"} <= names
    assert {"grids_magic4", "grids_inter16", "grids_zlib", "console_commands"} <= names
    for ep in points.values():  # every seed is valid: the fuzz starts from real input
        for seed in ep.seeds:
            ep.call(seed)


@pytest.mark.parametrize(
    "name", ["uplink_frames", "grids_inter16", "station", "journal_records", "g2o_graphs"]
)
def test_hostile_input_is_refused_not_crashed(points: dict[str, EntryPoint], name: str) -> None:
    res = fuzz_entry(points[name], 600)
    assert res.inputs == 600 and res.mutants == 300
    assert res.crashes == 0, res.crash_examples[:1]
    assert res.hangs == 0
    assert 0 < res.accepted_mutants < res.mutants  # it reaches past the first check, not all


def test_a_crash_is_counted_with_its_input() -> None:
    def fragile(data: bytes) -> object:
        if len(data) > 3:
            raise IndexError("boom")
        raise ValueError("refused")

    res = fuzz_entry(EntryPoint("fragile", [b"abcdef"], fragile, (ValueError,)), 100)
    assert res.crashes > 0 and res.crash_examples
    data, tb = res.crash_examples[0]
    assert len(data) > 3 and "IndexError: boom" in tb


def test_codecs_are_measured_for_what_they_can_refuse(points: dict[str, EntryPoint]) -> None:
    """A range coder has no redundancy: its accepted garbage is reported apart, and how much
    of it a codec decodes under a valid header is measured, not assumed."""
    grids = {n for n, ep in points.items() if not ep.redundant}
    assert grids == {n for n in points if n.startswith("grids_")}
    frac = grid_body_garbage(100)
    assert frac["magic4"] == 0.0  # its stream's end is checked
    assert frac["ctx16a"] > 0.5  # a context-model range coder decodes most random bodies
