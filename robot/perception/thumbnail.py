"""A small thumbnail of a detected object for the operator (paper 6.1), sent only on request.

The image is cropped around the object's outline (plus a margin), scaled so its long side is
at most ``max_side_px``, and JPEG-encoded at the highest quality in ``qualities`` that keeps
it within ``max_bytes`` (the radio is scarce: paper 4.1).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["Thumbnail", "make_thumbnail"]


@dataclass(frozen=True)
class Thumbnail:
    encoding: str  # "jpeg"
    width: int
    height: int
    data: bytes


def make_thumbnail(
    rgb: np.ndarray,
    bbox_px: tuple[int, int, int, int],
    *,
    margin_frac: float = 0.3,
    max_side_px: int = 64,
    max_bytes: int = 2000,
    qualities: tuple[int, ...] = (80, 65, 50, 35, 20, 10),
) -> Thumbnail:
    """JPEG of ``rgb`` (``(H, W, 3)`` uint8) cropped to ``bbox_px`` ``(u0, v0, u1, v1)``
    grown by ``margin_frac`` of its size; the lowest quality is used if none fits
    ``max_bytes``."""
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(
            f"make_thumbnail: expected (H, W, 3) uint8 RGB, got {img.dtype} {img.shape}"
        )
    h, w = img.shape[:2]
    u0, v0, u1, v1 = bbox_px
    if not (u1 > u0 and v1 > v0):
        raise ValueError(f"make_thumbnail: empty bbox {bbox_px}")
    mu, mv = int((u1 - u0) * margin_frac) + 1, int((v1 - v0) * margin_frac) + 1
    u0, v0 = max(0, u0 - mu), max(0, v0 - mv)
    u1, v1 = min(w, u1 + mu), min(h, v1 + mv)
    if u1 <= u0 or v1 <= v0:
        raise ValueError(f"make_thumbnail: bbox {bbox_px} is outside the {w}x{h} image")
    crop = img[v0:v1, u0:u1]
    scale = min(1.0, max_side_px / max(crop.shape[:2]))
    if scale < 1.0:
        size = (max(1, round(crop.shape[1] * scale)), max(1, round(crop.shape[0] * scale)))
        crop = cv2.resize(crop, size, interpolation=cv2.INTER_AREA)
    bgr = np.ascontiguousarray(crop[:, :, ::-1])
    data = b""
    for q in qualities:
        ok, buf = cv2.imencode(
            ".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, q, cv2.IMWRITE_JPEG_OPTIMIZE, 1]
        )
        if not ok:
            raise RuntimeError("make_thumbnail: JPEG encoding failed")
        data = buf.tobytes()
        if len(data) <= max_bytes:
            break
    return Thumbnail("jpeg", int(crop.shape[1]), int(crop.shape[0]), data)
