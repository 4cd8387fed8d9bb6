"""The robot head's tags as PyBullet renders them: the near face is seen (not the far one
through the head), read un-mirrored, and with :func:`sim.apriltag.head_texture` every face
has its own id."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from robot.perception.fiducial_detector import detect_tags
from sim.apriltag import FACES, head_mesh, head_texture
from sim.camera import CameraConfig, camera_axes, intrinsics
from sim.quiet_pybullet import import_pybullet
from sim.scene import Scene
from tests.sim.simworlds import make_world

CAM = CameraConfig()
W, H = 640, 480


def _matrix(x: float, y: float, yaw: float) -> np.ndarray:
    m = np.eye(4)
    m[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    m[:2, 3] = (x, y)
    return m


@pytest.fixture(scope="module")
def scene() -> Iterator[Scene]:
    s = Scene(
        make_world(robots=((5.0, 10.0, 0.0, "sensor"), (7.0, 10.0, 2.0, "sensor"))), ray_threads=1
    )
    yield s
    s.close()


def _render(scene: Scene, observer: np.ndarray, observed: np.ndarray) -> np.ndarray:
    scene.set_robot_poses(np.stack([observer, observed]))
    scene.sync()
    eye, fwd, up = camera_axes(observer, np.array(scene.geometry.camera_m), 0.0, CAM.tilt_rad)
    _, fy, _, _ = intrinsics(W, H, CAM)
    return scene.render(eye_m=eye, forward=fwd, up=up, width_px=W, height_px=H, fy_px=fy)


def test_the_near_face_is_seen_at_its_true_distance(scene: Scene) -> None:
    """The tag's apparent size is the near face's (head centre minus half a head away), not
    the far face's (plus half a head): the winding culls the right faces."""
    g = scene.geometry
    observer = _matrix(5.0, 10.0, 0.0)
    fx, _, _, _ = intrinsics(W, H, CAM)
    for d in (1.5, 2.5):
        # the teammate faces us: its front face looks back at the camera
        observed = observer @ _matrix(d, 0.0, math.pi)
        rgb = _render(scene, observer, observed)
        (tag,) = detect_tags(rgb)
        side_px = float(
            np.mean(np.linalg.norm(tag.corners_px - np.roll(tag.corners_px, 1, 0), axis=1))
        )
        # camera to the face plane, along x: teammate's head centre is at -head_center_x
        head_x = d - g.head_center_m[0]
        cam_x = g.camera_m[0]
        near = fx * g.tag_size_m / (head_x - g.head_half_m - cam_x)
        far = fx * g.tag_size_m / (head_x + g.head_half_m - cam_x)
        assert abs(side_px - near) < 0.35 * abs(near - far), (side_px, near, far)


def test_head_texture_gives_every_face_its_own_id(scene: Scene, tmp_path: Path) -> None:
    """A head built from the atlas (what ``sim.scene`` would load for ``ids_per_robot=4``):
    seen from each side, the tag read is ``4 robot + face``."""
    pb = import_pybullet()
    c, g = scene.client, scene.geometry
    robot_id = 5
    path = tmp_path / "atlas.png"
    cv2.imwrite(
        str(path),
        head_texture(robot_id, face_m=2 * g.head_half_m, tag_size_m=g.tag_size_m)[:, :, ::-1],
    )
    tex = pb.loadTexture(str(path), physicsClientId=c)
    v, i, uv, n = head_mesh(g.head_half_m, atlas=True)
    vis = pb.createVisualShape(
        pb.GEOM_MESH, vertices=v, indices=i, uvs=uv, normals=n, physicsClientId=c
    )
    head = pb.createMultiBody(0, -1, vis, basePosition=(0, 0, -10), physicsClientId=c)
    pb.changeVisualShape(head, -1, textureUniqueId=tex, rgbaColor=[1, 1, 1, 1], physicsClientId=c)
    try:
        observer = _matrix(5.0, 10.0, 0.0)
        far_away = observer @ _matrix(-30.0, 0.0, 0.0)  # robot 1's own head out of sight
        for face, name in enumerate(FACES):
            # turn the atlas head so that face `face` looks back at the camera
            normal_yaw = (0.0, math.pi / 2, math.pi, -math.pi / 2)[face]
            yaw = math.pi - normal_yaw
            centre = observer @ _matrix(2.0, 0.0, yaw)
            pos = (centre @ np.array([*g.head_center_m, 1.0]))[:3]
            q = pb.getQuaternionFromEuler((0.0, 0.0, yaw))
            pb.resetBasePositionAndOrientation(head, pos.tolist(), q, physicsClientId=c)
            rgb = _render(scene, observer, far_away)
            ids = [d.tag_id for d in detect_tags(rgb)]
            assert ids == [4 * robot_id + face], (name, ids)
    finally:
        pb.removeBody(head, physicsClientId=c)


def test_head_texture_refuses_ids_beyond_the_family() -> None:
    with pytest.raises(ValueError, match="robot ids 0..145"):
        head_texture(146)
