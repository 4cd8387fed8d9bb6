"""``magic bench perception``: its worlds keep the route clear and the objects in reach, and
its scoring counts what it says on hand-made reports (no simulator run: the suite itself is
the benchmark)."""

from __future__ import annotations

import math

import numpy as np

from mission.bench.perception import (
    FIRST_SEED,
    ROUTE_Y_M,
    WorldResult,
    _score,
    bench_world,
)
from protocol.messages import (
    Detection,
    DetectionImage,
    FiducialObservation,
    ObjectKind,
    PoseNode,
    covariance_to_upper,
)
from protocol.se2 import relative


def test_worlds_are_seeded_and_keep_their_objects_off_the_route() -> None:
    a, b = bench_world(FIRST_SEED, length_m=24.0), bench_world(FIRST_SEED, length_m=24.0)
    assert a == b and a != bench_world(FIRST_SEED + 1, length_m=24.0)
    kinds = sorted(o.kind for o in a.oois)
    assert kinds == ["static_ooi", "static_ooi", "toxic_vat", "toxic_vat"]
    for o in a.oois:  # beyond the robot's own keep-out (2.5 + 0.75 m), within 8 m
        assert 3.5 <= abs(o.xy_m[1] - ROUTE_Y_M) <= 6.0
    for s in a.solids:
        assert abs(s.center_m[1] - ROUTE_Y_M) - max(s.half_extents_m[:2]) > 1.5
    hostile = next(h for h in a.humans if h.kind == "hostile")
    assert abs(hostile.route_m[0][1] - ROUTE_Y_M) > 5.75 + 1.0  # its keep-out leaves the route
    assert len(a.robots) == 3


def test_scoring_counts_hits_misses_confusion_and_fiducials() -> None:
    world = bench_world(FIRST_SEED, length_m=24.0)
    start = np.array(world.robots[0].pose_m)
    ooi = next(o for o in world.oois if o.kind == "static_ooi")
    vat = next(o for o in world.oois if o.kind == "toxic_vat")
    trunk = next(s for s in world.solids if s.kind == "trunk")

    def at(xy: tuple[float, float], dx: float = 0.0) -> tuple[float, float]:
        p = relative(start, np.array([xy[0] + dx, xy[1], 0.0]))
        return (float(p[0]), float(p[1]))

    node = PoseNode(0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0,) * 6)
    cov = (0.01, 0.0, 0.01)
    mate = world.robots[1]
    # later (t >= 25 s) the robot stands 2 m from the teammate: its pose node 1 is there
    near = np.array([mate.pose_m[0] - 2.0, mate.pose_m[1], 0.0])
    rel = relative(near, np.array(mate.pose_m))
    sent = [
        (0.0, node),
        (30.0, PoseNode(1, 30.0, (20.0, 0.0, 0.0), (20.0, 0.0, 0.0), (1e-4,) * 6)),
        (2.0, Detection(1, 0, 2.0, ObjectKind.STATIC_OOI, at(ooi.xy_m, 0.2), cov, 0.25, 0.8, 1)),
        (9.0, Detection(2, 0, 9.0, ObjectKind.TOXIC_VAT, at(vat.xy_m), cov, 0.3, 0.9, 1)),
        # a trunk called an OOI: a false detection and a confusion
        (3.0, Detection(3, 0, 3.0, ObjectKind.STATIC_OOI, at(trunk.center_m[:2]), cov, 0.25, 1, 1)),
        (4.0, DetectionImage(1, 1, 2.0, 0.0, "jpeg", 8, 8, b"x" * 600)),
        (
            5.0,
            FiducialObservation(
                1,
                31.0,
                1,
                1,
                (float(rel[0]) + 0.05, float(rel[1]), float(rel[2]) + math.radians(2)),
                covariance_to_upper(np.diag([1e-4, 1e-4, 0.01**2])),
            ),
        ),
    ]
    first_in_range = np.full(len(world.oois), math.inf)
    first_in_range[world.oois.index(ooi)] = 1.0
    first_in_range[world.oois.index(vat)] = 1.0  # reported at 9 s: more than 5 s later
    res = WorldResult()

    def truth_at(t: float) -> np.ndarray:
        return start.copy() if t < 25.0 else near.copy()

    def human_xy(t: float) -> np.ndarray:
        return np.array([h.route_m[0] for h in world.humans])

    _score(world, sent, truth_at, human_xy, first_in_range, np.zeros(3, bool), res)
    assert (res.ooi_in_range, res.ooi_found) == (1, 1)
    assert (res.vat_in_range, res.vat_found) == (1, 0)
    assert res.static_ids == 3 and res.static_true == 2
    assert res.matched == 3 and res.confused == 1
    assert np.allclose(sorted(res.pos_err_m), [0.0, 0.2], atol=1e-5)
    assert res.thumb_bytes == [600] and res.detection_bytes > 0
    assert np.allclose(res.fid_err_m, [0.05], atol=1e-5)
    assert np.allclose(res.fid_err_deg, [2.0], atol=1e-3)
    assert np.allclose(res.fid_err_deg_2face, [2.0], atol=1e-3)  # sigma 0.01 rad: pinned
