"""Offscreen drawings of the operators' picture with cv2 (no viewer needed).

:func:`render_region` draws a square region of ``map`` as an RGB image, north (+y) up and east
(+x) right: the map with unexplored cells as fog, danger rings, objects, trails, goals and
robots (a disc with a heading tick and its id). SAGE's zoomed views (paper 6.4.2) are such
images; a whole-map one is a debug picture. :func:`thumbnail_mosaic` tiles the OOI thumbnails
with their classification for the SOC (paper 6.1). Pure functions over the picture.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from gcs.mapping.rasterization import OccupancyMap
from gcs.views.narration import TRIGGER_M, blast_radius_m
from gcs.views.operator_picture import ObjectSighting, OperatorPicture

__all__ = ["KIND_RGB", "map_gray", "render_region", "thumbnail_mosaic", "FOG", "FREE", "WALL"]

#: Gray levels of the map: fog of war over unknown cells, free, occupied.
FOG, FREE, WALL = 60, 235, 0

#: Object colours: dangerous kinds saturated, others muted (paper 6.4.1).
KIND_RGB = {
    "static_ooi": (230, 20, 20),
    "hostile": (255, 0, 160),
    "civilian": (30, 90, 255),
    "toxic_vat": (170, 120, 40),
    "mobile_ooi": (200, 80, 200),
    "unknown": (140, 140, 140),
}

_ROBOT_RGB = (0, 170, 0)
_UNLINKED_RGB = (230, 170, 0)


def map_gray(occupancy: OccupancyMap) -> NDArray[np.uint8]:
    """``(rows, cols)`` uint8 gray levels of the map (row 0 at the map's min y)."""
    v = occupancy.values
    out = np.full(v.shape, FOG, dtype=np.uint8)
    out[v == 0] = FREE
    out[v > 0] = WALL
    return out


def render_region(
    picture: OperatorPicture,
    occupancy: OccupancyMap | None,
    center_in_map: tuple[float, float],
    half_m: float,
    *,
    px: int = 256,
) -> NDArray[np.uint8]:
    """RGB ``(px, px, 3)`` view of the square ``center +- half_m`` of ``map``, north up."""
    cx, cy = float(center_in_map[0]), float(center_in_map[1])
    half = max(float(half_m), 1e-3)
    m_per_px = 2.0 * half / px
    x0, y1 = cx - half, cy + half
    img = np.full((px, px), FOG, dtype=np.uint8)
    if occupancy is not None and occupancy.values.size:
        # sample the map at each pixel centre (nearest cell): cheap and exact in orientation
        u = x0 + (np.arange(px) + 0.5) * m_per_px
        v = y1 - (np.arange(px) + 0.5) * m_per_px
        res = occupancy.resolution_m
        col = np.floor((u - occupancy.origin_in_map[0]) / res).astype(np.int64)
        row = np.floor((v - occupancy.origin_in_map[1]) / res).astype(np.int64)
        rows, cols = occupancy.shape
        okc = (col >= 0) & (col < cols)
        okr = (row >= 0) & (row < rows)
        sub = occupancy.values[np.ix_(row[okr], col[okc])]  # only the cells shown
        img[np.ix_(np.flatnonzero(okr), np.flatnonzero(okc))] = np.where(
            sub > 0, WALL, np.where(sub == 0, FREE, FOG)
        ).astype(np.uint8)
    rgb = np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))

    def pix(x: float, y: float) -> tuple[int, int]:
        return int(round((x - x0) / m_per_px)), int(round((y1 - y) / m_per_px))

    def inside(x: float, y: float, margin_m: float = 0.0) -> bool:
        return abs(x - cx) <= half + margin_m and abs(y - cy) <= half + margin_m

    def rad(r_m: float) -> int:
        return max(1, int(round(r_m / m_per_px)))

    for _, kind, pos in picture.hazards:
        blast = blast_radius_m(kind)
        if blast is None or not inside(*pos, blast):
            continue
        cv2.circle(rgb, pix(*pos), rad(blast), (255, 140, 0), 1, cv2.LINE_AA)
        cv2.circle(rgb, pix(*pos), rad(TRIGGER_M), (255, 0, 0), 1, cv2.LINE_AA)

    for o in picture.objects:
        if not inside(*o.position_in_map):
            continue
        color = KIND_RGB.get(o.kind_name, KIND_RGB["unknown"])
        cv2.circle(rgb, pix(*o.position_in_map), 3, color, -1, cv2.LINE_AA)
    if len(picture.frontiers_in_map):
        for x, y in picture.frontiers_in_map:
            if inside(x, y):
                cv2.drawMarker(rgb, pix(x, y), (0, 200, 200), cv2.MARKER_CROSS, 5, 1)
    for r in picture.robots:
        # only what the zoom shows (a view of one event, not of the team)
        if r.pose_in_map is not None and not inside(r.pose_in_map[0], r.pose_in_map[1], 30.0):
            continue
        if len(r.trail_in_map) >= 2:
            t = np.asarray(r.trail_in_map, dtype=float)
            pts = np.rint(np.column_stack([t[:, 0] - x0, y1 - t[:, 1]]) / m_per_px)
            pts = pts.astype(np.int32)
            cv2.polylines(rgb, [pts], False, (120, 200, 120), 1, cv2.LINE_AA)
        if r.goal_in_map is not None:
            cv2.drawMarker(rgb, pix(*r.goal_in_map[:2]), (0, 120, 255), cv2.MARKER_STAR, 8, 1)
    for r in picture.robots:
        if r.pose_in_map is None:
            continue
        x, y, yaw = (float(v) for v in r.pose_in_map)
        if not inside(x, y, 1.0):
            continue
        color = _ROBOT_RGB if r.linked else _UNLINKED_RGB
        p = pix(x, y)
        cv2.circle(rgb, p, 5, color, -1, cv2.LINE_AA)
        tip = pix(x + 0.6 * 12 * m_per_px * math.cos(yaw), y + 0.6 * 12 * m_per_px * math.sin(yaw))
        cv2.line(rgb, p, tip, (0, 0, 0), 2, cv2.LINE_AA)
        cv2.putText(
            rgb,
            str(r.robot_id),
            (p[0] + 6, p[1] - 6),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (0, 0, 0),
            1,
            cv2.LINE_AA,
        )
    return rgb


def thumbnail_mosaic(
    objects: Sequence[ObjectSighting], *, tile_px: int = 96, cols: int = 4, max_tiles: int = 16
) -> NDArray[np.uint8] | None:
    """RGB mosaic of the latest ``max_tiles`` thumbnails, each captioned with its object id and
    classification on a strip of the kind's colour; None when no object has one."""
    with_img = [o for o in objects if o.thumbnail is not None][-max_tiles:]
    if not with_img:
        return None
    rows = math.ceil(len(with_img) / cols)
    cap = 14
    out = np.full((rows * (tile_px + cap), min(cols, len(with_img)) * tile_px, 3), 30, np.uint8)
    for i, o in enumerate(with_img):
        assert o.thumbnail is not None
        r, c = divmod(i, cols)
        y, x = r * (tile_px + cap), c * tile_px
        t: np.ndarray = o.thumbnail
        h, w = t.shape[:2]
        s = tile_px / max(h, w)
        t = cv2.resize(t, (max(1, int(w * s)), max(1, int(h * s))), interpolation=cv2.INTER_AREA)
        out[y : y + t.shape[0], x : x + t.shape[1]] = t[:, :, :3]
        color = KIND_RGB.get(o.kind_name, KIND_RGB["unknown"])
        out[y + tile_px : y + tile_px + cap, x : x + tile_px] = color
        cv2.putText(
            out,
            f"{o.object_id} {o.kind_name}",
            (x + 2, y + tile_px + cap - 3),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.35,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
    return out
