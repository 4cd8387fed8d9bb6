"""One object, one detection id: the registry's fusion and its report decisions."""

from __future__ import annotations

import numpy as np
import pytest

from protocol.messages import ObjectKind
from robot.perception.object_registry import ObjectRegistry, RegistryConfig

OOI, VAT = int(ObjectKind.STATIC_OOI), int(ObjectKind.TOXIC_VAT)


def _see(reg: ObjectRegistry, kind: int, xy: tuple[float, float], sigma: float = 0.1):  # type: ignore[no-untyped-def]
    return reg.observe(kind, xy, np.eye(2) * sigma**2, radius_m=0.25, height_m=0.8, time_s=1.0)


def test_sightings_of_one_object_fuse_into_one_id_reported_about_once() -> None:
    reg = ObjectRegistry()
    rng = np.random.default_rng(3)
    truth = np.array([4.0, -2.0])
    reports = 0
    ids = set()
    for _ in range(50):
        obj, due = _see(reg, OOI, tuple(truth + rng.normal(0, 0.1, 2)))
        ids.add(obj.detection_id)
        if due:
            reg.mark_reported(obj)
            reports += 1
    assert len(reg) == 1 and ids == {1}
    assert reports <= 2
    (obj,) = reg.objects
    # the information-weighted mean of 50 sightings of sigma 0.1: sigma 0.014 (floored 0.03)
    assert np.hypot(*(obj.position_in_odom - truth)) < 0.05
    assert np.allclose(np.sqrt(np.diag(obj.covariance)), RegistryConfig().min_sigma_m, atol=1e-9)


def test_objects_apart_get_their_own_ids_and_a_moved_estimate_is_resent() -> None:
    reg = ObjectRegistry(RegistryConfig(merge_m=1.0, resend_shift_m=0.25))
    a, due_a = _see(reg, OOI, (0.0, 0.0))
    reg.mark_reported(a)
    b, due_b = _see(reg, VAT, (3.0, 0.0))
    assert due_a and due_b and a.detection_id != b.detection_id
    # a much better sighting 0.8 m away pulls the estimate past the resend shift
    a2, due = _see(reg, OOI, (0.8, 0.0), sigma=0.02)
    assert a2 is a and due and a.position_in_odom[0] > 0.25
    reg.mark_reported(a)
    _, due = _see(reg, OOI, (0.8, 0.0), sigma=0.5)
    assert not due
    assert reg.new_id() == 3  # tracks draw from the same sequence


def test_the_kind_is_the_majority_and_a_change_is_resent() -> None:
    reg = ObjectRegistry()
    obj, _ = _see(reg, OOI, (1.0, 1.0))
    reg.mark_reported(obj)
    _, due = _see(reg, VAT, (1.0, 1.0))
    assert obj.kind == OOI and not due  # a tie keeps the first kind
    _, due = _see(reg, VAT, (1.0, 1.0))
    assert obj.kind == VAT and due


def test_bad_sightings_are_refused_and_not_fused() -> None:
    reg = ObjectRegistry()
    with pytest.raises(ValueError, match="non-finite"):
        _see(reg, OOI, (float("nan"), 0.0))
    with pytest.raises(ValueError, match="positive definite"):
        reg.observe(OOI, (0.0, 0.0), np.zeros((2, 2)), radius_m=0.2, height_m=0.8, time_s=0.0)
    assert len(reg) == 0
    with pytest.raises(ValueError, match="merge_m"):
        RegistryConfig(merge_m=0.0)
