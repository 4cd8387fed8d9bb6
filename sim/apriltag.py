"""AprilTag 36h11 textures and the textured robot head (paper 4.3.2, Fig. 8).

Every robot carries four copies of its tag (id = robot id), one on each face of its head.
A tag measures ``tag_size_m`` (13.7 cm) *excluding* its white border: that is the 8x8-cell
black-bordered code OpenCV's ``generateImageMarker`` draws for ``DICT_APRILTAG_36h11``; a
white border of one cell and then the head's light grey surround it.

The head is a mesh with explicit texture coordinates so that each face shows the tag upright
and un-mirrored when seen from outside (OpenCV's detector does not decode mirrored tags).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["TAG_CELLS", "head_mesh", "tag_texture"]

#: Cells across a 36h11 tag including its black border (6 data + 2 border).
TAG_CELLS = 8


def tag_texture(
    tag_id: int, *, face_m: float = 0.2, tag_size_m: float = 0.137, cell_px: int = 24
) -> np.ndarray:
    """RGB texture (square, uint8) of one head face: the tag of ``tag_id`` (``tag_size_m``
    wide, black border included) centred on a ``face_m`` square, in a white border one cell
    wide, on light grey. Every cell is ``cell_px`` pixels; the texture's side is chosen so the
    tag spans ``tag_size_m / face_m`` of it (to within half a pixel)."""
    if not 0 <= tag_id < 587:
        raise ValueError(f"AprilTag 36h11 ids are 0..586, got {tag_id}")
    if not 0 < tag_size_m * (TAG_CELLS + 2) / TAG_CELLS <= face_m:
        raise ValueError(f"tag of {tag_size_m} m with its white border does not fit {face_m} m")
    dictionary = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    tag_px = TAG_CELLS * cell_px
    size_px = int(round(tag_px * face_m / tag_size_m))
    size_px += (size_px - tag_px) % 2  # equal margins
    marker = cv2.aruco.generateImageMarker(dictionary, tag_id, tag_px, borderBits=1)
    img = np.full((size_px, size_px), 215, dtype=np.uint8)
    white = tag_px + 2 * cell_px
    w0 = (size_px - white) // 2
    img[w0 : w0 + white, w0 : w0 + white] = 255
    t0 = (size_px - tag_px) // 2
    img[t0 : t0 + tag_px, t0 : t0 + tag_px] = marker
    return np.ascontiguousarray(np.repeat(img[:, :, None], 3, axis=2))


def head_mesh(
    half_m: float,
) -> tuple[list[list[float]], list[int], list[list[float]], list[list[float]]]:
    """A cube of half size ``half_m`` (head frame: x forward, y left, z up) as
    ``(vertices, indices, uvs, normals)`` for ``pybullet.createVisualShape(GEOM_MESH, ...)``.

    The four side faces map the whole texture, upright (texture top at +z) and read from
    outside; top and bottom map a corner of the texture (plain grey).
    """
    h = half_m
    verts: list[list[float]] = []
    uvs: list[list[float]] = []
    norms: list[list[float]] = []
    idx: list[int] = []

    def quad(corners: list[list[float]], normal: list[float], uv: list[list[float]]) -> None:
        base = len(verts)
        verts.extend(corners)
        uvs.extend(uv)
        norms.extend([normal] * 4)
        # counter-clockwise seen from outside (along -normal)
        idx.extend([base, base + 1, base + 2, base, base + 2, base + 3])

    # side faces: corners listed bottom-left, bottom-right, top-right, top-left as seen from
    # outside; texture (u to the right, v up) maps the image upright
    full = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]]
    quad([[h, h, -h], [h, -h, -h], [h, -h, h], [h, h, h]], [1, 0, 0], full)  # front (+x)
    quad([[-h, -h, -h], [-h, h, -h], [-h, h, h], [-h, -h, h]], [-1, 0, 0], full)  # back
    quad([[-h, h, -h], [h, h, -h], [h, h, h], [-h, h, h]], [0, 1, 0], full)  # left (+y)
    quad([[h, -h, -h], [-h, -h, -h], [-h, -h, h], [h, -h, h]], [0, -1, 0], full)  # right
    grey = [[0.01, 0.01], [0.02, 0.01], [0.02, 0.02], [0.01, 0.02]]
    quad([[-h, -h, h], [-h, h, h], [h, h, h], [h, -h, h]], [0, 0, 1], grey)  # top
    quad([[h, -h, -h], [h, h, -h], [-h, h, -h], [-h, -h, -h]], [0, 0, -1], grey)  # bottom
    return verts, idx, uvs, norms
