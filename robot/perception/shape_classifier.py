"""Learned thresholds on shape features (paper 5.2.1, third step) and their versioned file.

"Appropriate thresholds on the values of these four features (length, breadth, radius,
circumference) were then learned from a training dataset. Since we did not have access to
exact samples of all the objects that we needed to detect, the thresholds were then manually
enlarged." (paper 5.2.1)

A class (``cylinder``: a static OOI or toxic vat by shape; ``person``: a civilian or hostile)
is accepted when every feature lies in its ``[lo, hi]`` interval; a NaN feature is never
accepted. Two learners over labelled feature vectors, both followed by a fixed widening of
every bound (the paper's manual enlargement):

* :func:`peel_box` (shipped thresholds): from the box of all positives, bounds are moved
  inward where they shed the most negatives per positive lost, down to a target recall
  (PRIM-style peeling: recall is given up where the distractors are);
* :func:`learn_box`: quantiles of the positives plus a margin, the pair with the best F1
  (or, with ``min_recall``, the most precise pair that keeps that recall).

Version history: 1 had six features; 2 (:data:`FORMAT_VERSION`) adds ``bottom_m`` and
``side_gap_m`` (:mod:`robot.perception.shape_features`); a file of another version is
refused by name, never reinterpreted.

The file (``shape_thresholds_v2.json``) holds ``format`` (:data:`FORMAT`), ``version``
(:data:`FORMAT_VERSION`), ``feature_names`` (must equal
:data:`robot.perception.shape_features.FEATURE_NAMES`), per class ``lo``/``hi`` lists, and
free-form ``provenance`` (worlds trained on, scores). A corrupt, truncated, other-version or
other-feature file raises :class:`ThresholdFileError` naming the file and the problem.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from robot.perception.shape_features import FEATURE_NAMES

__all__ = [
    "DEFAULT_THRESHOLDS_PATH",
    "FORMAT",
    "FORMAT_VERSION",
    "ClassBox",
    "ShapeThresholds",
    "ThresholdFileError",
    "learn_box",
    "peel_box",
    "load_thresholds",
    "save_thresholds",
]

FORMAT = "magic-recon/shape-thresholds"
FORMAT_VERSION = 2
DEFAULT_THRESHOLDS_PATH = Path(__file__).with_name("shape_thresholds_v2.json")
CLASSES = ("cylinder", "person")


class ThresholdFileError(ValueError):
    """The thresholds file cannot be used; the message names the file and the problem."""


@dataclass(frozen=True)
class ClassBox:
    """Accept a feature vector when ``lo <= f <= hi`` for every feature."""

    lo: NDArray[np.float64]
    hi: NDArray[np.float64]

    def accepts(self, features: NDArray[np.float64]) -> NDArray[np.bool_]:
        """``(n, F) -> (n,)`` or ``(F,) -> ()``; NaN features are rejected."""
        f = np.asarray(features, dtype=np.float64)
        with np.errstate(invalid="ignore"):
            return np.all((f >= self.lo) & (f <= self.hi), axis=-1)  # type: ignore[no-any-return]


@dataclass(frozen=True)
class ShapeThresholds:
    feature_names: tuple[str, ...]
    boxes: dict[str, ClassBox]
    provenance: dict[str, Any] = field(default_factory=dict)

    def accepts(self, cls: str, features: NDArray[np.float64]) -> NDArray[np.bool_]:
        if cls not in self.boxes:
            raise KeyError(f"no thresholds for class {cls!r} (have {sorted(self.boxes)})")
        return self.boxes[cls].accepts(features)


def learn_box(
    positives: NDArray[np.float64],
    negatives: NDArray[np.float64],
    *,
    quantiles: tuple[float, ...] = (0.0, 0.01, 0.02, 0.05),
    margins: tuple[float, ...] = (0.0, 0.1, 0.25, 0.5),
    min_margin: NDArray[np.float64] | None = None,
    min_recall: float | None = None,
) -> tuple[ClassBox, dict[str, float]]:
    """Learn ``[lo, hi]`` per feature from positive and negative feature rows ``(n, F)``.

    For each quantile ``q`` and margin ``m``: ``lo = Q(q) - m * spread - min_margin``,
    ``hi = Q(1 - q) + m * spread + min_margin`` with ``spread = Q(1 - q) - Q(q)``; the pair
    with the best F1 on the given rows wins (ties: higher recall, then larger box). With
    ``min_recall``, the most precise pair whose recall reaches it wins instead (the most
    recalling one when none does): for a first stage whose misses are final while its false
    alarms meet a second test (colour, paper 5.2.1). Rows with NaN are left out of the
    quantiles. Returns the box and its training scores."""
    pos = np.asarray(positives, dtype=np.float64)
    neg = np.asarray(negatives, dtype=np.float64).reshape(-1, pos.shape[1])
    pos_ok = pos[np.isfinite(pos).all(axis=1)]
    if len(pos_ok) < 3:
        raise ValueError(f"learn_box: need at least 3 finite positive rows, got {len(pos_ok)}")
    extra = np.zeros(pos.shape[1]) if min_margin is None else np.asarray(min_margin, float)
    best: tuple[tuple[float, float, float], ClassBox, dict[str, float]] | None = None
    for q in quantiles:
        qlo = np.quantile(pos_ok, q, axis=0)
        qhi = np.quantile(pos_ok, 1.0 - q, axis=0)
        spread = qhi - qlo
        for m in margins:
            box = ClassBox(qlo - m * spread - extra, qhi + m * spread + extra)
            tp = int(box.accepts(pos).sum())
            fp = int(box.accepts(neg).sum()) if len(neg) else 0
            recall = tp / len(pos)
            precision = tp / max(tp + fp, 1)
            f1 = 2 * precision * recall / max(precision + recall, 1e-12)
            if min_recall is None:
                key = (round(f1, 6), round(recall, 6), m - q)
            elif recall >= min_recall:
                key = (1.0, round(precision, 6), q - m)
            else:
                key = (0.0, round(recall, 6), q - m)
            if best is None or key > best[0]:
                scores = {"recall": recall, "precision": precision, "f1": f1, "q": q, "m": m}
                best = (key, box, scores)
    assert best is not None
    return best[1], best[2]


def peel_box(
    positives: NDArray[np.float64],
    negatives: NDArray[np.float64],
    *,
    min_recall: float,
    min_margin: NDArray[np.float64] | None = None,
    fixed: NDArray[np.bool_] | None = None,
) -> tuple[ClassBox, dict[str, float]]:
    """Learn ``[lo, hi]`` by peeling (Friedman and Fisher's PRIM, top-down): start from the
    box of all finite positives and repeatedly move the one bound inward past the next
    positive(s) that removes the most negatives per positive lost, while the recall stays
    at least ``min_recall``; then widen every bound by ``min_margin`` (the paper's manual
    enlargement). Unlike quantile boxes, the recall given up is spent where the negatives
    are (a feature that separates is cut, one that does not is left wide). ``fixed``:
    features whose bounds are never peeled. Returns the box and its training scores."""
    pos = np.asarray(positives, dtype=np.float64)
    neg = np.asarray(negatives, dtype=np.float64).reshape(-1, pos.shape[1])
    pos_ok = pos[np.isfinite(pos).all(axis=1)]
    if len(pos_ok) < 3:
        raise ValueError(f"peel_box: need at least 3 finite positive rows, got {len(pos_ok)}")
    nf = pos.shape[1]
    lo, hi = pos_ok.min(axis=0), pos_ok.max(axis=0)
    frozen = np.zeros(nf, bool) if fixed is None else np.asarray(fixed, bool)
    min_keep = int(math.ceil(min_recall * len(pos)))
    with np.errstate(invalid="ignore"):
        p_in = np.all((pos_ok >= lo) & (pos_ok <= hi), axis=1)
        n_in = np.all((neg >= lo) & (neg <= hi), axis=1)
        while True:
            best: tuple[float, int, int, float] | None = None
            for i in range(nf):
                if frozen[i]:
                    continue
                vals = np.unique(pos_ok[p_in, i])
                if len(vals) < 2:
                    continue
                pv = np.sort(pos_ok[p_in, i])
                nv = np.sort(neg[n_in, i])
                budget = int(p_in.sum()) - min_keep
                # lo moved up to vals[k] loses the positives below it; hi down likewise
                lost_lo = np.searchsorted(pv, vals[1:], side="left")
                gone_lo = np.searchsorted(nv, vals[1:], side="left")
                lost_hi = len(pv) - np.searchsorted(pv, vals[:-1], side="right")
                gone_hi = len(nv) - np.searchsorted(nv, vals[:-1], side="right")
                for side, cuts, lost, gone in (
                    (0, vals[1:], lost_lo, gone_lo),
                    (1, vals[:-1], lost_hi, gone_hi),
                ):
                    ok = (lost <= budget) & (gone > 0)
                    if not ok.any():
                        continue
                    ratio = np.where(ok, gone / np.maximum(lost, 1), -1.0)
                    k = int(np.argmax(ratio))
                    if best is None or ratio[k] > best[0]:
                        best = (float(ratio[k]), i, side, float(cuts[k]))
            if best is None:
                break
            _, i, side, new = best
            if side == 0:
                lo[i] = new
            else:
                hi[i] = new
            p_in &= (pos_ok[:, i] >= lo[i]) & (pos_ok[:, i] <= hi[i])
            n_in &= (neg[:, i] >= lo[i]) & (neg[:, i] <= hi[i])
    extra = np.zeros(nf) if min_margin is None else np.asarray(min_margin, float)
    box = ClassBox(lo - extra, hi + extra)
    tp = int(box.accepts(pos).sum())
    fp = int(box.accepts(neg).sum()) if len(neg) else 0
    recall = tp / len(pos)
    precision = tp / max(tp + fp, 1)
    f1 = 2 * precision * recall / max(precision + recall, 1e-12)
    return box, {"recall": recall, "precision": precision, "f1": f1, "method": "peel"}  # type: ignore[dict-item]


def save_thresholds(path: str | Path, thresholds: ShapeThresholds) -> None:
    """Write the versioned JSON file (see the module docstring)."""
    doc = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "feature_names": list(thresholds.feature_names),
        "classes": {
            name: {"lo": [float(v) for v in box.lo], "hi": [float(v) for v in box.hi]}
            for name, box in thresholds.boxes.items()
        },
        "provenance": thresholds.provenance,
    }
    Path(path).write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")


def _num(v: Any, where: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        # JSON has no infinity: open-ended bounds are stored as +-1e9
        raise ThresholdFileError(f"{where}: expected a finite number, got {v!r}")
    return float(v)


def load_thresholds(
    path: str | Path = DEFAULT_THRESHOLDS_PATH,
    *,
    feature_names: tuple[str, ...] = FEATURE_NAMES,
) -> ShapeThresholds:
    """Read and check a thresholds file; any problem raises :class:`ThresholdFileError`."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except FileNotFoundError:
        raise ThresholdFileError(f"{p}: no such thresholds file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise ThresholdFileError(f"{p}: not a readable JSON thresholds file: {err}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ThresholdFileError(f"{p}: not a shape thresholds file (format != {FORMAT!r})")
    if doc.get("version") != FORMAT_VERSION:
        raise ThresholdFileError(
            f"{p}: thresholds file version {doc.get('version')!r}, this code reads "
            f"version {FORMAT_VERSION}"
        )
    names = doc.get("feature_names")
    if not isinstance(names, list) or tuple(names) != tuple(feature_names):
        raise ThresholdFileError(
            f"{p}: feature_names {names!r} do not match the detector's {list(feature_names)}"
        )
    classes = doc.get("classes")
    if not isinstance(classes, dict) or not classes:
        raise ThresholdFileError(f"{p}: 'classes' must be a non-empty object")
    boxes: dict[str, ClassBox] = {}
    for name, spec in classes.items():
        if not isinstance(spec, dict):
            raise ThresholdFileError(f"{p}: classes.{name} must be an object with lo and hi")
        bounds = []
        for key in ("lo", "hi"):
            vals = spec.get(key)
            if not isinstance(vals, list) or len(vals) != len(feature_names):
                raise ThresholdFileError(
                    f"{p}: classes.{name}.{key} must be a list of {len(feature_names)} numbers"
                )
            bounds.append(
                np.array([_num(v, f"{p}: classes.{name}.{key}[{i}]") for i, v in enumerate(vals)])
            )
        if np.any(bounds[0] > bounds[1]):
            i = int(np.argmax(bounds[0] > bounds[1]))
            raise ThresholdFileError(
                f"{p}: classes.{name}: lo > hi for feature {feature_names[i]!r}"
            )
        boxes[str(name)] = ClassBox(bounds[0], bounds[1])
    prov = doc.get("provenance", {})
    return ShapeThresholds(tuple(names), boxes, prov if isinstance(prov, dict) else {})
