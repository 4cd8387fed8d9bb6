"""The readable mission report, ``report.md``: the run, its scores, tables and plots
(issue 14 item 3). Relative image links, so the run directory can be moved or served."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from mission.report.report_builder import RunRecord, Scored

__all__ = ["headline_lines", "write_markdown"]

#: The headline metrics, in order, with how to print them.
_HEADLINE: tuple[tuple[str, str, str], ...] = (
    ("explored_frac", "explored fraction of the reachable area", "pct"),
    ("static_ooi_detected_frac", "static OOIs detected", "pct"),
    ("static_ooi_neutralized_frac", "static OOIs neutralized", "pct"),
    ("toxic_vats_detected_frac", "toxic vats detected", "pct"),
    ("hostiles_seen_frac", "hostiles seen by a robot (heard by the GCS or not)", "pct"),
    ("hostiles_detected_frac", "hostiles detected at the GCS", "pct"),
    ("hostiles_neutralized_frac", "hostiles neutralized", "pct"),
    ("robots_lost", "robots lost", "int"),
    ("civilians_harmed", "civilians harmed", "int"),
    ("blasts", "blasts", "int"),
    ("closures", "loop closures accepted (automatic)", "int"),
    ("cross_robot_closures", "... of them between robots", "int"),
    ("false_closures", "false loop closures (truth)", "int"),
    ("fiducial_edges", "fiducial edges", "int"),
    ("false_fiducial_edges", "false fiducial edges (truth)", "int"),
    ("closure_error_max_m", "largest closure error (m)", "f3"),
    ("ate_rmse_m", "ATE RMSE (m)", "f3"),
    ("occupancy_f1", "occupancy F1 of the global map", "f3"),
    ("occupancy_f1_aligned", "... with the map aligned as for the ATE", "f3"),
    ("occupancy_precision", "occupancy precision", "f3"),
    ("occupancy_recall", "occupancy recall", "f3"),
    ("uplink_bps", "uplink, team (bit/s)", "f0"),
    ("downlink_bps", "downlink, team (bit/s)", "f0"),
    ("radio_use_frac", "share of the shared radio", "pct"),
    ("interactions_per_min", "operator interactions per minute", "f2"),
    ("gcs_rejected_messages", "messages the GCS rejected", "int"),
    ("mission_s", "mission time (s)", "f1"),
    ("wall_s", "wall time (s)", "f1"),
    ("rtf", "real-time factor (mission s per wall s)", "f2"),
)


def _fmt(v: float | None, how: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    if how == "pct":
        return f"{100.0 * v:.1f}%"
    if how == "int":
        return f"{int(round(v))}"
    return f"{v:.{int(how[1:])}f}"


def headline_lines(metrics: dict[str, float]) -> list[str]:
    """The headline metrics, one ``label: value`` line each (for a terminal)."""
    width = max(len(label) for _, label, _ in _HEADLINE)
    return [f"{label:<{width}}  {_fmt(metrics.get(key), how)}" for key, label, how in _HEADLINE]


def write_markdown(record: RunRecord, scored: Scored, plots: list[Path], path: Path) -> Path:
    """Write ``report.md`` at ``path``; returns it."""
    meta, m = record.meta, scored.metrics
    roles = meta.get("roles", {})
    sensors = sum(v == "sensor" for v in roles.values())
    lines = [
        f"# Mission report: {meta.get('world_name')} (seed {meta.get('seed')})",
        "",
        f"Started {meta.get('started_utc', '?')}; {len(record.robot_ids)} robots "
        f"({sensors} sensor, {len(roles) - sensors} disruptor); planned "
        f"{meta.get('duration_s')} mission-s, ran {_fmt(m.get('mission_s'), 'f1')} mission-s "
        f"in {_fmt(m.get('wall_s'), 'f1')} wall-s (x{_fmt(m.get('rtf'), 'f2')} real time). "
        f"World fingerprint `{meta.get('world_fingerprint')}`; shared radio "
        f"{_fmt(m.get('radio_capacity_bps'), 'f0')} bit/s.",
        "",
        "Scores are against the simulator's ground truth (read only by this report). The map "
        "is scored in its own anchor frame (the map robot's start), not after a fitted "
        "alignment; ATE RMSE is after a rigid 2D alignment.",
        "",
        "## Scores",
        "",
        "| metric | value |",
        "| --- | ---: |",
    ]
    lines += [f"| {label} | {_fmt(m.get(key), how)} |" for key, label, how in _HEADLINE]
    lines += [
        "",
        "## Robots",
        "",
        "| robot | role | lost | distance (m, truth) | uplink (bit/s) | downlink (bit/s) "
        "| share of radio |",
        "| ---: | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in record.robot_ids:
        d = scored.per_robot.get(r, {})
        lines.append(
            f"| {r} | {roles.get(str(r), '?')} | {'yes' if d.get('lost') else 'no'} | "
            f"{_fmt(d.get('distance_m'), 'f1')} | {_fmt(d.get('uplink_bps'), 'f0')} | "
            f"{_fmt(d.get('downlink_bps'), 'f0')} | {_fmt(d.get('radio_share'), 'pct')} |"
        )
    modes = sorted({k for per in scored.modes_s.values() for k in per})
    for title, table, how in (
        ("Time per autonomy mode (s; cf. paper Table 4)", scored.modes_s, "f0"),
        ("Distance per autonomy mode (m, truth; cf. paper Table 5)", scored.modes_m, "f1"),
    ):
        lines += ["", f"## {title}", "", "| robot | " + " | ".join(modes) + " |",
                  "| ---: |" + " ---: |" * len(modes)]  # fmt: skip
        for r in record.robot_ids:
            row = table.get(r, {})
            lines.append(f"| {r} | " + " | ".join(_fmt(row.get(k, 0.0), how) for k in modes) + " |")
        team = [sum(table.get(r, {}).get(k, 0.0) for r in record.robot_ids) for k in modes]
        lines.append("| team | " + " | ".join(_fmt(v, how) for v in team) + " |")
    lines += _interaction_lines(record, scored)
    lines += ["", "## Objects of interest (truth)", "",
              "| object | id | seen by a robot at (s) | detected at the GCS at (s) "
              "| neutralized at (s) | detonated at (s) |",
              "| --- | ---: | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for o in scored.objects:
        when = [_fmt(o.get(k), "f1") if o.get(k) is not None else "-" for k in
                ("seen_s", "detected_s", "neutralized_s", "detonated_s")]  # fmt: skip
        lines.append(f"| {o['kind']} | {o['id']} | " + " | ".join(when) + " |")
    wrong = [
        (what, ce, i)
        for what, key in (("loop closure", "closure_errors"), ("fiducial", "fiducial_errors"),
                          ("operator or start hint", "operator_errors"))
        for ce in [scored.series.get(key, {})]
        for i, bad in enumerate(ce.get("false", [])) if bad
    ]  # fmt: skip
    if wrong:
        lines += ["", "## False edges in the pose graph (truth)", "",
                  "| edge | added at (s) | robot/node a | robot/node b | error (m) | error (deg) |",
                  "| --- | ---: | ---: | ---: | ---: | ---: |"]  # fmt: skip
        lines += [
            f"| {what} | {ce['time_s'][i]:.1f} | {ce['robot_a'][i]}/{ce['node_a'][i]} | "
            f"{ce['robot_b'][i]}/{ce['node_b'][i]} | {ce['error_m'][i]:.3f} | "
            f"{math.degrees(ce['error_rad'][i]):.2f} |"
            for what, ce, i in wrong
        ]
    if wrong and any(what.startswith("operator") for what, _, _ in wrong):
        lines += ["", "A start hint is the deployment plan's loose prior (its placement sigma), "
                  "not a measurement: its error is expected up to that sigma."]  # fmt: skip
    lines += ["", "## Plots", ""]
    if (path.parent / "map" / "global_map.png").is_file():  # a run stopped early has none
        lines += ["The exported global map: [map/global_map.png](map/global_map.png) "
                  "(and PGM + YAML for ROS map_server in map/).", ""]  # fmt: skip
    else:
        lines += ["No global map was exported (the run stopped before its end).", ""]
    for p in plots:
        lines += [f"![{p.stem}](plots/{p.name})", ""]
    planned_s, ran_s = meta.get("duration_s"), m.get("mission_s")
    stopped = (
        isinstance(planned_s, int | float)
        and isinstance(ran_s, int | float)
        and ran_s < planned_s - 0.5
    )
    if record.notes or stopped or m.get("truth_period_s", 0.0) > 1.0:
        lines += ["## Notes", ""]
        if stopped:
            lines.append(
                f"- the run stopped early: {ran_s:.1f} of {planned_s:g} mission-s ran (^C, "
                "SIGTERM or a failure: run.log says which); every figure is of what ran"
            )
        lines += [f"- {n}" for n in record.notes]
        tp = m.get("truth_period_s", math.nan)
        if math.isfinite(tp) and tp > 1.0:
            lines.append(
                f"- the truth track is coarse ({tp:.1f} s between poses: the run did not call "
                "`MissionRecorder.track` every step); node truth is interpolated, so ATE and "
                "closure errors are approximate"
            )
        lines.append("")
    events = [e for e in record.events if e.get("source") == "sim"]
    if events:
        lines += ["## Rule events (truth)", "", "| t (s) | event | subject | cause |",
                  "| ---: | --- | --- | --- |"]  # fmt: skip
        lines += [
            f"| {float(e['t_s']):.1f} | {e['kind']} | {e.get('subject', '')} | "
            f"{e.get('cause', '')} |"
            for e in events
        ]
        lines.append("")
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _interaction_lines(record: RunRecord, scored: Scored, limit: int = 50) -> list[str]:
    """The operators' accepted commands (``interaction`` events), if any: count, rate, list."""
    events = [e for e in record.events if e.get("kind") == "interaction"]
    if not events:
        return []
    per_min = scored.metrics.get("interactions_per_min", math.nan)
    lines = [
        "",
        "## Operator interactions (cf. paper Fig. 24)",
        "",
        f"{len(events)} accepted commands, {_fmt(per_min, 'f2')} per minute.",
        "",
        "| t (s) | operator | command | robots tasked |",
        "| ---: | --- | --- | --- |",
    ]
    for e in events[:limit]:
        robots = ",".join(str(r) for r in e.get("robots", []) or []) or "-"
        command = str(e.get("command", "?")).replace("|", "/")
        lines.append(
            f"| {_fmt(e.get('t_s'), 'f1')} | {e.get('operator', '?')} | `{command}` | {robots} |"
        )
    if len(events) > limit:
        lines.append(f"| ... | | {len(events) - limit} more | |")
    return lines
