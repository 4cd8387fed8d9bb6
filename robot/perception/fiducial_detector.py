"""Teammates' AprilTags in camera images -> their pose in the observer's ``base`` (paper 4.3.2).

Each robot carries its AprilTag 36h11 on the four side faces of its head (Fig. 8); a tag of
``tag_size_m`` (black border included, white border excluded). :func:`detect_tags` finds tags
with OpenCV's ``cv2.aruco.ArucoDetector`` (``DICT_APRILTAG_36h11``, AprilTag corner
refinement); :func:`estimate_teammates` turns the tags of one teammate into the pose of its
``base`` in the observer's ``base`` at the image time:

1. each tag's pose in the camera by IPPE (``SOLVEPNP_IPPE_SQUARE``);
2. the faces: the layout (:class:`TagLayoutConfig`) either names the face of every id
   (``ids_per_robot = 4``: id = 4 robot + face) or not (``ids_per_robot = 1``: the same id on
   all four faces, as on MAGIC's robots). The head is a cube, so one id on all faces leaves
   the teammate's heading ambiguous by quarter turns: each of the four hypotheses is refined
   and the one whose LIDAR housing (a black box in front of the head, :attr:`TagLayoutConfig.
   marker_in_base_m`) projects onto the darkest pixels wins; a sighting whose hypotheses are
   not told apart clearly is dropped (counted by the caller as ambiguous);
3. all corners of the teammate's visible tags refine one pose (Levenberg-Marquardt PnP);
4. covariance: the reprojection residual (at least ``min_pixel_sigma_px``) through the PnP
   Jacobian to the planar pose ``(x, y, yaw)``, plus a floor for the model's own errors.

Pure: numpy and cv2 only; nothing here knows the simulator.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import msgspec
import numpy as np

from protocol.messages import FiducialObservation, covariance_to_upper
from robot.perception.camera_model import Intrinsics, base_from_camera

__all__ = [
    "FiducialConfig",
    "TagDetection",
    "TagLayoutConfig",
    "TeammateSighting",
    "detect_tags",
    "estimate_teammates",
    "fiducial_observation",
    "fit_rows_px",
]

_FACE_NORMALS = ((1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0))  # front, left, back, right


class TagLayoutConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Where the tags are on a robot, in its ``base`` (the simulator's robot geometry: checked
    equal in the tests). ``ids_per_robot``: 4 (the simulator's heads: id = 4 robot + face;
    faces front, left, back, right) or 1 (id = robot id on every face, as on the paper's).
    ``marker_*``: the dark LIDAR housing used to tell the faces apart when the ids do not."""

    tag_size_m: float = 0.137
    head_center_in_base_m: tuple[float, float, float] = (-0.12, 0.0, 0.75)
    head_half_m: float = 0.1
    ids_per_robot: int = 4
    marker_in_base_m: tuple[float, float, float] = (0.2, 0.0, 0.45)
    marker_half_m: float = 0.05
    # Where the tag a viewer sees lies, along the face normal towards the viewer, from the head
    # centre: +head_half_m, on a real head and on the simulator's (sim.apriltag.head_mesh, whose
    # faces once culled the wrong way showed the far face: then -head_half_m fitted).
    tag_plane_offset_m: float = 0.1

    def __post_init__(self) -> None:
        if self.ids_per_robot not in (1, 4):
            raise ValueError(f"ids_per_robot must be 1 or 4, got {self.ids_per_robot}")
        if not 0 < self.tag_size_m < 2 * self.head_half_m:
            raise ValueError(
                f"tag_size_m must be in (0, {2 * self.head_half_m}), got {self.tag_size_m}"
            )

    def base_from_tag(self, face: int) -> np.ndarray:
        """``(4, 4)``: tag frame (x right, y up as seen from outside, z out of the face) to
        ``base`` of the robot carrying it."""
        nx, ny = _FACE_NORMALS[face % 4]
        z = np.array([nx, ny, 0.0])
        y = np.array([0.0, 0.0, 1.0])
        x = np.cross(y, z)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2] = x, y, z
        m[:3, 3] = np.array(self.head_center_in_base_m) + self.tag_plane_offset_m * z
        return m


class FiducialConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    layout: TagLayoutConfig = TagLayoutConfig()
    camera_in_base_m: tuple[float, float, float] = (-0.12, 0.0, 0.92)
    max_range_m: float = 6.0  # paper 4.3.2: robots detected each other up to about 5 m
    min_tag_px: float = 10.0  # smaller tags decode but their pose is poor
    min_pixel_sigma_px: float = 0.5
    floor_sigma_xy_m: float = 0.01
    floor_sigma_yaw_rad: float = 0.01
    marker_contrast: float = 0.6  # the darkest hypothesis must be below this x the next
    marker_max_gray: float = 30.0  # and this dark (the black housing: 16-19 measured, chassis 59)
    # one frontal tag pins the heading poorly (yaw errors up to ~30 deg measured with residuals
    # below 0.5 px): its yaw standard deviation is at least this
    single_face_sigma_yaw_rad: float = 0.3
    # ... and beyond this range its heading is too loose to be worth sending (measured at
    # 640x480: heading error p95 1.5 deg within 2 m, 6.7 deg at 2-3 m; two faces: 0.6 deg)
    single_face_max_range_m: float = 2.0


@dataclass(frozen=True)
class TagDetection:
    tag_id: int
    corners_px: np.ndarray  # (4, 2): the tag's top-left, top-right, bottom-right, bottom-left


@dataclass(frozen=True)
class TeammateSighting:
    """A teammate's ``base`` pose ``(x, y, yaw)`` in the observer's ``base`` at the image
    time, its 3x3 covariance, the tags used, the range (m) and the RMS reprojection error."""

    robot_id: int
    tag_id: int
    faces: tuple[int, ...]
    observed_in_base: tuple[float, float, float]
    covariance: np.ndarray
    range_m: float
    reprojection_rms_px: float


_DETECTOR: cv2.aruco.ArucoDetector | None = None


def _detector() -> cv2.aruco.ArucoDetector:
    global _DETECTOR
    if _DETECTOR is None:
        params = cv2.aruco.DetectorParameters()
        params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
        _DETECTOR = cv2.aruco.ArucoDetector(
            cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11), params
        )
    return _DETECTOR


def _uniform(gray: np.ndarray) -> bool:
    """Whether every pixel of a 2D uint8 image has the first pixel's value."""
    flat = gray.reshape(-1)
    return bool(cv2.countNonZero(cv2.absdiff(flat, np.full_like(flat, flat[0]))) == 0)


def detect_tags(rgb: np.ndarray) -> list[TagDetection]:
    """AprilTag 36h11 tags in an ``(H, W, 3)`` uint8 RGB (or ``(H, W)`` grey) image."""
    img = np.asarray(rgb)
    if img.dtype != np.uint8 or img.ndim not in (2, 3):
        raise ValueError(f"detect_tags: expected a uint8 image, got {img.dtype} {img.shape}")
    gray = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY) if img.ndim == 3 else img
    if gray.size and _uniform(gray):
        # one grey level (the simulator's flat answer for a frame with nothing to find):
        # the detector's adaptive threshold (pixel > local mean - 7) is the same everywhere,
        # no contour, no tag; 0.03 ms for the test against ~2 ms for the search at 320x240
        return []
    corners, ids, _ = _detector().detectMarkers(gray)
    if ids is None:
        return []
    return [
        TagDetection(int(i), np.asarray(c, dtype=np.float64).reshape(4, 2))
        for i, c in zip(ids.ravel(), corners, strict=True)
    ]


def _tag_points(size_m: float) -> np.ndarray:
    h = size_m / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def _to_matrix(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = cv2.Rodrigues(np.asarray(rvec, dtype=np.float64))[0]
    m[:3, 3] = np.asarray(tvec, dtype=np.float64).ravel()
    return m


def _se2(m: np.ndarray) -> np.ndarray:
    return np.array([m[0, 3], m[1, 3], math.atan2(m[1, 0], m[0, 0])])


def _gray_at(gray: np.ndarray, uv: np.ndarray) -> float:
    h, w = gray.shape
    ok = (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
    if not ok.any():
        return math.inf
    u = uv[ok, 0].astype(int)
    v = uv[ok, 1].astype(int)
    return float(np.median(gray[v, u]))


def estimate_teammates(
    rgb: np.ndarray,
    intrinsics: Intrinsics,
    pan_rad: float,
    tilt_rad: float,
    *,
    own_robot_id: int,
    config: FiducialConfig | None = None,
    detections: Sequence[TagDetection] | None = None,
) -> tuple[list[TeammateSighting], int]:
    """Teammates seen in one image and how many tag groups were dropped as ambiguous or poor.

    ``pan_rad``/``tilt_rad``/``intrinsics``: the image's camera (as its
    :class:`~protocol.sensors.CameraImage` states). Tags of ``own_robot_id`` are ignored.
    """
    cfg = config or FiducialConfig()
    lay = cfg.layout
    dets = detect_tags(rgb) if detections is None else list(detections)
    k_mat = intrinsics.matrix()
    gray = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY) if rgb.ndim == 3 else rgb
    base_from_cam = base_from_camera(pan_rad, tilt_rad, cfg.camera_in_base_m)
    groups: dict[int, list[TagDetection]] = {}
    for d in dets:
        rid = d.tag_id // lay.ids_per_robot
        if rid == own_robot_id:
            continue
        side = float(
            np.mean(np.linalg.norm(d.corners_px - np.roll(d.corners_px, 1, axis=0), axis=1))
        )
        if side < cfg.min_tag_px:
            continue
        groups.setdefault(rid, []).append(d)
    out: list[TeammateSighting] = []
    dropped = 0
    obj_tag = _tag_points(lay.tag_size_m)
    cam_from_base_own = np.linalg.inv(base_from_cam)
    for rid, tags in sorted(groups.items()):
        sighting = _fit_teammate(
            rid, tags, gray, k_mat, base_from_cam, cam_from_base_own, obj_tag, cfg
        )
        if sighting is None:
            dropped += 1
        else:
            out.append(sighting)
    return out, dropped


def _housing_points(lay: TagLayoutConfig) -> np.ndarray:
    """``(18, 3)``: where on the teammate's LIDAR housing (its ``base``) the face cue samples."""
    mx, my, mz = lay.marker_in_base_m
    e = 0.6 * lay.marker_half_m
    return np.array(
        [[mx + a, my + b, mz + c] for a in (-e, 0.0, e) for b in (-e, 0.0, e) for c in (0.0, e)]
    )


def fit_rows_px(
    detections: Sequence[TagDetection],
    intrinsics: Intrinsics,
    *,
    own_robot_id: int,
    config: FiducialConfig | None = None,
) -> float:
    """How far (pixels of this image, up or down) from the principal point's row the pixels
    :func:`estimate_teammates` reads for the teammates of ``detections`` lie: their tags'
    corners and, for each pose the anchor tag admits (IPPE's two, every face the layout
    leaves possible), the LIDAR housing it samples for the face cue. 0 without teammates.

    A camera's image of a band of rows about its principal point (the same width, focal
    length and camera; a smaller height) shows exactly those rows of the full image, so an
    image asked again at a higher resolution to fit these teammates needs only this band
    (scaled): issue 16, the tall fine images of a crowd's tags."""
    cfg = config or FiducialConfig()
    lay = cfg.layout
    k_mat = intrinsics.matrix()
    cy = intrinsics.cy_px
    obj_tag = _tag_points(lay.tag_size_m)
    housing = _housing_points(lay)
    dev = 0.0
    for d in detections:
        if d.tag_id // lay.ids_per_robot == own_robot_id:
            continue
        corners = np.asarray(d.corners_px, dtype=np.float64).reshape(4, 2)
        dev = max(dev, float(np.abs(corners[:, 1] - cy).max()))
        ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(
            obj_tag, corners, k_mat, np.zeros(5), flags=cv2.SOLVEPNP_IPPE_SQUARE
        )
        if not ok:
            continue
        faces = [d.tag_id % 4] if lay.ids_per_robot == 4 else [0, 1, 2, 3]
        for r, t in zip(rvecs, tvecs, strict=True):
            cam_from_tag = _to_matrix(r, t)
            for f in faces:
                cam_from_team = cam_from_tag @ np.linalg.inv(lay.base_from_tag(f))
                pc = housing @ cam_from_team[:3, :3].T + cam_from_team[:3, 3]
                if (pc[:, 2] <= 0).any():
                    continue
                dev = max(dev, float(np.abs(_project(pc, k_mat)[:, 1] - cy).max()))
    return dev


def _planar(params: np.ndarray) -> np.ndarray:
    """``(4, 4)`` observer-base-from-teammate-base of ``(x, y, z, yaw)`` (upright teammate)."""
    x, y, z, yaw = params
    m = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = (x, y, z)
    return m


def _project(points_cam: np.ndarray, k: np.ndarray) -> np.ndarray:
    z = np.maximum(points_cam[:, 2:3], 1e-6)
    return points_cam[:, :2] / z * [k[0, 0], k[1, 1]] + [k[0, 2], k[1, 2]]


def _fit_planar(
    x0: np.ndarray, obj: np.ndarray, cam_from_own: np.ndarray, k_mat: np.ndarray, img: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Levenberg-Marquardt over ``(x, y, z, yaw)``: the teammate's ``base`` in the observer's
    whose points ``obj`` (its ``base``) project onto ``img`` (``(N, 2)`` px) through
    ``cam_from_own`` and ``k_mat``. Returns the parameters, the residual ``(2N,)`` and its
    analytic Jacobian ``(2N, 4)`` there. Written out (4 parameters, a few dozen residuals):
    scipy's ``least_squares`` spent most of a tag fit in its own overhead and forward
    differences (issue 16: a 64-robot crowd's first second was mostly tag fits on board)."""
    a = cam_from_own[:3, :3]
    a0 = cam_from_own[:3, 3]
    fx, fy = k_mat[0, 0], k_mat[1, 1]
    cx, cy = k_mat[0, 2], k_mat[1, 2]
    ox, oy, oz = obj[:, 0], obj[:, 1], obj[:, 2]
    target = img.reshape(-1)

    def evaluate(p: np.ndarray, jacobian: bool) -> tuple[np.ndarray, np.ndarray | None]:
        c, s_ = math.cos(p[3]), math.sin(p[3])
        bx = c * ox - s_ * oy
        by = s_ * ox + c * oy
        pc = (
            np.outer(bx + p[0], a[:, 0])
            + np.outer(by + p[1], a[:, 1])
            + np.outer(oz + p[2], a[:, 2])
            + a0
        )
        z = np.maximum(pc[:, 2], 1e-6)
        xz, yz = pc[:, 0] / z, pc[:, 1] / z
        r = np.empty(2 * len(ox))
        r[0::2] = xz * fx + cx
        r[1::2] = yz * fy + cy
        r -= target
        if not jacobian:
            return r, None
        # d(camera point)/d(x, y, z) = the columns of a; d/d(yaw) = a (-by, bx, 0)
        d = np.empty((len(ox), 3, 4))
        d[:, :, :3] = a
        d[:, :, 3] = np.outer(-by, a[:, 0]) + np.outer(bx, a[:, 1])
        jac = np.empty((2 * len(ox), 4))
        jac[0::2] = fx * (d[:, 0, :] - xz[:, None] * d[:, 2, :]) / z[:, None]
        jac[1::2] = fy * (d[:, 1, :] - yz[:, None] * d[:, 2, :]) / z[:, None]
        return r, jac

    p = np.asarray(x0, dtype=np.float64).copy()
    r, jac = evaluate(p, True)
    assert jac is not None
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(100):
        jtj = jac.T @ jac
        g = jac.T @ r
        if float(np.abs(g).max()) < 1e-12:
            break
        diag = np.diag(np.maximum(np.diag(jtj), 1e-12))
        try:
            step = -np.linalg.solve(jtj + lam * diag, g)
        except np.linalg.LinAlgError:
            break
        p_new = p + step
        r_new, _ = evaluate(p_new, False)
        cost_new = float(r_new @ r_new)
        if cost_new < cost:
            # converged as MINPACK's defaults have it: the step or the cost's decrease
            # relatively below 1e-8 (pose changes of micrometres)
            done = float(np.abs(step).max()) <= 1e-8 * (1e-8 + float(np.abs(p).max()))
            done = done or cost - cost_new <= 1e-8 * cost
            p, cost = p_new, cost_new
            r, jac = evaluate(p, True)
            assert jac is not None
            lam = max(lam / 10, 1e-12)
            if done:
                break
        else:
            lam *= 10
            if lam > 1e12:
                break
    return p, r, jac


def _fit_teammate(
    rid: int,
    tags: list[TagDetection],
    gray: np.ndarray,
    k_mat: np.ndarray,
    base_from_cam: np.ndarray,
    cam_from_own: np.ndarray,
    obj_tag: np.ndarray,
    cfg: FiducialConfig,
) -> TeammateSighting | None:
    """One teammate's pose from its tags (see the module docstring), None when unusable."""
    lay = cfg.layout
    dist = np.zeros(5)
    # the teammate stands upright on the ground like the observer: fit (x, y, z, yaw) only,
    # which also removes IPPE's two-fold flip ambiguity of a single, nearly frontal tag
    tags = sorted(tags, key=lambda d: -cv2.contourArea(d.corners_px.astype(np.float32)))
    anchor = tags[0]
    ok, rvecs, tvecs, _ = cv2.solvePnPGeneric(
        obj_tag, anchor.corners_px, k_mat, dist, flags=cv2.SOLVEPNP_IPPE_SQUARE
    )
    if not ok:
        return None
    cam_from_tags = [_to_matrix(r, t) for r, t in zip(rvecs, tvecs, strict=True)]
    hyps = [anchor.tag_id % 4] if lay.ids_per_robot == 4 else [0, 1, 2, 3]
    img_all = np.vstack([d.corners_px for d in tags])

    best: list[tuple[float, float, np.ndarray, np.ndarray, tuple[int, ...]]] = []
    for h in hyps:
        fits = []
        for cam_from_tag in cam_from_tags:
            own_from_team = base_from_cam @ cam_from_tag @ np.linalg.inv(lay.base_from_tag(h))
            x0 = np.array(
                [*own_from_team[:3, 3], math.atan2(own_from_team[1, 0], own_from_team[0, 0])]
            )
            # faces of the other tags: relative quarter turns from the anchor, by bearing
            faces = [h]
            for d in tags[1:]:
                if lay.ids_per_robot == 4:
                    faces.append(d.tag_id % 4)
                    continue
                c_other = d.corners_px.mean(axis=0)
                cand = []
                for q in range(4):
                    bt = lay.base_from_tag(q)
                    pc = (cam_from_own @ own_from_team @ bt)[:3, 3]
                    cand.append(float(np.linalg.norm(_project(pc[None], k_mat)[0] - c_other)))
                faces.append(int(np.argmin(cand)))
            if len(set(faces)) != len(faces):
                continue
            obj = np.vstack(
                [
                    obj_tag @ lay.base_from_tag(f)[:3, :3].T + lay.base_from_tag(f)[:3, 3]
                    for f in faces
                ]
            )
            x, fun, jac = _fit_planar(x0, obj, cam_from_own, k_mat, img_all)
            fits.append(
                (float(np.sqrt(np.mean(fun.reshape(-1, 2) ** 2) * 2)), x, jac, obj, tuple(faces))
            )
        if not fits:
            continue
        rms, x, jac, obj, faces_t = min(fits, key=lambda f: f[0])
        own_from_team = _planar(x)
        # the face cue: the black LIDAR housing ahead of the head; sampled on the housing
        # itself (its upper half: the chassis hides its foot), not around it (the chassis top
        # beside it is lighter: 44 measured against the housing's 16-19)
        pts = _housing_points(lay)
        pc = (cam_from_own @ own_from_team)[:3]
        score = _gray_at(gray, _project(pts @ pc[:3, :3].T + pc[:3, 3], k_mat))
        best.append((score, rms, x, jac, faces_t))
    if not best:
        return None
    best.sort(key=lambda b: b[0])
    if best[0][0] > cfg.marker_max_gray or (
        len(best) > 1 and not best[0][0] < cfg.marker_contrast * best[1][0]
    ):
        return None  # the LIDAR housing is hidden or the faces are not told apart
    _, rms, params, jac, faces_t = best[0]
    own_from_team = _planar(params)
    rng = float(np.linalg.norm((cam_from_own @ own_from_team)[:3, 3]))
    if rng > cfg.max_range_m or (len(faces_t) == 1 and rng > cfg.single_face_max_range_m):
        return None
    sigma = max(rms, cfg.min_pixel_sigma_px)
    try:
        cov4 = np.linalg.inv(jac.T @ jac) * sigma**2
    except np.linalg.LinAlgError:
        return None
    cov3 = cov4[np.ix_([0, 1, 3], [0, 1, 3])]
    cov3 = 0.5 * (cov3 + cov3.T) + np.diag(
        [cfg.floor_sigma_xy_m**2, cfg.floor_sigma_xy_m**2, cfg.floor_sigma_yaw_rad**2]
    )
    if len(faces_t) == 1:
        cov3[2, 2] = max(cov3[2, 2], cfg.single_face_sigma_yaw_rad**2)
    yaw = (params[3] + math.pi) % (2 * math.pi) - math.pi
    return TeammateSighting(
        robot_id=rid,
        tag_id=anchor.tag_id,
        faces=faces_t,
        observed_in_base=(float(params[0]), float(params[1]), float(yaw)),
        covariance=cov3,
        range_m=rng,
        reprojection_rms_px=rms,
    )


def fiducial_observation(
    sighting: TeammateSighting,
    *,
    node_index: int,
    time_s: float,
    node_from_image_base: tuple[float, float, float] = (0.0, 0.0, 0.0),
    node_from_image_covariance: np.ndarray | None = None,
) -> FiducialObservation:
    """The radio message for ``sighting``, re-expressed in the ``base`` of pose node
    ``node_index`` (``node_from_image_base``: the image-time pose in that node's frame, from
    odometry, with its covariance added to the sighting's)."""
    x, y, yaw = node_from_image_base
    c, s = math.cos(yaw), math.sin(yaw)
    ox, oy, oyaw = sighting.observed_in_base
    pose = (
        x + c * ox - s * oy,
        y + s * ox + c * oy,
        (yaw + oyaw + math.pi) % (2 * math.pi) - math.pi,
    )
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cov = rot @ sighting.covariance @ rot.T
    if node_from_image_covariance is not None:
        cov = cov + np.asarray(node_from_image_covariance, dtype=float)
    return FiducialObservation(
        node_index=node_index,
        time_s=time_s,
        observed_robot_id=sighting.robot_id,
        tag_id=sighting.tag_id,
        observed_in_base=pose,
        covariance=covariance_to_upper(cov),
    )
