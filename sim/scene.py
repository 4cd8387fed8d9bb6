"""The PyBullet scene of a world: static solids, objects, people and robot bodies.

The only module (with :mod:`sim.camera`'s rendering call through it) that talks to PyBullet.
It runs in its own ``pybullet.DIRECT`` client (no GUI, no GPU), never steps PyBullet's
dynamics (bodies are kinematic: moved with ``resetBasePositionAndOrientation``), and offers
batched ray casts (``rayTestBatch``, at most 16384 rays per call, several threads) and
TinyRenderer images. Body ids map back to what they are (:attr:`Scene.body_kind`) so ray
hits can be attributed to an object of interest, a person or a robot.

Robot geometry in ``base`` (origin on the ground between the wheels): chassis box, a mast,
the LIDAR in front on top, the head (a cube carrying the four AprilTags) on the mast and the
pan-tilt camera above the head (paper 3.1, Fig. 5).
"""

from __future__ import annotations

import math
import operator
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numba as nb
import numpy as np

from sim.apriltag import head_mesh, head_texture
from sim.quiet_pybullet import import_pybullet

if TYPE_CHECKING:
    from sim.ray_worker import RayWorkerProcess
from sim.world_generator import Human, Ooi, Solid, World

__all__ = ["MAX_RAYS_PER_CALL", "RobotGeometry", "Scene"]

pb = import_pybullet()

#: Rays per ``rayTestBatch`` call (PyBullet refuses more than 16384 and silently returns
#: nothing for exactly 16384).
MAX_RAYS_PER_CALL = 16000


@dataclass(frozen=True)
class RobotGeometry:
    """Where things are on the robot, in ``base`` (metres)."""

    chassis_half_m: tuple[float, float, float] = (0.3, 0.25, 0.15)
    chassis_center_m: tuple[float, float, float] = (0.0, 0.0, 0.27)
    head_half_m: float = 0.1
    head_center_m: tuple[float, float, float] = (-0.12, 0.0, 0.75)
    lidar_m: tuple[float, float, float] = (0.2, 0.0, 0.52)
    camera_m: tuple[float, float, float] = (-0.12, 0.0, 0.92)
    tag_size_m: float = 0.137


_first = operator.itemgetter(0)
_third = operator.itemgetter(2)


@dataclass
class DynamicState:
    """What moves in a scene: robot transforms ``(N, 4, 4)`` (and which are hidden), people
    ``(xy (H, 2), ground z (H,), hidden (H,))``, detonated objects."""

    robots: np.ndarray | None = None
    robots_hidden: np.ndarray | None = None
    humans: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    hidden_oois: set[int] = field(default_factory=set)


def _quat_from_matrix(m: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion ``(x, y, z, w)`` of a 3x3 rotation."""
    t = m[0, 0] + m[1, 1] + m[2, 2]
    if t > 0:
        s = math.sqrt(t + 1.0) * 2
        return ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    if m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        return (0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s)
    if m[1, 1] > m[2, 2]:
        s = math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        return ((m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s)
    s = math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
    return ((m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s)


def _yaw_quat(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


class Scene:
    """PyBullet bodies for ``world`` with ``robot_count`` robots (ids ``0..robot_count-1``).

    ``body_kind[body_id]`` is ``("solid", kind)``, ``("ooi", ooi_id)``, ``("human",
    human_id)`` or ``("robot", robot_id)``.

    ``analytic_ground`` and ``cull`` (the simulator's scenes: issue 16, speed) make
    :meth:`render` fill the ground in after rasterizing and skip the bodies outside the
    frustum; its images are the same. They leave the scene's own bodies so: a caller drawing
    with ``getCameraImage`` itself (training) keeps both off.
    """

    def __init__(
        self,
        world: World,
        *,
        geometry: RobotGeometry | None = None,
        ray_threads: int = 2,
        ray_workers: int = 0,
        analytic_ground: bool = False,
        cull: bool = False,
    ) -> None:
        self.world = world
        self.geometry = geometry or RobotGeometry()
        self.ray_threads = ray_threads
        # overcast daylight: mostly ambient, a high sun (keeps vertical faces well lit)
        self.light_direction = [0.3, 0.2, 1.0]
        self.light_ambient = 0.65
        self.light_diffuse = 0.4
        # the dynamic state, mirrored to ray worker processes before each parallel cast
        self._state = DynamicState()
        self._state_version = 0
        self._workers: list[RayWorkerProcess] = []
        self.client = pb.connect(pb.DIRECT)
        self.body_kind: dict[int, tuple[str, object]] = {}
        self._tmp = tempfile.TemporaryDirectory(prefix="magic-sim-")
        c = self.client
        W, Hh = world.size_m
        # The ground plane z = 0 is visual only: ray casts clip rays at it analytically
        # (:meth:`ray_cast`), which keeps rays short and PyBullet's work small.
        he = (W / 2 + 20, Hh / 2 + 20, 0.05)
        vis = pb.createVisualShape(
            pb.GEOM_BOX, halfExtents=he, rgbaColor=(0.42, 0.5, 0.38, 1.0), physicsClientId=c
        )
        g = pb.createMultiBody(0, -1, vis, basePosition=(W / 2, Hh / 2, -0.05), physicsClientId=c)
        self.ground_body = int(g)
        self.body_kind[g] = ("solid", "ground")
        self._ground_xy_m = (W / 2 - he[0], Hh / 2 - he[1], W / 2 + he[0], Hh / 2 + he[1])
        #: The ground's pixels are filled in after rendering (:meth:`render`), not drawn by
        #: TinyRenderer: its two screen-wide triangles were ~45 % of a render's time.
        self.analytic_ground = analytic_ground
        self.ground_rgb: np.ndarray | None = None
        if analytic_ground:
            # the shaded colour, as TinyRenderer draws it (the only body yet): seen from above
            self.ground_rgb = self._render_raw(
                np.array([W / 2, Hh / 2, 5.0]),
                np.array([0.0, 0.0, -1.0]),
                np.array([0.0, 1.0, 0.0]),
                8,
                8,
                8.0,
                0.05,
                80.0,
            )[0][4, 4].copy()
            pb.changeVisualShape(g, -1, rgbaColor=(0.42, 0.5, 0.38, 0.0), physicsClientId=c)
        tops = [s.center_m[2] + s.half_extents_m[2] for s in world.solids]
        tops += [o.ground_z_m + o.height_m for o in world.oois]
        tops += [h.height_m + 1.0 for h in world.humans]
        #: Nothing static or walking reaches above this height (robots included).
        self.ceiling_m = max([*tops, 2.0]) + 0.1
        for s in world.solids:
            self._add_solid(s)
        self.ooi_body: dict[int, int] = {}
        for o in world.oois:
            self.ooi_body[o.ooi_id] = self._add_ooi(o)
        self.human_body: list[int] = [self._add_human(h) for h in world.humans]
        self.robot_bodies: list[tuple[int, int]] = []
        for r in world.robots:
            self.robot_bodies.append(self._add_robot(r.robot_id))
        self.robot_of_body = np.full(self._max_body() + 1, -1, dtype=np.int64)
        for rid, (b0, b1) in enumerate(self.robot_bodies):
            self.robot_of_body[b0] = rid
            self.robot_of_body[b1] = rid
        self.ooi_of_body = np.full(self._max_body() + 1, -1, dtype=np.int64)
        for oid, b in self.ooi_body.items():
            self.ooi_of_body[b] = oid
        self.human_of_body = np.full(self._max_body() + 1, -1, dtype=np.int64)
        for hid, b in enumerate(self.human_body):
            self.human_of_body[b] = hid
        self._setup_culling(cull)
        if ray_workers:
            from sim.ray_worker import RayWorkerProcess

            self._workers = [RayWorkerProcess(world, self.geometry) for _ in range(ray_workers)]

    # ---------------------------------------------------------------- culling
    def _setup_culling(self, on: bool) -> None:
        """Bounding spheres of every drawn body (the ground aside) and their shapes' colours.

        TinyRenderer transforms and clips every body of the scene for every image: with a
        crowded world's ~700 bodies that was ~20 ms an image before a pixel was drawn, and it
        skips a body whose colour is transparent. So :meth:`render` makes the bodies whose
        sphere misses the camera's frustum transparent (only those whose side changed since
        the last image: a ``changeVisualShape`` costs ~3 us) and the image is the same."""
        self.cull = on
        bodies = [b for b in sorted(self.body_kind) if b != self.ground_body]
        self._cull_ids = np.array(bodies, dtype=np.int64)
        self._cull_row = {b: i for i, b in enumerate(bodies)}
        self._cull_rgba: list[list[tuple[float, ...]]] = []
        centers = np.zeros((len(bodies), 3))
        radii = np.zeros(len(bodies))
        for i, b in enumerate(bodies):
            shapes = pb.getVisualShapeData(b, physicsClientId=self.client)
            self._cull_rgba.append([tuple(d[7]) for d in shapes])
            pos, _ = pb.getBasePositionAndOrientation(b, physicsClientId=self.client)
            centers[i] = pos
            lo, hi = pb.getAABB(b, physicsClientId=self.client)
            radii[i] = 0.5 * float(np.linalg.norm(np.subtract(hi, lo)))
        g = self.geometry
        # the chassis body's visual parts (chassis, mast to the head, LIDAR) around its origin
        cc = np.array(g.chassis_center_m)
        mast_top = np.array([g.head_center_m[0], 0.0, g.head_center_m[2] - g.head_half_m])
        reach = max(
            float(np.linalg.norm(g.chassis_half_m)),
            float(np.linalg.norm(mast_top - cc)) + 0.05,
            float(np.linalg.norm(np.array(g.lidar_m) - cc)) + 0.15,
        )
        for chassis, head in self.robot_bodies:
            radii[self._cull_row[chassis]] = reach + 0.01
            radii[self._cull_row[head]] = g.head_half_m * math.sqrt(3.0) + 0.01
        for s, b in zip(self.world.solids, [k for k in bodies if self.body_kind[k][0] == "solid"],
                        strict=True):  # fmt: skip
            centers[self._cull_row[b]] = s.center_m
            radii[self._cull_row[b]] = float(np.linalg.norm(s.half_extents_m)) + 0.01
        self._cull_center = centers
        self._cull_radius = radii
        self._cull_drawn = np.ones(len(bodies), dtype=bool)

    def _cull_move(self, body: int, position: tuple[float, float, float] | list[float]) -> None:
        self._cull_center[self._cull_row[body]] = position

    def _cull_to(
        self,
        eye_m: np.ndarray,
        forward: np.ndarray,
        up: np.ndarray,
        hfov_rad: float,
        vfov_rad: float,
        near_m: float,
        far_m: float,
    ) -> None:
        """Make the bodies that cannot show in this camera transparent, the others drawn."""
        from sim.camera import in_frustum

        # the far plane bounds depth, not distance: the frustum's far corners are farther
        reach_m = far_m * math.sqrt(1.0 + math.tan(hfov_rad / 2) ** 2 + math.tan(vfov_rad / 2) ** 2)
        want = in_frustum(
            eye_m,
            forward,
            up,
            hfov_rad=hfov_rad,
            vfov_rad=vfov_rad,
            near_m=near_m,
            centers_m=self._cull_center,
            radii_m=self._cull_radius,
            ranges_m=np.full(len(self._cull_radius), reach_m),
        )
        self._set_drawn(want)

    def _set_drawn(self, want: np.ndarray) -> None:
        c = self.client
        for i in np.flatnonzero(want != self._cull_drawn).tolist():
            b = int(self._cull_ids[i])
            rgba = self._cull_rgba[i]
            if want[i]:
                for k, col in enumerate(rgba):
                    pb.changeVisualShape(b, -1, shapeIndex=k, rgbaColor=col, physicsClientId=c)
            else:
                pb.changeVisualShape(b, -1, rgbaColor=(*rgba[0][:3], 0.0), physicsClientId=c)
        self._cull_drawn = want.copy()

    # ---------------------------------------------------------------- building
    def _max_body(self) -> int:
        return max(self.body_kind) if self.body_kind else 0

    def _add_box_body(self, s: Solid) -> int:
        c = self.client
        col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=s.half_extents_m, physicsClientId=c)
        vis = pb.createVisualShape(
            pb.GEOM_BOX, halfExtents=s.half_extents_m, rgbaColor=s.rgba, physicsClientId=c
        )
        b = pb.createMultiBody(
            0,
            col,
            vis,
            basePosition=s.center_m,
            baseOrientation=_yaw_quat(s.yaw_rad),
            physicsClientId=c,
        )
        self.body_kind[b] = ("solid", s.kind)
        return int(b)

    def _add_solid(self, s: Solid) -> int:
        c = self.client
        if s.shape == "box":
            return self._add_box_body(s)
        hx, hy, hz = s.half_extents_m
        if s.shape == "cylinder":
            col = pb.createCollisionShape(
                pb.GEOM_CYLINDER, radius=hx, height=2 * hz, physicsClientId=c
            )
            vis = pb.createVisualShape(
                pb.GEOM_CYLINDER, radius=hx, length=2 * hz, rgbaColor=s.rgba, physicsClientId=c
            )
        else:  # wedge: top rises along +x from the bottom face at -hx to the top at +hx
            v = [
                [-hx, -hy, -hz],
                [hx, -hy, -hz],
                [hx, -hy, hz],
                [-hx, hy, -hz],
                [hx, hy, -hz],
                [hx, hy, hz],
            ]
            idx = [0, 1, 2, 3, 5, 4, 0, 3, 4, 0, 4, 1, 1, 4, 5, 1, 5, 2, 0, 2, 5, 0, 5, 3]
            col = pb.createCollisionShape(pb.GEOM_MESH, vertices=v, physicsClientId=c)
            vis = pb.createVisualShape(
                pb.GEOM_MESH, vertices=v, indices=idx, rgbaColor=s.rgba, physicsClientId=c
            )
        b = pb.createMultiBody(
            0,
            col,
            vis,
            basePosition=s.center_m,
            baseOrientation=_yaw_quat(s.yaw_rad),
            physicsClientId=c,
        )
        self.body_kind[b] = ("solid", s.kind)
        return int(b)

    def _add_cylinder(
        self,
        radius_m: float,
        height_m: float,
        rgba: tuple[float, ...],
        base_m: tuple[float, float, float],
    ) -> int:
        """A static upright cylinder whose centre is at ``base_m`` (x, y, z of the centre)."""
        c = self.client
        col = pb.createCollisionShape(
            pb.GEOM_CYLINDER, radius=radius_m, height=height_m, physicsClientId=c
        )
        vis = pb.createVisualShape(
            pb.GEOM_CYLINDER, radius=radius_m, length=height_m, rgbaColor=rgba, physicsClientId=c
        )
        return int(pb.createMultiBody(0, col, vis, basePosition=base_m, physicsClientId=c))

    def _add_ooi(self, o: Ooi) -> int:
        centre = (o.xy_m[0], o.xy_m[1], o.ground_z_m + o.height_m / 2)
        b = self._add_cylinder(o.radius_m, o.height_m, o.rgba, centre)
        self.body_kind[b] = ("ooi", o.ooi_id)
        return b

    def _add_human(self, h: Human) -> int:
        x, y = h.route_m[0]
        b = self._add_cylinder(h.radius_m, h.height_m, h.rgba, (x, y, h.height_m / 2))
        self.body_kind[b] = ("human", h.human_id)
        return b

    def _add_robot(self, robot_id: int) -> tuple[int, int]:
        """Two bodies: the chassis (origin at its centre) whose collision shape is the chassis
        and head boxes (one broadphase entry per robot: fewer ray tests in a crowd; the mast
        and the LIDAR are visual only), and the tagged head (visual only, moved with it)."""
        c, g = self.client, self.geometry
        mast_top = g.head_center_m[2] - g.head_half_m
        chassis_top = g.chassis_center_m[2] + g.chassis_half_m[2]
        mast_half = (0.03, 0.03, (mast_top - chassis_top) / 2)
        mast_center = (g.head_center_m[0], 0.0, chassis_top + mast_half[2])
        lidar_half = (0.05, 0.05, 0.05)
        lidar_center = (g.lidar_m[0], g.lidar_m[1], g.lidar_m[2] - 0.07)
        halves = [g.chassis_half_m, mast_half, lidar_half]
        cc = np.array(g.chassis_center_m)
        centers = [list(np.array(p) - cc) for p in (g.chassis_center_m, mast_center, lidar_center)]
        head_rel = list(np.array(g.head_center_m) - cc)
        col = pb.createCollisionShapeArray(
            [pb.GEOM_BOX, pb.GEOM_BOX],
            halfExtents=[g.chassis_half_m, [g.head_half_m] * 3],
            collisionFramePositions=[[0.0, 0.0, 0.0], head_rel],
            physicsClientId=c,
        )
        vis = pb.createVisualShapeArray(
            [pb.GEOM_BOX] * 3,
            halfExtents=halves,
            visualFramePositions=centers,
            rgbaColors=[[0.25, 0.22, 0.2, 1], [0.3, 0.3, 0.3, 1], [0.1, 0.1, 0.1, 1]],
            physicsClientId=c,
        )
        chassis = pb.createMultiBody(0, col, vis, basePosition=(0, 0, -10), physicsClientId=c)
        # each face its own tag, id 4 robot + face: a sighting tells which side is seen
        tex = head_texture(robot_id, face_m=2 * g.head_half_m, tag_size_m=g.tag_size_m)
        path = Path(self._tmp.name) / f"tag{robot_id}.png"
        cv2.imwrite(str(path), tex[:, :, ::-1])
        tid = pb.loadTexture(str(path), physicsClientId=c)
        v, i, uv, n = head_mesh(g.head_half_m, atlas=True)
        hvis = pb.createVisualShape(
            pb.GEOM_MESH, vertices=v, indices=i, uvs=uv, normals=n, physicsClientId=c
        )
        head = pb.createMultiBody(0, -1, hvis, basePosition=(0, 0, -10), physicsClientId=c)
        pb.changeVisualShape(
            head, -1, textureUniqueId=tid, rgbaColor=[1, 1, 1, 1], physicsClientId=c
        )
        self.body_kind[chassis] = ("robot", robot_id)
        self.body_kind[head] = ("robot", robot_id)
        return int(chassis), int(head)

    # ---------------------------------------------------------------- moving
    def set_robot_poses(
        self, world_from_base: np.ndarray, *, hidden: np.ndarray | None = None
    ) -> None:
        """Move robot bodies to ``(N, 4, 4)`` transforms; ``hidden`` robots go under ground."""
        c, g = self.client, self.geometry
        self._state.robots = np.array(world_from_base)
        self._state.robots_hidden = None if hidden is None else np.array(hidden)
        self._state_version += 1
        hc = np.array([*g.head_center_m, 1.0])
        cc = np.array([*g.chassis_center_m, 1.0])
        for rid, (chassis, head) in enumerate(self.robot_bodies):
            m = world_from_base[rid]
            q = _quat_from_matrix(m[:3, :3])
            if hidden is not None and hidden[rid]:
                under = [float(m[0, 3]), float(m[1, 3]), _HIDDEN_Z_M]
                pb.resetBasePositionAndOrientation(chassis, under, q, physicsClientId=c)
                pb.resetBasePositionAndOrientation(head, under, q, physicsClientId=c)
                self._cull_move(chassis, under)
                self._cull_move(head, under)
                continue
            cp = (m @ cc)[:3].tolist()
            pb.resetBasePositionAndOrientation(chassis, cp, q, physicsClientId=c)
            hp = (m @ hc)[:3].tolist()
            pb.resetBasePositionAndOrientation(head, hp, q, physicsClientId=c)
            self._cull_move(chassis, cp)
            self._cull_move(head, hp)

    def set_human_positions(self, xy_m: np.ndarray, z_m: np.ndarray, *, hidden: np.ndarray) -> None:
        c = self.client
        self._state.humans = (np.array(xy_m), np.array(z_m), np.array(hidden))
        self._state_version += 1
        for hid, b in enumerate(self.human_body):
            h = self.world.humans[hid]
            z = _HIDDEN_Z_M if hidden[hid] else float(z_m[hid]) + h.height_m / 2
            pos = (float(xy_m[hid, 0]), float(xy_m[hid, 1]), z)
            pb.resetBasePositionAndOrientation(b, pos, (0, 0, 0, 1), physicsClientId=c)
            self._cull_move(b, pos)

    @property
    def hidden_oois(self) -> frozenset[int]:
        """The detonated objects, removed from view (:meth:`hide_ooi`)."""
        return frozenset(self._state.hidden_oois)

    def hide_ooi(self, ooi_id: int) -> None:
        """Remove a detonated object from view (it no longer stands there)."""
        self._state.hidden_oois.add(ooi_id)
        self._state_version += 1
        pb.resetBasePositionAndOrientation(
            self.ooi_body[ooi_id], (0, 0, _HIDDEN_Z_M), (0, 0, 0, 1), physicsClientId=self.client
        )
        self._cull_move(self.ooi_body[ooi_id], (0.0, 0.0, _HIDDEN_Z_M))

    def sync(self) -> None:
        """Refresh the broadphase after moving bodies (ray casts see the new poses)."""
        pb.performCollisionDetection(physicsClientId=self.client)

    # ---------------------------------------------------------------- sensing
    def ray_cast(self, from_m: np.ndarray, to_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cast rays ``(N, 3) -> (N, 3)`` in world; returns the hit fraction along each ray
        (1.0 for no hit) and the body hit (-1 for none; ``ground_body`` for the ground).

        Rays are first clipped analytically to the ground plane ``z = 0`` and to
        :attr:`ceiling_m` (nothing is higher), then cast by ``rayTestBatch`` in chunks of at
        most 16384 with ``ray_threads`` threads; a clipped ray that hits nothing hit the
        ground (or left the scene upwards)."""
        f = np.ascontiguousarray(from_m, dtype=np.float64).reshape(-1, 3)
        t = np.ascontiguousarray(to_m, dtype=np.float64).reshape(-1, 3)
        n = len(f)
        frac = np.ones(n, dtype=np.float64)
        body = np.full(n, -1, dtype=np.int64)
        if n == 0:
            return frac, body
        dz = t[:, 2] - f[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            s_ground = np.where(dz < 0, -f[:, 2] / dz, np.inf)
            s_top = np.where(dz > 0, (self.ceiling_m - f[:, 2]) / dz, np.inf)
        s_ground = np.where(f[:, 2] < 0, 0.0, s_ground)
        s_clip = np.minimum(np.minimum(s_ground, s_top), 1.0)
        s_clip = np.maximum(s_clip, 0.0)
        end = f + (t - f) * s_clip[:, None]
        if self._workers and n >= _PARALLEL_MIN_RAYS:
            # split the rays: the workers cast the first parts while this process casts the rest
            parts = np.array_split(np.arange(n), len(self._workers) + 1)
            for w, idx in zip(self._workers, parts[:-1], strict=False):
                w.submit(self._state_version, self._state, f[idx], end[idx])
            own = parts[-1]
            body[own], frac[own] = self.cast_raw(f[own], end[own])
            for w, idx in zip(self._workers, parts[:-1], strict=False):
                body[idx], frac[idx] = w.result()
        else:
            body[:], frac[:] = self.cast_raw(f, end)
        hit = body >= 0
        frac = np.where(hit, frac * s_clip, 1.0)
        ground = ~hit & (s_ground <= 1.0)
        frac[ground] = s_ground[ground]
        body[ground] = self.ground_body
        return frac, body

    def cast_raw(self, f: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``rayTestBatch`` in chunks: body ids (-1: none) and hit fractions."""
        n = len(f)
        body = np.full(n, -1, dtype=np.int64)
        frac = np.ones(n, dtype=np.float64)
        for k in range(0, n, MAX_RAYS_PER_CALL):
            res = pb.rayTestBatch(
                f[k : k + MAX_RAYS_PER_CALL],
                end[k : k + MAX_RAYS_PER_CALL],
                numThreads=self.ray_threads,
                physicsClientId=self.client,
            )
            m = min(MAX_RAYS_PER_CALL, n - k)
            if len(res) != m:
                raise RuntimeError(f"rayTestBatch returned {len(res)} results for {m} rays")
            body[k : k + m] = np.fromiter(map(_first, res), dtype=np.int64, count=m)
            frac[k : k + m] = np.fromiter(map(_third, res), dtype=np.float64, count=m)
        return body, frac

    def apply_state(self, state: DynamicState) -> None:
        """Set the dynamic state mirrored from another scene of the same world (ray workers)."""
        if state.robots is not None:
            self.set_robot_poses(state.robots, hidden=state.robots_hidden)
        if state.humans is not None:
            xy, z, hidden = state.humans
            self.set_human_positions(xy, z, hidden=hidden)
        for ooi_id in state.hidden_oois - self._state.hidden_oois:
            self.hide_ooi(ooi_id)
        self.sync()

    def render(
        self,
        *,
        eye_m: np.ndarray,
        forward: np.ndarray,
        up: np.ndarray,
        width_px: int,
        height_px: int,
        fy_px: float,
        near_m: float = 0.05,
        far_m: float = 80.0,
    ) -> np.ndarray:
        """RGB image ``(H, W, 3)`` uint8 from a pinhole camera at ``eye_m`` looking along
        ``forward`` (TinyRenderer, CPU). Principal point at the image centre.

        With :attr:`analytic_ground` the ground plane is not rasterized: the pixels nothing
        was drawn on whose ray meets ``z = 0`` (within the ground's extent and the far plane)
        get its shaded colour, exactly the pixels and the colour TinyRenderer gives it (its
        pixel (i, j) samples the ray through (i + 1, j + 1) of the viewport; nothing is
        below the ground: hidden bodies go to ``_HIDDEN_Z_M``)."""
        if self.cull:
            hfov = 2 * math.atan(width_px / 2 / fy_px)
            vfov = 2 * math.atan(height_px / 2 / fy_px)
            self._cull_to(eye_m, forward, up, hfov, vfov, near_m, far_m)
        rgb, depth = self._render_raw(eye_m, forward, up, width_px, height_px, fy_px, near_m, far_m)
        if self.ground_rgb is not None:
            self._fill_ground(rgb, depth, eye_m, forward, up, fy_px, near_m, far_m)
        return rgb

    def _fill_ground(
        self,
        rgb: np.ndarray,
        depth: np.ndarray,
        eye_m: np.ndarray,
        forward: np.ndarray,
        up: np.ndarray,
        fy_px: float,
        near_m: float,
        far_m: float,
    ) -> None:
        """Give the pixels :meth:`_ground_pixels` selects the ground's colour, in one compiled
        pass over the background pixels with the same arithmetic (the same pixels: issue 16,
        the numpy masks were ~20 % of a 320x240 render)."""
        assert self.ground_rgb is not None
        h, w = depth.shape
        eye = np.asarray(eye_m, dtype=np.float64)
        f = np.asarray(forward, dtype=np.float64)
        u = np.asarray(up, dtype=np.float64)
        r = np.cross(f, u)
        x = (2.0 * (np.arange(w) + 1.0) / w - 1.0) * (w / 2 / fy_px)
        y = (1.0 - 2.0 * (np.arange(h) + 1.0) / h) * (h / 2 / fy_px)
        _ground_fill(
            rgb,
            np.ascontiguousarray(depth, dtype=np.float32),
            x,
            y,
            eye,
            f,
            r,
            u,
            float(near_m),
            float(far_m),
            np.array(self._ground_xy_m, dtype=np.float64),
            np.asarray(self.ground_rgb, dtype=np.uint8),
        )

    def _ground_pixels(
        self,
        depth: np.ndarray,
        eye_m: np.ndarray,
        forward: np.ndarray,
        up: np.ndarray,
        fy_px: float,
        near_m: float,
        far_m: float,
    ) -> np.ndarray:
        """Boolean ``(H, W)``: background pixels whose ray meets the ground plane."""
        h, w = depth.shape
        eye = np.asarray(eye_m, dtype=np.float64)
        f = np.asarray(forward, dtype=np.float64)
        u = np.asarray(up, dtype=np.float64)
        r = np.cross(f, u)
        # the ray through pixel (i, j) is f + x_i r + y_j u (depth along f is its parameter)
        x = (2.0 * (np.arange(w) + 1.0) / w - 1.0) * (w / 2 / fy_px)
        y = (1.0 - 2.0 * (np.arange(h) + 1.0) / h) * (h / 2 / fy_px)
        dz = f[2] + x[None, :] * r[2] + y[:, None] * u[2]
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(dz < 0, -eye[2] / dz, np.inf)
        hit = (t >= near_m) & (t <= far_m) & (depth >= 1.0)
        if hit.any():
            x0, y0, x1, y1 = self._ground_xy_m
            rows, cols = np.nonzero(hit)
            tt = t[rows, cols]
            px = eye[0] + tt * (f[0] + x[cols] * r[0] + y[rows] * u[0])
            py = eye[1] + tt * (f[1] + x[cols] * r[1] + y[rows] * u[1])
            inside = (px >= x0) & (px <= x1) & (py >= y0) & (py <= y1)
            hit[rows[~inside], cols[~inside]] = False
        return hit

    def _render_raw(
        self,
        eye_m: np.ndarray,
        forward: np.ndarray,
        up: np.ndarray,
        width_px: int,
        height_px: int,
        fy_px: float,
        near_m: float,
        far_m: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """TinyRenderer's RGB ``(H, W, 3)`` and depth buffer ``(H, W)`` (1 where nothing)."""
        target = eye_m + forward
        view = pb.computeViewMatrix(eye_m.tolist(), target.tolist(), up.tolist())
        vfov_deg = math.degrees(2 * math.atan(height_px / 2 / fy_px))
        proj = pb.computeProjectionMatrixFOV(vfov_deg, width_px / height_px, near_m, far_m)
        out = pb.getCameraImage(
            width_px,
            height_px,
            view,
            proj,
            renderer=pb.ER_TINY_RENDERER,
            flags=pb.ER_NO_SEGMENTATION_MASK,  # not used: ~10 % of a render
            shadow=0,
            lightDirection=self.light_direction,
            lightAmbientCoeff=self.light_ambient,
            lightDiffuseCoeff=self.light_diffuse,
            lightSpecularCoeff=0.0,
            physicsClientId=self.client,
        )
        rgba = np.reshape(np.asarray(out[2], dtype=np.uint8), (height_px, width_px, 4))
        depth = np.reshape(np.asarray(out[3], dtype=np.float32), (height_px, width_px))
        return np.ascontiguousarray(rgba[:, :, :3]), depth

    def close(self) -> None:
        for w in self._workers:
            w.close()
        self._workers = []
        if self.client >= 0:
            try:
                pb.disconnect(physicsClientId=self.client)
            except pb.error:
                pass
            self.client = -1
        self._tmp.cleanup()


@nb.njit(cache=True, nogil=True)
def _ground_fill(
    rgb: np.ndarray,
    depth: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    eye: np.ndarray,
    f: np.ndarray,
    r: np.ndarray,
    u: np.ndarray,
    near_m: float,
    far_m: float,
    bounds: np.ndarray,
    colour: np.ndarray,
) -> None:  # pragma: no cover - compiled (its equality with _ground_pixels is tested)
    """:meth:`Scene._ground_pixels` and the fill, per pixel, the same operations in the same
    order (no fused multiply-adds: numba's default): the same pixels."""
    h, w = depth.shape
    x0, y0, x1, y1 = bounds[0], bounds[1], bounds[2], bounds[3]
    for i in range(h):
        for j in range(w):
            if not depth[i, j] >= 1.0:
                continue
            dz = f[2] + x[j] * r[2] + y[i] * u[2]
            if not dz < 0:
                continue
            t = -eye[2] / dz
            if not (t >= near_m and t <= far_m):
                continue
            px = eye[0] + t * (f[0] + x[j] * r[0] + y[i] * u[0])
            py = eye[1] + t * (f[1] + x[j] * r[1] + y[i] * u[1])
            if px >= x0 and px <= x1 and py >= y0 and py <= y1:
                rgb[i, j, 0] = colour[0]
                rgb[i, j, 1] = colour[1]
                rgb[i, j, 2] = colour[2]


#: Where hidden bodies go: below the ground, beyond any camera's far plane (the ground is not
#: drawn: :meth:`Scene.render`) and any ray (clipped at the ground).
_HIDDEN_Z_M = -1000.0

#: Below this many rays a cast stays in process (the round trip would cost more).
_PARALLEL_MIN_RAYS = 3000
