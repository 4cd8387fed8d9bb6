"""Colour of a LIDAR candidate by YCrCb thresholds (paper 5.2.1).

YCrCb separates chromaticity (Cr, Cb) from luminance (Y), which gives a basic lighting
invariance; per class, a box of ``[lo, hi]`` on Y, Cr and Cb is learnt from training images
taken under varied lighting (:func:`train_thresholds`: inner quantiles of the class's pixels,
widened by a margin), plus a range of the chroma angle ``atan2(Cb - 128, Cr - 128)``
(``hue_deg``): white light of any strength scales Y, Cr - 128 and Cb - 128 alike, so the angle
separates orange static OOIs from red hostiles where the boxes overlap (measured: 8 of 21
hostiles called static OOIs with boxes alone, 0 with the angle).
:func:`classify_candidate` projects a candidate cylinder into the image
chosen by the image memory, takes the pixels inside its outline and names the class whose box
holds the largest fraction of them (at least ``min_fraction``), else ``other``.

Cost (issue 14, session 13): the 8-bit pixels of a candidate are looked up in per-value
tables of the class boxes (one of 256 Y values, one of 65536 Cr, Cb pairs with their chroma
angle) built once per thresholds from the same features and comparisons (equal for all
16.7M YCrCb values): 0.39 -> 0.024 ms thread CPU for 3000 pixels.

Thresholds ship as a versioned JSON file beside this module
(``colour_thresholds_v1.json``); :func:`load_thresholds` refuses a corrupt, mismatched or
incomplete file with an error naming the file and what is wrong.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from robot.perception.camera_model import Intrinsics, project_in_base

__all__ = [
    "CLASSES",
    "DEFAULT_THRESHOLDS_PATH",
    "ColourResult",
    "ColourThresholdError",
    "ColourThresholds",
    "candidate_mask",
    "classify_candidate",
    "classify_pixels",
    "load_thresholds",
    "save_thresholds",
    "train_thresholds",
]

#: The colour classes, in the order used everywhere (``other`` is none of them).
CLASSES = ("static_ooi", "toxic_vat", "civilian", "hostile")
FORMAT = "magic-recon/colour-thresholds"
VERSION = 1
DEFAULT_THRESHOLDS_PATH = Path(__file__).with_name("colour_thresholds_v1.json")


class ColourThresholdError(ValueError):
    """A threshold file that cannot be used (the message names the file and the problem)."""


@dataclass(frozen=True)
class ColourThresholds:
    """``boxes[c]``: ``((y_lo, y_hi), (cr_lo, cr_hi), (cb_lo, cb_hi), (hue_lo, hue_hi))``
    (hue in degrees) per class of
    :data:`CLASSES`; ``min_fraction``: share of a candidate's pixels a class needs."""

    boxes: Mapping[str, tuple[tuple[float, float], ...]]
    min_fraction: float = 0.4
    trained_on: str = ""

    def lo_hi(self) -> tuple[np.ndarray, np.ndarray]:
        """``(lo, hi)`` arrays ``(C, 4)`` (Y, Cr, Cb, hue) in :data:`CLASSES` order."""
        lo = np.array([[b[0] for b in self.boxes[c]] for c in CLASSES], dtype=float)
        hi = np.array([[b[1] for b in self.boxes[c]] for c in CLASSES], dtype=float)
        return lo, hi


@dataclass(frozen=True)
class ColourResult:
    label: str  # one of CLASSES or "other"
    fraction: float  # share of the candidate's pixels in the winning box
    pixels: int  # pixels tested
    bbox_px: tuple[int, int, int, int]  # (u0, v0, u1, v1) of the outline, clipped


def save_thresholds(thresholds: ColourThresholds, path: str | Path) -> None:
    doc = {
        "format": FORMAT,
        "version": VERSION,
        "colour_space": "YCrCb (OpenCV COLOR_RGB2YCrCb, 8 bit)",
        "min_fraction": thresholds.min_fraction,
        "trained_on": thresholds.trained_on,
        "classes": {
            c: {"y": list(b[0]), "cr": list(b[1]), "cb": list(b[2]), "hue_deg": list(b[3])}
            for c, b in ((c, thresholds.boxes[c]) for c in CLASSES)
        },
    }
    Path(path).write_text(json.dumps(doc, indent=2) + "\n")


def load_thresholds(path: str | Path = DEFAULT_THRESHOLDS_PATH) -> ColourThresholds:
    """Read a threshold file; :class:`ColourThresholdError` names the file and the problem."""
    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except OSError as err:
        raise ColourThresholdError(f"{p}: cannot read: {err.strerror}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise ColourThresholdError(f"{p}: not valid JSON: {err}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ColourThresholdError(f"{p}: not a colour threshold file (format must be {FORMAT!r})")
    if doc.get("version") != VERSION:
        raise ColourThresholdError(
            f"{p}: threshold file version {doc.get('version')!r}, this code reads version {VERSION}"
        )
    classes = doc.get("classes")
    if not isinstance(classes, dict):
        raise ColourThresholdError(f"{p}: 'classes' must be an object")
    missing = [c for c in CLASSES if c not in classes]
    if missing:
        raise ColourThresholdError(f"{p}: classes missing: {', '.join(missing)}")
    boxes = {}
    for c in CLASSES:
        entry = classes[c]
        box = []
        for ch, lo_ok, hi_ok in (
            ("y", 0, 255),
            ("cr", 0, 255),
            ("cb", 0, 255),
            ("hue_deg", -180, 180),
        ):
            v = entry.get(ch) if isinstance(entry, dict) else None
            if not (
                isinstance(v, list)
                and len(v) == 2
                and all(isinstance(x, (int, float)) and math.isfinite(x) for x in v)
                and lo_ok <= v[0] <= v[1] <= hi_ok
            ):
                raise ColourThresholdError(
                    f"{p}: classes.{c}.{ch} must be [lo, hi] with {lo_ok} <= lo <= hi <= {hi_ok},"
                    f" got {v!r}"
                )
            box.append((float(v[0]), float(v[1])))
        boxes[c] = tuple(box)
    mf = doc.get("min_fraction")
    if not (isinstance(mf, (int, float)) and 0 < mf <= 1):
        raise ColourThresholdError(f"{p}: min_fraction must be in (0, 1], got {mf!r}")
    return ColourThresholds(boxes, float(mf), str(doc.get("trained_on", "")))  # type: ignore[arg-type]


def train_thresholds(
    pixels_ycrcb: Mapping[str, np.ndarray],
    *,
    quantile: float = 0.02,
    margin: float = 6.0,
    hue_margin_deg: float = 3.0,
    min_fraction: float = 0.4,
    trained_on: str = "",
) -> ColourThresholds:
    """Boxes from ``(N, 3)`` YCrCb training pixels per class: the ``[quantile, 1 - quantile]``
    range of each channel (and of the chroma angle) widened by ``margin`` (``hue_margin_deg``):
    the paper's manual enlargement."""
    boxes = {}
    for c in CLASSES:
        px = np.asarray(pixels_ycrcb.get(c, np.zeros((0, 3))), dtype=float).reshape(-1, 3)
        if len(px) < 20:
            raise ValueError(f"train_thresholds: class {c} has {len(px)} pixels, need >= 20")
        feat = _features(px)
        lo = np.quantile(feat, quantile, axis=0) - [margin, margin, margin, hue_margin_deg]
        hi = np.quantile(feat, 1 - quantile, axis=0) + [margin, margin, margin, hue_margin_deg]
        lim_lo, lim_hi = (0.0, 0.0, 0.0, -180.0), (255.0, 255.0, 255.0, 180.0)
        boxes[c] = tuple(
            (float(max(a0, a)), float(min(b0, b)))
            for a, b, a0, b0 in zip(lo, hi, lim_lo, lim_hi, strict=True)
        )
    return ColourThresholds(boxes, min_fraction, trained_on)  # type: ignore[arg-type]


def _features(ycrcb: np.ndarray) -> np.ndarray:
    """``(N, 4)``: Y, Cr, Cb and the chroma angle (deg) of ``(N, 3)`` YCrCb pixels."""
    hue = np.degrees(np.arctan2(ycrcb[:, 2] - 128.0, ycrcb[:, 1] - 128.0))
    return np.column_stack([ycrcb, hue])


_LUTS: dict[tuple[object, ...], tuple[np.ndarray, np.ndarray]] = {}


def _class_bits(thresholds: ColourThresholds) -> tuple[np.ndarray, np.ndarray]:
    """Per 8-bit ``Y`` (256,) and per ``(Cr, Cb)`` (65536,): a uint8 whose bit ``k`` says the
    value is inside class ``k``'s box (Y; Cr, Cb and the chroma angle), from the same float
    features and comparisons as :func:`classify_pixels` makes per pixel; kept per thresholds."""
    key = tuple((c, thresholds.boxes[c]) for c in CLASSES)
    got = _LUTS.get(key)
    if got is not None:
        return got
    lo, hi = thresholds.lo_hi()
    v = np.arange(256, dtype=float)
    cr = np.repeat(v, 256)
    cb = np.tile(v, 256)
    feat = _features(np.column_stack([np.zeros(len(cr)), cr, cb]))
    y_bits = np.zeros(256, dtype=np.uint8)
    cc_bits = np.zeros(len(cr), dtype=np.uint8)
    for k in range(len(CLASSES)):
        y_in = (v >= lo[k, 0]) & (v <= hi[k, 0])
        cc_in = np.all((feat[:, 1:] >= lo[k, 1:]) & (feat[:, 1:] <= hi[k, 1:]), axis=1)
        y_bits |= y_in.astype(np.uint8) << k
        cc_bits |= cc_in.astype(np.uint8) << k
    if len(_LUTS) >= 8:
        _LUTS.clear()
    _LUTS[key] = (y_bits, cc_bits)
    return y_bits, cc_bits


def classify_pixels(ycrcb: np.ndarray, thresholds: ColourThresholds) -> tuple[str, float]:
    """The class whose box holds the largest share of ``(N, 3)`` YCrCb pixels and that share;
    ``("other", share)`` below ``min_fraction``.

    8-bit pixels (as :func:`classify_candidate` gives them) are looked up in per-value tables
    of the same box tests (:func:`_class_bits`): the same shares, 4x less CPU than testing
    every pixel's features (session 13)."""
    raw = np.asarray(ycrcb)
    if raw.dtype == np.uint8 and raw.size:
        p8 = raw.reshape(-1, 3)
        y_bits, cc_bits = _class_bits(thresholds)
        bits = y_bits[p8[:, 0]] & cc_bits[p8[:, 1].astype(np.intp) * 256 + p8[:, 2]]
        n = len(p8)
        frac = np.array([np.count_nonzero(bits & (1 << k)) for k in range(len(CLASSES))]) / n
        k = int(np.argmax(frac))
        if frac[k] < thresholds.min_fraction:
            return "other", float(frac[k])
        return CLASSES[k], float(frac[k])
    px = np.asarray(ycrcb, dtype=float).reshape(-1, 3)
    if len(px) == 0:
        return "other", 0.0
    px = _features(px)
    lo, hi = thresholds.lo_hi()
    inside = np.all((px[None, :, :] >= lo[:, None, :]) & (px[None, :, :] <= hi[:, None, :]), axis=2)
    frac = inside.mean(axis=1)
    k = int(np.argmax(frac))
    if frac[k] < thresholds.min_fraction:
        return "other", float(frac[k])
    return CLASSES[k], float(frac[k])


def candidate_mask(
    center_in_base: tuple[float, float],
    radius_m: float,
    height_m: float,
    pan_rad: float,
    tilt_rad: float,
    intrinsics: Intrinsics,
    camera_in_base_m: tuple[float, float, float],
    *,
    bottom_z_m: float = 0.0,
    shrink: float = 0.7,
) -> tuple[np.ndarray, tuple[int, int, int, int]] | None:
    """Pixel mask ``(H, W)`` bool of the candidate cylinder's outline (its radius and height
    shrunk by ``shrink`` about its axis: the edges mix with the background) and the full
    outline's bounding box; None when it is behind the camera or outside the image."""
    n = 16
    a = np.linspace(0, 2 * math.pi, n, endpoint=False)
    cx, cy = center_in_base

    def outline(r: float, z0: float, z1: float) -> np.ndarray:
        ring = np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], axis=1)
        return np.vstack(
            [np.column_stack([ring, np.full(n, z0)]), np.column_stack([ring, np.full(n, z1)])]
        )

    mid = bottom_z_m + height_m / 2
    full, depth_f = project_in_base(
        outline(radius_m, bottom_z_m, bottom_z_m + height_m),
        pan_rad,
        tilt_rad,
        intrinsics,
        camera_in_base_m,
    )
    inner, depth_i = project_in_base(
        outline(radius_m * shrink, mid - height_m * shrink / 2, mid + height_m * shrink / 2),
        pan_rad,
        tilt_rad,
        intrinsics,
        camera_in_base_m,
    )
    if np.any(depth_f <= 0.05) or np.any(depth_i <= 0.05):
        return None
    w, h = intrinsics.width_px, intrinsics.height_px
    u0, v0 = np.floor(full.min(axis=0)).astype(int)
    u1, v1 = np.ceil(full.max(axis=0)).astype(int)
    u0, v0, u1, v1 = max(u0, 0), max(v0, 0), min(u1, w - 1), min(v1, h - 1)
    if u1 <= u0 or v1 <= v0:
        return None
    mask = np.zeros((h, w), dtype=np.uint8)
    hull = cv2.convexHull(np.round(inner).astype(np.int32))
    cv2.fillConvexPoly(mask, hull, 1)
    return mask.astype(bool), (int(u0), int(v0), int(u1), int(v1))


def classify_candidate(
    rgb: np.ndarray,
    center_in_base: tuple[float, float],
    radius_m: float,
    height_m: float,
    pan_rad: float,
    tilt_rad: float,
    intrinsics: Intrinsics,
    camera_in_base_m: tuple[float, float, float],
    thresholds: ColourThresholds,
    *,
    bottom_z_m: float = 0.0,
) -> ColourResult | None:
    """Colour class of a candidate cylinder (``center_in_base``: its axis in the ``base`` of
    the image's time) in ``rgb``; None when it does not project into the image."""
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(
            f"classify_candidate: expected (H, W, 3) uint8 RGB, got {img.dtype} {img.shape}"
        )
    if img.shape[:2] != (intrinsics.height_px, intrinsics.width_px):
        raise ValueError(
            f"classify_candidate: image {img.shape[1]}x{img.shape[0]} does not match intrinsics "
            f"{intrinsics.width_px}x{intrinsics.height_px}"
        )
    got = candidate_mask(
        center_in_base,
        radius_m,
        height_m,
        pan_rad,
        tilt_rad,
        intrinsics,
        camera_in_base_m,
        bottom_z_m=bottom_z_m,
    )
    if got is None:
        return None
    mask, bbox = got
    u0, v0, u1, v1 = bbox
    sub = img[v0 : v1 + 1, u0 : u1 + 1]
    m = mask[v0 : v1 + 1, u0 : u1 + 1]
    if not m.any():
        return None
    ycc = cv2.cvtColor(np.ascontiguousarray(sub), cv2.COLOR_RGB2YCrCb)[m]
    label, frac = classify_pixels(ycc, thresholds)
    return ColourResult(label, frac, int(m.sum()), bbox)
