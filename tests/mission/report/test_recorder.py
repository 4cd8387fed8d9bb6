"""The recorder on a real short team run (small world: simulator, robot nodes, GroundStation,
metered radio channels), the report it builds, and ``magic report RUN_DIR`` rebuilding it."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from mission.cli import main
from mission.report.recorder import MissionRecorder, ReportConfig
from mission.report.report_builder import RunDirError, build_report, load_run
from tests.mission.report.team_harness import run_small_team

pytestmark = pytest.mark.slow

PLOTS = (
    "explored.png",
    "map_vs_truth.png",
    "paths.png",
    "radio.png",
    "modes.png",
    "interactions.png",
    "events.png",
)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, float]]:
    run_dir = tmp_path_factory.mktemp("run")
    metrics, rec = run_small_team(
        run_dir, duration_s=12.0, sample_period_s=4.0, interactions_at_s=(3.0, 7.0)
    )
    assert metrics is not None
    assert rec.faults == 0
    return run_dir, metrics


def _same(a: dict[str, float], b: dict[str, float]) -> list[str]:
    return [
        k for k in sorted(a.keys() | b.keys())
        if not (k in a and k in b and (a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k]))))
    ]  # fmt: skip


def test_run_directory_holds_record_report_and_plots(run: tuple[Path, dict[str, float]]) -> None:
    run_dir, metrics = run
    for name in ("meta.json", "samples.jsonl", "events.jsonl", "truth_map.npz",
                 "truth_track.npz", "final.npz"):  # fmt: skip
        assert (run_dir / "record" / name).is_file(), name
    for name in ("global_map.pgm", "global_map.yaml", "global_map.png"):
        assert (run_dir / "map" / name).is_file(), name
    doc = json.loads((run_dir / "report.json").read_text())
    assert doc["metrics"]["mission_s"] == pytest.approx(metrics["mission_s"])
    assert doc["config"]["world_name"] == "small"
    assert set(doc["plots"]) == set(PLOTS)
    md = (run_dir / "report.md").read_text()
    assert "[map/global_map.png](map/global_map.png)" in md
    assert "stopped early" not in md  # it ran its whole duration
    for name in PLOTS:
        assert f"(plots/{name})" in md
        img = cv2.imread(str(run_dir / "plots" / name))
        assert img is not None and img.shape[0] > 200 and img.shape[1] > 400, name
        assert img.std() > 5, f"{name} is blank"


def test_metrics_are_scored_against_the_truth(run: tuple[Path, dict[str, float]]) -> None:
    _, m = run
    assert m["mission_s"] == pytest.approx(12.0, abs=0.06)
    assert 0.02 < m["explored_frac"] <= 1.0
    assert m["explored_area_m2"] > 50.0
    assert m["pose_nodes"] >= 8
    # the pipeline's quality is not under test here (the map and the graph are other modules'):
    # finite, in range and consistent
    assert 0.0 <= m["ate_rmse_m"] < 2.0
    p, r = m["occupancy_precision"], m["occupancy_recall"]
    assert 0.0 < p <= 1.0 and 0.0 < r <= 1.0
    assert m["occupancy_f1"] == pytest.approx(2 * p * r / (p + r))
    assert m["robots_lost"] == 0 and m["civilians_harmed"] == 0 and m["blasts"] == 0
    assert m["static_ooi_count"] == 2 and m["toxic_vats_count"] == 1
    assert m["static_ooi_neutralized_frac"] == 0.0
    assert 0 <= m["false_closures"] <= m["closures"]
    assert m["truth_period_s"] == pytest.approx(0.2, abs=0.051)
    assert m["interactions"] == 2
    assert m["interactions_per_min"] == pytest.approx(2 / (m["mission_s"] / 60.0))
    assert m["rtf"] > 0


def test_radio_metrics_add_up_from_the_metered_bytes(run: tuple[Path, dict[str, float]]) -> None:
    run_dir, m = run
    samples = load_run(run_dir).samples
    last = samples[-1]
    span = last["t_s"]
    up = sum(b for r, d, _, b in last["link_bytes"] if d == "up")
    down = sum(b for r, d, _, b in last["link_bytes"] if d == "down")
    assert up > 0 and down > 0
    assert m["uplink_bps"] == pytest.approx(up * 8 / span)
    assert m["downlink_bps"] == pytest.approx(down * 8 / span)
    assert m["radio_use_frac"] == pytest.approx((up + down) * 8 / span / 115_200.0)
    shares = sum(m[f"robot{r}.radio_share"] for r in range(4)) + m["broadcast_radio_share"]
    assert shares == pytest.approx(m["radio_use_frac"])
    streams = {s for _, _, s, _ in last["link_bytes"]}
    assert {"pose_node", "terrain_grid", "telemetry"} <= streams


def test_modes_cover_the_mission_time(run: tuple[Path, dict[str, float]]) -> None:
    run_dir, m = run
    doc = json.loads((run_dir / "report.json").read_text())
    for r, per in doc["modes_s"].items():
        assert sum(per.values()) == pytest.approx(load_run(run_dir).samples[-1]["t_s"]), r
    assert m.get("mode_autonomous_s", 0.0) > 0.0


def test_magic_report_rebuilds_the_same_metrics(
    run: tuple[Path, dict[str, float]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run_dir, metrics = run
    copy = tmp_path / "copy"
    shutil.copytree(run_dir, copy)
    for p in [copy / "report.json", copy / "report.md", *(copy / "plots").glob("*.png")]:
        p.unlink()
    assert main(["report", str(copy)]) == 0
    out = capsys.readouterr().out
    assert "occupancy F1 of the global map" in out
    rebuilt = json.loads((copy / "report.json").read_text())["metrics"]
    again = {k: (math.nan if v is None else v) for k, v in rebuilt.items()}
    assert _same(again, metrics) == []
    assert all((copy / "plots" / name).is_file() for name in PLOTS)


def test_detections_and_rule_events_are_matched_to_truth_objects(
    run: tuple[Path, dict[str, float]], tmp_path: Path
) -> None:
    run_dir, _ = run
    copy = tmp_path / "copy"
    shutil.copytree(run_dir, copy)
    meta = json.loads((copy / "record" / "meta.json").read_text())
    wfm = np.asarray(meta["world_from_map"])
    statics = [o for o in meta["oois"] if o["kind"] == "static_ooi"]
    vat = next(o for o in meta["oois"] if o["kind"] == "toxic_vat")

    def in_map(xy: list[float], off: float = 0.0) -> list[float]:
        c, s = math.cos(wfm[2]), math.sin(wfm[2])
        dx, dy = xy[0] + off - wfm[0], xy[1] - wfm[1]
        return [c * dx + s * dy, -s * dx + c * dy]

    lines = [
        # the first static OOI, seen 1 m off: detected (within ooi_match_m = 2 m)
        {"t_s": 5.0, "kind": "detection", "source": "mission", "object_kind": "static_ooi",
         "position_in_map": in_map(statics[0]["xy_m"], 1.0)},
        # the second, 3 m off: not detected
        {"t_s": 6.0, "kind": "detection", "source": "mission", "object_kind": "static_ooi",
         "position_in_map": in_map(statics[1]["xy_m"], 3.0)},
        # the vat's position called a static OOI: the vat is not detected by it
        {"t_s": 6.5, "kind": "detection", "source": "mission", "object_kind": "static_ooi",
         "position_in_map": in_map(vat["xy_m"])},
        {"t_s": 9.0, "kind": "neutralized", "source": "sim",
         "subject": f"static_ooi:{statics[0]['ooi_id']}", "cause": "laser", "robots": [3]},
        {"t_s": 10.0, "kind": "detonation", "source": "sim",
         "subject": f"static_ooi:{statics[1]['ooi_id']}", "cause": "robot:1", "robots": [1]},
        {"t_s": 10.0, "kind": "robot_lost", "source": "sim", "subject": "robot:1", "robots": [1]},
    ]  # fmt: skip
    with (copy / "record" / "events.jsonl").open("a") as f:
        for line in lines:
            f.write(json.dumps(line) + "\n")
    m = build_report(copy)
    assert m["static_ooi_detected_frac"] == 0.5
    assert m["static_ooi_neutralized_frac"] == 0.5
    assert m["toxic_vats_detected_frac"] == 0.0
    assert m["blasts"] == 1 and m["robots_lost"] == 1
    objects = json.loads((copy / "report.json").read_text())["objects"]
    first = next(
        o for o in objects if o["id"] == statics[0]["ooi_id"] and o["kind"] == "static_ooi"
    )
    assert first["detected_s"] == 5.0 and first["neutralized_s"] == 9.0


def test_an_unfinished_run_still_reports_what_it_has(
    run: tuple[Path, dict[str, float]], tmp_path: Path
) -> None:
    run_dir, metrics = run
    copy = tmp_path / "copy"
    shutil.copytree(run_dir / "record", copy / "record")
    (copy / "record" / "final.npz").unlink()
    (copy / "record" / "truth_track.npz").unlink()
    with (copy / "record" / "samples.jsonl").open("a") as f:
        f.write('{"t_s": 99.0, "trunc')  # killed mid-line
    m = build_report(copy)
    assert math.isnan(m["ate_rmse_m"]) and math.isnan(m["occupancy_f1"])
    assert m["explored_frac"] == pytest.approx(load_run(run_dir).samples[-1]["explored_frac"])
    assert m["uplink_bps"] == pytest.approx(metrics["uplink_bps"])
    md = (copy / "report.md").read_text()
    assert "did not finish" in md
    assert "map/global_map.png" not in md  # no dead link: the copy has no map/
    assert "No global map was exported" in md


def test_bad_run_dirs_are_one_line_and_status_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["report", str(tmp_path / "absent")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not a directory" in err
    assert main(["report", str(tmp_path)]) == 2
    assert "no record/meta.json" in capsys.readouterr().err
    (tmp_path / "record").mkdir()
    (tmp_path / "record" / "meta.json").write_text("{not json")
    with pytest.raises(RunDirError, match="meta.json"):
        load_run(tmp_path)
    (tmp_path / "record" / "meta.json").write_text('{"format_version": 99}')
    assert main(["report", str(tmp_path)]) == 2
    assert "format_version 99" in capsys.readouterr().err


def test_bad_roles_and_config_are_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="roles"):
        MissionRecorder(tmp_path, world_name="w", seed=0, duration_s=1.0, roles={0: "pilot"})
    with pytest.raises(ValueError, match="ooi_match_m"):
        ReportConfig(ooi_match_m=-1.0)


def test_a_bad_sample_is_a_counted_fault_not_a_stopped_run(tmp_path: Path) -> None:
    from gcs.ground_station import GroundStation
    from mission.config import CONFIGS_DIR
    from sim.simulator import Simulator, load_world_config

    world = load_world_config(CONFIGS_DIR / "world" / "small.yaml")
    with Simulator(world) as sim:
        roles = dict(zip(sim.robot_ids, sim.roles, strict=True))
        rec = MissionRecorder(tmp_path, world_name="small", seed=0, duration_s=1.0, roles=roles)
        station = GroundStation()
        bad: dict = {"not a (robot, direction, stream) key": 3}
        rec.sample(0.0, sim=sim, station=station, link_bytes=bad, modes={})
        assert rec.faults == 1
        sim.run_for(0.5)
        rec.sample(sim.time_s, sim=sim, station=station, link_bytes={}, modes={0: None})
        rec.event(sim.time_s, "note", payload=object())  # unknown values are kept as text
        assert rec.faults == 1
        metrics = rec.finish(sim=sim, station=station)
    assert metrics["mission_s"] == pytest.approx(0.5)
    assert math.isnan(metrics["ate_rmse_m"])  # no pose node: nothing to score, no error
    kinds = [json.loads(line)["kind"] for line in (tmp_path / "record" / "events.jsonl").open()]
    assert kinds.count("recorder_fault") == 1 and "note" in kinds


def test_magic_report_help_says_what_it_writes(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["report", "--help"])
    assert info.value.code == 0
    out = " ".join(capsys.readouterr().out.split())
    assert "RUN_DIR" in out and "report.json" in out and "report.md" in out


def test_a_hostile_a_robot_saw_is_reported_apart_from_what_reached_the_gcs(
    run: tuple[Path, dict[str, float]], tmp_path: Path
) -> None:
    # issue 14: the report said "hostiles detected 0%" while a robot (silent, then lost)
    # had backed away from "a hostile 5.7 m off": what robots saw and what the GCS heard
    # are two lines
    run_dir, metrics = run
    copy = tmp_path / "copy"
    shutil.copytree(run_dir, copy)
    assert math.isnan(build_report(copy)["hostiles_seen_frac"])  # none recorded: n/a
    samples = [
        json.loads(s) for s in (copy / "record" / "samples.jsonl").read_text().splitlines() if s
    ]
    last = next(s for s in reversed(samples) if s.get("hostiles_truth"))
    _, x, y = last["hostiles_truth"][0]
    lines = [
        # a robot's sighting 1 m off the hostile (within hostile_match_m): seen
        {"t_s": last["t_s"], "kind": "robot_sighting", "source": "mission", "robot_id": 2,
         "object_kind": "hostile", "position_world": [x + 1.0, y]},
        # a civilian called a hostile 20 m off: not this hostile
        {"t_s": last["t_s"], "kind": "robot_sighting", "source": "mission", "robot_id": 1,
         "object_kind": "hostile", "position_world": [x + 20.0, y]},
    ]  # fmt: skip
    with (copy / "record" / "events.jsonl").open("a") as f:
        for line in lines:
            f.write(json.dumps(line) + "\n")
    m = build_report(copy)
    assert m["hostiles_seen_frac"] == 1.0
    assert m["hostiles_detected_frac"] == metrics["hostiles_detected_frac"]  # the GCS's, as was
    text = (copy / "report.md").read_text()
    assert "hostiles seen by a robot (heard by the GCS or not) | 100.0%" in text
    assert "hostiles detected at the GCS" in text
    hostile = next(
        o for o in json.loads((copy / "report.json").read_text())["objects"]
        if o["kind"] == "hostile"
    )  # fmt: skip
    assert hostile["seen_s"] == last["t_s"]
