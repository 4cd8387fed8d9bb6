"""Export of the global occupancy map: ROS ``map_server`` PGM + YAML, and PNG (paper 4.8).

The PGM follows what ROS ``map_saver`` writes in ``trinary`` mode: 8-bit binary PGM (``P5``),
occupied ``0``, free ``254``, unknown ``205``, the first image row at the map's largest ``y``;
the YAML gives ``image`` (relative to the YAML), ``resolution``, ``origin`` ``[x, y, yaw]`` of
the lower-left pixel's corner in ``map``, ``negate: 0``, ``occupied_thresh: 0.65``,
``free_thresh: 0.196`` (so ``205`` reads back as unknown). The PNG is the same picture.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import yaml
from numpy.typing import NDArray

from gcs.mapping.rasterization import FREE, OCCUPIED, UNKNOWN, OccupancyMap

__all__ = ["map_image", "read_pgm_yaml", "write_pgm_yaml", "write_png"]

#: Pixel values of the trinary image (ROS map_saver).
PIXEL_OCCUPIED = 0
PIXEL_FREE = 254
PIXEL_UNKNOWN = 205
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196


def map_image(occupancy: OccupancyMap) -> NDArray[np.uint8]:
    """The map as an 8-bit grey image, first row at the largest ``y`` (north up)."""
    v = np.asarray(occupancy.values)
    if v.ndim != 2:
        raise ValueError(f"map values must be 2-D, got shape {v.shape}")
    known = np.isin(v, (UNKNOWN, FREE, OCCUPIED))
    if not known.all():
        bad = v[~known][0]
        raise ValueError(f"map values must be -1, 0 or 100, found {int(bad)}")
    img = np.full(v.shape, PIXEL_UNKNOWN, dtype=np.uint8)
    img[v == FREE] = PIXEL_FREE
    img[v == OCCUPIED] = PIXEL_OCCUPIED
    return np.ascontiguousarray(img[::-1])


def write_pgm_yaml(occupancy: OccupancyMap, path_stem: str | Path) -> tuple[Path, Path]:
    """Write ``<stem>.pgm`` and ``<stem>.yaml`` for ROS ``map_server``; returns both paths."""
    stem = Path(path_stem)
    if stem.suffix in (".pgm", ".yaml"):
        stem = stem.with_suffix("")
    img = map_image(occupancy)
    if img.size == 0:
        raise ValueError("cannot write an empty map (no node has a pose)")
    pgm = stem.with_suffix(".pgm")
    yml = stem.with_suffix(".yaml")
    stem.parent.mkdir(parents=True, exist_ok=True)
    rows, cols = img.shape
    pgm.write_bytes(f"P5\n{cols} {rows}\n255\n".encode("ascii") + img.tobytes())
    ox, oy = occupancy.origin_in_map
    doc = {
        "image": pgm.name,
        "mode": "trinary",
        "resolution": float(occupancy.resolution_m),
        "origin": [float(ox), float(oy), 0.0],
        "negate": 0,
        "occupied_thresh": OCCUPIED_THRESH,
        "free_thresh": FREE_THRESH,
    }
    yml.write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return pgm, yml


def write_png(occupancy: OccupancyMap, path: str | Path) -> Path:
    """Write the map as a PNG (same pixels as the PGM); returns the path."""
    out = Path(path)
    img = map_image(occupancy)
    if img.size == 0:
        raise ValueError("cannot write an empty map (no node has a pose)")
    out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(out), img):
        raise OSError(f"could not write {out}")
    return out


def read_pgm_yaml(yaml_path: str | Path) -> OccupancyMap:
    """Read a map written by :func:`write_pgm_yaml` (or ``map_saver`` in trinary mode, no
    negate, zero yaw) back into an :class:`OccupancyMap`."""
    yml = Path(yaml_path)
    doc = yaml.safe_load(yml.read_text(encoding="utf-8"))
    if not isinstance(doc, dict):
        raise ValueError(f"{yml}: not a map_server YAML mapping")
    for key in ("image", "resolution", "origin"):
        if key not in doc:
            raise ValueError(f"{yml}: missing key {key!r}")
    if int(doc.get("negate", 0)) != 0:
        raise ValueError(f"{yml}: negate must be 0")
    origin = doc["origin"]
    if len(origin) != 3 or float(origin[2]) != 0.0:
        raise ValueError(f"{yml}: origin must be [x, y, 0], got {origin!r}")
    res = float(doc["resolution"])
    if not (math.isfinite(res) and res > 0):
        raise ValueError(f"{yml}: resolution must be > 0, got {res}")
    img = cv2.imread(str(yml.parent / doc["image"]), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2:
        raise ValueError(f"{yml}: cannot read image {doc['image']!r} as 8-bit grey")
    p = (255.0 - img[::-1].astype(np.float64)) / 255.0
    occ_t = float(doc.get("occupied_thresh", OCCUPIED_THRESH))
    free_t = float(doc.get("free_thresh", FREE_THRESH))
    values = np.full(img.shape, UNKNOWN, dtype=np.int8)
    values[p > occ_t] = OCCUPIED
    values[p < free_t] = FREE
    return OccupancyMap(values, (float(origin[0]), float(origin[1])), res)
