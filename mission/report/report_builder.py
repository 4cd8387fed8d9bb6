"""Build a mission's report from its run directory alone (issue 14 item 3; paper section 7).

:func:`build_report` reads what :class:`~mission.report.recorder.MissionRecorder` kept in
``RUN_DIR/record/`` (see its module docstring), scores the run against the truth stored there,
and writes ``report.json`` (metrics, time series, configuration), ``report.md`` (readable, the
plots embedded) and ``plots/*.png``. It is what ``finish`` calls and what ``magic report
RUN_DIR`` runs, so a rebuild gives the same numbers.

Metrics (all floats; NaN where the record cannot say, e.g. no pose node yet):

* exploration: ``explored_frac`` (reachable truth cells the final map knows),
  ``explored_area_m2``, ``reachable_area_m2``;
* objects: ``static_ooi_detected_frac``, ``static_ooi_neutralized_frac``,
  ``toxic_vats_detected_frac``, ``hostiles_detected_frac``, ``hostiles_neutralized_frac``
  (detected: a GCS hazard or a detection event within ``ooi_match_m`` / ``hostile_match_m``
  of the object, in the truth frame: what reached the GCS; neutralized: the simulator's rule
  events); ``hostiles_seen_frac``: hostiles a robot's own perception labelled, heard by the
  GCS or not (``robot_sighting`` events: ``position_world``, placed by the recorder from the
  robot's true pose; a robot that saw a hostile from a radio shadow and was lost there
  backed away from it, "a hostile 5.7 m off", while the GCS never heard of it: small world
  seed 7); NaN when the record holds no robot sightings (robots in other processes);
* losses: ``robots_lost``, ``civilians_harmed``, ``blasts``;
* estimation: ``closures`` (automatic loop closures accepted), ``false_closures``,
  ``closure_error_max_m``; the same for ``fiducial_edges`` and ``operator_edges`` (start
  hints and accepted suggestions); ``ate_rmse_m``, ``occupancy_f1`` / ``_precision`` /
  ``_recall`` (the map in the GCS's frame, anchored at the first robot's start as the run
  placed it), ``occupancy_f1_aligned`` (the map moved by the rigid alignment the ATE uses: its
  shape apart from its anchoring; a diagnostic, not the issue's metric);
* radio: ``uplink_bps``, ``downlink_bps`` (team) and per robot ``robot<id>.uplink_bps``,
  ``robot<id>.downlink_bps``, ``robot<id>.radio_share``; ``broadcast_radio_share`` (the
  GCS's broadcasts to the team, metered once); ``radio_use_frac`` (all traffic over
  the shared capacity);
* autonomy (paper Tables 4-5): ``mode_<mode>_s``, ``mode_<mode>_m``; ``interactions``,
  ``interactions_per_min`` (paper Fig. 24);
* ``mission_s``, ``wall_s``, ``rtf`` (mission seconds per wall second, whole system).
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from gcs.mapping.rasterization import OccupancyMap
from mission.report.map_scoring import (
    cell_centres,
    explored_frac,
    occupancy_scores,
)
from mission.report.recorder import FORMAT_VERSION, ReportConfig
from mission.report.trajectory_scoring import (
    ate_rmse_m,
    closure_errors,
    false_closures,
    rigid_world_from_map,
)

__all__ = ["RunDirError", "RunRecord", "build_report", "load_run", "score_run"]


class RunDirError(ValueError):
    """The run directory is missing, incomplete or unreadable (the message says which file)."""


@dataclass
class RunRecord:
    """What a run directory holds, decoded."""

    run_dir: Path
    meta: dict[str, Any]
    config: ReportConfig
    samples: list[dict[str, Any]]
    events: list[dict[str, Any]]
    truth_occupied: NDArray[np.bool_]
    truth_reachable: NDArray[np.bool_]
    truth_resolution_m: float
    track_t: NDArray[np.float64] | None = None
    track_pose: NDArray[np.float64] | None = None  # (T, N, 3) world_from_base
    track_wall_s: float = math.nan
    final: dict[str, NDArray[Any]] | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def robot_ids(self) -> list[int]:
        return [int(r) for r in self.meta["robot_ids"]]

    @property
    def world_from_map(self) -> NDArray[np.float64] | None:
        w = self.meta.get("world_from_map")
        return None if w is None else np.asarray(w, dtype=np.float64)

    def final_map(self) -> OccupancyMap | None:
        if self.final is None:
            return None
        origin = self.final["map_origin_m"]
        return OccupancyMap(
            self.final["map_values"].astype(np.int8),
            (float(origin[0]), float(origin[1])),
            float(self.final["map_resolution_m"]),
        )


def _read_jsonl(path: Path) -> list[dict[str, Any]]:
    out = []
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise RunDirError(f"{path}: cannot read: {exc.strerror}") from None
    for n, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            if n == len(text.splitlines()):  # a run killed mid-line: keep what is whole
                break
            raise RunDirError(f"{path}:{n}: not a JSON line") from None
    return out


def load_run(run_dir: str | Path) -> RunRecord:
    """Decode ``run_dir``; :class:`RunDirError` names the first missing or bad file."""
    root = Path(run_dir)
    if not root.is_dir():
        raise RunDirError(f"{root}: not a directory")
    rec = root / "record"
    meta_path = rec / "meta.json"
    if not meta_path.is_file():
        raise RunDirError(f"{root}: not a run directory (no record/meta.json)")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise RunDirError(f"{meta_path}: unreadable: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format_version") != FORMAT_VERSION:
        got = meta.get("format_version") if isinstance(meta, dict) else None
        raise RunDirError(f"{meta_path}: format_version {got!r}, expected {FORMAT_VERSION}")
    import msgspec

    try:
        config = msgspec.convert(meta.get("report_config", {}), ReportConfig)
    except (msgspec.ValidationError, ValueError) as exc:
        raise RunDirError(f"{meta_path}: report_config: {exc}") from None
    try:
        with np.load(rec / "truth_map.npz") as z:
            occ, reach, res = z["vertical_occupancy"], z["reachable"], float(z["resolution_m"])
    except (OSError, KeyError, ValueError) as exc:
        raise RunDirError(f"{rec / 'truth_map.npz'}: unreadable: {exc}") from None
    record = RunRecord(
        root, meta, config, _read_jsonl(rec / "samples.jsonl"), _read_jsonl(rec / "events.jsonl"),
        occ.astype(bool), reach.astype(bool), res,
    )  # fmt: skip
    track = rec / "truth_track.npz"
    if track.is_file():
        try:
            with np.load(track) as z:
                record.track_t = z["time_s"].astype(np.float64)
                record.track_pose = z["world_from_base"].astype(np.float64)
                record.track_wall_s = float(z["wall_s"])
        except (OSError, KeyError, ValueError) as exc:
            raise RunDirError(f"{track}: unreadable: {exc}") from None
    else:
        record.notes.append("no truth track (the run did not finish): truth from the samples")
    final = rec / "final.npz"
    if final.is_file():
        try:
            with np.load(final) as z:
                record.final = {k: z[k] for k in z.files}
        except (OSError, ValueError) as exc:
            raise RunDirError(f"{final}: unreadable: {exc}") from None
    else:
        record.notes.append(
            "no final graph and map (the run did not finish): estimation metrics are NaN"
        )
    return record


# ---- scoring ---------------------------------------------------------------------------------


def _to_world(world_from_map: NDArray[np.float64], xy: NDArray[np.float64]) -> NDArray[np.float64]:
    c, s = math.cos(world_from_map[2]), math.sin(world_from_map[2])
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    return np.stack(
        [
            world_from_map[0] + c * xy[:, 0] - s * xy[:, 1],
            world_from_map[1] + s * xy[:, 0] + c * xy[:, 1],
        ],
        axis=1,
    )


def _sightings(
    record: RunRecord,
) -> tuple[NDArray[np.float64], NDArray[np.str_], NDArray[np.float64]]:
    """``(time_s (K,), object kind (K,), xy in world (K, 2))`` of every GCS hazard (as of
    each sample) and every detection event with a position."""
    wfm = record.world_from_map
    times: list[float] = []
    kinds: list[str] = []
    xys: list[tuple[float, float]] = []
    if wfm is not None:
        for s in record.samples:
            for _hid, kind, x, y in s.get("hazards", []):
                times.append(float(s["t_s"]))
                kinds.append(str(kind))
                xys.append((float(x), float(y)))
        for e in record.events:
            if e.get("kind") == "detection" and e.get("position_in_map") is not None:
                times.append(float(e["t_s"]))
                kinds.append(str(e.get("object_kind", "unknown")).lower())
                x, y = e["position_in_map"][:2]
                xys.append((float(x), float(y)))
    xy = _to_world(wfm, np.asarray(xys)) if wfm is not None and xys else np.zeros((0, 2))
    return np.asarray(times, dtype=np.float64), np.asarray(kinds, dtype=str), xy


@dataclass
class Scored:
    metrics: dict[str, float]
    series: dict[str, Any]
    objects: list[dict[str, Any]]
    per_robot: dict[int, dict[str, float]]
    modes_s: dict[int, dict[str, float]]
    modes_m: dict[int, dict[str, float]]


def _first(times: NDArray[np.float64], hit: NDArray[np.bool_]) -> float | None:
    return float(times[hit].min()) if np.any(hit) else None


def _objects(record: RunRecord, metrics: dict[str, float]) -> list[dict[str, Any]]:
    """Each truth object with when it was first detected and neutralized (or None). A hostile
    is matched against where it was at the sighting's time (its sampled truth, interpolated)."""
    cfg = record.config
    t, kinds, xy = _sightings(record)
    neutralized = {
        e["subject"]: float(e["t_s"])
        for e in record.events
        if e.get("source") == "sim" and e.get("kind") == "neutralized"
    }
    detonated = {
        e["subject"]: float(e["t_s"])
        for e in record.events
        if e.get("source") == "sim" and e.get("kind") == "detonation"
    }
    objects: list[dict[str, Any]] = []
    for o in record.meta.get("oois", []):
        at = np.asarray(o["xy_m"], dtype=np.float64)
        hit = (kinds == o["kind"]) & (np.hypot(*(xy - at).T) <= cfg.ooi_match_m)
        subject = f"{o['kind']}:{o['ooi_id']}"
        objects.append({
            "kind": o["kind"], "id": o["ooi_id"], "xy_m": [float(v) for v in at],
            "detected_s": _first(t, hit),
            "neutralized_s": neutralized.get(subject), "detonated_s": detonated.get(subject),
        })  # fmt: skip
    hostile_ids = [h["human_id"] for h in record.meta.get("humans", []) if h["kind"] == "hostile"]
    robot_seen = [
        e for e in record.events
        if e.get("kind") == "robot_sighting" and e.get("position_world") is not None
    ]  # fmt: skip
    seen_t = np.array([float(e["t_s"]) for e in robot_seen], dtype=np.float64)
    seen_kinds = np.array([str(e.get("object_kind", "")).lower() for e in robot_seen], dtype=str)
    seen_xy = np.array(
        [[float(v) for v in e["position_world"][:2]] for e in robot_seen], dtype=np.float64
    ).reshape(-1, 2)
    for hid in hostile_ids:
        track = np.array(
            [(float(s["t_s"]), h[1], h[2]) for s in record.samples
             for h in s.get("hostiles_truth", []) if int(h[0]) == hid]
        ).reshape(-1, 3)  # fmt: skip
        hit = np.zeros(len(t), dtype=bool)
        if len(track):
            where = np.stack(
                [np.interp(t, track[:, 0], track[:, 1]), np.interp(t, track[:, 0], track[:, 2])],
                axis=1,
            )
            hit = (kinds == "hostile") & (np.hypot(*(xy - where).T) <= cfg.hostile_match_m)
        seen = np.zeros(len(seen_t), dtype=bool)
        if len(track) and len(seen_t):
            at = np.stack(
                [
                    np.interp(seen_t, track[:, 0], track[:, 1]),
                    np.interp(seen_t, track[:, 0], track[:, 2]),
                ],
                axis=1,
            )
            seen = (seen_kinds == "hostile") & (np.hypot(*(seen_xy - at).T) <= cfg.hostile_match_m)
        objects.append({
            "kind": "hostile", "id": hid, "xy_m": None, "detected_s": _first(t, hit),
            "seen_s": _first(seen_t, seen),
            "neutralized_s": neutralized.get(f"hostile:{hid}"),
            "detonated_s": detonated.get(f"hostile:{hid}"),
        })  # fmt: skip

    def frac(kind: str, key: str) -> float:
        sel = [o for o in objects if o["kind"] == kind]
        return sum(o[key] is not None for o in sel) / len(sel) if sel else math.nan

    for kind, name in (
        ("static_ooi", "static_ooi"),
        ("toxic_vat", "toxic_vats"),
        ("hostile", "hostiles"),
    ):
        metrics[f"{name}_count"] = float(sum(o["kind"] == kind for o in objects))
        metrics[f"{name}_detected_frac"] = frac(kind, "detected_s")
    metrics["static_ooi_neutralized_frac"] = frac("static_ooi", "neutralized_s")
    metrics["hostiles_neutralized_frac"] = frac("hostile", "neutralized_s")
    metrics["hostiles_seen_frac"] = frac("hostile", "seen_s") if robot_seen else math.nan
    return objects


def _radio(
    record: RunRecord, metrics: dict[str, float], series: dict[str, Any]
) -> dict[int, dict[str, float]]:
    """Bits per second per robot, direction and stream, over the run and over time."""
    per_robot: dict[int, dict[str, float]] = {r: {} for r in record.robot_ids}
    samples = [s for s in record.samples if s.get("link_bytes") is not None]
    capacity = float(record.meta.get("radio_capacity_bps", math.nan))
    times = [float(s["t_s"]) for s in samples]
    # cumulative bytes per key over samples
    keys = sorted({(int(r), str(d), str(st)) for s in samples for r, d, st, _ in s["link_bytes"]})
    cum = np.zeros((len(samples), len(keys)))
    index = {k: i for i, k in enumerate(keys)}
    for j, s in enumerate(samples):
        for r, d, st, b in s["link_bytes"]:
            cum[j, index[(int(r), str(d), str(st))]] = float(b)
    span = times[-1] if times else math.nan
    total_bits = cum[-1].sum() * 8.0 if len(samples) else 0.0
    for direction in ("up", "down"):
        cols = [i for (r, d, _), i in index.items() if d == direction]
        bits = cum[-1, cols].sum() * 8.0 if len(samples) and cols else 0.0
        metrics[f"{'uplink' if direction == 'up' else 'downlink'}_bps"] = (
            bits / span if span > 0 else math.nan
        )
    for r in record.robot_ids:
        for direction, name in (("up", "uplink_bps"), ("down", "downlink_bps")):
            cols = [i for (rr, d, _), i in index.items() if rr == r and d == direction]
            bits = cum[-1, cols].sum() * 8.0 if len(samples) and cols else 0.0
            per_robot[r][name] = bits / span if span > 0 else math.nan
        both = per_robot[r]["uplink_bps"] + per_robot[r]["downlink_bps"]
        per_robot[r]["radio_share"] = both / capacity
    metrics["radio_use_frac"] = total_bits / (capacity * span) if span > 0 else math.nan
    # what the GCS sent the whole team at once (the hazard/frames broadcast, coalesced acks:
    # metered once under robot id -1), beside the robots' own shares
    cols = [i for (rr, _, _), i in index.items() if rr < 0]
    bits = cum[-1, cols].sum() * 8.0 if len(samples) and cols else 0.0
    metrics["broadcast_radio_share"] = bits / (capacity * span) if span > 0 else math.nan
    metrics["radio_capacity_bps"] = capacity
    # rates between samples (bps), by key
    if len(samples) >= 2:
        dt = np.diff(np.asarray(times))
        rates = np.diff(cum, axis=0) * 8.0 / np.maximum(dt, 1e-9)[:, None]
        series["radio"] = {
            "t_s": times[1:],  # each rate holds over the interval ending at its time
            "start_s": times[0],
            "keys": [list(k) for k in keys],
            "bps": rates.tolist(),
        }
    else:
        series["radio"] = {"t_s": [], "keys": [list(k) for k in keys], "bps": []}
    return per_robot


def _modes(record: RunRecord) -> tuple[dict[int, dict[str, float]], dict[int, dict[str, float]]]:
    """Time (s) and truth distance (m) per robot and autonomy mode (paper Tables 4-5). With the
    robots' mode changes recorded (``mode`` events) and a truth track: each track interval
    goes to the mode reported at its start (``unknown`` before the first report, ``disabled``
    from the robot's loss on), at the track's resolution. Otherwise the interval up to each
    sample goes to the mode reported at that sample."""
    changes = [e for e in record.events if e.get("kind") == "mode"]
    track_t = record.track_t
    if changes and track_t is not None and record.track_pose is not None and len(track_t) >= 2:
        return _modes_from_changes(record, changes, track_t, record.track_pose)
    time_s: dict[int, dict[str, float]] = {r: defaultdict(float) for r in record.robot_ids}
    dist_m: dict[int, dict[str, float]] = {r: defaultdict(float) for r in record.robot_ids}
    prev_t = 0.0
    prev_d: dict[int, float] = dict.fromkeys(record.robot_ids, 0.0)
    for s in record.samples:
        t = float(s["t_s"])
        for r in record.robot_ids:
            mode = s.get("modes", {}).get(str(r), "unknown")
            if not s.get("alive", {}).get(str(r), True):
                mode = "disabled"
            d = float(s.get("distance_m", {}).get(str(r), prev_d[r]))
            time_s[r][mode] += t - prev_t
            dist_m[r][mode] += d - prev_d[r]
            prev_d[r] = d
        prev_t = t
    return {r: dict(v) for r, v in time_s.items()}, {r: dict(v) for r, v in dist_m.items()}


def _modes_from_changes(
    record: RunRecord,
    changes: list[dict[str, Any]],
    t: NDArray[np.float64],
    pose: NDArray[np.float64],
) -> tuple[dict[int, dict[str, float]], dict[int, dict[str, float]]]:
    """:func:`_modes` from ``mode`` events over the truth track ``t`` (T,), ``pose`` (T, N, 3)."""
    lost_s: dict[int, float] = {}
    for e in record.events:
        if e.get("source") == "sim" and e.get("kind") == "robot_lost":
            for r in e.get("robots", []):
                lost_s[int(r)] = min(lost_s.get(int(r), math.inf), float(e["t_s"]))
    time_s: dict[int, dict[str, float]] = {}
    dist_m: dict[int, dict[str, float]] = {}
    dt = np.diff(t)
    for k, r in enumerate(record.robot_ids):
        mine = sorted(
            (float(e["t_s"]), str(e.get("mode", "unknown")))
            for e in changes
            if int(e.get("robot_id", -1)) == r
        )
        step_m = np.hypot(*np.diff(pose[:, k, :2], axis=0).T)
        names = ["unknown"] + [m for _, m in mine]
        at = np.searchsorted(np.array([c for c, _ in mine]), t[:-1], side="right")
        label = np.array(names, dtype=object)[at]
        label[t[:-1] >= lost_s.get(r, math.inf)] = "disabled"
        per_t: dict[str, float] = defaultdict(float)
        per_d: dict[str, float] = defaultdict(float)
        if t[0] > 0:  # before the track began (it starts with the first step)
            per_t["unknown"] += float(t[0])
        for name in set(label.tolist()):
            sel = label == name
            per_t[name] += float(dt[sel].sum())
            per_d[name] += float(step_m[sel].sum())
        time_s[r], dist_m[r] = dict(per_t), dict(per_d)
    return time_s, dist_m


def _score_edges(
    f: dict[str, NDArray[Any]],
    prefix: str,
    truth_of: dict[int, NDArray[np.float64]],
    cfg: ReportConfig,
) -> dict[str, list[Any]]:
    """The relative edges ``prefix_*`` of the final graph against the true relative poses of
    their nodes (edges whose nodes have no truth are left out): per edge the robots and node
    indices, time, error and whether it is false (``false_closure_m`` / ``_rad``). A fiducial
    edge joins the observed robot's node nearest in time, so a moving robot adds its motion
    between the two times to the error."""
    ka, kb = f[f"{prefix}_key_a"], f[f"{prefix}_key_b"]
    scored = [
        i for i in range(len(ka))
        if np.all(np.isfinite(truth_of.get(int(ka[i]), np.nan)))
        and np.all(np.isfinite(truth_of.get(int(kb[i]), np.nan)))
    ]  # fmt: skip
    err_m, err_rad = closure_errors(
        f[f"{prefix}_a_from_b"][scored],
        np.array([truth_of[int(ka[i])] for i in scored]).reshape(-1, 3),
        np.array([truth_of[int(kb[i])] for i in scored]).reshape(-1, 3),
    )
    false = false_closures(err_m, err_rad, max_m=cfg.false_closure_m, max_rad=cfg.false_closure_rad)
    return {
        "robot_a": [int(ka[i] >> 32) for i in scored],
        "node_a": [int(ka[i] & 0xFFFFFFFF) for i in scored],
        "robot_b": [int(kb[i] >> 32) for i in scored],
        "node_b": [int(kb[i] & 0xFFFFFFFF) for i in scored],
        "false": [bool(v) for v in false],
        "time_s": [float(v) for v in f[f"{prefix}_time_s"][scored]],
        "error_m": [float(v) for v in err_m],
        "error_rad": [float(v) for v in err_rad],
    }


def score_run(record: RunRecord) -> Scored:
    """Every metric and time series of the run (module docstring)."""
    cfg = record.config
    metrics: dict[str, float] = {}
    series: dict[str, Any] = {}
    last = record.samples[-1] if record.samples else {}
    if record.track_t is not None and len(record.track_t):
        mission_s = float(record.track_t[-1])
        wall_s = record.track_wall_s
    else:
        mission_s = float(last.get("t_s", math.nan))
        wall_s = float(last.get("wall_s", math.nan))
    metrics["mission_s"] = mission_s
    metrics["wall_s"] = wall_s
    metrics["rtf"] = mission_s / wall_s if wall_s > 0 else math.nan

    # exploration
    res = record.truth_resolution_m
    metrics["reachable_area_m2"] = float(np.count_nonzero(record.truth_reachable)) * res * res
    occupancy = record.final_map()
    wfm = record.world_from_map
    if occupancy is not None and wfm is not None:
        c, s_ = math.cos(wfm[2]), math.sin(wfm[2])
        d = cell_centres(record.truth_reachable, res) - wfm[:2]
        in_map = np.stack([c * d[:, 0] + s_ * d[:, 1], -s_ * d[:, 0] + c * d[:, 1]], axis=1)
        metrics["explored_frac"], _ = explored_frac(occupancy, in_map)
        known = np.count_nonzero(occupancy.values != -1)
        metrics["explored_area_m2"] = float(known) * occupancy.resolution_m**2
        occ = occupancy_scores(
            occupancy, record.truth_occupied, res, wfm, tolerance_m=cfg.occupancy_tolerance_m
        )
        metrics["occupancy_f1"] = occ.f1
        metrics["occupancy_precision"] = occ.precision
        metrics["occupancy_recall"] = occ.recall
    else:
        metrics["explored_frac"] = float(last.get("explored_frac", math.nan) or math.nan)
        metrics["explored_area_m2"] = float(last.get("known_area_m2", math.nan) or math.nan)
        for k in ("occupancy_f1", "occupancy_precision", "occupancy_recall"):
            metrics[k] = math.nan
    series["t_s"] = [float(s["t_s"]) for s in record.samples]
    series["explored_frac"] = [
        math.nan if s.get("explored_frac") is None else float(s["explored_frac"])
        for s in record.samples
    ]
    series["known_area_m2"] = [float(s.get("known_area_m2", math.nan)) for s in record.samples]
    series["closures"] = [int(s.get("closures", 0)) for s in record.samples]
    series["gcs_rejected"] = [int(s.get("rejected", 0)) for s in record.samples]
    metrics["gcs_rejected_messages"] = float(last["rejected"]) if "rejected" in last else math.nan

    objects = _objects(record, metrics)

    sim_events = [e for e in record.events if e.get("source") == "sim"]
    metrics["robots_lost"] = float(sum(e["kind"] == "robot_lost" for e in sim_events))
    metrics["civilians_harmed"] = float(sum(e["kind"] == "civilian_harmed" for e in sim_events))
    metrics["blasts"] = float(sum(e["kind"] == "detonation" for e in sim_events))

    # pose graph against the truth
    if record.final is not None:
        f = record.final
        truth_of = {int(k): f["node_world_from_base"][i] for i, k in enumerate(f["node_key"])}
        ok = np.all(np.isfinite(f["node_world_from_base"]), axis=1)
        metrics["pose_nodes"] = float(len(f["node_key"]))
        metrics["ate_rmse_m"] = (
            ate_rmse_m(f["node_map_from_base"][ok], f["node_world_from_base"][ok])
            if np.count_nonzero(ok) >= 3
            else math.nan
        )
        metrics["occupancy_f1_aligned"] = math.nan
        if occupancy is not None and np.count_nonzero(ok) >= 3:
            aligned = rigid_world_from_map(
                f["node_map_from_base"][ok], f["node_world_from_base"][ok]
            )
            metrics["occupancy_f1_aligned"] = occupancy_scores(
                occupancy,
                record.truth_occupied,
                res,
                aligned,
                tolerance_m=cfg.occupancy_tolerance_m,
            ).f1
        for prefix, count, false_name in (
            ("closure", "closures", "false_closures"),
            ("fiducial", "fiducial_edges", "false_fiducial_edges"),
            ("operator", "operator_edges", "false_operator_edges"),
        ):
            if f"{prefix}_key_a" not in f:
                continue
            found = _score_edges(f, prefix, truth_of, cfg)
            metrics[count] = float(len(f[f"{prefix}_key_a"]))
            metrics[false_name] = float(sum(found["false"]))
            metrics[f"{prefix}_error_max_m"] = max(found["error_m"], default=math.nan)
            metrics[f"{prefix}_error_median_m"] = (
                float(np.median(found["error_m"])) if found["error_m"] else math.nan
            )
            series[f"{prefix}_errors"] = found
        ka, kb = f["closure_key_a"], f["closure_key_b"]
        metrics["cross_robot_closures"] = float(np.count_nonzero((ka >> 32) != (kb >> 32)))
    else:
        for k in ("pose_nodes", "ate_rmse_m", "occupancy_f1_aligned", "closures",
                  "cross_robot_closures", "false_closures", "closure_error_max_m",
                  "closure_error_median_m", "fiducial_edges", "false_fiducial_edges"):  # fmt: skip
            metrics[k] = math.nan
    if record.track_t is not None and len(record.track_t) >= 2:
        metrics["truth_period_s"] = float(np.median(np.diff(record.track_t)))
    else:
        metrics["truth_period_s"] = math.nan

    per_robot = _radio(record, metrics, series)
    modes_s, modes_m = _modes(record)
    for table, unit in ((modes_s, "s"), (modes_m, "m")):
        totals: dict[str, float] = defaultdict(float)
        for per in table.values():
            for mode, v in per.items():
                totals[mode] += v
        for mode, v in sorted(totals.items()):
            metrics[f"mode_{mode}_{unit}"] = v
    interactions = [e for e in record.events if e.get("kind") == "interaction"]
    metrics["interactions"] = float(len(interactions))
    metrics["interactions_per_min"] = (
        len(interactions) / (mission_s / 60.0) if mission_s > 0 else math.nan
    )
    metrics["detection_events"] = float(sum(e.get("kind") == "detection" for e in record.events))
    for r, row in per_robot.items():
        alive = last.get("alive", {}).get(str(r), True)
        row["lost"] = 0.0 if alive else 1.0
        row["distance_m"] = float(last.get("distance_m", {}).get(str(r), math.nan))
        for name in ("uplink_bps", "downlink_bps", "radio_share"):
            metrics[f"robot{r}.{name}"] = row[name]
    return Scored(metrics, series, objects, per_robot, modes_s, modes_m)


def build_report(run_dir: str | Path) -> dict[str, float]:
    """Score the run in ``run_dir`` and write ``report.json``, ``report.md`` and
    ``plots/*.png`` there; returns the metrics. :class:`RunDirError` on a bad directory."""
    from mission.report import plots
    from mission.report.markdown import write_markdown

    record = load_run(run_dir)
    scored = score_run(record)
    plot_dir = record.run_dir / "plots"
    plot_dir.mkdir(exist_ok=True)
    written = plots.draw_all(record, scored, plot_dir)
    doc = {
        "format_version": FORMAT_VERSION,
        "config": {k: v for k, v in record.meta.items() if k not in ("humans",)},
        "metrics": scored.metrics,
        "robots": {str(r): v for r, v in scored.per_robot.items()},
        "modes_s": {str(r): v for r, v in scored.modes_s.items()},
        "modes_m": {str(r): v for r, v in scored.modes_m.items()},
        "objects": scored.objects,
        "series": scored.series,
        "events": record.events,
        "plots": [p.name for p in written],
        "notes": record.notes,
    }
    (record.run_dir / "report.json").write_text(
        json.dumps(_finite_json(doc), indent=1), encoding="utf-8"
    )
    write_markdown(record, scored, written, record.run_dir / "report.md")
    return scored.metrics


def _finite_json(v: Any) -> Any:
    """NaN and infinities as null (JSON has neither)."""
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _finite_json(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_finite_json(x) for x in v]
    return v
