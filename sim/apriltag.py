"""AprilTag 36h11 textures and the textured robot head (paper 4.3.2, Fig. 8).

Every robot carries four copies of its tag (id = robot id), one on each face of its head
(:func:`tag_texture`), or one tag per face (:func:`head_texture`, id = 4 robot id + face).
A tag measures ``tag_size_m`` (13.7 cm) *excluding* its white border: that is the 8x8-cell
black-bordered code OpenCV's ``generateImageMarker`` draws for ``DICT_APRILTAG_36h11``; a
white border of one cell and then the head's light grey surround it.

The head is a mesh with explicit texture coordinates so that each face shows the tag upright
and un-mirrored when seen from outside (OpenCV's detector does not decode mirrored tags).
"""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["FACES", "TAG_CELLS", "head_mesh", "head_texture", "tag_texture"]

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


#: Faces of the head in the order of their tag ids with :func:`head_texture` (id = 4 robot +
#: face), as in :mod:`robot.perception.fiducial_detector` (``ids_per_robot = 4``).
FACES = ("front", "left", "back", "right")


def head_texture(
    robot_id: int, *, face_m: float = 0.2, tag_size_m: float = 0.137, cell_px: int = 24
) -> np.ndarray:
    """A 2x2 atlas of the four faces' textures (:func:`tag_texture`), each face its own tag,
    id ``4 robot_id + face`` (:data:`FACES` order; row-major: front, left / back, right), for
    :func:`head_mesh` with ``atlas=True``: every face then tells which side of the teammate is
    seen, so its heading has no quarter-turn ambiguity (paper 4.3.2 used one id per robot)."""
    if not 0 <= 4 * robot_id + 3 < 587:
        raise ValueError(f"robot {robot_id}: 4 tag ids per robot need robot ids 0..145")
    faces = [
        tag_texture(4 * robot_id + k, face_m=face_m, tag_size_m=tag_size_m, cell_px=cell_px)
        for k in range(4)
    ]
    return np.ascontiguousarray(np.vstack([np.hstack(faces[0:2]), np.hstack(faces[2:4])]))


def head_mesh(
    half_m: float, *, atlas: bool = False
) -> tuple[list[list[float]], list[int], list[list[float]], list[list[float]]]:
    """A cube of half size ``half_m`` (head frame: x forward, y left, z up) as
    ``(vertices, indices, uvs, normals)`` for ``pybullet.createVisualShape(GEOM_MESH, ...)``.

    The four side faces map the whole texture (``atlas``: each face its quadrant of a
    :func:`head_texture`), upright (texture top at +z) and read from outside; top and bottom
    map a corner of the texture (plain grey).
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
        # PyBullet's TinyRenderer culls the faces whose triangles run counter-clockwise on
        # screen: listed that way the viewer saw the head's *far* face from inside (measured:
        # tags 0.2 m too far). Clockwise seen from outside shows the near face.
        idx.extend([base, base + 2, base + 1, base, base + 3, base + 2])

    # side faces: corners listed bottom-left, bottom-right, top-right, top-left as seen from
    # outside; texture (u to the right, v up) maps the image upright
    # (PyBullet samples textures with u mirrored relative to this: measured, a tag mapped
    # with u running left to right reads mirrored from outside)
    full = [[1.0, 0.0], [0.0, 0.0], [0.0, 1.0], [1.0, 1.0]]

    def uv_of(face: int) -> list[list[float]]:
        if not atlas:
            return full
        # image row 0 (front, left) is the texture's top half: v in [0.5, 1]
        u0, v0 = 0.5 * (face % 2), 0.5 * (1 - face // 2)
        return [[u0 + 0.5 * u, v0 + 0.5 * v] for u, v in full]

    quad([[h, h, -h], [h, -h, -h], [h, -h, h], [h, h, h]], [1, 0, 0], uv_of(0))  # front (+x)
    quad([[-h, -h, -h], [-h, h, -h], [-h, h, h], [-h, -h, h]], [-1, 0, 0], uv_of(2))  # back
    quad([[-h, h, -h], [h, h, -h], [h, h, h], [-h, h, h]], [0, 1, 0], uv_of(1))  # left (+y)
    quad([[h, -h, -h], [-h, -h, -h], [-h, -h, h], [h, -h, h]], [0, -1, 0], uv_of(3))  # right
    grey = [[0.01, 0.01], [0.02, 0.01], [0.02, 0.02], [0.01, 0.02]]
    quad([[-h, -h, h], [-h, h, h], [h, h, h], [h, -h, h]], [0, 0, 1], grey)  # top
    quad([[h, -h, -h], [h, h, -h], [-h, h, -h], [-h, -h, -h]], [0, 0, -1], grey)  # bottom
    return verts, idx, uvs, norms
