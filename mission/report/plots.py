"""The mission report's plots (PNG, matplotlib's Agg backend; issue 14 item 3, paper section 7).

One function per figure, each from a decoded run record and its scores
(:mod:`mission.report.report_builder`); :func:`draw_all` draws every one and returns the paths.
Map figures are in the truth frame (``world``, metres); the GCS's estimate is brought there by
the run's ``world_from_map`` (the map's own anchor, not a fitted alignment).
"""

from __future__ import annotations

import math
from collections import defaultdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import matplotlib

matplotlib.use("Agg")  # files only: no display, no GUI toolkit

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Patch  # noqa: E402

from mission.report.map_scoring import map_in_world  # noqa: E402

if TYPE_CHECKING:
    from mission.report.report_builder import RunRecord, Scored

__all__ = ["draw_all"]

_DPI = 110
_MODE_COLOURS = {
    "autonomous": "#2ca02c",
    "semi_autonomous": "#98df8a",
    "teleoperated": "#d62728",
    "idle": "#c7c7c7",
    "paused": "#ff7f0e",
    "disabled": "#000000",
    "unknown": "#9467bd",
}
_EVENT_STYLE = {  # kind -> (colour, marker)
    "detection": ("#1f77b4", "o"),
    "neutralized": ("#2ca02c", "*"),
    "neutralization": ("#2ca02c", "P"),
    "detonation": ("#d62728", "X"),
    "blast": ("#d62728", "X"),
    "robot_lost": ("#000000", "v"),
    "civilian_harmed": ("#e377c2", "v"),
    "closure": ("#9467bd", "|"),
    "interaction": ("#ff7f0e", "s"),
}


#: Planner decisions whose event name reads wrong to a person (the planner's "lost" is a
#: robot silent too long to count on, not a robot the rules disabled).
_PLANNER_WORDS = {
    "planner_robot_lost": "robot silent too long, not counted on",
    "planner_robot_silent": "robot silent",
    "planner_robot_back": "robot heard again",
    "planner_goal_in_shadow": "robot fell silent on its goal",
}


def _num(metrics: dict[str, float], key: str, spec: str, scale: float = 1.0) -> str:
    """A metric formatted for a title; ``n/a`` when the run cannot say (NaN or absent)."""
    v = metrics.get(key, math.nan)
    return format(v * scale, spec) if v is not None and math.isfinite(v) else "n/a"


def _legend(ax: Any, **kwargs: Any) -> None:
    """A legend only when something is labelled (an empty run draws none)."""
    if ax.get_legend_handles_labels()[0]:
        ax.legend(**kwargs)


def _robot_colour(k: int) -> Any:
    return plt.get_cmap("tab10")(k % 10)


def _save(fig: Figure, path: Path) -> Path:
    fig.savefig(path, dpi=_DPI, bbox_inches="tight")
    plt.close(fig)
    return path


def _extent(record: RunRecord) -> tuple[float, float, float, float]:
    rows, cols = record.truth_occupied.shape
    res = record.truth_resolution_m
    return (0.0, cols * res, 0.0, rows * res)


def _truth_background(record: RunRecord) -> np.ndarray:
    """0 outside, 1 reachable, 2 structure."""
    img = np.zeros(record.truth_occupied.shape, dtype=np.int8)
    img[record.truth_reachable] = 1
    img[record.truth_occupied] = 2
    return img


_TRUTH_CMAP = ListedColormap(["#d9d9d9", "#ffffff", "#202020"])
_MAP_CMAP = ListedColormap(["#bdbdbd", "#ffffff", "#202020"])  # unknown, free, occupied


def explored(record: RunRecord, scored: Scored, path: Path) -> Path:
    """Explored fraction of the reachable area (truth) and known map area over time."""
    s = scored.series
    fig, ax = plt.subplots(figsize=(8, 4))
    t = np.asarray(s["t_s"], dtype=float)
    frac = np.asarray(s["explored_frac"], dtype=float)
    ax.plot(t, 100.0 * frac, color="#1f77b4", lw=2, label="explored (% of reachable, truth)")
    ax.set_xlabel("mission time (s)")
    ax.set_ylabel("explored reachable area (%)", color="#1f77b4")
    ax.set_ylim(0, 105)
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.plot(t, s["known_area_m2"], color="#ff7f0e", lw=1.5, ls="--", label="known map area (m²)")
    ax2.set_ylabel("known map area (m², estimate)", color="#ff7f0e")
    ax2.set_ylim(bottom=0)
    lines = ax.get_lines() + ax2.get_lines()
    ax.legend(lines, [str(ln.get_label()) for ln in lines], loc="lower right")
    final = _num(scored.metrics, "explored_frac", ".1f", 100.0)
    ax.set_title(f"Exploration over time (final: {final}% of the reachable area)")
    return _save(fig, path)


def map_vs_truth(record: RunRecord, scored: Scored, path: Path) -> Path:
    """The final global map beside the truth, and their overlay."""
    ext = _extent(record)
    aspect = (ext[3] - ext[2]) / max(ext[1] - ext[0], 1e-9)
    fig, axes = plt.subplots(
        1, 3, figsize=(18, 6 * aspect + 1.6), sharex=True, sharey=True, layout="constrained"
    )
    # "antialiased": thin walls survive the downsampling to screen pixels
    style = {"origin": "lower", "extent": ext, "interpolation": "antialiased"}
    axes[0].imshow(_truth_background(record), cmap=_TRUTH_CMAP, vmin=0, vmax=2, **style)
    axes[0].set_title("truth\nblack structures, white reachable, grey not reachable")
    occupancy = record.final_map()
    wfm = record.world_from_map
    m = scored.metrics
    if occupancy is not None and wfm is not None and occupancy.values.size:
        est = map_in_world(occupancy, wfm, record.truth_occupied.shape, record.truth_resolution_m)
        code = np.zeros(est.shape, dtype=np.int8)
        code[est == 0] = 1
        code[est == 100] = 2
        axes[1].imshow(code, cmap=_MAP_CMAP, vmin=0, vmax=2, **style)
        overlay = np.ones((*est.shape, 3))
        overlay[est == 0] = (0.88, 0.9, 1.0)
        truth_occ, est_occ = record.truth_occupied, est == 100
        overlay[truth_occ & ~est_occ] = (0.7, 0.7, 0.7)
        overlay[est_occ & ~truth_occ] = (0.85, 0.1, 0.1)
        overlay[est_occ & truth_occ] = (0.0, 0.0, 0.0)
        axes[2].imshow(overlay, **style)
        handles = [
            Patch(color=(0, 0, 0), label="occupied in both"),
            Patch(color=(0.85, 0.1, 0.1), label="map only (cell-exact)"),
            Patch(color=(0.7, 0.7, 0.7), label="truth only"),
            Patch(color=(0.88, 0.9, 1.0), label="map free"),
        ]
        fig.legend(handles=handles, loc="outside lower right", ncols=4, fontsize=9)
    else:
        for ax in axes[1:]:
            ax.text(0.5, 0.5, "no final map", ha="center", va="center", transform=ax.transAxes)
    axes[1].set_title(
        "GCS global map (in the truth frame)\ngrey unknown, white free, black occupied"
    )
    axes[2].set_title(
        f"overlay: occupancy F1 {_num(m, 'occupancy_f1', '.3f')} "
        f"(±{record.config.occupancy_tolerance_m:g} m)\n"
        f"precision {_num(m, 'occupancy_precision', '.3f')}, "
        f"recall {_num(m, 'occupancy_recall', '.3f')}"
    )
    for ax in axes:
        ax.set_xlabel("x (m, world)")
        ax.set_aspect("equal")
    axes[0].set_ylabel("y (m, world)")
    fig.suptitle(
        f"Final global map vs truth: explored {_num(m, 'explored_frac', '.1f', 100.0)}% "
        f"of the reachable area ({_num(m, 'explored_area_m2', '.0f')} m² known)"
    )
    return _save(fig, path)


def paths(record: RunRecord, scored: Scored, path: Path) -> Path:
    """Each robot's true path and its posterior (GCS estimate) path, with the objects."""
    fig, ax = plt.subplots(figsize=(10, 7))
    ax.imshow(_truth_background(record), origin="lower", extent=_extent(record),
              cmap=_TRUTH_CMAP, vmin=0, vmax=2, alpha=0.45, interpolation="nearest")  # fmt: skip
    ids = record.robot_ids
    roles = record.meta.get("roles", {})
    if record.track_pose is not None and len(record.track_pose):
        for k, r in enumerate(ids):
            xy = record.track_pose[:, k, :2]
            ax.plot(xy[:, 0], xy[:, 1], color=_robot_colour(k), lw=1.8,
                    label=f"robot {r} ({roles.get(str(r), '?')}) truth")  # fmt: skip
            ax.plot(*xy[0], marker="o", color=_robot_colour(k), ms=6)
    else:
        for k, r in enumerate(ids):
            xy = np.array([s["truth"][str(r)][:2] for s in record.samples if str(r) in s["truth"]])
            if len(xy):
                ax.plot(xy[:, 0], xy[:, 1], color=_robot_colour(k), lw=1.8,
                        label=f"robot {r} truth (samples)")  # fmt: skip
    wfm = record.world_from_map
    if record.final is not None and wfm is not None:
        f = record.final
        c, s = math.cos(wfm[2]), math.sin(wfm[2])
        for k, r in enumerate(ids):
            sel = f["node_robot"] == r
            p = f["node_map_from_base"][sel]
            if not len(p):
                continue
            x = wfm[0] + c * p[:, 0] - s * p[:, 1]
            y = wfm[1] + s * p[:, 0] + c * p[:, 1]
            ax.plot(x, y, color=_robot_colour(k), lw=1.0, ls="--",
                    label=f"robot {r} estimate (GCS)")  # fmt: skip
    kinds = {
        "static_ooi": ("#ff7f0e", "o", "static OOI"),
        "toxic_vat": ("#bcbd22", "s", "toxic vat"),
    }
    shown: set[str] = set()
    for o in scored.objects:
        if o["xy_m"] is None:
            continue
        colour, marker, label = kinds.get(o["kind"], ("#7f7f7f", "o", o["kind"]))
        done = o["neutralized_s"] is not None
        ax.plot(*o["xy_m"], marker=marker, color=colour, ms=10, mec="k",
                mfc=colour if o["detected_s"] is not None else "none",
                label=None if o["kind"] in shown else f"{label} (filled: detected)")  # fmt: skip
        shown.add(o["kind"])
        if done:
            ax.plot(*o["xy_m"], marker="+", color="#2ca02c", ms=14, mew=2)
    m = scored.metrics
    ax.set_title(f"Robot paths: truth (solid) and GCS estimate (dashed); ATE RMSE "
                 f"{_num(m, 'ate_rmse_m', '.3f')} m")  # fmt: skip
    ax.set_xlabel("x (m, world)")
    ax.set_ylabel("y (m, world)")
    ax.set_aspect("equal")
    _legend(ax, loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)
    return _save(fig, path)


def radio(record: RunRecord, scored: Scored, path: Path) -> Path:
    """Radio use over time: by stream (all robots, both directions) and by robot."""
    r = scored.series["radio"]
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(10, 7.5), sharex=True)
    capacity = scored.metrics.get("radio_capacity_bps", math.nan)
    if r["t_s"]:
        t = np.asarray(r["t_s"])
        bps = np.asarray(r["bps"]).reshape(len(t), -1)
        keys = [tuple(k) for k in r["keys"]]
        by_stream: dict[str, np.ndarray] = defaultdict(lambda: np.zeros(len(t)))
        by_robot: dict[tuple[int, str], np.ndarray] = defaultdict(lambda: np.zeros(len(t)))
        for i, (rid, d, stream) in enumerate(keys):
            by_stream[f"{stream} ({d})"] = by_stream[f"{stream} ({d})"] + bps[:, i]
            by_robot[(int(rid), d)] = by_robot[(int(rid), d)] + bps[:, i]
        names = sorted(by_stream, key=lambda n: -float(by_stream[n].sum()))
        edges = np.concatenate([[float(r.get("start_s", 0.0))], t])
        cmap = plt.get_cmap("tab20")
        bottom = np.zeros(len(t))
        for i, name in enumerate(names):  # stacked stairs: each rate holds over its interval
            top = bottom + by_stream[name] / 1000.0
            ax1.stairs(top, edges, baseline=bottom, fill=True, color=cmap(i % 20), label=name)
            bottom = top
        _legend(ax1, loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=7, title="stream")
        for k, rid in enumerate(record.robot_ids):
            for d, ls in (("up", "-"), ("down", ":")):
                if (rid, d) in by_robot:
                    ax2.stairs(
                        by_robot[(rid, d)] / 1000.0, edges, color=_robot_colour(k), ls=ls,
                        lw=1.6, baseline=None, label=f"robot {rid} {d}link",
                    )  # fmt: skip
        _legend(ax2, loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=7)
    else:
        ax1.text(0.5, 0.5, "fewer than two samples", ha="center", transform=ax1.transAxes)
    if math.isfinite(capacity):
        top = ax1.get_ylim()[1]
        if top >= 0.3 * capacity / 1000.0:  # the line would not flatten the data
            ax1.axhline(capacity / 1000.0, color="k", ls="--", lw=1)
            note = f"shared radio capacity {capacity / 1000:.1f} kbit/s (dashed)"
        else:
            note = f"shared radio capacity {capacity / 1000:.1f} kbit/s (off the scale)"
        ax1.text(0.01, 0.97, note, transform=ax1.transAxes, va="top", fontsize=8)
    m = scored.metrics
    ax1.set_title(
        f"Radio use by stream (all robots): {_num(m, 'radio_use_frac', '.2f', 100.0)}% of "
        f"the shared capacity over the run"
    )
    ax1.set_ylabel("kbit/s")
    ax2.set_title("Radio use by robot (solid uplink, dotted downlink)")
    ax2.set_ylabel("kbit/s")
    ax2.set_xlabel("mission time (s)")
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    return _save(fig, path)


def modes(record: RunRecord, scored: Scored, path: Path) -> Path:
    """Time and distance per robot and autonomy mode (paper Tables 4-5, Figs. 27-28)."""
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(12, 0.6 * len(record.robot_ids) + 2.5))
    ids = record.robot_ids
    all_modes = sorted({m for per in scored.modes_s.values() for m in per})
    labels = [f"robot {r}" for r in ids]
    for ax, table, unit, title in (
        (ax1, scored.modes_s, "s", "time per autonomy mode"),
        (ax2, scored.modes_m, "m", "distance per autonomy mode (truth)"),
    ):
        left = np.zeros(len(ids))
        for mode in all_modes:
            v = np.array([table.get(r, {}).get(mode, 0.0) for r in ids])
            ax.barh(labels, v, left=left, color=_MODE_COLOURS.get(mode, "#8c564b"), label=mode)
            left += v
        ax.set_xlabel(f"{'time (s)' if unit == 's' else 'distance (m)'}")
        ax.set_title(title)
        ax.invert_yaxis()
        ax.grid(axis="x", alpha=0.3)
    _legend(ax2, loc="center left", bbox_to_anchor=(1.01, 0.5), title="mode")
    fig.suptitle("Autonomy modes (cf. paper Tables 4-5, Figs. 27-28)")
    return _save(fig, path)


def interactions(record: RunRecord, scored: Scored, path: Path) -> Path:
    """Operator interactions per minute (paper Fig. 24), in one-minute bins (a last, partial
    minute is scaled to its length)."""
    mission_s = scored.metrics.get("mission_s", math.nan)
    end_min = mission_s / 60.0 if math.isfinite(mission_s) and mission_s > 0 else 1.0
    edges = np.append(np.arange(0.0, end_min, 1.0), end_min)
    times = [float(e["t_s"]) / 60.0 for e in record.events if e.get("kind") == "interaction"]
    counts, _ = np.histogram(np.clip(times, 0.0, end_min), bins=edges)
    widths = np.diff(edges)
    rate = counts / np.maximum(widths, 1e-9)
    fig, ax = plt.subplots(figsize=(8, 3.5), layout="constrained")
    ax.bar(edges[:-1], rate, width=widths * 0.95, align="edge", color="#ff7f0e")
    ax.set_xlim(0, end_min)
    ax.set_ylim(0, max(1.0, float(rate.max(initial=0.0)) * 1.15))
    ax.set_xlabel("mission time (min)")
    ax.set_ylabel("interactions per minute")
    total = int(counts.sum())
    per_min = scored.metrics.get("interactions_per_min", math.nan)
    ax.set_title(
        f"Operator interactions per minute (cf. paper Fig. 24): {total} in all, "
        f"{per_min:.2f}/min on average"
    )
    if total == 0:
        ax.text(0.5, 0.5, "no operator interactions: the mission ran unattended",
                ha="center", va="center", transform=ax.transAxes)  # fmt: skip
    ax.grid(axis="y", alpha=0.3)
    return _save(fig, path)


def events(record: RunRecord, scored: Scored, path: Path) -> Path:
    """Events over mission time, one row per kind (truth events from the simulator's rules,
    mission events from the run)."""
    rows: dict[str, list[tuple[float, str]]] = defaultdict(list)
    for e in record.events:
        kind = str(e.get("kind"))
        if kind.startswith("planner_"):  # the GCS's planner decisions, in words
            words = _PLANNER_WORDS.get(kind, kind.removeprefix("planner_").replace("_", " "))
            label = f"planner: {words} (mission)"
        else:
            what = f"{kind}: {e['object_kind']}" if "object_kind" in e else kind
            label = f"{what} ({'truth' if e.get('source') == 'sim' else 'mission'})"
        rows[label].append((float(e["t_s"]), kind))
    for o in scored.objects:  # first detection of each truth object, as scored
        if o["detected_s"] is not None:
            rows[f"{o['kind']} detected (scored)"].append((float(o["detected_s"]), "detection"))
    fig, ax = plt.subplots(figsize=(10, 0.45 * max(len(rows), 2) + 2.2))
    # top to bottom: truth, scored, the GCS's detections and events, its planner's decisions
    order = {"(truth)": 0, "(scored)": 1, "(mission)": 2}
    names = sorted(rows, key=lambda n: (order.get(n.rsplit(" ", 1)[-1], 3), "planner" in n, n))
    for i, name in enumerate(names):
        for t, kind in rows[name]:
            colour, marker = _EVENT_STYLE.get(kind, ("#7f7f7f", "o"))
            ax.plot(t, i, marker=marker, color=colour, ms=9, ls="none")
    ax.set_yticks(range(len(names)), names)
    ax.set_ylim(max(len(names), 1) - 0.3, -0.7)  # the first row on top
    end_s = scored.metrics.get("mission_s", 1.0)
    ax.set_xlim(0, 1.03 * max(end_s if math.isfinite(end_s) else 1.0, 1.0))
    ax.set_xlabel("mission time (s)")
    if not names:
        ax.text(0.5, 0.5, "no events", ha="center", va="center", transform=ax.transAxes)
    m = scored.metrics
    ax.set_title(
        f"Events: {int(m.get('blasts', 0))} blasts, {int(m.get('robots_lost', 0))} robots lost, "
        f"{int(m.get('civilians_harmed', 0))} civilians harmed\n"
        "(truth): the simulator's rules; (scored): a truth object's first detection; "
        "(mission): what the GCS knew and decided",
        fontsize=10,
    )
    ax.grid(axis="x", alpha=0.3)
    return _save(fig, path)


def draw_all(record: RunRecord, scored: Scored, out_dir: Path) -> list[Path]:
    """Every figure into ``out_dir``; returns the paths in reading order."""
    return [
        explored(record, scored, out_dir / "explored.png"),
        map_vs_truth(record, scored, out_dir / "map_vs_truth.png"),
        paths(record, scored, out_dir / "paths.png"),
        radio(record, scored, out_dir / "radio.png"),
        modes(record, scored, out_dir / "modes.png"),
        interactions(record, scored, out_dir / "interactions.png"),
        events(record, scored, out_dir / "events.png"),
    ]
